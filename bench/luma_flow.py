"""Flow of a deeper (10-bit) source through the two ways of making 8-bit frames of it: rounded
(``v2v_server.luma.to_uint8``, ``(v + 128) // 257``, what the sample's frames and its flow use)
against the top byte (``v >> 8``). A bundled clip is encoded as HEVC yuv420p10le, decoded to
full-range uint16 luma, and each flow option runs on both 8-bit forms of the same frames.

    python -m bench.luma_flow [--frames 81] [--options tracked tracked-g12 ultrafast]
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import av
import numpy as np

from v2v_server.flow.estimate import FlowEstimator
from v2v_server.luma import to_uint8
from v2v_server.ops.startup import SAMPLE_VIDEOS
from v2v_server.frames.decode import iter_luma

CLIP = SAMPLE_VIDEOS / "bbb_camera_596x336.mp4"
STEP = 5  # frames per voxel grid (the paper's recipe: 5 bins, one frame per bin)


def ten_bit_frames(folder: Path, n: int) -> np.ndarray:
    """uint16 (n, H, W): the first ``n`` frames of ``CLIP`` encoded at 10 bits and decoded."""
    out = folder / "ten.mkv"
    with av.open(str(CLIP)) as src, av.open(str(out), "w") as dst:
        s = dst.add_stream("libx265", rate=25)
        s.width, s.height, s.pix_fmt = 596, 336, "yuv420p10le"
        s.options = {"x265-params": "log-level=error"}
        for i, f in enumerate(src.decode(video=0)):
            if i >= n:
                break
            for p in s.encode(f.reformat(format="yuv420p10le")):
                dst.mux(p)
        for p in s.encode():
            dst.mux(p)
    return np.stack([f for _, f in zip(range(n), iter_luma(out))])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=81)
    ap.add_argument("--options", nargs="+", default=["tracked", "tracked-g12", "ultrafast"])
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        frames = ten_bit_frames(Path(tmp), args.frames)
    rounded, top = to_uint8(frames), (frames >> 8).astype(np.uint8)
    print(f"{CLIP.name} at 10 bits: {frames.shape} {frames.dtype}; pixels whose 8-bit code differs: "
          f"{np.mean(rounded != top):.3f}")
    for name in args.options:
        est = FlowEstimator(name)
        a, b = est.voxel_flows(top, STEP), est.voxel_flows(rounded, STEP)
        d = np.abs(a - b)
        print(f"{name}: mean |flow| {np.abs(b).mean():.3f} px; |rounded - top byte| mean {d.mean():.4f} px, "
              f"p99 {np.quantile(d, 0.99):.3f}, max {d.max():.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

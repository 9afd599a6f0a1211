"""What full-range frames cost per decoded frame, against plain luma decoding in the same run.

``python -m bench.frame_range [--repeat 5]`` decodes each bundled clip and times, per frame:

* ``codes + crop`` (baseline): plane 0 as stored, the WebVid top-rows cut, one 128 x 128 crop
  copied out: the crop without full-range expansion;
* ``+ expand(crop)``: the same plus the full-range table on the crop (what samples.py does);
* ``decode_luma``: the whole kept region expanded (what ``--check``, ``v2v-eval --video`` and
  the benches read), plus the same crop.

Best of ``--repeat`` passes (the machine is shared; the best pass is the least disturbed).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from v2v_server.frames.decode import decode_codes, decode_luma, open_video

CLIPS = ("bikes.mp4", "webvid_like_596x336.mp4", "bigbuckbunny.mp4")
ROWS = lambda h: max(1, int(h * 0.54))  # noqa: E731  (the default keep_top_fraction)


def _pass(path: Path, mode: str) -> float:
    c, s, _ = open_video(path)
    n, t = 0, time.perf_counter()
    if mode == "luma":
        for y in decode_luma(c, s, ROWS):
            np.ascontiguousarray(y[:128, :128])
            n += 1
    else:
        for codes, expand in decode_codes(c, s, ROWS):
            crop = np.ascontiguousarray(codes[:128, :128])
            if mode == "expand":
                expand(crop)
            n += 1
    return (time.perf_counter() - t) / n * 1e3


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeat", type=int, default=5)
    args = p.parse_args(argv)
    root = Path(__file__).resolve().parents[1] / "v2v_server" / "sample_videos"
    print("| clip | codes + crop, ms/frame | + expand(crop) | ratio | decode_luma + crop | ratio |")
    print("|---|---|---|---|---|---|")
    for name in CLIPS:
        best = {m: float("inf") for m in ("codes", "expand", "luma")}
        for _ in range(args.repeat):
            for m in best:
                best[m] = min(best[m], _pass(root / name, m))
        b = best["codes"]
        print(f"| {name} | {b:.3f} | {best['expand']:.3f} | {best['expand'] / b:.3f} | {best['luma']:.3f} | "
              f"{best['luma'] / b:.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Where one worker core's time goes per sample, and how far a bit-identical speed-up of the
stages after decoding could take it: ``python -m bench.sample_cost``.

Runs a worker's own path (``bench.speed.worker_core``: ``samples.video_samples`` and the wire
narrowing, the flow as its grid as a served worker sends it) in this process on one thread, on
copies of the WebVid-like clip (596 x 336 H.264; ``--clip`` another), every output (voxels, frames, tracked flow), the paper's
sample (40 voxel grids of 5 bins, 128 x 128), at ``crops_per_window`` 1 and 4. Per sample it
prints the CPU-milliseconds of the whole path, of simulation and of flow (``SamplePass.seconds``,
which ``make_sample`` times with a wall clock: run it on an otherwise idle machine), and the
cost of its statistics (``samples/stats.py``: event rates, active pixels, flow magnitude, timed
under ``SamplePass.seconds.stats``) and the rest (decoding, cropping, range expansion, narrowing). Against the decode bound measured in
the same run (``bench.speed.bare_decode``: PyAV, luma plane, one thread) it gives the worker's
share of the bound and its *ceiling*: the share if simulation and flow cost nothing, the most
any bit-identical speed-up of them can give. Rounds are interleaved; medians are printed.

It also decodes the clip with FFmpeg's grayscale-only flag (``AV_CODEC_FLAG_GRAY``, which skips
chroma in decoders built with ``--enable-gray``) and prints its speed against plain decoding and
whether the luma is the same: the one bit-identical decoding shortcut FFmpeg offers.
"""
from __future__ import annotations

import argparse
import hashlib
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import List, Optional

from bench.speed import SPAN, bare_decode, clip_path, make_corpus, warm_kernel, worker_core


def path_cost(corpus: Path, crops: int, videos: int) -> dict:
    """CPU-ms per sample of the worker's path (``bench.speed.worker_core``, every output, the
    flow as its grid) at ``crops`` crops per window: total, simulate, flow, stats and the rest."""
    busy: dict = {}
    total = 1e3 / worker_core(corpus, ("voxels", "frames", "flow"), crops, videos, flow_grid=True, busy=busy)
    sim, flo, st = (busy.get(k, 0.0) * 1e3 / busy["samples"] for k in ("simulate", "flow", "stats"))
    return {"total": total, "simulate": sim, "flow": flo, "stats": st, "rest": total - sim - flo - st}


def gray_decode(path: Path) -> dict:
    """Luma frames per CPU-second with and without ``AV_CODEC_FLAG_GRAY``, and whether the luma
    planes are byte-identical."""
    import av
    import numpy as np

    out = {}
    for gray in (False, True):
        c = av.open(str(path))
        s = c.streams.video[0]
        s.thread_type, s.codec_context.thread_count = "SLICE", 1
        if gray:
            s.codec_context.flags |= av.codec.context.Flags.gray
        h, n = hashlib.sha1(), 0
        t = time.process_time()
        for fr in c.decode(s):
            pl = fr.planes[0]
            h.update(np.frombuffer(pl, np.uint8).reshape(fr.height, pl.line_size)[:, :fr.width].tobytes())
            n += 1
        out["gray" if gray else "plain"] = (n / (time.process_time() - t), h.hexdigest())
        c.close()
    return out


def measure(clip: Path, videos: int = 4, rounds: int = 3) -> dict:
    """Medians over ``rounds`` interleaved rounds: ``bound`` (samples/CPU-s), ``rows`` (crops per
    window -> CPU-ms per sample: total, simulate, flow, stats, rest; share of the bound; ceiling),
    ``gray`` (speed vs plain decoding, luma identical)."""
    corpus = make_corpus(Path(tempfile.mkdtemp(prefix="v2v-cost-")) / "c", videos, clip)
    warm_kernel()
    path_cost(corpus, 1, 1)  # numba's cached kernels loaded, OpenCV warmed
    bound, runs, gray = [], {1: [], 4: []}, []
    for _ in range(rounds):
        bound.append(bare_decode(clip, 2) / SPAN)
        for crops in runs:
            runs[crops].append(path_cost(corpus, crops, videos))
        g = gray_decode(clip)
        gray.append((g["gray"][0] / g["plain"][0], g["gray"][1] == g["plain"][1]))
    b = statistics.median(bound)
    rows = {}
    for crops, rs in runs.items():
        m = {k: statistics.median(r[k] for r in rs) for k in rs[0]}
        m.update(share=1e3 / m["total"] / b, ceiling=1e3 / m["rest"] / b)
        rows[crops] = m
    return {"bound": b, "rows": rows, "gray": {"speed": statistics.median(r for r, _ in gray),
                                               "identical": all(s for _, s in gray)}}


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clip", default="webvid_like_596x336.mp4")
    ap.add_argument("--videos", type=int, default=4, help="clip copies per round (2 windows each)")
    ap.add_argument("--rounds", type=int, default=3)
    a = ap.parse_args(argv)
    clip = clip_path(a.clip)
    r = measure(clip, a.videos, a.rounds)
    b = r["bound"]
    print(f"decode bound: {b:.2f} samples/CPU-s ({1e3 / b:.0f} CPU-ms per 201-frame window); "
          f"clip {clip.name}, {a.rounds} interleaved rounds, medians\n")
    print("| crops per window | CPU-ms per sample | simulate | flow | stats | rest (decode, crop, narrow) "
          "| share of decode bound | ceiling (simulate, flow free) |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for crops, m in r["rows"].items():
        print(f"| {crops} | {m['total']:.0f} | {m['simulate']:.0f} ({m['simulate'] / m['total']:.0%}) "
              f"| {m['flow']:.0f} ({m['flow'] / m['total']:.0%}) | {m['stats']:.1f} ({m['stats'] / m['total']:.1%}) "
              f"| {m['rest']:.0f} | {m['share']:.0%} "
              f"| {m['ceiling']:.0%} |")
    print(f"\nAV_CODEC_FLAG_GRAY: decode {r['gray']['speed']:.2f}x plain, luma identical: {r['gray']['identical']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

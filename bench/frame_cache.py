"""What the decoded-frame cache buys a worker core, and what it costs in bytes:
``python -m bench.frame_cache``.

On copies of the WebVid-like clip (596 x 336 H.264, 2 windows each; ``--clip`` another), a
worker's own path (``bench.speed.worker_core``: every output, the paper's sample, one crop per
window, the tracked flow as its grid) runs in this process on one thread: without the cache,
then for each format (``raw``, ``zstd``) epoch 0 (decoding and storing into a fresh cache) and
epoch 1 (cut from the entries). Each row is samples per CPU-second and its share of the decode
bound measured in the same run (``bench.speed.bare_decode``: PyAV, luma only, one thread, per
201-frame window); rounds are interleaved, medians printed. Then the bytes: per video, per
frame, per hour of 596 x 336 video at 25 fps and for the WebVid subsets of the paper; and a
budget of half the corpus (policy ``keep``): epoch 1's hit ratio and samples per CPU-second.
With ``--serve``, the same epochs 1+ through ``v2v-serve --workers 2`` read by a raw client
(``bench.speed.producer``), cache off and warm (filled by ``--warm-cache`` first).
"""
from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
from pathlib import Path
from typing import List, Optional

from bench.speed import SPAN, bare_decode, clip_path, make_corpus, producer, warm_kernel, worker_core

OUTPUTS = ("voxels", "frames", "flow")
#: Windows of 200 frame pairs in the paper's WebVid subsets (WebVid10k: 22,725 windows).
WEBVID_WINDOWS = {"WebVid100": 227, "WebVid1k": 2272, "WebVid10k": 22725}


def settle() -> None:
    """Wait out the racy window of the files just copied (``sources.local.RACY_NS``): a file changed
    within it is decoded and not stored, which would make epoch 0 store fewer entries."""
    import time

    from v2v_server.sources.local import RACY_NS

    time.sleep(RACY_NS / 1e9 + 0.02)


def _caches(cache: Path, fmt: str, gb: float = 64.0):
    from v2v_server.frames.host_caches import HostCaches

    return HostCaches.open(str(cache), frame_cache_gb=gb, frame_cache_format=fmt)


def _entry_bytes(caches) -> List[int]:
    """Bytes of each entry in the frame cache of ``caches``."""
    return [size for _, size, _ in caches.frame_cache.disk.entries()]


def measure(clip: Path, videos: int, rounds: int) -> dict:
    """Medians over ``rounds`` interleaved rounds: ``bound`` (samples/CPU-s), ``rows`` (name ->
    samples/CPU-s), ``bytes`` (format -> bytes per video)."""
    tmp = Path(tempfile.mkdtemp(prefix="v2v-fcache-"))
    corpus = make_corpus(tmp / "c", videos, clip)
    settle()
    warm_kernel()
    worker_core(corpus, OUTPUTS, 1, 1, flow_grid=True)  # numba's cached kernels loaded, OpenCV warmed
    runs: dict = {}
    sizes: dict = {}
    bound = []
    try:
        for r in range(rounds):
            bound.append(bare_decode(clip, 2) / SPAN)
            runs.setdefault("off", []).append(worker_core(corpus, OUTPUTS, 1, videos, flow_grid=True))
            for fmt in ("raw", "zstd"):
                cache = tmp / f"cache-{fmt}-{r}"
                caches = _caches(cache, fmt)
                runs.setdefault(f"{fmt} epoch 0", []).append(
                    worker_core(corpus, OUTPUTS, 1, videos, flow_grid=True, caches=caches, epoch=0))
                runs.setdefault(f"{fmt} epoch 1", []).append(
                    worker_core(corpus, OUTPUTS, 1, videos, flow_grid=True, caches=caches, epoch=1))
                sizes[fmt] = _entry_bytes(caches)
                shutil.rmtree(cache)
        half = sum(sizes["raw"]) / 2
        caches = _caches(tmp / "cache-half", "raw", half / (1 << 30))
        worker_core(corpus, OUTPUTS, 1, videos, flow_grid=True, caches=caches, epoch=0)
        caches.take_stats()
        budget_rate = worker_core(corpus, OUTPUTS, 1, videos, flow_grid=True, caches=caches, epoch=1)
        st = caches.take_stats()["frame_cache"]
        looked = st["hits"] + sum(st["misses"].values())
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {"bound": statistics.median(bound), "rows": {k: statistics.median(v) for k, v in runs.items()},
            "bytes": {f: statistics.median(v) for f, v in sizes.items()},
            "budget": {"hit_ratio": st["hits"] / looked if looked else 0.0, "rate": budget_rate}}


def frames_per_video(clip: Path) -> int:
    """Frames one pass of the clip decodes at the paper's recipe (what an entry holds)."""
    from v2v_server.frames.video_read import read_video
    from v2v_server.samples.recipe import SampleRecipe
    from v2v_server.sources.local import LocalSource

    with read_video(LocalSource(clip.parent), clip.name, SampleRecipe(shot_cuts="off").reads) as read:
        return sum(1 for _ in read.frames)


def serve(clip: Path, videos: int, samples: int) -> dict:
    """``bench.speed.producer`` with 2 workers, epochs 1+: cache off, and warm (``raw``)."""
    import subprocess

    tmp = Path(tempfile.mkdtemp(prefix="v2v-fcache-serve-"))
    try:
        corpus = make_corpus(tmp / "c", videos, clip)
        settle()
        cache = ["--frame-cache-gb", "64", "--cache-dir", str(tmp / "cache")]
        subprocess.run([sys.executable, "-m", "v2v_server.cli", "--videos", str(corpus), "--workers", "2",
                        "--warm-cache", *cache], check=True, capture_output=True, timeout=1800)
        return {"off": producer(corpus, 2, samples, []), "raw": producer(corpus, 2, samples, cache)}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clip", default="webvid_like_596x336.mp4")
    ap.add_argument("--videos", type=int, default=4, help="clip copies (2 windows each)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--serve", type=int, default=0, metavar="SAMPLES",
                    help="also measure SAMPLES samples through v2v-serve --workers 2, cache off and warm")
    a = ap.parse_args(argv)
    clip = clip_path(a.clip)
    r = measure(clip, a.videos, a.rounds)
    b = r["bound"]
    print(f"decode bound: {b:.2f} samples/CPU-s ({1e3 / b:.0f} CPU-ms per 201-frame window); clip {clip.name}, "
          f"{a.videos} copies, every output, one crop per window, {a.rounds} interleaved rounds, medians\n")
    print("| worker path | samples/CPU-s | CPU-ms per sample | share of decode bound | vs cache off |")
    print("|---|---:|---:|---:|---:|")
    off = r["rows"]["off"]
    for name, v in r["rows"].items():
        print(f"| {name} | {v:.2f} | {1e3 / v:.0f} | {v / b:.2f}x | {v / off:.2f}x |")
    n = frames_per_video(clip)
    print(f"\n| format | bytes per video ({n} frames) | per frame | per hour of this video (25 fps) | "
          + " | ".join(WEBVID_WINDOWS) + " |")
    print("|---|---:|---:|---:|" + "---:|" * len(WEBVID_WINDOWS))
    for fmt, nb in r["bytes"].items():
        per = nb / n
        sub = " | ".join(f"{per * 200 * w / 1e9:.0f} GB" for w in WEBVID_WINDOWS.values())
        print(f"| {fmt} | {nb / 1e6:.1f} MB | {per / 1e3:.1f} kB | {per * 25 * 3600 / 1e9:.1f} GB | {sub} |")
    bud = r["budget"]
    print(f"\nbudget of half the corpus (raw, policy keep): epoch 1 hit ratio {bud['hit_ratio']:.0%}, "
          f"{bud['rate']:.2f} samples/CPU-s ({bud['rate'] / off:.2f}x cache off)")
    if a.serve:
        s = serve(clip, a.videos, a.serve)
        print("\n| v2v-serve --workers 2, epochs 1+ | samples/s | per worker CPU-s | server CPU-ms per sample |")
        print("|---|---:|---:|---:|")
        for name, m in s.items():
            print(f"| cache {name} | {m['samples_per_s']:.2f} | {m['per_worker_cpu_s']:.2f} | "
                  f"{m['server_cpu_s'] * 1e3:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

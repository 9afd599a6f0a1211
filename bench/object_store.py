"""Reading the corpus from an object store against local disk, in one run (docs/object_store.md).

Starts a SeaweedFS S3 server on this host (harness/object_store.py), uploads the bundled clips,
and measures:

1. samples/s of one worker core making the same samples (the Ray engine's stage,
   ``ray_data.SampleMaker``, in this process) from the folder and from the bucket, as a
   ratio (store / local), alternating the two ``--repeats`` times;
2. bytes fetched from the store per sample and per video, against the video's file size;
3. start-up cost of a large corpus: seconds and peak Python memory (tracemalloc) to get the
   video list of a prefix of ``--objects`` objects and of a ``--objects``-line video list,
   without a manifest (first start: the prefix is listed, page by page) and with one
   (restart, other shards).

    python -m bench.object_store [--objects 10000] [--repeats 3]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
import tracemalloc
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CLIPS = ROOT / "v2v_server" / "sample_videos"


def _cfg(tmp: Path, **kw):
    """The paper's recipe with L = 20 voxel grids of 5 bins (101-frame windows: the bundled clips of
    132, 250 and 450 frames give 1, 2 and 4 windows), 128-pixel crops."""
    from v2v_server.ops.config import ServeConfig

    return ServeConfig(shot_cuts="off", sequence_length=20, flow_preset="ultrafast", cache_dir=str(tmp / "cache"), **kw)


class Epochs:
    """One worker's ``SampleMaker`` on ``videos``, built once (as a Ray actor or a v2v-serve
    worker keeps its store client), making whole epochs."""

    def __init__(self, cfg, videos: str):
        from v2v_server.ray_data import SampleMaker, epoch_descriptors, scan_corpus_windows

        self.rc = scan_corpus_windows(videos, cfg)
        self.maker = SampleMaker.of(cfg, videos, ("voxels", "frames"))
        self.descs = epoch_descriptors(self.rc, 0)

    def run(self):
        """(samples, seconds, store stats) of one epoch."""
        self.maker.source.take_stats()
        t0 = time.perf_counter()
        n = 0
        for d in self.descs:
            for _ in self.maker.video_rows(d["video"], 0, json.loads(d["entries"])):
                n += 1
        return n, time.perf_counter() - t0, self.maker.source.take_stats()


def startup(cfg_kw: dict, tmp: Path, videos: str, manifest: bool) -> tuple:
    """(seconds, peak MiB of Python allocations, videos) to list ``videos``."""
    from v2v_server.ops.config import source_from_config

    cfg = _cfg(tmp, **cfg_kw)
    src = source_from_config(cfg, videos)
    if not manifest and getattr(src, "manifest", None):
        Path(src.manifest.path).unlink(missing_ok=True)
    tracemalloc.start()
    t0 = time.perf_counter()
    src.check()
    found, _ = src.list_videos(cfg.video_extensions)
    dt = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1] / (1 << 20)
    tracemalloc.stop()
    return dt, peak, len(found)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--objects", type=int, default=10000)
    p.add_argument("--repeats", type=int, default=3)
    a = p.parse_args(argv)
    from harness.object_store import SeaweedS3

    with tempfile.TemporaryDirectory(prefix="v2v-bench-store-") as t, SeaweedS3() as s3:
        tmp = Path(t)
        os.environ.update(s3.env(), XDG_CACHE_HOME=str(tmp / "xdg"))
        s3.upload(CLIPS, "s3://bench/clips/", [p.name for p in sorted(CLIPS.glob("*.mp4"))])
        cfg = _cfg(tmp)
        local, store = Epochs(cfg, str(CLIPS)), Epochs(cfg, "s3://bench/clips/")
        local.run(), store.run()  # warm: kernels compiled, files in the page cache, store client connected
        rates = {"local": [], "store": []}
        for _ in range(a.repeats):  # alternated, so that the machine's load falls on both
            for name, e in (("local", local), ("store", store)):
                n, dt, stats = e.run()
                rates[name].append(n / dt)
                if name == "store":
                    st = stats
        size = sum(p.stat().st_size for p in CLIPS.glob("*.mp4"))
        lo, so = statistics.median(rates["local"]), statistics.median(rates["store"])
        print(f"recipe: L={cfg.sequence_length} x {cfg.num_bins} bins, crop {cfg.crop_size}, {n} samples of "
              f"{len(store.rc.windows)} videos per epoch, outputs voxels + frames")
        print(f"samples/s per worker core: local {lo:.3f}, store {so:.3f}, ratio store/local {so / lo:.3f} "
              f"(median of {a.repeats} alternated epochs)")
        print(f"store bytes fetched per epoch {st['bytes']} in {st['reads']} range request(s); file sizes {size}; "
              f"fetched / file size {st['bytes'] / size:.3f}; per sample {st['bytes'] / n:.0f} B; "
              f"store wait {st['read_s']:.3f} s per epoch")

        # a large corpus: N small objects under a prefix, and an N-line list
        fs = s3.fs()
        names = [f"{i // 1000:03d}/{i:07d}.mp4" for i in range(a.objects)]
        t0 = time.perf_counter()
        fs.pipe({f"bench/big/{n}": b"x" for n in names})
        print(f"uploaded {a.objects} objects in {time.perf_counter() - t0:.1f} s")
        lst = tmp / "list.txt"
        lst.write_text("".join(f"{n} 250 1.0 1.0\n" for n in names))
        rows = []
        for label, videos, kw in (("prefix", "s3://bench/big/", {}),
                                  ("list", "s3://bench/big/", {"video_list": str(lst)})):
            for manifest in (False, True):
                dt, mib, found = startup(kw, tmp, videos, manifest)
                rows.append((label, manifest, dt, mib, found))
        print(f"{'corpus':<28} {'manifest':<9} {'seconds':>8} {'peak MiB':>9} {'videos':>7}")
        for label, manifest, dt, mib, found in rows:
            what = f"{a.objects}-object prefix" if label == "prefix" else f"{a.objects}-line video list"
            print(f"{what:<28} {'yes' if manifest else 'no':<9} {dt:>8.3f} {mib:>9.1f} {found:>7}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

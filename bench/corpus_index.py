"""What the corpus index saves: the Ray engine's scan of a corpus, first with an empty index (every
video decoded to find its cuts under ``shot_cuts: avoid``) and again with the same ``cache_dir``
(answered from the index), in one run.

``python -m bench.corpus_index [--clips 60] [--json docs/corpus_index.json]`` makes a folder of
``--clips`` hard links to the bundled one-shot clip ``bbb_camera_596x336.mp4`` (one shot longer
than a 201-frame window, so every link is usable under the default recipe), scans it twice with ``ray_data.scan_corpus_windows`` and
prints seconds per scan, per clip, and the ratio first / second.

``--start-entries 65000,250000,1000000`` also measures what a ``v2v-serve`` start pays to read
a warm index (``frames.known.known_windows``: a status and a lookup per video, 500 lookups a
query) on folders of that many links whose entries are all in the index (written with SQLite
directly from one real verdict, one row per link): seconds, microseconds per video, and the
growth of the process's peak RSS over the call.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import sqlite3
import tempfile
import time
from pathlib import Path

from harness.data import SAMPLE_VIDEOS
from v2v_server.frames.host_caches import HostCaches
from v2v_server.ops.config import ServeConfig
from v2v_server.ray_data import scan_corpus_windows
from v2v_server.frames.check import check_video
from v2v_server.frames.known import known_windows
from v2v_server.frames.corpus_index import CorpusIndex, index_path, layout_key
from v2v_server.sources.local import RACY_NS, LocalSource

CLIP = "bbb_camera_596x336.mp4"


def run(clips: int) -> dict:
    """Seconds of a first and a second scan of ``clips`` links to :data:`CLIP`."""
    with tempfile.TemporaryDirectory() as tmp:
        corpus = Path(tmp, "corpus")
        corpus.mkdir()
        for i in range(clips):
            os.link(SAMPLE_VIDEOS / CLIP, corpus / f"clip_{i:05d}.mp4")
        time.sleep(2 * RACY_NS / 1e9)  # links are new: their change time must leave the racy window
        cfg = ServeConfig(cache_dir=str(Path(tmp, "cache")))
        out = {"clips": clips}
        for name in ("first", "second"):
            t0 = time.perf_counter()
            corpus_windows = scan_corpus_windows(corpus, cfg)
            out[f"{name}_s"] = round(time.perf_counter() - t0, 3)
            assert len(corpus_windows.windows) == clips, corpus_windows.skipped
        out["first_ms_per_clip"] = round(out["first_s"] / clips * 1e3, 2)
        out["second_ms_per_clip"] = round(out["second_s"] / clips * 1e3, 2)
        out["ratio"] = round(out["first_s"] / out["second_s"], 1)
    return out


def start(entries: int) -> dict:
    """Seconds and peak-RSS growth of ``known_windows`` over ``entries`` links, all indexed."""
    with tempfile.TemporaryDirectory() as tmp:
        corpus, cache = Path(tmp, "corpus"), Path(tmp, "cache")
        corpus.mkdir()
        names = [f"{i // 1000:04d}/clip_{i:07d}.mp4" for i in range(entries)]
        for d in {n.split("/")[0] for n in names}:
            (corpus / d).mkdir()
        copies = []  # a file holds at most 65,000 links (ext4): one copy of the clip per 60,000
        for i, n in enumerate(names):
            if i % 60_000 == 0:
                copies.append(Path(tmp, f"{CLIP}.{len(copies)}"))
                shutil.copyfile(SAMPLE_VIDEOS / CLIP, copies[-1])
            os.link(copies[-1], corpus / n)
        time.sleep(2 * RACY_NS / 1e9)
        cfg = ServeConfig(cache_dir=str(cache))
        w, d = cfg.recipe.windows, cfg.recipe.decode
        source, caches = LocalSource(corpus), HostCaches(str(cache))
        verdict = check_video(w, d, source, names[0], caches)  # one real verdict, written for every link
        db = sqlite3.connect(index_path(cache))
        with db:
            db.executemany("INSERT OR REPLACE INTO entries VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                           ((source.where(n), layout_key(w, d), source.listed_identity(n), verdict.frames,
                             verdict.windows, 1, "", "", "[]", 596, 336, "h264", 25.0, json.dumps(verdict.to_json()),
                             0.0)
                            for n in names))
        db.close()
        assert len(CorpusIndex(index_path(cache))) == entries
        source, caches = LocalSource(corpus), HostCaches(str(cache))  # a fresh start's
        rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        t0 = time.perf_counter()
        known = known_windows(w, d, source, names, caches)
        s = time.perf_counter() - t0
        assert known.known == entries and known.samples == entries * verdict.windows
        return {"entries": entries, "seconds": round(s, 2), "us_per_video": round(s / entries * 1e6, 1),
                "peak_rss_growth_mb": round((resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0) / 1024, 1)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clips", type=int, default=60)
    ap.add_argument("--start-entries", default="", help="comma-separated corpus sizes for the start's read of a "
                                                        "warm index (empty: not measured)")
    ap.add_argument("--json", type=Path, default=None, help="write the result here too")
    args = ap.parse_args(argv)
    r = run(args.clips)
    if args.start_entries:
        r["start"] = [start(int(n)) for n in args.start_entries.split(",")]
    print(json.dumps(r))
    if args.json:
        args.json.write_text(json.dumps(r, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""What the corpus index saves: the Ray engine's scan of a corpus, first with an empty index (every
video decoded to find its cuts under ``shot_cuts: avoid``) and again with the same ``cache_dir``
(answered from the index), in one run.

``python -m bench.corpus_index [--clips 60] [--json docs/corpus_index.json]`` makes a folder of
``--clips`` hard links to the bundled one-shot clip ``bbb_camera_596x336.mp4`` (one shot longer
than a 201-frame window, so every link is usable under the default recipe), scans it twice with ``ray_data.scan_corpus_windows`` and
prints seconds per scan, per clip, and the ratio first / second.
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

from harness.data import SAMPLE_VIDEOS
from v2v_server.ops.config import ServeConfig
from v2v_server.ray_data import scan_corpus_windows
from v2v_server.videos.local import RACY_NS

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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clips", type=int, default=60)
    ap.add_argument("--json", type=Path, default=None, help="write the result here too")
    args = ap.parse_args(argv)
    r = run(args.clips)
    print(json.dumps(r))
    if args.json:
        args.json.write_text(json.dumps(r, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Server start, first batch and server memory against the number of videos in a folder corpus.

Run: ``python -m bench.corpus_scale [--sizes 65000,250000,1000000] [--baseline-tree DIR] [--out FILE]``
(docs/scaling.md, "A corpus of a million files", holds its table).

For each size N the bench makes a folder of N hard links (subfolders of 1000) to the bundled
one-shot clip, so a corpus of a million entries costs inodes, not bytes (ext4 allows 65,000
links to one file, so every 60,000 links get a copy of their own). On it, ``v2v-serve
--workers 1`` starts with small samples (L = 4, 64 px crops, so that decoding does not hide
what the corpus size costs), and one trainer reads one batch. Rows: seconds from the
process start to the "serving" log line, seconds to the first batch, and the peak resident
memory (``VmHWM``) of the server process and of its worker. With ``--baseline-tree``, every
size is measured also with the code of another checkout (``PYTHONPATH``), in the same run,
and the table shows the ratios. The trainer reads by plan (``V2VStreamDataset``).
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import List, Optional

from harness.serve import ServeProcess
from v2v_client import V2VStreamDataset

CLIP = Path(__file__).resolve().parent.parent / "v2v_server" / "sample_videos" / "bbb_camera_596x336.mp4"
LINKS_PER_COPY = 60_000  # ext4 allows 65,000 links to one inode
PER_FOLDER = 1000


def link_corpus(root: Path, n: int, clip: Path = CLIP) -> Path:
    """A folder ``root/videos`` of ``n`` hard links to ``clip`` (``d0000/v000.mp4`` ...), 1000 a
    subfolder; the copies the links point at lie in ``root`` beside it. Returns the folder."""
    videos = root / "videos"
    videos.mkdir(parents=True)
    base = None
    for i in range(n):
        if i % LINKS_PER_COPY == 0:
            base = root / f"copy{i // LINKS_PER_COPY}.mp4"
            shutil.copyfile(clip, base)
        d = videos / f"d{i // PER_FOLDER:04d}"
        if i % PER_FOLDER == 0:
            d.mkdir()
        os.link(base, d / f"v{i % PER_FOLDER:03d}.mp4")
    return videos


def peak_rss_mb(pid: int) -> float:
    """Peak resident memory (``VmHWM``) of process ``pid``, MB (1e6 bytes); 0 when it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024 / 1e6
    except OSError:
        pass
    return 0.0


def children(pid: int) -> List[int]:
    """The process ids of ``pid``'s children (all its threads')."""
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            out += [int(k) for k in (task / "children").read_text().split()]
        except OSError:
            continue
    return out


def measure(videos: Path, tree: str, timeout_s: float) -> dict:
    """Start ``v2v-serve`` on ``videos`` with the code of the checkout ``tree`` and read one batch
    (of 4 samples) by plan."""
    args = ["--videos", str(videos), "--workers", "1", "--sequence-length", "4", "--crop-size", "64",
            "--batch-size", "4", "--seed", "1", "--shot-cuts", "off", "--log-level", "INFO"]
    # ``python -m`` puts the working folder first on sys.path: the server starts in ``tree``
    t0 = time.monotonic()
    with ServeProcess(args, ready_timeout_s=timeout_s, env={"PYTHONPATH": tree}, wrap=["env", "-C", tree]) as srv:
        serving = time.monotonic() - t0
        it = iter(V2VStreamDataset(srv.endpoint, 4, outputs=("voxels",), prefetch=1, timeout_s=timeout_s))
        try:
            next(it)
            first = time.monotonic() - t0
            server = peak_rss_mb(srv.proc.pid)
            workers = [peak_rss_mb(c) for c in children(srv.proc.pid)]
        finally:
            it.close()
    return {"serving_s": serving, "first_batch_s": first, "server_mb": server, "worker_mb": max(workers, default=0.0)}


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", default="65000,250000,1000000", help="corpus sizes (videos), comma-separated")
    p.add_argument("--baseline-tree", help="a checkout whose code is measured too, for ratios (e.g. a worktree of main)")
    p.add_argument("--timeout", type=float, default=900.0, help="seconds a server may take to start or to give a batch")
    p.add_argument("--tmp", default=None, help="folder for the generated corpora (default: the system's temp folder)")
    p.add_argument("--out", help="also write the table (markdown) here")
    a = p.parse_args(argv)
    here = str(Path(__file__).resolve().parent.parent)
    trees = ([("baseline", a.baseline_tree)] if a.baseline_tree else []) + [("this tree", here)]
    lines = ["| videos | code | to serving (s) | to first batch (s) | server peak RSS (MB) | worker peak RSS (MB) |",
             "|---:|---|---:|---:|---:|---:|"]
    for n in [int(s) for s in a.sizes.split(",")]:
        with tempfile.TemporaryDirectory(prefix="v2v-corpus-scale-", dir=a.tmp) as d:
            t = time.monotonic()
            videos = link_corpus(Path(d), n)
            print(f"{n} links made in {time.monotonic() - t:.1f} s", file=sys.stderr)
            rows = {}
            for name, tree in trees:
                rows[name] = r = measure(videos, tree, a.timeout)
                print(f"{n} {name}: {r}", file=sys.stderr)
                lines.append(f"| {n:,} | {name} | {r['serving_s']:.1f} | {r['first_batch_s']:.1f} | "
                             f"{r['server_mb']:.0f} | {r['worker_mb']:.0f} |")
            if "baseline" in rows and "this tree" in rows:
                b, c = rows["baseline"], rows["this tree"]
                lines.append(f"| {n:,} | baseline / this tree | {b['serving_s'] / c['serving_s']:.2f}x | "
                             f"{b['first_batch_s'] / c['first_batch_s']:.2f}x | {b['server_mb'] / c['server_mb']:.2f}x | "
                             f"{b['worker_mb'] / max(c['worker_mb'], 1e-9):.2f}x |")
    table = "\n".join(lines)
    print(table)
    if a.out:
        Path(a.out).write_text(table + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

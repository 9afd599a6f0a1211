"""How well batches mix videos, how much the epoch order changes, and what shuffling costs.

Usage: ``python -m bench.shuffle [--clips 24] [--workers 1,4] [--out FILE.json]``

Makes a corpus of ``--clips`` small synthetic clips (``harness.corpus.write_video``; 5 windows
each at the tiny layout below), then for each worker count runs a real ``v2v-serve`` for two
epochs under ``--shuffle none`` and ``--shuffle epoch`` (default ``--shuffle-batches``), one
trainer (``V2VStreamDataset``) reading every batch. Prints, per run:

* distinct videos per batch, mean over epoch 0's batches;
* Kendall's tau between the epoch orders of epochs 0 and 1 (each sample's position in the
  order the trainer received them; 1 = the same order, 0 = unrelated);
* samples/s over the two epochs (start of the iteration to the last batch; the same machine,
  the same run), and
  for ``epoch`` its ratio to ``none`` at the same worker count.

docs/shuffle.md quotes its output.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Dict, List, Sequence, Tuple

#: Tiny samples (L = 4 voxel grids of 5 bins, 32 px crops): 21 frames per window.
LAYOUT = ["--sequence-length", "4", "--crop-size", "32", "--max-samples-per-video", "5", "--batch-size", "8",
          "--seed", "3", "--flow-preset", "ultrafast"]
#: Frames per clip: 5 windows of 20 frames and the last one.
CLIP_FRAMES = 101


def make_corpus(root: Path, clips: int) -> Path:
    """``clips`` synthetic clips of ``CLIP_FRAMES`` frames, 64 x 48 px, in ``root``."""
    from harness.corpus import write_video

    root.mkdir(parents=True, exist_ok=True)
    for i in range(clips):
        write_video(root / f"clip{i:02d}.mp4", CLIP_FRAMES, 64 + 2 * (i % 4), 48)
    return root


def kendall_tau(a: Sequence[str], b: Sequence[str]) -> float:
    """Kendall's tau-a between two orders of the same items (those in both): +1 same order,
    -1 reversed, about 0 unrelated. O(n^2); n is a few hundred here."""
    common = set(a) & set(b)
    ra = {x: i for i, x in enumerate(x for x in a if x in common)}
    rb = {x: i for i, x in enumerate(x for x in b if x in common)}
    items = list(ra)
    n = len(items)
    if n < 2:
        return float("nan")
    s = 0
    for i in range(n):
        for j in range(i + 1, n):
            x, y = items[i], items[j]
            s += 1 if (ra[x] - ra[y]) * (rb[x] - rb[y]) > 0 else -1
    return s / (n * (n - 1) / 2)


def read_epochs(endpoint: str) -> Tuple[Dict[int, List[List[str]]], float]:
    """Every batch of the stream by epoch (sample ids in batch order), and samples/s from the
    start of the iteration to the last batch (the wait for the first batch included: a
    shuffle buffer delays it)."""
    from v2v_client import V2VStreamDataset

    batches: Dict[int, List[List[str]]] = {}
    n, t0 = 0, time.monotonic()
    for b in V2VStreamDataset(endpoint, outputs=("voxels",), credits=4, timeout_s=120):
        ids = [s for s, pad in zip(b["sample_ids"], b["padding"].tolist()) if not pad]
        batches.setdefault(int(b["epoch"]), []).append(ids)
        n += len(ids)
    return batches, n / max(time.monotonic() - t0, 1e-9)


def run(corpus: Path, workers: int, shuffle: str) -> dict:
    """One two-epoch stream; the figures of the module docstring."""
    from harness.serve import ServeProcess

    with ServeProcess(["--videos", str(corpus), "--workers", str(workers), "--epochs", "2", "--shuffle", shuffle,
                       *LAYOUT], ready_timeout_s=120) as srv:
        batches, rate = read_epochs(srv.endpoint)
        srv.wait(60)
    order = {e: [s for b in bs for s in b] for e, bs in batches.items()}
    distinct = statistics.mean(len({s.rsplit("#", 1)[0] for s in b}) for b in batches[0])
    return {"workers": workers, "shuffle": shuffle, "batches_epoch0": len(batches[0]),
            "samples_epoch0": len(order[0]), "distinct_videos_per_batch": round(distinct, 2),
            "kendall_tau_epoch0_vs_1": round(kendall_tau(order[0], order[1]), 3), "samples_per_s": round(rate, 1)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--clips", type=int, default=24)
    p.add_argument("--workers", default="1,4", help="comma list of worker counts")
    p.add_argument("--out", help="also write the rows as JSON here")
    a = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        corpus = make_corpus(Path(tmp) / "clips", a.clips)
        for w in [int(x) for x in a.workers.split(",")]:
            for shuffle in ("none", "epoch"):
                rows.append(run(corpus, w, shuffle))
                print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    print(f"{a.clips} clips x 5 windows, batch 8, two epochs, one trainer\n")
    print("| workers | shuffle | distinct videos / batch (epoch 0) | Kendall tau epoch 0 vs 1 | samples/s | vs none |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        base = next(x for x in rows if x["workers"] == r["workers"] and x["shuffle"] == "none")
        print(f"| {r['workers']} | {r['shuffle']} | {r['distinct_videos_per_batch']:.2f} | "
              f"{r['kendall_tau_epoch0_vs_1']:+.3f} | {r['samples_per_s']:.1f} | "
              f"{r['samples_per_s'] / base['samples_per_s']:.2f} |")
    if a.out:
        Path(a.out).write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

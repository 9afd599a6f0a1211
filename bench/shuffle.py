"""How well batches mix videos, how much the epoch order changes, and what shuffling costs.

Usage: ``python -m bench.shuffle [--clips 24] [--workers 1,4] [--rounds 3] [--out FILE.json]``

Makes a corpus of ``--clips`` small synthetic clips (``harness.corpus.write_video``; 5 windows
each at the tiny layout below), then for each worker count runs a real ``v2v-serve`` for two
epochs under ``--shuffle none`` and ``--shuffle epoch`` (default ``--shuffle-buffer``), one
trainer (``V2VStreamDataset``) reading every batch, ``--rounds`` times (seeds 3, 4, ...; the
settings interleaved). Prints, per setting:

* distinct videos per batch, mean over epoch 0's batches (and over the rounds);
* Kendall's tau between the epoch orders of epochs 0 and 1 (each sample's position in the
  order the trainer received them; 1 = the same order, 0 = unrelated), mean over the rounds;
* seconds to the first batch, and samples/s over the two epochs (start of the iteration to
  the last batch), medians over the rounds, with the ratio to ``none`` at the same worker count;

what the alternative design, a shuffle buffer that stacks batches of randomly picked samples,
would cost per sample of the default recipe (:func:`copy_cost`), and distinct videos per batch
against ``shuffle_buffer`` for one worker at the default recipe's shape (:func:`buffer_sizes`).

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
          "--flow-preset", "ultrafast"]
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


def read_epochs(endpoint: str) -> Tuple[Dict[int, List[List[str]]], float, float]:
    """Every batch of the stream by epoch (sample ids in batch order), samples/s from the start
    of the iteration to the last batch (the wait for the first batch included: a shuffle buffer
    delays it), and seconds to the first batch."""
    from v2v_client import V2VStreamDataset

    batches: Dict[int, List[List[str]]] = {}
    n, t0, first = 0, time.monotonic(), None
    for b in V2VStreamDataset(endpoint, outputs=("voxels",), credits=4, timeout_s=120):
        first = first if first is not None else time.monotonic() - t0
        ids = [s for s, pad in zip(b["sample_ids"], b["padding"].tolist()) if not pad]
        batches.setdefault(int(b["epoch"]), []).append(ids)
        n += len(ids)
    return batches, n / max(time.monotonic() - t0, 1e-9), first or 0.0


def run(corpus: Path, workers: int, shuffle: str, seed: int) -> dict:
    """One two-epoch stream; the figures of the module docstring."""
    from harness.serve import ServeProcess

    with ServeProcess(["--videos", str(corpus), "--workers", str(workers), "--epochs", "2", "--shuffle", shuffle,
                       *LAYOUT, "--seed", str(seed)], ready_timeout_s=120) as srv:
        batches, rate, first_s = read_epochs(srv.endpoint)
        srv.wait(60)
    order = {e: [s for b in bs for s in b] for e, bs in batches.items()}
    distinct = statistics.mean(len({s.rsplit("#", 1)[0] for s in b}) for b in batches[0])
    return {"workers": workers, "shuffle": shuffle, "seed": seed, "batches_epoch0": len(batches[0]),
            "samples_epoch0": len(order[0]), "distinct_videos_per_batch": distinct,
            "kendall_tau_epoch0_vs_1": kendall_tau(order[0], order[1]), "samples_per_s": rate,
            "first_batch_s": first_s}


def copy_cost(batch: int = 12, rounds: int = 5) -> dict:
    """What a shuffle buffer that picks made samples at random would add: its batches are not
    consecutive rows of one buffer, so each is stacked (one more copy of every byte, on the
    server's one loop thread). Measured on samples of the default recipe (L = 40, 5 bins,
    128 px: voxels int8, frames uint8, flow float16): ms per sample, median of ``rounds``."""
    import numpy as np

    from v2v_server.service.datapath import BatchAssembler, make_batch

    arrays = {"voxels": np.ones((40, 5, 128, 128), np.int8), "frames": np.ones((41, 128, 128), np.uint8),
              "flow": np.ones((40, 2, 128, 128), np.float16)}
    asm = BatchAssembler(batch)
    out = []
    for _ in range(rounds):
        samples = [asm.place(f"v#{i}", {}, arrays, lane=i) for i in range(batch)]  # one row of each buffer
        t0 = time.perf_counter()
        make_batch(samples).arrays  # stacked: the copy
        out.append((time.perf_counter() - t0) / batch * 1e3)
        del samples
    return {"sample_mb": sum(a.nbytes for a in arrays.values()) / 1e6, "stack_ms_per_sample": statistics.median(out)}


def buffer_sizes(sizes=(12, 32, 64, 128, 256), videos: int = 200, windows: int = 10, batch: int = 12) -> dict:
    """Distinct videos per batch against ``shuffle_buffer`` for one worker's arrivals (each video's
    ``windows`` samples in order, video after video) at the default recipe's shape (10 windows
    per video, batches of 12), from the pure ``Batcher`` (no server): size -> mean."""
    from v2v_server.delivery.batcher import Batcher
    from v2v_server.delivery.ledger import DeliveryLedger
    from v2v_wire.ids import SampleKey

    out = {}
    for size in sizes:
        ledger = DeliveryLedger(lease_s=1.0, client_timeout_s=1.0)
        b = Batcher(batch, list, ledger, lanes=-(-size // batch), seed=0)
        for v in range(videos):
            for w in range(windows):
                b.add(0, ("voxels",), SampleKey(f"v{v}", w, 0), None, b.lane(0, ("voxels",)))
        b.flush(lambda e: True)
        out[size] = statistics.mean(len({k.video for k in ledger.batches[i].keys}) for i in ledger.ready)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--clips", type=int, default=24)
    p.add_argument("--workers", default="1,4", help="comma list of worker counts")
    p.add_argument("--rounds", type=int, default=3, help="runs per setting (seeds 3, 4, ...), interleaved")
    p.add_argument("--out", help="also write the rows as JSON here")
    a = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        corpus = make_corpus(Path(tmp) / "clips", a.clips)
        for r in range(a.rounds):
            for w in [int(x) for x in a.workers.split(",")]:
                for shuffle in ("none", "epoch"):
                    rows.append(run(corpus, w, shuffle, 3 + r))
                    print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    cost, sizes = copy_cost(), buffer_sizes()
    print(f"{a.clips} clips x 5 windows, batch 8, shuffle_buffer 64 (8 open batches), two epochs, one trainer; "
          f"mean of {a.rounds} runs (seeds 3-{2 + a.rounds}), samples/s median\n")
    print("| workers | shuffle | distinct videos / batch (epoch 0) | Kendall tau epoch 0 vs 1 | first batch (s) "
          "| samples/s | vs none |")
    print("|---|---|---|---|---|---|---|")
    table = {}
    for r in rows:
        table.setdefault((r["workers"], r["shuffle"]), []).append(r)
    for (w, shuffle), rs in table.items():
        rate = statistics.median(x["samples_per_s"] for x in rs)
        base = statistics.median(x["samples_per_s"] for x in table[(w, "none")])
        print(f"| {w} | {shuffle} | {statistics.mean(x['distinct_videos_per_batch'] for x in rs):.2f} | "
              f"{statistics.mean(x['kendall_tau_epoch0_vs_1'] for x in rs):+.3f} | "
              f"{statistics.median(x['first_batch_s'] for x in rs):.2f} | {rate:.1f} | {rate / base:.2f} |")
    print(f"\nA shuffle buffer picking made samples at random would stack every batch: "
          f"{cost['stack_ms_per_sample']:.2f} ms per {cost['sample_mb']:.1f} MB sample of the default recipe "
          f"on the server's loop thread (one more copy of every byte).")
    print("\nOne worker, 10 windows per video, batches of 12 (the default recipe's shape; the pure Batcher):\n")
    print("| shuffle_buffer | " + " | ".join(str(k) for k in sizes) + " |")
    print("|---|" + "---|" * len(sizes))
    print("| distinct videos / batch | " + " | ".join(f"{v:.2f}" for v in sizes.values()) + " |")
    if a.out:
        Path(a.out).write_text(json.dumps({"runs": rows, "copy_cost": cost, "buffer_sizes": sizes}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

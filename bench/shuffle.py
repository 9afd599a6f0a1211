"""How well batches mix videos, how much the epoch order changes, and what shuffling costs.

Usage: ``python -m bench.shuffle [--clips 24] [--workers 1,4] [--rounds 3] [--out FILE.json]``,
or ``python -m bench.shuffle --small-epoch [--rounds 2] [--samples 36]`` for :func:`small_epoch`.

Makes a corpus of ``--clips`` small synthetic clips (``harness.corpus.write_video``; 5 windows
each at the small layout below), then for each worker count runs a real ``v2v-serve`` for
``EPOCHS`` epochs under ``--shuffle none`` and ``--shuffle epoch`` (default ``--shuffle-buffer``), one
trainer (``V2VPushDataset``) reading every batch, ``--rounds`` times (seeds 3, 4, ...; the
settings interleaved). Prints, per setting:

* distinct videos per batch, mean over epoch 0's batches (and over the rounds);
* Kendall's tau between the epoch orders of epochs 0 and 1 (each sample's position in the
  order the trainer received them; 1 = the same order, 0 = unrelated), mean over the rounds;
* seconds to the first batch, samples/s over the whole run (start of the iteration to the last
  batch) and over epochs 1 on (epoch 1's first batch to the last: the buffer in its steady
  state), medians over the rounds, with their ratios to ``none`` at the same worker count;

what the alternative design, a shuffle buffer that stacks batches of randomly picked samples,
would cost per sample of the default recipe (:func:`copy_cost`), and distinct videos per batch
against ``shuffle_buffer`` for one worker at the default recipe's shape (:func:`buffer_sizes`).

``--small-epoch`` measures instead what shuffling costs when an epoch is smaller than the shuffle
buffer (:func:`small_epoch`).

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

#: Small samples (L = 8 voxel grids of 5 bins, 64 px crops): 41 frames per window.
LAYOUT = ["--sequence-length", "8", "--crop-size", "64", "--max-samples-per-video", "5", "--batch-size", "8",
          "--flow-preset", "ultrafast"]
#: Frames per clip: 5 windows of 40 frames and the last one.
CLIP_FRAMES = 201
#: Epochs per run: orders are compared between epochs 0 and 1; throughput is taken over epochs 1 on.
EPOCHS = 4


def make_corpus(root: Path, clips: int) -> Path:
    """``clips`` synthetic clips of ``CLIP_FRAMES`` frames, 96-102 x 72 px, in ``root``."""
    from harness.corpus import write_video

    root.mkdir(parents=True, exist_ok=True)
    for i in range(clips):
        write_video(root / f"clip{i:02d}.mp4", CLIP_FRAMES, 96 + 2 * (i % 4), 72)
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


def read_epochs(endpoint: str) -> Tuple[Dict[int, List[List[str]]], dict]:
    """Every batch of the stream by epoch (sample ids in batch order), and its timing: seconds
    to the first batch, samples/s over the whole run (from the start of the iteration), and
    samples/s over epochs 1 on (from epoch 1's first batch to the last batch: the buffer is in
    its steady state)."""
    from v2v_client import V2VPushDataset

    batches: Dict[int, List[List[str]]] = {}
    t0, first, first_e1, n_e1 = time.monotonic(), None, None, 0
    for b in V2VPushDataset(endpoint, outputs=("voxels",), credits=4, timeout_s=120):
        now = time.monotonic() - t0
        first = first if first is not None else now
        e = int(b["epoch"])
        ids = [s for s, pad in zip(b["sample_ids"], b["padding"].tolist()) if not pad]
        batches.setdefault(e, []).append(ids)
        if e >= 1:
            if first_e1 is None:
                first_e1 = now
            else:
                n_e1 += len(ids)
    end = time.monotonic() - t0
    n = sum(len(b) for bs in batches.values() for b in bs)
    return batches, {"first_batch_s": first or 0.0, "samples_per_s": n / max(end, 1e-9),
                     "steady_samples_per_s": n_e1 / max(end - (first_e1 or 0.0), 1e-9)}


def run(corpus: Path, workers: int, shuffle: str, seed: int) -> dict:
    """One stream of ``EPOCHS`` epochs; the figures of the module docstring."""
    from harness.serve import ServeProcess

    with ServeProcess(["--videos", str(corpus), "--shot-cuts", "off", "--workers", str(workers), "--epochs", str(EPOCHS),
                       "--shuffle", shuffle, *LAYOUT, "--seed", str(seed)], ready_timeout_s=120) as srv:
        batches, timing = read_epochs(srv.endpoint)
        srv.wait(60)
    order = {e: [s for b in bs for s in b] for e, bs in batches.items()}
    distinct = statistics.mean(len({s.rsplit("#", 1)[0] for s in b}) for b in batches[0])
    return {"workers": workers, "shuffle": shuffle, "seed": seed, "batches_epoch0": len(batches[0]),
            "samples_epoch0": len(order[0]), "distinct_videos_per_batch": distinct,
            "kendall_tau_epoch0_vs_1": kendall_tau(order[0], order[1]), **timing}


def copy_cost(batch: int = 12, rounds: int = 5) -> dict:
    """What a shuffle buffer that picks made samples at random would add: its batches are not
    consecutive rows of one buffer, so each is stacked (one more copy of every byte, on the
    server's one loop thread). Measured on samples of the default recipe (L = 40, 5 bins,
    128 px: voxels int8, frames uint8, flow float16): ms per sample, median of ``rounds``."""
    import numpy as np

    from v2v_server.service.assembly import BatchAssembler, make_batch

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
    per video, batches of 12), from the pure ``Batcher`` (no server), told how many samples are
    still to come as the server tells it once the files' counts are known (``"counted"``) and
    with the count unknown (``"unknown"``): ``{"counted": {size: (distinct videos per batch,
    samples left for the epoch-end flush)}, "unknown": {...}}``, both means over 5 seeds."""
    from v2v_server.delivery.batcher import Batcher
    from v2v_server.delivery.ledger import DeliveryLedger
    from v2v_wire.ids import SampleKey

    keys = [SampleKey(f"v{v}", w, 0) for v in range(videos) for w in range(windows)]

    def one(size, counted, seed):
        ledger = DeliveryLedger(lease_s=1.0, client_timeout_s=1.0, max_credits=64)
        b = Batcher(batch, list, ledger, lanes=-(-size // batch), seed=seed)
        for i, k in enumerate(keys):
            more = len(keys) - 1 - i if counted else None
            b.add(0, ("voxels",), k, None, b.lane(0, ("voxels",), more))
        left = b.fill()[0]
        b.flush(lambda e: True)
        return statistics.mean(len({k.video for k in ledger.batches[i].keys}) for i in ledger.ready), left

    out: dict = {"counted": {}, "unknown": {}}
    for size in sizes:
        for counted, into in ((True, out["counted"]), (False, out["unknown"])):
            runs = [one(size, counted, seed) for seed in range(5)]
            into[size] = (statistics.mean(r[0] for r in runs), statistics.mean(r[1] for r in runs))
    return out


def small_epoch(rounds: int = 2, samples: int = 36, copies: int = 6) -> List[dict]:
    """An epoch smaller than the shuffle buffer: ``copies`` copies of the WebVid-like clip
    (``bench.speed``: 2 windows each, so 12 samples per epoch at 6 copies), one worker, batches
    of 4 (the default buffer of 64 is 16 open batches), every output, read raw as fast as a
    client takes it (``bench.speed.producer``, ``samples`` measured after two batches).
    ``--shuffle none`` and ``--shuffle epoch`` interleaved for ``rounds`` rounds, each round
    also measuring the decode bound (``bench.speed.bare_decode``). One row per run:
    ``decode_share`` (samples per worker CPU-second / the round's decode bound) and
    ``server_cpu_s_per_gb`` (the server main process)."""
    from bench.speed import SPAN, bare_decode, clip_path, make_corpus as copies_of, producer, worker_core

    rows = []
    with tempfile.TemporaryDirectory(prefix="v2v-shuffle-") as d:
        corpus = copies_of(Path(d) / "webvid", copies)
        worker_core(corpus, ("voxels", "frames", "flow"), videos=1)  # load the compiled kernels once, unmeasured
        for r in range(rounds):
            bound = bare_decode(clip_path(), 2) / SPAN
            for shuffle in (("none", "epoch") if r % 2 == 0 else ("epoch", "none")):
                p = producer(corpus, 1, samples, ["--shuffle", shuffle])
                rows.append({"round": r, "shuffle": shuffle, "decode_bound": bound,
                             "decode_share": p["per_worker_cpu_s"] / bound, **p})
                print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    return rows


def print_small_epoch(rows: List[dict], samples: int) -> None:
    """The table of :func:`small_epoch`: per setting, the best round of each figure and its
    ratio to ``none``'s best."""
    best = {}
    for shuffle in ("none", "epoch"):
        rs = [r for r in rows if r["shuffle"] == shuffle]
        best[shuffle] = {"decode_share": max(r["decode_share"] for r in rs),
                         "server_cpu_s_per_gb": min(r["server_cpu_s_per_gb"] for r in rs),
                         "samples_per_s": max(r["samples_per_s"] for r in rs),
                         "core_share": max(r["core_share"] for r in rs)}
    print(f"6 copies of the WebVid-like clip (12 samples per epoch), 1 worker, batches of 4, every output, "
          f"{samples} samples measured; best of {len({r['round'] for r in rows})} interleaved rounds\n")
    print("| shuffle | samples / worker CPU-s, share of the decode bound | vs none | server main CPU-s / GB "
          "| vs none | samples/s | worker core share |")
    print("|---|---|---|---|---|---|---|")
    for shuffle, b in best.items():
        base = best["none"]
        print(f"| {shuffle} | {b['decode_share']:.2f} | {b['decode_share'] / base['decode_share']:.2f} | "
              f"{b['server_cpu_s_per_gb']:.2f} | {b['server_cpu_s_per_gb'] / base['server_cpu_s_per_gb']:.2f} | "
              f"{b['samples_per_s']:.2f} | {b['core_share']:.2f} |")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--clips", type=int, default=24)
    p.add_argument("--workers", default="1,4", help="comma list of worker counts")
    p.add_argument("--rounds", type=int, default=3, help="runs per setting (seeds 3, 4, ...), interleaved")
    p.add_argument("--out", help="also write the rows as JSON here")
    p.add_argument("--small-epoch", action="store_true", help="measure an epoch smaller than the buffer instead")
    p.add_argument("--samples", type=int, default=36, help="--small-epoch: samples measured per run")
    a = p.parse_args(argv)
    if a.small_epoch:
        rows = small_epoch(a.rounds, a.samples)
        print_small_epoch(rows, a.samples)
        if a.out:
            Path(a.out).write_text(json.dumps(rows, indent=1) + "\n")
        return 0
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        corpus = make_corpus(Path(tmp) / "clips", a.clips)
        for r in range(a.rounds):
            for w in [int(x) for x in a.workers.split(",")]:
                for shuffle in ("none", "epoch"):
                    rows.append(run(corpus, w, shuffle, 3 + r))
                    print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    cost, sizes = copy_cost(), buffer_sizes()
    print(f"{a.clips} clips x 5 windows, L = 8, 64 px crops, batch 8, shuffle_buffer 64 (8 open batches), "
          f"{EPOCHS} epochs, one trainer reading voxels; distinct videos and tau: means of {a.rounds} runs "
          f"(seeds 3-{2 + a.rounds}); times: medians\n")
    print("| workers | shuffle | distinct videos / batch (epoch 0) | Kendall tau epoch 0 vs 1 | first batch (s) "
          "| samples/s, whole run | vs none | samples/s, epochs 1 on | vs none |")
    print("|---|---|---|---|---|---|---|---|---|")
    table = {}
    for r in rows:
        table.setdefault((r["workers"], r["shuffle"]), []).append(r)

    def med(key, rs):
        return statistics.median(x[key] for x in rs)

    for (w, shuffle), rs in table.items():
        base = table[(w, "none")]
        print(f"| {w} | {shuffle} | {statistics.mean(x['distinct_videos_per_batch'] for x in rs):.2f} | "
              f"{statistics.mean(x['kendall_tau_epoch0_vs_1'] for x in rs):+.3f} | {med('first_batch_s', rs):.2f} | "
              f"{med('samples_per_s', rs):.1f} | {med('samples_per_s', rs) / med('samples_per_s', base):.2f} | "
              f"{med('steady_samples_per_s', rs):.1f} | "
              f"{med('steady_samples_per_s', rs) / med('steady_samples_per_s', base):.2f} |")
    print(f"\nA shuffle buffer picking made samples at random would stack every batch: "
          f"{cost['stack_ms_per_sample']:.2f} ms per {cost['sample_mb']:.1f} MB sample of the default recipe "
          f"on the server's loop thread (one more copy of every byte).")
    print("\nOne worker, 200 videos of 10 windows, batches of 12 (the default recipe's shape; the pure Batcher, "
          "means of 5 seeds):\n")
    cols = list(sizes["counted"])
    print("| shuffle_buffer | " + " | ".join(str(k) for k in cols) + " |")
    print("|---|" + "---|" * len(cols))
    counted, unknown = sizes["counted"], sizes["unknown"]
    for label, table, i, fmt in (("distinct videos / batch", counted, 0, ".2f"),
                                 ("samples left for the epoch-end flush", counted, 1, ".1f"),
                                 ("the same, count unknown: distinct videos", unknown, 0, ".2f"),
                                 ("the same, count unknown: samples left", unknown, 1, ".1f")):
        print(f"| {label} | " + " | ".join(format(table[k][i], fmt) for k in cols) + " |")
    if a.out:
        Path(a.out).write_text(json.dumps({"runs": rows, "copy_cost": cost, "buffer_sizes": sizes}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

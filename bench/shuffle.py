"""How well a plan's batches mix videos, how much the epoch order changes, and what its shuffle
buffer costs.

Usage: ``python -m bench.shuffle [--clips 24] [--workers 1,4] [--rounds 3] [--out FILE.json]``,
or ``python -m bench.shuffle --small-epoch [--rounds 2] [--samples 36]`` for :func:`small_epoch`.

Makes a corpus of ``--clips`` small synthetic clips (``harness.corpus.write_video``; 5 windows
each at the small layout below), then for each worker count runs a real ``v2v-serve`` with
``--shuffle-buffer 1`` (the production order: each epoch's video order, windows in order) and
the default ``--shuffle-buffer`` (``BUFFERS``), one trainer (``V2VStreamDataset``) reading every
batch of epochs ``0 .. EPOCHS - 1``, ``--rounds`` times (seeds 3, 4, ...; the settings
interleaved). Prints, per setting:

* distinct videos per batch, mean over epoch 0's batches (and over the rounds);
* Kendall's tau between the epoch orders of epochs 0 and 1 (each sample's position in the
  order the trainer received them; 1 = the same order, 0 = unrelated), mean over the rounds;
* seconds to the first batch, samples/s over the whole run (start of the iteration to the last
  batch) and over epochs 1 on (epoch 1's first batch to the last: the buffer in its steady
  state), medians over the rounds, with their ratios to buffer 1 at the same worker count;

and distinct videos per batch against ``shuffle_buffer`` at the default recipe's shape, from the
pure plan (:func:`buffer_sizes`).

``--small-epoch`` measures instead what shuffling costs when an epoch is smaller than the shuffle
buffer (:func:`small_epoch`).

Nothing in docs/ quotes its output (docs/shuffle.md measures the mixing on the pure plan).
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
#: The shuffle buffers compared: the production order, and the default (``v2v_wire.plan.SHUFFLE_BUFFER``).
BUFFERS = (1, 64)


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


def _epochs(endpoint: str):
    """The batches of epochs ``0 .. EPOCHS - 1`` of the plan at ``endpoint``, in turn (4 fetches in flight)."""
    from v2v_client import V2VStreamDataset

    ds = V2VStreamDataset(endpoint, outputs=("voxels",), prefetch=4, timeout_s=120)
    for e in range(EPOCHS):
        ds.set_epoch(e)
        yield from ds


def read_epochs(endpoint: str) -> Tuple[Dict[int, List[List[str]]], dict]:
    """Every batch of epochs ``0 .. EPOCHS - 1`` by epoch (sample ids in batch order, padding
    rows left out), and its timing: seconds to the first batch, samples/s over the whole run
    (from the start of the iteration), and samples/s over epochs 1 on (from epoch 1's first
    batch to the last batch: the buffer is in its steady state)."""
    batches: Dict[int, List[List[str]]] = {}
    t0, first, first_e1, n_e1 = time.monotonic(), None, None, 0
    for b in _epochs(endpoint):
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


def run(corpus: Path, workers: int, buffer: int, seed: int) -> dict:
    """``EPOCHS`` epochs of a plan with ``--shuffle-buffer buffer``; the figures of the module docstring."""
    from harness.serve import ServeProcess

    with ServeProcess(["--videos", str(corpus), "--shot-cuts", "off", "--workers", str(workers),
                       "--shuffle-buffer", str(buffer), *LAYOUT, "--seed", str(seed)], ready_timeout_s=120) as srv:
        batches, timing = read_epochs(srv.endpoint)
    order = {e: [s for b in bs for s in b] for e, bs in batches.items()}
    distinct = statistics.mean(len({s.rsplit("#", 1)[0] for s in b}) for b in batches[0])
    return {"workers": workers, "shuffle_buffer": buffer, "seed": seed, "batches_epoch0": len(batches[0]),
            "samples_epoch0": len(order[0]), "distinct_videos_per_batch": distinct,
            "kendall_tau_epoch0_vs_1": kendall_tau(order[0], order[1]), **timing}


def buffer_sizes(sizes=(1, 12, 32, 64, 128, 256), videos: int = 200, windows: int = 10, batch: int = 12,
                 seeds: int = 5) -> Dict[int, float]:
    """Distinct videos per batch of epoch 0 against ``shuffle_buffer`` at the default recipe's shape
    (``videos`` videos of ``windows`` windows, batches of ``batch``), from the pure plan
    (``v2v_wire.plan.distinct_videos``, no server): ``{size: mean over seeds 0 .. seeds - 1}``."""
    from v2v_wire.plan import EpochPlan, Manifest, distinct_videos

    manifest = Manifest.of({f"v{i:03d}.mp4": windows for i in range(videos)})
    return {size: statistics.mean(distinct_videos(EpochPlan(manifest, seed, 0, size), batch) for seed in range(seeds))
            for size in sizes}


def small_epoch(rounds: int = 2, samples: int = 36, copies: int = 6) -> List[dict]:
    """An epoch smaller than the shuffle buffer: ``copies`` copies of the WebVid-like clip
    (``bench.speed``: 2 windows each, so 12 samples per epoch at 6 copies), one worker, batches
    of 4, every output, read raw as fast as a client takes it (``bench.speed.producer``,
    ``samples`` measured after two batches). Each of ``BUFFERS`` as ``--shuffle-buffer``,
    interleaved for ``rounds`` rounds, each round also measuring the decode bound
    (``bench.speed.bare_decode``). One row per run: ``decode_share`` (samples per worker
    CPU-second / the round's decode bound) and ``server_cpu_s_per_gb`` (the server main process)."""
    from bench.speed import SPAN, bare_decode, clip_path, make_corpus as copies_of, producer, worker_core

    rows = []
    with tempfile.TemporaryDirectory(prefix="v2v-shuffle-") as d:
        corpus = copies_of(Path(d) / "webvid", copies)
        worker_core(corpus, ("voxels", "frames", "flow"), videos=1)  # load the compiled kernels once, unmeasured
        for r in range(rounds):
            bound = bare_decode(clip_path(), 2) / SPAN
            for buffer in (BUFFERS if r % 2 == 0 else BUFFERS[::-1]):
                p = producer(corpus, 1, samples, ["--shuffle-buffer", str(buffer)])
                rows.append({"round": r, "shuffle_buffer": buffer, "decode_bound": bound,
                             "decode_share": p["per_worker_cpu_s"] / bound, **p})
                print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    return rows


def print_small_epoch(rows: List[dict], samples: int) -> None:
    """The table of :func:`small_epoch`: per shuffle buffer, the best round of each figure and its
    ratio to buffer 1's best."""
    best = {}
    for buffer in BUFFERS:
        rs = [r for r in rows if r["shuffle_buffer"] == buffer]
        best[buffer] = {"decode_share": max(r["decode_share"] for r in rs),
                        "server_cpu_s_per_gb": min(r["server_cpu_s_per_gb"] for r in rs),
                        "samples_per_s": max(r["samples_per_s"] for r in rs),
                        "core_share": max(r["core_share"] for r in rs)}
    print(f"6 copies of the WebVid-like clip (12 samples per epoch), 1 worker, batches of 4, every output, "
          f"{samples} samples measured; best of {len({r['round'] for r in rows})} interleaved rounds\n")
    print("| shuffle_buffer | samples / worker CPU-s, share of the decode bound | vs 1 | server main CPU-s / GB "
          "| vs 1 | samples/s | worker core share |")
    print("|---|---|---|---|---|---|---|")
    base = best[BUFFERS[0]]
    for buffer, b in best.items():
        print(f"| {buffer} | {b['decode_share']:.2f} | {b['decode_share'] / base['decode_share']:.2f} | "
              f"{b['server_cpu_s_per_gb']:.2f} | {b['server_cpu_s_per_gb'] / base['server_cpu_s_per_gb']:.2f} | "
              f"{b['samples_per_s']:.2f} | {b['core_share']:.2f} |")


def print_runs(rows: List[dict], rounds: int, clips: int) -> None:
    """The table of the served runs (module docstring): per worker count and shuffle buffer,
    means of the mixing figures and medians of the times, with ratios to buffer 1."""
    print(f"{clips} clips x 5 windows, L = 8, 64 px crops, batch 8, {EPOCHS} epochs, one trainer reading voxels; "
          f"distinct videos and tau: means of {rounds} runs (seeds 3-{2 + rounds}); times: medians\n")
    print("| workers | shuffle_buffer | distinct videos / batch (epoch 0) | Kendall tau epoch 0 vs 1 | first batch (s) "
          "| samples/s, whole run | vs 1 | samples/s, epochs 1 on | vs 1 |")
    print("|---|---|---|---|---|---|---|---|---|")
    table: Dict[tuple, List[dict]] = {}
    for r in rows:
        table.setdefault((r["workers"], r["shuffle_buffer"]), []).append(r)

    def med(key, rs):
        return statistics.median(x[key] for x in rs)

    for (w, buffer), rs in table.items():
        base = table[(w, BUFFERS[0])]
        print(f"| {w} | {buffer} | {statistics.mean(x['distinct_videos_per_batch'] for x in rs):.2f} | "
              f"{statistics.mean(x['kendall_tau_epoch0_vs_1'] for x in rs):+.3f} | {med('first_batch_s', rs):.2f} | "
              f"{med('samples_per_s', rs):.1f} | {med('samples_per_s', rs) / med('samples_per_s', base):.2f} | "
              f"{med('steady_samples_per_s', rs):.1f} | "
              f"{med('steady_samples_per_s', rs) / med('steady_samples_per_s', base):.2f} |")


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
                for buffer in BUFFERS:
                    rows.append(run(corpus, w, buffer, 3 + r))
                    print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    print_runs(rows, a.rounds, a.clips)
    sizes = buffer_sizes()
    print("\n200 videos of 10 windows, batches of 12 (the default recipe's shape; the pure plan, means of 5 seeds):\n")
    print("| shuffle_buffer | " + " | ".join(str(k) for k in sizes) + " |")
    print("|---|" + "---|" * len(sizes))
    print("| distinct videos / batch | " + " | ".join(f"{v:.2f}" for v in sizes.values()) + " |")
    if a.out:
        Path(a.out).write_text(json.dumps({"runs": rows, "buffer_sizes": sizes}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Whether the trainer's read path keeps up with its server, without a GPU (docs/trainer_feed.md).

Run: ``python -m bench.trainer_feed [--workers 1] [--batch 12] [--batches 16] [--out docs]``.

A real ``v2v-serve`` (serving by plan, the paper's sample: 40 voxel grids of 5 bins, 128 x 128,
shot cuts off; ``--workers`` workers) over ``--copies`` copies of the WebVid-like clip, once with
its frame cache warm (``--warm-cache`` filled it first) and once cold (no frame cache). On each:

* **server alone**: ``v2v-loadtest`` on that server before and after the trainer rows
  (``--batches`` measured after reading past the server's made-ahead stock: ``--warmup`` and the
  shuffle buffer's batches), the rate it makes samples with nothing else reading; the ratios
  divide by the faster of the two;
* **trainer**: the real ``v2v-train`` loop (``trainer.loop.train_loop``) on the real read path
  (``trainer.data.make_stream`` and ``read_path``: ``ReadAhead`` over the plan's epochs) with the
  model's step replaced by a stand-in of fixed duration (``StandIn``: the host's part of a step,
  then a sleep, as a host waits on its GPU, using no CPU), at stand-in rates of ``RATES`` times
  the server's; each run starts at an epoch of its own, so no run reads what another made;
* **before**: the same loop on the read path without reading ahead (``trainer.data.make_loader``:
  a DataLoader without workers over the plan's epochs, what ``v2v-train`` read through before),
  at half the server's rate, where every batch is made before the loop asks.

Each row reports the trainer's samples/s, its data-wait fraction, the wait per step (median,
90th percentile: the fixed per-step read cost when the server keeps ahead) and the ratio of
samples/s to min(server alone, stand-in alone) (the stand-in alone: the samples over the steps'
stand-in time). Figures over the steps after ``--warmup``. Gates: that ratio >= 0.9 at each rate
read ahead, and the median wait <= 30 ms a step at half the server's rate.
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import List, Optional

import torch

from bench.speed import make_corpus
from harness.serve import ServeProcess
from v2v_server.delivery.policy import DeliveryPolicy
from trainer.data import drop_padding, make_loader, make_stream, read_path
from trainer.loop import RunHooks, Schedule, train_loop
from trainer.tasks import get_task

#: Stand-in rates, as multiples of the server alone's samples/s.
RATES = (0.5, 1.0, 2.0)
#: Gates: trainer samples/s over min(server alone, stand-in alone), and the median wait a step
#: when every batch was made before the loop asks (seconds).
RATIO_GATE, WAIT_GATE_S = 0.9, 0.030
#: v2v-serve's default shuffle buffer (samples): what a server makes before its first fetch is answered.
SHUFFLE_BUFFER = DeliveryPolicy().shuffle_buffer


class StandIn:
    """``trainer.core.Trainer`` with its model's step replaced by ``step_s`` seconds of sleep:
    the host's part of a step on a CUDA host (padding dropped; the copies and the model's work
    are the device's, which the host waits on without using a core)."""

    def __init__(self, out: Path, step_s: float, task: str = "e2vid"):
        self.out, self.step_s, self.task, self.cfg, self.step = Path(out), step_s, task, {}, 0
        self.spec = get_task(task)

    def train_step(self, batch: dict, sync: bool = False) -> dict:
        batch, n = drop_padding(batch)
        time.sleep(self.step_s)
        self.step += 1
        return {"loss": torch.zeros(()), "samples": n, "lr": 0.0}


def server_alone(endpoint: str, batches: int, warmup: int) -> dict:
    """``v2v-loadtest --json`` on ``endpoint``: its last line, parsed."""
    out = subprocess.run(["v2v-loadtest", "--connect", endpoint, "--batches", str(batches), "--warmup", str(warmup),
                          "--json"], capture_output=True, text=True, timeout=600, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def trainer_row(endpoint: str, epoch: int, step_s: float, batches: int, warmup: int, ahead: bool, tmp: Path) -> dict:
    """The loop on the read path (``ahead``: ``read_path``; else ``make_loader``) from ``epoch``,
    a stand-in step of ``step_s``; figures over the steps after ``warmup``."""
    stream = make_stream(endpoint, "e2vid", raw=True, timeout_s=120.0)
    stream.dataset.set_epoch(epoch)
    feed = read_path(stream, torch.device("cpu")) if ahead else make_loader(stream, torch.device("cpu"))
    steps: List[dict] = []
    hooks = RunHooks(on_batch=lambda batch, stats: steps.append(stats) or stats.__setitem__("t", time.perf_counter()),
                     files=False)
    standin = StandIn(tmp, step_s)
    try:
        train_loop(standin, feed, warmup + batches, Schedule(0, 0, False, 10, False), lambda: None, hooks)
    finally:
        if hasattr(feed, "close"):
            feed.close()
    timed = steps[warmup:]
    span = timed[-1]["t"] - steps[warmup - 1]["t"]
    samples = sum(s["samples"] for s in timed)
    waits = sorted(s["data_wait_s"] for s in timed)
    return {"read_path": "ahead" if ahead else "before", "step_s": round(step_s, 4), "steps": len(timed),
            "samples": samples, "samples_per_s": samples / span, "data_wait_fraction": sum(waits) / span,
            "wait_median_ms": 1000 * statistics.median(waits), "wait_p90_ms": 1000 * waits[int(0.9 * (len(waits) - 1))],
            "standin_alone": samples / (len(timed) * step_s)}


def cache_rows(corpus: Path, cache: str, a, tmp: Path) -> dict:
    """Server alone, then the trainer rows, on one server (``cache``: "warm" or "cold")."""
    args = ["--workers", str(a.workers), "--videos", str(corpus), "--shot-cuts", "off", "--batch-size", str(a.batch)]
    if cache == "warm":
        args += ["--frame-cache-gb", "4", "--cache-dir", str(tmp / "cache")]
        subprocess.run(["v2v-serve", "--warm-cache", *args], check=True, capture_output=True, timeout=900)
    res: dict = {"cache": cache, "rows": []}
    with ServeProcess(args) as srv:
        warmup = a.warmup + -(-SHUFFLE_BUFFER // a.batch)  # past the samples made before the first fetch
        before = server_alone(srv.endpoint, a.batches, warmup)["samples_per_s"]
        print(json.dumps({"cache": cache, "server_alone_before": before}), flush=True)
        runs = [(f, True) for f in RATES] + [(0.5, False)]
        for i, (f, ahead) in enumerate(runs):
            row = trainer_row(srv.endpoint, 100 * (i + 1), a.batch / (f * before), a.batches, a.warmup, ahead, tmp)
            row["rate_x"] = f
            res["rows"].append(row)
            print(json.dumps({"cache": cache, **row}), flush=True)
        after = server_alone(srv.endpoint, a.batches, warmup)["samples_per_s"]
    res["server_alone"] = {"before": before, "after": after, "samples_per_s": max(before, after)}
    for row in res["rows"]:
        row["ratio"] = row["samples_per_s"] / min(res["server_alone"]["samples_per_s"], row["standin_alone"])
    print(json.dumps({"cache": cache, "server_alone": res["server_alone"]}), flush=True)
    return res


def gates(results: List[dict]) -> List[str]:
    """What missed a gate (empty when every gate held)."""
    missed = []
    for r in results:
        for row in r["rows"]:
            if row["read_path"] != "ahead":
                continue
            if row["ratio"] < RATIO_GATE:
                missed.append(f"{r['cache']} {row['rate_x']}x: ratio {row['ratio']:.2f} < {RATIO_GATE}")
            if row["rate_x"] == 0.5 and row["wait_median_ms"] > 1000 * WAIT_GATE_S:
                missed.append(f"{r['cache']} 0.5x: median wait {row['wait_median_ms']:.0f} ms > {1000 * WAIT_GATE_S:.0f}")
    return missed


def markdown(results: List[dict]) -> str:
    lines = ["| frame cache | server alone (samples/s) | read path | stand-in rate | stand-in alone (samples/s) | "
             "trainer samples/s | data-wait fraction | wait a step, median / p90 (ms) | ratio |",
             "|---|---:|---|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        for row in r["rows"]:
            lines.append(f"| {r['cache']} | {r['server_alone']['samples_per_s']:.1f} | {row['read_path']} | "
                         f"{row['rate_x']}x | {row['standin_alone']:.1f} | {row['samples_per_s']:.1f} | "
                         f"{row['data_wait_fraction']:.2f} | {row['wait_median_ms']:.0f} / {row['wait_p90_ms']:.0f} | "
                         f"{row['ratio']:.2f} |")
    return "\n".join(lines)


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--batch", type=int, default=12, help="rows per batch (the paper's: 12)")
    ap.add_argument("--copies", type=int, default=24, help="copies of the WebVid-like clip (2 samples each)")
    ap.add_argument("--batches", type=int, default=16, help="measured steps per row")
    ap.add_argument("--warmup", type=int, default=3, help="steps before measuring")
    ap.add_argument("--caches", default="warm,cold", help="which servers: warm, cold or both")
    ap.add_argument("--out", type=Path, default=None, help="folder for trainer_feed.json")
    a = ap.parse_args(argv)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        corpus = make_corpus(Path(tmp) / "corpus", a.copies)
        for cache in a.caches.split(","):
            results.append(cache_rows(corpus, cache, a, Path(tmp)))
    print(markdown(results))
    missed = gates(results)
    print("gates: " + ("met" if not missed else "missed: " + "; ".join(missed)))
    if a.out is not None:
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "trainer_feed.json").write_text(json.dumps({"args": vars(a) | {"out": str(a.out)}, "results": results,
                                                             "missed": missed}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

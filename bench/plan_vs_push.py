"""Serving by plan against push, in one run on one machine (docs/plan.md, "Measured").

Run: ``python -m bench.plan_vs_push [--rounds 2] [--batches 12] [--out docs]``.

Rows, each setting run ``rounds`` times, plan and push alternating:

* samples/s with 1 and 2 workers through ``v2v-serve`` (a ``V2VStreamDataset`` against
  ``v2v-loadtest``'s reader), and the server's peak memory (server and workers): resident (RSS)
  and proportional (PSS: the workers' shared-memory slot rings, which the server maps too,
  counted once);
* 4 crops per window against one, on one worker, both models;
* the trainer's longest wait between two batches while one of two workers is stopped
  (SIGSTOP) for ``--stall-s`` seconds, and with a slow 1920 x 1080 file in the corpus (the
  street clip's first ``SLOW_FRAMES`` frames upscaled, ``bench.frame_scale.make_source``) beside
  one window's make of that file in this process (its decode and simulation, ``video_samples``);
* distinct videos per batch of 12 at the push bench's shape (200 videos of 10 windows, a buffer
  of 64), from the pure parts (``EpochPlan`` against ``Batcher``, ``bench.shuffle.buffer_sizes``).

Corpus: the bundled clips, copied ``--copies`` times; the default recipe with shot cuts off.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import List, Optional

import torch

from bench.shuffle import buffer_sizes
from bench.throughput import tree_pss_mb, tree_rss_mb
from harness.faults import good_corpus
from harness.serve import ServeProcess
from v2v_client import V2VStreamDataset
from v2v_client.loadtest import run_loadtest
from v2v_wire.plan import EpochPlan, Manifest, distinct_videos

BATCH = 4


class PeakRss:
    """Samples a process tree's resident and proportional memory every 0.2 s in a thread;
    ``stop()`` gives both peaks, MB."""

    def __init__(self, pid: int):
        self.pid, self.peak, self.peak_pss, self._stop = pid, 0.0, 0.0, threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()

    def _run(self) -> None:
        while not self._stop.wait(0.2):
            self.peak = max(self.peak, tree_rss_mb(self.pid))
            self.peak_pss = max(self.peak_pss, tree_pss_mb(self.pid))

    def stop(self) -> dict:
        self._stop.set()
        self._t.join()
        return {"peak_rss_mb": self.peak, "peak_pss_mb": self.peak_pss}


def read_plan(endpoint: str, batches: int, warmup: int = 1, on_batch=None) -> dict:
    """``batches`` batches of a ``V2VStreamDataset`` over as many epochs as needed (after ``warmup``
    unmeasured ones): samples/s and the longest wait between two batches, s."""
    ds = V2VStreamDataset(endpoint, BATCH, timeout_s=300)
    n = samples = 0
    t0 = last = None
    longest = 0.0
    epoch = 0
    while n < warmup + batches:
        ds.set_epoch(epoch)
        for b in torch.utils.data.DataLoader(ds, batch_size=None):
            now = time.perf_counter()
            if n == warmup:
                t0 = now
            elif n > warmup:
                samples += int((~b["padding"]).sum())
                longest = max(longest, now - last)
            last = now
            n += 1
            if on_batch is not None:
                on_batch(n)
            if n >= warmup + batches:
                break
        epoch += 1
    seconds = last - t0
    return {"samples_per_s": samples / seconds if seconds > 0 else 0.0, "samples": samples, "seconds": seconds,
            "longest_wait_s": longest}


def read_push(endpoint: str, batches: int) -> dict:
    r = run_loadtest(endpoint, batches, timeout_s=300, warmup=1)
    return {"samples_per_s": r["samples_per_s"], "samples": r["samples"], "seconds": r["seconds"]}


def push_wait(endpoint: str, batches: int, on_batch=None) -> float:
    """The longest wait between two of ``batches`` batches of a ``V2VPushDataset`` after the
    first two, s; ``on_batch(n)`` after the n-th."""
    from v2v_client import V2VPushDataset

    longest, last = 0.0, None
    for n, _ in enumerate(V2VPushDataset(endpoint, timeout_s=300), 1):
        now = time.perf_counter()
        if last is not None and n > 2:
            longest = max(longest, now - last)
        last = now
        if on_batch is not None:
            on_batch(n)
        if n >= batches + 1:
            break
    return longest


def throughput(corpus: Path, mode: str, workers: int, batches: int, extra: List[str]) -> dict:
    args = ["--videos", str(corpus), "--shot-cuts", "off", "--workers", str(workers), "--batch-size", str(BATCH),
            "--delivery", mode, *extra]
    with ServeProcess(args, ready_timeout_s=600) as srv:
        rss = PeakRss(srv.proc.pid)
        r = read_plan(srv.endpoint, batches) if mode == "plan" else read_push(srv.endpoint, batches)
        r.update(rss.stop())
    return r


def stalled(corpus: Path, mode: str, batches: int, stall_s: float) -> dict:
    """The longest wait between batches while one of two workers is stopped ``stall_s`` s."""
    args = ["--videos", str(corpus), "--shot-cuts", "off", "--workers", "2", "--batch-size", str(BATCH),
            "--delivery", mode]
    with ServeProcess(args, ready_timeout_s=600) as srv:
        def stop_one(n: int) -> None:
            if n == 2:
                victim = busiest_worker(srv.proc.pid)
                stopped.append(victim)
                os.kill(victim, signal.SIGSTOP)
                threading.Timer(stall_s, os.kill, (victim, signal.SIGCONT)).start()

        stopped: List[int] = []

        if mode == "plan":
            return {**read_plan(srv.endpoint, batches, on_batch=stop_one), "stopped": stopped}
        return {"longest_wait_s": push_wait(srv.endpoint, batches, stop_one), "stopped": stopped}


#: Frames of the slow 1080p file: two windows of the default recipe.
SLOW_FRAMES = 402


def slow_file(corpus: Path) -> dict:
    """Add a 1920 x 1080 file to ``corpus``; the seconds one window of it takes to make here."""
    from bench.frame_scale import make_source
    from bench.speed import clip_path
    from v2v_server.flow.estimate import FlowEstimator
    from v2v_server.ops.config import ServeConfig
    from v2v_server.samples.make import video_samples
    from v2v_server.sources.local import LocalSource

    make_source(clip_path(), corpus / "slow_1080p.mp4", (1920, 1080), SLOW_FRAMES)
    recipe = ServeConfig.from_dict({"shot_cuts": "off"}).recipe
    flow = FlowEstimator(recipe.flow_preset)
    t = time.perf_counter()
    with video_samples(recipe, LocalSource(corpus), "slow_1080p.mp4", 0, ("voxels", "frames", "flow"), (), flow) as run:
        next(iter(run))
    return {"window_s": time.perf_counter() - t}


def slow_wait(corpus: Path, mode: str, batches: int) -> dict:
    """The longest wait between batches, 2 workers, with ``slow_file``'s file in ``corpus``."""
    args = ["--videos", str(corpus), "--shot-cuts", "off", "--workers", "2", "--batch-size", str(BATCH),
            "--delivery", mode]
    with ServeProcess(args, ready_timeout_s=600) as srv:
        if mode == "plan":
            return read_plan(srv.endpoint, batches)
        return {"longest_wait_s": push_wait(srv.endpoint, batches)}


def busiest_worker(server_pid: int) -> int:
    """The server's worker process (``v2v_server`` worker, not multiprocessing's resource
    tracker) that used the most CPU over 0.3 s: one busy on a task."""
    def cpu(pid: int) -> int:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return int(fields[11]) + int(fields[12])

    kids = [int(p) for p in Path(f"/proc/{server_pid}/task/{server_pid}/children").read_text().split()]
    workers = [p for p in kids if b"resource_tracker" not in Path(f"/proc/{p}/cmdline").read_bytes()]
    before = {p: cpu(p) for p in workers}
    time.sleep(0.3)
    return max(workers, key=lambda p: cpu(p) - before[p])


def mixing() -> dict:
    m = Manifest.of({f"v/{i:03d}.mp4": 10 for i in range(200)})
    plan = statistics.mean(distinct_videos(EpochPlan(m, s, 0, 64), 12) for s in range(5))
    return {"plan": plan, "push": buffer_sizes(sizes=(64,))["counted"][64][0]}


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--batches", type=int, default=12)
    ap.add_argument("--copies", type=int, default=2)
    ap.add_argument("--stall-s", type=float, default=20.0)
    ap.add_argument("--parts", default="throughput,crops,stall,slow", help="which rows to run, comma-separated")
    ap.add_argument("--out", type=Path, default=None, help="folder for plan_vs_push.json")
    a = ap.parse_args(argv)
    out: dict = {"mixing": mixing(), "throughput": [], "crops": [], "stall": [], "slow": []}
    print(json.dumps(out["mixing"]), flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        corpus = good_corpus(Path(tmp), a.copies)
        parts = set(a.parts.split(","))
        for r in range(a.rounds):
            for workers in (1, 2) if "throughput" in parts else ():
                for mode in ("push", "plan") if r % 2 == 0 else ("plan", "push"):
                    row = {"round": r, "workers": workers, "mode": mode, **throughput(corpus, mode, workers, a.batches, [])}
                    out["throughput"].append(row)
                    print(json.dumps(row), flush=True)
            for crops in (1, 4) if "crops" in parts else ():
                for mode in ("push", "plan"):
                    row = {"round": r, "crops": crops, "mode": mode,
                           **throughput(corpus, mode, 1, a.batches, ["--crops-per-window", str(crops)])}
                    out["crops"].append(row)
                    print(json.dumps(row), flush=True)
        for mode in ("push", "plan") if "stall" in parts else ():
            row = {"mode": mode, "stall_s": a.stall_s, **stalled(corpus, mode, a.batches, a.stall_s)}
            out["stall"].append(row)
            print(json.dumps(row), flush=True)
        if "slow" in parts:
            made = slow_file(corpus)
            for mode in ("push", "plan"):
                row = {"mode": mode, **made, **slow_wait(corpus, mode, a.batches)}
                out["slow"].append(row)
                print(json.dumps(row), flush=True)
    if a.out is not None:
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "plan_vs_push.json").write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Throughput and memory of the stream, with ratios against a baseline run in the same run.

Run: ``python -m bench.throughput [--batches 6] [--out docs/throughput.md]``.

Rows: batches/s and samples/s read by plan (``v2v_client.loadtest.run_loadtest``: the plan's
epochs in turn through ``V2VStreamDataset``, as ``v2v-train`` reads them) for worker counts and
the outputs a trainer asks for (workers compute only those), each with its ratio to the
baseline (1 worker, all outputs); then the server's resident memory (server + workers)
under a stalled and under a fast trainer (one fetch in flight).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import List, Optional

from v2v_client import PlanEpochs, V2VStreamDataset
from v2v_client.loadtest import run_loadtest
from v2v_wire.plan import SHUFFLE_BUFFER
from harness.serve import ServeProcess


def tree_memory_mb(pid: int, file: str = "status", field: str = "VmRSS:") -> float:
    """A figure of a process and all its descendants summed, MB (1e6 bytes): ``field`` (in kB)
    of ``/proc/PID/file``."""
    total, stack = 0, [pid]
    while stack:
        p = stack.pop()
        try:
            for line in Path(f"/proc/{p}/{file}").read_text().splitlines():
                if line.startswith(field):
                    total += int(line.split()[1]) * 1024
            stack += [int(k) for k in Path(f"/proc/{p}/task/{p}/children").read_text().split()]
        except OSError:
            continue
    return total / 1e6


def tree_rss_mb(pid: int) -> float:
    """Resident memory of a process and all its descendants, MB (1e6 bytes)."""
    return tree_memory_mb(pid)


def tree_pss_mb(pid: int) -> float:
    """Proportional set size of a process and all its descendants, MB (1e6 bytes): pages shared
    between them (the slot rings) counted once."""
    return tree_memory_mb(pid, "smaps_rollup", "Pss:")


def measure(corpus: Path, workers: int, outputs, batches: int, extra: List[str]) -> dict:
    """``batches`` batches of 4 read by ``run_loadtest`` after one batch and the server's made-ahead
    stock (its shuffle buffer), read unmeasured: the rate the workers make samples at."""
    args = ["--videos", str(corpus), "--shot-cuts", "off", "--workers", str(workers), "--batch-size", "4", "--seed", "1", *extra]
    with ServeProcess(args) as srv:
        r = run_loadtest(srv.endpoint, batches, outputs=outputs, timeout_s=120, warmup=1 + -(-SHUFFLE_BUFFER // 4))
    return r


def memory(corpus: Path, stall_s: float, fast_batches: int) -> dict:
    args = ["--videos", str(corpus), "--shot-cuts", "off", "--workers", "2", "--batch-size", "4"]
    out = {}
    with ServeProcess(args) as srv:
        it = iter(PlanEpochs(V2VStreamDataset(srv.endpoint, prefetch=1, timeout_s=120)))
        next(it)
        time.sleep(2.0)
        out["stalled_start_mb"] = tree_rss_mb(srv.proc.pid)
        time.sleep(stall_s)  # the trainer takes nothing more
        out["stalled_end_mb"] = tree_rss_mb(srv.proc.pid)
        for _ in range(fast_batches):
            next(it)
        out["fast_end_mb"] = tree_rss_mb(srv.proc.pid)
        it.close()
    return out


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batches", type=int, default=6, help="measured batches per row (batch size 4)")
    p.add_argument("--copies", type=int, default=2, help="copies of each bundled clip in the corpus")
    p.add_argument("--stall", type=float, default=15.0, help="seconds the stalled trainer takes nothing")
    p.add_argument("--out", help="also write the tables (markdown) here")
    a = p.parse_args(argv)
    from harness.faults import good_corpus  # here: bench.speed imports this module for tree_rss_mb alone

    all3 = ("voxels", "frames", "flow")
    rows = [
        ("1 worker, voxels+frames+flow (baseline)", 1, all3, []),
        ("2 workers, voxels+frames+flow", 2, all3, []),
        ("2 workers, voxels+flow (EvFlow)", 2, ("voxels", "flow"), []),
        ("2 workers, voxels only", 2, ("voxels",), []),
        ("2 workers, all, DIS ultrafast", 2, all3, ["--flow-preset", "ultrafast"]),
    ]
    with tempfile.TemporaryDirectory(prefix="v2v-tp-") as d:
        corpus = good_corpus(Path(d), a.copies)
        results = []
        for name, w, outs, extra in rows:
            r = measure(corpus, w, outs, a.batches, extra)
            results.append((name, r))
            print(f"{name}: {r['batches_per_s']:.2f} batches/s", file=sys.stderr)
        mem = memory(corpus, a.stall, 10)
    base = results[0][1]["samples_per_s"]
    lines = ["| setting | batches/s | samples/s | MB/s | wait fraction | samples/s vs baseline |",
             "|---|---:|---:|---:|---:|---:|"]
    for name, r in results:
        lines.append(f"| {name} | {r['batches_per_s']:.2f} | {r['samples_per_s']:.2f} | {r['mbytes_per_s']:.0f} | "
                     f"{r['wait_fraction']:.2f} | {r['samples_per_s'] / base:.2f}x |")
    lines += ["", "| server + workers resident memory | MB |", "|---|---:|",
              f"| stalled trainer, 2 s after its last batch | {mem['stalled_start_mb']:.0f} |",
              f"| same trainer after {a.stall:.0f} s more of taking nothing | {mem['stalled_end_mb']:.0f} |",
              f"| after it then reads 10 batches fast | {mem['fast_end_mb']:.0f} |"]
    table = "\n".join(lines)
    print(table)
    if a.out:
        Path(a.out).write_text(
            "# Stream throughput and memory\n\nCommand: `python -m bench.throughput --out docs/throughput.md` "
            f"(bundled clips x{a.copies}, L = 40 x 5 bins, 128 x 128 crops, batches of 4, {a.batches} batches a row, "
            "on this project's 2-core CPU machine; the wait fraction is the trainer's share of time waiting, with "
            "no training step, so it is 1 by construction here).\n\n" + table + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

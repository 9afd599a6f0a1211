"""The delivery simulator at volume: many seeds, the seeds per second, and every failure with the
command that replays it.

Run: ``python -m bench.delivery_sim --seeds 100000 [--scenario mixed/main] [--jobs N] [--out
docs/simulator.json]``. Splits the seeds over ``--jobs`` processes (default: the CPU count), each
running ``harness.delivery_sim`` seeds in order; prints one line per failure and a summary, and
writes the JSON summary to ``--out``. The seeds run under ``PYTHONHASHSEED=0`` (this command
re-executes itself so), as ``python -m harness.delivery_sim`` replays them.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import platform
import sys
import time
from pathlib import Path
from typing import List, Optional


def _chunk(args) -> dict:
    name, seeds = args
    from harness.delivery_sim.scenarios import run_seeds

    out = run_seeds(name, seeds)
    out.pop("results")
    return out


def run(name: str, seeds: int, jobs: int, start: int = 0) -> dict:
    """``seeds`` seeds of scenario ``name`` from ``start`` over ``jobs`` processes: the summary."""
    size = max(1, min(500, seeds // (jobs * 8) or 1))
    chunks = [(name, range(a, min(a + size, start + seeds))) for a in range(start, start + seeds, size)]
    t0 = time.perf_counter()
    failures: List[dict] = []
    done = 0
    with multiprocessing.get_context("fork").Pool(jobs) as pool:
        for out in pool.imap_unordered(_chunk, chunks):
            done += out["seeds"]
            for f in out["failures"]:
                failures.append(f)
                print(f"seed {f['seed']}: {f['what']}\n  replay: {f['replay']}", flush=True)
    dt = time.perf_counter() - t0
    return {"scenario": name, "seeds": done, "first_seed": start, "failed": len(failures),
            "failures": sorted(failures, key=lambda f: f["seed"])[:100], "seconds": round(dt, 1),
            "seeds_per_s": round(done / dt, 1), "jobs": jobs, "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "command": f"python -m bench.delivery_sim --seeds {seeds} --scenario {name} --jobs {jobs}"}


def main(argv: Optional[List[str]] = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if os.environ.get("PYTHONHASHSEED") != "0":
        os.execve(sys.executable, [sys.executable, "-m", "bench.delivery_sim", *argv],
                  dict(os.environ, PYTHONHASHSEED="0"))
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=100000, help="seeds to run (default 100000)")
    p.add_argument("--start", type=int, default=0, help="the first seed (default 0)")
    p.add_argument("--scenario", default="mixed/main", help="a simulator scenario (default mixed/main)")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="processes (default: the CPU count)")
    p.add_argument("--out", help="also write the JSON summary here (e.g. docs/simulator.json)")
    a = p.parse_args(argv)
    out = run(a.scenario, a.seeds, a.jobs, a.start)
    print(f"{out['scenario']}: {out['seeds']} seeds, {out['failed']} failed, {out['seconds']} s, "
          f"{out['seeds_per_s']} seeds/s on {a.jobs} process(es)")
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(out, indent=1) + "\n")
    return 1 if out["failed"] else 0


if __name__ == "__main__":
    sys.exit(main())

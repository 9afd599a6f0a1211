"""What Hugging Face Accelerate's dispatch mode costs against per-rank reading of a plan
(``v2v_client.prepare_loader``).

Run: ``python -m bench.launchers [--copies 4] [--windows 4] [--crop 128] [--length 8]``. For each mode
it starts a fresh ``v2v-serve`` (the bundled clips, ``--copies`` of each) and a 2-rank CPU job
(``torchrun --standalone --nproc_per_node 2 -m harness.accelerate_plan_job``, gloo,
``prepare_loader``) reading frames for one epoch of the plan, and prints per mode: steps per rank,
each rank's CPU seconds per step (every thread of the process: its fetches, the dispatcher's
concatenation and broadcast, the tiny model) and wall seconds per step, from each rank's first
batch to the end of its loop. Under dispatch rank 0 reads every rank's rows and sends the others'
over gloo; per rank each reads its own.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import List, Optional

from harness import faults
from harness.faults import Layout
from harness.serve import ServeProcess


def run_mode(corpus: Path, layout: Layout, mode: str, out: Path) -> List[dict]:
    """One 2-rank job in ``mode`` ("dispatch" or "per-rank") against a fresh server: the ranks' records."""
    out.mkdir()
    per_rank = ["--per-rank"] if mode == "per-rank" else []
    with ServeProcess(["--videos", str(corpus), "--workers", "2", *layout.args()]) as srv:
        r = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                            "-m", "harness.accelerate_plan_job", srv.endpoint, str(out), "--prepare", "loader",
                            "--batch-size", str(layout.batch), *per_rank], capture_output=True, text=True, timeout=1200)
        if r.returncode:
            raise RuntimeError(f"{mode} job failed:\n{r.stderr[-3000:]}")
    ranks = [json.loads(p.read_text()) for p in sorted(out.glob("rank*.json"))]
    errors = [r["error"] for r in ranks if r["error"]]
    if errors:
        raise RuntimeError(f"{mode} job failed: {errors[0]}")
    return ranks


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--copies", type=int, default=4)
    p.add_argument("--windows", type=int, default=4)
    p.add_argument("--crop", type=int, default=128)
    p.add_argument("--length", type=int, default=8)
    a = p.parse_args(argv)
    layout = Layout(L=a.length, crop=a.crop, windows=a.windows, batch=4)
    print("| mode | steps per rank | rank 0 CPU s/step | rank 1 CPU s/step | wall s/step |\n|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        corpus = faults.good_corpus(Path(tmp), a.copies)
        for mode in ("dispatch", "per-rank"):
            ranks = run_mode(corpus, layout, mode, Path(tmp) / mode)
            steps = sum(ranks[0]["steps"].values())
            cpu = [r["cpu_s"] / max(1, sum(r["steps"].values()) - 1) for r in ranks]
            wall = max(r["wall_s"] for r in ranks) / max(1, steps - 1)
            print(f"| {mode} | {steps} | {cpu[0]:.4f} | {cpu[1]:.4f} | {wall:.3f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

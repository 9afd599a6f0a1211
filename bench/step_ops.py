"""Aten ops dispatched per training step, ``speed: eager`` against ``speed: fast``, on the CPU:
``python -m bench.step_ops [--tasks e2vid,evflow,...] [--amp fp32,bf16] [--compile evflow]``.

Each of the five networks at toy sizes (``harness/toy_steps.py``: 3 bins, base 4 channels,
sequences of 3 grids, batch 2, 32-pixel crops, E-RAFT 64) takes one step, then a second step
is profiled (``torch.profiler`` on the CPU, ``harness.toy_steps.step_ops``: every ``aten::``
op, nested ones included). Per network and precision the table gives the ops of the eager step,
of the fast step and their ratio; ``fast+compile`` (networks named by ``--compile``) adds
``compile: true`` (inductor on the CPU: its kernels are C++ calls the profiler does not count
as aten ops, so the column shows what compilation removes from the dispatcher); "host reads"
counts ``.item()``-style reads in the fast step (the optimiser's host-side step counters with
the CPU's fused Adam; its forward and backward have none, tests/test_trainer_fast.py).

A second table counts one Adam step alone per implementation (per-parameter loop, foreach,
fused) over the toy E2VID's parameters.

A CPU op count is a proxy for the launches a CUDA step makes (each aten op on CUDA launches
one kernel or more); it says nothing of CUDA graphs, which replay a whole step in one launch.
"""
from __future__ import annotations

import argparse
import logging
import platform
import sys

import torch

from harness.toy_steps import HOST_READS, TASKS, step_ops, toy_batch, toy_trainer


def ops(task: str, speed: str, amp: str, **extra) -> dict:
    """``{"ops": aten ops of the second step, "host_reads": of them HOST_READS}``."""
    t, _ = toy_trainer(task, speed, amp, **extra)
    t.train_step(toy_batch(task, 0), sync=False)
    c = step_ops(t, toy_batch(task, 1))
    return {"ops": sum(c.values()), "host_reads": sum(c[h] for h in HOST_READS)}


def table(tasks, amps, compiled) -> list:
    """Markdown rows, one per network and precision."""
    rows = ["| network | precision | eager ops/step | fast ops/step | fast / eager | fast+compile ops/step "
            "| host reads (fast) |", "|---|---|---|---|---|---|---|"]
    for task in tasks:
        for amp in amps:
            e, f = ops(task, "eager", amp), ops(task, "fast", amp)
            c = ops(task, "fast", amp, compile=True)["ops"] if task in compiled else "-"
            rows.append(f"| {task} | {amp} | {e['ops']:,} | {f['ops']:,} | {f['ops'] / e['ops']:.2f} | "
                        f"{c if c == '-' else f'{c:,}'} | {f['host_reads']} |")
            print(rows[-1], file=sys.stderr, flush=True)
    return rows


def optimiser_table(task: str = "e2vid") -> list:
    """Markdown rows: aten ops of one Adam step alone (amsgrad, the toy ``task``'s parameters
    and gradients of one training step) per implementation: the per-parameter loop, foreach, fused."""
    rows = ["| Adam step over the toy " + task + "'s parameters | aten ops |", "|---|---|"]
    t, _ = toy_trainer(task, "eager")
    t.train_step(toy_batch(task, 0), sync=False)
    params = list(t.model.parameters())
    impls = (("per-parameter loop (eager)", {}), ("foreach", {"foreach": True}), ("fused (fast)", {"fused": True}))
    for name, kw in impls:
        opt = torch.optim.Adam(params, lr=1e-4, amsgrad=True, **kw)
        opt.step()  # the state exists before the profiled step
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
            opt.step()
        rows.append(f"| {name} | {sum(1 for e in prof.events() if e.name.startswith('aten::')):,} |")
    return rows


def main(argv=None) -> int:
    """Print the table (markdown) with the torch version, CPU and command."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", default=",".join(TASKS))
    ap.add_argument("--amp", default="fp32,bf16", help="precisions, comma-separated (fp32, bf16)")
    ap.add_argument("--compile", default="", help="networks also measured with compile: true (slow to compile)")
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    logging.disable(logging.WARNING)
    torch.set_num_threads(a.threads)
    rows = table(a.tasks.split(","), a.amp.split(","), set(filter(None, a.compile.split(","))))
    print(f"torch {torch.__version__}, {platform.processor() or platform.machine()}, {a.threads} thread(s); "
          f"`python -m bench.step_ops {' '.join(argv if argv is not None else sys.argv[1:])}`\n")
    print("\n".join(rows))
    print()
    print("\n".join(optimiser_table()))
    return 0


if __name__ == "__main__":
    sys.exit(main())

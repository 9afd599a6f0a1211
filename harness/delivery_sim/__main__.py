"""Run the delivery simulator from the command line.

Usage::

    python -m harness.delivery_sim --scenario trainers --seed 1234 --trace   # replay one seed
    python -m harness.delivery_sim --scenario trainers/main --seeds 0:1000   # a range of seeds
    python -m harness.delivery_sim --scenario a,b --seeds 20 --json          # several, as JSON lines
    python -m harness.delivery_sim --list                                     # the scenarios

Prints one line per failing seed (its violation and the command that replays it), with
``--trace`` every message and decision of the run up to the violation, and with ``--json`` one
JSON object per scenario (seeds run, failures with their seeds and replay commands, seeds per
second). Exits 1 when a seed failed. A run is deterministic under one ``PYTHONHASHSEED`` (the
core iterates sets of strings): this command fixes it to 0, re-executing itself when it is not.
"""
from __future__ import annotations

import argparse
import json
import os
import sys


def _fixed_hash_seed(argv) -> None:
    """Re-execute under ``PYTHONHASHSEED=0`` so a seed replays exactly."""
    if os.environ.get("PYTHONHASHSEED") != "0":
        env = dict(os.environ, PYTHONHASHSEED="0")
        os.execve(sys.executable, [sys.executable, "-m", "harness.delivery_sim", *argv], env)


def _seeds(text: str) -> range:
    a, _, b = text.partition(":")
    return range(int(a), int(b)) if b else range(int(a))


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    _fixed_hash_seed(argv)
    from harness.delivery_sim.scenarios import SCENARIOS, run_seeds

    ap = argparse.ArgumentParser(prog="python -m harness.delivery_sim", description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="mixed/main", help="a family or a named scenario, or several joined by "
                                                             "commas (--list)")
    ap.add_argument("--seed", type=int, help="run this one seed")
    ap.add_argument("--seeds", default="100", help="N (seeds 0..N-1) or A:B (default 100)")
    ap.add_argument("--trace", action="store_true", help="print the run's trace (with --seed)")
    ap.add_argument("--json", action="store_true", help="print each scenario's outcome as one JSON line")
    ap.add_argument("--list", action="store_true", help="list the scenarios")
    args = ap.parse_args(argv)
    if args.list:
        for name, sc in SCENARIOS.items():
            print(f"{name:<30} {sc.doc}" + (f"  [fails on main: {sc.xfail}]" if sc.xfail else ""))
        return 0
    names = args.scenario.split(",")
    unknown = [n for n in names if n not in SCENARIOS]
    if unknown:
        ap.error(f"unknown scenario(s) {unknown}; --list shows them")
    seeds = [args.seed] if args.seed is not None else _seeds(args.seeds)
    failed = 0
    for name in names:
        outcome = run_seeds(name, seeds, trace=args.trace)
        for r in outcome.pop("results"):
            if args.trace and r.trace is not None:
                print("\n".join(r.trace))
            if not r.ok and not args.json:
                print(f"seed {r.seed}: {r.violation}\n  replay: {r.replay()}")
        failed += outcome["failed"]
        print(json.dumps(outcome) if args.json else
              f"{name}: {outcome['seeds']} seed(s), {outcome['failed']} failed, {outcome['seeds_per_s']:.1f} seeds/s",
              flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

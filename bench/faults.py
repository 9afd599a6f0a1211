"""Fault scenarios (``harness/faults.py``, ``harness/faults_deploy.py``) against a real v2v-serve on 127.0.0.1: is any
sample lost or doubled?

Run: ``python -m bench.faults [--only NAME ...] [--out docs/faults.md]``. Prints a table:
scenario, samples expected, delivered, lost, duplicated, seconds to recover, notes.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import List, Optional

from harness import faults, faults_deploy
from harness.faults import Layout

SCENARIOS = {**faults.SCENARIOS, **faults_deploy.SCENARIOS}


def format_table(rows: List[dict]) -> str:
    head = "| scenario | expected | delivered | lost | duplicated | seconds to recover | notes |\n|---|---|---|---|---|---|---|"
    lines = [head]
    for r in rows:
        rec = "-" if r["recover_s"] is None else f"{r['recover_s']:.2f}"
        lines.append(f"| {r['scenario']} | {r['expected']} | {r['delivered']} | {r['lost']} | {r['duplicated']} | "
                     f"{rec} | {r['notes']} |")
    return "\n".join(lines)


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--only", nargs="*", choices=sorted(SCENARIOS), help="scenarios to run (default: all)")
    p.add_argument("--out", help="also write the table (markdown) here")
    p.add_argument("--kills", type=int, default=4, help="worker kills in the worker scenario")
    a = p.parse_args(argv)
    layout = Layout(L=8, crop=96, windows=3, batch=2)
    rows = []
    for name in a.only or list(SCENARIOS):
        with tempfile.TemporaryDirectory(prefix=f"v2v-{name}-") as d:
            kw = {"kills": a.kills, "copies": 6} if name == "worker_kill" else {}
            t = time.monotonic()
            r = SCENARIOS[name](Path(d), layout, **kw)
            if "skipped" in r:
                print(f"{name}: skipped ({r['skipped']})", file=sys.stderr)
                continue
            r["notes"] += f"; {time.monotonic() - t:.0f} s"
            rows.append(r)
            print(json.dumps(r), file=sys.stderr)
    table = format_table(rows)
    print(table)
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text("# Fault scenarios\n\nCommand: `python -m bench.faults --out docs/faults.md`\n\n"
                               + table + "\n")
    bad = [r for r in rows if r["lost"] or r["duplicated"] or r["unexpected"]]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())

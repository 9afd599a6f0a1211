"""Fault scenarios against real v2v-serve processes serving by plan: is any sample lost or doubled?

The scenarios (``harness/faults.py``, ``harness/faults_misuse.py``, ``harness/faults_deploy.py``,
``harness/faults_fs.py``, ``harness/faults_fleet.py``) run servers on 127.0.0.1 read by ``V2VStreamDataset``.
Run: ``python -m bench.faults [--only NAME ...] [--out docs/faults.md]``. Prints a table:
scenario, samples expected, delivered, lost, duplicated, seconds to recover, notes.
"""
from __future__ import annotations

if __name__ == "__main__":  # Ctrl-C or SIGTERM from the start, the imports below included: one line
    import sys

    from v2v_wire.commands import run_command

    sys.exit(run_command("bench.faults", "bench.faults:main"))

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import List, Optional

from harness import faults, faults_deploy, faults_fleet, faults_fs, faults_misuse
from harness.faults import Layout
from v2v_wire.commands import writable_problem, write_whole

SCENARIOS = {**faults.SCENARIOS, **faults_misuse.SCENARIOS, **faults_deploy.SCENARIOS, **faults_fs.SCENARIOS,
             **faults_fleet.SCENARIOS}


def format_table(rows: List[dict]) -> str:
    """The rows as a markdown table."""
    head = "| scenario | expected | delivered | lost | duplicated | seconds to recover | notes |\n|---|---|---|---|---|---|---|"
    lines = [head]
    for r in rows:
        rec = "-" if r["recover_s"] is None else f"{r['recover_s']:.2f}"
        lines.append(f"| {r['scenario']} | {r['expected']} | {r['delivered']} | {r['lost']} | {r['duplicated']} | "
                     f"{rec} | {r['notes']} |")
    return "\n".join(lines)


def main(argv: Optional[List[str]] = None) -> int:
    """Run the scenarios; exit 1 when one lost, doubled or invented a sample, or failed to run."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--only", nargs="*", choices=sorted(SCENARIOS), help="scenarios to run (default: all)")
    p.add_argument("--out", help="also write the table (markdown) here")
    p.add_argument("--kills", type=int, default=4, help="worker kills in the worker scenario")
    a = p.parse_args(argv)
    problem = writable_problem(Path(a.out)) if a.out else ""
    if problem:
        print(f"bench.faults: --out {a.out}: {problem}", file=sys.stderr)
        return 2
    layout = Layout(L=8, crop=96, windows=3, batch=2)
    rows, not_run = [], []
    for name in a.only or list(SCENARIOS):
        with tempfile.TemporaryDirectory(prefix=f"v2v-{name}-") as d:
            kw = {"kills": a.kills, "copies": 6} if name == "worker_kill" else {}
            t = time.monotonic()
            try:
                r = SCENARIOS[name](Path(d), layout, **kw)
            except Exception as e:  # noqa: BLE001 - the table lists it as not run, with why
                r = {"skipped": f"failed: {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"[:300]}
            if "skipped" in r:
                print(f"{name}: not run ({r['skipped']})", file=sys.stderr)
                not_run.append((name, r["skipped"]))
                continue
            r["notes"] += f"; {time.monotonic() - t:.0f} s"
            rows.append(r)
            print(json.dumps(r), file=sys.stderr)
    table = format_table(rows)
    print(table)
    if a.out:
        write_whole(a.out, "# Fault scenarios\n\nCommand: `python -m bench.faults --out docs/faults.md`\n\n"
                               + TABLE_NOTE + table + "\n\n" + not_run_note(not_run) + FS_FAULTS + NOT_CARRIED)
    bad = [r for r in rows if r["lost"] or r["duplicated"] or r["unexpected"]]
    for r in bad:
        print(f"FAILED: {r['scenario']}", file=sys.stderr)
    return 1 if bad or any(why.startswith("failed") for _, why in not_run) else 0


def not_run_note(not_run: List[tuple]) -> str:
    """The paragraph naming the scenarios this run left out of the table, and why ("" when none)."""
    if not not_run:
        return ""
    return ("Not run in this run (no row above): " + "; ".join(f"`{n}` ({why})" for n, why in not_run) + ".\n\n")


#: Read before the table: what its columns count under plan delivery.
TABLE_NOTE = """Every scenario runs real `v2v-serve` processes on
127.0.0.1 (one on `[::1]`), read by `V2VStreamDataset`. *expected* is the sample ids the epoch(s)
hold (`v2v-serve --check`'s verdicts; with several epochs or jobs an id counts once per epoch or
job); *delivered*, *lost* and *duplicated* count the ids the trainers trained on, padding rows left
out, across every rank, restart and resumed run. A server serving by plan never ends by itself:
each scenario stops it with SIGINT (exit 130, one line). *seconds to recover*: from the fault to
the next batch.

"""

#: What the server does when its own filesystem work fails (docs/faults.md, after the table).
FS_FAULTS = """## The server's own filesystem work

A filesystem operation the server process does on its own schedule turns an `OSError` of any
kind into `v2v_fs_errors_total{where}` (every time) and one log line per `where` and cause (the
errno's name) for the server's life; serving goes on:

| where | what fails | serving goes on |
|---|---|---|
| `frame_cache` | the scan of `cache_dir/frames` for the gauges (every 5 s) | by decoding (the workers meet the same folder, and decode); the gauges keep their last values |
| `progress` | the terminal's progress line (EIO after a hang-up) | without the progress line |

Row "frame cache's folder replaced by a file while serving" above: the workers decode instead,
every sample of both epochs is read once, and the scan counts the failure and logs it once.

The shared-memory sweep of dead servers' files (at start and when a worker is restarted) and the
removal of a dead worker's slot ring log a failure once per cause and leave the file; the store
manifest is written at start, and a failed write is a warning (the store is listed again at the
next start). Workers log a cache volume's fault once per cause and count it
(`v2v_frame_cache_misses_total{cause="corrupt"}`, `..._not_stored_total{cause="write_error"}`); the
object cache reads a video from the store when its folder fails.

The corpus index (`cache_dir/corpus_index.sqlite`) is a cache of what passes learned, never a
source of samples: a file that cannot be opened, has damaged pages, cannot be written (another
user's file, a read-only file system), whose lock another process holds for more than 5 s (once,
not per video), or holds an entry v2v never writes (a non-integer `windows`) is one warning
naming the file and the fault. The index is then off in that process and in the processes it
starts (`--check`'s pool, the server's workers), `--check` prints the verdicts of a run without
it, and a server serves every sample (the epoch's size is then unknown at start): row "corpus
index locked by another process" above; `tests/test_corpus_index.py`
(`test_a_damaged_index_is_one_warning_and_the_check_answers_as_without_it`,
`test_a_locked_index_is_one_warning_after_one_wait_not_one_per_video`,
`test_a_read_only_index_is_one_warning_and_the_check_goes_on`).

At start, a `--cache-dir` whose cache folder cannot be made or written, with a cache on, is a
one-line error naming it (exit 2): a cache asked for and unusable is a setting to fix, not a run
at a fifth of the speed (row "unusable --cache-dir at start" above).
"""

#: The rows of push delivery's table that have no counterpart under plan delivery, and why.
NOT_CARRIED = """
## Rows of push delivery not carried over

Push delivery (`--delivery push`, `V2VPushDataset`, `StreamLoader`) is gone; these of its rows
tested what only it had: leases, grants, revokes, consumer ids and groups, the `--state-dir`
journal, `--epochs`, resume states of delivered ids, and the client's shared-memory hand-off.

| push row | why it has no plan counterpart |
|---|---|
| client stalled 6 s > lease 2 s | a lease and re-sending held batches to another consumer are push's; a plan reader holds nothing another needs (the suspended and frozen trainer rows are the plan's stall) |
| peer ignores revoke (lease 1 s, revoke timeout 2 s) | a plan server grants and revokes nothing |
| trainer steps 0.7 s slower than lease 0.5 s | leases and credits; a plan reader's speed is its own (the loop-stops-reading row) |
| two independent trainers resume 3 s apart after a server restart, with --state-dir | the promise was the journal's; a plan's checkpoint is the trainer's position (the server-restart and DDP-resume-after-restart rows) |
| two trainers read one consumer id at once | consumer ids are push's: any number of plan readers read one server, each its own positions |
| a peer sits on 4 grants, never acknowledging | grants and acknowledgements are push's |
| first hello claims epoch 5 of an --epochs 2 server | `--epochs` is push's (refused with a plan); a plan trainer owns its epochs (`set_epoch`), and an epoch beyond any fetch's range is refused (the lying-positions row) |
| batch directory behind a symbolic link | the batch directory is push's hand-off to a client mapping batches (`shm=True`), which `V2VStreamDataset` refuses; rows come as socket frames |
| resume states of 700 k ids | a push resume state lists the ids delivered; a position is an epoch, an offset and the plan's identity, the same size at any corpus size |

Of the filesystem table, `journal` (the `--state-dir` journal) and `shm` (a batch file of the
batch directory push's server kept for that hand-off) were push's.
"""


"""Fault scenarios (``harness/faults.py``, ``harness/faults_misuse.py``, ``harness/faults_deploy.py``) against a real
v2v-serve on 127.0.0.1: is any sample lost or doubled?

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

from harness import faults, faults_deploy, faults_misuse
from harness.faults import Layout

SCENARIOS = {**faults.SCENARIOS, **faults_misuse.SCENARIOS, **faults_deploy.SCENARIOS}


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
                               + table + "\n\n" + FS_FAULTS)
    bad = [r for r in rows if r["lost"] or r["duplicated"] or r["unexpected"]]
    return 1 if bad else 0


#: What the server does when its own filesystem work fails (docs/faults.md, after the table).
FS_FAULTS = """## The server's own filesystem work

Every filesystem operation the server process does on its own schedule turns an `OSError` of
any kind into `v2v_fs_errors_total{where}` (every time) and one log line per `where` and cause
(the errno's name) for the server's life; serving goes on. What it serves meanwhile:

| where | what fails | serving goes on |
|---|---|---|
| `frame_cache` | the scan of `cache_dir/frames` for the gauges (every 5 s) | by decoding (the workers meet the same folder, and decode); the gauges keep their last values |
| `journal` | appends, fsync and the rewrite at an epoch's end of `--state-dir` | without the journal: records stay current in memory and the file is written again whole every 5 s once it can be; a restart meanwhile reads the journal as it was, so samples acknowledged since are sent again, none lost |
| `shm` | making or removing a batch file in the server's `/dev/shm` directory | batches go as socket frames |
| `progress` | the terminal's progress line (EIO after a hang-up) | without the progress line |

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
it, and a server serves every sample (the epoch's size is then unknown at start). Tests:
`tests/test_corpus_index.py` (`test_a_damaged_index_is_one_warning_and_the_check_answers_as_without_it`,
`test_a_locked_index_is_one_warning_after_one_wait_not_one_per_video`,
`test_a_read_only_index_is_one_warning_and_the_check_goes_on`,
`test_a_server_starting_on_a_faulty_index_serves_the_whole_epoch`).

At start the choice differs per setting: a `--cache-dir` whose cache folder cannot be made or
written, with a cache on, is a one-line error naming it (exit 2): a cache asked for and unusable
is a setting to fix, not a run at a fifth of the speed. A `--state-dir` that cannot hold the
journal is the same (exit 2): the journal is the promise that a restart repeats nothing, which
serving without it would break silently. Tests: `tests/test_frame_cache.py`
(`test_cache_folder_replaced_by_a_file_while_serving`,
`test_unusable_cache_dir_at_start_is_one_clear_line`), `tests/test_journal.py`
(`test_a_folder_that_fails_while_serving_is_counted_and_written_again_whole`,
`test_unusable_state_dir_at_start_is_one_clear_line`).
"""


if __name__ == "__main__":
    sys.exit(main())

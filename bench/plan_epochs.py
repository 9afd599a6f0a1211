"""A plan server's decisions per fetch with many epochs read at once (issue 86, item 5): the pure
``PlanScheduler`` a server's loop runs each turn (``answer``, and ``task_for``'s ``needed``), with one
pending fetch of ``--batch`` rows in each of 1, 4 and ``--epochs`` epochs at once, over a manifest
of ``--videos`` videos whose slots are all known (the plans complete). Prints each case's seconds
per loop turn (CPU, the median of ``--turns``) and per pending fetch, the plans built in the
turns, and the per-fetch ratio to 1 epoch (the gate: a fetch's cost does not grow with the epochs
read at once).

``python -m bench.plan_epochs --videos 1000000 --epochs 16`` (about a minute here: the plans are
built once each, 2-3 s apiece at a million videos)."""
from __future__ import annotations

import argparse
import gc
import json
import statistics
import time
from typing import List, Optional

from v2v_server.delivery import plan_schedule
from v2v_server.delivery.plan_schedule import PlanScheduler, needed
from v2v_wire.plan import EpochPlan, Manifest


class _Counted(EpochPlan):
    built = 0

    def __init__(self, *a, **k):
        type(self).built += 1
        super().__init__(*a, **k)


def measure(videos: int, epochs: int, batch: int, turns: int) -> dict:
    """Seconds per loop turn and per pending fetch at 1, 4 and ``epochs`` epochs read at once."""
    plan_schedule.EpochPlan = _Counted  # count the builds the scheduler makes
    try:
        manifest = Manifest.of({f"d{i % 1000}/{i:07d}.mp4": 2 for i in range(videos)})
        scheduler = PlanScheduler(manifest, 0, 64, ("voxels",), lookahead=64, keep_samples=batch)
        out, request = {}, 0
        for at_once in sorted({1, min(4, epochs), epochs}):
            for e in range(len({f.epoch for f in scheduler.pending}), at_once):  # one reader more per epoch
                request += 1
                scheduler.fetch(("job", e), request, e, 0, batch, 0.0)
            scheduler.answer(0.0)  # a first turn, and the collector's pass over the plans just built, untimed
            needed(scheduler, 0.0)  # what task_for decides from, with no task started
            gc.collect()
            built, times = _Counted.built, []
            for _ in range(turns):  # a loop turn: what the server asks of the scheduler (no sample made yet)
                t0 = time.process_time()
                scheduler.answer(0.0)
                needed(scheduler, 0.0)
                times.append(time.process_time() - t0)
            s = statistics.median(times)
            out[at_once] = {"s_per_turn": round(s, 6), "s_per_fetch": round(s / at_once, 6),
                            "plans_built_in_turns": _Counted.built - built}
        base = out[1]["s_per_fetch"]
        for row in out.values():
            row["per_fetch_vs_1_epoch"] = round(row["s_per_fetch"] / base, 2)
        return {"videos": videos, "batch": batch, "turns": turns, "plans_built": _Counted.built, "cases": out}
    finally:
        plan_schedule.EpochPlan = EpochPlan


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--videos", type=int, default=1_000_000)
    p.add_argument("--epochs", type=int, default=16)
    p.add_argument("--batch", type=int, default=12)
    p.add_argument("--turns", type=int, default=20)
    a = p.parse_args(argv)
    print(json.dumps(measure(a.videos, a.epochs, a.batch, a.turns), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""A seeded world driving serving by plan's decisions (``delivery.plan_feed.PlanFeed``), as
``harness.delivery_sim`` drives push's: time is ticks, every choice comes from ``random.Random(seed)``,
so a seed replays exactly.

What the world does to the feed:

* workers decode at one sample a tick, stall (3-60 ticks), die (the pool replaces them), and hang
  until the task timeout; files give fewer windows than their slots, or break;
* the server is killed and started again (a fresh ``PlanFeed`` and a fresh pool of workers: made
  samples, pending fetches and running tasks gone);
* jobs of 1-3 ranks ask up to two steps ahead, ask again a fetch unanswered for ``RETRY`` ticks
  (a lost reply, a restarted server), checkpoint and resume at another world size and batch size,
  and roll back to an older checkpoint of the epoch (the rows read since count again);
* readers ask for a subset of the outputs, and a new output widens what workers make mid-run.

:func:`check` runs one seed and returns what went wrong (empty: each job read each epoch's plan
exactly: every position once, at its place, a sample wherever its window was given, padding only
for windows a file did not give, and a bounded store). ``python -m harness.plan_world --seeds
0:100000`` runs a range (``tests/test_plan_feed.py`` runs 1,000 seeds); ``--seeds 35:36`` replays one.
"""
from __future__ import annotations

import argparse
import json
import random
import sys
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

from v2v_server.delivery.plan_feed import PlanFeed
from v2v_wire.ids import SampleKey
from v2v_wire.plan import EpochPlan, Manifest

#: Ticks a fetch may go unanswered before its reader asks again (``V2VPlanDataset.retry_s``).
RETRY = 30

#: The outputs a worker may make; readers ask for a non-empty prefix of them.
OUTPUTS = ("voxels", "frames", "flow")


@dataclass
class Worker:
    ident: str
    task: Optional[object] = None
    todo: List[SampleKey] = field(default_factory=list)
    stalled_until: float = 0.0


@dataclass
class Job:
    name: str
    world: int
    batch: int
    outputs: Tuple[str, ...]
    epoch: int = 0
    start: int = 0  # the position this layout started at
    step: int = 0  # next step to ask for, per rank alike
    asked: Dict[Tuple[int, int], Tuple[int, int]] = field(default_factory=dict)  # (step, rank) -> (request, tick)
    rows: Dict[int, Dict[int, object]] = field(default_factory=dict)  # epoch -> position -> row read
    taken: int = 0  # steps whose every rank's rows arrived
    checkpoints: List[int] = field(default_factory=lambda: [0])  # positions of this epoch saved (its start)


@dataclass
class Outcome:
    """One seed's run: its problems (empty when the feed kept the contract) and what it did."""

    seed: int
    problems: List[str]
    restarts: int = 0
    resumes: int = 0
    rollbacks: int = 0
    widened: int = 0
    biggest_store: int = 0


def check(seed: int, ticks: int = 30000) -> Outcome:
    """Run the world of ``seed`` (module docstring) for at most ``ticks`` ticks."""
    rng = random.Random(seed)
    kpw = rng.choice([1, 1, 2])
    slots = {f"v{i:02d}.mp4": rng.randint(0, 6) for i in range(rng.randint(1, 14))}
    given = {v: (n if rng.random() < 0.8 else rng.randint(0, n)) for v, n in slots.items()}  # short decodes
    broken = {v for v in slots if rng.random() < 0.1}  # the pass breaks after its windows
    m = Manifest.of(slots, kpw)
    settings = dict(lookahead=rng.choice([0, 8]), keep_samples=rng.choice([0, 4, 32]), hedge_s=5.0, task_timeout_s=40.0)
    buffer = rng.choice([1, 4, 16])

    def new_feed() -> PlanFeed:
        return PlanFeed(m, seed, buffer, OUTPUTS, **settings)

    feed = new_feed()
    workers = [Worker(f"w{i}") for i in range(rng.randint(1, 3))]
    next_worker = len(workers)
    jobs = [Job(f"j{i}", rng.randint(1, 3), rng.randint(1, 5), OUTPUTS[:rng.randint(1, 3)])
            for i in range(rng.randint(1, 2))]
    restart_p = rng.choice([0.0, 0.001, 0.003])
    out = Outcome(seed, [])
    epochs, request = 2, 0
    for now in range(ticks):
        if rng.random() < restart_p:  # the server killed and started again, with its workers
            feed = new_feed()
            workers = [Worker(f"w{next_worker + i}") for i in range(len(workers))]
            next_worker += len(workers)
            out.restarts += 1
        for job in jobs:
            if job.epoch >= epochs:
                continue
            plan = feed.plan(job.epoch)
            steps = plan.steps(job.world, job.batch, job.start)
            if rng.random() < 0.002 and job.outputs != OUTPUTS:  # a reader asks for one more output
                job.outputs = OUTPUTS[:len(job.outputs) + 1]
                out.widened += 1
            while job.step < min(steps, job.taken + 2):
                for r in range(job.world):
                    request += 1
                    job.asked[(job.step, r)] = (request, now)
                    pos = plan.batch_positions(job.step, r, job.world, job.batch, job.start)
                    feed.fetch((job.name, r, job.outputs), request, job.epoch, pos.start, pos.stop, now, job.outputs)
                job.step += 1
            for (s, r), (q, at) in list(job.asked.items()):  # unanswered: asked again
                if q > 0 and now - at >= RETRY:
                    request += 1
                    job.asked[(s, r)] = (request, now)
                    pos = plan.batch_positions(s, r, job.world, job.batch, job.start)
                    feed.fetch((job.name, r, job.outputs), request, job.epoch, pos.start, pos.stop, now, job.outputs)
            if job.taken >= steps:
                job.epoch, job.start, job.step, job.taken, job.asked, job.checkpoints = job.epoch + 1, 0, 0, 0, {}, [0]
            elif job.taken and rng.random() < 0.01:  # checkpoint, stop, resume at another layout
                job.start += job.taken * job.world * job.batch
                job.checkpoints.append(job.start)
                if rng.random() < 0.3:  # ... or roll back to an older checkpoint (those after it are gone)
                    back = rng.randrange(len(job.checkpoints) - 1)
                    job.start, job.checkpoints = job.checkpoints[back], job.checkpoints[:back + 1]
                    out.rollbacks += 1
                out.resumes += 1
                # rows fetched ahead of the steps the loop took, or read since the checkpoint, count again
                job.rows[job.epoch] = {p: row for p, row in job.rows.get(job.epoch, {}).items() if p < job.start}
                job.world, job.batch = rng.randint(1, 3), rng.randint(1, 5)
                job.step = job.taken = 0
                job.asked = {}
        for f, rows in feed.answer(now):
            job = next(j for j in jobs if j.name == f.client[0])
            hit = [(s, r) for (s, r), (q, _) in job.asked.items() if q == f.request and r == f.client[1]]
            if f.epoch != job.epoch or not hit:
                continue  # an answer to a fetch no longer waited for: dropped, as the reader drops it
            plan = feed.plan(f.epoch)
            for row in rows:
                if row.key != plan.key(row.position):
                    out.problems.append(f"epoch {f.epoch} position {row.position}: {row.key}, the plan says "
                                        f"{plan.key(row.position)}")
                if row.sample is not None and row.sample[:2] != (f.epoch, row.key):
                    out.problems.append(f"epoch {f.epoch} position {row.position}: the sample of {row.sample[:2]}")
                if row.sample is not None and not set(f.client[2]) <= set(row.sample[2]):
                    out.problems.append(f"epoch {f.epoch} position {row.position}: made with {row.sample[2]}, "
                                        f"asked {f.client[2]}")
                if row.key is not None:
                    seen = job.rows.setdefault(f.epoch, {})
                    if row.position in seen:
                        out.problems.append(f"{job.name} epoch {f.epoch}: position {row.position} read twice")
                    seen[row.position] = row
            job.asked[hit[0]] = (-1, now)
            while all(job.asked.get((job.taken, r), (0,))[0] == -1 for r in range(job.world)) and job.taken < job.step:
                job.taken += 1
        for w in list(workers):
            if rng.random() < 0.002:  # killed: the pool replaces it
                feed.worker_lost(w.ident)
                workers.remove(w)
                workers.append(Worker(f"w{next_worker}"))
                next_worker += 1
                continue
            if rng.random() < 0.004:
                w.stalled_until = now + rng.choice([3, 20, 60])
            if now < w.stalled_until:
                continue
            if w.task is None:
                w.task = feed.task_for(w.ident, now)
                if w.task is not None:
                    t = w.task
                    w.todo = [SampleKey.at(t.video, i, kpw) for i in range(given[t.video] * kpw)
                              if (i // kpw, i % kpw) not in set(t.skip)]
                continue
            t = w.task
            if w.todo:
                key = w.todo.pop(0)
                feed.sample(w.ident, t.task, key, now, lambda lane, e=t.epoch, k=key, o=t.outputs: (e, k, o))
            else:
                error = "decoder error: broken packet" if t.video in broken and given[t.video] < slots[t.video] else None
                feed.done(w.ident, t.task, given[t.video], {}, error)
                w.task = None
        for ident, _ in feed.timed_out(now):
            for w in workers:
                if w.ident == ident:
                    w.task, w.todo, w.stalled_until = None, [], 0.0
        out.biggest_store = max(out.biggest_store, len(feed.store))
        if all(j.epoch >= epochs for j in jobs):
            break
    for job in jobs:
        if job.epoch < epochs:
            out.problems.append(f"{job.name} stuck in epoch {job.epoch} at step {job.taken}")
            continue
        for e in range(epochs):
            plan = EpochPlan(m, seed, e, buffer)
            rows = job.rows.get(e, {})
            if sorted(rows) != list(range(len(plan))):
                out.problems.append(f"{job.name} epoch {e}: read {len(rows)} of {len(plan)} positions")
            for p, r in rows.items():
                if r.sample is None and r.key.window < given[r.key.video]:
                    out.problems.append(f"{job.name} epoch {e} position {p}: padding for {r.key}, a window the file gives")
                if r.sample is not None and r.key.window >= given[r.key.video]:
                    out.problems.append(f"{job.name} epoch {e} position {p}: a sample of {r.key}, not given")
    # memory: what pending fetches name, plus the kept ones, plus the samples decoded ahead
    bound = settings["keep_samples"] + 2 * (5 * 3 * 5 + settings["lookahead"]) + max(slots.values(), default=0) * kpw * 3
    if out.biggest_store > bound:
        out.problems.append(f"the store held {out.biggest_store} samples, over {bound}")
    return out


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="0:1000", help="a range a:b of seeds (b excluded)")
    ap.add_argument("--json", action="store_true", help="one JSON line of totals")
    a = ap.parse_args(argv)
    lo, hi = (int(x) for x in a.seeds.split(":"))
    t = time.perf_counter()
    failed, totals = [], {"restarts": 0, "resumes": 0, "rollbacks": 0, "widened": 0}
    for seed in range(lo, hi):
        o = check(seed)
        for k in totals:
            totals[k] += getattr(o, k)
        if o.problems:
            failed.append(seed)
            if not a.json:
                print(f"seed {seed}: {o.problems[0]} (+{len(o.problems) - 1} more)")
    summary = {"seeds": hi - lo, "failed": len(failed), "failed_seeds": failed[:20], **totals,
               "seconds": round(time.perf_counter() - t, 1)}
    print(json.dumps(summary) if a.json else f"{hi - lo} seeds, {len(failed)} failed; {totals}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

"""A seeded world driving serving by plan's decisions (``delivery.plan_feed.PlanFeed``): time is ticks, every choice comes from ``random.Random(seed)``,
so a seed replays exactly.

What the world does to the feed:

* workers decode at one sample a tick, stall (3-60 ticks), die (the pool replaces them), and hang
  until the task timeout; files give fewer windows than their slots, or break (at one place, each
  pass); a store that fails for a while cuts one or two passes of other files short;
* the corpus index knows some videos' slots at start, none or all; the others' the server learns
  from their first decode (the plan unfolds), and the index keeps a whole pass's count for a
  server started again;
* the server is killed and started again (a fresh ``PlanFeed`` and a fresh pool of workers: made
  samples, pending fetches and running tasks gone), and while it is down a file may be replaced
  under its name by another cut (another tag, other windows, its index entry gone): the plan's
  identity changes, a job's position of the plan before is refused and it reads that epoch
  again from its start under the new plan;
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

#: Ticks a fetch may go unanswered before its reader asks again (``V2VStreamDataset.retry_s``).
RETRY = 30

#: The outputs a worker may make; readers ask for a non-empty prefix of them.
OUTPUTS = ("voxels", "frames", "flow")


@dataclass
class Worker:
    ident: str
    task: Optional[object] = None
    todo: List[SampleKey] = field(default_factory=list)
    stalled_until: float = 0.0
    windows: int = 0  # what this pass gives
    error: Optional[str] = None  # why it stops early


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
    plan: Optional[str] = None  # the identity (manifest fingerprint) of the plan its position is of
    read_under: Dict[int, tuple] = field(default_factory=dict)  # epoch -> (manifest, windows given) it was read under


@dataclass
class Outcome:
    """One seed's run: its problems (empty when the feed kept the contract) and what it did."""

    seed: int
    problems: List[str]
    restarts: int = 0
    resumes: int = 0
    rollbacks: int = 0
    widened: int = 0
    replaced: int = 0
    refused: int = 0
    biggest_store: int = 0


def check(seed: int, ticks: int = 30000) -> Outcome:
    """Run the world of ``seed`` (module docstring) for at most ``ticks`` ticks."""
    return World(seed).run(ticks)


class World:
    """One seed's corpus, server, workers and jobs (module docstring); :meth:`run` plays it."""

    epochs = 2

    def __init__(self, seed: int):
        self.seed = seed
        self.rng = rng = random.Random(seed)
        self.kpw = rng.choice([1, 1, 2])
        self.slots = {f"v{i:02d}.mp4": rng.randint(0, 6) for i in range(rng.randint(1, 14))}
        self.tags = {v: 0 for v in self.slots}  # which cut of each file (another after a replacement)
        self.given = {v: (n if rng.random() < 0.8 else rng.randint(0, n)) for v, n in self.slots.items()}  # short
        self.broken = {v for v in self.slots if rng.random() < 0.1}  # the pass breaks after its windows
        known = rng.choice([0.0, 0.5, 1.0])
        self.index = {v: n for v, n in self.slots.items() if rng.random() < known}  # the corpus index
        # what each epoch lists: the index's slots, the decode's windows for the others
        self.truth = Manifest.of({v: self.index.get(v, self.given[v]) for v in self.slots}, self.kpw)
        self.settings = dict(lookahead=rng.choice([0, 8]), keep_samples=rng.choice([0, 4, 32]), hedge_s=5.0,
                             task_timeout_s=40.0)
        self.buffer = rng.choice([1, 4, 16])
        self.feed = self.new_feed()
        self.workers = [Worker(f"w{i}") for i in range(rng.randint(1, 3))]
        self.next_worker = len(self.workers)
        self.jobs = [Job(f"j{i}", rng.randint(1, 3), rng.randint(1, 5), OUTPUTS[:rng.randint(1, 3)])
                     for i in range(rng.randint(1, 2))]
        self.restart_p = rng.choice([0.0, 0.001, 0.003])
        self.out = Outcome(seed, [])
        self.request = 0
        # passes a store failing for a while cuts short, fewer than the feed's PASS_ATTEMPTS
        self.flaky = {v: rng.randint(1, 2) for v, n in self.given.items() if v not in self.broken and n and rng.random() < 0.2}
        # files replaced while the server is down: drawn apart, so the other draws stay each seed's
        self.cuts = random.Random(f"cuts/{seed}")
        self.replace_p = self.cuts.choice([0.0, 1.0])
        self.identity = self.feed.manifest.fingerprint()

    def new_feed(self) -> PlanFeed:
        tags = {v: f"cut {n}" for v, n in self.tags.items()}
        manifest = Manifest.of({v: self.index.get(v) for v in self.slots}, self.kpw, tags)
        return PlanFeed(manifest, self.seed, self.buffer, OUTPUTS, **self.settings)

    def replace_file(self) -> None:
        """While the server is down, a file is replaced under its name by another cut: another
        tag, its windows drawn again, what the corpus index knew of it gone (its identity changed)."""
        v = self.cuts.choice(sorted(self.slots))
        self.tags[v] += 1
        self.slots[v] = self.given[v] = self.cuts.randint(0, 6)
        self.index.pop(v, None)
        self.broken.discard(v)
        self.flaky.pop(v, None)
        self.truth = Manifest.of({u: self.index.get(u, self.given[u]) for u in self.slots}, self.kpw)
        self.out.replaced += 1

    def run(self, ticks: int) -> Outcome:
        for now in range(ticks):
            if self.rng.random() < self.restart_p:  # the server killed and started again, with its workers
                if self.cuts.random() < self.replace_p:
                    self.replace_file()
                self.feed = self.new_feed()
                self.identity = self.feed.manifest.fingerprint()
                self.workers = [Worker(f"w{self.next_worker + i}") for i in range(len(self.workers))]
                self.next_worker += len(self.workers)
                self.out.restarts += 1
            for job in self.jobs:
                if job.epoch < self.epochs:
                    self.ask(job, now)
            for f, rows in self.feed.answer(now):
                self.take(f, rows, now)
            self.decode(now)
            self.out.biggest_store = max(self.out.biggest_store, len(self.feed.store))
            if all(j.epoch >= self.epochs for j in self.jobs):
                break
        self.judge()
        return self.out

    def fetch(self, job: Job, step: int, rank: int, plan: EpochPlan, now: int) -> None:
        self.request += 1
        job.asked[(step, rank)] = (self.request, now)
        pos = plan.batch_positions(step, rank, job.world, job.batch, job.start)
        self.feed.fetch((job.name, rank, job.outputs), self.request, job.epoch, pos.start, pos.stop, now, job.outputs)

    def ask(self, job: Job, now: int) -> None:
        """A job's turn: ask up to two steps ahead, ask again what went unanswered, end its epoch,
        or checkpoint and resume at another layout (or roll back)."""
        rng, out = self.rng, self.out
        if job.plan is not None and job.plan != self.identity:  # its position is of another plan: refused
            job.start, job.step, job.taken, job.asked, job.checkpoints = 0, 0, 0, {}, [0]
            job.rows[job.epoch] = {}
            out.refused += 1
        job.plan = self.identity
        plan = self.feed.plan(job.epoch)
        steps = plan.steps(job.world, job.batch, job.start) if plan.complete else None  # unfolding: not known
        if rng.random() < 0.002 and job.outputs != OUTPUTS:  # a reader asks for one more output
            job.outputs = OUTPUTS[:len(job.outputs) + 1]
            out.widened += 1
        while job.step < min(job.taken + 2 if steps is None else steps, job.taken + 2):
            for r in range(job.world):
                self.fetch(job, job.step, r, plan, now)
            job.step += 1
        for (s, r), (q, at) in list(job.asked.items()):  # unanswered: asked again
            if q > 0 and now - at >= RETRY:
                self.fetch(job, s, r, plan, now)
        if steps is not None and job.taken >= steps:
            job.read_under[job.epoch] = (self.truth, dict(self.given))
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

    def take(self, f, rows, now: int) -> None:
        """An answer reaches its job: each row checked against the plan and noted once."""
        problems = self.out.problems
        job = next(j for j in self.jobs if j.name == f.client[0])
        hit = [(s, r) for (s, r), (q, _) in job.asked.items() if q == f.request and r == f.client[1]]
        if f.epoch != job.epoch or not hit:
            return  # an answer to a fetch no longer waited for: dropped, as the reader drops it
        plan = self.feed.plan(f.epoch)
        for row in rows:
            if row.key != plan.key(row.position):
                problems.append(f"epoch {f.epoch} position {row.position}: {row.key}, the plan says "
                                f"{plan.key(row.position)}")
            if row.sample is not None and row.sample[:2] != (f.epoch, row.key):
                problems.append(f"epoch {f.epoch} position {row.position}: the sample of {row.sample[:2]}")
            if row.sample is not None and not set(f.client[2]) <= set(row.sample[2]):
                problems.append(f"epoch {f.epoch} position {row.position}: made with {row.sample[2]}, "
                                f"asked {f.client[2]}")
            if row.key is not None:
                seen = job.rows.setdefault(f.epoch, {})
                if row.position in seen:
                    problems.append(f"{job.name} epoch {f.epoch}: position {row.position} read twice")
                seen[row.position] = row
        job.asked[hit[0]] = (-1, now)
        while all(job.asked.get((job.taken, r), (0,))[0] == -1 for r in range(job.world)) and job.taken < job.step:
            job.taken += 1

    def decode(self, now: int) -> None:
        """The workers' turn: one sample a tick unless stalled; some die, some stall, some hang."""
        rng, feed, kpw = self.rng, self.feed, self.kpw
        for w in list(self.workers):
            if rng.random() < 0.002:  # killed: the pool replaces it
                feed.worker_lost(w.ident)
                self.workers.remove(w)
                self.workers.append(Worker(f"w{self.next_worker}"))
                self.next_worker += 1
                continue
            if rng.random() < 0.004:
                w.stalled_until = now + rng.choice([3, 20, 60])
            if now < w.stalled_until:
                continue
            if w.task is None:
                w.task = t = feed.task_for(w.ident, now)
                if t is not None:
                    w.windows, w.error = self.given[t.video], None
                    if t.video in self.broken and w.windows < self.slots[t.video]:
                        w.error = "decoder error: broken packet"
                    elif self.flaky.get(t.video):
                        self.flaky[t.video] -= 1
                        w.windows, w.error = rng.randrange(w.windows), "reading: the store timed out"
                    w.todo = [SampleKey.at(t.video, i, kpw) for i in range(w.windows * kpw)
                              if (i // kpw, i % kpw) not in set(t.skip)]
                continue
            t = w.task
            if w.todo:
                key = w.todo.pop(0)
                feed.sample(w.ident, t.task, key, now, lambda lane, e=t.epoch, k=key, o=t.outputs: (e, k, o))
            else:
                feed.done(w.ident, t.task, w.windows, {}, w.error, "error" if w.error else "")
                if w.error is None:
                    self.index.setdefault(t.video, w.windows)  # a whole pass's count, as a worker records it
                w.task = None
        for ident, _ in feed.timed_out(now):
            for w in self.workers:
                if w.ident == ident:
                    w.task, w.todo, w.stalled_until = None, [], 0.0

    def judge(self) -> None:
        """Each job read each epoch's plan exactly; the store stayed bounded."""
        problems = self.out.problems
        for job in self.jobs:
            if job.epoch < self.epochs:
                problems.append(f"{job.name} stuck in epoch {job.epoch} at step {job.taken}")
                continue
            for e in range(self.epochs):
                truth, given = job.read_under[e]  # the plan of the corpus as it was while the epoch was read
                plan = EpochPlan(truth, self.seed, e, self.buffer)
                rows = job.rows.get(e, {})
                if sorted(rows) != list(range(len(plan))):
                    problems.append(f"{job.name} epoch {e}: read {len(rows)} of {len(plan)} positions")
                for p, r in rows.items():
                    if r.sample is None and r.key.window < given[r.key.video]:
                        problems.append(f"{job.name} epoch {e} position {p}: padding for {r.key}, a window the file gives")
                    if r.sample is not None and r.key.window >= given[r.key.video]:
                        problems.append(f"{job.name} epoch {e} position {p}: a sample of {r.key}, not given")
        # memory: what pending fetches name, plus the kept ones, plus the samples decoded ahead
        bound = self.settings["keep_samples"] + 2 * (5 * 3 * 5 + self.settings["lookahead"]) + \
            max(self.slots.values(), default=0) * self.kpw * 3
        if self.out.biggest_store > bound:
            problems.append(f"the store held {self.out.biggest_store} samples, over {bound}")


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="0:1000", help="a range a:b of seeds (b excluded)")
    ap.add_argument("--json", action="store_true", help="one JSON line of totals")
    a = ap.parse_args(argv)
    lo, hi = (int(x) for x in a.seeds.split(":"))
    t = time.perf_counter()
    failed, totals = [], {"restarts": 0, "resumes": 0, "rollbacks": 0, "widened": 0, "replaced": 0, "refused": 0}
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

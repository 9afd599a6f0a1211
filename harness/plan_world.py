"""A seeded world driving serving by plan's decisions (``delivery.plan_schedule.PlanScheduler``) and the
client's reading rules: time is ticks, every choice comes from ``random.Random(seed)``, so a seed
replays exactly.

What the world does:

* a corpus of 1-14 videos of 0-6 windows, or (in :data:`LONG_SHARE` of the seeds that run
  servers) 1-8 videos of 0-20 windows, at 1 or 2 samples a window: 0-40 samples a video;
* workers decode at one sample a tick, stall (3-60 ticks), die (the pool replaces them), and hang
  until the task timeout; files give fewer windows than their slots or none, or break (at one
  place, each pass); a store that fails for a while cuts one or two passes of other files short;
* servers make 0 or 8 samples ahead, or a shuffle buffer (1, 4 or 16) as ``PlanServer`` sets
  them, and keep 0, 4 or 32 fetched ones;
* the corpus index knows some videos' slots at start, none or all; the others' the server learns
  from their first decode (the plan unfolds), and the index keeps a whole pass's count for a
  server started again;
* 1 server, or 2-4 each serving one shard (``select_shard``'s videos, a ``PlanScheduler`` of its own)
  read as one interleaved plan (``v2v_wire.plan_shards``); each server is killed and started
  again on its own (a fresh ``PlanScheduler`` and a fresh pool of workers: made samples, pending
  fetches and running tasks gone), and while it is down a file of its shard may be replaced under
  its name by another cut (another tag, other windows, its index entry gone): the plan's identity
  changes, a job's position of the plan before is refused (``Position.from_dict``, as the client
  and the server check it) and it reads that epoch again from its start under the new plan;
* one or two jobs at once, each of 1-3 ranks at 1-5 rows a rank (fewer rows than shards
  included), read by the main process or by 1-3 DataLoader workers per rank, or (in
  :data:`BIG_SHARE` of the jobs) of 1-8 ranks at 1-32 rows, read by the main process or 1, 2 or 4
  DataLoader workers per rank (1-32 readers), persistent or not (``harness.plan_world_jobs``:
  real ``V2VStreamDataset`` objects take ``set_epoch`` and ``load_state_dict`` in the main process,
  the workers' copies at their next pass); each reader's pass is a client of its own (its
  connection: an answer to a pass that ended cannot be sent, and the server forgets the client);
  each reader asks up to two items ahead, asks again a fetch unanswered for ``RETRY`` ticks (a
  lost reply, a restarted server), settles the epoch's end as the client does (probing shards
  whose length it does not know); jobs checkpoint and resume in the same process or at another
  layout, and roll back to an older checkpoint of the epoch (the rows read since count again);
* in :data:`CUT_SHARE` of the seeds that run servers, the first job is cut off mid-epoch (5-95 %
  into its first or second epoch: its processes killed, it asks nothing more, its fetches in
  flight stay asked) and started again 1-51 ticks later against the same servers, from its first
  epoch, asking for the same outputs at a layout drawn anew;
* readers ask for a subset of the outputs, and a new output widens what workers make mid-run;
* a third of the seeds run a fleet instead (``harness.plan_world_fleet``): 1-16 hosts each serving
  the whole corpus's one plan, joining, leaving, stalling and restarting mid-epoch, read through
  the client's own fleet decisions (``fleet_pass.Pass``, ``v2v_wire.fleet.Router``) over a
  seeded transport that delays and loses messages; jobs resume a position on another number of
  hosts.

:func:`check` runs one seed and returns what went wrong (empty: each job read each epoch's
interleaved plan exactly: every position once across ranks and workers, at its place, a sample
wherever its window was given, padding only for windows a file did not give and past a shard's or
the epoch's end; every reader ended at the step the epoch ends at; each worker's pass was of the
epoch and position the loop set; a position refused exactly when a file was replaced; bounded
stores; each sample read made once where one job reads at a time (:meth:`World.judge_decodes`,
which names what it leaves out); a fleet's jobs, each epoch as one server's plan says:
``harness.plan_world_fleet``).
``python -m harness.plan_world --seeds 0:100000`` runs a range (``tests/test_plan_schedule.py``
runs 1,000 seeds); ``--seeds 35:36`` replays one.
"""
from __future__ import annotations

if __name__ == "__main__":  # Ctrl-C or SIGTERM from the start, the imports below included: one line
    import sys

    from v2v_wire.commands import run_command

    sys.exit(run_command("harness.plan_world", "harness.plan_world:main"))

import argparse
import json
import logging
import random
import sys
import time
import traceback
from dataclasses import dataclass, field
from typing import List, Optional, Tuple

from harness.plan_world_fleet import FleetWorld
from harness.plan_world_jobs import OUTPUTS, Job, Reading, layout
from v2v_server.delivery.plan_schedule import PlanScheduler
from v2v_server.ops.startup import select_shard
from v2v_wire.ids import SampleKey
from v2v_wire.plan import EpochPlan, Manifest, PlanIdentity
from v2v_wire.plan_shards import shards_identity, shards_samples


#: The share of seeds that run a fleet (``harness.plan_world_fleet``) instead of 1-4 shards.
FLEET_SHARE = 1 / 3
#: Samples the servers may make of the epochs read per sample the readers read
#: (:meth:`World.judge_decodes`): each once, and what a decode makes ahead of a fetch that a
#: job's end leaves unread.
MADE_PER_READ = 1.05
#: The share of the seeds that run servers (not a fleet) whose videos give 0-20 windows (0-40
#: samples at 2 a window), not 0-6 (at most 8 videos, not 14: the seeds stay cheap).
LONG_SHARE = 0.35
#: The share of the jobs of the seeds that run servers drawn big (``plan_world_jobs.layout``:
#: 1-32 readers, 1-32 rows a rank).
BIG_SHARE = 0.4
#: The share of the seeds that run servers whose first job is cut off mid-epoch and started again.
CUT_SHARE = 0.5


@dataclass
class Worker:
    """One decode worker of a server's pool: its task, the samples it has yet to send, and how
    this pass ends (``windows`` given, ``error`` when it stops early)."""

    ident: str
    task: Optional[object] = None
    todo: List[SampleKey] = field(default_factory=list)
    stalled_until: float = 0.0
    windows: int = 0  # what this pass gives
    error: Optional[str] = None  # why it stops early


@dataclass(eq=False)
class Server:
    """One server: shard ``shard`` of the corpus (``videos``, ``select_shard``'s), its scheduler, the
    identity of the plan it serves and its pool of workers."""

    shard: int
    videos: List[str]
    scheduler: Optional[PlanScheduler] = None
    identity: str = ""
    workers: List[Worker] = field(default_factory=list)


@dataclass
class Outcome:
    """One seed's run: its problems (empty when the scheduler kept the contract) and what it did."""

    seed: int
    problems: List[str]
    shards: int = 1
    sharded: int = 0  # 1 when it ran several shards
    restarts: int = 0
    resumes: int = 0
    rollbacks: int = 0
    widened: int = 0
    replaced: int = 0
    refused: int = 0
    probes: int = 0
    direct_passes: int = 0
    loader_passes: int = 0
    biggest_store: int = 0
    fleets: int = 0  # 1 when it ran a fleet (``harness.plan_world_fleet``)
    big_fleets: int = 0  # 1 when 8 or more of its hosts were up at once
    fleet_joins: int = 0
    fleet_leaves: int = 0
    fleet_stalls: int = 0
    fleet_dead_names: int = 0  # hosts killed whose names stayed where the readers resolve the fleet
    fleet_restarts: int = 0
    fleet_resumes: int = 0
    resized: int = 0  # resumes read on with another number of hosts than the position was taken with
    hedged: int = 0  # makes a reader's router hedged to another host
    copies: int = 0  # makes of a video's samples asked of a second host (hedges, copies, a host gone)
    withdrawn: int = 0  # makes a reader withdrew, its samples had from another host first
    moves: int = 0  # makes a reader asked as a move off a host it measured slow (Make.move)
    answered: int = 0  # rows holding a sample the servers answered fetches with, of the epochs read
    read: int = 0  # rows holding a sample the readers took (items' parts and probes), of the epochs read
    abandoned: int = 0  # rows holding a sample answered to a pass that had ended, of the epochs read
    made: int = 0  # samples the servers made of the epochs read
    cut_off: int = 0  # jobs cut off mid-epoch (a new job started after each)
    counted: int = 0  # 1 when its decodes were counted (:meth:`World.judge_decodes`)
    counted_readers: int = 0  # 1 when counted and a job read with 16 or more processes at once
    counted_batch: int = 0  # 1 when counted and a job read 16 or more rows a rank
    counted_long: int = 0  # 1 when counted and a video gave 20 or more samples
    counted_cut: int = 0  # 1 when counted and a job was cut off mid-epoch


def check(seed: int, ticks: int = 30000) -> Outcome:
    """Run the world of ``seed`` (module docstring) for at most ``ticks`` ticks; an exception
    raised in it (a server's or a reader's error) is its problem, named with where it was raised."""
    try:
        return World(seed).run(ticks)
    except Exception as e:  # noqa: BLE001 - reported as the seed's problem
        where = traceback.extract_tb(e.__traceback__)[-1]
        return Outcome(seed, [f"raised {type(e).__name__}: {e} ({where.filename}:{where.lineno})"])


class World:
    """One seed's corpus, servers, workers and jobs (module docstring); :meth:`run` plays it."""

    epochs = 2

    def __init__(self, seed: int):
        self.seed = seed
        self.rng = rng = random.Random(seed)
        # a third of the seeds run a fleet instead (drawn apart, as the cuts); the shard servers'
        # long videos, settings as PlanServer's, big jobs and cut-off jobs are drawn apart too
        # (``shape``), so that a fleet's seed draws what ``FleetWorld`` reads as it always has
        self.in_fleet = random.Random(f"fleet/{seed}").random() < FLEET_SHARE
        self.shape = shape = random.Random(f"shape/{seed}")
        self.kpw = rng.choice([1, 1, 2])
        long = not self.in_fleet and shape.random() < LONG_SHARE
        most, videos = (20, 8) if long else (6, 14)  # windows a video gives, videos, at most
        self.slots = {f"v{i:02d}.mp4": rng.randint(0, most) for i in range(min(videos, rng.randint(1, 14)))}
        self.tags = {v: 0 for v in self.slots}  # which cut of each file (another after a replacement)
        whole = rng.choice([0.8, 0.5])  # the share of files that give every window; the others are short or empty
        self.given = {v: (n if rng.random() < whole else rng.choice([0, rng.randint(0, n)]))
                      for v, n in self.slots.items()}
        self.broken = {v for v in self.slots if rng.random() < 0.1}  # the pass breaks after its windows
        known = rng.choice([0.0, 0.5, 1.0])
        self.index = {v: n for v, n in self.slots.items() if rng.random() < known}  # the corpus index
        self.settings = dict(lookahead=rng.choice([0, 8]), keep_samples=rng.choice([0, 4, 32]), hedge_s=5.0,
                             task_timeout_s=40.0)
        self.buffer = rng.choice([1, 4, 16])
        if not self.in_fleet and shape.random() < 0.4:  # made ahead: a shuffle buffer, as PlanServer sets it
            self.settings["lookahead"] = self.buffer
        shards = rng.choice([1, 1, 2, 3, 4])
        self.servers = [Server(i, select_shard(sorted(self.slots), i, shards)) for i in range(shards)]
        pool = rng.randint(1, 3)
        self.next_worker = 0
        for s in self.servers:
            self.start(s, pool)
        self.identify()
        self.named_jobs = 0
        self.jobs = [self.new_job(0) for _ in range(rng.randint(1, 2))]
        self.concurrent = len(self.jobs) > 1  # two jobs read at once
        if not self.in_fleet and shape.random() < CUT_SHARE:
            self.jobs[0].cut = shape.randrange(self.epochs), shape.uniform(0.05, 0.95)
        self.restart_p = rng.choice([0.0, 0.001, 0.003])
        self.out = Outcome(seed, [], shards, int(shards > 1))
        self.reading = Reading(self)
        # passes a store failing for a while cuts short, fewer than the scheduler's PASS_ATTEMPTS
        self.flaky = {v: rng.randint(1, 2) for v, n in self.given.items() if v not in self.broken and n and rng.random() < 0.2}
        # files replaced while a server is down: drawn apart, so the other draws stay each seed's
        self.cuts = random.Random(f"cuts/{seed}")
        self.replace_p = self.cuts.choice([0.0, 1.0])
        self.fleet = FleetWorld(self) if self.in_fleet else None

    def new_job(self, begins: int) -> Job:
        """A job starting at tick ``begins``, asking for a prefix of the outputs: of 1-3 ranks at 1-5
        rows, read by the main process or 1-3 DataLoader workers a rank; or, for the shard servers,
        in :data:`BIG_SHARE` of the jobs, of a big layout (:func:`plan_world_jobs.layout`)."""
        rng, self.named_jobs = self.rng, self.named_jobs + 1
        if not self.in_fleet and self.shape.random() < BIG_SHARE:
            ranks, batch, loader, persistent = layout(self.shape, True)
            return Job(f"j{self.named_jobs - 1}", ranks, batch, OUTPUTS[:self.shape.randint(1, 3)], loader, persistent,
                       big=True, begins=begins)
        ranks, batch, outputs = rng.randint(1, 3), rng.randint(1, 5), OUTPUTS[:rng.randint(1, 3)]
        return Job(f"j{self.named_jobs - 1}", ranks, batch, outputs, rng.choice([0, 0, 1, 2, 3]), rng.random() < 0.7,
                   begins=begins)

    def cut_off(self, job: Job, now: int) -> None:
        """``job`` is cut off mid-epoch (its processes killed: it asks nothing more, the fetches it
        has in flight stay asked); the job is started again 1-51 ticks later against the same
        servers, asking for the same outputs, at a layout drawn anew, from its first epoch."""
        job.gone = True
        job.read_under[job.epoch] = (self.truths(), dict(self.given))
        self.out.cut_off += 1
        again = self.new_job(now + 1 + self.rng.randint(0, 50))
        again.outputs = job.outputs
        self.jobs.append(again)

    def start(self, server: Server, pool: int) -> None:
        """(Re)start ``server``: a fresh scheduler over its shard's manifest (the corpus index's slots,
        the files' tags) and a fresh pool of ``pool`` workers."""
        tags = {v: f"cut {self.tags[v]}" for v in server.videos}
        manifest = Manifest.of({v: self.index.get(v) for v in server.videos}, self.kpw, tags)
        server.scheduler = PlanScheduler(manifest, self.seed, self.buffer, OUTPUTS, **self.settings)
        server.identity = manifest.fingerprint()
        server.workers = [Worker(f"w{self.next_worker + i}") for i in range(pool)]
        self.next_worker += pool

    def identify(self) -> None:
        """The identity of the plan the servers serve together (``plan_shards.shards_identity``),
        a new object (each job checks its position against it)."""
        self.plan = shards_identity([PlanIdentity(s.identity, "world", self.seed, self.buffer) for s in self.servers])

    def truths(self) -> List[Manifest]:
        """What each shard's epochs list: the index's slots, the decode's windows for the others."""
        return [Manifest.of({v: self.index.get(v, self.given[v]) for v in s.videos}, self.kpw) for s in self.servers]

    @staticmethod
    def samples_of(server: Server, epoch: int) -> Optional[int]:
        """The epoch's samples a server's answers carry (``PlanServer._samples``), None while unknown."""
        plan = server.scheduler.plans.get(epoch)
        return len(plan) if plan is not None and plan.complete else server.scheduler.slots.epoch_samples

    def replace_file(self, server: Server) -> None:
        """While ``server`` is down, a file of its shard is replaced under its name by another cut:
        another tag, its windows drawn again, what the corpus index knew of it gone (its identity changed)."""
        if not server.videos:
            return
        v = self.cuts.choice(server.videos)
        self.tags[v] += 1
        self.slots[v] = self.given[v] = self.cuts.randint(0, 6)
        self.index.pop(v, None)
        self.broken.discard(v)
        self.flaky.pop(v, None)
        self.out.replaced += 1

    def run(self, ticks: int) -> Outcome:
        """Play at most ``ticks`` ticks (until every job read every epoch), then judge."""
        if self.fleet is not None:
            return self.fleet.run(ticks)
        for now in range(ticks):
            for s in self.servers:
                if self.rng.random() < self.restart_p:  # killed and started again, with its workers
                    if self.cuts.random() < self.replace_p:
                        self.replace_file(s)
                    self.start(s, len(s.workers))
                    self.identify()
                    self.out.restarts += 1
            for job in list(self.jobs):
                if job.epoch < self.epochs and not job.gone and now >= job.begins:
                    self.reading.ask(job, now)
            for k, s in enumerate(self.servers):
                for f, rows in s.scheduler.answer(now):
                    self.out.answered += sum(1 for r in rows if r.sample is not None) if f.epoch < self.epochs else 0
                    self.reading.take(k, f, rows, now)
                self.decode(s, now)
                self.out.biggest_store = max(self.out.biggest_store, len(s.scheduler.store))
            if all(j.epoch >= self.epochs or j.gone for j in self.jobs):
                break
        self.judge()
        return self.out

    def decode(self, server: Server, now: int) -> None:
        """A server's workers' turn: one sample a tick unless stalled; some die, some stall, some hang."""
        rng, scheduler, kpw = self.rng, server.scheduler, self.kpw
        for w in list(server.workers):
            if rng.random() < 0.002:  # killed: the pool replaces it
                scheduler.worker_lost(w.ident)
                server.workers.remove(w)
                server.workers.append(Worker(f"w{self.next_worker}"))
                self.next_worker += 1
                continue
            if rng.random() < 0.004:
                w.stalled_until = now + rng.choice([3, 20, 60])
            if now < w.stalled_until:
                continue
            if w.task is None:
                w.task = t = scheduler.task_for(w.ident, now)
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
                scheduler.sample(w.ident, t.task, key, now, lambda e=t.epoch, k=key, o=t.outputs: (e, k, o))
            else:
                scheduler.done(w.ident, t.task, w.windows, {}, w.error, "error" if w.error else "")
                if w.error is None:
                    self.index.setdefault(t.video, w.windows)  # a whole pass's count, as a worker records it
                w.task = None
        for ident, _ in scheduler.timed_out(now):
            for w in server.workers:
                if w.ident == ident:
                    w.task, w.todo, w.stalled_until = None, [], 0.0

    def judge(self) -> None:
        """The shards together serve each video once; each job read each epoch's interleaved plan
        exactly; each server's store stayed bounded."""
        problems = self.out.problems
        served = sorted(v for s in self.servers for v in s.videos)
        if served != sorted(self.slots):
            problems.append(f"the shards serve {served}, the corpus is {sorted(self.slots)}")
        for job in self.jobs:
            if job.gone:  # the epochs it read whole, and what it read of the one it was cut off in
                for e in range(job.epoch + 1):
                    self.judge_epoch(job, e, whole=e < job.epoch)
                continue
            if job.epoch < self.epochs:
                problems.append(f"{job.name} stuck in epoch {job.epoch} at step {job.taken()}")
                continue
            for e in range(self.epochs):
                self.judge_epoch(job, e)
        # memory: what pending fetches name (each job's readers, 2 items and a probe a shard each,
        # at its widest layout), plus the kept ones, plus the samples decoded ahead
        bound = self.settings["keep_samples"] + sum(j.most_named + self.settings["lookahead"] for j in self.jobs) + \
            max(self.slots.values(), default=0) * self.kpw * 3
        if self.out.biggest_store > bound:
            problems.append(f"a store held {self.out.biggest_store} samples, over {bound}")
        self.judge_decodes()

    def judge_decodes(self) -> None:
        """Each sample read is made once: the samples the servers made of the epochs read, at most
        :data:`MADE_PER_READ` per sample the readers asked and took (an item's part or a probe's
        row; a row read again after a rollback, a refusal, by the job started again after one cut
        off, or asked by a probe and then by its step, counts again), or that were answered to a
        pass that had ended (a reader cut off or resumed elsewhere: a server makes what was
        asked, and learns the reader left only when its answer cannot be sent). Counted
        wherever one job reads at a time (cut off and started again included), at any number of
        readers, batch size and video length, except where:

        * two jobs read at once: each reads the epoch at its own place, and a bounded store holds
          what both are about to read only while they are close (the rest is made again for the
          one behind);
        * a server restarted: what it had made is gone, and is made again;
        * an output was widened: what was made lacks it, and is made again;
        * the servers make ahead fewer samples than a shuffle buffer (``lookahead`` < the buffer,
          a setting ``PlanServer`` never makes): a decode makes a whole video, whose samples the
          buffer spreads past what the store may keep of them."""
        out, s = self.out, self.settings
        if self.concurrent or out.restarts or out.widened or s["lookahead"] < self.buffer:
            return
        out.counted = 1
        out.counted_readers = int(any(j.most_readers >= 16 for j in self.jobs))
        out.counted_batch = int(any(j.most_batch >= 16 for j in self.jobs))
        out.counted_long = int(max(self.given.values(), default=0) * self.kpw >= 20)
        out.counted_cut = int(out.cut_off > 0)
        out.made = sum(n for sv in self.servers for e, n in sv.scheduler.epoch_made.items() if e < self.epochs)
        asked = out.read + out.abandoned
        if out.made > MADE_PER_READ * max(1, asked):
            out.problems.append(f"the servers made {out.made} samples of the epochs read for {out.read} read and "
                                f"{out.abandoned} answered to passes that had ended: over {MADE_PER_READ} a sample")

    def judge_epoch(self, job: Job, e: int, whole: bool = True) -> None:
        """Every position of epoch ``e`` of the shards' plans as they were while it was read, once
        (``whole``; else those read), at its place: a sample wherever its window was given, padding
        for a window not given, past a shard's end and past the epoch's end."""
        problems = self.out.problems
        truths, given = job.read_under[e]
        plans = [EpochPlan(m, self.seed, e, self.buffer) for m in truths]
        n, total = len(plans), shards_samples([len(p) for p in plans])
        rows = job.rows.get(e, {})
        missing = [t for t in range(total) if t not in rows]
        if missing and whole:
            problems.append(f"{job.name} epoch {e}: read {total - len(missing)} of {total} positions")
        for t, (k, r) in rows.items():
            plan = plans[t % n]
            want = plan.key(t // n) if t < total and t // n < len(plan) else None
            if k != t % n or r.key != want:
                problems.append(f"{job.name} epoch {e} position {t}: {r.key} of shard {k}, the plan says {want}")
            elif r.key is None and r.sample is not None:
                problems.append(f"{job.name} epoch {e} position {t}: a sample past the end")
            elif r.key is not None and (r.sample is None) == (r.key.window < given[r.key.video]):
                what, file = ("padding", "gives") if r.sample is None else ("a sample", "does not give")
                problems.append(f"{job.name} epoch {e} position {t}: {what} for {r.key}, whose window the file {file}")


#: What ``main`` and ``tests/test_plan_schedule.py`` add up over seeds (``Outcome``'s counts).
TOTALS = ("sharded", "restarts", "resumes", "rollbacks", "widened", "replaced", "refused", "probes", "direct_passes",
          "loader_passes", "fleets", "big_fleets", "fleet_joins", "fleet_leaves", "fleet_dead_names", "fleet_stalls",
          "fleet_restarts", "fleet_resumes", "resized", "hedged", "copies", "withdrawn", "moves", "cut_off", "counted", "counted_readers",
          "counted_batch", "counted_long", "counted_cut")


def _seeds(text: str) -> Tuple[int, int]:
    """``--seeds a:b``: integers 0 <= a <= b (argparse names the option on error)."""
    lo, _, hi = text.partition(":")
    try:
        lo_i, hi_i = int(lo), int(hi)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a range a:b of integers") from None
    if not 0 <= lo_i <= hi_i:
        raise argparse.ArgumentTypeError(f"{text!r}: a range a:b needs 0 <= a <= b")
    return lo_i, hi_i


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="0:1000", type=_seeds, help="a range a:b of seeds (b excluded)")
    ap.add_argument("--json", action="store_true", help="one JSON line of totals")
    a = ap.parse_args(argv)
    logging.getLogger("v2v.client").setLevel(logging.ERROR)  # a fleet's hosts left out and back, by the thousand
    lo, hi = a.seeds
    t = time.perf_counter()
    failed, totals, most = [], dict.fromkeys(TOTALS, 0), 0.0
    for seed in range(lo, hi):
        o = check(seed)
        for k in totals:
            totals[k] += getattr(o, k)
        if o.counted:
            most = max(most, o.made / max(1, o.read + o.abandoned))
        if o.problems:
            failed.append(seed)
            if not a.json:
                print(f"seed {seed}: {o.problems[0]} (+{len(o.problems) - 1} more)")
    summary = {"seeds": hi - lo, "failed": len(failed), "failed_seeds": failed[:20], **totals,
               "most_made_per_read": round(most, 3), "seconds": round(time.perf_counter() - t, 1)}
    print(json.dumps(summary) if a.json else f"{hi - lo} seeds, {len(failed)} failed; {totals}; at most "
          f"{most:.3f} made a sample read where counted; {summary['seconds']} s")
    return 1 if failed else 0

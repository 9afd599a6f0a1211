"""The jobs of ``harness.plan_world``: how a trainer's processes read the world's servers by plan,
through the client's own rules.

Each reading process is a :class:`Reader`: one rank's items ``item, item + workers, ...`` of one
epoch from a global position (``v2v_client.plan_dataset._rows``; a DataLoader worker ``j`` of
``k`` reads every ``k``-th from ``j``), each pass a client of its own to the servers (a pass
opens its own connection). An item's fetch is split among the shards holding its
rows (``plan_shards.shard_parts``), asked of each shard's server, and merged in the interleave's
order (``plan_shards.interleaved``). Over several shards an item is yielded once
``plan_shards.step_in_epoch`` settles it, each shard whose length is not known asked for the row
``plan_shards.probes`` names; over one, once answered (``fetch.Shards`` of one). A reader ends where the
epoch's steps (``v2v_wire.plan.epoch_steps`` of ``plan_shards.shards_samples``) say, as ``_read`` breaks.

A job with DataLoader workers holds a real ``V2VStreamDataset`` per rank (no socket is opened):
its main process calls ``set_epoch`` and ``load_state_dict``, and each worker's copy (persistent,
made at the process's first pass, or made anew at each pass) takes them at its pass's start
through the dataset's shared control block (``__iter__``), then starts where
``plan_dataset._start_of`` says.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

from v2v_client.plan_dataset import V2VStreamDataset, _rows, _start_of
from v2v_wire.plan import PlanIdentity, PlanMismatch, Position, epoch_steps
from v2v_wire.plan_shards import (furthest_slot, interleaved, probes, shard_parts, shard_ranges, shards_samples,
                                  step_in_epoch)

#: Ticks a fetch may go unanswered before its reader asks again (``V2VStreamDataset.retry_s``).
RETRY = 30

#: Items a reader has in flight (``V2VStreamDataset.prefetch``).
PREFETCH = 2

#: The outputs a worker may make; readers ask for a non-empty prefix of them.
OUTPUTS = ("voxels", "frames", "flow")

#: Where a job's datasets point: they never connect (the world answers their fetches).
ENDPOINT = "tcp://127.0.0.1:9"


def layout(rng, big: bool) -> Tuple[int, int, int, bool]:
    """A job's layout drawn by ``rng``: (ranks, rows a rank, DataLoader workers a rank (0: the
    main process reads), persistent workers). A big job: 1-8 ranks of 1-32 rows, 0, 1, 2 or 4
    workers a rank (4 twice as often: 1-32 readers, 16 and more in over a quarter); else 1-3
    ranks of 1-5 rows, 0-3 workers a rank."""
    if big:
        return rng.randint(1, 8), rng.randint(1, 32), rng.choice([0, 1, 2, 4, 4]), rng.random() < 0.7
    return rng.randint(1, 3), rng.randint(1, 5), rng.choice([0, 0, 1, 2, 3]), rng.random() < 0.7


@dataclass(eq=False)
class Reader:
    """One process's pass: rank ``rank``'s items from ``item`` on, every ``workers``-th, of
    ``epoch`` from global position ``origin``; ``client``: the name the servers know its fetches
    by (a pass opens its own connection). ``samples``: each shard's samples per epoch as
    this reader knows them (None: not yet); ``seen``: ``plan_shards.furthest_slot``; ``parts``:
    item -> shard -> its rows (None until answered); ``asked``: (shard, ("step", item) or
    ("probe", position)) -> (request, tick) unanswered; ``end``: the item it ended at."""

    rank: int
    worker: int
    workers: int
    epoch: int
    origin: int
    item: int
    samples: List[Optional[int]]
    steps: Optional[int]  # the epoch's steps as known when the pass began (the items it asks)
    first: int = 0  # the item its pass began at
    next_ask: int = 0
    seen: int = 0
    parts: Dict[int, Dict[int, Optional[list]]] = field(default_factory=dict)
    probed: Dict[Tuple[int, int], bool] = field(default_factory=dict)
    asked: Dict[Tuple[int, tuple], Tuple[int, int]] = field(default_factory=dict)
    end: Optional[int] = None
    client: tuple = ()


@dataclass(eq=False)
class Job:
    """A trainer: ``world`` ranks of ``batch`` rows, read by ``loader`` DataLoader workers per rank
    (0: the main process reads), ``persistent`` or made at each pass; ``big``: its layouts are
    drawn from the big ranges (:func:`layout`). ``cut``: (epoch, share of it) where it is cut
    off (its processes killed: it asks nothing more, its fetches in flight stay asked); ``gone``
    once it is; ``begins``: the tick it starts at."""

    name: str
    world: int
    batch: int
    outputs: Tuple[str, ...]
    loader: int = 0
    persistent: bool = True
    epoch: int = 0
    start: int = 0  # the position the loop set for this pass (its checkpoint, or the epoch's start)
    rows: Dict[int, Dict[int, tuple]] = field(default_factory=dict)  # epoch -> global position -> (shard, row)
    checkpoints: List[int] = field(default_factory=lambda: [0])  # positions of this epoch saved (its start)
    plan: Optional[PlanIdentity] = None  # the identity of the plan its position is of
    tags: Optional[dict] = None  # the files' cuts when it took that plan
    read_under: Dict[int, tuple] = field(default_factory=dict)  # epoch -> (truths, windows given) it was read under
    readers: List[Reader] = field(default_factory=list)
    datasets: Optional[List[V2VStreamDataset]] = None  # one per rank, with DataLoader workers
    copies: Optional[List[List[V2VStreamDataset]]] = None  # each rank's workers' copies
    big: bool = False
    cut: Optional[Tuple[int, float]] = None
    gone: bool = False
    begins: int = 0
    passes: int = 0  # passes begun: each reader's client is of its pass
    most_named: int = 0  # the most positions its readers' fetches in flight name at once, over its layouts
    most_readers: int = 0  # the most processes it read with at once, over its layouts
    most_batch: int = 0  # the most rows a rank it read, over its layouts

    @property
    def readers_count(self) -> int:
        """Processes that read: a rank's main process, or its DataLoader workers."""
        return self.world * max(1, self.loader)

    @property
    def per_step(self) -> int:
        """Positions every rank together reads at a step."""
        return self.world * self.batch

    def taken(self) -> int:
        """Steps the loop took (every rank's batches of each, in order), from ``start``."""
        return min(r.item for r in self.readers) if self.readers else 0


class Reading:
    """The jobs' turns in ``world`` (a ``harness.plan_world.World``: its ``servers``, ``plan``
    (the identity of the plan they serve, a new object at each restart), ``tags``, ``rng``, ``out``)."""

    def __init__(self, world):
        self.world = world
        self.request = 0
        self.requests: Dict[int, tuple] = {}  # request id -> (job, reader, shard, what)

    # ------------------------------------------------------------------ passes
    def begin(self, job: Job, new_process: bool, resumed: bool) -> None:
        """A pass of ``job`` begins at ``job.start`` of ``job.epoch``: its readers, each knowing what
        ``plan_info`` says now; with DataLoader workers, what each worker's copy takes from the
        main process's ``set_epoch`` / ``load_state_dict``, checked against what the loop set."""
        w = self.world
        samples = [w.samples_of(s, job.epoch) for s in w.servers]
        steps = epoch_steps(shards_samples(samples), job.world, job.batch, job.start)
        job.passes += 1
        job.most_named = max(job.most_named, job.readers_count * (PREFETCH * job.batch + len(w.servers)))
        job.most_readers, job.most_batch = max(job.most_readers, job.readers_count), max(job.most_batch, job.batch)
        if not job.loader:
            job.readers = [Reader(r, 0, 1, job.epoch, job.start, 0, list(samples), steps,
                                  client=(job.name, job.passes, r, 0)) for r in range(job.world)]
            w.out.direct_passes += 1
            return
        if new_process or job.datasets is None:
            job.datasets = [V2VStreamDataset(ENDPOINT, job.batch, rank=r, world_size=job.world)
                            for r in range(job.world)]
            job.copies = None
        for ds in job.datasets:
            if resumed:
                ds.load_state_dict(Position(w.plan, job.epoch, job.start).to_dict())
            if not resumed or w.rng.random() < 0.5:  # the loop's set_epoch (load_state_dict set it too)
                ds.set_epoch(job.epoch)
        if job.copies is None or not job.persistent:  # the workers start (fork: the control block is shared)
            job.copies = [[copy.deepcopy(ds, {id(ds._control): ds._control}) for _ in range(job.loader)]
                          for ds in job.datasets]
        job.readers = []
        for r, copies in enumerate(job.copies):
            for j, c in enumerate(copies):
                c.__iter__()  # the pass begins: the copy takes what the main process set
                epoch, origin, item = _start_of(c._upcoming, c.epoch, c.start, j)
                if (epoch, origin, item) != (job.epoch, job.start, j):
                    w.out.problems.append(f"{job.name} rank {r} worker {j}: a pass of epoch {epoch} from {origin} "
                                          f"(item {item}), the loop set epoch {job.epoch} from {job.start}")
                job.readers.append(Reader(r, j, job.loader, epoch, origin, item, list(samples), steps, item, item,
                                          client=(job.name, job.passes, r, j)))
        w.out.loader_passes += 1

    # ------------------------------------------------------------------ a job's turn
    def ask(self, job: Job, now: int) -> None:
        """A job's turn: start (again, under a changed plan: the position refused), each reader's
        turn, end its epoch, or checkpoint and resume (the same process, or another at another
        layout) or roll back."""
        w, rng, out = self.world, self.world.rng, self.world.out
        if job.cut is not None and job.epoch == job.cut[0] and job.plan is w.plan and \
                job.start + job.taken() * job.per_step >= job.cut[1] * shards_samples([t.samples for t in w.truths()]):
            w.cut_off(job, now)
            return
        if job.plan is not w.plan:  # the first turn, or a server started again since the last
            if job.plan is not None and self.refused(job):  # the epoch read again under the new plan
                job.start, job.checkpoints, job.rows[job.epoch] = 0, [0], {}
                job.plan = None
                out.refused += 1
            if job.plan is None:
                self.begin(job, True, False)
            job.plan, job.tags = w.plan, dict(w.tags)
        if rng.random() < 0.002 and job.outputs != OUTPUTS:  # a reader asks for one more output
            job.outputs = OUTPUTS[:len(job.outputs) + 1]
            out.widened += 1
        for reader in job.readers:
            self.turn(job, reader, now)
        if all(r.end is not None for r in job.readers):
            job.read_under[job.epoch] = (w.truths(), dict(w.given))
            job.epoch, job.start, job.checkpoints = job.epoch + 1, 0, [0]
            if job.epoch < w.epochs:
                self.begin(job, False, False)
        elif job.taken() and rng.random() < 0.01:
            self.resume(job)

    def refused(self, job: Job) -> bool:
        """Whether the job's position is refused under the plan the servers serve now (the client's
        and the server's check, ``Position.from_dict``); checked against whether a file of the
        corpus was replaced since the job took its plan."""
        try:
            Position.from_dict(Position(job.plan, job.epoch, job.start).to_dict(), expected=self.world.plan)
            refused = False
        except PlanMismatch:
            refused = True
        if refused != (job.tags != self.world.tags):
            self.world.out.problems.append(f"{job.name}: its position {'refused' if refused else 'taken'} under "
                                           f"the plan after a restart, {'no' if refused else 'a'} file replaced")
        return refused

    def resume(self, job: Job) -> None:
        """Checkpoint after the steps the loop took and resume there, or at an older checkpoint
        of the epoch (those after it are gone; the rows read since count again): in the same
        process (its workers persist) or in another, at another layout."""
        rng, out = self.world.rng, self.world.out
        job.start += job.taken() * job.per_step
        job.checkpoints.append(job.start)
        if rng.random() < 0.3:
            back = rng.randrange(len(job.checkpoints) - 1)
            job.start, job.checkpoints = job.checkpoints[back], job.checkpoints[:back + 1]
            out.rollbacks += 1
        out.resumes += 1
        job.rows[job.epoch] = {p: row for p, row in job.rows.get(job.epoch, {}).items() if p < job.start}
        new = not job.loader or rng.random() < 0.5
        if new:
            job.world, job.batch, job.loader, job.persistent = layout(rng, job.big)
        self.begin(job, new, True)

    def turn(self, job: Job, reader: Reader, now: int) -> None:
        """One reader's turn: ask its next items (up to :data:`PREFETCH` in flight), ask again
        what went unanswered, and yield or end at its head item."""
        while reader.end is None and len(reader.parts) < PREFETCH and \
                (reader.steps is None or reader.next_ask < reader.steps):
            self.begin_item(job, reader, reader.next_ask, now)
            reader.next_ask += reader.workers
        for (k, what), (_, at) in list(reader.asked.items()):
            if now - at >= RETRY:
                self.fetch(job, reader, k, what, now)
        n = len(self.world.servers)
        while reader.end is None:
            i = reader.item
            steps = epoch_steps(shards_samples(reader.samples), job.world, job.batch, reader.origin)
            if steps is not None and i >= steps:
                self.ended(job, reader)
                return
            got = reader.parts.get(i)
            if got is None or any(p is None for p in got.values()):
                return
            first = reader.origin + i * job.per_step
            if n > 1 and step_in_epoch(first, reader.samples, reader.seen) is None:
                for k, q in probes(first, reader.samples):
                    if (k, q) not in reader.probed:
                        reader.probed[(k, q)] = False
                        self.fetch(job, reader, k, ("probe", q), now)
                        self.world.out.probes += 1
                return
            self.emit(job, reader, i)

    def ended(self, job: Job, reader: Reader) -> None:
        """``reader`` ends its pass: at the first of its items past the epoch's end, as the
        corpus says it is (every rank at the same step)."""
        w = self.world
        total = shards_samples([t.samples for t in w.truths()])
        steps = epoch_steps(total, job.world, job.batch, job.start)
        k, first = reader.workers, reader.first
        want = first if first >= steps else first + -(-(steps - first) // k) * k  # its first item past the end
        if reader.item != want:
            w.out.problems.append(f"{job.name} epoch {reader.epoch} rank {reader.rank} worker {reader.worker}: "
                                  f"ended at step {reader.item}, the epoch ends at step {steps}")
        reader.end = reader.item

    # ------------------------------------------------------------------ fetches
    def begin_item(self, job: Job, reader: Reader, i: int, now: int) -> None:
        """Ask each shard holding some of item ``i``'s rows for its part."""
        reader.parts[i] = dict.fromkeys(shard_parts(*self.rows_of(job, reader, i), len(self.world.servers)))
        for k in reader.parts[i]:
            self.fetch(job, reader, k, ("step", i), now)

    def rows_of(self, job: Job, reader: Reader, i: int) -> Tuple[int, int]:
        """Global positions ``[start, stop)`` of ``reader``'s item ``i`` (the client's rule)."""
        return _rows({"group": 1, "origin": reader.origin, "world": job.world, "rank": reader.rank}, i, job.batch)

    def fetch(self, job: Job, reader: Reader, k: int, what: tuple, now: int) -> None:
        """Ask shard ``k``'s server for ``what``: its part of an item, or one row (a probe)."""
        if what[0] == "step":
            lo, hi = shard_ranges(*self.rows_of(job, reader, what[1]), len(self.world.servers))[k]
        else:
            lo, hi = what[1], what[1] + 1
        self.request += 1
        reader.asked[(k, what)] = (self.request, now)
        self.requests[self.request] = (job, reader, k, what)
        self.world.servers[k].scheduler.fetch(reader.client + (job.outputs,), self.request, reader.epoch, lo, hi,
                                              now, job.outputs)

    def take(self, k: int, f, rows, now: int) -> None:
        """Shard ``k``'s answer reaches its reader: each row checked against that server's plan,
        what it says of the shard's length and slots noted, an item's part kept for the merge."""
        entry = self.requests.pop(f.request, None)
        if entry is None:
            return
        job, reader, _, what = entry
        w = self.world
        if job.gone or reader not in job.readers or reader.end is not None:
            # its pass ended, its connection closed: the send fails and the server forgets the
            # client (``PlanServer._send``), having made what it asked
            w.servers[k].scheduler.forget(f.client)
            if f.epoch < w.epochs:
                w.out.abandoned += sum(1 for r in rows if r.sample is not None)
            return
        if reader.asked.pop((k, what), None) is None:
            return  # an answer to a fetch asked again: dropped, as the reader drops it
        self.check_rows(job, k, f, rows)
        samples = w.samples_of(w.servers[k], f.epoch)
        if samples is not None:
            reader.samples[k] = samples
        reader.seen = furthest_slot(reader.seen, k, len(w.servers), f.start, [r.key for r in rows])
        if f.epoch < w.epochs:  # an item's part or a probe's row (its step asks the sample again)
            w.out.read += sum(1 for r in rows if r.sample is not None)
        if what[0] == "probe":
            if rows[0].key is None and samples is None:
                w.out.problems.append(f"shard {k}: position {what[1]} answered past the end without its samples")
            reader.probed[(k, what[1])] = rows[0].key is not None
            return
        if what[1] in reader.parts:
            reader.parts[what[1]][k] = rows

    def check_rows(self, job: Job, k: int, f, rows) -> None:
        """Shard ``k``'s rows of fetch ``f``: each key its server's plan's at that position, each
        sample of that epoch and key, made with the outputs the fetch asked for."""
        problems = self.world.out.problems
        plan = self.world.servers[k].scheduler.plan(f.epoch)
        for row in rows:
            if row.key != plan.key(row.position):
                problems.append(f"shard {k} epoch {f.epoch} position {row.position}: {row.key}, the plan says "
                                f"{plan.key(row.position)}")
            if row.sample is not None and row.sample[:2] != (f.epoch, row.key):
                problems.append(f"shard {k} epoch {f.epoch} position {row.position}: the sample of {row.sample[:2]}")
            if row.sample is not None and not set(f.client[-1]) <= set(row.sample[2]):
                problems.append(f"shard {k} epoch {f.epoch} position {row.position}: made with {row.sample[2]}, "
                                f"asked {f.client[-1]}")

    def emit(self, job: Job, reader: Reader, i: int) -> None:
        """``reader`` yields item ``i``: the shards' parts merged in the interleave's order, each
        row noted once at its global position."""
        start, stop = self.rows_of(job, reader, i)
        got = reader.parts.pop(i)
        seen = job.rows.setdefault(reader.epoch, {})
        for t, (k, j) in zip(range(start, stop), interleaved(start, stop, len(self.world.servers))):
            if t in seen:
                self.world.out.problems.append(f"{job.name} epoch {reader.epoch}: position {t} read twice")
            seen[t] = (k, got[k][j])
        reader.item += reader.workers

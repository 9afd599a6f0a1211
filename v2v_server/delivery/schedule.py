"""The epoch scheduler: which samples are owed in which epoch, and which task makes them.

Pure: no sockets, no processes, no clock of its own (``now`` is an argument, seconds).
``server.py`` feeds it what workers and clients say; the stateful tests in
``tests/test_delivery_core.py`` drive it directly.

Terms:

* a *sample key* is ``(video, index)``, the index of the sample in its video (``window x
  crops_per_window + crop``); its wire id is made by ``ids.make_sample_id``;
* a *job* is one video of one epoch; a *task* is one attempt at a job by one worker (a
  reassigned job gets a new task id, so a late copy from the old attempt is recognised and
  ignored);
* a *consumer* is whoever acknowledges samples: one DDP rank ``("g:<group>", rank)`` or one
  dataset ``("c:<consumer id>", worker)``; the consumer key survives reconnects and trainer
  restarts (it travels in the client's ``state_dict()``);
* a sample of an epoch is *delivered* when some consumer's record holds it, *live* while it
  sits in a batch (queued or in flight), *failed* when its index failed in this epoch (that
  index only, this epoch only), else *owed*: it must be made (again).

A consumer's resume state is authoritative: ``apply_resume`` replaces that consumer's record
of every open epoch by the ids in the state, so samples it acknowledged after its checkpoint
are owed again. An epoch is *complete* when every sample of every video is delivered or failed
and no job is queued or running.
"""
from __future__ import annotations

import collections
import itertools
from dataclasses import dataclass, field
from typing import Deque, Dict, FrozenSet, Hashable, Iterable, List, Optional, Set, Tuple

from v2v_wire import ids

SampleKey = Tuple[str, int]
Consumer = Hashable


def parse_sample_id(sid, crops_per_window: int = 1) -> Optional[SampleKey]:
    """``"path/clip.mp4#3"`` -> ``("path/clip.mp4", 3)`` (with ``crops_per_window`` K > 1:
    ``"clip.mp4#3.1"`` -> ``("clip.mp4", 3 * K + 1)``, see ``ids.py``); None for anything
    else (non-str, no ``#``, an index that is not ASCII digits, absurd lengths)."""
    try:
        return ids.parse_sample_id(sid, crops_per_window)
    except ValueError:
        return None


def sample_id(key: SampleKey, crops_per_window: int = 1) -> str:
    """``("clip.mp4", 3)`` -> ``"clip.mp4#3"`` (the inverse of :func:`parse_sample_id`)."""
    k = crops_per_window
    return ids.make_sample_id(key[0], key[1] // k, key[1] % k, k)


@dataclass(frozen=True)
class Task:
    """One attempt at one job, to hand to an idle worker.

    Attributes:
        task_id: unique per attempt.
        epoch: epoch index.
        video: path relative to the corpus root.
        skip: indices the worker must not make (delivered, live or failed ones).
    """

    task_id: int
    epoch: int
    video: str
    skip: FrozenSet[int]


@dataclass
class Job:
    epoch: int
    video: str
    state: str = "queued"  # queued | running | done
    task_id: Optional[int] = None
    worker: Optional[Hashable] = None
    last_progress: float = 0.0
    crashes: int = 0
    samples: Optional[int] = None  # samples the file gave in this epoch (known once a pass ended)
    failed: Dict[int, str] = field(default_factory=dict)  # index -> reason (this epoch only)
    error: Optional[str] = None  # the pass over the file stopped early in this epoch
    index_crashes: Dict[int, int] = field(default_factory=dict)  # index -> worker crashes blamed on it
    gave_up: bool = False  # crashed too often: the rest of the file is skipped this epoch


@dataclass
class EpochPlan:
    """Every sample of one epoch: jobs, who holds what (records), what is live in batches.
    Per-video indexes keep each update proportional to one file, not the corpus."""

    epoch: int
    jobs: Dict[str, Job] = field(default_factory=dict)
    records: Dict[Consumer, Set[SampleKey]] = field(default_factory=dict)
    live: Set[SampleKey] = field(default_factory=set)
    complete: bool = False
    held: Dict[str, Dict[int, int]] = field(default_factory=dict)  # video -> index -> records holding it
    live_by_video: Dict[str, Set[int]] = field(default_factory=dict)
    unfinished: int = 0  # jobs queued or running

    def delivered(self) -> Set[SampleKey]:
        """Every sample some consumer holds (O(samples): for tests and reports)."""
        return {(v, k) for v, ws in self.held.items() for k, n in ws.items() if n > 0}

    def is_delivered(self, key: SampleKey) -> bool:
        return self.held.get(key[0], {}).get(key[1], 0) > 0

    def have(self, video: str) -> Set[int]:
        """Windows of ``video`` delivered or live."""
        return {k for k, n in self.held.get(video, {}).items() if n > 0} | self.live_by_video.get(video, set())

    def add_live(self, key: SampleKey) -> None:
        self.live.add(key)
        self.live_by_video.setdefault(key[0], set()).add(key[1])

    def drop_live(self, key: SampleKey) -> None:
        if key in self.live:
            self.live.discard(key)
            self.live_by_video[key[0]].discard(key[1])

    def set_record(self, consumer: Consumer, keys: Iterable[SampleKey]) -> Set[str]:
        """Replace a consumer's record; returns the videos whose holdings changed."""
        old = self.records.get(consumer, set())
        new = set(keys)
        for v, k in old - new:
            self.held[v][k] -= 1
        for v, k in new - old:
            self.held.setdefault(v, {})[k] = self.held.get(v, {}).get(k, 0) + 1
        self.records[consumer] = new
        return {v for v, _ in old ^ new}

    def add_record(self, consumer: Consumer, keys: Iterable[SampleKey]) -> None:
        rec = self.records.setdefault(consumer, set())
        for key in keys:
            if key not in rec:
                rec.add(key)
                ws = self.held.setdefault(key[0], {})
                ws[key[1]] = ws.get(key[1], 0) + 1


class EpochScheduler:
    """Plans epochs of ``videos`` and tracks every sample of them.

    Args:
        videos: corpus-relative paths (never re-read: the scheduler never opens files).
        epochs: stop after this many epochs (None: unbounded).
        max_task_crashes: crashes blamed on one index before it fails for the epoch (twice
            as many in one file give the file up for the epoch; see ``worker_lost``).
        lookahead: epochs that may be open beyond the oldest incomplete one.
        keep_epochs: complete epochs kept so an older resume state can reopen them.

    Nothing here raises on peer input: bad ids are ignored by the caller's parser.
    """

    def __init__(self, videos: Iterable[str], epochs: Optional[int] = None, max_task_crashes: int = 3,
                 lookahead: int = 1, keep_epochs: int = 2):
        self.videos = list(videos)
        self.known = set(self.videos)
        self.max_epochs = epochs
        self.max_task_crashes = max_task_crashes
        self.lookahead = lookahead
        self.keep_epochs = keep_epochs
        self.plans: Dict[int, EpochPlan] = {}
        self.next_epoch = 0
        self.queue: Deque[Tuple[int, str]] = collections.deque()
        self.running: Dict[int, Job] = {}  # task id -> job
        self._task_ids = itertools.count()
        self.pending_records: Dict[int, Dict[Consumer, Set[SampleKey]]] = {}  # for epochs not opened yet
        self.file_failures: Dict[str, str] = {}  # video -> last reason it failed (for logs and stats)

    # ------------------------------------------------------------------ epochs
    def _open_epoch(self) -> bool:
        if self.max_epochs is not None and self.next_epoch >= self.max_epochs:
            return False
        incomplete = [e for e, p in self.plans.items() if not p.complete]
        if incomplete and self.next_epoch - min(incomplete) > self.lookahead:
            return False
        e = self.next_epoch
        self.next_epoch += 1
        plan = EpochPlan(e)
        for consumer, keys in self.pending_records.pop(e, {}).items():
            plan.set_record(consumer, keys)
        for v in self.videos:
            plan.jobs[v] = Job(e, v)
            plan.unfinished += 1
            self.queue.append((e, v))
        self.plans[e] = plan
        self._check_complete(plan)
        return True

    def finished(self) -> bool:
        """True when the last of ``epochs`` epochs is complete (never for unbounded streams)."""
        return (self.max_epochs is not None and self.next_epoch >= self.max_epochs
                and all(p.complete for p in self.plans.values()))

    def owed(self, epoch: int) -> Set[SampleKey]:
        """Samples of ``epoch`` that must still be made: not delivered, live or failed, in
        videos whose sample count is known (a job not yet run owes its whole file)."""
        p = self.plans.get(epoch)
        if p is None:
            return set()
        return {(v, k) for v in p.jobs for k in self._owed_in(p, v)}

    @staticmethod
    def _owed_in(plan: EpochPlan, video: str) -> Set[int]:
        job = plan.jobs[video]
        if job.samples is None:
            return set()
        have = plan.have(video)
        return {k for k in range(job.samples) if k not in job.failed and k not in have}

    def _skip(self, job: Job, plan: EpochPlan) -> FrozenSet[int]:
        return frozenset(plan.have(job.video) | set(job.failed))

    @staticmethod
    def _set_state(plan: EpochPlan, job: Job, state: str) -> None:
        if (job.state == "done") != (state == "done"):
            plan.unfinished += 1 if job.state == "done" else -1
        job.state = state

    def _check_complete(self, plan: EpochPlan) -> bool:
        """Complete when no job is queued or running and nothing is live (a done job never
        owes anything: ``_reconcile`` queues it again first)."""
        if plan.complete:
            return True
        if plan.unfinished or plan.live:
            return False
        plan.complete = True
        return True

    def prune(self, forgettable: Iterable[int]) -> None:
        """Forget complete epochs in ``forgettable`` (e.g. announced to clients) except the
        newest ``keep_epochs`` complete ones (an older resume state can still reopen those)."""
        forgettable = set(forgettable)
        done = sorted(e for e, p in self.plans.items() if p.complete)
        for e in done[:-self.keep_epochs] if self.keep_epochs > 0 else done:
            if e in forgettable:
                del self.plans[e]

    # ------------------------------------------------------------------ tasks
    def next_task(self, worker: Hashable, now: float) -> Optional[Task]:
        """The next task for an idle ``worker`` (opens a new epoch when every job is handed out),
        or None when there is nothing to do now."""
        while True:
            while self.queue:
                e, v = self.queue.popleft()
                plan = self.plans.get(e)
                if plan is None or plan.complete:
                    continue
                job = plan.jobs[v]
                if job.state != "queued":
                    continue
                if job.samples is not None and not self._owed_in(plan, v):
                    self._set_state(plan, job, "done")  # nothing left to make of it (e.g. a resume state covered it)
                    self._check_complete(plan)
                    continue
                tid = next(self._task_ids)
                self._set_state(plan, job, "running")
                job.task_id, job.worker, job.last_progress = tid, worker, now
                self.running[tid] = job
                return Task(tid, e, v, self._skip(job, plan))
            if not self._open_epoch():
                return None

    def _current(self, task_id, worker) -> Optional[Job]:
        job = self.running.get(task_id) if isinstance(task_id, int) else None
        if job is None or job.worker != worker:
            return None  # a reassigned task's late copy, or a stranger
        return job

    def accept_sample(self, task_id, worker: Hashable, index, now: float) -> Optional[SampleKey]:
        """A worker made ``index`` of its task. Returns the sample key to batch, or None when
        the sample must be dropped (late copy of a reassigned task, already delivered or live,
        or not an index of that task)."""
        job = self._current(task_id, worker)
        if job is None or isinstance(index, bool) or not isinstance(index, int) or index < 0:
            return None
        job.last_progress = now
        plan = self.plans[job.epoch]
        key = (job.video, index)
        if key in plan.live or plan.is_delivered(key) or index in job.failed:
            return None
        plan.add_live(key)
        return key

    def task_done(self, task_id, worker: Hashable, samples: int, failed: Optional[Dict[int, str]] = None,
                  error: Optional[str] = None) -> Optional[Job]:
        """A worker finished its task: ``samples`` the file gave (complete windows x crops),
        ``failed`` sample indices that could not be made (index -> reason), ``error`` when the
        pass stopped early (the index it stopped in counts as failed; later ones do not exist
        this epoch).
        Returns the job, or None for a late copy."""
        job = self._current(task_id, worker)
        if job is None:
            return None
        del self.running[task_id]
        plan = self.plans[job.epoch]
        job.worker, job.task_id = None, None
        samples = samples if isinstance(samples, int) and samples >= 0 else 0
        for k, why in (failed or {}).items():
            if isinstance(k, str) and k.isascii() and k.isdigit() and len(k) <= 9:
                k = int(k)
            if isinstance(k, int) and not isinstance(k, bool) and k >= 0:
                job.failed[k] = str(why)
        if error:
            job.error = error
            self.file_failures[job.video] = error
            self._stop_at(job, plan, samples, error)
        else:
            job.samples = samples if job.samples is None else max(job.samples, samples)
        self._set_state(plan, job, "done")
        self._reconcile(plan, {job.video})
        return job

    @staticmethod
    def _stop_at(job: Job, plan: EpochPlan, first: int, reason: str) -> None:
        """The pass over ``job``'s file stopped in the first index at or after ``first`` that is
        neither made nor failed: that index fails for this epoch and none beyond it exists."""
        have = plan.have(job.video)
        stop = max(first, 0)
        while stop in have or stop in job.failed:
            stop += 1
        job.failed.setdefault(stop, reason)
        job.samples = stop + 1

    def worker_lost(self, worker: Hashable) -> Optional[Job]:
        """A worker died (or hung and was replaced) during a job. The crash is blamed on the
        first index of the file not yet made: after ``max_task_crashes`` crashes in that
        index it fails for this epoch and the job goes on after it; after twice as many
        crashes in all the file is given up for the epoch (``job.gave_up``: indices from the
        failed one on do not exist this epoch). Otherwise the job goes back to the front of the
        queue. Returns the job, if any."""
        for tid, job in list(self.running.items()):
            if job.worker != worker:
                continue
            del self.running[tid]
            job.worker, job.task_id = None, None
            job.crashes += 1
            plan = self.plans[job.epoch]
            have = plan.have(job.video)
            stop = 0
            while stop in have or stop in job.failed:
                stop += 1
            job.index_crashes[stop] = job.index_crashes.get(stop, 0) + 1
            reason = f"worker crashed {job.index_crashes[stop]} times while making sample {stop}"
            if job.crashes >= 2 * self.max_task_crashes:
                job.error = f"worker crashed {job.crashes} times while processing it"
                job.gave_up = True
                self.file_failures[job.video] = job.error
                self._stop_at(job, plan, stop, job.error)
                self._set_state(plan, job, "done")
                self._reconcile(plan, {job.video})
                return job
            if job.index_crashes[stop] >= self.max_task_crashes:
                job.failed[stop] = reason
                self.file_failures[job.video] = reason
            self._set_state(plan, job, "queued")
            self.queue.appendleft((job.epoch, job.video))
            return job
        return None

    def expire(self, now: float, task_timeout_s: float) -> List[Tuple[Hashable, Job]]:
        """Jobs whose worker sent nothing for ``task_timeout_s``: each is reassigned (queued
        again, counted as a crash) and its worker returned so the pool can replace it; anything
        the old attempt still sends is ignored."""
        out = []
        for tid, job in list(self.running.items()):
            if now - job.last_progress > task_timeout_s:
                w = job.worker
                self.worker_lost(w)
                out.append((w, job))
        return out

    # ------------------------------------------------------------------ delivery
    def _drop_live(self, epoch: int, keys: Iterable[SampleKey]):
        """``keys`` of ``epoch`` left the live set: ``(plan, keys as a list)``, plan None for
        an unknown epoch (nothing done)."""
        plan = self.plans.get(epoch)
        if plan is None:
            return None, []
        keys = list(keys)
        for k in keys:
            plan.drop_live(k)
        return plan, keys

    def delivered(self, consumer: Consumer, epoch: int, keys: Iterable[SampleKey]) -> None:
        """``consumer`` acknowledged ``keys`` of ``epoch`` (they left the live set)."""
        plan, keys = self._drop_live(epoch, keys)
        if plan is None:
            return
        plan.add_record(consumer, keys)
        self._reconcile(plan, set())

    def discarded(self, epoch: int, keys: Iterable[SampleKey]) -> None:
        """Live samples thrown away undelivered (filtered out of a batch): owed again unless
        some consumer already holds them."""
        plan, keys = self._drop_live(epoch, keys)
        if plan is None:
            return
        self._reconcile(plan, {v for v, _ in keys})

    def is_delivered(self, epoch: int, key: SampleKey) -> bool:
        plan = self.plans.get(epoch)
        return plan is not None and plan.is_delivered(key)

    def apply_resume(self, consumer: Consumer, completed_epoch: int,
                     delivered: Dict[int, Set[SampleKey]]) -> None:
        """A consumer's resume state (authoritative for that consumer): in every epoch after
        ``completed_epoch`` its record becomes exactly ``delivered[epoch]``; samples it had
        acknowledged beyond that become owed again (a complete epoch reopens). A fresh
        scheduler starts at ``completed_epoch + 1``."""
        delivered = {e: {k for k in ks if k[0] in self.known} for e, ks in delivered.items()}
        if not self.plans and self.next_epoch <= completed_epoch:
            self.next_epoch = completed_epoch + 1
        for e, plan in self.plans.items():
            if e <= completed_epoch:
                continue
            changed = plan.set_record(consumer, delivered.get(e, ()))
            self._reconcile(plan, changed)
        for e, ks in delivered.items():
            if e > completed_epoch and e >= self.next_epoch:
                self.pending_records.setdefault(e, {})[consumer] = set(ks)

    def _reconcile(self, plan: EpochPlan, videos: Iterable[str]) -> None:
        """Queue again the done jobs of ``videos`` that owe indices; reopen the epoch if so."""
        for v in videos:
            job = plan.jobs.get(v)
            if job is not None and job.state == "done" and self._owed_in(plan, v):
                self._set_state(plan, job, "queued")
                self.queue.append((plan.epoch, v))
                plan.complete = False
        if plan.live:
            plan.complete = False
        self._check_complete(plan)

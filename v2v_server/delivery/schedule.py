"""The epoch scheduler: which samples are owed in which epoch, and which task makes them.

Pure: no sockets, no processes, no clock of its own (``now`` is an argument, seconds).
``server.py`` feeds it what workers and clients say; the stateful tests in
``tests/test_delivery_core.py`` drive it directly.

Terms:

* a sample is named by its ``ids.SampleKey`` ``(video, window, crop)``; a video's samples are
  numbered in the order they are made (``SampleKey.ordinal``), which is how a file's sample count
  and the place a pass over it stopped are told;
* a *job* is one video of one epoch; a *task* is one attempt at a job by one worker (a
  reassigned job gets a new task id, so a late copy from the old attempt is recognised and
  ignored);
* a *consumer* is whoever acknowledges samples: one DDP rank ``("g:<group>", rank)`` or one
  dataset ``("c:<consumer id>", worker)``; the consumer key survives reconnects and trainer
  restarts (it travels in the client's ``state_dict()``);
* a sample of an epoch is *delivered* when some consumer's record holds it, *live* while it
  sits in a batch (queued or in flight), *failed* when it failed in this epoch (that sample
  only, this epoch only), else *owed*: it must be made (again).

A consumer's resume state is authoritative: ``apply_resume`` replaces that consumer's record
of every open epoch by the keys in the state, so samples it acknowledged after its checkpoint
are owed again. An epoch is *complete* when every sample of every video is delivered or failed
and no job is queued or running.

``EpochPlan`` keeps the book of one epoch (jobs, records, live samples, completion);
``EpochScheduler`` opens and forgets epochs, hands out tasks and applies what workers and
consumers report to the right plan.
"""
from __future__ import annotations

import collections
import itertools
from dataclasses import dataclass, field
from typing import Callable, Deque, Dict, FrozenSet, Hashable, Iterable, List, Optional, Set, Tuple, Union

from v2v_server.delivery.batcher import video_order
from v2v_wire.ids import SampleKey, window_keys

#: Crashes blamed on one sample before it fails for the epoch (the server's policy, ``core.DeliveryPolicy``).
MAX_TASK_CRASHES = 3
#: Complete epochs kept (by the scheduler, and by the journal across a restart) so that an older
#: resume state can reopen them (docs/delivery.md, "Ends of epochs and of the stream", limit (e)).
KEEP_EPOCHS = 2

Consumer = Hashable


@dataclass(frozen=True)
class Task:
    """One attempt at one job, to hand to an idle worker.

    Attributes:
        task_id: unique per attempt.
        epoch: epoch index.
        video: path relative to the corpus root.
        skip: samples of ``video`` the worker must not make (delivered, live or failed ones).
    """

    task_id: int
    epoch: int
    video: str
    skip: FrozenSet[SampleKey]


@dataclass(slots=True)  # one per video and open epoch: no instance dict
class Job:
    epoch: int
    video: str
    state: str = "queued"  # queued | running | done
    task_id: Optional[int] = None
    worker: Optional[Hashable] = None
    last_progress: float = 0.0  # task-clock seconds the task started or its worker last sent a sample at
    crashes: int = 0
    samples: Optional[int] = None  # samples the file gave in this epoch (known once a pass ended)
    failed: Dict[SampleKey, str] = field(default_factory=dict)  # sample -> reason (this epoch only)
    error: Optional[str] = None  # the pass over the file stopped early in this epoch
    sample_crashes: Dict[SampleKey, int] = field(default_factory=dict)  # sample -> worker crashes blamed on it
    gave_up: bool = False  # crashed too often: the rest of the file is skipped this epoch


class Jobs(Dict[str, Job]):
    """One epoch's jobs by video, made when first looked up: ``jobs[video]`` gives a video of
    ``videos`` that nothing touched yet a new queued :class:`Job`, so opening an epoch makes
    no object per video (a corpus of a million files would otherwise allocate a million jobs,
    and the garbage collector walk them, before the first task). ``get``, ``in``, ``len`` and
    iteration see only the jobs made; ``len(videos)`` is the epoch's size.

    Raises:
        KeyError: ``jobs[video]`` for a video not in ``videos``.
    """

    def __init__(self, epoch: int, videos: Union[Set[str], FrozenSet[str]]):
        super().__init__()
        self.epoch, self.videos = epoch, videos

    def __missing__(self, video: str) -> Job:
        if video not in self.videos:
            raise KeyError(video)
        job = self[video] = Job(self.epoch, video)
        return job


@dataclass
class EpochPlan:
    """Every sample of one epoch: jobs, who holds what (records), what is live in batches.
    Per-video indexes keep each update proportional to one file, not the corpus.
    ``crops_per_window``: samples per window (numbers a video's samples, ``SampleKey.at``).
    ``jobs``: a :class:`Jobs` (a plain dict holds every job itself)."""

    epoch: int
    crops_per_window: int = 1
    jobs: Dict[str, Job] = field(default_factory=dict)
    records: Dict[Consumer, Set[SampleKey]] = field(default_factory=dict)
    live: Set[SampleKey] = field(default_factory=set)
    complete: bool = False
    told: bool = False  # some reader was told it is complete: it no longer holds the stream back
    served: bool = False  # this server granted some of its samples (so it knows who has what since)
    #: a complete epoch kept without its jobs (read back from the journal, or pruned to the records of the
    #: consumers that may still resume into it: ``EpochScheduler.prune``): by video, the samples that left a
    #: record since, the only ones it makes again (any other sample is some record's, perhaps one it forgot)
    only: Optional[Dict[str, Set[SampleKey]]] = None
    held: Dict[str, Dict[SampleKey, int]] = field(default_factory=dict)  # video -> sample -> records holding it
    live_by_video: Dict[str, Set[SampleKey]] = field(default_factory=dict)
    open_jobs: Dict[str, None] = field(default_factory=dict)  # videos of jobs queued or running, in epoch order

    # ------------------------------------------------------------------ holdings
    def delivered(self) -> Set[SampleKey]:
        """Every sample some consumer holds (O(samples): for tests and reports)."""
        return {k for ks in self.held.values() for k, n in ks.items() if n > 0}

    def is_delivered(self, key: SampleKey) -> bool:
        """Some record holds ``key`` (in a plan kept without its jobs, :attr:`only`, any key that
        did not leave a record since: perhaps one the plan forgot)."""
        return self.held.get(key.video, {}).get(key, 0) > 0 or (self.only is not None and
                                                                 key not in self.only.get(key.video, ()))

    def have(self, video: str) -> Set[SampleKey]:
        """Samples of ``video`` delivered or live."""
        return {k for k, n in self.held.get(video, {}).items() if n > 0} | self.live_by_video.get(video, set())

    def progress(self) -> Tuple[int, int]:
        """``(videos, done)``: the epoch's videos, and those whose job is done (O(1))."""
        n = len(self.jobs.videos) if isinstance(self.jobs, Jobs) else len(self.jobs)
        return n, n - len(self.open_jobs)

    @classmethod
    def kept(cls, epoch: int, crops_per_window: int, videos, records: Dict[Consumer, Set[SampleKey]],
             served: bool, owed: Iterable[SampleKey] = ()) -> "EpochPlan":
        """A complete, told ``epoch`` of ``videos`` kept without its jobs, holding ``records``, making ``owed``
        again (:attr:`only`: a journal's samples that left a record since the epoch closed)."""
        plan = cls(epoch, crops_per_window, Jobs(epoch, videos), complete=True, told=True, served=served, only={})
        plan._owed_again(owed)
        for consumer, keys in records.items():
            plan.add_record(consumer, keys)
        return plan

    def keep_for(self, keeps: Callable[[Consumer], bool], videos) -> Dict[int, "EpochPlan"]:
        """This complete epoch, forgotten but for the records of the consumers ``keeps`` names
        (those that may still resume into it: docs/delivery.md limit (e)): ``{}`` when there are
        none, else ``{epoch: a plan kept for them alone}`` (:meth:`kept`; this one when it is that already)."""
        kept = {c: r for c, r in self.records.items() if r and keeps(c)}
        if not kept or (self.only is not None and len(kept) == sum(1 for r in self.records.values() if r)):
            return {self.epoch: self} if kept else {}
        return {self.epoch: EpochPlan.kept(self.epoch, self.crops_per_window, videos, kept, self.served)}

    def add_live(self, key: SampleKey) -> None:
        self.live.add(key)
        self.live_by_video.setdefault(key.video, set()).add(key)

    def drop_live(self, key: SampleKey) -> None:
        if key in self.live:
            self.live.discard(key)
            self.live_by_video[key.video].discard(key)

    def set_record(self, consumer: Consumer, keys: Iterable[SampleKey]) -> Set[str]:
        """Replace a consumer's record; returns the videos whose holdings changed."""
        old = self.records.get(consumer, set())
        new = set(keys)
        for k in old - new:
            self.held[k.video][k] -= 1
        self._owed_again(old - new)
        for k in new - old:
            ks = self.held.setdefault(k.video, {})
            ks[k] = ks.get(k, 0) + 1
        self.records[consumer] = new
        return {k.video for k in old ^ new}

    def _owed_again(self, keys: Iterable[SampleKey]) -> None:
        """``keys`` left a record: a plan kept without its jobs may make them again (:attr:`only`)."""
        if self.only is not None:
            for k in keys:
                self.only.setdefault(k.video, set()).add(k)

    def add_record(self, consumer: Consumer, keys: Iterable[SampleKey]) -> None:
        rec = self.records.setdefault(consumer, set())
        for key in keys:
            if key not in rec:
                rec.add(key)
                ks = self.held.setdefault(key.video, {})
                ks[key] = ks.get(key, 0) + 1

    def given_back(self, consumer: Consumer, keys: Iterable[SampleKey]) -> None:
        """``consumer`` gave back a batch of ``keys`` it was granted, and the batch is queued
        again: the keys leave its record and are live again (the epoch is open again)."""
        rec = self.records.get(consumer, set())
        keys = list(keys)
        self._owed_again(keys)
        for k in keys:
            if k in rec:
                rec.discard(k)
                self.held[k.video][k] -= 1
            self.add_live(k)
            self.complete = False

    # ------------------------------------------------------------------ jobs
    def owed_in(self, video: str) -> Set[SampleKey]:
        """Samples of ``video`` still to make: not delivered, live or failed, among the
        samples the file gave (none while that count is unknown)."""
        job = self.jobs[video]
        if self.only is not None:
            have, k = self.have(video), self.crops_per_window
            return {key for key in self.only.get(video, ()) if key not in have and key not in job.failed
                    and (job.samples is None or key.ordinal(k) < job.samples)}
        if job.samples is None:
            return set()
        have = self.have(video)
        k = self.crops_per_window
        return {key for key in (SampleKey.at(video, i, k) for i in range(job.samples))
                if key not in job.failed and key not in have}

    def skip(self, job: Job, count: Optional[int] = None) -> FrozenSet[SampleKey]:
        """What a task of ``job`` must not make: samples delivered, live or failed; in a plan kept
        without its jobs (:attr:`only`), also every other sample of the file's ``count`` (samples
        its last pass gave) when known."""
        skip = self.have(job.video) | set(job.failed)
        if self.only is not None and count is not None:
            owed = self.only.get(job.video, set())
            skip.update(k for k in (SampleKey.at(job.video, i, self.crops_per_window) for i in range(count))
                        if k not in owed)
        return frozenset(skip)

    def set_state(self, job: Job, state: str) -> None:
        if (job.state == "done") != (state == "done"):
            if state == "done":
                self.open_jobs.pop(job.video, None)
            else:
                self.open_jobs[job.video] = None
        job.state = state

    def to_come(self, counts: Dict[str, int], per_video: Optional[int], limit: int) -> Optional[int]:
        """How many samples the queued and running jobs can still bring: each file's count
        (``job.samples`` once known this epoch, else ``counts[video]`` from an earlier pass (a
        file gives the same windows every epoch), else the bound ``per_video``) less its
        samples delivered, live or failed. Stops adding once past ``limit`` (returns a number
        > ``limit``); None when some file's count is unknown before that."""
        total = 0
        for v in self.open_jobs:
            job = self.jobs.get(v)  # None: not handed out yet, no job made (``Jobs``)
            if self.only is not None:  # kept without its jobs: only what left a record is made again
                total += len(self.only.get(v, set()) - self.have(v))
                continue
            n = job.samples if job is not None and job.samples is not None else counts.get(v, per_video)
            if n is None:
                return None
            total += max(0, n - len(self.have(v)) - (len(job.failed) if job is not None else 0))
            if total > limit:
                break
        return total

    def check_complete(self) -> bool:
        """Complete when no job is queued or running and nothing is live (a done job never
        owes anything: ``requeue`` queues it again first)."""
        if self.complete:
            return True
        if self.open_jobs or self.live:
            return False
        self.complete = True
        return True

    def first_unmade(self, job: Job, first: int = 0) -> SampleKey:
        """The first sample of ``job``'s file, numbered ``first`` or later, neither made nor failed."""
        have = self.have(job.video)
        i = max(first, 0)
        while True:
            key = SampleKey.at(job.video, i, self.crops_per_window)
            if key not in have and key not in job.failed:
                return key
            i += 1

    def stop_at(self, job: Job, first: int, reason: str) -> None:
        """The pass over ``job``'s file stopped in the first sample numbered ``first`` or later
        that is neither made nor failed: it fails for this epoch and none beyond it exists."""
        stop = self.first_unmade(job, first)
        job.failed.setdefault(stop, reason)
        job.samples = stop.ordinal(self.crops_per_window) + 1

    def crashed(self, job: Job, max_crashes: int) -> Optional[str]:
        """A worker died during ``job``: the crash is blamed on the first sample of the file
        not yet made. After ``max_crashes`` crashes in that sample it fails for this epoch;
        after twice as many crashes in all the file is given up for the epoch (the job is done,
        ``job.gave_up``, and samples from the failed one on do not exist this epoch). Returns
        the reason of the failure recorded, or None."""
        job.crashes += 1
        stop = self.first_unmade(job)
        n = job.sample_crashes[stop] = job.sample_crashes.get(stop, 0) + 1
        if job.crashes >= 2 * max_crashes:
            job.error = f"worker crashed {job.crashes} times while processing it"
            job.gave_up = True
            self.stop_at(job, stop.ordinal(self.crops_per_window), job.error)
            self.set_state(job, "done")
            return job.error
        if n >= max_crashes:
            job.failed[stop] = f"worker crashed {n} times while making sample {stop.sample_id(self.crops_per_window)}"
            return job.failed[stop]
        return None

    def requeue(self, videos: Iterable[str]) -> List[str]:
        """Done jobs of ``videos`` that owe samples go back to queued (the epoch reopens);
        returns those videos, for the scheduler's queue."""
        out = []
        for v in videos:
            job = self.jobs.get(v)
            if job is None and self.only:  # kept without its jobs: one made as done, to queue if it owes
                job = self.jobs[v]
                job.state = "done"
            if job is not None and job.state == "done" and self.owed_in(v):
                self.set_state(job, "queued")
                out.append(v)
                self.complete = False
        if self.live:
            self.complete = False
        self.check_complete()
        return out


class EpochScheduler:
    """Plans epochs of ``videos`` and tracks every sample of them.

    Args:
        videos: corpus-relative paths (never re-read: the scheduler never opens files).
        epochs: stop after this many epochs (None: unbounded).
        max_task_crashes: crashes blamed on one sample before it fails for the epoch (twice
            as many in one file give the file up for the epoch; see ``worker_lost``).
        lookahead: epochs open beyond the oldest one neither complete nor ``EpochPlan.told``.
        keep_epochs: complete epochs kept so an older resume state can reopen them.
        crops_per_window: samples per window (K of ``ids.py``).
        shuffle_seed: None: the listing's order; an int: ``batcher.video_order(videos, seed, epoch)``.
        max_samples_per_video: windows a file gives at most per epoch (None: unknown), for :meth:`to_come` first.
        first_epoch: the epoch to open first (after a journal's closed ones; it keeps the last ``keep_epochs``).
        kept: older closed epochs it keeps too (a journal's, ``Journal.kept``), each with the samples it makes again.

    Nothing here raises on peer input: what does not name a sample of the task is dropped.
    """

    def __init__(self, videos: Iterable[str], epochs: Optional[int] = None, max_task_crashes: int = MAX_TASK_CRASHES,
                 lookahead: int = 1, keep_epochs: int = KEEP_EPOCHS, crops_per_window: int = 1,
                 shuffle_seed: Optional[int] = None, max_samples_per_video: Optional[int] = None, first_epoch: int = 0,
                 kept: Optional[Dict[int, Set[SampleKey]]] = None):
        self.videos, self.shuffle_seed, self.max_samples_per_video = list(videos), shuffle_seed, max_samples_per_video
        self.counts: Dict[str, int] = {}  # video -> samples its last complete pass gave (any epoch)
        self.known = frozenset(self.videos)
        self.max_epochs, self.max_task_crashes, self.next_epoch = epochs, max_task_crashes, first_epoch
        self.lookahead, self.keep_epochs, self.crops_per_window = lookahead, keep_epochs, crops_per_window
        kept = kept or {}
        self.plans = {e: EpochPlan.kept(e, crops_per_window, self.known, {}, True, kept.get(e, ())) for e in sorted(
            {e for e in kept if e < first_epoch}.union(range(max(0, first_epoch - keep_epochs), first_epoch)))}
        self.queue: Deque[Tuple[int, str]] = collections.deque(
            (e, v) for e, plan in self.plans.items() for v in plan.requeue(list(plan.only)))  # what they make again
        self.running: Dict[int, Job] = {}  # task id -> job
        self._task_ids = itertools.count()
        self.pending_records: Dict[int, Dict[Consumer, Set[SampleKey]]] = {}  # for epochs not opened yet
        self.file_failures: Dict[str, str] = {}  # video -> last reason it failed (for logs and stats)

    # ------------------------------------------------------------------ epochs
    def _open_epoch(self) -> bool:
        if self.max_epochs is not None and self.next_epoch >= self.max_epochs:
            return False
        behind = [e for e, p in self.plans.items() if not (p.complete or p.told)]
        if behind and self.next_epoch - min(behind) > self.lookahead:
            return False
        e = self.next_epoch
        self.next_epoch += 1
        plan = EpochPlan(e, self.crops_per_window, Jobs(e, self.known))
        for consumer, keys in self.pending_records.pop(e, {}).items():
            plan.set_record(consumer, keys)
        order = self.epoch_order(e)
        plan.open_jobs = dict.fromkeys(order)  # every job starts queued
        self.queue.extend((e, v) for v in order)
        self.plans[e] = plan
        plan.check_complete()
        return True

    def epoch_order(self, epoch: int) -> List[str]:
        """The order ``epoch`` hands the videos out in (``batcher.video_order``, or the listing's)."""
        return list(self.videos) if self.shuffle_seed is None else video_order(self.videos, self.shuffle_seed, epoch)

    def finished(self, told: bool = False) -> bool:
        """The last of ``epochs`` epochs is complete (never for unbounded streams); with ``told``,
        an epoch told complete to some reader counts (what a later reader lacks waits for it)."""
        return (self.max_epochs is not None and self.next_epoch >= self.max_epochs
                and all(p.complete or (told and p.told) for p in self.plans.values()))

    def owed(self, epoch: int) -> Set[SampleKey]:
        """Samples of ``epoch`` that must still be made: not delivered, live or failed, in
        videos whose sample count is known (a job not yet run owes its whole file)."""
        p = self.plans.get(epoch)
        if p is None:
            return set()
        return {k for v in p.jobs for k in p.owed_in(v)}

    def to_come(self, epoch: int, limit: int) -> Optional[int]:
        """How many samples ``epoch`` can still make (``EpochPlan.to_come``: each queued
        or running file's count from this epoch's or an earlier pass, else ``max_samples_per_video x
        crops_per_window``); a number > ``limit`` means at least that many, None means unknown.
        0 for an epoch not open."""
        p = self.plans.get(epoch)
        if p is None:
            return 0
        per_video = None if self.max_samples_per_video is None else self.max_samples_per_video * self.crops_per_window
        return p.to_come(self.counts, per_video, limit)

    def prune(self, forgettable: Iterable[int], keeps: Callable[[Consumer, int], bool] = lambda c, e: False) -> None:
        """Forget complete epochs in ``forgettable`` (e.g. announced to clients) except the
        newest ``keep_epochs`` complete ones (an older resume state can still reopen those), but
        for the consumers ``keeps(consumer, epoch)`` names (``EpochPlan.keep_for``)."""
        done = sorted(e for e, p in self.plans.items() if p.complete)
        for e in sorted(set(done[:-self.keep_epochs] if self.keep_epochs > 0 else done) & set(forgettable)):
            self.plans.update(self.plans.pop(e).keep_for(lambda c: keeps(c, e), self.known))

    def _reconcile(self, plan: EpochPlan, videos: Iterable[str]) -> None:
        """Queue again the done jobs of ``videos`` that owe samples."""
        for v in plan.requeue(videos):
            self.queue.append((plan.epoch, v))

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
                if job.samples is not None and not plan.owed_in(v):
                    plan.set_state(job, "done")  # nothing left to make of it (e.g. a resume state covered it)
                    plan.check_complete()
                    continue
                tid = next(self._task_ids)
                plan.set_state(job, "running")
                job.task_id, job.worker, job.last_progress = tid, worker, now
                self.running[tid] = job
                return Task(tid, e, v, plan.skip(job, self.counts.get(v)))
            if not self._open_epoch():
                return None

    def _current(self, task_id, worker) -> Optional[Job]:
        job = self.running.get(task_id) if isinstance(task_id, int) else None
        if job is None or job.worker != worker:
            return None  # a reassigned task's late copy, or a stranger
        return job

    def accept_sample(self, task_id, worker: Hashable, key: SampleKey, now: float) -> Optional[SampleKey]:
        """A worker made sample ``key`` of its task. Returns the key to batch, or None when the
        sample must be dropped (late copy of a reassigned task, already delivered or live,
        failed, or not a sample of that task's video)."""
        job = self._current(task_id, worker)
        if job is None or not isinstance(key, SampleKey) or key.video != job.video:
            return None
        if not 0 <= key.crop < self.crops_per_window or key.window < 0:
            return None
        job.last_progress = now
        plan = self.plans[job.epoch]
        if key in plan.live or plan.is_delivered(key) or key in job.failed:
            return None
        plan.add_live(key)
        return key

    def task_done(self, task_id, worker: Hashable, windows: int, failed: Optional[Dict[int, str]] = None,
                  error: Optional[str] = None) -> Optional[Job]:
        """A worker finished its task: ``windows`` complete windows the file gave (each gives
        ``crops_per_window`` samples), ``failed`` windows that could not be made (window ->
        reason; each fails its crops), ``error`` when the pass stopped early (the first sample
        not made in the window it stopped in counts as failed; later ones do not exist this
        epoch). Window numbers may come as decimal strings (msgpack map keys).
        Returns the job, or None for a late copy."""
        job = self._current(task_id, worker)
        if job is None:
            return None
        del self.running[task_id]
        plan = self.plans[job.epoch]
        job.worker, job.task_id = None, None
        k = self.crops_per_window
        samples = windows * k if isinstance(windows, int) and not isinstance(windows, bool) and windows >= 0 else 0
        for w, why in (failed or {}).items():
            if isinstance(w, str) and w.isascii() and w.isdigit() and len(w) <= 9:
                w = int(w)
            if isinstance(w, int) and not isinstance(w, bool) and w >= 0:
                for key in window_keys(job.video, w, k):
                    job.failed[key] = str(why)
        if error:
            job.error = error
            self.file_failures[job.video] = error
            plan.stop_at(job, samples, error)
        else:
            job.samples = samples if job.samples is None else max(job.samples, samples)
            self.counts[job.video] = job.samples
        plan.set_state(job, "done")
        self._reconcile(plan, {job.video})
        return job

    def worker_lost(self, worker: Hashable) -> Optional[Job]:
        """A worker died (or hung and was replaced) during a job. The crash is blamed on the
        first sample of the file not yet made: after ``max_task_crashes`` crashes in that
        sample it fails for this epoch and the job goes on after it; after twice as many
        crashes in all the file is given up for the epoch (``job.gave_up``: samples from the
        failed one on do not exist this epoch). Otherwise the job goes back to the front of the
        queue. Returns the job, if any."""
        for tid, job in list(self.running.items()):
            if job.worker != worker:
                continue
            del self.running[tid]
            job.worker, job.task_id = None, None
            plan = self.plans[job.epoch]
            reason = plan.crashed(job, self.max_task_crashes)
            if reason is not None:
                self.file_failures[job.video] = reason
            if job.gave_up:
                self._reconcile(plan, {job.video})
            else:
                plan.set_state(job, "queued")
                self.queue.appendleft((job.epoch, job.video))
            return job
        return None

    def expire(self, now: float, task_timeout_s: float) -> List[Tuple[Hashable, Job]]:
        """Jobs whose worker sent nothing for ``task_timeout_s`` (``now``: the clock :meth:`next_task` and
        :meth:`accept_sample` were given, ``feed.TaskClock``): each is reassigned (queued again, counted as a
        crash) and its worker returned so the pool can replace it; anything the old attempt sends is ignored."""
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

    def undelivered(self, consumer: Consumer, epoch: int, keys: Iterable[SampleKey]) -> None:
        """``consumer`` gave back a granted batch of ``keys`` of ``epoch`` unused; it is queued again."""
        if epoch in self.plans:
            self.plans[epoch].given_back(consumer, keys)

    def discarded(self, epoch: int, keys: Iterable[SampleKey]) -> None:
        """Live samples thrown away undelivered (filtered out of a batch): owed again unless
        some consumer already holds them."""
        plan, keys = self._drop_live(epoch, keys)
        if plan is None:
            return
        self._reconcile(plan, {k.video for k in keys})

    def is_delivered(self, epoch: int, key: SampleKey) -> bool:
        plan = self.plans.get(epoch)
        return plan is not None and plan.is_delivered(key)

    def apply_resume(self, consumer: Consumer, completed_epoch: int,
                     delivered: Dict[int, Set[SampleKey]]) -> None:
        """A consumer's resume state (authoritative for that consumer): in every epoch after
        ``completed_epoch``, open or not, its record becomes exactly ``delivered[epoch]``; what it
        had acknowledged beyond that is owed again (a complete epoch reopens). A fresh scheduler (no plan, no
        record of an epoch not opened: a journal's grant) starts at ``completed_epoch + 1`` if it serves that epoch."""
        delivered = {e: {k for k in ks if k.video in self.known} for e, ks in delivered.items()}
        fresh = not self.plans and not self.pending_records
        if fresh and self.next_epoch <= completed_epoch < (self.max_epochs or completed_epoch + 2) - 1:
            self.next_epoch = completed_epoch + 1
        for e, plan in self.plans.items():
            if e <= completed_epoch:
                continue
            changed = plan.set_record(consumer, delivered.get(e, ()))
            self._reconcile(plan, changed)
        for e in set(delivered) | set(self.pending_records):  # an epoch not open yet: its record, kept
            if e > completed_epoch and e >= self.next_epoch:
                self.pending_records.setdefault(e, {})[consumer] = set(delivered.get(e, ()))

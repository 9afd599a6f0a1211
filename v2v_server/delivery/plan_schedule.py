"""Serving by plan, pure: which video an idle worker decodes next, which made samples a server
keeps, and which fetches it can answer. A server is stateless compute: it keeps no record of who
read what, only made samples, and any fetch names its rows itself (epoch and positions of
``v2v_wire.plan.EpochPlan``).

* **Fetches.** A client asks for positions ``start .. stop - 1`` of an epoch (one rank's batch
  at one step). A fetch is answered when each of its positions has its sample made, failed for
  this epoch (the decode gave fewer windows than the manifest's slots, or the pass broke) or lies
  past the epoch's end: the last two are padding rows.
* **Tasks.** A task is one video of one epoch (a decode makes a video's samples in order: each
  video is decoded once per epoch while its samples are kept). An idle worker gets the first video
  (in the order of the positions that need it) that a pending fetch needs a sample of; else the
  next video the positions after the furthest fetch need (past an epoch's end, the next epoch's
  first ones), while the samples made ahead and not yet fetched, with those the running tasks
  will make, stay within ``lookahead`` samples: the fetches to come find their samples made, the
  workers stay busy across an epoch's end, and a server holds a bounded number of samples.
  Each reader (a rank, a DataLoader worker: a connection of its own) has its own head and reads
  its own items: what lies ahead of one head another reader was answered (:meth:`Heads.read`) is
  neither made ahead for it nor made by a decode again.
* **Hedging.** A task that sent nothing for ``hedge_s`` while a fetch waits on it is handed to
  a second idle worker too; a sample's content is a function of (seed, epoch, id), so the first
  copy of each sample wins and the other is dropped.
* **Keeping.** Made samples wait in a store until fetched. Fetched ones stay, least recently
  fetched first out, while there are at most ``keep_samples`` of them (another job, a fetch asked
  again after a lost reply). Samples never fetched go once the store holds more than
  ``keep_samples + lookahead`` and the largest video's samples besides those pending fetches
  name (a batch asked is not made ahead) and those of the videos of unknown slots decoded while a
  fetch waited on the plan to unfold (each worker took one: they are that fetch's, read in
  production order), those no pending fetch names, in the order readers
  need them last (Belady's rule): first those of epochs no fetch named for :data:`IDLE_S` (a job
  that left), then those no moving head reaches (behind every reader's last fetch, or reached by
  idle heads only: a job cut off), then the furthest from the nearest moving head before them
  (:class:`Heads`; where every head of an epoch is idle and none of the epoch before reaches it,
  its furthest fetch: a job paused, which reads on from there). A decode makes a whole video,
  whose samples the shuffle buffer spreads over positions far apart: dropping the oldest would
  drop what the plan reaches next, and decode its video again. A fetch whose sample went makes
  it again. Stock a moving head reaches only past ``lookahead`` and a shuffle buffer (made for a
  job cut off mid-epoch, ahead of the job started after it) is kept beside that bound, up to as
  many samples again: it is read when the new job's head reaches it, where dropping it would
  decode its videos twice in the epoch. A sample a plan still unfolding has not placed yet counts
  at its place in the production order (the shuffle buffer draws a sample about there:
  :func:`production_places`), and is kept where no head moves (it is read next); those of the
  videos a pending fetch waits on to unfold the plan are that fetch's. The next epoch's samples,
  before any reader fetched it (or where only a job cut off did), lie past the end of the epoch
  the heads read: they reach them there.
* **Unfolding.** A video whose slots the manifest does not know gets them from its first decode
  that ends (:meth:`PlanScheduler.learn`: the windows it found), and every plan kept unfolds with them
  (``EpochPlan.learn``). A fetch of positions not decided yet waits on the next videos of the
  production order (:func:`unfolding`), decoded in turn: nothing is read but what is served.
* **A pass that stops on an error** (``cause`` ``"error"``: a store that fails past its library's
  retries, a decoder error) is asked again while fewer than :data:`PASS_ATTEMPTS` passes of that
  video in a row stopped so; the next pass skips the samples made. Only then are the samples it
  lacks failed for the epoch, and a video whose slots are not known learns them from the most
  windows those passes gave: a pass cut short by a store that fails for a while never fixes a
  video's slots, so a server started again lists the same samples (a file that breaks at one
  place breaks there each time). A short or static file (``"short"``, ``"static"``) is its own
  verdict, never asked again.
* **A decode that gives more samples than the manifest's slots** is an error naming the video
  (:class:`SlotsExceeded`): the corpus index is stale, never a silent drop.

Nothing here owns a socket, a clock or a process (``now`` is passed in); ``tests/test_plan_schedule.py``
drives it with a seeded world of workers that stall, die and lag.
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Hashable, Iterator, List, Mapping, Optional, Sequence, Set, Tuple

import numpy as np

from v2v_wire.ids import SampleKey
from v2v_wire.plan import EpochPlan, Manifest
from v2v_wire.worker_messages import Task

from .plan_orders import Order, Orders

#: Plans a server keeps built, more while pending fetches or running tasks name more epochs:
#: those are always kept (a plan of a million videos takes about 2 s to build: one rebuilt for
#: each fetch would make a fetch's cost grow with the epochs read at once); the failures of an
#: epoch whose plan goes are forgotten with it.
PLANS_KEPT = 4


#: Passes of a video in a row that may stop on an error before the samples they lack fail for the
#: epoch (module docstring): the storage libraries retry each read ``store_max_attempts`` times
#: already, so a pass that still stops is asked again a few times, not forever (a file broken at
#: one place costs this many passes once per server, then one per epoch).
PASS_ATTEMPTS = 3

#: Seconds after an epoch's last fetch its samples made but never fetched may go (a job that left).
IDLE_S = 600.0

#: Epochs whose samples made a server counts (the latest): what its readers made of each epoch,
#: against what they read of it, says whether a sample was made twice (``stream_info``'s ``feed``).
EPOCHS_COUNTED = 16

#: Readers' heads tracked (:class:`Heads`), the least recently moved out past it: two epochs'
#: for each reader of a job of 32 (8 ranks x 4 DataLoader workers).
HEADS_KEPT = 64
#: A head is idle (its reader stopped, or left) once, with no fetch pending, it asked nothing and
#: was answered nothing for this many of its own intervals between fetches, and for at least
#: :data:`HEAD_IDLE_S`: a sample only idle heads reach is one no reader needs soon.
HEAD_IDLE_INTERVALS = 4
HEAD_IDLE_S = 2.0
#: Seconds within which the readers of one job make their first fetch of an epoch (its ranks'
#: DataLoader workers start together); a job started after another was cut off, or resumed in new
#: processes, starts later than that after the old one's readers did (:meth:`Heads.read`).
JOB_START_S = 5.0
#: Epochs whose positions' answer times are kept (:meth:`Heads.read`), the latest answered: as
#: many as the plans kept, each array as long as its plan's furthest position answered (8 bytes a
#: position, as the plan's own production index).
ANSWERED_EPOCHS = PLANS_KEPT



class SlotsExceeded(ValueError):
    """A worker's decode gave a sample past its video's slots in the manifest (the message
    names the video, the sample and the slots)."""


@dataclass
class Pending:
    """A client's fetch of positions ``start .. stop - 1`` of ``epoch``, waiting for its rows."""

    client: Hashable
    request: int
    epoch: int
    start: int
    stop: int
    decided: Optional[List[Optional[SampleKey]]] = field(default=None, repr=False, compare=False)

    def unfolds(self, plan: EpochPlan) -> bool:
        """It asks positions ``plan`` (its epoch's) has not decided yet: it waits on the plan to
        unfold (:func:`unfolding`)."""
        return not plan.complete and self.stop > plan.known

    def keys(self, plan: EpochPlan) -> List[Optional[SampleKey]]:
        """The keys of its positions ``plan`` (its epoch's) decided, from ``start`` on (None past the
        epoch's end); kept once every one is (what a plan says of a position never changes), so a
        fetch waiting looks its keys up once, not at each turn."""
        if self.decided is not None:
            return self.decided
        stop = self.stop if plan.complete else min(self.stop, plan.known)
        keys = [plan.key(p) for p in range(self.start, stop)]
        if stop == self.stop:
            self.decided = keys
        return keys


@dataclass
class Row:
    """One row of an answered fetch: the sample (``key``, ``sample``: what ``build`` made) or
    padding (``key`` None past the epoch's end; ``reason`` for a sample the decode did not give)."""

    position: int
    key: Optional[SampleKey]
    sample: Any = None
    reason: Optional[str] = None

    @property
    def padding(self) -> bool:
        return self.sample is None


@dataclass
class Run:
    """One video of one epoch being decoded: its copies (task id -> worker) and when each last
    sent something."""

    epoch: int
    video: str
    copies: Dict[int, Hashable] = field(default_factory=dict)
    progress: Dict[int, float] = field(default_factory=dict)
    skips: Dict[int, Set[Tuple[int, int]]] = field(default_factory=dict)  # task id -> (window, crop) not asked of it
    made: Set[Tuple[int, int]] = field(default_factory=set)  # (window, crop) its copies made: a hedge skips them
    error: Optional[str] = None  # why the last pass that ended stopped early

    def end(self, task_id: int) -> None:
        """Copy ``task_id`` ended."""
        for d in (self.copies, self.progress, self.skips):
            d.pop(task_id, None)


@dataclass
class Head:
    """Where one reader reads an epoch: the furthest stop it asked, when it last asked or was
    answered (s), the mean seconds between its fetches (0 until its second), and when (s) and
    where (the start of) its first fetch was."""

    stop: int
    at: float
    interval: float = 0.0
    since: float = 0.0  # its first fetch (s)
    first: int = 0  # its first fetch's start: a reader reads on from there, never before it


class Heads:
    """Each reader's head in each epoch it reads, from its fetches (a reader is a fetch's
    ``client``: one rank or DataLoader worker): what the server keeps and makes follows the
    heads that move (:func:`trim`, :meth:`PlanScheduler._start`), not the furthest fetch alone,
    so a job cut off mid-epoch leaves no claim on the store once its head is idle."""

    def __init__(self):
        self.heads: "OrderedDict[Tuple[Hashable, int], Head]" = OrderedDict()
        # epoch -> each position's latest answer (s; -inf: never), the ANSWERED_EPOCHS latest answered
        self.answers: "OrderedDict[int, np.ndarray]" = OrderedDict()

    def fetched(self, client: Hashable, epoch: int, stop: int, now: float, start: int = 0) -> None:
        """``client`` asked positions ``start`` up to ``stop`` of ``epoch`` at ``now`` (s)."""
        h = self.heads.pop((client, epoch), None)
        if h is None:
            h = Head(stop, now, since=now, first=start)
        else:
            gap = max(0.0, now - h.at)
            # the furthest stop: a reader's fetches in flight, and one asked again, end anywhere behind it
            h.stop, h.at, h.interval = max(h.stop, stop), now, gap if not h.interval else 0.75 * h.interval + 0.25 * gap
        self.heads[(client, epoch)] = h
        while len(self.heads) > HEADS_KEPT:
            self.heads.popitem(last=False)

    def forget(self, client: Hashable) -> None:
        """``client`` left: its heads go."""
        for k in [k for k in self.heads if k[0] == client]:
            del self.heads[k]

    def answered(self, client: Hashable, epoch: int, now: float, start: int = 0, stop: int = 0) -> None:
        """A fetch of ``client`` in ``epoch`` was answered at ``now`` (s) with positions ``start ..
        stop - 1``: its idle time counts from here, and each position's answer time is noted
        (:meth:`read`)."""
        h = self.heads.get((client, epoch))
        if h is not None:
            h.at = max(h.at, now)
        if stop > start:
            times = self.answers.pop(epoch, None)
            if times is None or len(times) < stop:
                grown = np.full(max(stop, 2 * (0 if times is None else len(times))), -np.inf)
                if times is not None:
                    grown[:len(times)] = times
                times = grown
            times[start:stop] = now
            self.answers[epoch] = times
            while len(self.answers) > ANSWERED_EPOCHS:
                self.answers.popitem(last=False)

    def read(self, epoch: int, now: float, waiting: Set[Hashable] = frozenset()) -> Callable[[int], bool]:
        """Whether a position of ``epoch`` was read by the job reading now: one reader of a job
        was given it, which the others never ask (each reads its own items) though it lies ahead
        of their heads. The readers of one job start together (within :data:`JOB_START_S`), so
        a head that appeared later is a new job's (one started after another was cut off, or a
        job resumed in new processes), which reads on from its readers' first fetches: a
        position counts when it was answered since the newest job's first fetch, or at all
        where it lies before that job's first position (the new job never reads it); where no
        head moves (its readers paused), any answered. Every position of the epoch counts,
        however long ago its reader passed it: a head left behind (an old job's, idle only after
        a few of its intervals) must not make ahead what the new job read, nor what the old job
        read before the new one's start."""
        times, live = self.answers.get(epoch), self._moving(epoch, now, waiting)
        if times is None:
            return lambda p: False
        newest = max((h.since for h in live), default=-np.inf)
        job = [h for h in live if h.since >= newest - JOB_START_S]  # the newest job's readers
        since, first = min((h.since for h in job), default=-np.inf), min((h.first for h in job), default=0)
        return lambda p: 0 <= p < len(times) and times[p] > -np.inf and (times[p] >= since or p < first)

    def moving(self, epoch: int, now: float, waiting: Set[Hashable] = frozenset()) -> List[int]:
        """The stops of ``epoch``'s heads that are not idle at ``now``: those of the ``waiting``
        clients (a fetch of theirs is pending), and those asked or answered within
        :data:`HEAD_IDLE_INTERVALS` of their intervals and :data:`HEAD_IDLE_S`."""
        return [h.stop for h in self._moving(epoch, now, waiting)]

    def _moving(self, epoch: int, now: float, waiting: Set[Hashable]) -> List[Head]:
        return [h for (c, e), h in self.heads.items()
                if e == epoch and (c in waiting or now - h.at <= max(HEAD_IDLE_S, HEAD_IDLE_INTERVALS * h.interval))]


class Making:
    """The outputs workers make: those the fetches so far asked for, of ``offered`` (in its
    order); and each running task's, so that the
    samples of a task started before an output was asked for are dropped as they come.

    Args:
        offered: the outputs workers may make (``protocol.OUTPUTS`` order).
    """

    def __init__(self, offered: Sequence[str]):
        self.offered = tuple(offered)
        self.now: Tuple[str, ...] = ()
        self.tasks: Dict[int, Tuple[str, ...]] = {}  # running task id -> the outputs it makes

    def ask(self, outputs: Optional[Sequence[str]]) -> bool:
        """A fetch asks for ``outputs`` (None: every one offered). Returns True when that widens
        what workers make (the samples made so far lack an output).

        Raises:
            ValueError: an output not offered, naming it."""
        asked = self.offered if outputs is None else tuple(outputs)
        if not set(asked) <= set(self.offered):
            raise ValueError(f"fetch outputs {sorted(set(asked) - set(self.offered))}: not among {list(self.offered)}")
        if set(asked) <= set(self.now):
            return False
        self.now = tuple(o for o in self.offered if o in asked or o in self.now)
        return True

    def start(self, task_id: int) -> Tuple[str, ...]:
        """The outputs task ``task_id``, starting now, makes."""
        self.tasks[task_id] = self.now
        return self.now


def spare_samples(store: Sequence, fetched: Set, named: Set, live: Set[int], count: int,
                  reached: Callable[[Tuple[int, SampleKey]], Optional[int]] = lambda sk: None) -> List:
    """The ``count`` samples of ``store`` (keys ``(epoch, key)``, oldest first) to drop, never
    fetched and named by no pending fetch, in the order a reader needs them last (Belady's rule):
    those of epochs not in ``live`` (no fetch for :data:`IDLE_S`: a job that left), then those no
    reader reaches any more (``reached`` None: behind every moving head of a live epoch, or of an
    epoch whose plan went), oldest first within each; then those a reader reaches, the furthest
    (``reached``: positions from the nearest moving head before it, :class:`Heads`) first."""
    def order(sk):
        if sk[0] not in live:
            return 0, 0
        d = reached(sk)
        return (1, 0) if d is None else (2, -d)
    spare = [sk for sk in store if sk not in named and sk not in fetched]
    return sorted(spare, key=order)[:count]  # stable: oldest first within a class


def positions_after(plan_of: Callable[[int], EpochPlan], kept: Mapping[int, EpochPlan], epoch: int, stop: int,
                    count: int, keep: Set[int] = frozenset()) -> Iterator[Tuple[int, str, Optional[SampleKey]]]:
    """(epoch, video, key) of the ``count`` positions of ``epoch`` from ``stop`` on (``plan_of``:
    an epoch's plan; ``kept``: the plans built); where the plan is not decided that far, (epoch,
    video, None) for the videos whose slots unfold it next, in order; past the epoch's end, the
    next epoch's first ones (a trainer reads its epochs in turn: decoding them while it reads the
    end of this one keeps the workers busy across the boundary), unless every kept plan is one of
    ``keep`` (the epochs pending fetches and running tasks name, and those read ahead of): a plan
    built for it would then drop one in use, to be built again."""
    plan = plan_of(epoch)
    yield from _positions(plan, stop, count)
    if plan.complete:
        rest = stop + count - max(stop, len(plan))
        room = epoch + 1 in kept or len(kept) < PLANS_KEPT or any(e not in keep for e in kept)
        if rest > 0 and len(plan) and room:
            yield from _positions(plan_of(epoch + 1), 0, rest)


def _positions(plan: EpochPlan, start: int, count: int) -> Iterator[Tuple[int, str, Optional[SampleKey]]]:
    """(epoch, video, key) of positions ``start`` .. ``start + count - 1`` of ``plan`` that are
    decided and hold a sample; then, where they are not decided, (epoch, video, None) for the
    videos that unfold it next."""
    for p in range(start, min(plan.known, start + count)):
        key = plan.key(p)
        yield plan.epoch, key.video, key
    if not plan.complete and start + count > plan.known:
        for v in plan.next_videos(start + count - max(start, plan.known)):
            yield plan.epoch, v, None


def pass_ended(stopped: Dict[str, Tuple[int, int]], video: str, windows: int, cause: str) -> Optional[int]:
    """A pass of ``video`` that gave ``windows`` ended with ``cause`` (``worker_messages.CAUSES``):
    None while it is to be asked again (it stopped on an error, one of fewer than
    :data:`PASS_ATTEMPTS` in a row), else the windows the video's slots are learned from (the most
    that pass or the ones before it in a row gave). ``stopped``: video -> (passes in a row that
    stopped on an error, the most windows they gave), updated."""
    if cause != "error":
        stopped.pop(video, None)
        return windows
    passes, most = stopped.get(video, (0, 0))
    stopped[video] = passes + 1, max(most, windows)
    return None if passes + 1 < PASS_ATTEMPTS else max(most, windows)


class Slots:
    """Each video's samples per epoch as a server knows them: the manifest's (the corpus index's
    counts), then each other video's from its first decode (:meth:`learn`).

    Attributes:
        windows: video -> its slots (windows), None while not known.
        samples: video -> its samples per epoch (slots x crops per window), None while not known.
        largest: the most samples a known video gives.
        unknown: how many videos' slots are not known.
    """

    def __init__(self, manifest: Manifest):
        self.kpw = manifest.crops_per_window
        self.windows: Dict[str, Optional[int]] = dict(manifest.slots)
        self.samples = {v: None if n is None else n * self.kpw for v, n in manifest.slots}
        self.largest = max((n for n in self.samples.values() if n), default=0)
        self.unknown = sum(1 for n in self.samples.values() if n is None)
        self._total: Optional[int] = None

    def expected(self, video: str) -> int:
        """Samples ``video`` gives per epoch: its own, or while not known the largest known."""
        n = self.samples.get(video, 0)
        return max(self.largest, self.kpw) if n is None else n

    def learn(self, video: str, windows: int) -> None:
        """``video``'s slots are ``windows``."""
        self.unknown -= self.windows[video] is None
        self.windows[video], self.samples[video] = windows, windows * self.kpw
        self.largest = max(self.largest, windows * self.kpw)

    @property
    def epoch_samples(self) -> Optional[int]:
        """Samples every epoch lists, once every video's slots are known; None before."""
        if self.unknown:
            return None
        if self._total is None:
            self._total = sum(self.samples.values())
        return self._total


def made_by_video(s: "PlanScheduler") -> Dict[Tuple[int, str], int]:
    """(epoch, video) -> the samples of it scheduler ``s`` holds made or failed (its store and
    its failed samples)."""
    made: Dict[Tuple[int, str], int] = {}
    for (e, k) in list(s.store) + list(s.failed):
        made[(e, k.video)] = made.get((e, k.video), 0) + 1
    return made


def unfolding(plan: EpochPlan, stop: int, slots: Slots, made: Mapping[Tuple[int, str], int]) -> List[Tuple[int, str]]:
    """(epoch, video) of the next videos of ``plan``'s production order whose slots would decide
    its positions up to ``stop`` (by their expected samples), less those whose samples are all
    made (``made``: samples made or failed per (epoch, video))."""
    i, counted = plan.counted
    deficit, out = plan.made_by(stop) + 1 - counted, []
    while deficit > 0 and i < len(plan.videos):
        v = plan.videos[i]
        if slots.samples.get(v) is None or made.get((plan.epoch, v), 0) < slots.samples[v]:
            out.append((plan.epoch, v))
        deficit -= slots.expected(v)
        i += 1
    return out


class PlanScheduler:
    """The server's scheduler when serving by plan: which video an idle worker decodes next,
    which made samples it keeps, which fetches it answers (module docstring).

    Args:
        manifest: the corpus's slots (``v2v_wire.plan.Manifest``).
        seed, shuffle_buffer: the plan's (``EpochPlan``).
        outputs: the outputs workers may make (``protocol.OUTPUTS`` order; :class:`Making`).
        lookahead: samples a server makes ahead of the fetches (made or being made, not yet fetched).
        keep_samples: fetched samples kept for other fetches (least recently used out).
        hedge_s: seconds a task may send nothing while a fetch waits before another worker takes it too.
        task_timeout_s: seconds a task may send nothing before its worker is called hung.

    Raises:
        ValueError: a setting out of range, naming it.
    """

    def __init__(self, manifest: Manifest, seed: int, shuffle_buffer: int, outputs: Sequence[str],
                 lookahead: int = 64, keep_samples: int = 64, hedge_s: float = 30.0, task_timeout_s: float = 300.0):
        for name, v in (("lookahead", lookahead), ("keep_samples", keep_samples)):
            if v < 0:
                raise ValueError(f"{name} must be >= 0, got {v}")
        if not 0 < hedge_s <= task_timeout_s:
            raise ValueError(f"hedge_s must be > 0 and <= task_timeout_s, got {hedge_s} and {task_timeout_s}")
        self.manifest, self.seed, self.shuffle_buffer = manifest, seed, shuffle_buffer
        self.slots, self.making = Slots(manifest), Making(outputs)
        self.lookahead, self.keep_samples = lookahead, keep_samples
        self.hedge_s, self.task_timeout_s = hedge_s, task_timeout_s
        self.plans: "OrderedDict[int, EpochPlan]" = OrderedDict()
        self.pending: List[Pending] = []
        self.orders = Orders(manifest.crops_per_window)  # a fleet's makes (plan_orders)
        self.store: "OrderedDict[Tuple[int, SampleKey], Any]" = OrderedDict()  # made, oldest or least recently fetched first
        self.fetched: Set[Tuple[int, SampleKey]] = set()  # stored samples some fetch was answered with
        self.failed: Dict[Tuple[int, SampleKey], str] = {}  # not given by its decode this epoch
        self.runs: Dict[Tuple[int, str], Run] = {}
        self.task_run: Dict[int, Tuple[int, str]] = {}
        self.fetched_at, self.fetched_to = {}, {}  # epoch -> when a fetch last named it; the furthest stop one named
        self.heads = Heads()
        self.stopped: Dict[str, Tuple[int, int]] = {}  # video -> (passes in a row that stopped on an error, most windows)
        self.passed: Dict[Tuple[int, str], Set[Tuple[int, int]]] = {}  # (epoch, video) asked again -> made before
        # (epoch, video) of unknown slots decoded while a fetch waited on the plan to unfold: its
        # samples are that fetch's, kept past the bound until fetched (trim)
        self.unfolded: Set[Tuple[int, str]] = set()
        # tasks started; samples made; EpochPlans built (one per epoch read, however many at once)
        self._task_ids = self.samples_made = self.plans_built = 0
        self.epoch_made: Dict[int, int] = {}  # epoch -> samples made of it, the EPOCHS_COUNTED latest

    # ------------------------------------------------------------------ plans and fetches
    def plan(self, epoch: int) -> EpochPlan:
        """The plan of ``epoch``, built on first use, kept while a pending fetch or a running task
        names its epoch (others go, least recently used first, past :data:`PLANS_KEPT`)."""
        p = self.plans.get(epoch)
        if p is None:
            p = self.plans[epoch] = EpochPlan(self.manifest, self.seed, epoch, self.shuffle_buffer)
            self.plans_built += 1
            if not p.complete:
                p.learn(self.slots.windows)
            named = {f.epoch for f in self.pending} | {e for e, _ in self.runs} | {epoch}
            for gone in [e for e in self.plans if e not in named][:max(0, len(self.plans) - PLANS_KEPT)]:
                del self.plans[gone]  # least recently used first
                self.failed = {sk: why for sk, why in self.failed.items() if sk[0] != gone}
        else:
            self.plans.move_to_end(epoch)
        return p

    def fetch(self, client: Hashable, request: int, epoch: int, start: int, stop: int, now: float,
              outputs: Optional[Sequence[str]] = None) -> None:
        """Queue a fetch of positions ``start .. stop - 1`` of ``epoch`` and ``outputs`` (default:
        every one of ``outputs``), asked at ``now`` (s). An output no fetch asked for before widens
        what workers make: the samples kept lack it, so they go, and the running tasks' samples
        are dropped as they come (their videos are decoded again with it).

        Raises:
            ValueError: ``start`` < 0 or ``stop`` <= ``start``, or more than 4096 positions; an
                output not in ``outputs``.
        """
        if not 0 <= start < stop or stop - start > 4096:
            raise ValueError(f"fetch positions {start}..{stop - 1}: must be 1 to 4096 positions from >= 0")
        if self.making.ask(outputs):  # what is kept lacks an output
            self.store, self.fetched = OrderedDict(), set()
        self.plan(epoch)
        self.pending.append(Pending(client, request, epoch, start, stop))
        self.fetched_at[epoch], self.fetched_to[epoch] = now, max(self.fetched_to.get(epoch, 0), stop)
        self.heads.fetched(client, epoch, stop, now, start)

    def make(self, client: Hashable, request: int, epoch: int, video: str, ordinals: Optional[Sequence[int]],
             now: float, outputs: Optional[Sequence[str]] = None, position: int = 0) -> int:
        """Queue a make of the samples ``ordinals`` of ``video`` in ``epoch`` (None: its windows
        only, answered once its slots are known, from the corpus index or its decode), asked at
        ``now``: a reader of a fleet routes each video to a host (``v2v_wire.fleet``). The videos
        made for are decoded after those pending fetches wait on, in the order of (epoch,
        ``position``: the first position needing the video), then of arrival. Outputs as :meth:`fetch`.
        Returns the samples newly asked (``Orders.add``: not a retry's).

        Raises:
            ValueError: a video not in the manifest, or an ordinal past its samples where they
                are known (naming them); an output not offered.
        """
        new = self.orders.add(Order(client, request, epoch, video, None if ordinals is None else tuple(ordinals),
                                    position), self.slots.samples)
        if self.making.ask(outputs):
            self.store, self.fetched = OrderedDict(), set()
        self.fetched_at[epoch] = now
        return new

    def place(self, epoch: int, video: str, route: Optional[str], now: float,
              move: bool = False) -> Tuple[Optional[str], List[Order]]:
        """Where a make of ``video`` in ``epoch`` with ``route`` and ``move`` (``Make``) is made,
        None here (``Orders.place``), and the makes waiting here on it that a move placed
        elsewhere with it, each to be answered ``Moved`` (``Orders.take``). A video is started
        here once a worker decodes it or its samples are stored: it stays."""
        started = move and ((epoch, video) in self.runs or any(e == epoch and k.video == video for e, k in self.store))
        to = self.orders.place(epoch, video, route, now, move, started)
        return to, self.orders.take(epoch, video) if to is not None and move else []

    @property
    def reach(self) -> int:
        """Positions past a moving head its reader's samples are made ahead for: ``lookahead``
        and a shuffle buffer (a decode makes a whole video, whose samples the buffer spreads)."""
        return self.lookahead + self.shuffle_buffer

    def queued(self) -> int:
        """Samples every reader's makes ask that are not made yet (``Orders.queued``): what a
        host says its readers in each answer to a make and to a ``plan_ask``."""
        return self.orders.queued(self.slots.expected)

    def withdraw(self, of: Callable[[Hashable], bool], request: int) -> None:
        """Drop the make ``request`` of the client ``of`` matches (``plan_messages.Withdraw``: its
        samples were had elsewhere) while it waits: its video is decoded only for the makes and
        fetches still waiting on it. A decode started goes on."""
        self.orders.withdraw(of, request)

    def forget(self, client: Hashable) -> None:
        """Drop ``client``'s pending fetches and makes (it left)."""
        self.pending = [f for f in self.pending if f.client != client]
        self.orders.forget(client)
        self.heads.forget(client)

    def answer(self, now: float) -> List[Tuple[Any, List[Row]]]:
        """Every pending fetch and make that can be answered at ``now``, with its rows
        (:class:`Pending` or :class:`Order`); they leave the queue, and their samples move to the
        store's fetched end."""
        out, waiting, ordered = [], [], []
        for f in self.pending + self.orders.waiting:
            rows = self._rows(f) if isinstance(f, Pending) else self._order_rows(f)
            if rows is None:
                (waiting if isinstance(f, Pending) else ordered).append(f)
                continue
            out.append((f, rows))
            if isinstance(f, Order):
                self.orders.answered(f, now)
            else:  # positions past the plan's decided ones hold no sample: a fetch far past the end costs nothing
                known = self.plans[f.epoch].known if f.epoch in self.plans else f.start
                self.heads.answered(f.client, f.epoch, now, f.start, max(f.start, min(f.stop, known)))
            for r in rows:
                if r.sample is not None:
                    self.store.move_to_end((f.epoch, r.key))
                    self.fetched.add((f.epoch, r.key))
        self.pending, self.orders.waiting = waiting, ordered
        trim(self, now)
        return out

    def _order_rows(self, o: Order) -> Optional[List[Row]]:
        rows = self.orders.rows(o, self.store, self.failed, self.slots.samples)
        return None if rows is None else [Row(i, key, sample, reason) for i, key, sample, reason in rows]

    def _rows(self, f: Pending) -> Optional[List[Row]]:
        plan = self.plan(f.epoch)
        rows = []
        if f.unfolds(plan):
            return None  # not decided yet
        for p, key in zip(range(f.start, f.stop), f.keys(plan)):
            if key is None:
                rows.append(Row(p, None))
                continue
            sk = (f.epoch, key)
            if sk in self.store:
                rows.append(Row(p, key, self.store[sk]))
            elif sk in self.failed:
                rows.append(Row(p, key, reason=self.failed[sk]))
            else:
                return None
        return rows

    # ------------------------------------------------------------------ workers
    def task_for(self, worker: Hashable, now: float, codecs: Sequence[str] = ()) -> Optional[Task]:
        """The task for an idle ``worker``: the first video a pending fetch waits on; else a
        hedge of one that sent nothing for ``hedge_s`` while a fetch waits on it; else the next
        video to decode ahead; None when none."""
        waited, ahead = needed(self, now)
        waited += [ek for ek in self.orders.videos(self.store, self.failed, self.slots.samples)
                   if ek not in waited]  # makes: after fetches, by position
        for ek in waited:
            if ek not in self.runs:
                return self._start(ek, worker, now, codecs)
        for ek in waited:
            run = self.runs[ek]
            if len(run.copies) == 1 and worker not in run.copies.values() and \
                    now - max(run.progress.values()) >= self.hedge_s:
                return self._start(ek, worker, now, codecs)
        return self._start(ahead[0], worker, now, codecs) if ahead else None

    def _start(self, ek: Tuple[int, str], worker: Hashable, now: float, codecs: Sequence[str]) -> Task:
        epoch, video = ek
        self._task_ids += 1
        tid = self._task_ids
        run = self.runs.get(ek)
        if run is None:  # a pass asked again after one stopped on an error skips what those made
            run = self.runs[ek] = Run(epoch, video, made=self.passed.pop(ek, set()))
        run.copies[tid], run.progress[tid] = worker, now
        self.task_run[tid] = ek
        if self.slots.samples.get(video) is None and any(f.epoch == epoch and f.unfolds(self.plan(epoch))
                                                         for f in self.pending):
            self.unfolded.add(ek)
        skip = {(k.window, k.crop) for (e, k) in list(self.store) + list(self.failed) if e == epoch and k.video == video}
        skip |= run.made  # made by the copy it hedges, and read already: not made again
        skip |= self._read_by_all(epoch, video, now)
        run.skips[tid] = skip
        return Task(tid, epoch, video, self.making.start(tid), tuple(sorted(skip)), tuple(codecs))

    def _read_by_all(self, epoch: int, video: str, now: float) -> Set[Tuple[int, int]]:
        """(window, crop) of ``video``'s samples in ``epoch`` at decided positions behind every
        moving head of the epoch (:class:`Heads`) or answered to a reader (:meth:`Heads.read`:
        the other readers of its job never ask them), named by no pending fetch, where no make
        waits on the video: read already, so a decode asked again for a sample dropped before its
        fetch (or asked again by a reader going back), or for the next items of a slow reader,
        makes only the samples still to be read."""
        waiting = {f.client for f in self.pending}
        plan, heads, n = self.plans.get(epoch), self.heads.moving(epoch, now, waiting), self.slots.samples.get(video)
        read = self.heads.read(epoch, now, waiting)
        if plan is None or not (heads or epoch in self.heads.answers) or not n or \
                any(o.epoch == epoch and o.video == video for o in self.orders.waiting):
            return set()
        behind = min(heads, default=0)
        asked = [(f.start, f.stop) for f in self.pending if f.epoch == epoch]
        out = set()
        for i in range(n):
            key = SampleKey.at(video, i, self.manifest.crops_per_window)
            p = plan.position(key)
            if p is not None and (p < behind or read(p)) and \
                    not any(a <= p < b for a, b in asked):
                out.add((key.window, key.crop))
        return out

    def sample(self, worker: Hashable, task_id: int, key: SampleKey, now: float, build: Callable) -> bool:
        """Worker ``worker`` sent sample ``key`` of task ``task_id``; ``build()`` makes the sample
        object (called only when the sample is wanted). Returns True when it was kept: False for
        a task that is not running (late, lost) or a sample another copy gave first.

        Raises:
            SlotsExceeded: ``key`` lies past its video's slots in the manifest."""
        ek = self.task_run.get(task_id)
        if ek is None or self.runs[ek].copies.get(task_id) != worker or key.video != ek[1]:
            return False
        run = self.runs[ek]
        run.progress[task_id] = now
        sk = (ek[0], key)
        kpw = self.manifest.crops_per_window
        slots = self.slots.samples.get(key.video, 0)
        if slots is not None and key.ordinal(kpw) >= slots:
            raise SlotsExceeded(f"{key.video}: the decode gave {key.sample_id(kpw)}, past the manifest's "
                                f"{slots // kpw} window(s) for it (a stale corpus index, or a file changed in place)")
        if sk in self.store or (key.window, key.crop) in run.made or \
                self.making.tasks.get(task_id) != self.making.now:  # made already (kept, or read), or lacks an output
            return False
        self.failed.pop(sk, None)
        self.store[sk] = build()
        run.made.add((key.window, key.crop))
        self.samples_made += 1
        self.epoch_made[ek[0]] = self.epoch_made.get(ek[0], 0) + 1
        if len(self.epoch_made) > EPOCHS_COUNTED:
            del self.epoch_made[min(self.epoch_made)]
        return True

    def done(self, worker: Hashable, task_id: int, windows: int, failed: Dict[int, str],
             error: Optional[str], cause: str = "") -> Optional[Run]:
        """Task ``task_id`` ended: the video gave ``windows`` complete windows (``failed``:
        window -> reason; ``error``: why it gave fewer windows than it should; ``cause``: that
        reason's code, ``worker_messages.CAUSES``; ``failed`` keyed by int or, as ``Done`` carries
        it, by its digits). A pass that stopped on an error (``cause``
        ``"error"``) is asked again up to :data:`PASS_ATTEMPTS` passes in a row (module
        docstring). Otherwise the samples of the video's slots past ``windows`` or in ``failed``,
        asked of this copy and not made by another, are failed for the epoch (padding rows), and a
        video whose slots are not known learns them. Returns the run, or None for a task that was
        not running."""
        ek = self.task_run.get(task_id)
        if ek is None or self.runs[ek].copies.get(task_id) != worker:
            return None
        failed = {int(k): why for k, why in failed.items()}  # the wire's ``Done`` keys a window by its digits
        skip = self.runs[ek].skips.get(task_id, set())
        run = self._end(task_id)
        run.error = error
        epoch, video = ek
        kpw = self.manifest.crops_per_window
        most = pass_ended(self.stopped, video, windows, cause)
        if most is None:  # its missing samples are needed still: the next pass makes them, and only them
            self.passed.setdefault(ek, set()).update(run.made)
            return run
        self.passed.pop(ek, None)
        if self.slots.samples.get(video, 0) is None:
            self.learn(video, most)
        why_short = error or f"the decode gave {windows} window(s), the manifest {self.slots.samples.get(video, 0) // kpw}"
        for i in range(self.slots.samples.get(video, 0)):
            key = SampleKey.at(video, i, kpw)
            gone = key.window in failed or key.window >= windows
            if gone and (key.window, key.crop) not in skip and (epoch, key) not in self.store:
                self.failed.setdefault((epoch, key), failed.get(key.window, why_short))
        return run

    def learn(self, video: str, windows: int) -> None:
        """``video``'s slots are ``windows`` (its first decode's count): the plans unfold with it."""
        self.slots.learn(video, windows)
        for plan in self.plans.values():
            if not plan.complete:
                plan.learn(self.slots.windows)

    def worker_lost(self, worker: Hashable) -> Optional[Run]:
        """``worker`` died: its copies end; a video no copy decodes any more is needed again
        (its missing samples are handed out anew). Returns the run it held, if any."""
        lost = None
        for tid, ek in list(self.task_run.items()):
            if self.runs[ek].copies.get(tid) == worker:
                lost = self._end(tid)
        return lost

    def _end(self, task_id: int) -> Run:
        """Copy ``task_id`` ended: it is forgotten, and its run with its last copy."""
        ek = self.task_run.pop(task_id)
        self.making.tasks.pop(task_id, None)
        run = self.runs[ek]
        run.end(task_id)
        if not run.copies:
            del self.runs[ek]
        return run

    def timed_out(self, now: float) -> List[Tuple[Hashable, Run]]:
        """Copies that sent nothing for ``task_timeout_s``: each ends as a lost worker's. The
        server reads every worker message whatever its clients do, so silence is the worker's own."""
        out = []
        for tid, ek in list(self.task_run.items()):
            run = self.runs[ek]
            if now - run.progress[tid] > self.task_timeout_s:
                worker = run.copies[tid]
                self.worker_lost(worker)
                out.append((worker, run))
        return out


def needed(s: "PlanScheduler", now: float) -> Tuple[List[Tuple[int, str]], List[Tuple[int, str]]]:
    """(epoch, video) scheduler ``s`` decodes next at ``now``: those the pending fetches need a sample of (neither
    stored nor failed), by the first position needing it, or, where a fetch's positions are
    not decided yet, whose slots decide them (:func:`unfolding`); and those the positions
    after each moving head of an epoch need (:class:`Heads`: pending, or answered lately; the
    furthest stop asked of a kept plan a fetch named within :data:`IDLE_S` of ``now`` where no
    head moves; not followed by a fetch of the next epoch), the nearest first, not being
    decoded, while the samples made ahead (stored and not fetched, within ``lookahead`` and a
    shuffle buffer past a moving head, or still to come from running tasks) stay within
    ``lookahead`` (module docstring): a job cut off leaves no stock that stops the next. Past
    an epoch's end the next epoch's first positions are made ahead only while no fetch has
    named that epoch: once one has, its own furthest fetch leads (what was fetched of it may
    have left the store)."""
    store, failed, runs, slots = s.store, s.failed, s.runs, s.slots
    made = made_by_video(s)
    waited: Dict[Tuple[int, str], Tuple[int, int]] = {}
    live = {e: stop for e, stop in s.fetched_to.items() if e in s.plans and now - s.fetched_at[e] < IDLE_S}
    waiting = {f.client for f in s.pending}
    # where readers read: each moving head of a reader's newest epoch (the furthest fetch where none moves)
    heads = {e: s.heads.moving(e, now, waiting) or [stop] for e, stop in live.items() if e + 1 not in live}
    for f in s.pending:
        plan = s.plan(f.epoch)
        heads.setdefault(f.epoch, []).append(f.stop)
        for p, key in zip(range(f.start, f.stop), f.keys(plan)):
            if key is not None and (f.epoch, key) not in store and (f.epoch, key) not in failed:
                ek = (f.epoch, key.video)
                waited[ek] = min(waited.get(ek, (f.epoch, p)), (f.epoch, p))
        if f.unfolds(plan):
            for i, ek in enumerate(unfolding(plan, f.stop, slots, made)):
                waited[ek] = min(waited.get(ek, (f.epoch, plan.known + i)), (f.epoch, plan.known + i))
    reach = s.reach

    def ahead_of_a_head(sk) -> bool:  # made ahead for a moving head, not far past every one (a job cut off)
        plan = s.plans.get(sk[0])
        p = None if plan is None else plan.position(sk[1])
        return p is None or sk[0] not in heads or any(0 <= p - h < reach for h in heads[sk[0]])

    budget = s.lookahead - sum(1 for sk in store if sk not in s.fetched and ahead_of_a_head(sk))
    budget -= sum(max(0, slots.expected(v) - made.get((e, v), 0)) for (e, v) in set(runs) | set(waited))
    ahead: List[Tuple[int, str]] = []
    keep = set(heads) | {e for e, _ in runs}
    read = {e: s.heads.read(e, now, waiting) for e in heads}

    def was_read(e: int, key: Optional[SampleKey]) -> bool:  # answered to a reader still reading (Heads.read)
        p = None if key is None or e not in read else s.plans[e].position(key)
        return p is not None and read[e](p)

    for epoch, stop in sorted((e, h) for e, hs in heads.items() for h in set(hs)):
        if budget <= 0:  # before positions_after, which may build the next epoch's plan
            break
        for e, video, key in positions_after(s.plan, s.plans, epoch, stop, reach, keep):
            if budget <= 0 or (e != epoch and (e in heads or e in live)):
                break
            ek, n = (e, video), slots.samples.get(video)
            if ek in waited or ek in runs or ek in ahead or (e, key) in store or (e, key) in failed or was_read(e, key):
                continue
            if key is None and n is not None and made.get(ek, 0) >= n:
                continue
            ahead.append(ek)
            budget -= slots.expected(video) - made.get(ek, 0)
    return sorted(waited, key=waited.__getitem__), ahead


def production_places(plan: EpochPlan, keys: Set[SampleKey], slots: Slots) -> Iterator[Tuple[SampleKey, int]]:
    """(key, place) of ``keys``, samples no decided position of ``plan`` holds yet: each one's index
    in the production order, at least the plan's edge (``known``), the samples of videos whose
    slots are not known counted as :meth:`Slots.expected` gives. A shuffle buffer draws a sample
    at about its production index (it enters the buffer that many positions before, and is drawn
    a buffer's worth of positions later on average), so the order of the places is the order in
    which the plan reaches the samples, the ones produced last last."""
    if not keys:
        return
    counted, start = plan.counted
    starts: Dict[str, int] = {}
    wanted, i = {k.video for k in keys}, counted
    while len(starts) < len(wanted) and i < len(plan.videos):  # the videos not counted, in production order
        v = plan.videos[i]
        if v in wanted:
            starts[v] = start
        start += slots.expected(v)
        i += 1
    for k in keys:
        first = plan.production_start(k.video)
        if first is None:
            first = starts.get(k.video, start)
        yield k, max(plan.known, first + k.ordinal(plan.crops_per_window))


def trim(s: "PlanScheduler", now: float) -> None:
    """Scheduler ``s``'s keeping (module docstring): drop fetched samples past ``keep_samples``
    (least recently fetched first); then, while the store holds more than ``keep_samples +
    lookahead`` plus the largest video's samples besides those pending fetches name and the
    stock a moving head reaches past its reach (up to as many again), samples never fetched that
    no pending fetch names, the ones readers need last first (:func:`spare_samples`)."""
    fetched = [sk for sk in s.store if sk in s.fetched]
    for sk in fetched[:max(0, len(fetched) - s.keep_samples)]:
        del s.store[sk]
        s.fetched.discard(sk)
    bound = max(s.lookahead, s.shuffle_buffer)
    if s.unfolded:
        unfetched = {(e, k.video) for (e, k) in s.store if (e, k) not in s.fetched}
        s.unfolded = {ek for ek in s.unfolded if ek in s.runs or ek in unfetched and
                      now - s.fetched_at.get(ek[0], now) < IDLE_S}  # an epoch no fetch named a while: a job that left
    over = len(s.store) - s.keep_samples - bound - s.slots.largest
    if over <= 0:
        return
    # a decode a plan's unfolding started, of a size not known: each worker took one, whose
    # samples the plan reaches in production order (dropped, they were made again: 1.2-1.5 made a
    # sample read with 4 videos of 40 samples and 2-3 workers)
    named = {sk for sk in s.store if (sk[0], sk[1].video) in s.unfolded and sk not in s.fetched}
    unfolds = set()
    for f in s.pending:
        plan = s.plan(f.epoch)
        named.update((f.epoch, key) for key in f.keys(plan) if key is not None)
        if f.unfolds(plan):
            unfolds.add(f.epoch)
    if unfolds:  # a fetch of positions not decided yet names the videos whose slots decide them (unfolding)
        made = made_by_video(s)
        waited = {ek for f in s.pending if f.epoch in unfolds
                  for ek in unfolding(s.plans[f.epoch], f.stop, s.slots, made)}
        named.update(sk for sk in s.store if (sk[0], sk[1].video) in waited and sk not in s.fetched)
    # what a pending fetch names is a batch asked now, not made ahead: the bound is on the rest
    over -= sum(1 for sk in named if sk in s.store and sk not in s.fetched)
    if over <= 0:
        return
    live = {e for e, t in s.fetched_at.items() if now - t < IDLE_S}
    waiting = {f.client for f in s.pending}
    heads = {e: s.heads.moving(e, now, waiting) for e in live}
    # the epoch after one read, where no head moves (none fetched it yet, or a job cut off did): the
    # heads of the epoch before reach it past their end (its first positions are made ahead of
    # them, positions_after)
    for e in sorted(live):
        if heads.get(e) and not heads.get(e + 1) and e + 1 in s.plans and s.plans[e].complete:
            heads[e + 1] = [h - len(s.plans[e]) for h in heads[e]]
            live.add(e + 1)
    # an epoch read by readers all paused (an evaluation, a checkpoint): their furthest fetch, as
    # needed() makes ahead of it (taken as unreached, the stock it made ahead went oldest first,
    # and was made again while the job was paused)
    for e in live:
        if not heads.get(e) and e in s.fetched_to:
            heads[e] = [s.fetched_to[e]]
    asked = set(named)
    named |= s.orders.named(list(s.store), now)
    undecided = {}  # samples of a plan still unfolding past its decided positions -> where it places them, about
    for e in live & set(s.plans):
        keys = [k for (e2, k) in s.store if e2 == e and (e2, k) not in s.fetched]
        undecided.update(((e, k), p) for k, p in production_places(s.plans[e], s.plans[e].undecided(keys), s.slots))

    def reached(sk: Tuple[int, SampleKey]) -> Optional[int]:  # an undecided sample at its place in production
        plan, stops = s.plans.get(sk[0]), heads.get(sk[0], ())
        p = None if plan is None else undecided[sk] if sk in undecided else plan.position(sk[1])
        return None if p is None else min((p - h for h in stops if h <= p), default=None)

    named |= {sk for sk in undecided if reached(sk) is None}  # the plan's edge, where no head moves: read next

    # stock a moving head reaches past what it makes ahead for itself (a cut-off job's, ahead of
    # the next job's head, decided or deciding the plan's next positions): kept beside the bound,
    # up to a bound's worth, until the head reaches it
    later = sum(1 for sk in s.store if sk not in s.fetched and sk not in asked and (reached(sk) or 0) >= s.reach)
    over -= min(later, bound)
    if over <= 0:
        return
    for sk in spare_samples(s.store, s.fetched, named, live, over, reached):
        del s.store[sk]

"""Which decode host makes which video, decided by the reader at run time: a fleet of hosts that
each serve the whole corpus's one plan (docs/scaling.md, "One plan, any fleet").

A sample's bytes are a function of (seed, epoch, sample id), whoever makes them, so the plan's
order never depends on who decodes; only the speed does. The rules, pure (no socket, no clock:
``now`` is passed in, in seconds of any monotonic clock):

* **Ownership** is weighted rendezvous hashing (Thaler & Ravishankar's highest random weight,
  with Schindelhauer & Schomaker's weights): a video's hosts are ranked by ``w_h / -ln(u(h, v))``
  with ``u`` a uniform draw from (host, video); the first is its *owner*. A video stays on its
  owner while the fleet and the weights do not change, so a host's frame cache stays warm across
  epochs; a host that joins takes about ``1 / N`` of the videos, one that leaves gives only its
  own, each to the next host of that video's ranking (:func:`rank_hosts`).
* **Weights follow speed, in steps.** Each host measures its own decode capacity, samples made
  per second its workers were busy times its workers (:class:`RateMeter`, fed by the server), and
  says it in every answer; its weight is that rate relative to the fleet's mean, rounded to a step
  of ``2 ** (1 / 4)`` and changed only when the measure leaves the step by more than three quarters
  of a step (:func:`weight_step`): a fast host owns more videos, and noise moves none. The host
  measures, not the reader: a reader sees only the answers it waited for, and a host whose work
  was copied elsewhere, or that was still starting, would read slower than it is and be starved
  of the work that would measure it again.
* **Bounded load, and in time.** A video goes to the first host of its ranking whose queued samples
  stay within its share (its rate over the fleet's) of everything queued (Mirrokni, Thorup &
  Zadimoghaddam, "Consistent hashing with bounded loads"), and that would make it, at its rate
  and after what it holds for earlier positions, within the seconds until the reader's head
  reaches it (``due``); a host past either by a fraction ``x`` of ``slack`` keeps the videos
  whose draw (:func:`spill_draw`) is at least ``x``, none past ``1 + slack``; else the video goes
  to the first host of its ranking that would make it within ``1 + slack`` of the soonest (readers
  late together spread over the near-best hosts). A host that falls behind sheds new videos to
  the next hosts of their rankings until it catches up, and a slow host is given the videos
  needed later, not those the reader is about to wait on. A video takes a host its queue, then
  what one of its workers takes to decode the whole video (one worker decodes a video, whatever
  slice of it a reader asks), and is asked at the latest position its decode can start
  (:meth:`Router.start_by`), the order the host works its makes in: a long video starts before
  the short ones needed a little earlier.
* **A host is measured before it is loaded.** A host that has not said its rate yet is asked
  for :data:`MEASURING_DECODES` videos per worker by each reader (of its slice of each video), and the reader's
  window counts it at that (:meth:`Router.ahead_decodes`); its share grows to the window's
  :data:`AHEAD_DECODES` once its first decodes measure it. A slow host loaded blind holds
  the epoch's first clips, which the head then waits on one by one: so when a reader hears a
  host's first rate, the videos it asked of it that it would make late at that rate
  (:meth:`Router.overdue`) move to the next pick (:meth:`Router.move_off`), every reader's make
  of each waiting there with it (``Make.move``: unless the host started its decode).
* **The hosts' view, not the reader's.** A job has several readers (ranks times DataLoader
  workers), and several jobs may read one fleet; each reader routes on its own, with no
  coordinator. So each host says in every answer, and in its answer to a ping (a ``plan_ask``,
  which its server loop answers within its poll whatever its workers do), the samples all
  readers asked of it and it has not made (:meth:`Router.heard`). The load bound, the deadlines
  and the copies count that queue, this reader's own asks since added; readers that heard the
  same reports rank a video's hosts alike and pick alike (a video asked of two hosts is decoded
  twice). Readers ask a video at different times, over different views, so each asks it of its
  *arbiter*, the first host of its ranking that is not suspect (:meth:`Router.arbiter`), naming
  the host it picked (``Make.route``): the arbiter keeps the first reader's pick and tells every
  later reader (``Moved``), or makes the video where it holds it already.
* **Copies and hedging.** A video the reader waits on is copied to a host with nothing queued by
  any reader, the first such of the video's ranking, where that host would make it sooner
  (:meth:`Router.copy`); one asked only of hosts that answered nothing for ``hedge_s``
  (stalled, stopped, gone) is asked of the next host of its ranking too, whatever its load, so
  every reader of a job hedges it to the same host (:meth:`Router.hedges`);
  the first copy's rows win. Once a reader has asked its epoch's last step, each video it awaits
  of one host is copied to the first host of its ranking :data:`BACKUP_STEPS` weight steps faster
  that would make it sooner (:meth:`Router.backup`): the same host for every reader of the
  job, so a clip's readers wait on one copy. A host with nothing queued takes, as a move, the
  first video a reader awaits that it would make before the host holding it starts it
  (:meth:`Router.share`):
  the idle host is one reader's of the job, so the job moves one video there, not one a reader.
  A host with this reader's work queued that answered nothing, not
  even a ping, for ``hedge_s`` is *suspect*: it is routed nothing new until it answers again. A
  host busy with other readers' work still answers pings, and is not. One that left a ping
  unanswered for :data:`QUIET_S` is *quiet* (a paused process): it keeps what it was asked, and
  new videos go to the hosts that answer.

``harness/fleet_sim.py`` runs these rules over 128 simulated hosts; ``tests/test_fleet.py``
checks each property.
"""
from __future__ import annotations

import functools
import hashlib
import math
from dataclasses import dataclass, field
from typing import Collection, Dict, Iterable, List, Mapping, Optional, Sequence, Tuple

import numpy as np

__all__ = ["host_key", "video_key", "rank_hosts", "weight_step", "spill_draw", "RateMeter", "Router",
           "PINGS_PER_HEDGE", "QUIET_S", "AHEAD_DECODES", "MEASURING_DECODES", "SLIDE_WINDOWS", "SLACK", "HEDGE_S",
           "BACKUP_STEPS"]

_MASK = np.uint64(0xFFFFFFFFFFFFFFFF)
#: Weights move in steps of this factor (a quarter octave): finer steps follow speed closer but
#: move videos at every wobble of a measured rate.
WEIGHT_STEP = 2 ** 0.25
#: XORed into a video's key for its spill draws (:func:`spill_draw`), apart from its ranking's.
SPILL_SALT = 0x5DEECE66D
#: How far past its share of the queued samples, or its deadline, a host is still routed to (the
#: bounded load's ``1 + epsilon`` is ``1 + SLACK``). 128 simulated hosts at sigma 0.2, seeds 0 and
#: 1, whole-epoch share: one reader 0.89 and 0.85 at 0.25, 0.90 and 0.91 at 0.1, 0.89 and 0.84 at
#: 0.5; 8 readers 0.82 and 0.83 at 0.25, 0.74 and 0.71 at 0.1 (their differing views of a queue
#: send a video asked near its edge to two hosts: docs/scaling.md).
SLACK = 0.25
#: Seconds a host may answer nothing, not even a ping, while a reader waits on it before its
#: videos are asked of the next hosts of their rankings too (a failover): a host's server loop
#: answers a ping within its 0.1 s poll whatever its workers do, so :data:`PINGS_PER_HEDGE` pings
#: unanswered over this long is a host stopped or gone, not one busy, and a process paused for
#: less (a collection, a starved container) keeps its videos rather than have them decoded twice.
HEDGE_S = 10.0
#: Pings a silent host is sent before it is suspect (``hedge_s`` apart over this): one lost or
#: late answer does not make a busy host suspect.
PINGS_PER_HEDGE = 4
#: Seconds a host may leave a reader's ping unanswered before it is *quiet* (:meth:`Router.quiet`):
#: routed no new video while a host of the video's ranking answers, the videos it was asked kept
#: (no copy: a hedge waits for ``hedge_s``). A host's server loop answers a ping within its
#: 0.1 s poll whatever its workers do, so one silent this long after a ping is paused (stopped,
#: starved, a stalled machine), and each video routed to it waits until it runs again; routed
#: to until it was suspect, a stalled host took up to ``hedge_s`` of new work, which the job then
#: waited on or copied when it came back. 128 simulated hosts, seed 0: 8, 32 and 128 readers read
#: 0.825, 0.779 and 0.664 of the hosts' capacity without this rule, 0.845, 0.851 and 0.759 with
#: it, at sigma 0.2, within 0.003 of the same decodes a clip (sigma 0.5 and one reader:
#: docs/scaling.md).
QUIET_S = 1.0
#: Decodes per worker a reader asks ahead of a host that said its rate: a clip of many windows
#: decodes for many times the mean, and the steps after it must find their clips made meanwhile
#: (6 gave 0.72 of the hosts' rate over 10-90 % of the epoch at 128 simulated hosts, 10 gave
#: 0.97: docs/scaling.md).
AHEAD_DECODES = 10
#: Videos per worker a reader asks at most of a host that has not said its rate yet
#: (:meth:`Router.route`), and decodes it asks ahead of it (:meth:`Router.ahead_decodes`): enough to
#: keep its workers busy until its first decodes measure it. Asked a full window's share before
#: that, a host of a third of the mean speed held a third of a minute of the epoch's first clips,
#: which the head then waited on one by one (128 simulated hosts of sigma 0.5: 0.60 of the hosts'
#: rate over the epoch, 0.83 with this bound: docs/scaling.md).
MEASURING_DECODES = 2
#: How far a reader's window slides past its decodes ahead while its head waits, in windows: it
#: asks as many more positions as the hosts make meanwhile at their rate (:meth:`Router.slide`).
#: A window fixed to the head has the hosts make all of it during one long wait, then asks the
#: next window at once when the head moves on, every video of it due within seconds: the readers
#: send them to the few hosts that would make them soonest, which the head then waits on one by
#: one. 128 simulated hosts, whole epoch, seeds 0-2: one reader 0.91/0.89 -> 0.92/0.91 (sigma
#: 0.2/0.5), 8 readers at sigma 0.5 0.80 -> 0.88 (docs/scaling.md); the rows a reader holds grow
#: by as much, at most.
SLIDE_WINDOWS = 1
#: Weight steps (:data:`WEIGHT_STEP`) a host must stand above a video's holder to be that video's
#: backup at an epoch's end (:meth:`Router.backup`): two, about 1.4 times as fast. A copy on a
#: host about as fast as the holder ends little sooner and decodes the clip twice.
BACKUP_STEPS = 2


def _key(text: str) -> int:
    return int.from_bytes(hashlib.blake2b(text.encode(), digest_size=8).digest(), "little")


@functools.lru_cache(maxsize=4096)
def host_key(host: str) -> int:
    """A host's 64-bit key: BLAKE2b of its name (``tcp://10.0.0.7:5555``, a pod's name)."""
    return _key("host/" + host)


def video_key(video: str) -> int:
    """A video's 64-bit key: BLAKE2b of its corpus-relative path."""
    return _key("video/" + video)


def _uniform(hosts: np.ndarray, video: int) -> np.ndarray:
    """float64 (len(hosts),) in (0, 1): SplitMix64 of each host key XOR the video key, top 53 bits."""
    with np.errstate(over="ignore"):
        z = (hosts ^ np.uint64(video)) + np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return ((z >> np.uint64(11)).astype(np.float64) + 0.5) / float(1 << 53)


def spill_draw(video: str, hosts: Sequence[str]) -> List[float]:
    """Each host's draw in (0, 1) for ``video``, drawn apart from its ranking's: a host past its
    bounds by a fraction ``x`` of the slack sheds the videos whose draw is under ``x``
    (:meth:`Router.route`). Every reader draws alike, so readers whose views of a host's queue
    differ a little shed the same videos but for a few, where a shed-all edge would send every
    video asked near it to two hosts."""
    keys = np.array([host_key(h) for h in hosts], dtype=np.uint64)
    return _uniform(keys, video_key(video) ^ SPILL_SALT).tolist()


def rank_hosts(video: str, hosts: Sequence[str], weights: Optional[Mapping[str, float]] = None) -> List[str]:
    """``hosts`` ranked for ``video`` by weighted rendezvous hashing, best first: the owner, then
    where its work goes when the owner is full, suspect or gone.

    Args:
        video: the corpus-relative path.
        hosts: distinct host names.
        weights: host -> weight > 0 (default 1 each; a missing host weighs 1).
    Returns:
        A new list of the same names.
    Raises:
        ValueError: a weight <= 0, naming its host.
    """
    if not hosts:
        return []
    keys = np.array([host_key(h) for h in hosts], dtype=np.uint64)
    w = np.array([1.0 if weights is None else float(weights.get(h, 1.0)) for h in hosts])
    if (w <= 0).any():
        bad = [h for h, x in zip(hosts, w) if x <= 0]
        raise ValueError(f"host weight must be > 0: {bad[0]!r} has {weights[bad[0]]}")
    score = w / -np.log(_uniform(keys, video_key(video)))
    return [hosts[i] for i in np.argsort(-score, kind="stable")]


def weight_step(rate: float, mean: float, current: Optional[int] = None) -> int:
    """The step ``i`` of a host's weight ``WEIGHT_STEP ** i`` for its ``rate`` against the fleet's
    ``mean`` (both samples/s, > 0): the nearest step, or ``current`` while the measure lies within
    three quarters of a step of it (hysteresis: a rate wobbling at a step's edge moves nothing)."""
    exact = math.log(rate / mean, WEIGHT_STEP)
    if current is not None and abs(exact - current) <= 0.75:
        return current
    return int(round(exact))


@dataclass
class RateMeter:
    """A host's decode capacity, as its server measures it: samples made per second of its
    workers' busy time, each second's weight halved every ``half_life_s`` seconds.

    Attributes:
        samples, busy_s: the decayed counts (samples; busy seconds per worker).
        last: when they were last added to (None: never), in seconds.
    """

    half_life_s: float = 30.0
    samples: float = 0.0
    busy_s: float = 0.0
    last: Optional[float] = None

    def add(self, samples: float, busy_s: float, now: float) -> None:
        """``samples`` more samples made in ``busy_s`` more busy seconds per worker, at ``now``."""
        if self.last is not None and now > self.last:
            f = 0.5 ** ((now - self.last) / self.half_life_s)
            self.samples *= f
            self.busy_s *= f
        self.last = now if self.last is None else max(self.last, now)
        self.samples += samples
        self.busy_s += busy_s

    def rate(self) -> Optional[float]:
        """Samples/s, or None before a fifth of a busy second's worth of samples."""
        return self.samples / self.busy_s if self.busy_s >= 0.2 and self.samples > 0 else None


@dataclass
class _Host:
    rate: Optional[float] = None  # samples/s, as the host last said (None: not yet)
    queued: Dict[Tuple[int, str], int] = field(default_factory=dict)  # (epoch, video) -> samples
    at: Dict[Tuple[int, str], int] = field(default_factory=dict)  # (epoch, video) -> its first position needing it
    load: int = 0  # the samples queued, summed
    heard: float = 0.0  # when it last answered anything, a ping included (or joined)
    step: Optional[int] = None  # weight step (None: not measured yet)
    workers: int = 1  # its decode workers (its stream info's ``feed.workers``), each making one video at a time
    others: float = 0.0  # samples it said other readers have queued on it (its queue less this reader's)
    said: float = 0.0  # when it said it
    pinged: float = float("-inf")  # when this reader last pinged it


class Router:
    """One reader's routing of videos to a fleet's hosts (module docstring).

    Args:
        hosts: the hosts' names.
        slack: how far past its share of the queued samples a host is still routed to (> 0).
        hedge_s: seconds a host may answer nothing while a reader waits on it before its videos
            are asked of the next hosts too.
        patience_s: seconds a reader waits on a video before it asks a copy (:meth:`copy`): how
            late a video's last host may make it and keep it (:meth:`route`).
        now: the clock's reading at start.
        workers: each of ``hosts``'s decode workers (:meth:`join`).

    Raises:
        ValueError: ``slack`` or ``hedge_s`` <= 0, ``patience_s`` < 0, a host named twice, or
            ``workers`` < 1.
    """

    def __init__(self, hosts: Iterable[str], slack: float = SLACK, hedge_s: float = HEDGE_S, now: float = 0.0,
                 patience_s: float = 1.0, workers: int = 1):
        if slack <= 0 or hedge_s <= 0 or patience_s < 0:
            raise ValueError(f"slack and hedge_s must be > 0 and patience_s >= 0, got {slack}, {hedge_s} and "
                             f"{patience_s}")
        self.slack, self.hedge_s, self.patience_s = slack, hedge_s, patience_s
        #: Seconds a host holding this reader's work may answer nothing before it is pinged: a
        #: host busy for other readers answers a few pings before it would be suspect.
        self.ping_s = hedge_s / PINGS_PER_HEDGE
        self.hosts: Dict[str, _Host] = {}
        self.asked: Dict[Tuple[int, str], List[str]] = {}  # (epoch, video) -> the hosts asked, in order
        #: host -> requests this reader awaits an answer to from it: its pass's in flight, which
        #: the pass keeps (a request outlives the queue :meth:`move_off` and :meth:`moved` take
        #: off a host: a move asked of a host that died is awaited there still).
        self.awaited: Mapping[str, Collection] = {}
        self.listened: Optional[float] = None  # when this reader last read its hosts' answers (:meth:`listen`)
        self._load = 0
        self._routed = [0, 0]  # videos routed, their samples summed: :meth:`per_video`
        for h in hosts:
            self.join(h, now, workers=workers)

    # ------------------------------------------------------------------ the fleet
    def join(self, host: str, now: float, rate: Optional[float] = None, workers: int = 1) -> None:
        """``host`` serves from ``now`` on with ``workers`` decode workers; ``rate``: the
        samples/s it said before (a reader's earlier pass), which weighs it until it says anew.

        Raises:
            ValueError: a host already in the fleet, or ``workers`` < 1."""
        if host in self.hosts:
            raise ValueError(f"host {host!r} is in the fleet already")
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise ValueError(f"host {host!r}: workers must be an int >= 1, got {workers!r}")
        self.hosts[host] = _Host(heard=now, rate=rate, workers=workers)

    def leave(self, host: str) -> List[Tuple[int, str]]:
        """``host`` is gone: returns the (epoch, video) it held and no other host was asked for,
        to route again (:meth:`route`)."""
        gone = self.hosts.pop(host, None)
        if gone is None:
            return []
        self._load -= gone.load
        orphans = []
        for ev in gone.queued:
            others = [h for h in self.asked.get(ev, ()) if h != host and h in self.hosts]
            self.asked[ev] = others
            if not others:
                orphans.append(ev)
        return orphans

    def weights(self) -> Dict[str, float]:
        """host -> weight (``WEIGHT_STEP ** step``; 1 while its rate is not known)."""
        rates = {h: s.rate for h, s in self.hosts.items()}
        known = [r for r in rates.values() if r]
        if known:
            mean = sum(known) / len(known)
            for h, s in self.hosts.items():
                if rates[h]:
                    s.step = weight_step(rates[h], mean, s.step)
        return {h: WEIGHT_STEP ** (s.step or 0) for h, s in self.hosts.items()}

    def owner(self, video: str) -> str:
        """``video``'s owner under the fleet and weights now."""
        return rank_hosts(video, list(self.hosts), self.weights())[0]

    def suspect(self, host: str, now: float) -> bool:
        """``host`` has work queued, or a request this reader awaits (:attr:`awaited`), and
        answered nothing for ``hedge_s``."""
        s = self.hosts[host]
        return self._waits_on(host, s) and now - s.heard >= self.hedge_s

    def quiet(self, host: str, now: float) -> bool:
        """``host`` has answered nothing since this reader pinged it (:meth:`pings`), :data:`QUIET_S`
        or more before ``now``: a paused process, routed no new video (:meth:`route`,
        :meth:`copy`) until it answers."""
        s = self.hosts[host]
        return s.pinged > s.heard and now - s.pinged >= QUIET_S

    def _waits_on(self, host: str, s: _Host) -> bool:
        return bool(s.queued or self.awaited.get(host))

    def awaits(self, host: str, now: float) -> None:
        """This reader sends ``host`` a request at ``now`` (before its pass counts it in
        :attr:`awaited`): a host it waited on for nothing counts its silence from now."""
        s = self.hosts.get(host)
        if s is not None and not self._waits_on(host, s):
            s.heard = max(s.heard, now)

    # ------------------------------------------------------------------ routing
    def route(self, epoch: int, video: str, samples: int, now: float, exclude: Sequence[str] = (),
              due: Optional[float] = None, position: Optional[int] = None,
              held: Optional[str] = None, video_samples: Optional[int] = None) -> Optional[str]:
        """The host to ask for ``samples`` samples of ``video`` in ``epoch``: the first of its
        ranking that is not suspect, not quiet (:meth:`quiet`; all of them quiet: of those), not
        in ``exclude``, within its bounded load (its queue, every
        reader's (:meth:`backlog`), and these samples within its share, its weight over the
        fleet's, of everything queued on the fleet) and, where the reader needs the video within
        ``due`` seconds, that would make it within that (:meth:`finish`; a host makes the videos
        asked of it in the order of ``position``, :meth:`start_by` of the first needing each): a host past
        either by a fraction ``x`` of ``slack`` keeps the video when its draw
        (:func:`spill_draw`) is at least ``x``; else the one of those that would make it first. ``held``,
        the host that made the video last (its frame cache holds it), is kept before them while
        it would make it in time, or :attr:`patience_s` late, whatever its load: a load bound
        crossed by a few samples' chance would move a video off its warm cache (a small fleet's
        share of a reader's queue is a few videos), and a host that falls behind falls behind its
        deadlines too. Readers that heard the same queues pick the same host. None when no host
        is left. A host that has not said its rate is past its bounds once this reader's queue
        there and these samples pass :data:`MEASURING_DECODES` of its videos per worker
        (:meth:`measuring_samples`). Where every host is past them: the first of the ranking
        that would make the video within ``1 + slack`` of the soonest any would (of those within
        that measure, else of all), so readers that fell behind together, each seeing its own
        queues, spread their late videos over the near-best hosts instead of each sending them
        all to the one best host. ``video_samples``: what the host's decode of the video makes,
        every window's samples (default ``samples``): a job's reader asks its slice of a video,
        and the host's worker decodes all of it (:meth:`finish`).

        The host's queue takes the video (:meth:`answered` and :meth:`finished` clear it)."""
        self._routed[0] += 1
        self._routed[1] += samples
        weights = self.weights()
        ranking = self._answering(video, now, exclude, weights)
        if not ranking:
            return None
        backlog = {h: self.backlog(h, now) for h in self.hosts}
        total = sum(backlog.values()) + samples
        weight = sum(weights[h] for h in ranking)

        def in_time(h: str, late_s: float = 0.0) -> bool:
            return due is None or \
                self.finish(h, samples, position, now, video_samples) <= (1 + self.slack) * due + late_s

        def measuring(h: str) -> bool:  # not said its rate, and asked what measures it already
            return self.hosts[h].rate is None and self.hosts[h].load + samples > self.measuring_samples(h)

        def past(h: str) -> float:  # how far past its bounds, in slacks: 0 at its share and its due
            if measuring(h):
                return float("inf")
            load = (backlog[h] + samples) / (total * weights[h] / weight) - 1
            late = float("inf") if due is not None and due <= 0 else \
                0.0 if due is None else self.finish(h, samples, position, now, video_samples) / due - 1
            return max(load, late) / self.slack

        if held in ranking and due is not None and in_time(held, self.patience_s):
            pick = held
        else:
            keep = dict(zip(ranking, spill_draw(video, ranking)))
            pick = next((h for h in ranking if keep[h] >= past(h)), None)
        if pick is None:
            pool = [h for h in ranking if not measuring(h)] or ranking
            ends = {h: self.finish(h, samples, position, now, video_samples) for h in pool}
            best = min(ends.values())
            pick = next(h for h in pool if ends[h] <= (1 + self.slack) * best)
        self.ask(pick, epoch, video, samples, now, position)
        return pick

    def _answering(self, video: str, now: float, exclude: Collection[str] = (),
                   weights: Optional[Mapping[str, float]] = None) -> List[str]:
        """``video``'s ranking less ``exclude`` and the suspect hosts, the quiet ones left out too
        unless every one left is quiet: the hosts :meth:`route` and :meth:`hedges` pick from."""
        ranking = [h for h in rank_hosts(video, list(self.hosts), self.weights() if weights is None else weights)
                   if h not in exclude and not self.suspect(h, now)]
        return [h for h in ranking if not self.quiet(h, now)] or ranking

    def per_video(self) -> float:
        """Samples a video routed so far asked, on average (2 before any: a WebVid clip's windows)."""
        return self._routed[1] / self._routed[0] if self._routed[0] else 2.0

    def measuring_samples(self, host: str) -> float:
        """Samples this reader may queue on ``host`` while it has not said its rate:
        :data:`MEASURING_DECODES` videos per worker of :meth:`per_video` samples (each reader of
        a job asks its slice of each video, so the readers together ask about that many videos)."""
        return MEASURING_DECODES * self.hosts[host].workers * self.per_video()

    def ahead_decodes(self) -> int:
        """Decodes a reader asks ahead of the fleet: :data:`AHEAD_DECODES` per worker of each host
        that said its rate, :data:`MEASURING_DECODES` per worker of each that has not (its
        window grows as the hosts' first decodes measure them)."""
        return sum(s.workers * (AHEAD_DECODES if s.rate else MEASURING_DECODES) for s in self.hosts.values())

    def slide(self, ahead: int, waited_s: float) -> int:
        """Positions a reader's window of ``ahead`` positions spans once its head has waited
        ``waited_s`` seconds on the hosts (not on its own trainer): ``ahead`` and what the fleet
        makes meanwhile at its rate (:meth:`capacity`), at most :data:`SLIDE_WINDOWS` windows
        more; ``ahead`` while a host has not said its rate (the first hosts measured would take
        what the others' measuring bound sheds, :meth:`route`)."""
        if waited_s <= 0 or not self.hosts or not all(s.rate for s in self.hosts.values()):
            return ahead
        return ahead + int(min(SLIDE_WINDOWS * ahead, self.capacity() * waited_s))

    def start_by(self, position: int, video_samples: int) -> int:
        """The position a video first needed at ``position`` is asked at (``Make.position``, the
        order a host works its makes in, and :meth:`route`'s ``position``): ``position`` less
        the positions the fleet reads while one of its workers decodes the video's
        ``video_samples`` (the fleet's workers times them: it reads at its workers' summed rate),
        at least 0. A host that works its makes by the first position needing each starts a long
        video when the head is a short video's decode away and the head waits on it for the
        rest; by this, the latest start that makes it in time, it starts it early enough
        (least laxity first). 128 simulated hosts, seeds 0-2: 8 readers 0.82 -> 0.87 of the
        hosts' capacity at sigma 0.2, 32 readers 0.79 -> 0.85 (docs/scaling.md)."""
        workers = sum(s.workers for s in self.hosts.values())
        return max(0, position - video_samples * workers)

    def overdue(self, host: str, epoch: int, now: float, due: Mapping[str, Optional[float]],
                video_samples: Mapping[str, int]) -> List[str]:
        """The videos of ``epoch`` this reader queued on ``host`` that it would make, at the rate it
        said (:meth:`finish`, ``video_samples``: each one's whole decode), later than ``1 +
        slack`` times their ``due`` (seconds until the reader's head needs each; None: not
        judged), in the order the host works them. A host is loaded before its first decodes
        measure it (:data:`MEASURING_DECODES`); one that turns out slow holds the epoch's first
        videos, which the head would wait on one by one: a reader that hears its first rate
        moves these off it (:meth:`move_off`). None is left as started: a reader cannot tell
        which the host started (a job's readers each queue a few slices of its videos, so
        leaving each reader's first per worker left them all: 32 simulated readers at sigma 0.5,
        seed 0, 0.66 -> 0.86 of the hosts' capacity), and the host keeps those it started
        (``Make.move``)."""
        s = self.hosts.get(host)
        if s is None or not s.rate:
            return []
        mine = sorted((ev for ev in s.queued if ev[0] == epoch), key=lambda ev: s.at.get(ev, 0))
        out = []
        for _, video in mine:
            d = due.get(video)
            if d is not None and self.finish(host, 0, s.at.get((epoch, video)), now, video_samples[video]) > \
                    (1 + self.slack) * d:
                out.append(video)
        return out

    def move_off(self, host: str, epoch: int, video: str, samples: int, now: float, due: Optional[float],
                 position: Optional[int], video_samples: Optional[int] = None, exclude: Sequence[str] = ()) -> \
            Optional[str]:
        """Route ``video`` (``samples`` of it for this reader) again, ``host`` excluded (one of
        :meth:`overdue`'s): its queue leaves ``host`` and goes to the pick (:meth:`route`);
        None, and it stays, where no other host would take it."""
        s = self.hosts.get(host)
        ev = (epoch, video)
        if s is None or ev not in s.queued:
            return None
        at = s.at.get(ev)
        self._unqueue(s, ev)
        pick = self.route(epoch, video, samples, now, exclude=[host, *exclude], due=due, position=position,
                          video_samples=video_samples)
        if pick is None:
            self.ask(host, epoch, video, samples, now, at)
            return None
        asked = self.asked.get(ev, [])
        if host in asked:
            asked.remove(host)
        return pick

    def arbiter(self, video: str, now: float) -> Optional[str]:
        """The host that says where ``video`` is made: the first of its ranking that is not
        suspect (None: no host). A reader asks it first, whichever host :meth:`route` picked
        (``Make.route``): it makes the video, or tells where the first reader to ask it placed it,
        so readers whose views differ still have each video made once."""
        weights = self.weights()
        return next((h for h in rank_hosts(video, list(self.hosts), weights) if not self.suspect(h, now)), None)

    def moved(self, epoch: int, video: str, host: str, to: str, now: float) -> None:
        """``host`` said ``video`` is made at ``to`` (its arbiter's placement, or its own hold):
        this reader's queue of it moves there."""
        s = self.hosts.get(host)
        n = s.queued.get((epoch, video)) if s is not None else None
        if n is None or to == host or to not in self.hosts:
            return
        position = s.at.get((epoch, video))
        self._unqueue(s, (epoch, video))
        asked = self.asked.get((epoch, video), [])
        if host in asked:
            asked.remove(host)
        self.ask(to, epoch, video, n, now, position)

    def backlog(self, host: str, now: Optional[float] = None) -> float:
        """Samples queued on ``host`` by every reader: this reader's, and the others' as the host
        last said them, less what it made since at its rate (``now`` None: as said)."""
        s = self.hosts[host]
        return s.load + self._others(s, now)

    def _others(self, s: _Host, now: Optional[float]) -> float:
        if not s.others or now is None:
            return s.others
        return max(0.0, s.others - (now - s.said) * self._rate(s))

    def _rate(self, s: _Host) -> float:
        """A host's samples/s as this reader counts it: as it said, else the fleet's mean, else 1."""
        return s.rate or self.mean_rate() or 1.0

    def finish(self, host: str, samples: int, position: Optional[int] = None, now: Optional[float] = None,
               video_samples: Optional[int] = None) -> float:
        """Seconds ``host`` would take to make ``samples`` more of one video at ``position`` and
        its queued samples it makes first, at the rate it said (a host that said none yet: the
        fleet's mean, else 1 sample/s): this reader's at earlier positions (all, for ``position``
        None), and the other readers' (:meth:`backlog`) in the same proportion (their positions
        are not said; all of them while this reader queued nothing there), then one of its
        workers' decode of the whole video, ``video_samples`` (default ``samples``) at a worker's
        share of the rate: one worker decodes a video, so a clip of many windows on a slow host
        of many workers takes many times what the host's rate says, and a job's reader that
        asks one sample of it waits on all of it. The host works its queue with every worker, so
        what it makes first delays this video by that queue over the whole host's rate."""
        s = self.hosts[host]
        first = s.load if position is None else sum(n for ev, n in s.queued.items() if s.at.get(ev, 0) <= position)
        others = self._others(s, now)
        if others:
            others *= first / s.load if s.load else 1.0
        rate = self._rate(s)
        return (first + others + (video_samples or samples) * s.workers) / rate

    def decode_s(self, video_samples: int, host: Optional[str] = None) -> float:
        """Seconds one worker of a mean host (``host`` given: of that host, at the rate it said,
        else the fleet's mean) takes to decode a video of ``video_samples`` samples: the fleet's
        rate (:meth:`capacity`) over its workers, or the host's over its own."""
        if host is not None:
            s = self.hosts[host]
            return video_samples * s.workers / self._rate(s)
        workers = sum(s.workers for s in self.hosts.values())
        return video_samples * workers / self.capacity() if workers else 0.0

    def backup(self, epoch: int, video: str, samples: int, now: float, host: str, video_samples: int,
               asked_s: float, position: Optional[int] = None, exclude: Collection[str] = (),
               end_s: float = 0.0) -> Optional[str]:
        """Where a reader at its epoch's end copies ``video`` (``samples`` of it, its whole decode
        ``video_samples``, first needed at ``position``), asked of ``host`` alone ``asked_s``
        seconds ago: the first host of the video's ranking that answers (neither suspect nor
        quiet; none of ``exclude``), has said its rate and stands :data:`BACKUP_STEPS` weight
        steps or more above ``host`` (any such host, for a quiet ``host``: a paused process), if
        it would make it (:meth:`finish`: what it makes first, then the decode), by ``1 +
        slack``, before ``host`` does: what ``host`` has left (:meth:`left_s`), at least its
        whole decode (a queued decode starts after the ask); and only where that is later than
        ``end_s``, the seconds until the reader's head reaches the epoch's end (``Pass.due``):
        a video made before then holds no one at the end, and where the window spans much of a
        small epoch, copies of all of them cost decodes (64 simulated hosts, 6,000 clips, 32
        readers: 1.064 decodes a clip). None: no copy.

        MapReduce's backup tasks: at an epoch's end the hosts run out of work while its last
        clips are made on slow hosts and on hosts that stalled (docs/scaling.md). The pick and
        the test use the hosts' own figures (ranking, weights, rates, queues), which every
        reader of a job hears alike, so the readers of a clip copy it to one host, whose one
        decode answers them all. Each reader copying to its own share of the idle hosts, one
        clip of 19 samples was copied to six hosts while a reader with no idle host in its
        share waited on the slow one (128 simulated hosts, 32 readers, sigma 0.5). The pick's
        queue takes the video."""
        weights = self.weights()  # steps the hosts' weights
        quiet, floor = self.quiet(host, now), (self.hosts[host].step or 0) + BACKUP_STEPS
        fast = [h for h in self._answering(video, now, {host, *exclude}, weights)
                if self.hosts[h].rate and (quiet or (self.hosts[h].step or 0) >= floor)]
        if not fast:
            return None
        pick = fast[0]
        left = max(self.left_s(host, video_samples, asked_s, now), self.decode_s(video_samples, host))
        if left <= end_s or self.finish(pick, samples, None, now, video_samples) * (1 + self.slack) >= left:
            return None
        self.ask(pick, epoch, video, samples, now, position)
        return pick

    def left_s(self, host: str, video_samples: int, asked_s: float, now: float) -> float:
        """Seconds ``host``, asked ``asked_s`` seconds ago for a video of ``video_samples``
        samples, has left of its decode at most: the decode (:meth:`decode_s`) less ``asked_s``
        (started at the ask at the earliest; below 0: late by its own measure); infinite for a
        quiet host (:meth:`quiet`: a paused process, which makes nothing until it runs again)."""
        return float("inf") if self.quiet(host, now) else self.decode_s(video_samples, host) - asked_s

    def mean_rate(self) -> Optional[float]:
        """The mean of the rates the hosts said (samples/s), None before any."""
        known = [s.rate for s in self.hosts.values() if s.rate]
        return sum(known) / len(known) if known else None

    def capacity(self) -> float:
        """The fleet's samples/s: each host's rate (the mean for one that said none yet, else 1)."""
        mean = self.mean_rate() or 1.0
        return sum(s.rate or mean for s in self.hosts.values())

    def answered(self, host: str, epoch: int, video: str, now: float, done: bool,
                 rate: Optional[float] = None, queued: Optional[int] = None) -> None:
        """``host`` answered about ``video`` at ``now``, saying its capacity ``rate`` (samples/s,
        None: not measured yet) and its queue ``queued`` (:meth:`heard`); ``done``: it holds no
        more of that video for this reader (every sample asked of it is answered)."""
        s = self.hosts.get(host)
        if s is None:
            return
        if done:
            self._unqueue(s, (epoch, video))
        self.heard(host, now, rate, queued)

    def heard(self, host: str, now: float, rate: Optional[float] = None, queued: Optional[int] = None) -> None:
        """``host`` answered at ``now`` (rows, or a ping): it is alive. ``rate``: its capacity
        (samples/s; None: not said); ``queued``: the samples every reader asked of it that it has
        not made (None: not said), of which those this reader queued there are its own."""
        s = self.hosts.get(host)
        if s is None:
            return
        s.heard = max(s.heard, now)
        if rate is not None and rate > 0:
            s.rate = rate
        if queued is not None:
            s.others, s.said = max(0.0, float(queued) - s.load), now

    def listen(self, now: float) -> None:
        """This reader reads its hosts' answers at ``now`` (each turn of its loop). The seconds
        since it last did, past :attr:`ping_s`, it heard nothing and pinged no one: its loop held
        batches its trainer had not taken (a rank waiting on the job's slowest), or its process
        was paused. They do not count toward any host's silence (:meth:`suspect`): else a reader
        takes its own deafness for its hosts' and, at its first turn after the pause, hedges
        everything they are making."""
        if self.listened is not None:
            deaf = now - self.listened - self.ping_s
            if deaf > 0:
                for s in self.hosts.values():
                    s.heard = min(now, s.heard + deaf)
        self.listened = now if self.listened is None else max(self.listened, now)

    def pings(self, now: float) -> List[str]:
        """The hosts to ping at ``now`` (a ``plan_ask``; its answer is :meth:`heard`), each at most
        every :attr:`ping_s`: those holding this reader's work that answered nothing for
        :attr:`ping_s`, and those whose rate this reader does not know (one that other readers'
        work measured is then weighed and asked ahead for as measured: :meth:`ahead_decodes`). A
        host whose workers are busy with other readers' work answers a ping from its server loop,
        and so is never taken for silent (:meth:`suspect`)."""
        out = []
        for h, s in self.hosts.items():
            if (s.rate is None or self._waits_on(h, s) and now - s.heard >= self.ping_s) and now - s.pinged >= self.ping_s:
                s.pinged = now
                out.append(h)
        return out

    def finished(self, epoch: int, video: str) -> None:
        """Every sample of ``video`` in ``epoch`` is read: no host holds it for this reader."""
        for h in self.asked.pop((epoch, video), ()):
            s = self.hosts.get(h)
            if s is not None:
                self._unqueue(s, (epoch, video))

    @property
    def load(self) -> int:
        """Samples queued on every host, summed."""
        return self._load

    def ask(self, host: str, epoch: int, video: str, samples: int, now: float,
            position: Optional[int] = None) -> None:
        """``host`` is asked ``samples`` more samples of ``video``, first needed at ``position``
        (a reader that keeps asking one host for a video's samples as its plan decides them)."""
        s = self.hosts.get(host)
        if s is None:
            return
        if not self._waits_on(host, s):
            s.heard = max(s.heard, now)  # an idle host's silence counts from its first ask
        self._queue(s, (epoch, video), samples)
        if position is not None:
            s.at[(epoch, video)] = min(s.at.get((epoch, video), position), position)
        asked = self.asked.setdefault((epoch, video), [])
        if host not in asked:
            asked.append(host)

    def _queue(self, s: _Host, ev: Tuple[int, str], samples: int) -> None:
        s.queued[ev] = s.queued.get(ev, 0) + samples
        s.load += samples
        self._load += samples

    def _unqueue(self, s: _Host, ev: Tuple[int, str]) -> None:
        s.at.pop(ev, None)
        n = s.queued.pop(ev, None)
        if n is None:
            return
        s.load -= n
        self._load -= n

    def copy(self, epoch: int, video: str, samples: int, now: float, asked: Sequence[str],
             position: Optional[int] = None, refused: Collection[str] = (),
             video_samples: Optional[int] = None, waited: float = 0.0) -> Optional[str]:
        """The host to ask a copy of ``video`` (``samples`` samples, first needed at
        ``position``) that a reader waits on, asked of ``asked``: the first of its ranking with
        nothing queued by any reader (:meth:`backlog`), not suspect or quiet, not one that ``refused`` a
        make of it, if it would make it sooner (:meth:`finish`) than the hosts asked would (a
        slow host, or one with earlier work queued; ``video_samples``: as :meth:`finish`), or
        if every host asked is late: the reader has waited on it ``waited`` seconds (since it
        asked, or since its head began to wait if later), longer than the host's own
        :meth:`finish` of it says now (a host behind its word: a queue grown while it was
        paused, work the reader does not see), a backup request after the expected latency
        ("The Tail at Scale"). 128 simulated hosts, sigma 0.2: 32 readers 0.73 of the hosts'
        capacity without the late rule, 0.78 with it (docs/scaling.md). The host's queue takes
        the video; None: no copy (a host silent for ``hedge_s`` is :meth:`hedges`'s)."""
        hosts = [h for h in asked if h in self.hosts]
        free = [h for h in self.idle(now) if h not in asked and h not in refused]
        if not free:
            return None
        pick = rank_hosts(video, free, self.weights())[0]  # the one every reader waiting on it picks
        late = bool(hosts) and all(waited > self.finish(h, samples, position, now, video_samples) for h in hosts)
        if not late and not self._sooner(pick, hosts, samples, position, now, video_samples):
            return None
        self.ask(pick, epoch, video, samples, now, position)
        return pick

    def _sooner(self, pick: str, hosts: Sequence[str], samples: int, position: Optional[int], now: float,
                video_samples: Optional[int]) -> bool:
        """``pick`` would make the video (:meth:`finish`) before every host of ``hosts`` made
        what it makes first: before they start it."""
        clears = min((self.finish(h, 0, position, now) for h in hosts), default=0.0)
        return self.finish(pick, samples, position, now, video_samples) < clears

    def share(self, host: str, epoch: int, video: str, samples: int, now: float, position: Optional[int],
              video_samples: Optional[int], idle: Sequence[str], exclude: Collection[str] = ()) -> Optional[str]:
        """Where ``video`` (``samples`` of it for this reader, first needed at ``position``),
        queued on ``host``, is moved to be made sooner: the first of its ranking among ``idle``
        (:meth:`idle`; none of ``exclude``) if it would make it before ``host`` starts it
        (:meth:`copy`'s rule); None: it stays. Its queue moves when ``host`` says it moved it
        (:meth:`moved`): a host that died before it answers keeps it, hedged as any video of a
        silent host, and the pick stays free for a copy of it."""
        s = self.hosts.get(host)
        ev = (epoch, video)
        free = [h for h in idle if h != host and h not in exclude]
        if s is None or ev not in s.queued or not free:
            return None
        pick = rank_hosts(video, free, self.weights())[0]
        if not self._sooner(pick, [host], samples, position, now, video_samples):
            return None
        return pick

    def idle(self, now: float) -> List[str]:
        """The hosts nothing is queued on by any reader (:meth:`backlog`) that answer (neither
        suspect nor quiet): those a copy may go to (:meth:`copy`)."""
        return [h for h in self.hosts if self.backlog(h, now) <= 0 and not self.suspect(h, now)
                and not self.quiet(h, now)]

    def hedges(self, waiting: Iterable[Tuple[int, str, int]], now: float,
               refused: Optional[Mapping[str, Collection[str]]] = None,
               awaited: Optional[Mapping[str, Collection[str]]] = None,
               due: Optional[Mapping[str, Optional[float]]] = None,
               video_samples: Optional[Mapping[str, int]] = None) -> List[Tuple[int, str, str]]:
        """Of the videos a reader waits on (``(epoch, video, samples)``), those it awaits only of
        hosts that answered nothing for ``hedge_s`` (``awaited``: video -> the hosts its requests
        in flight went to; default: the hosts this router asked) and needs soon: each asked of
        the next host of its ranking too that answers (neither suspect nor quiet), not one that
        refused a make of it (``refused``: video -> hosts), whatever its load (every host quiet:
        the first of them). Every reader of a job that waits on the video hedges it to that one
        host, whose one decode then answers them all; picked by the bounded load
        (:meth:`route`), each reader's pick followed its own view of the queues, and one
        reader's hedge of a clip the job's last step waited on went to a host of 0.57x that
        stalled in turn, another reader's to one of 1.74x (128 simulated hosts, 32 readers,
        sigma 0.5, seeds 0-3: 0.871-0.890 of the hosts' capacity at 1.021 decodes a clip,
        against 0.854-0.885 at 1.030: docs/scaling.md). ``due``: video -> seconds until the
        reader's head needs it (missing or None: now); a video due later than ``hedge_s`` and a
        worker's decode of it (:meth:`decode_s`, ``video_samples``: its whole decode, default
        ``samples``) stays with its silent host, which may come back (a paused process) and
        make it in time, until it comes that near: hedging a silent host's whole queue at once
        decodes all of it twice when the host comes back (128 simulated hosts stalling 10 s every
        300 s on average, seeds 0-2, 1-32 readers: 0.001-0.011 fewer decodes a clip, the share of
        the hosts' capacity within 0.005: docs/scaling.md). Returns ``(epoch, video, host)`` for each new copy."""
        out = []
        for epoch, video, samples in waiting:
            hosts = self.asked.get((epoch, video), ()) if awaited is None else awaited.get(video, ())
            asked = [h for h in hosts if h in self.hosts]
            if asked and not all(self.suspect(h, now) for h in asked):
                continue
            d = None if due is None else due.get(video)
            if d is not None and d > self.hedge_s + self.decode_s((video_samples or {}).get(video, samples)):
                continue
            ranking = self._answering(video, now, {*asked, *(refused or {}).get(video, ())})
            if ranking:
                self.ask(ranking[0], epoch, video, samples, now)
                out.append((epoch, video, ranking[0]))
        return out

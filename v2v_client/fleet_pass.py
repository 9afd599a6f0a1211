"""One pass of a fleet's reader over one epoch (``fleet_read.Fleet.fetch_all``): its explicit state
and each decision of its loop, a state machine free of I/O and of torch: the hosts' messages and
the clock go in (:meth:`Pass.receive`, each method's ``now``), the messages for the hosts come out
(:attr:`Pass.outbox`), and what the pass learned for the passes after it goes into the reader's
:class:`ReaderMemory`. The ``Fleet`` does the I/O: it sends the outbox, takes the hosts' answers,
joins and leaves out hosts (:attr:`Pass.refusing`: hosts that refuse every make of this reader).

The state is the epoch's plan (``EpochPlan``, unfolding with each video's windows), the steps in
the window (the step being read, the *head*, to ``ahead`` positions past it), what each video was
asked of which host (:class:`Video`), the rows got and not yet read, and the requests in flight.
Each turn of the loop: fill the window, ask what its decided positions need and the windows that
decide the rest (:meth:`Pass.ask_window`), hand the head's rows on once each is known
(:meth:`Pass.head_rows`), else rescue what the head waits on (:meth:`Pass.rescue`: pings of quiet
hosts, hedges of silent ones, copies, moves to idle hosts, the epoch's end's copies, lost
replies) and take the hosts' answers (:func:`take`).
"""
from __future__ import annotations

import heapq
import logging
import time
from dataclasses import dataclass, field
from typing import Callable, Dict, Iterable, List, Mapping, Optional, Set, Tuple

import numpy as np

from v2v_wire.codecs import decode_batch_arrays
from v2v_wire.outputs import wire_zeros_row
from v2v_wire.fleet import QUIET_S, Router, host_key
from v2v_wire.plan import EpochPlan, Manifest, PlanIdentity
from v2v_wire.plan_messages import (MAX_MAKE_PATH, MAX_MAKE_SAMPLES, Fetch, Make, Moved, PlanAsk, PlanInfo, Refused, Rows,
                                     Withdraw)
from v2v_wire.protocol import MAX_BATCH_BYTES, ProtocolError

from .fetch import BrokenPeer, PlanServerError, _with_padding

__all__ = ["Pass", "ReaderMemory", "Flights", "Video", "merged", "refused", "steal", "share_idle", "back_up",
           "UNFOLD_PER_HOST", "STEAL_S", "IDLE_SCAN", "SHARE_S", "HOST_REFUSALS"]

log = logging.getLogger("v2v.client")

#: Videos whose windows a reader asks for at once while its plan unfolds, per host.
UNFOLD_PER_HOST = 4
#: Videos a reader looks at per idle host (:func:`share_idle`), the first its plan needs of those
#: it awaits: the rest are further from the head than a move is worth.
IDLE_SCAN = 16
#: Seconds between a reader's looks for idle hosts (:func:`share_idle`): a turn comes with each
#: answer, hundreds a second over 128 hosts, and a look scans what the reader awaits; a clip's
#: decode takes seconds, so a host idle for a quarter of one costs little.
SHARE_S = 0.25
#: Seconds the head may wait on a video before the next host of its ranking is asked for a copy
#: too (:func:`steal`).
STEAL_S = 1.0
_LAST = 2 ** 62 - 1
#: Refusal codes (``plan_messages.REFUSALS``) that say a host serves none of this reader's makes:
#: outputs it does not serve, a compression it lacks. The host is left out; a refusal for another
#: plan leaves it out of the pass (``Fleet.other_plan``: a host restarted on a corpus that
#: changed); any other refusal is of the one make, asked of another host while the host stays.
HOST_REFUSALS = ("outputs", "compression")


def merged(rows: List[tuple], like: Dict[str, np.ndarray], epoch: int, start: int,
           samples: Optional[int]) -> Tuple[Rows, Dict[str, np.ndarray]]:
    """One step's ``Rows`` and arrays from its rows in position order (``(sample id, padding,
    params, arrays row, host)``; a padding row's arrays are zeros shaped as ``like``'s)."""
    arrays = {name: np.stack([r[3][name] if not r[1] else np.zeros_like(like[name]) for r in rows]) for name in like}
    return Rows(0, epoch, start, [r[0] for r in rows], [r[1] for r in rows], [r[2] for r in rows], [],
                samples), arrays


def _zeros(stream: Optional[dict], outputs) -> Optional[Dict[str, np.ndarray]]:
    """A row of zeros of each of ``outputs`` as a host's reply of padding rows only holds it, from
    the hosts' ``stream`` info (its shapes); None without them."""
    if not stream or not {"sequence_length", "num_bins", "crop_size"} <= set(stream):
        return None
    return {o: wire_zeros_row(o, stream) for o in outputs or stream["outputs"]}


@dataclass
class ReaderMemory:
    """What a reader of a fleet keeps across its passes (one per process: ``servers.Servers``
    holds it, pickled to its DataLoader workers), each updated in place by the passes:

    * ``windows``: video path -> the windows its file gives, as the manifest or a host said;
    * ``rates``: host endpoint -> the samples/s it said (an unchanged fleet routes each video
      where it did);
    * ``made``: video path -> the host whose rows of it were read last (its frame cache holds
      the video: ``Router.route``'s ``held``);
    * ``same``: endpoint -> the endpoint of the same host read in its place
      (``fleet_read.alias_of``: each said once);
    * ``known``: manifest fingerprint -> the manifest, of the plans read (a pass no host serves
      any more names the files changed since);
    * ``left_out``: peer endpoint -> why it is left out (``fleet_read.Fleet.leave_out``: each
      named once)."""

    windows: Dict[str, int] = field(default_factory=dict)
    rates: Dict[str, float] = field(default_factory=dict)
    made: Dict[str, str] = field(default_factory=dict)
    same: Dict[str, str] = field(default_factory=dict)
    known: Dict[str, Manifest] = field(default_factory=dict)
    left_out: Dict[str, str] = field(default_factory=dict)


class Flights(dict):
    """``(host, request id) -> (video, ordinals)``: a pass's makes in flight, by host in
    :attr:`hosts` (host -> its requests in flight; the ``Router``'s ``awaited``, so a host it
    awaits a request of is pinged and, silent, hedged whatever its queue holds); in :attr:`moves`,
    the host each move in flight moves its video to, and when it was asked (asked again after
    ``retry_s``, a move is asked as one), of which those in :attr:`held` its host kept
    (:meth:`kept`); and in :attr:`sent`, a heap of ``(when asked, request, video)`` (one entry
    a request, left behind when it is answered: :meth:`Pass.rescue` skips those). Taken out by
    ``del`` and ``pop``, with its move."""

    def __init__(self):
        super().__init__()
        self.hosts: Dict[str, Set[Tuple[str, int]]] = {}
        self.moves: Dict[Tuple[str, int], Tuple[str, float]] = {}
        self.held: Set[Tuple[str, int]] = set()
        self.sent: List[Tuple[float, Tuple[str, int], str]] = []

    def __setitem__(self, key: Tuple[str, int], value) -> None:
        self.hosts.setdefault(key[0], set()).add(key)
        super().__setitem__(key, value)

    def __delitem__(self, key: Tuple[str, int]) -> None:
        super().__delitem__(key)
        self._less(key)
        self.moves.pop(key, None)
        self.held.discard(key)

    def pop(self, key: Tuple[str, int], *default):
        if key in self:
            self._less(key)
            self.moves.pop(key, None)
            self.held.discard(key)
        return super().pop(key, *default)

    def destinations(self, kept: bool = True) -> Set[str]:
        """The hosts the moves in flight go to (each taken until its video's holder answers;
        ``kept`` False: not those of the moves :attr:`held`)."""
        return {to for key, (to, _) in self.moves.items() if kept or key not in self.held}

    def moving(self, requests, kept: bool = True) -> bool:
        """Whether one of ``requests`` (``(host, request id)``) is a move in flight (``kept``
        False: one not :attr:`held`)."""
        return any(r in self.moves and (kept or r not in self.held) for r in requests)

    def kept(self, heard: Callable[[str], Optional[float]], now: float) -> None:
        """Count as kept by their hosts (:attr:`held`) the moves asked :data:`QUIET_S` or more
        before ``now`` of a host heard since (``heard(host)``: when it last answered, None: not
        a host of the fleet). A host answers a move it places elsewhere (``Moved``) within its
        server loop's poll, whatever its workers do, and keeps one whose decode it started
        (``Make.move``) without a word until the rows. The epoch's end copies such a video
        (:func:`back_up`, which looks past the moves held): taken for in flight until the rows,
        a kept move stopped its copy while the job's last steps waited on slow hosts' decodes
        (128 simulated hosts, seed 0, sigma 0.5: 32 readers 0.874 -> 0.899 of the hosts'
        capacity, one reader 0.923 both, at 1.023 and 1.007 decodes a clip). The moves to idle
        hosts (:func:`share_idle`) still wait for the rows: freeing the idle host a kept move
        named for the next move made one reader 0.880. A kept move asked again after
        ``retry_s`` is asked as a move: a host that lost it moves it, one that started it
        keeps it again."""
        for key, (_, at) in self.moves.items():
            if key not in self.held and now - at >= QUIET_S:
                last = heard(key[0])
                if last is not None and last > at:
                    self.held.add(key)

    def _less(self, key: Tuple[str, int]) -> None:
        keys = self.hosts[key[0]]
        keys.discard(key)
        if not keys:
            del self.hosts[key[0]]


@dataclass
class Video:
    """What this reader asked of one video in one pass: the host it asks, the first position that
    needs it (its makes are asked at :meth:`Pass.start_by` of it), the samples asked (ordinal -> request id),
    and the requests in flight ((host, request id) -> (host, ordinals, asked at): each host
    numbers its requests itself), the hosts that refused a make of it (it is asked of others),
    whether its arbiter placed it at a host this reader does not read (``here``: the
    arbiter is asked to make it itself, not asked where it is placed again), and whether it was
    moved to an idle host (``shared``: once a pass, :func:`share_idle`; hosts whose placements
    of it name each other would otherwise pass it back and forth), and whether it was copied at
    the epoch's end (``backed``: once a pass, :func:`back_up`)."""

    host: Optional[str] = None
    position: int = _LAST
    asked: Dict[int, int] = field(default_factory=dict)
    flight: Dict[Tuple[str, int], Tuple[str, Optional[Tuple[int, ...]], float]] = field(default_factory=dict)
    refused: Dict[str, str] = field(default_factory=dict)
    here: bool = False
    shared: bool = False
    backed: bool = False

    @property
    def holders(self) -> Set[str]:
        """The hosts its requests in flight went to."""
        return {h for h, _, _ in self.flight.values()}

    @property
    def first_asked(self) -> float:
        """When the first of its requests in flight was asked (it has one at least)."""
        return min(at for _, _, at in self.flight.values())


class Pass:
    """One epoch read from a fleet (module docstring).

    Args:
        router: the reader's view of the hosts (``v2v_wire.fleet.Router``: who serves, their
            queues and rates, the placement rules); the ``Fleet`` joins and leaves hosts in it.
        memory: what the reader keeps across passes (:class:`ReaderMemory`; updated).
        manifest: the plan's manifest.
        identity: the plan read (its identity: every make names it).
        first: the :class:`Fetch` of the pass's first step (its epoch and outputs are the pass's).
        prefetch: steps the window holds at least.
        retry_s: seconds a make may go unanswered before it is asked again.
        endpoint: the fleet's endpoint spec, as errors name it.
        withdraws: the hosts that said they take a ``Withdraw`` (the ``Fleet``'s set, read live).
        named: peers named as left out already (the ``Fleet``'s, read live): a ``Moved`` to one
            is not named again.
        stream: the hosts' stream info (a padding row's shapes before any row), else learned
            from the first ``PlanInfo`` of the plan.
        ahead: positions past the head whose videos are asked for (None: :attr:`ahead`'s rule).
        now: the clock's reading at start (default ``time.monotonic()``).
        reader: this reader's index among the job's readers and their count (ranks times
            DataLoader workers: ``(rank * workers + worker, ranks * workers)``): each idle host is
            the one reader's of the job its key falls to (:func:`share_idle`).

    Outputs: :attr:`outbox` (``(host endpoint, message)``: ``Make``, ``PlanAsk``, ``Withdraw``;
    a make's ``compression`` is its link's, set as the ``Fleet`` sends it), :attr:`refusing`
    (``(host, refusal code, message)`` of a host that refuses every make of this reader: the
    ``Fleet`` leaves it out), and :attr:`last_served` (the last step's rows by host).
    """

    def __init__(self, router: Router, memory: ReaderMemory, manifest: Manifest, identity: PlanIdentity,
                 first: Fetch, prefetch: int, retry_s: float, endpoint: str = "", withdraws: Set[str] = frozenset(),
                 named: Optional[Mapping[str, str]] = None, stream: Optional[dict] = None, ahead: Optional[int] = None,
                 now: Optional[float] = None, reader: Tuple[int, int] = (0, 1)):
        self.router, self.memory, self.identity, self.prefetch, self.retry_s = router, memory, identity, prefetch, retry_s
        self.endpoint, self.withdraws, self.stream, self.fixed_ahead = endpoint, withdraws, stream, ahead
        self.named = {} if named is None else named
        self.epoch, self.outputs, self.kpw = first.epoch, first.outputs, manifest.crops_per_window
        self.plan = EpochPlan(manifest, identity.seed, first.epoch, identity.shuffle_buffer)
        self.plan.learn(memory.windows)
        self.outbox: List[Tuple[str, object]] = []
        self.refusing: List[Tuple[str, str, str]] = []
        self.requests: Dict[str, int] = {}  # host -> the last request id asked of it (each host numbers its own)
        self.like: Optional[Dict[str, np.ndarray]] = None  # one row of each array: a padding row's zeros
        self.last_served: Tuple[Optional[Rows], Dict[str, int]] = (None, {})  # the last step's rows by host
        self.window: List[int] = []
        self.spans: Dict[int, Tuple[int, int]] = {}
        self.videos: Dict[str, Video] = {}
        self.got: Dict[Tuple[str, int], tuple] = {}  # (video, ordinal) -> (id, padding, params, arrays row, host)
        self.flight = Flights()  # (host, request) -> asked
        router.awaited = self.flight.hosts
        self.told: Set[str] = set()  # videos whose windows were asked for
        self.unread: Set[str] = set()  # hosts an arbiter placed a video at that this pass does not ask: named once
        self.parked: List[Tuple[str, Optional[Tuple[int, ...]]]] = []  # asks no host could take yet
        self.head_since = time.monotonic() if now is None else now
        self.exhausted = False
        self._windows = (-1, 0)  # (videos whose windows are known, their windows summed): per_video's
        self.reader = reader
        self.shared_at = -SHARE_S  # when share_idle last looked
        self.backed_at = -SHARE_S  # when back_up last looked
        self.examined = 0  # the first position of the window :meth:`ask_window` has not looked at

    @property
    def ahead(self) -> int:
        """Positions the window spans: the reader's (``ahead``), else the router's decodes ahead
        (``Router.ahead_decodes``) of two windows' samples each, of the hosts serving now (a fleet
        that grows mid-pass is asked ahead for all; a host's share grows once it is measured)."""
        if self.fixed_ahead is not None:
            return self.fixed_ahead
        return (self.router.ahead_decodes() or 1) * self.kpw * 2

    @property
    def at_end(self) -> bool:
        """The window holds the epoch's last step (the steps to read are all taken)."""
        return self.exhausted or self.plan.complete and bool(self.window) and \
            self.spans[self.window[-1]][1] >= len(self.plan)

    # ------------------------------------------------------------------ asking
    def add(self, step: int, fetch: Fetch) -> None:
        """Step ``step`` (positions ``fetch.start`` .. ``fetch.stop - 1``) joins the window."""
        self.window.append(step)
        self.spans[step] = (fetch.start, fetch.stop)

    def reach(self, now: float) -> int:
        """Positions the window spans at ``now``: :attr:`ahead`, slid while the head waits on the
        hosts (``Router.slide`` of the seconds since :attr:`head_since`); a fixed ``ahead`` does
        not slide."""
        if self.fixed_ahead is not None:
            return self.fixed_ahead
        return self.router.slide(self.ahead, now - self.head_since)

    def fill(self, todo, fetch_of, now: Optional[float] = None) -> None:
        """Take steps from ``todo`` until the window spans :meth:`reach` positions (``now``
        None: :attr:`ahead`) and ``prefetch`` steps."""
        reach = self.ahead if now is None else self.reach(now)
        while not self.exhausted and (self.spans[self.window[-1]][0] - self.spans[self.window[0]][0] < reach
                                      or len(self.window) < self.prefetch):
            nxt = next(todo, None)
            if nxt is None:
                self.exhausted = True
                return
            f = fetch_of(0, nxt)
            self.add(nxt, f)
            if self.plan.complete and f.start >= len(self.plan):
                return  # past the epoch's end: no step after it holds a sample

    def send(self, video: str, ordinals: Optional[Tuple[int, ...]], host: str, now: float,
             spill: Optional[str] = None, here: bool = False, move: bool = False) -> None:
        """Ask ``host`` for ``ordinals`` of ``video`` (None: its windows): of the video's arbiter
        (``Router.arbiter``), to be made there unless a reader placed it elsewhere, or (``spill``)
        placed at that host unless the arbiter holds it (``Make.route``), or (``move``, with
        ``spill``) moved off ``host`` to ``spill`` unless it started it (``Make.move``,
        :meth:`rebalance`); of another host, or (``here``) made there: asked of one that said
        where it is placed, or a copy (a hedge, a backup request), which an arbiter would move
        back to the host it copies."""
        req = self.requests[host] = self.requests.get(host, 0) + 1
        v = self.videos.setdefault(video, Video())
        route = spill if spill is not None else "" if not (here or v.here) and host == self.router.arbiter(video, now) \
            else None
        self.outbox.append((host, Make(req, self.epoch, video, ordinals, self.outputs, self.identity, "none",
                                       self.start_by(video), route, move)))
        self.router.awaits(host, now)
        self.flight[(host, req)] = (video, ordinals)
        heapq.heappush(self.flight.sent, (now, (host, req), video))
        if move and spill is not None:
            self.flight.moves[(host, req)] = (spill, now)
        v.flight[(host, req)] = (host, ordinals, now)
        for o in ordinals or ():
            v.asked[o] = req

    def ask(self, video: str, ordinals: Optional[Tuple[int, ...]], now: float, position: Optional[int] = None) -> None:
        """Ask for ``ordinals`` of ``video`` of its host while that one answers, else the router's pick.

        With no host to ask (every host gone, silent, left out or not joined yet) it is parked:
        asked at the next :meth:`rescue` (the ``Fleet`` fails a pass whose every host is left out).

        Raises:
            PlanServerError: a path longer than a make names, or every host refused a make of the
                video (the last refusal's line)."""
        v = self.videos.setdefault(video, Video())
        if position is not None:
            v.position = min(v.position, position)
        if len(video.encode()) > MAX_MAKE_PATH:
            raise PlanServerError(f"{video[:80]}...: a path over {MAX_MAKE_PATH} bytes, which a fleet's make "
                                  "cannot name: read these hosts as shards (v2v-serve --shard I/N)")
        if ordinals is not None and len(ordinals) > MAX_MAKE_SAMPLES:
            for i in range(0, len(ordinals), MAX_MAKE_SAMPLES):
                self.ask(video, ordinals[i:i + MAX_MAKE_SAMPLES], now)
            return
        count = self.asked_samples([ordinals])
        if v.refused and all(h in v.refused for h in self.router.hosts):
            ep, why = next(reversed(v.refused.items()))
            raise PlanServerError(f"{ep}: {why} (every host of the fleet refused a make of it)")
        spill = None
        if v.host in self.router.hosts and not self.router.suspect(v.host, now) and v.host not in v.refused:
            self.router.ask(v.host, self.epoch, video, count, now, self.start_by(video))
        else:
            v.host = self.router.route(self.epoch, video, count, now, exclude=list(v.refused), due=self.due(v.position),
                                       position=self.start_by(video), held=self.memory.made.get(video),
                                       video_samples=self.video_samples(video))
            arbiter = self.router.arbiter(video, now)
            if v.host is not None and arbiter not in (None, v.host) and arbiter not in v.refused:
                spill, v.host = v.host, arbiter  # asked of the arbiter, to place it there
                self.router.moved(self.epoch, video, spill, arbiter, now)
        if v.host is not None:
            self.send(video, ordinals, v.host, now, spill)
        else:
            self.parked.append((video, ordinals))  # every host gone, silent or not joined yet: asked at the next rescue

    def per_video(self) -> int:
        """Samples a video gives, on average over those whose windows are known (a make of a
        video's windows decodes all of them)."""
        w = self.memory.windows
        if self._windows[0] != len(w):  # learned elsewhere than :meth:`receive`: counted again
            self._windows = (len(w), sum(w.values()))
        return max(1, round(self.kpw * self._windows[1] / self._windows[0])) if w else self.kpw

    def asked_samples(self, ordinals: Iterable[Optional[Tuple[int, ...]]]) -> int:
        """Samples the makes asking ``ordinals`` (each a make's; None: a video's windows, counted
        as :meth:`per_video`) ask in all: what a move or copy of them queues on its host."""
        return sum(len(ords) if ords else self.per_video() for ords in ordinals)

    def video_samples(self, video: str) -> int:
        """Samples a host's decode of ``video`` makes, every window's, whichever of them this
        reader asks (``Router.finish``): its windows where known, else :meth:`per_video`."""
        windows = self.memory.windows.get(video)
        return windows * self.kpw if windows else self.per_video()

    def start_by(self, video: str) -> int:
        """The position ``video`` is asked at (``Make.position``: its hosts work their makes in
        that order): ``Router.start_by`` of the first position needing it, so a long video is
        started a decode's time before the head needs it (unknown: past every known one)."""
        v = self.videos[video]
        return _LAST if v.position >= _LAST else self.router.start_by(v.position, self.video_samples(video))

    def due(self, position: int) -> Optional[float]:
        """Seconds until the head reaches ``position`` at the fleet's rate (None: a position past
        the plan's known ones, or no host to make it)."""
        if position >= _LAST or not self.window or not self.router.hosts:
            return None
        return max(0.0, position - self.spans[self.window[0]][0]) / self.router.capacity()

    def ask_window(self, now: float) -> None:
        """Ask for the samples the window's decided positions hold, and for the windows of the
        next videos of the production order where the plan is not decided that far."""
        want: Dict[str, List[int]] = {}
        first: Dict[str, int] = {}
        undecided = False
        for s in self.window:  # each position once: from the first not looked at to the first undecided
            start, stop = self.spans[s]
            for p in range(max(start, self.examined), stop):
                if p >= self.plan.known:
                    undecided = not self.plan.complete
                    break
                key = self.plan.key(p)
                o = key.ordinal(self.kpw)
                if (key.video, o) not in self.got and o not in self.videos.get(key.video, Video()).asked:
                    want.setdefault(key.video, []).append(o)
                    first.setdefault(key.video, p)
                self.examined = p + 1
            if undecided or self.plan.complete and stop > self.plan.known:
                break
        for video, ords in want.items():
            self.ask(video, tuple(sorted(set(ords))), now, first[video])
        if not undecided:
            return
        budget = UNFOLD_PER_HOST * max(1, len(self.router.hosts)) - sum(
            1 for _, ords in self.flight.values() if ords is None)
        position = self.plan.known  # where the videos unfolding next put their samples, about
        for video in self.plan.next_videos(len(self.plan.videos)):
            if budget <= 0:
                return
            if video not in self.memory.windows and video not in self.told:
                self.told.add(video)
                self.ask(video, None, now, position)
                budget -= 1
            position += self.per_video()

    def rebalance(self, host: str, now: float) -> None:
        """Host ``host`` said its first rate: the videos this reader asked of it that it would
        make late at that rate (``Router.overdue``; a host is loaded before its first decodes
        measure it) are asked of it again as a move to the host ``Router.move_off`` picks
        (``Make.move``): unless it started the video, it answers every reader's make of it
        waiting there with ``Moved``, so the video is still made once. Only of a host that takes
        a ``Withdraw`` (one that does not would not move it either)."""
        s = self.router.hosts.get(host)
        if s is None or host not in self.withdraws:
            return
        mine = [video for e, video in s.queued if e == self.epoch and video in self.videos]
        due = {video: self.due(self.videos[video].position) for video in mine}
        whole = {video: self.video_samples(video) for video in mine}
        for video in self.router.overdue(host, self.epoch, now, due, whole):
            v = self.videos[video]
            flights = [(hr, ords) for hr, (h, ords, _) in v.flight.items() if h == host]
            if v.host != host or not flights:
                continue
            count = self.asked_samples(ords for _, ords in flights)
            pick = self.router.move_off(host, self.epoch, video, count, now, due[video], self.start_by(video),
                                        whole[video], exclude=list(v.refused))
            if pick is None:
                continue
            for hr, ords in flights:  # the host answers the make it replaces with Moved too
                del v.flight[hr]
                self.flight.pop(hr, None)
                self.send(video, ords, host, now, spill=pick, move=True)

    # ------------------------------------------------------------------ the head
    def head_rows(self, now: Optional[float] = None) -> Optional[Tuple[int, Rows, Dict[str, np.ndarray]]]:
        """``(step, rows, arrays)`` of the head once each of its positions is known (made,
        failed or past the epoch's end), its samples taken out of what was got; None before.

        Raises:
            PlanServerError: a step of padding rows only before any reply, from a host that
                did not say its stream's shapes (they are not known)."""
        head = self.window[0]
        start, stop = self.spans[head]
        if stop > self.plan.known and not self.plan.complete:
            return None
        keys = [self.plan.key(p) for p in range(start, stop)]
        rows = []
        for key in keys:
            if key is None:
                rows.append((None, True, {"padding": "past the epoch's end"}, None, None))
            elif (key.video, key.ordinal(self.kpw)) in self.got:
                rows.append(self.got[(key.video, key.ordinal(self.kpw))])
            else:
                return None
        for key in keys:
            if key is not None:
                del self.got[(key.video, key.ordinal(self.kpw))]
        like = next((r[3] for r in rows if not r[1]), self.like) or _zeros(self.stream, self.outputs)
        if like is None:
            raise PlanServerError(f"{self.endpoint}: epoch {self.epoch} positions {start}..{stop - 1}: no row "
                                  "holds a sample and none was read before (the arrays' shapes are not known)")
        out, arrays = merged(rows, like, self.epoch, start, len(self.plan) if self.plan.complete else None)
        self.last_served = (out, {h: sum(1 for r in rows if r[4] == h) for h in {r[4] for r in rows if not r[1]}})
        self.window.pop(0)
        del self.spans[head]
        self.head_since = time.monotonic() if now is None else now
        return head, out, arrays

    def turn(self, todo, fetch_of, now: float, hold: bool = False) -> Optional[Tuple[int, Rows, Dict[str, np.ndarray]]]:
        """The pass's part of a turn (``Fleet.turn``): the window filled from ``todo`` and asked
        for, then the head's rows (:meth:`head_rows`) and the quiet hosts pinged (:meth:`ping`),
        else, the head not known or held (``hold``: the loop holds the steps it may), what it
        waits on rescued (:meth:`rescue`). Returns the head, or None.

        Raises:
            PlanServerError: as :meth:`ask` and :meth:`head_rows`."""
        self.fill(todo, fetch_of, now)
        self.ask_window(now)
        head = None if hold else self.head_rows(now)
        if head is None:
            self.rescue(now)
        else:
            self.ping(now)
        return head

    def wanted(self, now: float) -> None:
        """The reader wants the head's rows from ``now`` on (its loop took a step):
        the head waits on the hosts from then, not while the trainer ran (:meth:`reach`, the
        copies of :func:`steal`)."""
        self.head_since = max(self.head_since, now)

    # ------------------------------------------------------------------ what the head waits on
    def ping(self, now: float) -> None:
        """Ping the hosts ``Router.pings`` names (a ``PlanAsk``: a host's server loop answers it
        whatever its workers do), at every turn, the head's rows had or not: a host making a long
        video for this reader says nothing else meanwhile, and a reader that pinged only while its
        head waited took a host it had not pinged for a while for silent at its next wait."""
        for h in self.router.pings(now):
            self.outbox.append((h, PlanAsk()))

    def rescue(self, now: float) -> None:
        """Hedges of silent hosts' videos, copies of what the head waits on, moves to idle hosts
        (:func:`share_idle`), copies to idle hosts at the epoch's end (:func:`back_up`, the
        moves their hosts kept counted first: ``Flights.kept``), makes asked again (of the next
        hosts for a host gone, of the same after ``retry_s``: a lost reply, a restart), and the
        asks no host could take before."""
        self.ping(now)
        parked, self.parked = self.parked, []
        for video, ords in parked:
            self.ask(video, ords, now)
        # what a turn looks at is what is awaited of silent hosts, hosts gone and late answers,
        # not every request in flight: a turn of a pass over 128 hosts holds thousands in flight
        silent = {h for h in self.router.hosts if self.router.suspect(h, now)}
        out = [h for h in self.flight.hosts if h in silent or h not in self.router.hosts]
        awaited = {}  # the videos awaited only of silent hosts or hosts gone: the hedges' candidates
        for video in sorted({self.flight[hr][0] for h in out for hr in self.flight.hosts[h]},
                            key=lambda video: (self.videos[video].position, video)):
            hosts = self.videos[video].holders
            if all(h in silent or h not in self.router.hosts for h in hosts):
                awaited[video] = hosts
        waiting = [(self.epoch, video, len(self.videos[video].flight)) for video in awaited]
        due = {video: self.due(self.videos[video].position) for video, hosts in awaited.items() if hosts & silent}
        for _, video, host in self.router.hedges(waiting, now, {video: self.videos[video].refused for video in awaited
                                                                 if self.videos[video].refused}, awaited, due,
                                                 {video: self.video_samples(video) for video in due}):
            v = self.videos[video]
            v.host = host
            for h, ords, _ in list(v.flight.values()):
                self.send(video, ords, host, now, here=True)  # a hedge is made where asked, not moved back
        hosts = self.router.hosts
        self.flight.kept(lambda h: hosts[h].heard if h in hosts else None, now)
        steal(self, now, now - self.head_since >= STEAL_S)
        share_idle(self, now)
        back_up(self, now)
        for h in [h for h in self.flight.hosts if h not in self.router.hosts]:
            for hr in sorted(self.flight.hosts.get(h, ())):  # left the fleet: its videos go to the
                video, ords = self.flight.pop(hr)  # next hosts of their rankings
                v = self.videos[video]
                del v.flight[hr]
                v.host = None if v.host == h else v.host
                self.ask(video, ords, now)
        sent = self.flight.sent
        while sent and now - sent[0][0] >= self.retry_s:  # unanswered for retry_s: a lost reply, a restart
            _, hr, video = heapq.heappop(sent)
            if hr not in self.flight:
                continue  # answered, or asked again already
            h, ords, _ = self.videos[video].flight[hr]
            # asked again (a move as a move) before the request it replaces is dropped, so the
            # host's silence counts on
            spill = self.flight.moves.get(hr, (None,))[0]  # a move kept is asked as a move again
            self.send(video, ords, h, now, spill=spill, move=spill is not None)
            del self.videos[video].flight[hr]
            self.flight.pop(hr, None)

    def receive(self, ep: str, msg, frames, now: float) -> None:
        """Take host ``ep``'s message: what a new host serves, a make's rows (kept by (video,
        ordinal); its video's windows unfold the plan), or a refusal (:func:`refused`); the
        first rate it says moves what it would make late (:meth:`rebalance`).

        Raises:
            BrokenPeer: rows whose arrays cannot be read.
            PlanServerError: every host refused a make of the video."""
        measured = ep in self.router.hosts and bool(self.router.hosts[ep].rate)
        self._take(ep, msg, frames, now)
        if not measured and ep in self.router.hosts and self.router.hosts[ep].rate:
            self.rebalance(ep, now)  # its first rate

    def _take(self, ep: str, msg, frames, now: float) -> None:
        if isinstance(msg, PlanInfo):  # a new host's (the Fleet joins it), or a ping's answer: alive, with its rate and queue
            self.router.heard(ep, now, msg.rate, msg.queued)
            if self.stream is None and not self.identity.problem(msg.plan):
                self.stream = msg.stream
            return
        if isinstance(msg, Moved):
            self.moved(ep, msg, now)
            return
        if isinstance(msg, Refused):
            refused(self, ep, msg, now)
            return
        what = self.flight.get((ep, msg.request)) if isinstance(msg, Rows) else None
        if what is None or msg.epoch != self.epoch:  # another pass's answer to a number this one asks: still in flight
            if isinstance(msg, Rows) and ep in self.router.hosts:
                self.router.heard(ep, now, msg.rate, msg.queued)  # it answers: not silent
            return  # an answer to a request asked again or beaten by a copy, or of another pass
        video, ordinals = what
        try:  # read before the make counts as answered: a peer that breaks the protocol leaves it in flight
            if len(msg.padding) != len(ordinals or ()):
                raise ProtocolError(f"{len(msg.padding)} rows for the {len(ordinals or ())} samples asked")
            arrays = _with_padding(decode_batch_arrays(msg.arrays, frames, MAX_BATCH_BYTES), msg.padding)
        except ProtocolError as e:
            raise BrokenPeer(ep, f"rows of {video}: {e}") from None
        del self.flight[(ep, msg.request)]
        v = self.videos[video]
        v.flight.pop((ep, msg.request), None)
        if msg.windows is not None and video not in self.memory.windows:
            self.memory.windows[video] = msg.windows
            if self._windows[0] == len(self.memory.windows) - 1:
                self._windows = (self._windows[0] + 1, self._windows[1] + msg.windows)
            self.plan.learn(self.memory.windows)
        if v.host != ep and (ordinals is None or any((video, o) not in self.got for o in ordinals)):
            v.host = ep  # it answered first: it holds the video's samples (and frames) for the asks that follow
        for j, o in enumerate(ordinals or ()):
            if (video, o) in self.got:
                continue  # another copy came first
            row = {name: a[j] for name, a in arrays.items()}
            self.got[(video, o)] = (msg.sample_ids[j], msg.padding[j], msg.params[j], row, ep)
            self.memory.made[video] = ep
        if self.like is None:  # a row of zeros of each array (a reply of padding rows only gives their shapes)
            self.like = {name: np.zeros(a.shape[1:], a.dtype) for name, a in arrays.items()}
        for hr, (h, ords, _) in list(v.flight.items()):  # copies of what is now got: withdrawn where they wait
            if all((video, o) in self.got for o in ords or ()) and (ords or msg.windows is not None):
                del v.flight[hr]
                self.flight.pop(hr, None)
                if h in self.withdraws:
                    self.outbox.append((h, Withdraw(hr[1])))
        self.router.answered(ep, self.epoch, video, now, not any(h == ep for h, _, _ in v.flight.values()), msg.rate,
                             msg.queued)
        if msg.rate:
            self.memory.rates[ep] = msg.rate
        if not v.flight:
            self.router.finished(self.epoch, video)


    def moved(self, ep: str, msg: Moved, now: float) -> None:
        """Host ``ep``, a video's arbiter, said the make ``msg.request`` is made at ``msg.host``:
        asked there (at ``ep`` again where this reader does not read that host: a host it has not
        joined, or one suspect)."""
        what = self.flight.pop((ep, msg.request), None)
        self.router.heard(ep, now)
        if what is None:
            return
        video, ordinals = what
        v = self.videos[video]
        v.flight.pop((ep, msg.request), None)
        to = msg.host if msg.host in self.router.hosts and not self.router.suspect(msg.host, now) \
            and msg.host not in v.refused else ep
        self.router.moved(self.epoch, video, ep, to, now)
        if v.host == ep:
            v.host = to
        if to == ep and not v.here:  # once a video a pass: its next makes ask the arbiter to make it
            v.here = True
            if msg.host not in self.named and msg.host not in self.unread:  # each host named once a pass
                self.unread.add(msg.host)
                why = "silent" if msg.host in self.router.hosts and self.router.suspect(msg.host, now) else \
                    "one that refused a make of it" if msg.host in v.refused else "a host this reader does not read"
                log.warning("%s: placed %s at %s, %s: it and the others placed there are made at their arbiters "
                            "for this pass", ep, video, msg.host, why)
        self.send(video, ordinals, to, now, here=True)


def refused(read: "Pass", ep: str, msg: Refused, now: float) -> None:
    """Host ``ep`` refused a make of ``read``'s: for another plan, or every make this reader asks
    (:data:`HOST_REFUSALS`), the host is noted in ``read.refusing`` (the ``Fleet`` leaves it out of
    the pass, ``Fleet.other_plan``, or the process, ``Fleet.leave_out``, and its videos are asked
    of their next hosts at the next :meth:`Pass.rescue`); else the one make: asked of the next
    host of the video's ranking that has not refused it, the host staying in the fleet.

    Raises:
        PlanServerError: every host refused a make of the video (:meth:`Pass.ask`)."""
    what = read.flight.get((ep, msg.request))
    if what is None:
        return  # a refusal of a request asked again, or of none (-1: a message it could not read)
    if msg.code == "plan" or msg.code in HOST_REFUSALS:  # a corpus that changed; outputs or a codec it lacks
        read.refusing.append((ep, msg.code, msg.message))
        return  # in flight still: once the host is left out, the next rescue asks it of the next host
    del read.flight[(ep, msg.request)]
    video, ordinals = what
    v = read.videos[video]
    v.flight.pop((ep, msg.request), None)
    v.refused[ep] = msg.message
    if v.host == ep:
        v.host = None
    # it answered (not silent) and holds none of the video now
    read.router.answered(ep, read.epoch, video, now, not any(h == ep for h, _, _ in v.flight.values()))
    if not any(o == ordinals for _, o, _ in v.flight.values()):  # no copy in flight elsewhere
        read.ask(video, ordinals, now)


def steal(read: "Pass", now: float, late: bool) -> None:
    """Copies of the videos the head waits on, the samples its positions hold or the windows
    that decide them (the first copy's answer wins), once the head has waited :data:`STEAL_S`
    (``late``), of the host ``Router.copy`` picks, where it goes first (its position is the
    fleet's earliest), or where the hosts asked are late by their own measure (the wait
    counted from the ask, or from when the head began to wait if later). A slow host's videos
    stop gating the fleet, at the cost of a decode where a host would otherwise idle or where
    the step would wait."""
    if not late:
        return
    start, stop = read.spans[read.window[0]]
    missing: Dict[str, Optional[List[int]]] = {}
    for p in range(start, min(stop, read.plan.known)):
        key = read.plan.key(p)
        if key is not None and (key.video, key.ordinal(read.kpw)) not in read.got:
            missing.setdefault(key.video, []).append(key.ordinal(read.kpw))
    if stop > read.plan.known and not read.plan.complete:  # the windows that decide the head
        for video in read.plan.next_videos(UNFOLD_PER_HOST * len(read.router.hosts)):
            if video not in read.memory.windows and video in read.told:
                missing.setdefault(video, None)
    for video, ords in missing.items():
        v = read.videos.get(video)
        if v is None or not v.flight:
            continue
        asked = sorted(v.holders)
        n = read.asked_samples([ords])
        waited = now - max(read.head_since, v.first_asked)
        h = read.router.copy(read.epoch, video, n, now, asked, read.start_by(video), v.refused,
                             read.video_samples(video), waited)
        if h is not None:
            read.send(video, None if ords is None else tuple(sorted(ords)), h, now, here=True)  # made where asked


def share_idle(read: "Pass", now: float) -> None:
    """The videos this reader awaits of one host, the first its plan needs, moved to the hosts
    nothing is queued on (``Router.idle``), each where ``Router.share`` says the idle host makes
    it before its host would start it: the host answers every reader's make of it waiting there
    with ``Moved`` (``Make.move``; one that started it keeps it), so it is still made once, and
    the idle host starts it at once. At an epoch's end, and wherever the window's shares came
    out uneven, an idle host takes work queued behind a slow host rather than idle while the
    job waits on that host. Only of hosts that take a ``Withdraw`` (as :meth:`Pass.rebalance`);
    at most :data:`IDLE_SCAN` videos per idle host are looked at, every :data:`SHARE_S`. A
    video is moved once a pass; until its holder answers, the move keeps the video and the idle
    host from other moves (the reader's queues change with the answer: ``Router.share``). Each
    idle host is shared by one reader of the job, the one its key falls to (``Pass.reader``):
    every reader hears a host idle at once, and each moving a video there gave 128 simulated
    readers 1.23 decodes a clip at 0.71 of the hosts' capacity (0.87 at 1.04 so:
    docs/scaling.md)."""
    if now < read.shared_at + SHARE_S:
        return
    read.shared_at = now
    index, readers = read.reader
    moving = read.flight.destinations()
    idle = [h for h in read.router.idle(now) if host_key(h) % readers == index and h not in moving]
    if not idle:
        return
    awaited = {video for hr, (video, _) in read.flight.items() if hr not in read.flight.moves}
    first = heapq.nsmallest(IDLE_SCAN * len(idle), ((read.videos[video].position, video) for video in awaited))
    for position, video in first:
        if not idle or position >= _LAST:
            return
        v = read.videos[video]
        hosts = v.holders
        if len(hosts) != 1 or not hosts <= read.withdraws or v.shared or read.flight.moving(v.flight):
            continue  # copied, hedged, moved or moving already; or a host that would not move it
        (host,) = hosts
        count = read.asked_samples(ords for _, ords, _ in v.flight.values())
        pick = read.router.share(host, read.epoch, video, count, now, read.start_by(video), read.video_samples(video),
                                 idle, v.refused)
        if pick is None:
            continue
        idle.remove(pick)  # one video a look: its queue moves there with the host's Moved
        v.shared = True
        for hr, (_, ords, _) in list(v.flight.items()):  # the host answers the make it replaces with Moved too
            del v.flight[hr]
            read.flight.pop(hr, None)
            read.send(video, ords, host, now, spill=pick, move=True)


def back_up(read: "Pass", now: float) -> None:
    """Once the window holds the epoch's last step, each video in flight of one host is copied
    where ``Router.backup`` says (MapReduce's backup tasks): the first host of its ranking well
    faster than its holder that would make it sooner, the one every reader of the job picks for
    it, where the holder would make it after the head reaches the epoch's end (:meth:`Pass.due`);
    the videos whose host has the most left first; a video in a move its host kept
    (``Flights.kept``) as any other. A video is copied once a pass, every :data:`SHARE_S` at
    most. 128 simulated hosts, whole epoch, seed 0: at sigma 0.5, 1, 8, 32 and 128 readers read
    0.923, 0.922, 0.899 and 0.864 of the hosts' capacity (0.904, 0.905, 0.871 and 0.850 with
    each reader's copies on its own share of the idle hosts), at sigma 0.2
    0.929, 0.913, 0.909 and 0.905 (0.929, 0.908, 0.901, 0.902), at 1.007-1.030 decodes a clip
    (docs/scaling.md)."""
    if not read.at_end or now < read.backed_at + SHARE_S:
        return
    read.backed_at = now
    router = read.router
    moving = read.flight.destinations(kept=False)  # a move its holder kept is no move: copied as any
    waits = []
    for video in {video for video, _ in read.flight.values()}:
        v = read.videos[video]
        hosts = v.holders
        if v.backed or len(hosts) != 1 or not hosts <= router.hosts.keys() or read.flight.moving(v.flight, kept=False):
            continue
        (host,) = hosts
        whole = read.video_samples(video)
        asked_s = now - v.first_asked
        waits.append((-router.left_s(host, whole, asked_s, now), video, host, whole, asked_s))
    end_s = read.due(len(read.plan)) or 0.0
    for _, video, host, whole, asked_s in sorted(waits):
        v = read.videos[video]
        count = read.asked_samples(ords for _, ords, _ in v.flight.values())
        pick = router.backup(read.epoch, video, count, now, host, whole, asked_s, read.start_by(video), moving, end_s)
        if pick is None:
            continue
        v.backed = True
        for _, ords, _ in list(v.flight.values()):
            read.send(video, ords, pick, now, here=True)  # made where asked

"""The simulator's fleet (``harness.fleet_sim``) read by the client's own reader: each rank a real
``v2v_client.fleet_pass.Pass`` with its own ``v2v_wire.fleet.Router`` and ``ReaderMemory``, turned
as ``fleet_read.Fleet.fetch_all``'s thread turns it (``Pass.turn``: fill, ask the window, the
head's rows and the quiet hosts pinged, else rescue; the hosts' answers taken as they come, or
after half a second), its ``Make``, ``PlanAsk`` and ``Withdraw`` messages taken by a model of
the hosts, its rows tiny arrays in real ``Rows``.

The hosts are ``fleet_sim``'s (the same corpus, speeds, workers and stalls, each host measuring
its own capacity as a server does) with a server's side of the protocol: a make with a route is
placed as ``plan_orders.Orders.place`` places it (made here, or ``Moved`` to where a reader
placed it first; a move takes every reader's make of the video waiting here along), else queued
by its ``position``; a worker decodes a whole video, making its samples in window order evenly
over the decode, and a make is answered once the samples it asks are made (``part``); a host
keeps what it made and answers a later make of it at once; a ``Withdraw`` drops a make
still waiting; a ``PlanAsk`` is answered with the host's rate and queue. A stalled host takes
nothing until its stall ends, as a paused process reads its socket only when it runs again.
Messages take no time on the way.

The job: ``ranks`` readers, each reading its slice of every step (as data-parallel ranks read
their batches), each up to ``READ_AHEAD`` + ``HELD_STEPS`` steps ahead of the slowest
(``ReadAhead``'s batches held ready, and the pass's thread's), its pass turning on while it
holds them; the trainer takes a step as soon as every rank has it. Pure and seeded: no
socket, no clock. ``python -m harness.fleet_sim`` prints its figures as the routed row, beside
the static split's.
"""
from __future__ import annotations

import heapq
import inspect
import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Set, Tuple

import numpy as np

from harness.fleet_sim import Fleet, Result, _Stalls, _speeds, corpus, said_rate
from v2v_client import V2VStreamDataset
from v2v_client.fleet_pass import STEAL_S, Pass, ReaderMemory
from v2v_client.fleet_read import HELD_STEPS
from v2v_client.read_ahead import READ_AHEAD
from v2v_server.delivery.plan_orders import TOLD_S
from v2v_wire.fleet import RateMeter, Router
from v2v_wire.plan import Manifest, PlanIdentity
from v2v_wire.plan_messages import Fetch, Make, Moved, PlanAsk, PlanInfo, Rows, Withdraw
from v2v_wire.protocol import encode_arrays

#: The readers' ``retry_s`` and ``prefetch``: ``V2VStreamDataset``'s defaults.
_DEFAULTS = inspect.signature(V2VStreamDataset).parameters
RETRY_S, PREFETCH = _DEFAULTS["retry_s"].default, _DEFAULTS["prefetch"].default
#: Seconds a pass's loop waits for an answer before it turns anyway (``Fleet.take``).
TAKE_S = 0.5
#: The outputs asked, and the hosts' stream (a padding row's shapes): one byte a sample.
OUTPUTS = ("voxel",)
STREAM = {"sequence_length": 1, "num_bins": 1, "crop_size": 1, "flow_dtype": "float16", "outputs": list(OUTPUTS)}


@dataclass(eq=False)
class _Host:
    """One host: its makes waiting by video (``(rank, request, ordinals)``), its queue of videos
    (by the first position a make asks them at), its decodes running (video -> [start, end,
    samples and busy seconds its meter counted]), the videos it made (kept), where it placed
    videos (video -> (host, when)), its workers free, and the samples the readers' makes named
    that no make of the same reader waiting here named (made already or not; a make placed
    elsewhere names none: its ``v2v_samples_asked_total``)."""

    name: str
    k: int
    free: int
    meter: RateMeter = field(default_factory=RateMeter)
    waiting: Dict[str, List[Tuple[int, int, Tuple[int, ...]]]] = field(default_factory=dict)
    queue: List[Tuple[int, int, str]] = field(default_factory=list)
    running: Dict[str, List[float]] = field(default_factory=dict)
    made: Set[str] = field(default_factory=set)
    placed: Dict[str, Tuple[str, float]] = field(default_factory=dict)
    queued: int = 0
    asked: int = 0


@dataclass(frozen=True)
class Wait:
    """A step the job waited on (:meth:`PassWorld.waited`): taken at ``taken_at`` (seconds of the
    simulated epoch), ``waited_s`` after the step before; its first rank had it at ``first_at``,
    and the last, rank ``rank``, once the rows of ``sample`` (``video#ordinal``) came from
    ``host`` at ``arrived_at``: the row the whole job waited for."""

    step: int
    taken_at: float
    waited_s: float
    first_at: float
    rank: int
    sample: str
    host: str
    arrived_at: float


@dataclass(eq=False)
class _Reader:
    """One rank's process: its pass, the steps it has yet to add, the answers it has not taken,
    the steps it handed on, and its wake-ups (only the latest counts)."""

    rank: int
    read: Pass
    todo: object
    inbox: List[Tuple[str, object, list]] = field(default_factory=list)
    yielded: int = 0
    token: int = 0
    wake_at: float = math.inf


class PassWorld:
    """One epoch of fleet ``f`` (``fleet_sim.Fleet``; ``f.lookahead`` is not used: each pass
    asks ahead by its own rule, or ``ahead`` positions: ``Pass``'s ``ahead``) read by ``f.ranks``
    real passes (module docstring)."""

    def __init__(self, f: Fleet, epoch: int = 0, routers: Optional[Sequence[Router]] = None,
                 held: Optional[Dict[str, str]] = None, ahead: Optional[int] = None):
        if f.ranks < 1 or f.step % f.ranks or (routers is not None and len(routers) != f.ranks):
            raise ValueError(f"ranks must divide step ({f.step}) and each rank have one router, got ranks={f.ranks} "
                             f"and {None if routers is None else len(routers)} routers")
        self.f, self.epoch = f, epoch
        self.slots = corpus(f)
        manifest = Manifest.of(self.slots)
        self.identity = PlanIdentity(manifest.fingerprint(), "fleet_sim", f.seed, 64)
        self.speeds = _speeds(f)
        self.names = [f"host-{k:03d}" for k in range(f.hosts)]
        self.index = {h: k for k, h in enumerate(self.names)}
        self.hosts = [_Host(h, k, f.slots) for k, h in enumerate(self.names)]
        self.events: List[tuple] = []
        self.seq = 0
        self.now = 0.0
        self.decodes = 0
        self.decoded: List[Tuple[int, float, float]] = []  # (host, start, end) of each decode ended
        self.per = f.step // f.ranks
        self.samples = sum(self.slots.values())  # the epoch's positions holding a sample (a window a sample)
        self.steps = -(-self.samples // f.step)
        self.readers: List[_Reader] = []
        routers = routers or [Router(self.names, slack=f.slack, hedge_s=f.hedge_s, patience_s=STEAL_S, workers=f.slots)
                              for _ in range(f.ranks)]
        #: the readers' clock at the epoch's start: after what routers kept from an epoch before heard
        self.t0 = max((s.heard for r in routers for s in r.hosts.values()), default=0.0)
        for r, router in enumerate(routers):
            memory = ReaderMemory(windows=dict(self.slots), made=dict(held or {}))
            read = Pass(router, memory, manifest, self.identity, self.fetch_of(r, 0), PREFETCH, RETRY_S,
                        "fleet_sim", set(self.names), stream=STREAM, ahead=ahead, now=self.t0, reader=(r, f.ranks))
            read.add(0, self.fetch_of(r, 0))
            self.readers.append(_Reader(r, read, iter(range(1, self.steps))))
        self.stalls = _Stalls(f, 4 * self.samples / (float(self.speeds.sum()) * f.slots) + 600.0)
        self.step_times: List[Tuple[int, float]] = []
        self.made_by: Dict[str, str] = {}  # clip -> the host whose copy was read first
        self.arrived: Dict[Tuple[int, str], Tuple[float, str]] = {}  # (rank, sample id) -> (when its rows came, from)
        #: step -> (when, rank, (when its last row came, from, its sample id)) as each rank handed it on
        self.handed: Dict[int, List[Tuple[float, int, Tuple[float, str, str]]]] = {}

    def fetch_of(self, rank: int, step: int) -> Fetch:
        """Rank ``rank``'s slice of step ``step``."""
        start = step * self.f.step + rank * self.per
        return Fetch(0, self.epoch, start, start + self.per, OUTPUTS, self.identity)

    # ------------------------------------------------------------------ events
    def push(self, t: float, kind: str, a, b=None) -> None:
        """An event at ``t``: ``"wake"`` (rank, token), ``"done"`` (host, video), ``"part"``
        (host, (video, rank, request)) or ``"host"`` (host, (rank, message))."""
        self.seq += 1
        heapq.heappush(self.events, (t, self.seq, kind, a, b))

    def to_reader(self, rank: int, ep: str, msg, frames=()) -> None:
        """Host ``ep``'s message to rank ``rank``: taken at its next turn, which it wakes now."""
        rd = self.readers[rank]
        rd.inbox.append((ep, msg, list(frames)))
        if rd.wake_at > self.now:
            self.wake(rd, self.now)

    def wake(self, rd: _Reader, t: float) -> None:
        """Rank ``rd`` turns at ``t``, and not at any wake-up asked before."""
        rd.token += 1
        rd.wake_at = t
        self.push(t, "wake", rd.rank, rd.token)

    # ------------------------------------------------------------------ hosts
    def rate(self, h: _Host) -> Optional[float]:
        """The capacity host ``h`` says now (``fleet_sim.said_rate``)."""
        return said_rate(h.meter, h.running, self.slots.__getitem__, self.now, self.f.slots, self.now)

    def host_message(self, k: int, rank: int, msg) -> None:
        """Host ``k`` takes rank ``rank``'s message (at its stall's end if stalled now)."""
        h = self.hosts[k]
        if self.stalls.silent(k, self.now):  # read when the process runs again
            i = int(np.searchsorted(self.stalls.ends[k], self.now, side="right"))
            self.push(float(self.stalls.ends[k][i]), "host", k, (rank, msg))
            return
        if isinstance(msg, PlanAsk):
            self.to_reader(rank, h.name, PlanInfo(self.identity, self.samples, STREAM, queued=h.queued,
                                                  rate=self.rate(h), withdraws=True))
        elif isinstance(msg, Withdraw):
            for video, makes in h.waiting.items():
                left = [m for m in makes if (m[0], m[1]) != (rank, msg.request)]
                if len(left) != len(makes):
                    h.queued -= sum(len(m[2]) for m in makes if (m[0], m[1]) == (rank, msg.request))
                    h.waiting[video] = left
                    break
        elif isinstance(msg, Make):
            self.make(h, rank, msg)

    def place(self, h: _Host, msg: Make) -> Optional[str]:
        """``Orders.place``: where ``msg`` is made, None here."""
        if msg.route is None:
            return None
        placed = h.placed.get(msg.video)
        if placed is not None and self.now - placed[1] < TOLD_S:
            return placed[0]
        started = msg.move and (msg.video in h.running or msg.video in h.made)
        if msg.route == "" or msg.video in h.made or started or not msg.move and h.waiting.get(msg.video):
            return None
        h.placed[msg.video] = (msg.route, self.now)
        return msg.route

    def make(self, h: _Host, rank: int, msg: Make) -> None:
        """``take_make``: placed elsewhere (``Moved``), answered from what ``h`` made, or queued."""
        to = self.place(h, msg)
        if to is not None:
            if msg.move:  # every reader's make of it waiting here goes with it
                for r, req, ords in h.waiting.pop(msg.video, []):
                    h.queued -= len(ords)
                    self.to_reader(r, h.name, Moved(req, to))
            self.to_reader(rank, h.name, Moved(msg.request, to))
            return
        ords = tuple(msg.ordinals) if msg.ordinals is not None else ()
        kept, named = [], set()
        for r, req, asked in h.waiting.get(msg.video, ()):  # ``Orders.add``: a retry replaces the make it repeats
            if r == rank:
                named.update(asked)
            if r == rank and set(asked) <= set(ords):
                h.queued -= len(asked)
            else:
                kept.append((r, req, asked))
        h.asked += len(set(ords) - named)
        if msg.video in h.waiting:
            h.waiting[msg.video] = kept
        if msg.video in h.made or not ords:
            self.answer(h, rank, msg.request, msg.video, ords)
            return
        h.waiting.setdefault(msg.video, []).append((rank, msg.request, ords))
        h.queued += len(ords)
        if msg.video in h.running:
            self.answer_at(h, msg.video, rank, msg.request, ords)
            return
        heapq.heappush(h.queue, (msg.position, self.seq, msg.video))
        self.seq += 1
        self.start_work(h)

    def start_work(self, h: _Host) -> None:
        """``h``'s free workers start the queue's first videos some make still waits on."""
        while h.free and h.queue:
            _, _, video = heapq.heappop(h.queue)
            if video in h.made or video in h.running or not h.waiting.get(video):
                continue
            h.free -= 1
            self.decodes += 1
            end = self.stalls.finish(h.k, self.now, self.slots[video] / self.speeds[h.k])
            h.running[video] = [self.now, end, 0.0, 0.0]
            self.push(end, "done", h.k, video)
            for r, req, ords in list(h.waiting[video]):
                self.answer_at(h, video, r, req, ords)

    def answer_at(self, h: _Host, video: str, rank: int, request: int, ords: Tuple[int, ...]) -> None:
        """A make of ``video``, which a worker of ``h`` decodes, answered once its last sample is
        made (``PlanScheduler.answer``: a worker sends each sample as it makes it, its windows in
        order, evenly over the decode's work): now if made, else at that time (``part``)."""
        start = h.running[video][0]
        at = self.stalls.finish(h.k, start, (max(ords) + 1) / self.speeds[h.k])  # a worker's seconds a sample
        if at <= self.now:
            self.part(h.k, (video, rank, request))
        else:
            self.push(at, "part", h.k, (video, rank, request))

    def part(self, k: int, make: Tuple[str, int, int]) -> None:
        """Host ``k`` made the last sample make ``make`` (video, rank, request) asks: answered,
        unless answered or withdrawn before."""
        h, (video, rank, request) = self.hosts[k], make
        makes = h.waiting.get(video, [])
        for i, (r, req, ords) in enumerate(makes):
            if (r, req) == (rank, request):
                del makes[i]
                h.queued -= len(ords)
                self.answer(h, rank, request, video, ords)
                return

    def done(self, k: int, video: str) -> None:
        """Host ``k`` made ``video``: counted by its meter, kept, and every make waiting on it answered."""
        h = self.hosts[k]
        h.free += 1
        start, _, counted, busy = h.running.pop(video)
        self.decoded.append((k, start, self.now))
        h.meter.add(self.slots[video] - counted, (self.now - start - busy) / self.f.slots, self.now)
        h.made.add(video)
        for r, req, ords in h.waiting.pop(video, []):
            h.queued -= len(ords)
            self.answer(h, r, req, video, ords)
        self.start_work(h)

    def answer(self, h: _Host, rank: int, request: int, video: str, ords: Tuple[int, ...]) -> None:
        """``PlanServer._send_rows``: ``h``'s rows of ``ords`` of ``video``, with its rate and queue."""
        specs, frames = encode_arrays({"voxel": np.zeros((len(ords), 1), np.uint8)})
        rows = Rows(request, self.epoch, 0, [f"{video}#{o}" for o in ords], [False] * len(ords), [{}] * len(ords),
                    specs, self.samples, self.slots[video], rate=self.rate(h), queued=h.queued)
        self.to_reader(rank, h.name, rows, [fr.tobytes() for fr in frames])

    # ------------------------------------------------------------------ readers
    def turn(self, rd: _Reader) -> None:
        """Rank ``rd``'s answers taken and its pass turned (``Fleet.turn``) until its head waits,
        or, once it holds ``READ_AHEAD`` + ``HELD_STEPS`` steps the job has not taken (the
        loop's and the pass's thread's), turned holding them (what the head waits on rescued);
        turned again at the next answer, or after half a second."""
        read, at = rd.read, self.t0 + self.now
        read.router.listen(at)
        for ep, msg, frames in rd.inbox:
            keys = [(sid, _key(sid)) for sid in msg.sample_ids if sid is not None] if isinstance(msg, Rows) else ()
            new = [(sid, key) for sid, key in keys if key not in read.got]
            read.receive(ep, msg, frames, at)
            for sid, key in new:
                if key in read.got:  # the rows the pass keeps (not a late copy's, dropped)
                    self.arrived[(rd.rank, sid)] = (self.now, ep)
            self.send(rd)
        rd.inbox = []
        while read.window:
            hold = rd.yielded - self.taken() >= READ_AHEAD + HELD_STEPS
            head = read.turn(rd.todo, lambda _, s, r=rd.rank: self.fetch_of(r, s), at, hold)
            self.send(rd)
            if head is None:
                self.wake(rd, self.now + TAKE_S)
                return
            self.check(rd, *head[:2])
            rd.yielded += 1
            self.job()

    def check(self, rd: _Reader, step: int, rows: Rows) -> None:
        """Rank ``rd``'s step ``step`` holds its slice's samples of the plan, in order, then
        padding past the epoch's end.

        Raises:
            RuntimeError: a row that is not the plan's sample there, naming it."""
        f = self.fetch_of(rd.rank, step)
        plan, kpw = rd.read.plan, rd.read.kpw
        last = (-1.0, "", "")
        for p, got in zip(range(f.start, f.stop), rows.sample_ids):
            key = plan.key(p)
            want = None if key is None else f"{key.video}#{key.ordinal(kpw)}"
            if got != want:
                raise RuntimeError(f"fleet_sim_pass: rank {rd.rank} read {got} at position {p}, the plan's is {want}")
            if key is not None:
                self.made_by.setdefault(key.video, rd.read.memory.made[key.video])
                last = max(last, (*self.arrived.pop((rd.rank, got)), got))
        self.handed.setdefault(step, []).append((self.now, rd.rank, last))

    def taken(self) -> int:
        """Steps the job has taken: those every rank has handed on."""
        return min(rd.yielded for rd in self.readers)

    def job(self) -> None:
        """The trainer takes each step every rank has; a rank's loop then takes a step its pass
        held (``ReadAhead`` holds ``READ_AHEAD``), which wants the next from now
        (``Pass.wanted``) and turns at once (``Fleet.fetch_all`` wakes its thread)."""
        taken = self.taken()
        while len(self.step_times) < taken:
            self.take_step()

    def take_step(self) -> None:
        """The trainer takes the next step now; each rank whose loop held more than
        ``READ_AHEAD`` steps takes one its pass held into the loop's room, which wants the next
        from now (``Pass.wanted``) and turns at once (``Fleet.fetch_all`` wakes its thread)."""
        before = len(self.step_times)
        self.step_times.append((min(self.samples, before * self.f.step + self.f.step), self.now))
        for rd in self.readers:
            if rd.yielded > before + READ_AHEAD:  # the loop's room took one the pass held
                rd.read.wanted(self.t0 + self.now)
                if rd.read.window and rd.wake_at > self.now:
                    self.wake(rd, self.now)

    def send(self, rd: _Reader) -> None:
        """Rank ``rd``'s outbox, each message to its host now (``Fleet.send_out``)."""
        out, rd.read.outbox = rd.read.outbox, []
        for ep, msg in out:
            self.push(self.now, "host", self.index[ep], (rd.rank, msg))

    def handle(self, kind: str, a, b) -> None:
        """Event ``kind`` (:meth:`push`) at :attr:`now`."""
        if kind == "wake":
            rd = self.readers[a]
            if b == rd.token:
                rd.wake_at = math.inf
                self.turn(rd)
        elif kind == "done":
            self.done(a, b)
        elif kind == "part":
            self.part(a, b)
        else:
            self.host_message(a, *b)

    def run(self) -> Result:
        """The epoch, event by event, until the job took its last step.

        Raises:
            RuntimeError: no event left before then (stuck), or a row not the plan's (:meth:`check`)."""
        for rd in self.readers:
            self.wake(rd, 0.0)
        while len(self.step_times) < self.steps:
            if not self.events:
                raise RuntimeError(f"fleet_sim_pass: stuck at step {len(self.step_times)} of {self.steps}")
            self.now, _, kind, a, b = heapq.heappop(self.events)
            self.handle(kind, a, b)
        end = self.now
        lo, hi = int(0.1 * self.samples), int(0.9 * self.samples)
        t_lo = next(t for p, t in self.step_times if p >= lo)
        t_hi = next(t for p, t in self.step_times if p >= hi)
        f = self.f
        capacity = float(sum(self.speeds[k] * f.slots * (1 - self.stalls.stalled(k, end) / end)
                             for k in range(f.hosts)))
        clips = sum(1 for n in self.slots.values() if n)
        decoding, idle_end = self.busy(end, capacity)
        return Result("routed", self.samples, self.steps * f.step, end, self.samples / end,
                      (hi - lo) / max(t_hi - t_lo, 1e-9), capacity, self.decodes / max(1, clips), self.made_by,
                      decoding, idle_end)

    def busy(self, end: float, capacity: float) -> Tuple[float, float]:
        """``(decoding, idle_end)`` of an epoch that ended at ``end`` seconds with ``capacity``
        samples/s (``Result``'s): the work the hosts' workers did in it, each second of a decode
        out of a stall counted at its host's speed, decodes still running at the end up to it,
        as a share of the capacity's; and the capacity's share that idled in the last tenth."""
        tail = 0.9 * end

        def unstalled(k: int, a: float, b: float) -> float:  # host k's seconds in [a, b) out of its stalls
            return b - a - (self.stalls.stalled(k, b) - self.stalls.stalled(k, a))
        spans = self.decoded + [(h.k, start, end) for h in self.hosts for start, *_ in h.running.values()]
        work = sum(self.speeds[k] * unstalled(k, a, min(b, end)) for k, a, b in spans)
        work_end = sum(self.speeds[k] * unstalled(k, max(a, tail), min(b, end)) for k, a, b in spans if b > tail)
        cap_end = float(sum(self.speeds[k] * self.f.slots * unstalled(k, tail, end) for k in range(self.f.hosts)))
        whole = capacity * end
        return work / whole, (cap_end - work_end) / whole

    def waited(self, at_least_s: float) -> List[Wait]:
        """The steps the job took ``at_least_s`` seconds or more after the one before, each with
        the rank it waited for last and that rank's last row (after :meth:`run`)."""
        out, before = [], 0.0
        for step, (_, t) in enumerate(self.step_times):
            if t - before >= at_least_s:
                handed = self.handed[step]
                when, rank, (arrived, host, sample) = max(handed)
                out.append(Wait(step, t, t - before, min(h[0] for h in handed), rank, sample, host, arrived))
            before = t
        return out


def _key(sample_id: str) -> Tuple[str, int]:
    """``(video, ordinal)`` of a row's sample id (``video#ordinal``, as :meth:`PassWorld.answer` names it)."""
    video, ordinal = sample_id.rsplit("#", 1)
    return video, int(ordinal)


def simulate_pass(f: Fleet, epoch: int = 0, routers: Optional[Sequence[Router]] = None,
                  held: Optional[Dict[str, str]] = None) -> Result:
    """One epoch of fleet ``f`` read by ``f.ranks`` real passes (:class:`PassWorld`); ``routers``:
    each rank's router kept from an earlier epoch (default new ones); ``held``: clip -> the host
    that made it in that epoch (its frame cache holds it: ``Router.route``'s ``held``).

    Raises:
        ValueError: ranks that do not divide the step.
        RuntimeError: the epoch stuck (no event left before every step was read)."""
    return PassWorld(f, epoch, routers, held).run()

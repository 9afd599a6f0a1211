"""The fleets of ``harness.plan_world``: 1-16 hosts that each serve the whole corpus's one plan
(the manifest a single server serves), read by jobs through the client's own decisions
(``v2v_client.fleet_pass.Pass``, ``v2v_wire.fleet.Router``, ``v2v_client.fleet_read.Fleet``'s
joins, leaves and manifest), each host a real ``PlanScheduler`` taking ``make``\\ s.

What a fleet's world does:

* hosts join mid-epoch (their name appears where the readers resolve the fleet; a reader asks
  it what it serves and it joins at its answer), leave (killed: its scheduler, made samples and
  makes gone; its name goes after a lag, or, a third of the time, stays, as in a static list of
  endpoints: hedges take over what it held; :data:`DOOMED` of the hosts die so, as soon as they
  answer a make saying their first rate, which is when a reader moves what that rate makes late
  off them), stall (answer nothing for 10-80 s: hedges and copies
  of what the head waits on take over) and restart (a fresh ``PlanScheduler`` and pool, after a
  while down, under the same name or a new one); their workers stall, die and hang as a
  server's do (``World.decode``);
* every message is encoded to the wire and decoded at the other end with the real parsers
  (``decode_plan_client``, ``plan_server_message``, the arrays' frames): a seeded transport
  delays each by 1-4 ticks and may lose it (the reader asks again after ``retry_s``);
* jobs of 1-3 ranks at 1-5 rows, each rank read by 1-2 processes (DataLoader workers), each
  process's pass a ``Fleet`` of the hosts that answered at its start (the others join as they
  answer), what it learned kept across its passes (``ReaderMemory``); each step's rows are merged by
  ``Pass.head_rows`` and the pass ends where the rows' samples say the epoch ends (as
  ``plan_dataset._read``); jobs checkpoint and resume, or roll back, in new processes at
  another layout, reading another part of the fleet.

A sample's bytes are a function of (seed, epoch, sample id) (:func:`content`) made from the
sample a host's scheduler stored. :meth:`FleetWorld.judge` checks each job read each epoch
exactly as one server's plan says: every position once, at its place, the sample id and bytes
of that plan's key there, padding only past the epoch's end or for a window its file did not
give; each process ended at its first step past the epoch's end. A tick is :data:`DT` seconds of
the readers' clock; the hosts' schedulers count ticks, as ``harness.plan_world``'s servers do.
"""
from __future__ import annotations

import hashlib
import heapq
import itertools
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import numpy as np

from harness.plan_world_jobs import OUTPUTS
from v2v_client.fleet_pass import Pass, ReaderMemory
from v2v_client.fleet_read import Fleet
from v2v_client.plan_state import _rows
from v2v_server.delivery.plan_orders import Order
from v2v_server.service.plan_server import take_make
from v2v_wire.plan import EpochPlan, Manifest, PlanIdentity, epoch_steps
from v2v_wire.plan_messages import (MANIFEST_PART, Fetch, Make, ManifestAsk, ManifestPart, PlanAsk, PlanInfo,
                                    Refused, Rows, Withdraw, decode_plan_client, plan_server_message)
from v2v_wire.protocol import MAX_CLIENT_MSG, encode_arrays, pack, unpack

#: Seconds of the readers' clock a tick (a worker makes a sample a tick).
DT = 0.2
#: The readers' ``retry_s``: a make unanswered this long is asked again.
RETRY_S = 6.0
#: Ticks a pass's loop waits for a message before it turns anyway (``fleet_pass.take``'s half second).
POLL = 3
#: Most hosts up at once.
MOST_HOSTS = 16
#: The share of hosts killed as soon as they answer a make saying their first rate, their names
#: left where the readers resolve the fleet (a static list of endpoints).
DOOMED = 0.05
#: Bytes of a sample's content (:func:`content`), its one array (``"bytes"``).
WIDTH = 8
#: The recipe's shapes a host says (a padding row's zeros, read before any reply, follow them).
STREAM = {"sequence_length": 1, "num_bins": 1, "crop_size": 2, "flow_dtype": "float16", "outputs": list(OUTPUTS)}


def content(seed: int, epoch: int, sample_id: str) -> np.ndarray:
    """The bytes of sample ``sample_id`` of ``epoch``, whichever host makes it."""
    return np.frombuffer(hashlib.blake2b(f"{seed}/{epoch}/{sample_id}".encode(), digest_size=WIDTH).digest(),
                         np.uint8)


@dataclass(eq=False)
class Host:
    """One host of the fleet: ``World.start`` gives it a scheduler and a pool (as a server's);
    ``inbox``: the messages it has yet to take (a stalled host takes none)."""

    name: str
    videos: List[str]
    shard: int = 0
    scheduler: Optional[object] = None
    identity: str = ""
    workers: list = field(default_factory=list)
    up: bool = True
    stalled_until: int = 0
    inbox: list = field(default_factory=list)
    withdraws: bool = True  # takes a Withdraw (an older server does not, and refuses one)
    said_rate: bool = False  # it answered a make saying its rate
    doomed: bool = False  # killed once it said its first rate (a reader moves what it measured late off it then)


class Link:
    """A reader's link to one host through the world's transport (``fetch.Link``'s ``ids``,
    ``compression``, ``_send``; ``_recv`` only for ``load_manifest``, answered at once)."""

    def __init__(self, net: "Net", reader: int, endpoint: str):
        self.net, self.reader, self.endpoint = net, reader, endpoint
        self.ids = itertools.count(1)
        self.compression = "none"
        self.replies: list = []

    def _send(self, header: dict) -> None:
        self.net.send(self, pack(header))

    def _recv(self, deadline: float):
        return self.replies.pop(0) if self.replies else None

    def __exit__(self, *exc) -> None:
        pass


class ReaderFleet(Fleet):
    """``fleet_read.Fleet`` whose links are the world's (no socket); ``reader``: its number, the
    client the hosts answer."""

    def __init__(self, net: "Net", reader: int, endpoint: list, plan: PlanIdentity, hedge_s: float,
                 memory: ReaderMemory, ahead: Optional[int], now: float):
        self.net, self.reader = net, reader
        super().__init__(endpoint, [], plan, 120.0, None, "none", memory, ahead, hedge_s)
        self.resolved = now
        hedges = self.router.hedges

        def counted(waiting, at, *args, **kwargs):
            out = hedges(waiting, at, *args, **kwargs)
            net.out.hedged += len(out)
            return out
        self.router.hedges = counted

    def _link(self, ep: str) -> Link:
        if ep not in self.links:
            self.links[ep] = Link(self.net, self.reader, ep)
        return self.links[ep]


class Net:
    """The hosts and the transport between them and the readers: each message encoded, delayed
    1 + up to ``lag`` ticks or lost (``loss``), and decoded at its end; the hosts' side of
    ``PlanServer._client`` and ``_send_rows``."""

    def __init__(self, world, lag: int, loss: float):
        self.world, self.rng, self.out, self.lag, self.loss = world, world.rng, world.out, lag, loss
        self.hosts: Dict[str, Host] = {}
        self.queue: list = []  # (due tick, number, to, what)
        self.sent = 0
        self.readers: Dict[int, object] = {}  # reader number -> its process (FleetWorld's Proc)
        self.now, self.hedge_s = 0, 0.0  # the tick; the readers' hedge_s (FleetWorld's)
        self.none_live = 0  # the last tick no host was up and not stalled
        self.down_since: Dict[tuple, list] = {}  # (reader, epoch, video) -> [tick, hosts]: makes to hosts down since one up
        self.stuck: set = set()  # those judged: each named once
        self.asked: Dict[tuple, str] = {}  # (reader, epoch, video, ordinals) -> the first host asked
        self.now = 0

    def identity(self, host: Host) -> PlanIdentity:
        return PlanIdentity(host.identity, "world", self.world.seed, self.world.buffer)

    def info(self, host: Host) -> PlanInfo:
        """What ``host`` serves (``PlanServer``'s answer to ``plan_ask``)."""
        return PlanInfo(self.identity(host), self.world.samples_of(host, 0),
                        dict(STREAM, feed={"workers": len(host.workers)}), queued=host.scheduler.queued(),
                        rate=self.rate(host), withdraws=host.withdraws)

    @staticmethod
    def rate(host: Host) -> Optional[float]:
        """The decode capacity ``host`` says (samples/s), as a server measures it: its workers at a
        sample a tick, once it has made a sample (None before)."""
        return len(host.workers) / DT if host.scheduler.samples_made else None

    def post(self, to, what) -> None:
        """Queue ``what`` for ``to`` (a host's name, or a reader's number), unless lost."""
        if self.rng.random() < self.loss:
            return
        self.sent += 1
        heapq.heappush(self.queue, (self.now + 1 + self.rng.randint(0, self.lag), self.sent, to, what))

    def send(self, link: Link, frame: bytes) -> None:
        """A reader's message to a host, read as ``PlanServer`` reads it; a manifest ask is
        answered at once (``load_manifest`` waits on it)."""
        msg = decode_plan_client(frame, MAX_CLIENT_MSG)
        host = self.hosts.get(link.endpoint)
        if isinstance(msg, ManifestAsk):
            if host is not None and host.up:
                link.replies.append((self.wire(self.manifest_part(host, msg.offset).to_wire()), []))
            return
        if isinstance(msg, Make) and host is not None:
            self.judge_dead(link.reader, msg, host)
        if isinstance(msg, Make) and msg.ordinals is not None:
            ask = (link.reader, msg.epoch, msg.video, msg.ordinals)
            if self.asked.setdefault(ask, link.endpoint) != link.endpoint:
                self.out.copies += 1
        self.post(link.endpoint, (link.reader, msg))

    def judge_dead(self, reader: int, msg: Make, host: Host) -> None:
        """A reader that keeps asking a video of hosts that are down, while another host is up
        and not stalled, asks it of another host within ``hedge_s`` and three ``RETRY_S`` (its
        silence found, a hedge, a reply's lag): else it would wait on them for good (a move
        asked of a host that died before it answered, awaited where its queue is no more)."""
        key = (reader, msg.epoch, msg.video)
        if host.up:
            self.down_since.pop(key, None)
            return
        stretch = self.down_since.setdefault(key, [self.now, set()])
        if host.name not in stretch[1]:  # a host it had not asked: a hedge, which found it down too
            stretch[0] = self.now
            stretch[1].add(host.name)
        since = max(stretch[0], self.none_live)
        if self.now - since > (self.hedge_s + 3 * RETRY_S) / DT and key not in self.stuck:
            self.stuck.add(key)
            self.out.problems.append(f"reader {reader} asked {msg.video} of epoch {msg.epoch} of hosts down "
                                     f"({', '.join(sorted(stretch[1]))}) from tick {since} to {self.now}, while a host "
                                     "was up, and of no other host")

    @staticmethod
    def wire(header: dict):
        """A server's message as a reader decodes it."""
        return plan_server_message(unpack(pack(header)))

    def manifest_part(self, host: Host, offset: int) -> ManifestPart:
        """``PlanServer._manifest_part``: the videos, tags and the slots ``host`` knows now."""
        m = host.scheduler.manifest
        part = m.slots[offset:offset + MANIFEST_PART]
        return ManifestPart(offset, len(m.slots), m.crops_per_window, [v for v, _ in part],
                            list(m.tags[offset:offset + MANIFEST_PART]),
                            [host.scheduler.slots.windows.get(v) for v, _ in part])

    def deliver(self, now: int) -> None:
        """The messages due at ``now``: to a host's inbox (none to a host down), to a reader's pass
        (none to a pass that ended: its sockets are closed)."""
        self.now = now
        if not any(h.up and now >= h.stalled_until for h in self.hosts.values()):
            self.none_live = now
        while self.queue and self.queue[0][0] <= now:
            _, _, to, what = heapq.heappop(self.queue)
            if isinstance(to, str):
                host = self.hosts.get(to)
                if host is not None and host.up:
                    host.inbox.append(what)
                continue
            proc = self.readers.get(to)
            if proc is not None and proc.read is not None:
                ep, header, frames = what
                proc.fleet.receive(proc.read, ep, self.wire(header), frames, now * DT)
                proc.woken = True

    def serve(self, host: Host, now: int) -> None:
        """A host's turn: take its messages, answer what it can, decode (none while stalled; an
        idle host, with nothing asked or decoding, skips its turn: it makes nothing ahead for makes)."""
        s = host.scheduler
        if not host.up or now < host.stalled_until or not (host.inbox or s.orders.waiting or s.pending or s.runs):
            return
        for reader, msg in host.inbox:
            if isinstance(msg, PlanAsk):
                self.post(reader, (host.name, self.info(host).to_wire(), []))
                continue
            if isinstance(msg, Withdraw):  # PlanServer's: another host's copy came first
                if not host.withdraws:
                    self.out.problems.append(f"{host.name}: a Withdraw sent to a server that does not take one")
                self.out.withdrawn += 1
                s.withdraw(lambda client, reader=reader: client[0] == reader, msg.request)
                continue
            problem = self.identity(host).problem(msg.plan)
            if problem or not isinstance(msg, Make):
                self.out.problems.append(f"{host.name}: a {type(msg).__name__} under {problem}")
                self.post(reader, (host.name, Refused(msg.request, str(problem), "plan").to_wire(), []))
                continue
            self.out.moves += msg.move
            for client, answer in take_make(s, (reader, msg.outputs), msg, now)[1]:
                if isinstance(answer, Refused):
                    self.out.problems.append(f"{host.name}: make refused: {answer.message}")
                self.post(client[0], (host.name, answer.to_wire(), []))
        host.inbox = []
        for order, rows in s.answer(now):
            self.answer(host, order, rows)
        self.world.decode(host, now)

    def answer(self, host: Host, o: Order, rows) -> None:
        """``PlanServer._send_rows`` of make ``o``: each row's id, padding and the bytes of the
        sample the host stored (checked to be the one the make names, with its outputs)."""
        kpw, seed = self.world.kpw, self.world.seed
        real = []
        for r in rows:
            if r.sample is None:
                continue
            if r.sample[:2] != (o.epoch, r.key) or not set(o.client[1]) <= set(r.sample[2]):
                self.out.problems.append(f"{host.name}: make of {r.key} in epoch {o.epoch} answered with {r.sample}")
            real.append(content(seed, r.sample[0], r.sample[1].sample_id(kpw)))
        host.said_rate = host.said_rate or self.rate(host) is not None
        specs, frames = encode_arrays({"bytes": np.stack(real) if real else np.zeros((0, WIDTH), np.uint8)})
        head = Rows(o.request, o.epoch, 0, [r.key.sample_id(kpw) for r in rows], [r.padding for r in rows],
                    [{} if r.sample is not None else {"padding": r.reason} for r in rows], specs,
                    self.world.samples_of(host, o.epoch), host.scheduler.slots.windows.get(o.video),
                    rate=self.rate(host), queued=host.scheduler.queued())
        self.post(o.client[0], (host.name, head.to_wire(), [f.tobytes() for f in frames]))


@dataclass(eq=False)
class Proc:
    """One process of a fleet job: rank ``rank``'s items ``worker``, ``worker + workers``, ... of
    each pass; what it learned (``memory``, kept across its passes); its pass (``read``, None
    between passes) over its ``fleet``, the items left to add (``todo``), the epoch's steps as
    known, where it ended."""

    rank: int
    worker: int
    workers: int
    memory: ReaderMemory = field(default_factory=ReaderMemory)
    read: Optional[Pass] = None
    fleet: Optional[Fleet] = None
    todo: object = None
    steps: Optional[int] = None
    origin: int = 0
    first: int = 0
    item: int = 0  # the next item it yields
    end: Optional[int] = None
    fetch_of: object = None  # item -> its Fetch (``Pass.fill``'s)
    reader: int = 0  # its pass's number: the client the hosts answer
    woken: bool = False  # a message came since its last turn
    last: int = 0  # the tick of its last turn


@dataclass(eq=False)
class FleetJob:
    """A trainer reading the fleet: ``world`` ranks of ``batch`` rows, ``workers`` processes a rank."""

    name: str
    world: int
    batch: int
    workers: int
    outputs: tuple
    epoch: int = 0
    start: int = 0
    checkpoints: List[int] = field(default_factory=lambda: [0])
    rows: Dict[int, Dict[int, tuple]] = field(default_factory=dict)  # epoch -> position -> (id, padding, bytes)
    procs: List[Proc] = field(default_factory=list)
    ahead: Optional[int] = None
    hosts: int = 0  # hosts its last pass began with
    resumed: bool = False  # its next pass is the first of a resume

    def taken(self) -> int:
        """Steps the loop took from ``start`` (every rank's items in order)."""
        return min(p.item for p in self.procs) if self.procs else 0


class FleetWorld:
    """A seed's fleet and its jobs (module docstring); ``world``: the ``harness.plan_world.World``
    whose corpus, workers and outcome it uses."""

    def __init__(self, world):
        self.world = w = world
        rng = self.rng = w.rng
        self.net = Net(w, rng.choice([0, 1, 3]), rng.choice([0.0, 0.0, 0.02, 0.1]))
        self.dns: List[str] = []  # the names the fleet's endpoint resolves to now
        self.later: list = []  # (tick, what, host): a name leaving the dns, a host coming up
        self.names = 0
        self.pool = rng.randint(1, 2)
        self.hedge_s = self.net.hedge_s = rng.choice([2.0, 10.0])
        self.event_p = rng.choice([0.005, 0.01, 0.02])
        for _ in range(rng.choice([1, 1, 2, 3, 4, 6, 8, 12, 16])):
            self.add_host()
        self.jobs = [FleetJob(f"f{i}", rng.randint(1, 3), rng.randint(1, 5), rng.randint(1, 2),
                              OUTPUTS[:rng.randint(1, 3)], ahead=rng.choice([None, 4, 16]))
                     for i in range(rng.randint(1, 2))]
        for job in self.jobs:
            self.new_procs(job)
        self.reader_ids = itertools.count(1)
        w.out.fleets = 1
        truth = Manifest.of({v: w.index.get(v, w.given[v]) for v in sorted(w.slots)}, w.kpw)
        self.plans = [EpochPlan(truth, w.seed, e, w.buffer) for e in range(w.epochs)]

    # ------------------------------------------------------------------ the fleet
    def up(self) -> List[Host]:
        return [h for h in self.net.hosts.values() if h.up]

    def add_host(self) -> None:
        """A host starts under a new name, which the fleet's endpoint resolves to from now on."""
        self.names += 1
        name = f"tcp://10.0.{self.names // 250}.{self.names % 250 + 1}:5555"
        # a quarter of the hosts are older servers, which take no Withdraw (drawn apart from the world's stream)
        older = hashlib.sha256(f"{self.world.seed} {name}".encode()).digest()[0] < 64
        host = self.net.hosts[name] = Host(name, sorted(self.world.slots), withdraws=not older,
                                           doomed=self.rng.random() < DOOMED)
        self.world.start(host, self.pool)
        self.dns.append(name)
        self.world.out.big_fleets = max(self.world.out.big_fleets, int(len(self.up()) >= 8))

    def kill(self, host: Host) -> None:
        """``host`` is killed: its scheduler's state and its messages are gone."""
        host.up, host.inbox, host.workers, host.stalled_until = False, [], [], 0

    def events(self, now: int) -> None:
        """Now and then a host joins, leaves, stalls or restarts; names leave the dns after a lag
        and hosts down come up."""
        rng, out = self.rng, self.world.out
        for tick, what, host in [x for x in self.later if x[0] <= now]:
            self.later.remove((tick, what, host))
            if what == "gone" and host.name in self.dns:
                self.dns.remove(host.name)
            elif what == "same":
                self.world.start(host, self.pool)
                host.up = True
            elif what == "new":
                self.add_host()
        for host in self.up():
            if host.doomed and host.said_rate and len(self.up()) > 1:
                self.kill(host)  # its name stays
                out.fleet_dead_names += 1
        if rng.random() >= self.event_p:
            return
        up = self.up()
        kind = rng.choice(["join", "leave", "leave", "stall", "restart"])
        if kind == "join" and len(up) < MOST_HOSTS:
            self.add_host()
            out.fleet_joins += 1
        elif kind == "leave" and len(up) > 1:
            host = rng.choice(up)
            self.kill(host)
            if rng.random() < 1 / 3:  # a static list of endpoints: its name stays, and it answers nothing
                out.fleet_dead_names += 1
            else:
                self.later.append((now + rng.randint(0, 50), "gone", host))
            out.fleet_leaves += 1
        elif kind == "stall" and up:
            rng.choice(up).stalled_until = now + rng.randint(50, 400)
            out.fleet_stalls += 1
        elif kind == "restart" and up:
            host = rng.choice(up)
            self.kill(host)
            back = now + rng.randint(0, 100)
            if rng.random() < 0.5:
                self.later.append((back, "same", host))
            else:
                self.later += [(now + rng.randint(0, 50), "gone", host), (back, "new", None)]
            out.fleet_restarts += 1

    # ------------------------------------------------------------------ jobs
    def run(self, ticks: int):
        """Play at most ``ticks`` ticks (until every job read every epoch), then judge."""
        w = self.world
        for now in range(ticks):
            self.events(now)
            self.net.deliver(now)
            for job in self.jobs:
                if job.epoch < w.epochs:
                    self.job_turn(job, now)
            for host in list(self.net.hosts.values()):
                self.net.serve(host, now)
            if all(j.epoch >= w.epochs for j in self.jobs):
                break
        self.judge()
        return w.out

    def new_procs(self, job: FleetJob) -> None:
        job.procs = [Proc(r, j, job.workers) for r in range(job.world) for j in range(job.workers)]

    def job_turn(self, job: FleetJob, now: int) -> None:
        """A job's turn: each process's pass (begun where none is), then the epoch's end, or a
        checkpoint resumed in new processes."""
        for proc in job.procs:
            if proc.end is None and proc.read is None:
                self.begin(job, proc, now)
            if proc.read is not None and (proc.woken or now - proc.last >= POLL):
                self.turn(job, proc, now)
        if all(p.end is not None for p in job.procs):
            self.ended(job)
            job.epoch, job.start, job.checkpoints = job.epoch + 1, 0, [0]
            for p in job.procs:
                p.end, p.item = None, p.worker
        elif job.taken() and self.rng.random() < 0.005:
            self.resume(job)

    def begin(self, job: FleetJob, proc: Proc, now: int) -> None:
        """``proc``'s pass of ``job.epoch`` from ``job.start``: a ``Fleet`` of the hosts that answered
        what they serve (some of those up, the manifest's host first), the epoch's steps as its
        first host says, its first item added (``Fleet.fetch_all``)."""
        up = [h for h in self.up() if h.name in self.dns]
        if not up:
            return  # no host answers: asked again at its next turn
        now_s, net = now * DT, self.net
        hosts = self.rng.sample(up, self.rng.randint(1, len(up)))
        if job.resumed and len(hosts) != job.hosts:
            self.world.out.resized += 1  # a position taken with some hosts read on with another number
        job.hosts, job.resumed = len(hosts), False
        rd = next(self.reader_ids)
        plan = net.identity(hosts[0])
        fleet = ReaderFleet(net, rd, self.dns, plan, self.hedge_s, proc.memory, job.ahead, now_s)
        for h in hosts:
            fleet.join(h.name, net.wire(net.info(h).to_wire()), now_s)
        manifest = fleet._manifest(job.epoch)
        r = {"group": 1, "origin": job.start, "world": job.world, "rank": proc.rank}
        epoch = job.epoch
        proc.fetch_of = lambda req, i: Fetch(req, epoch, *_rows(r, i, job.batch), job.outputs, plan)
        proc.origin, proc.item = job.start, proc.worker
        proc.steps = epoch_steps(net.info(hosts[0]).samples, job.world, job.batch, job.start)
        items = range(proc.worker, proc.steps, job.workers) if proc.steps is not None else \
            itertools.count(proc.worker, job.workers)
        proc.todo = iter(items)
        first = next(proc.todo, None)
        if first is None:
            proc.end = proc.worker
            return
        f0 = proc.fetch_of(0, first)
        proc.read, proc.fleet = fleet.pass_for(manifest, f0, 2, RETRY_S, now_s), fleet
        proc.read.add(first, f0)
        proc.reader = rd
        net.readers[rd] = proc

    def turn(self, job: FleetJob, proc: Proc, now: int) -> None:
        """``proc``'s turn of ``Fleet.fetch_all``'s loop, taken when a message came or :data:`POLL`
        ticks passed (``fleet_pass.take``): the steps whose rows are known, noted, until the head
        waits (then what it waits on is rescued) or the pass ends (``plan_dataset._read``)."""
        read, now_s = proc.read, now * DT
        proc.woken, proc.last = False, now
        while read.window:
            head = proc.fleet.turn(read, proc.todo, proc.fetch_of, now_s)
            if head is None:
                return
            i, rows, arrays = head
            if proc.steps is None:
                proc.steps = epoch_steps(rows.samples, job.world, job.batch, proc.origin)
            if proc.steps is not None and i >= proc.steps:
                break
            self.note(job, proc, i, rows, arrays)
        proc.end, proc.read = proc.item, None
        self.net.readers.pop(proc.reader, None)

    def note(self, job: FleetJob, proc: Proc, i: int, rows: Rows, arrays) -> None:
        """Item ``i``'s rows, each noted once at its position."""
        start, stop = _rows({"group": 1, "origin": proc.origin, "world": job.world, "rank": proc.rank}, i, job.batch)
        if i != proc.item or rows.start != start or len(rows.sample_ids) != stop - start:
            self.world.out.problems.append(f"{job.name}: item {i} (positions {rows.start}.. x{len(rows.sample_ids)}) "
                                           f"yielded, {proc.item} ({start}..{stop - 1}) next")
        seen = job.rows.setdefault(job.epoch, {})
        for j, (t, sid, pad) in enumerate(zip(range(start, stop), rows.sample_ids, rows.padding)):
            if t in seen:
                self.world.out.problems.append(f"{job.name} epoch {job.epoch}: position {t} read twice")
            seen[t] = (sid, pad, b"".join(a[j].tobytes() for a in arrays.values()))
        proc.item = i + proc.workers

    def resume(self, job: FleetJob) -> None:
        """Checkpoint after the steps the loop took and resume there, or at an older checkpoint
        of the epoch, in new processes at another layout (the rows read since count again)."""
        rng = self.rng
        job.start += job.taken() * job.world * job.batch
        job.checkpoints.append(job.start)
        if rng.random() < 0.3:
            back = rng.randrange(len(job.checkpoints) - 1)
            job.start, job.checkpoints = job.checkpoints[back], job.checkpoints[:back + 1]
        job.rows[job.epoch] = {p: row for p, row in job.rows.get(job.epoch, {}).items() if p < job.start}
        for p in job.procs:
            self.net.readers.pop(p.reader, None)
        job.world, job.batch, job.workers = rng.randint(1, 3), rng.randint(1, 5), rng.randint(1, 2)
        self.new_procs(job)
        job.resumed = True
        self.world.out.fleet_resumes += 1

    # ------------------------------------------------------------------ judging
    def ended(self, job: FleetJob) -> None:
        """Each process ended at its first item past the epoch's end (one server's plan's)."""
        steps = epoch_steps(len(self.plans[job.epoch]), job.world, job.batch, job.start)
        for p in job.procs:
            k = p.workers
            want = p.worker if p.worker >= steps else p.worker + -(-(steps - p.worker) // k) * k
            if p.end != want:
                self.world.out.problems.append(f"{job.name} epoch {job.epoch} rank {p.rank} worker {p.worker}: ended "
                                               f"at step {p.end}, the epoch ends at step {steps}")

    def judge(self) -> None:
        """Each job read each epoch as one server's plan says (module docstring)."""
        w, problems = self.world, self.world.out.problems
        for job in self.jobs:
            if job.epoch < w.epochs:
                problems.append(f"{job.name} stuck in epoch {job.epoch} at step {job.taken()} from {job.start}")
                continue
            for e, plan in enumerate(self.plans):
                rows = job.rows.get(e, {})
                missing = [t for t in range(len(plan)) if t not in rows]
                if missing:
                    problems.append(f"{job.name} epoch {e}: read {len(plan) - len(missing)} of {len(plan)} positions")
                for t, (sid, pad, b) in sorted(rows.items()):
                    key = plan.key(t) if t < len(plan) else None
                    want = key.sample_id(w.kpw) if key is not None else None
                    gap = key is None or key.window >= w.given[key.video]
                    body = bytes(len(b)) if gap else content(w.seed, e, want).tobytes()  # zeros of any array
                    if (sid, pad, b) != (want, gap, body):
                        problems.append(f"{job.name} epoch {e} position {t}: {sid} (padding {pad}), one server's "
                                        f"plan says {want} (padding {gap}){'' if b == body else ', other bytes'}")

"""The grant protocol (docs/delivery.md, "The protocol") through every interleaving.

The server's pure delivery core (``v2v_server.delivery.core.DeliveryCore``) and the client's
real protocol objects (``v2v_client.session.ServerSession`` with its ``HeldBatches`` book and the
reader's ``v2v_client.resume.ResumeState``) talk over two FIFO channels per connection with
messages in flight, every message going through the real wire encoding both ways (the client's
typed messages packed and read back by the server's bounded decoder; the server's messages as
the frames the session reads). Every step of the client between receiving a batch and yielding
it is a separate step: the I/O thread reads one message (and sends what the session decided);
the consumer takes the next item, tries to take it (``ServerSession.take``: ask, claim once
granted, ack), yields it; the I/O thread sends what the consumer's steps decided. Any client may
stop taking steps at any point (SIGSTOP, a GC pause, swap) while the server's clock runs on, the
server may itself stall, connections may break (whatever was in flight is lost, the client says
hello on a new socket), and trainers may crash and resume from any older checkpoint. After
every step no sample reaches two training loops' histories in an epoch; at the end every sample
of every epoch was trained on exactly once.

``test_a_client_paused_at_each_point_*`` drives the same pieces through one fixed schedule per
point, pausing the client there for longer than the lease, the revoke timeout and the client
timeout together while another client reads.
"""
from __future__ import annotations

import collections
import queue
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import numpy as np
import pytest
from hypothesis import HealthCheck, settings, strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, precondition, rule

from bench.lease import ack_only
from v2v_client.options import StreamOptions
from v2v_client.resume import ResumeState, take_epoch_end
from v2v_client.session import ServerSession
from v2v_server.delivery.core import DeliveryCore, DeliveryPolicy
from v2v_server.delivery.journal import FILE as JOURNAL_FILE, Journal
from v2v_server.delivery.ledger import STALL_S
from v2v_wire import stream_messages as sm
from v2v_wire.ids import SampleKey, parse_sample_id
from v2v_wire.messages import Ack, Bye, Heartbeat, Hello, Hold, Released, Resume, decode_client
from v2v_wire.protocol import encode_arrays, pack, unpack

WINDOWS = {"a.mp4": 3, "b.mp4": 2, "c.mp4": 3}
EPOCHS = 2
LEASE, TIMEOUT, REVOKE = 2.0, 4.0, 1.5
SEEN = collections.Counter()


@dataclass
class Payload:
    sample_ids: List[str]

    def subset(self, keep):
        return Payload([self.sample_ids[i] for i in keep])


@dataclass
class Sample:
    sample_id: str


def make_batch(samples):
    return Payload([s.sample_id for s in samples])


def batch_frames(b) -> list:
    """A batch as the server sends it: its header, then one tiny voxels array frame."""
    n = len(b.payload.sample_ids)
    specs, frames = encode_arrays({"voxels": np.zeros((n, 1), np.int8)})
    header = sm.Batch(b.batch_id, b.epoch, tuple(b.payload.sample_ids), ({},) * n, tuple(specs), None, b.batch_id < 0)
    return [pack(header.to_wire())] + [memoryview(f).cast("B") for f in frames]


def options(credits: int) -> StreamOptions:
    return StreamOptions(outputs=("voxels",), credits=credits, timeout_s=60.0, heartbeat_s=1.0, raw=False,
                         reconnect=False, reconnect_timeout_s=60.0, curve_keys=None, rank=0, world_size=1,
                         group="default", shm=False)


@dataclass
class Client:
    """One trainer process: its I/O thread's real session, its record, the consumer's step in
    progress, and the channels of its current connection."""

    name: str
    credits: int = 2
    gen: int = 0
    alive: bool = False
    instance: str = "p0"  # the process's token: a crash makes a new process
    session: ServerSession = None
    record: ResumeState = None
    up: list = field(default_factory=list)  # client -> server, in flight (typed messages)
    down: list = field(default_factory=list)  # server -> client, in flight (frames)
    pending: Optional[dict] = None  # the batch the consumer is taking (waits on a grant)
    claimed: Optional[tuple] = None  # (epoch, ids) claimed, not yet yielded
    history: list = field(default_factory=list)  # (epoch, sample id) the training loop got
    checkpoints: list = field(default_factory=list)  # (record state, len(history))

    @property
    def ident(self) -> bytes:
        return f"{self.name}.{self.gen}".encode()

    def send(self) -> None:
        """The I/O thread sends what the session decided."""
        self.up.extend((self.ident, m) for m in self.session.outgoing())


class Net:
    """The server, its workers (instant) and the clients, on one clock."""

    def __init__(self, names=("t0", "t1"), credits=(2, 2)):
        self.now = 0.0
        self.last_tick = 0.0
        self.core = DeliveryCore(list(WINDOWS), DeliveryPolicy(batch_size=2, epochs=EPOCHS, lease_s=LEASE,
                                                               client_timeout_s=TIMEOUT, revoke_s=REVOKE,
                                                               max_credits=4, shuffle="none"), make_batch,
                                 stall_s=STALL_S)
        self.clients = [Client(n, c) for n, c in zip(names, credits)]
        for c in self.clients:
            c.record = ResumeState(c.name)

    # ------------------------------------------------------------------ server
    def server_reads(self, c: Client, n: int = 1) -> None:
        """The server reads up to ``n`` messages of ``c``'s connection (in order), as its edge
        decodes them."""
        for _ in range(n):
            if not c.up:
                return
            ident, m = c.up.pop(0)
            m = decode_client(pack(m.to_wire()), 1 << 20, 4)
            if isinstance(m, Hello):
                replies = self.core.hello(ident, m, self.now)
            else:
                replies = self.core.message(ident, m, self.now)
            self.route(replies)

    def route(self, msgs) -> None:
        by_ident = {c.ident: c for c in self.clients if c.alive}
        for ident, m in msgs:
            c = by_ident.get(ident)
            if c is not None:
                c.down.append(batch_frames(m) if hasattr(m, "payload") else [pack(m.to_wire())])

    def tick(self) -> None:
        """One turn of the server loop: workers make what is asked, then leases, sends, epochs."""
        for _ in range(4):
            t = self.core.task_for(b"w", self.now)
            if t is None:
                break
            for k in range(WINDOWS[t.video]):
                if (k, 0) not in t.skip:
                    self.core.sample(b"w", t.task, SampleKey(t.video, k), self.now,
                                     lambda lane, s=SampleKey(t.video, k).sample_id(): Sample(s))
            self.core.done(b"w", t.task, WINDOWS[t.video], {}, None)
        sends, msgs = self.core.tick(self.now)
        self.route(sends)
        self.route(msgs)
        self.last_tick = self.now

    def advance(self, dt: float, listening: bool = True) -> None:
        """The clock runs ``dt``; a listening server reads everything and ticks every 0.5 s."""
        if not listening:
            self.now += dt
            return
        end = self.now + dt
        while self.now < end:
            self.now = min(end, self.now + 0.5)
            for c in self.clients:
                self.server_reads(c, len(c.up))
            self.tick()

    # ------------------------------------------------------------------ the client's steps
    def connect(self, c: Client) -> None:
        """A new connection (a new iterator, or a restarted process): a new session says hello."""
        c.gen += 1
        c.alive = True
        c.up, c.down = [], []
        c.pending = c.claimed = None
        c.session = ServerSession(c.name, options(c.credits), c.record, c.name, instance=c.instance)
        c.session.hello(new_socket=True, at=self.host_clock(c))
        c.send()

    def host_clock(self, c: Client) -> float:
        """The client's host's monotonic clock (``Connection._socket`` numbers its hellos by it):
        later for each new socket, even at the same simulated time."""
        return self.now + c.gen * 1e-6

    def io_reads(self, c: Client) -> None:
        """The I/O thread hands one message from the server to the session and sends what it decided."""
        if not c.down:
            return
        frames = c.down.pop(0)
        kind = unpack(frames[0])["type"]
        SEEN[kind] += 1
        c.session.on_message(frames)
        c.send()

    def io_forwards(self, c: Client) -> None:
        """The I/O thread sends what the consumer's steps decided."""
        c.send()

    def consumer_next(self, c: Client) -> None:
        """The consumer takes the next item off the queue: an epoch's end told to the current session
        is recorded; a batch of an epoch it completed is given back; any other batch becomes the one
        it takes."""
        if c.pending is not None or c.claimed is not None:
            return
        try:
            item = c.session.items.get_nowait()
        except queue.Empty:
            return
        if isinstance(item, sm.EpochDone):  # as the endpoint's loop (one told a session a hello ended is not)
            c.session.held.of_session(item, lambda current: take_epoch_end(c.record, item, False, current))
        elif isinstance(item, dict):
            if c.record.is_complete(item["epoch"]):
                c.session.give_back(item)
            else:
                c.pending = item

    def consumer_claims(self, c: Client) -> None:
        """The consumer tries to take its batch (``ServerSession.take``: asks for its grant, claims
        it once granted recording its samples in the same step, acks it)."""
        item = c.pending
        if item is None:
            return
        ok, keep = c.session.take(item, lambda: c.record.claim(item["epoch"], item["batch_id"], item["sample_ids"],
                                                                 False))
        if ok:
            c.pending, c.claimed = None, (item["epoch"], [item["sample_ids"][i] for i in keep])
        elif c.session.held.current.get(item["batch_id"]) is not item:
            c.pending = None  # given back meanwhile: the next one

    def consumer_yields(self, c: Client) -> None:
        """The training loop gets the claimed batch; the trainer checkpoints."""
        if c.claimed is None:
            return
        e, keep = c.claimed
        c.claimed = None
        SEEN["yield"] += 1
        c.history += [(e, s) for s in keep]
        c.checkpoints.append((c.record.state(), len(c.history)))

    def step(self, c: Client) -> None:
        """Every part of the client takes one step."""
        self.io_forwards(c)
        self.io_reads(c)
        self.consumer_yields(c)
        self.consumer_claims(c)
        self.consumer_next(c)

    def heartbeat(self, c: Client) -> None:
        """The I/O thread's clock: heartbeats, and asking again for what stays unanswered."""
        c.session.tick(self.now)
        c.send()

    def close(self, c: Client) -> None:
        """Leaving the loop: what the session queued, its releases and bye, read by the server."""
        c.up.extend((c.ident, m) for m in c.session.outgoing() + c.session.closing())
        for _ in range(len(c.up)):
            self.server_reads(c)
        c.alive = False

    # ------------------------------------------------------------------ checks
    def trained(self):
        return collections.Counter(x for c in self.clients for x in c.history)

    def quiet(self) -> bool:
        return not any(c.up or c.down or not c.session.items.empty() or c.pending or c.claimed
                       for c in self.clients if c.session is not None)

    def run_to_end(self, rounds: int = 2000) -> None:
        for c in self.clients:
            if not c.alive:
                self.connect(c)
        for _ in range(rounds):
            if self.core.finished() and self.quiet():
                break  # finished, and nothing in flight that could reopen an epoch
            for c in self.clients:
                for _ in range(4):
                    self.step(c)
                self.heartbeat(c)
            self.advance(0.5)
        assert self.core.finished(), "the stream never finished"
        expected = {(e, SampleKey(v, k).sample_id()) for e in range(EPOCHS) for v, n in WINDOWS.items()
                    for k in range(n)}
        got = self.trained()
        assert {k: n for k, n in got.items() if n > 1} == {}, "trained twice"
        assert expected - set(got) == set(), "lost"


class LeaseMachine(RuleBasedStateMachine):
    def __init__(self):
        super().__init__()
        self.net = Net(("t0", "t1", "t2"), (2, 3, 1))
        for c in self.net.clients:
            self.net.connect(c)

    def client(self, i) -> Client:
        return self.net.clients[i]

    @rule(i=st.integers(0, 2), part=st.sampled_from(["forward", "read", "next", "claim", "yield"]))
    def client_part(self, i, part):
        c = self.client(i)
        if not c.alive:
            return
        n = self.net
        {"forward": n.io_forwards, "read": n.io_reads, "next": n.consumer_next, "claim": n.consumer_claims,
         "yield": n.consumer_yields}[part](c)

    @rule(i=st.integers(0, 2), n=st.integers(1, 8))
    def client_runs(self, i, n):
        """Every part of the client takes ``n`` steps (the server reads and ticks between)."""
        c = self.client(i)
        for _ in range(n):
            if c.alive:
                self.net.step(c)
                self.net.server_reads(c, len(c.up))
                self.net.tick()

    @rule(i=st.integers(0, 2), n=st.integers(1, 3))
    def server_reads(self, i, n):
        self.net.server_reads(self.client(i), n)

    @rule()
    def server_ticks(self):
        self.net.tick()

    @rule(dt=st.sampled_from([0.5, 1.0, 2.5, 5.0]), beats=st.lists(st.booleans(), min_size=3, max_size=3))
    def time_passes(self, dt, beats):
        """The clock runs; the clients whose I/O thread runs (``beats``) heartbeat; the others
        are paused at whatever point they were."""
        for c, beat in zip(self.net.clients, beats):
            if beat and c.alive:
                self.net.heartbeat(c)
            SEEN["paused"] += not beat
        self.net.advance(dt)

    @rule(dt=st.sampled_from([2.0, 6.0]))
    def server_stalls(self, dt):
        """The server process stops (SIGSTOP, swap) while clients go on; then its loop runs."""
        SEEN["server_stall"] += 1
        for c in self.net.clients:
            if c.alive:
                self.net.heartbeat(c)
        self.net.advance(dt, listening=False)
        self.net.tick()

    @rule(i=st.integers(0, 2))
    def connection_breaks(self, i):
        """The connection breaks: what was in flight either way is lost; a new socket (a new
        identity, ``Connection._socket``) says hello."""
        c = self.client(i)
        if c.alive:
            SEEN["reconnect"] += 1
            c.up.clear()
            c.down.clear()
            c.gen += 1
            c.session.outgoing()  # decided, never sent: the old socket is gone
            c.session.hello(new_socket=True, at=self.net.host_clock(c))
            c.send()

    @rule(i=st.integers(0, 2))
    def leave_loop(self, i):
        c = self.client(i)
        if c.alive and c.claimed is None:
            self.net.close(c)

    @rule(i=st.integers(0, 2))
    def join(self, i):
        c = self.client(i)
        if not c.alive:
            self.net.connect(c)

    @precondition(lambda self: any(c.checkpoints for c in self.net.clients))
    @rule(data=st.data())
    def crash_and_resume(self, data):
        """A trainer dies (its messages in flight may still arrive) and restarts from any older
        checkpoint: its model forgets what came after."""
        i = data.draw(st.sampled_from([i for i, c in enumerate(self.net.clients) if c.checkpoints]))
        c = self.client(i)
        j = data.draw(st.integers(0, len(c.checkpoints) - 1))
        state, n = c.checkpoints[j]
        c.record = ResumeState(c.name)
        c.record.load(state)
        c.history = c.history[:n]
        del c.checkpoints[j + 1:]
        SEEN["crash"] += 1
        late = list(c.up)
        c.instance = f"p{c.gen}"  # a new process
        self.net.connect(c)
        c.up[:0] = late  # the dead process's messages were on the wire before the new hello

    @invariant()
    def credits_bound_what_is_held(self):
        """Leased, revoked and granted-unacknowledged batches together never exceed a client's
        credits, at the server or in the client's book."""
        for c in self.net.core.ledger.clients.values():
            assert self.net.core.ledger.table.held_count(c.ident) <= c.credits
        for c in self.net.clients:
            if c.alive:
                held = c.session.held
                assert len(held.current) <= c.credits and held.asked | held.granted <= set(held.current)

    @invariant()
    def no_sample_twice(self):
        dup = {k: n for k, n in self.net.trained().items() if n > 1}
        assert not dup, f"trained twice: {dup}"

    def teardown(self):
        self.net.run_to_end()


LeaseMachine.TestCase.settings = settings(max_examples=300, stateful_step_count=60, deadline=None,
                                          suppress_health_check=list(HealthCheck))
TestLeaseProtocol = LeaseMachine.TestCase


# ------------------------------------------------------------------ one schedule per pause point
POINTS = ["received", "asked", "hold_at_server", "granted_in_flight", "granted", "claimed", "ack_queued",
          "ack_sent"]


def _to_point(net: Net, a: Client, point: str) -> None:
    """Run client ``a`` alone from its hello to ``point`` on its first batch."""
    def kind(i=0):
        return unpack(a.down[i][0])["type"]

    for _ in range(40):
        net.server_reads(a, len(a.up))
        net.tick()
        if a.down and kind() != "batch":
            net.io_reads(a)
            continue
        if a.down:
            break
    net.io_reads(a)  # the batch: received, and asked for at once (GRANT_AHEAD)
    if point == "received":
        a.up.clear()  # paused before the I/O thread's hold left the process
        a.session.held.asked.clear()
        return
    if point == "asked":
        return
    net.server_reads(a, len(a.up))  # the hold is read: granted (and recorded) at the server
    if point == "hold_at_server":
        return
    while a.down and kind() != "granted":
        net.io_reads(a)
    if point == "granted_in_flight":
        return
    net.io_reads(a)
    net.consumer_next(a)
    if point == "granted":
        return
    net.consumer_claims(a)
    assert a.claimed is not None
    if point == "claimed":
        a.session.outgoing()  # paused before the ack was queued: it never leaves
        return
    if point == "ack_queued":
        return
    net.io_forwards(a)
    assert point == "ack_sent"


def _b_reads_past_every_timeout(net: Net, b: Client) -> None:
    """Client B connects and reads, with heartbeats, while the server's clock runs past the
    lease, the revoke timeout and the client timeout together (the other client paused)."""
    net.connect(b)
    for _ in range(int((LEASE + REVOKE + TIMEOUT + 2) / 0.5)):
        for _ in range(4):
            net.step(b)
        net.heartbeat(b)
        net.advance(0.5)


@pytest.mark.parametrize("point", POINTS)
def test_a_client_paused_at_each_point_between_receipt_and_yield_doubles_and_loses_nothing(point):
    """Client A is stopped at ``point`` on its first batch for longer than the lease, the revoke
    timeout and the client timeout together, while client B reads and the server ticks; then A
    resumes where it stopped (its I/O thread first or its consumer first), and both run to the
    end: every sample of every epoch reaches one training loop, once."""
    for io_first in (True, False):
        net = Net(("a", "b"), (4, 1))
        a, b = net.clients
        net.connect(a)
        _to_point(net, a, point)
        _b_reads_past_every_timeout(net, b)
        if io_first:
            net.io_forwards(a)
            net.io_reads(a)
        net.consumer_yields(a)
        net.consumer_claims(a)
        net.consumer_yields(a)
        net.run_to_end()


def test_a_stalled_server_drops_nobody_for_its_own_silence():
    """The server's loop stops for longer than the client timeout while the clients' messages
    wait in its socket: when it runs again, nobody is dropped and no lease is revoked."""
    net = Net(("a",), (2,))
    (a,) = net.clients
    net.connect(a)
    for _ in range(6):
        net.step(a)
        net.advance(0.5)
    table = net.core.ledger.table
    assert a.ident in net.core.ledger.clients
    held = {bid: table.get(bid).state for bid in table.held_by(a.ident)}
    net.heartbeat(a)
    net.advance(TIMEOUT + LEASE + 1, listening=False)
    net.tick()  # before reading the waiting messages: the stall is not the client's silence
    c = net.core.ledger.clients.get(a.ident)
    assert c is not None and net.core.ledger.stalls == 1
    assert {bid: table.get(bid).state for bid in table.held_by(a.ident)} == held  # nothing revoked or taken
    assert STALL_S < TIMEOUT
    net.run_to_end()


def _read_epoch_0_but_one(core: DeliveryCore, ident: bytes) -> int:
    """``ident`` (4 credits) is sent every batch of the one-epoch stream at once, is granted and
    acknowledges all but the last, which it asks for and keeps granted; returns that batch's id."""
    _make_everything(core, 0.0)
    sends, _ = core.tick(0.0)
    held = sorted(b.batch_id for i, b in sends if i == ident)
    assert len(held) == 4 and not core.ledger.ready  # 8 samples, 2 a batch
    for bid in held[:-1]:
        core.message(ident, Hold((bid,)), 0.1)
        core.message(ident, Ack((bid,)), 0.1)
    assert core.message(ident, Hold((held[-1],)), 0.2)[0][1].batch_ids == (held[-1],)
    return held[-1]


def test_a_reader_is_told_an_epoch_complete_only_once_it_holds_no_grant_of_it():
    """A granted batch may still be given back unused (the loop left before taking it): its
    holder is told its epoch complete only once it is acknowledged, so it never forgets an epoch
    it still holds samples of; given back, the batch is sent again."""
    core = _one_epoch_core()
    core.hello(b"a.1", Hello(("voxels",), 4, consumer="a"), 0.0)
    last = _read_epoch_0_but_one(core, b"a.1")
    core.tick(0.3)
    a = core.ledger.clients[b"a.1"]
    assert core.sched.plans[0].complete and a.completed == -1  # granted, not acknowledged
    back = core.message(b"a.1", Released((last,)), 0.3)
    assert back == [] and not core.sched.plans[0].complete and last in core.ledger.ready
    sends, _ = core.tick(0.4)
    assert (b"a.1", last) in [(i, b.batch_id) for i, b in sends]  # sent again
    core.message(b"a.1", Hold((last,)), 0.5)
    core.message(b"a.1", Ack((last,)), 0.5)
    _, msgs = core.tick(0.6)
    assert a.completed == 0 and [m.to_wire()["type"] for i, m in msgs if i == b"a.1"][:2] == ["epoch_done", "end"]


def test_an_ack_lost_with_a_broken_connection_is_said_again():
    """ZeroMQ reconnects a broken connection behind the socket (same identity, no new hello), and
    what was in the kernel's buffers is lost: an ``ack`` lost so would leave the batch granted, and
    its reader never told the epoch complete. The session names what it acknowledged in its next
    heartbeat's ``hold``; the server answers ``granted`` while it holds it, and the ack is said again."""
    net = Net(names=("t0",), credits=(2,))
    c = net.clients[0]
    net.connect(c)
    lost = []
    for _ in range(100):
        net.step(c)
        net.heartbeat(c)
        acks = [x for x in c.up if isinstance(x[1], Ack)]
        if acks and not lost:
            c.up.remove(acks[0])
            lost.append(acks[0][1])
        net.advance(0.5)
    assert lost and lost[0] not in {m for _, m in c.up}
    net.run_to_end()
    assert [unpack(f[0])["type"] for f in c.down][-1:] in ([], ["end"])


def test_a_dead_processs_late_hello_does_not_undo_what_a_newer_process_read():
    """A killed trainer's hello, held by a partition, reaches the server after its restarted process
    read the epoch and left: it waits for its connection to speak again (a dead process never
    does), is forgotten after the client timeout, and the newer process's record stands. A
    restart from an older checkpoint, whose process lives, is let in and reopens the epoch."""
    core = _one_epoch_core()
    core.hello(b"new", Hello(("voxels",), 4, consumer="t1", instance="B"), 0.0)
    last = _read_epoch_0_but_one(core, b"new")
    core.message(b"new", Ack((last,)), 0.3)
    core.message(b"new", Bye(), 0.4)
    assert core.sched.plans[0].complete
    assert core.hello(b"dead", Hello(("voxels",), 4, consumer="t1", instance="A"), 5.0) == []  # waits
    for t in np.arange(5.5, 5.0 + TIMEOUT + 2.0, 0.5):
        sends, msgs = core.tick(float(t))
        assert sends == [] and not [m for i, m in msgs if isinstance(m, sm.Welcome)]
    assert core.sched.plans[0].complete and not core.admission.pending  # forgotten, the record stands
    core.hello(b"restart", Hello(("voxels",), 4, consumer="t1", instance="C"), 20.0)
    welcomed = []
    for t in np.arange(20.5, 24.0, 0.5):
        core.message(b"restart", Heartbeat(), float(t))  # its process lives
        welcomed += [m for i, m in core.tick(float(t))[1] if isinstance(m, sm.Welcome)]
    assert welcomed and not core.sched.plans[0].complete  # its older state reopens the epoch


def test_a_restarted_process_paused_while_its_hello_waits_is_let_in_once_it_speaks():
    """A trainer restarted from an older checkpoint says hello, which waits for its proof of life,
    and its process is paused longer than the client timeout (swap, SIGSTOP) twice: right after
    its hello, and right after the hello it says again. The server forgets a silent waiting hello
    so that it holds nothing back, but its connection is not told: the session awaits that hello's
    welcome and ignores ``unknown_client``. The hello waits again once its connection speaks,
    so the reader is let in and reads the batch its dead process was granted
    (hypothesis ``LeaseMachine``: a.mp4#2 and b.mp4#0 of epoch 0 lost)."""
    net = Net(names=("t",), credits=(1,))
    c = net.clients[0]
    net.connect(c)
    for _ in range(6):  # batch 0 yielded and checkpointed; batch 1 granted, not yet yielded
        net.step(c)
        net.server_reads(c, len(c.up))
        net.tick()
    state, n = c.checkpoints[0]
    c.record = ResumeState(c.name)
    c.record.load(state)
    c.history, c.instance = c.history[:n], "p1"  # a new process, from the first checkpoint
    net.connect(c)
    net.heartbeat(c)
    net.advance(TIMEOUT + 1.0)  # read, waits, paused: forgotten
    assert not net.core.admission.pending
    net.heartbeat(c)
    net.advance(0.5)
    for _ in range(3):
        net.io_reads(c)  # on main: unknown_client, hello again (awaiting its welcome)
    net.advance(TIMEOUT + 1.0)  # paused again
    net.run_to_end()  # on main: the stream never finished (unknown_client ignored for good)
    assert sorted(s for e, s in c.history if e == 0) == [SampleKey(v, k).sample_id() for v, n in WINDOWS.items()
                                                         for k in range(n)]


def test_a_hello_said_again_and_lost_in_a_server_crash_is_said_once_more():
    """A trainer paused past the client timeout wakes to ``dropped`` and says hello again; the server
    crashes before it reads that hello and restarts. The session awaits the lost hello's welcome,
    ignoring what answers messages said before it, but every heartbeat names its latest hello and
    the restarted server's ``unknown_client`` names it back: the hello is gone, so the session says
    it once more, and the stream ends with every sample read once (docs/delivery.md, rule 5;
    simulator finding F27, ``rehello_lost_in_server_crash``)."""
    net = Net(names=("t",), credits=(1,))
    c = net.clients[0]
    net.connect(c)
    for _ in range(6):
        net.step(c)
        net.server_reads(c, len(c.up))
        net.tick()
    net.advance(TIMEOUT + 1.0)  # the trainer is paused: dropped for silence
    while c.down:
        net.io_reads(c)  # it wakes: what was sent meanwhile, then ``dropped``
    assert [m.hello_id for _, m in c.up if isinstance(m, Hello)] == [2]
    c.up.clear()  # the server is killed before it reads the hello
    net.core = Net(names=(), credits=()).core  # and restarts (without --state-dir: it trusts the state)
    for _ in range(2):  # its clock's first turn, then a heartbeat
        net.heartbeat(c)
        net.advance(1.0)
    answers = [sm.stream_message(unpack(f[0])) for f in c.down]  # to its heartbeat and its holds said again
    assert {m.code for m in answers} == {"unknown_client"} and sorted(m.hello_id for m in answers)[-2:] == [0, 2]
    while c.down:
        net.io_reads(c)
    assert [m.hello_id for _, m in c.up if isinstance(m, Hello)] == [3]  # on main: none, for good
    net.run_to_end()


def test_a_hello_lost_in_a_break_zeromq_mends_is_said_again_at_the_next_heartbeat():
    """A session says hello again on its connection (an end it missed, F38 and F45; a codec the
    server lacks) and a break of the connection that ZeroMQ mends behind the socket loses that
    hello. The server still holds the session before it and, the stream over, tells it the last
    epoch's end and ``end`` at each heartbeat, which the session ignores while it awaits its
    welcome. Its heartbeats name the lost hello; the server, which let in an older one on that
    connection, answers ``unknown_client`` naming it, so the session says it once more, is
    welcomed, and the stream ends for its loop (simulator finding F50, ``mixed`` seed 30965)."""
    net = Net(names=("t",), credits=(1,))
    c = net.clients[0]
    net.run_to_end()
    while not c.session.items.empty():
        c.session.items.get_nowait()
    c.session.hello(at=net.host_clock(c))
    c.send()
    [(_, lost)] = [(i, m) for i, m in c.up if isinstance(m, Hello)]
    c.up.clear()  # lost in the break
    said, told = [], []
    for _ in range(6):  # three seconds of heartbeats
        net.heartbeat(c)
        said += [m.hello_id for _, m in c.up if isinstance(m, Hello)]
        net.advance(0.5)
        while c.down:
            net.io_reads(c)
        while not c.session.items.empty():
            told.append(c.session.items.get_nowait())
    assert said and said[0] > lost.hello_id  # on main: none; the session awaited its welcome for good
    assert [type(x) for x in told][-1:] == [StopIteration], told


def test_a_late_hello_of_a_readers_older_connection_never_fences_its_newer_one():
    """A loader worker's connection closed (or its process killed) while its socket still
    connected: its hello arrives after the next worker's, of the same reader process (``instance``).
    Hellos of one reader are numbered by the host's monotonic clock; the older one is refused
    (``fenced``) and the newer connection reads on, its record and grant untouched."""
    core = _one_epoch_core()
    core.hello(b"w1.new", Hello(("voxels",), 4, consumer="x/1", hello_id=2_000_000, instance="L"), 0.0)
    last = _read_epoch_0_but_one(core, b"w1.new")  # granted, waiting in the loader's queue
    late = core.hello(b"w1.old", Hello(("voxels",), 4, consumer="x/1", hello_id=1_000_000, instance="L"), 0.3)
    assert [(i, m.code) for i, m in late] == [(b"w1.old", "fenced")]
    assert b"w1.new" in core.ledger.clients and core.ledger.table.get(last).state == "granted"
    assert core.sched.plans[0].complete  # the older state reopened nothing


def test_a_late_hello_numbered_as_the_one_let_in_never_fences_it():
    """A loader worker's iteration opened a connection, closed it and opened the next within one
    tick of the host's monotonic clock: both hellos carry the same ``hello_id``. The first one's
    arrives late, after the second's was let in and its grant reached the loop: it is not newer, so
    it is refused (``fenced``); let in, it fenced the live connection and its resume state (naming
    nothing) sent the grant the loop received to another worker (simulator finding F46, mixed
    108414). The same connection's hello said again is still let in."""
    core = _one_epoch_core()
    hello = Hello(("voxels",), 4, consumer="x/1", hello_id=63_868_658, instance="L")
    core.hello(b"w1.new", hello, 0.0)
    last = _read_epoch_0_but_one(core, b"w1.new")  # granted, waiting in the loader's queue
    late = core.hello(b"w1.old", hello, 0.3)
    assert [(i, getattr(m, "code", type(m).__name__)) for i, m in late] == [(b"w1.old", "fenced")]
    assert b"w1.new" in core.ledger.clients and core.ledger.table.get(last).state == "granted"
    again = core.hello(b"w1.new", hello, 0.4)
    assert [(i, type(m).__name__) for i, m in again] == [(b"w1.new", "Welcome")]


def test_a_reader_sitting_on_a_grant_delays_the_others_end_of_the_epoch_by_the_lease_at_most():
    """Reader A keeps a grant of epoch 0 and never acknowledges it (a stuck loop, an hour of
    validation): reader B, holding nothing of epoch 0, is told the epoch complete and the stream
    ended ``lease_s`` after A's grant at most, never waiting on A. A grant A gives back after
    that goes to A, which was not told, never to B; A is told once it took it."""
    core = _one_epoch_core()
    core.hello(b"a.1", Hello(("voxels",), 2, consumer="a"), 0.0)
    core.hello(b"b.1", Hello(("voxels",), 1, consumer="b"), 0.0)
    table = core.ledger.table
    _make_everything(core, 0.0)
    kept = None
    granted_at = None
    for step in range(100):
        now = 0.1 * step
        core.message(b"a.1", Heartbeat(), now)
        core.message(b"b.1", Heartbeat(), now)
        sends, msgs = core.tick(now)
        told_b = [m.to_wire()["type"] for i, m in msgs if i == b"b.1" and m.to_wire()["type"] != "drained"]
        if told_b:
            break
        for ident, b in sends:
            core.message(ident, Hold((b.batch_id,)), now)
            if ident == b"a.1" and granted_at is None:
                granted_at, kept = now, b.batch_id  # A keeps its first grant and never acknowledges it
            else:
                core.message(ident, Ack((b.batch_id,)), now)
    assert told_b == ["epoch_done", "end"] and granted_at is not None
    assert now - granted_at <= LEASE + 0.2, (now, granted_at)
    assert core.ledger.clients[b"a.1"].completed == -1  # A holds samples of epoch 0 still
    core.message(b"a.1", Released((kept,)), now)
    sends, msgs = core.tick(now + 0.1)
    assert [(i, b.batch_id) for i, b in sends] == [(b"a.1", kept)]  # to A, the one not told
    core.message(b"a.1", Hold((kept,)), now + 0.2)
    core.message(b"a.1", Ack((kept,)), now + 0.2)
    _, msgs = core.tick(now + 0.3)
    assert [m.to_wire()["type"] for i, m in msgs if i == b"a.1"][:2] == ["epoch_done", "end"]


def test_a_reader_sitting_on_what_it_was_sent_delays_the_others_end_of_the_epoch_within_the_stated_bound():
    """docs/delivery.md's bound: reader A never takes what it is sent and answers each revoke
    with a ``hold`` at the last moment (the latest a leased batch can become a grant), then sits
    on the grants; reader B, reading everything else, is told the epoch complete and the stream
    ended at most ``2 lease_s + revoke_s`` after the last batch sent to A."""
    core = _one_epoch_core()
    core.hello(b"a.1", Hello(("voxels",), 2, consumer="a"), 0.0)
    core.hello(b"b.1", Hello(("voxels",), 1, consumer="b"), 0.0)
    _make_everything(core, 0.0)
    sent_to_a: Dict[int, float] = {}
    revoked_at: Dict[int, float] = {}
    told_b: List[str] = []
    for step in range(400):
        now = 0.05 * step
        core.message(b"a.1", Heartbeat(), now)
        core.message(b"b.1", Heartbeat(), now)
        for bid, t in list(revoked_at.items()):
            if now >= t + REVOKE - 0.1:  # the revoke's deadline is about to pass: A asks for it
                assert core.message(b"a.1", Hold((bid,)), now)[0][1].batch_ids == (bid,)
                del revoked_at[bid]
        sends, msgs = core.tick(now)
        for ident, m in msgs:
            if ident == b"a.1" and isinstance(m, sm.Revoke):
                revoked_at.update((bid, now) for bid in m.batch_ids)
        told_b += [m.to_wire()["type"] for i, m in msgs if i == b"b.1" and m.to_wire()["type"] != "drained"]
        if told_b:
            break
        for ident, b in sends:
            if ident == b"a.1":
                sent_to_a[b.batch_id] = now
            else:
                core.message(ident, Hold((b.batch_id,)), now)
                core.message(ident, Ack((b.batch_id,)), now)
    assert told_b == ["epoch_done", "end"] and sent_to_a and not revoked_at
    assert b"a.1" in core.ledger.clients and core.ledger.clients[b"a.1"].completed == -1  # A sits on 2 grants
    assert {core.ledger.table.get(bid).state for bid in sent_to_a} == {"granted"}
    waited = now - max(sent_to_a.values())
    assert LEASE + REVOKE < waited <= 2 * LEASE + REVOKE + 0.1, (now, sent_to_a)  # the worst case, within the bound


def test_the_ack_only_rule_doubles_on_the_same_schedule():
    """The ack-only client rule (take any batch still held, ask for nothing: ``bench.lease``'s
    baseline), paused after its claim on the schedule above: the server gives the batch to B
    meanwhile and A yields it too. The same pieces tell the two rules apart."""
    with ack_only():
        net = Net(("a", "b"), (4, 1))
        a, b = net.clients
        net.connect(a)
        net.server_reads(a, len(a.up))
        net.tick()
        while a.session.items.empty():
            net.io_reads(a)
        net.consumer_next(a)
        net.consumer_claims(a)
        assert a.claimed is not None  # taken, its ack queued: then A stops
        _b_reads_past_every_timeout(net, b)
        net.consumer_yields(a)
        with pytest.raises(AssertionError, match="trained twice"):
            net.run_to_end()


def _one_epoch_core(epochs: int = 1) -> DeliveryCore:
    return DeliveryCore(list(WINDOWS), DeliveryPolicy(batch_size=2, epochs=epochs, lease_s=LEASE, client_timeout_s=TIMEOUT,
                                                      revoke_s=REVOKE, max_credits=4, shuffle="none"), make_batch,
                        stall_s=STALL_S)


def _make_everything(core: DeliveryCore, now: float) -> None:
    """The server's workers make every sample asked for (instantly)."""
    while True:
        t = core.task_for(b"w", now)
        if t is None:
            return
        for k in range(WINDOWS[t.video]):
            if (k, 0) not in t.skip:
                core.sample(b"w", t.task, SampleKey(t.video, k), now,
                            lambda lane, s=SampleKey(t.video, k).sample_id(): Sample(s))
        core.done(b"w", t.task, WINDOWS[t.video], {}, None)


def _turn(core: DeliveryCore, now: float) -> Dict[bytes, list]:
    """One turn of the server loop: what each client is sent (batch ids, and "drained")."""
    _make_everything(core, now)
    sends, msgs = core.tick(now)
    out: Dict[bytes, list] = collections.defaultdict(list)
    for ident, b in sends:
        out[ident].append(b.batch_id)
    for ident, m in msgs:
        out[ident].append(m.to_wire()["type"])
    return out


def _hello(core: DeliveryCore, ident: bytes, consumer: str, now: float, delivered=(), ends_on_drained=True):
    resume = Resume(-1, {0: frozenset(parse_sample_id(s) for s in delivered)} if delivered else {})
    core.hello(ident, Hello(("voxels",), 2, consumer=consumer, resume=resume, ends_on_drained=ends_on_drained),
               now)


def _two_workers_then_a_new_iteration(ends_on_drained: bool):
    """A StreamLoader's two workers (consumers x/0 and x/1, 2 credits each) read the 4 batches
    of a 1-epoch stream; the loop receives 3 and leaves the iteration while x/1's fourth batch
    ``b``, granted, waits in the loader's queue. In the next iteration worker 0 says hello
    first and is told ``drained`` (``b`` is still granted to worker 1's old connection, which
    has not closed yet); then worker 1's old connection gives ``b`` back, and worker 1 says
    hello. Returns (the core, ``b``, what each connection was sent after the first iteration)."""
    core = _one_epoch_core()
    for ident, consumer in ((b"x0.1", "x/0"), (b"x1.1", "x/1")):
        _hello(core, ident, consumer, 0.0, ends_on_drained=ends_on_drained)
    sent = _turn(core, 0.0)
    a_ids, b_ids = sorted(sent[b"x0.1"]), sorted(sent[b"x1.1"])
    assert len(a_ids) == len(b_ids) == 2
    received = {}
    for ident, bids in ((b"x0.1", a_ids), (b"x1.1", b_ids)):
        core.message(ident, Hold(tuple(bids)), 0.1)
        received[ident] = [s for bid in bids[: 2 if ident == b"x0.1" else 1]
                           for s in core.ledger.batches[bid].payload.sample_ids]
    core.message(b"x0.1", Ack(tuple(a_ids)), 0.2)
    core.message(b"x1.1", Ack((b_ids[0],)), 0.2)
    b = b_ids[1]
    _turn(core, 0.3)
    # the next iteration: worker 0's old connection closes, its new one says hello
    core.message(b"x0.1", Bye(), 1.0)
    _hello(core, b"x0.2", "x/0", 1.0, received[b"x0.1"], ends_on_drained)
    after = collections.defaultdict(list)
    for ident, got in _turn(core, 1.1).items():
        after[ident] += got
    # worker 1's old connection gives b back and closes; its new one says hello
    core.message(b"x1.1", Released((b,)), 2.0)
    core.message(b"x1.1", Bye(), 2.0)
    for ident, got in _turn(core, 2.1).items():
        after[ident] += got
    _hello(core, b"x1.2", "x/1", 2.2, received[b"x1.1"], ends_on_drained)
    for ident, got in _turn(core, 2.3).items():
        after[ident] += got
    return core, b, after


def test_a_dataloader_worker_told_drained_is_sent_nothing_after_it():
    """A StreamLoader worker ends its iteration on ``drained``: the server must send it nothing
    after it. Else the batch a sibling's old connection gives back goes to the worker that is
    leaving, the sibling's new connection is told ``drained`` meanwhile (the batch is leased
    elsewhere), the leaving worker gives it back with its ``bye``, and nobody in the iteration
    reads it: the loop's iteration ends without its samples (seen under load in
    tests/test_loaders.py's break-and-iterate-again scenario)."""
    core, b, after = _two_workers_then_a_new_iteration(ends_on_drained=True)
    assert after[b"x0.2"] == ["drained"], after  # told while b is granted to its sibling: allowed
    assert after[b"x1.2"] == [b], after  # b goes to the worker that still reads
    core.message(b"x0.2", Bye(), 3.0)
    core.message(b"x1.2", Hold((b,)), 3.0)
    core.message(b"x1.2", Ack((b,)), 3.0)
    _turn(core, 3.1)
    assert core.finished()


def test_a_client_that_reads_on_after_drained_is_still_sent_what_comes_back():
    """A client that does not end on ``drained`` (a trainer without DataLoader workers) is
    sent a batch given back after it was told ``drained``."""
    core, b, after = _two_workers_then_a_new_iteration(ends_on_drained=False)
    assert after[b"x0.2"] == ["drained", b], after


def test_no_worker_is_told_drained_while_a_batch_is_leased_to_anyone():
    """A trainer is sent batches and stops before asking for them (stopped, then dead for good);
    two StreamLoader workers read the rest and ack it. A worker told ``drained`` ends its
    iteration and is sent nothing more, so the trainer's batches, back in the queue once its
    lease runs out and it is dropped, would reach no loop: the workers are told ``drained`` only
    once nothing is leased anywhere, and the trainer's batches reach them (docs/delivery.md, "The
    protocol", rule 6; the simulator's F12, F13)."""
    core = _one_epoch_core()
    _hello(core, b"t.1", "t", 0.0, ends_on_drained=False)
    leased = [m for m in _turn(core, 0.0)[b"t.1"] if isinstance(m, int)]
    assert leased
    got: Dict[bytes, list] = {b"x0.1": [], b"x1.1": []}
    for ident, consumer in ((b"x0.1", "x/0"), (b"x1.1", "x/1")):
        _hello(core, ident, consumer, 0.1)
    drained_at: Dict[bytes, float] = {}
    acked: set = set()
    now = 0.1
    while len(drained_at) < 2 and now < 10 * (LEASE + REVOKE + TIMEOUT):
        for ident, out in _turn(core, now).items():
            for m in out if ident in got else ():
                if m == "drained":
                    drained_at.setdefault(ident, now)
                elif isinstance(m, int):
                    got[ident].append(m)
        for ident, bids in got.items():
            new = tuple(b for b in bids if b not in acked)
            core.message(ident, Hold(new) if new else Heartbeat(), now)
            if new:
                core.message(ident, Ack(new), now)
                acked.update(new)
        now += 0.25
    assert set(leased) <= set(got[b"x0.1"] + got[b"x1.1"]), (leased, got)
    assert len(drained_at) == 2 and min(drained_at.values()) >= LEASE, drained_at
    assert core.finished()


def test_a_client_that_closed_after_its_last_messages_still_gives_back_what_it_released():
    """A trainer breaks out of its loop: its ``hold``, the batches it gives back and ``bye`` go
    out and its connection closes. A server that reads them after the close cannot send the
    answer to the hold (a real ROUTER with ``ROUTER_MANDATORY`` and no such peer), and must still
    read the release that follows as the client's: the batch goes back to the queue, not to a
    consumer that never yielded it. The client is forgotten once its messages are read."""
    import zmq

    from v2v_server.delivery.ledger import BatchRecord
    from v2v_server.ops.config import ServeConfig
    from v2v_server.ops.metrics import ServerMetrics
    from v2v_server.service.client_side import ClientSide
    from v2v_wire.protocol import pack

    cfg = ServeConfig()
    core = DeliveryCore(["v.mp4"], DeliveryPolicy(), lambda samples: samples)
    clients = ClientSide(cfg, core, ServerMetrics())
    ctx = zmq.Context()
    frontend = ctx.socket(zmq.ROUTER)
    frontend.setsockopt(zmq.ROUTER_MANDATORY, 1)
    frontend.bind("inproc://v2v-closed-client")
    try:
        clients.attach(frontend, None)
        ident = b"gone"
        hello = Hello(("voxels",), 2, consumer="A", resume=Resume(-1, {}))
        core.hello(ident, hello, 0.0)  # its welcome was sent while it was connected
        core.ledger.add_batch(BatchRecord(7, 0, [SampleKey("v.mp4", 0)], None, outputs=frozenset({"voxels"})))
        assert [(to, b.batch_id) for to, b in core.ledger.sends(0.0)[0]] == [(ident, 7)]

        def said(msg) -> None:  # what the closed client sent, read now
            clients.on_message([zmq.Frame(ident), zmq.Frame(pack(msg.to_wire()))])

        said(Hold((7,)))  # granted; the answer cannot be sent
        said(Released((7,)))
        assert list(core.ledger.ready) == [7]  # back to the queue for another trainer
        said(Bye())
        core.caught_up()
        assert core.connected() == []
    finally:
        frontend.close(0)
        ctx.term()


def test_a_reader_sitting_on_a_grant_forever_never_makes_an_unbounded_stream_keep_more_epochs():
    """On a stream without ``--epochs``, reader A keeps one grant of epoch 0 and never
    acknowledges it while reader B reads 12 epochs: B is told each epoch complete, and the server
    keeps a bounded number of epochs open (it does not accumulate one per epoch B reads, as it
    did when an epoch waited for every grant of it); A's grant stays in the table, A's."""
    core = DeliveryCore(list(WINDOWS), DeliveryPolicy(batch_size=2, epochs=None, lease_s=LEASE,
                                                      client_timeout_s=TIMEOUT, revoke_s=REVOKE, max_credits=4,
                                                      shuffle="none"), make_batch, stall_s=STALL_S)
    core.hello(b"a", Hello(("voxels",), 1, consumer="a"), 0.0)
    core.hello(b"b", Hello(("voxels",), 2, consumer="b"), 0.0)
    kept, told_b, most_open, now = None, [], 0, 0.0
    while len(told_b) < 12 and now < 600:
        now += 0.5
        _make_everything(core, now)
        core.message(b"a", Heartbeat(), now)
        core.message(b"b", Heartbeat(), now)
        sends, msgs = core.tick(now)
        for ident, b in sends:
            core.message(ident, Hold((b.batch_id,)), now)
            if ident == b"a" and kept is None:
                kept = b.batch_id  # A's one grant, never acknowledged
            elif ident == b"b":
                core.message(ident, Ack((b.batch_id,)), now)
        told_b += [m.epoch for i, m in msgs if i == b"b" and m.to_wire()["type"] == "epoch_done"]
        most_open = max(most_open, len(core.sched.plans))
    assert told_b == list(range(12)), told_b
    assert most_open <= core.sched.keep_epochs + core.sched.lookahead + 2, most_open
    assert core.ledger.table.get(kept).state == "granted" and core.ledger.clients[b"a"].completed < 0


def test_a_grant_given_back_for_an_epoch_its_loop_completed_is_owed_again_when_the_release_is_lost():
    """The hypothesis machine's schedule: t0 reads two batches of epoch 0 ahead and crashes back
    to its first checkpoint; every client is dropped for silence; t2's old session had been told
    epoch 0 complete, and its new session is sent and granted a reopened batch of epoch 0 before
    its loop takes that ``epoch_done``. The loop then gives the batch back, the connection breaks
    with the release unsent, and the next hello says epoch 0 complete without naming the batch:
    the batch goes back to the queue (it was retired as taken, and its samples reached no loop)."""
    m = LeaseMachine()
    n = m.net
    m.client_runs(0, 7)
    m.client_runs(0, 2)
    t0 = n.clients[0]
    state, kept = t0.checkpoints[0]
    t0.record = ResumeState(t0.name)
    t0.record.load(state)
    t0.history = t0.history[:kept]
    del t0.checkpoints[1:]
    t0.instance = "p1"  # a new process
    n.connect(t0)
    for _ in range(5):  # its connection speaks on (it is let in); the others are dropped for silence
        m.time_passes(1.0, [True, False, False])
    m.client_runs(0, 7)
    m.client_runs(2, 8)
    given_back = [b for b in n.core.ledger.table.batches.values() if b.state == "granted" and b.holder == b"t2.1"]
    assert given_back and given_back[0].epoch == 0, "the schedule no longer reaches the case"
    m.connection_breaks(2)
    n.run_to_end()  # asserts every id of both epochs trained once


def _say_hello(core: DeliveryCore, ident: bytes, rec: ResumeState, credits: int, now: float, instance: str):
    """``rec``'s reader says hello at its position (``ResumeState.place`` before), through the wire."""
    group, rank, world = rec.position
    h = Hello(("voxels",), credits, consumer=rec.consumer, resume=rec.hello_resume(), group=group or None,
              rank=rank, world_size=world, instance=instance)
    return core.hello(ident, decode_client(pack(h.to_wire()), 1 << 20, 4), now)


def _read_to_the_end(core: DeliveryCore, readers: Dict[bytes, ResumeState], now: float) -> List[tuple]:
    """Readers that heartbeat and take every batch they are sent (a batch of an epoch a reader's
    record completed is given back; DDP padding is not a sample) until the stream ends: the
    (epoch, sample id) their loops got."""
    got = []
    for _ in range(200):
        now += 0.5
        for ident in readers:  # its I/O thread's heartbeat (a waiting hello's proof of life)
            core.message(ident, Heartbeat(), now)
        _make_everything(core, now)
        sends, msgs = core.tick(now)
        for ident, b in sends:
            rec = readers[ident]
            if b.batch_id < 0:
                continue
            if rec.is_complete(b.epoch):
                core.message(ident, Released((b.batch_id,)), now)
                continue
            assert core.message(ident, Hold((b.batch_id,)), now)[0][1].batch_ids == (b.batch_id,)
            keep = rec.claim(b.epoch, b.batch_id, b.payload.sample_ids, False)
            got += [(b.epoch, b.payload.sample_ids[i]) for i in keep]
            core.message(ident, Ack((b.batch_id,)), now)
        for ident, m in msgs:
            if isinstance(m, sm.EpochDone):
                readers[ident].complete(m.epoch)
        if core.finished():
            return got
    raise AssertionError("the stream did not end")


@pytest.mark.parametrize("world", [1, 3])
def test_a_gathered_state_loses_no_grant_of_an_epoch_one_rank_had_not_completed(world):
    """A DDP job of 2 ranks: rank 0 takes its 3 batches of epoch 0; rank 1 is granted the 4th,
    ``b``, and its loop has not reached it (it stopped, or a validation pass holds the job) when
    both checkpoint. ``b``'s grant grows ``lease_s`` old and rank 0 is told epoch 0 complete, so
    rank 0's state says epoch 0 complete while rank 1's names nothing of it. The job resumes at
    world size 1 (another consumer) or 3 (the same group: new rank 0 is old rank 0's consumer)
    from both states gathered: ``b``'s samples reached no loop the resumed job keeps, so it must
    read them; every other sample of epoch 0 it must not read again."""
    core = DeliveryCore(list(WINDOWS), DeliveryPolicy(batch_size=2, epochs=2, lease_s=LEASE, client_timeout_s=100.0,
                                                      revoke_s=REVOKE, max_credits=4, shuffle="none"),
                        make_batch, stall_s=STALL_S)
    ranks = [ResumeState("job"), ResumeState("job")]
    for r, rec in enumerate(ranks):
        rec.place("g", r, 2)
        _say_hello(core, b"r%d" % r, rec, 3 - 2 * r, 0.0, f"job1.rank{r}")
    got = []
    sent = _turn(core, 0.0)
    assert len(sent[b"r0"]) == 3 and len(sent[b"r1"]) == 1, sent
    for bid in sent[b"r0"]:
        b = core.ledger.batches[bid]
        core.message(b"r0", Hold((bid,)), 0.1)
        got += [(0, sid) for sid in b.payload.sample_ids]
        ranks[0].claim(0, bid, b.payload.sample_ids, False)
        core.message(b"r0", Ack((bid,)), 0.1)
    (b,) = sent[b"r1"]
    core.message(b"r1", Hold((b,)), 0.1)  # granted; rank 1's loop has not taken it
    assert "epoch_done" in _turn(core, LEASE + 1.0)[b"r0"]
    ranks[0].complete(0)
    states = [rec.state() for rec in ranks]  # both checkpoint now
    for r in range(2):  # the job is killed
        core.message(b"r%d" % r, Bye(), LEASE + 1.5)
    readers = {}
    for r in range(world):  # each rank of the resumed job loads every rank's state
        readers[b"s%d" % r] = rec = ResumeState()
        rec.load(ResumeState.gathered(states).state())
        rec.place("g", r, world)
        _say_hello(core, b"s%d" % r, rec, 2, LEASE + 2.0, f"job2.rank{r}")
    got += _read_to_the_end(core, readers, LEASE + 2.0)
    every = collections.Counter((e, SampleKey(v, k).sample_id()) for e in range(2) for v, n in WINDOWS.items()
                                for k in range(n))
    assert collections.Counter(got) == every


def test_a_client_found_unreachable_is_forgotten_only_once_its_messages_are_read():
    """The answer to a hold cannot reach a client that closed right after its last messages: the
    core is told (``unreachable``) and still reads the release that follows as that client's (the
    batch goes back to the queue); once nothing is left unread (``caught_up``) it is forgotten."""
    core = _one_epoch_core()
    core.hello(b"gone", Hello(("voxels",), 2, consumer="g"), 0.0)
    _make_everything(core, 0.0)
    sends, _ = core.tick(0.0)
    bid = next(b.batch_id for i, b in sends if i == b"gone")
    assert core.message(b"gone", Hold((bid,)), 0.1)[0][1].batch_ids == (bid,)
    core.unreachable(b"gone")  # the granted answer could not be sent
    core.message(b"gone", Released((bid,)), 0.1)
    assert core.ledger.table.get(bid).state == "ready" and b"gone" in core.connected()
    core.message(b"gone", Bye(), 0.1)
    core.caught_up()
    assert core.connected() == [] and core.ledger.table.get(bid).state == "ready"


def test_a_host_crash_never_takes_from_the_journal_a_grant_a_client_received(tmp_path):
    """docs/delivery.md, "Restarts with a journal": the server's client side (the real
    ``ClientSide`` on a real ROUTER socket) puts a grant's record on disk before the grant leaves.
    When the client receives it nothing of the journal is unsynced, so a host crash then (the
    file cut back to that size) keeps it: the reader's resume is let in and no other reader is
    sent those samples. Cut back to before the grant's record (what an ``fsync`` once a second
    alone allows), the other reader is sent them and the honest state is refused: a doubling."""
    import zmq

    from v2v_server.ops.config import ServeConfig
    from v2v_server.ops.metrics import ServerMetrics
    from v2v_server.service.client_side import ClientSide

    def core_on() -> DeliveryCore:
        return DeliveryCore(list(WINDOWS), DeliveryPolicy(batch_size=2, epochs=1, lease_s=LEASE,
                                                          client_timeout_s=TIMEOUT, revoke_s=REVOKE,
                                                          max_credits=4, shuffle="none"), make_batch,
                            journal=Journal(str(tmp_path), "recipe", fsync_s=1e9), stall_s=STALL_S)

    path = tmp_path / JOURNAL_FILE
    core = core_on()
    ctx = zmq.Context()
    router, dealer = ctx.socket(zmq.ROUTER), ctx.socket(zmq.DEALER)
    try:
        port = router.bind_to_random_port("tcp://127.0.0.1")
        dealer.setsockopt(zmq.IDENTITY, b"a")
        dealer.connect(f"tcp://127.0.0.1:{port}")
        clients = ClientSide(ServeConfig(), core, ServerMetrics(progress=False))
        clients.frontend = router
        _hello(core, b"a", "a", 0.0, ends_on_drained=False)
        bid = _turn(core, 0.0)[b"a"][0]
        before = path.stat().st_size
        dealer.send(pack(Hold((bid,)).to_wire()))
        assert router.poll(5000), "the hold never arrived"
        clients.read(True)
        assert dealer.poll(5000), "no answer to the hold"
        granted = sm.stream_message(unpack(dealer.recv_multipart()[0]))
        assert isinstance(granted, sm.Granted) and tuple(granted.batch_ids) == (bid,), granted
        assert not core.journal.unsynced  # what the client holds is on disk
        on_disk = path.stat().st_size
    finally:
        dealer.close(0)
        router.close(0)
        ctx.term()
    assert on_disk > before
    ids = frozenset(core.ledger.table.get(bid).keys)
    core.journal.close()

    def after_crash(size: int):
        """Another reader, then the grant's reader resuming honestly, on a server restarted from
        the journal cut back to ``size`` bytes: (the samples ``b`` is sent, the answer to ``a``)."""
        with open(path, "r+b") as f:
            f.truncate(size)
        restarted = core_on()
        _hello(restarted, b"b", "b", 0.5, ends_on_drained=False)
        to_b = {k for x in _turn(restarted, 0.5)[b"b"] if isinstance(x, int) for k in restarted.ledger.table.get(x).keys}
        resume = Resume(-1, {0: ids}, origins=(restarted.server_id,))
        answer = restarted.hello(b"a2", Hello(("voxels",), 2, consumer="a", resume=resume), 1.0)[0][1]
        restarted.journal.close()
        return to_b, answer

    to_b, answer = after_crash(on_disk)
    assert not ids & to_b and isinstance(answer, sm.Welcome), (to_b, answer)
    to_b, answer = after_crash(before)  # the grant's record lost: the doubling a durable grant prevents
    assert ids <= to_b and isinstance(answer, sm.ServerError) and answer.code == "resume", answer


def _worker_hello(core: DeliveryCore, ident: bytes, record: ResumeState, now: float, hello_id: int) -> None:
    """A StreamLoader worker's hello from its record (``ResumeState.hello_resume``), as its session says it,
    read by the server through the wire encoding."""
    h = Hello(("voxels",), 2, consumer=record.consumer, resume=record.hello_resume(), ends_on_drained=True,
              instance="p", hello_id=hello_id)
    core.hello(ident, decode_client(pack(h.to_wire()), 1 << 20, 4), now)


def _sent_ids(core: DeliveryCore, ident: bytes, now: float) -> list:
    return [list(core.ledger.batches[b].payload.sample_ids) for b in _turn(core, now)[ident] if isinstance(b, int)]


def _last_batch_queued_at_a_hello(record: ResumeState, epochs: int = 1, others_read: bool = False):
    """One StreamLoader worker (consumer ``x/0``) reads epoch 0 of an ``epochs``-epoch stream (alone,
    or beside a trainer ``t``); the loop receives every batch but the last, ``b``, granted and waiting
    in the loader's queue (the worker's pipeline). The worker's connection goes silent (cut off), and
    with ``others_read`` the trainer reads every epoch meanwhile. The worker says hello again: its
    hello names ``b``'s ids as handed on (the loop may still receive it) and ``b`` as queued, so the
    server tells the worker no end of epoch 0 until its ack. Returns (the core, ``b``, ``b``'s sample ids)."""
    core = _one_epoch_core(epochs)
    _worker_hello(core, b"x.1", record, 0.0, 1)
    if others_read:
        _hello(core, b"t", "t", 0.0, ends_on_drained=False)
    last = None
    for step in range(40 + 100 * others_read):
        now = 0.1 * step
        sent = _turn(core, now)
        for bid in [b for b in sent[b"t"] if isinstance(b, int)]:
            core.message(b"t", Hold((bid,)), now)
            core.message(b"t", Ack((bid,)), now)
        for bid in sent[b"x.1"] if step < 40 else ():  # then the worker's connection is silent
            if not isinstance(bid, int) or core.ledger.batches[bid].epoch != 0:
                continue
            core.message(b"x.1", Hold((bid,)), now)
            record.claim(0, bid, list(core.ledger.batches[bid].payload.sample_ids), loader=True)
            if last is not None:  # the loop received the batch before it
                core.message(b"x.1", Ack(tuple(record.received([last[0]]))), now)
            last = (bid, list(core.ledger.batches[bid].payload.sample_ids))
    _worker_hello(core, b"x.2", record, 15.0, 2)
    told = _turn(core, 15.0)[b"x.2"]
    assert "epoch_done" not in told and "end" not in told, told
    return core, last[0], last[1]


@pytest.mark.parametrize("epochs, others_read", [(1, False), (3, True)])
def test_a_batch_in_the_loaders_queue_at_a_hello_reaches_the_loop_once(epochs, others_read):
    """A worker's hello names the batch waiting in the loader's queue as handed on and queued: the
    server tells its connection no end of that epoch until the ack. The loop leaves the iteration
    without it: the worker gives it back and closes, its record keeps the epoch open, so the next
    iteration's hello omits the ids and the server makes them again for it; a loop that receives it
    acknowledges it, and the epochs' ends come (docs/delivery.md, "DataLoader workers"). With a
    trainer that read all three epochs while the worker was cut off, the server told the worker
    epochs 0-2 complete at its hello and forgot epoch 0 before the loop left: the ids were lost
    (the simulator's F21, loader 1099, and F26, loader 1095)."""
    record = ResumeState("x/0")
    core, b, ids = _last_batch_queued_at_a_hello(record, epochs, others_read)
    record.clear_pipeline()  # the loop left: abandon, the worker's connection gives b back and closes
    core.message(b"x.2", Released((b,)), 15.1)
    assert "epoch_done" not in _turn(core, 15.1)[b"x.2"]  # it closes: its bye is on the way
    core.message(b"x.2", Bye(), 15.2)
    _worker_hello(core, b"x.3", record, 16.0, 3)
    again = [s for step in range(10) for batch in _sent_ids(core, b"x.3", 16.0 + 0.1 * step) for s in batch]
    assert sorted(again) == sorted(ids), (again, ids)

    record = ResumeState("x/0")
    core, b, ids = _last_batch_queued_at_a_hello(record, epochs, others_read)
    assert not record.is_complete(0)
    answer = core.message(b"x.2", Hold((b,)), 15.1)[0][1]  # an ack lost with a broken connection: said again
    assert answer.batch_ids == (b,), answer
    core.message(b"x.2", Ack(tuple(record.received([b]))), 15.1)  # the loop received it
    told = _turn(core, 15.2)[b"x.2"]
    assert "epoch_done" in told and "end" in told, told
    for e in range(epochs):
        record.complete(e)
    assert record.is_complete(epochs - 1) and record.hello_resume().delivered == {}
    _worker_hello(core, b"x.3", record, 16.0, 3)
    assert [s for step in range(10) for batch in _sent_ids(core, b"x.3", 16.0 + 0.1 * step) for s in batch] == []


def test_a_receipt_no_connection_read_is_named_by_the_next_iterations_hello():
    """The worker's connection ended on the stream's ``end`` while ``b`` waited in the loader's
    queue; the loop then received ``b`` and wrote its receipt, which no connection read. A
    persistent worker's next iteration (``EndpointStream.attach_loader`` on the same pipe) takes
    it into the record, so its hello names ``b`` and the server does not make it again (the
    simulator's F22, loader 1708)."""
    from v2v_client.endpoint import EndpointStream
    from v2v_client.loader import LoaderLink

    stream = EndpointStream("tcp://127.0.0.1:9", options(2))
    stream.consumer = "x/0"
    link = LoaderLink(1, {})
    try:
        stream.attach_loader(0, link.receipts[0], None)
        core, b, ids = _last_batch_queued_at_a_hello(stream.record)
        core.message(b"x.2", Bye(), 15.1)  # the connection ends, its last batch still queued
        link.receipt(0, b)  # the loop receives b
        link.end_iteration()  # and iterates again: the persistent worker starts its next iteration
        stream.attach_loader(0, link.receipts[0], None)
        assert set(ids) <= set(stream.record.hello_resume().delivered.get(0, ())) or stream.record.is_complete(0)
        _worker_hello(core, b"x.3", stream.record, 16.0, 3)
        again = [s for step in range(10) for batch in _sent_ids(core, b"x.3", 16.0 + 0.1 * step) for s in batch]
        assert again == [], (again, ids)
    finally:
        stream.close()
        link.close()

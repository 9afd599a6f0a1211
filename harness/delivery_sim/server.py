"""The simulated server: the REAL ``DeliveryCore`` (scheduler, ledger, batcher, journal, admission,
ends of epochs and of the stream) in a stand-in for its socket shell, and decode workers
simulated at the task level.

:class:`SimServer` does what ``service/server.py``, ``client_side.py`` and ``worker_side.py``
do around the core, and nothing more: it decodes each client message with the real bounded
decoder (``v2v_wire.messages.decode_client`` with the core's ``resume_bound``; a bad one is a
protocol error for that peer), hands it to ``DeliveryCore.hello`` / ``message``, sends what they
answer, runs the core's ``tick`` each turn and sends what it says, reads its workers only while
fewer than ``prefetch`` batches wait (and tells the core, each turn, whether it did: ``timed_out``),
broadcasts heartbeats, tells the core which clients it could not reach (``unreachable``) and when
nothing sent is left unread (``caught_up``), and exits when the core says so (``exit_due``).

:class:`ServerProbe` is the one place the checks read the server's books (``oracle.py``).
"""
from __future__ import annotations

import collections
import logging
from dataclasses import dataclass, field
from typing import Deque, Dict, List, Optional, Set, Tuple

from v2v_server.delivery.core import DeliveryCore, DeliveryPolicy
from v2v_server.delivery.journal import Journal
from v2v_server.delivery.ledger import STALL_S
from v2v_wire.ids import SampleKey
from v2v_wire.messages import BadPeers, Hello, WireError, decode_client
from v2v_wire.protocol import MAX_CLIENT_MSG, PROTOCOL_VERSION, pack
from v2v_wire.stream_messages import Batch, EpochDone, Heartbeat, ServerError, Welcome

from harness.delivery_sim.net import Net
from harness.delivery_sim.workers import SimWorker, WorkerFaults
from harness.delivery_sim.world import Proc, Sim

log = logging.getLogger("v2v.server")

#: The recipe fingerprint the simulated server serves (the journal and resume states carry it).
RECIPE = "sim-recipe-1"
#: Client messages read per turn (``client_side.CLIENT_BURST``) and worker messages (``server._loop``).
CLIENT_BURST, WORKER_BURST = 100, 16
#: Seconds between two turns of an idle loop (``zmq.Poller.poll(100)``).
POLL_S = 0.1


@dataclass
class Corpus:
    """The simulated corpus: windows per video; windows that fail every epoch (a frame-size
    change) and files whose decoding stops at a window (the pass ends there every epoch)."""

    windows: Dict[str, int]
    bad: Set[Tuple[str, int]] = field(default_factory=set)
    truncated: Dict[str, int] = field(default_factory=dict)

    def epoch_ids(self) -> Set[str]:
        """The sample ids one epoch holds when no worker crash fails a window."""
        out = set()
        for v, n in self.windows.items():
            stop = self.truncated.get(v, n)
            out |= {SampleKey(v, k).sample_id() for k in range(min(n, stop)) if (v, k) not in self.bad}
        return out


class SimPayload:
    """A batch's payload as the core sees it: only its sample ids (``subset`` keeps some)."""

    __slots__ = ("sample_ids",)

    def __init__(self, sample_ids):
        self.sample_ids = tuple(sample_ids)

    def subset(self, keep):
        return SimPayload(self.sample_ids[i] for i in keep)


def make_batch(samples) -> SimPayload:
    return SimPayload(samples)


def batch_frames(b) -> list:
    """The frames of one batch message: its header (``stream_messages.Batch``) and one int8
    array of one byte per sample (the client checks it against the ids)."""
    n = len(b.payload.sample_ids)
    spec = {"name": "voxels", "dtype": "int8", "shape": [n]}
    header = Batch(b.batch_id, b.epoch, b.payload.sample_ids, ({},) * n, (spec,), None, b.batch_id < 0)
    return [pack(header.to_wire()), bytes(n)]


@dataclass
class ServerConfig:
    """The simulated server's settings (``policy``: the core's)."""

    corpus: Corpus
    policy: DeliveryPolicy
    workers: int = 2
    prefetch: int = 4
    state_dir: Optional[str] = None
    heartbeat_s: float = 1.0
    end_grace_s: float = 1e9
    sample_s: Tuple[float, float] = (0.002, 0.02)  # seconds a worker takes per sample
    worker_faults: WorkerFaults = field(default_factory=WorkerFaults)


class SimServer:
    """One incarnation of the server process (a restart is a new one over the same ``state_dir``).

    Args:
        sim, net: the world and the network (``net.server`` is set to it).
        cfg: the settings.
        incarnation: counts restarts (names the process and the workers).
        on_sent: ``(ident, message)`` of every control message and batch header it sends, for the checks.
        on_read: ``(ident, message)`` of every client message it decoded, before the core handles it
            (for the checks).
        on_timeout: ``(worker ident, job, hung)`` of every task the core expired, ``hung``: whether
            the run made that worker hang (for the checks: a task of a worker that did not hang
            must never expire).
    """

    def __init__(self, sim: Sim, net: Net, cfg: ServerConfig, incarnation: int = 0, on_sent=None, on_read=None,
                 on_timeout=None):
        self.sim, self.net, self.cfg = sim, net, cfg
        self.proc = Proc(f"server{incarnation}")
        self.on_sent = on_sent or (lambda ident, msg, batch: None)
        self.on_read = on_read or (lambda ident, msg: None)
        self.on_timeout = on_timeout or (lambda ident, job, hung: None)
        #: (epoch, video) -> workers lost on that job to a fault the run injected (a death, or a
        #: hang the task timeout ended): the crashes ``ServerProbe.excused`` may excuse
        self.injected_losses: Dict[Tuple[int, str], int] = {}
        self.journal = Journal(cfg.state_dir, RECIPE) if cfg.state_dir else None
        videos = sorted(cfg.corpus.windows)
        self.core = DeliveryCore(videos, cfg.policy, make_batch, self.journal, stall_s=STALL_S,
                                 end_grace_s=cfg.end_grace_s, first_batch_id=round(sim.now * 1e9))  # as the shell's
        self.core.info = self.info
        self.inbox: Deque[Tuple[bytes, list]] = collections.deque()
        self.backend: Deque[tuple] = collections.deque()
        self.bad = BadPeers()
        self.workers: Dict[bytes, "SimWorker"] = {}
        self._wgen = 0
        for _ in range(cfg.workers):
            self._spawn_worker()
        self._turn_token = 0
        self._turn_at = None
        self.next_beat = sim.now
        self.exited = False
        net.server_up(self)
        self.wake(0.0)

    # ------------------------------------------------------------------ the loop
    def wake(self, dt: float = 0.0) -> None:
        """Run a turn ``dt`` from now, unless one is due sooner (the poll wakes on a message)."""
        t = self.sim.now + dt
        if self._turn_at is not None and self._turn_at <= t:
            return
        self._turn_token += 1
        self._turn_at = t
        self.sim.at(t, self._turn, self._turn_token, proc=self.proc)

    def receive(self, ident: bytes, frames: list) -> None:
        self.inbox.append((ident, frames))
        self.wake(0.0)

    def from_worker(self, msg: tuple) -> None:
        self.backend.append(msg)
        self.wake(0.0)

    def _turn(self, token: int) -> None:
        if token != self._turn_token:
            return
        self._turn_at = None
        now = self.sim.now
        reading = self.core.ready_count() < self.cfg.prefetch  # the shell polls its workers this turn
        self._read_clients()
        for _ in range(WORKER_BURST):
            if not self.backend or self.core.ready_count() >= self.cfg.prefetch:
                break
            self._on_worker(self.backend.popleft())
        self._watch_workers(now, reading)
        self._dispatch(now)
        self._send(now)
        if self.journal is not None:
            self.journal.sync(now)
        if now >= self.next_beat:
            for ident in self.core.connected():
                self.send(ident, Heartbeat())
            self.next_beat = now + self.cfg.heartbeat_s
        if self.core.exit_due(now):
            self.exit()
            return
        self.wake(0.0 if self.inbox or (self.backend and self.core.ready_count() < self.cfg.prefetch)
                  else POLL_S)

    def _read_clients(self) -> None:
        for _ in range(CLIENT_BURST):
            if not self.inbox:
                break
            self._on_client(*self.inbox.popleft())
        if not self.inbox:  # what an unreachable client sent before it closed has been read
            self.core.caught_up()

    def _on_client(self, ident: bytes, frames: list) -> None:
        now = self.sim.now
        if self.bad.banned(ident, now):
            return
        try:
            if len(frames) != 1:
                raise WireError(f"expected 1 frame after the identity, got {len(frames)}")
            msg = decode_client(frames[0], MAX_CLIENT_MSG, self.cfg.policy.max_credits,
                                self.cfg.policy.crops_per_window, self.core.resume_bound)
        except WireError as e:
            self.sim.log(self.proc.name, f"bad message from {ident.hex()[:8]}: {e}")
            _, banned = self.bad.strike(ident, now)
            if not self.bad.banned(ident, now) or banned:
                self.send(ident, ServerError(f"protocol error: {e}"))
            self.core.forget(ident)
            return
        self.sim.log(self.proc.name, lambda: f"<- {ident.hex()[:8]} {_show(msg)}")
        self.on_read(ident, msg)
        if isinstance(msg, Hello):
            replies = self.core.hello(ident, msg, now)
        else:
            replies = self.core.message(ident, msg, now)
        for to, reply in replies:
            self.send(to, reply)

    def _send(self, now: float) -> None:
        sends, msgs = self.core.tick(now)
        for ident, b in sends:
            if self.core.client_outputs(ident) is None:
                continue
            self.sim.log(self.proc.name, lambda: f"-> {ident.hex()[:8]} batch {b.batch_id} e{b.epoch} "
                                                 f"{list(b.payload.sample_ids)}")
            if self.net.send_down(ident, batch_frames(b)):
                self.on_sent(ident, None, b)
            else:
                self.core.unreachable(ident)
        for ident, msg in msgs:
            self.send(ident, msg)

    def send(self, ident: bytes, msg) -> None:
        """One control message; an unreachable client is forgotten once its messages are read."""
        if not isinstance(msg, Heartbeat):
            self.sim.log(self.proc.name, lambda: f"-> {ident.hex()[:8]} {_show(msg)}")
        if self.net.send_down(ident, [pack(msg.to_wire())]):
            self.on_sent(ident, msg, None)
        else:
            self.core.unreachable(ident)

    def info(self) -> dict:
        """A welcome's stream info (what the client reads of it)."""
        p = self.cfg.policy
        return {"recipe": RECIPE, "max_hello_bytes": MAX_CLIENT_MSG, "protocol": PROTOCOL_VERSION,
                "epochs": p.epochs, "batch_size": p.batch_size, "lease_s": p.lease_s,
                "client_timeout_s": p.client_timeout_s, "max_credits": p.max_credits, "shard": "0/1"}

    def exit(self) -> None:
        """The process ends (end of stream, or killed): its workers go with it."""
        self.sim.log(self.proc.name, "exits")
        self.proc.dead = True
        self.exited = True
        for w in self.workers.values():
            w.proc.dead = True
        if self.net.server is self:
            self.net.server_down()
        if self.journal is not None:
            self.journal.close()

    def crash(self) -> None:
        """SIGKILL: no goodbye; the journal's appends are in the page cache (they survive)."""
        self.sim.log(self.proc.name, "killed")
        self.proc.dead = True
        for w in self.workers.values():
            w.proc.dead = True
        self.net.server_down()
        if self.journal is not None:
            self.journal.close()  # what was appended is on disk already; the descriptor goes with the process

    # ------------------------------------------------------------------ workers
    def _spawn_worker(self) -> None:
        self._wgen += 1
        w = SimWorker(self, f"{self.proc.name}.w{self._wgen}".encode())
        self.workers[w.ident] = w

    def _on_worker(self, msg: tuple) -> None:
        kind, ident = msg[0], msg[1]
        if ident not in self.workers:
            return  # a replaced worker's last words
        now = self.sim.now
        if kind == "sample":
            _, _, task, key = msg
            self.core.sample(ident, task, key, now, lambda lane, k=key: k.sample_id())
        else:
            _, _, task, windows, failed, error = msg
            if self.core.done(ident, task, windows, failed, error) is not None:
                self.workers[ident].idle = True

    def _lost(self, job, injected: bool) -> None:
        if injected:
            key = (job.epoch, job.video)
            self.injected_losses[key] = self.injected_losses.get(key, 0) + 1

    def _watch_workers(self, now: float, reading: bool) -> None:
        for ident, w in list(self.workers.items()):
            if w.proc.dead:  # only a drawn death kills a worker of a live server
                self.sim.log(self.proc.name, f"worker {ident.decode()} died")
                job = self.core.worker_lost(ident)
                if job is not None:
                    self._lost(job, True)
                del self.workers[ident]
                self._spawn_worker()
        for ident, job in self.core.timed_out(now, reading):
            w = self.workers.pop(ident, None)
            if w is not None:
                self.sim.log(self.proc.name, f"worker {ident.decode()} timed out: replaced")
                self._lost(job, w.hung)
                self.on_timeout(ident, job, w.hung)
                w.replaced()
                self._spawn_worker()

    def _dispatch(self, now: float) -> None:
        for w in list(self.workers.values()):
            if not w.idle:
                continue
            task = self.core.task_for(w.ident, now)
            if task is None:
                return
            w.start(task)


class ServerProbe:
    """What the checks read of a server's books (``core``'s batch table, connections, scheduler
    and journal): the one place outside the core that knows their layout."""

    def __init__(self, server: SimServer):
        self.core = server.core
        self.journal = server.journal
        self.injected_losses = server.injected_losses
        self.seen: Dict[int, object] = {}  # epoch -> its plan as last seen (a plan forgotten in a step keeps its books)

    def remember(self) -> None:
        """Keep the plans as they are now: an epoch announced and forgotten in the next step is
        judged on the books it had."""
        self.seen.update(self.core.sched.plans)

    def _plan(self, epoch: int):
        return self.core.sched.plans.get(epoch) or self.seen.get(epoch)

    def client_holdings(self) -> List[Tuple[bytes, int, int]]:
        """``(ident, batches held: leased, revoked or granted, credits)`` per connected client."""
        table = self.core.ledger.table
        return [(i, table.held_count(i), c.credits) for i, c in self.core.ledger.clients.items()]

    def batches(self) -> List[Tuple[int, int, int, str, object]]:
        """``(batch id, epoch, samples, state, consumer)`` of every batch in the table."""
        return [(b.batch_id, b.epoch, len(b.keys), b.state, b.consumer)
                for b in self.core.ledger.table.batches.values()]

    def takes_back(self, ident: bytes, batch_ids) -> List[int]:
        """The batches a ``Released`` from ``ident`` that the core is about to read gives back
        (``DeliveryCore.message``, ``Ledger.released``): those its table holds for that connection,
        if the server knows it (a server that never let its hello in takes nothing back)."""
        if ident not in self.core.ledger.clients:
            return []
        return [b for b in batch_ids if self.core.ledger.table.holds(ident, b)]

    def told_upto(self) -> int:
        """The newest epoch told complete to some connection (every older one was told too)."""
        return self.core.ends.told_upto

    def plan_epochs(self) -> List[int]:
        return sorted(self.core.sched.plans)

    def records(self):
        """``(where, epoch, consumer, sample count)`` of every consumer record the server keeps:
        in open epochs, for epochs not open yet, and in the journal."""
        s = self.core.sched
        for e, p in s.plans.items():
            for consumer, keys in p.records.items():
                yield "plan", e, consumer, len(keys)
        for e, recs in s.pending_records.items():
            for consumer, keys in recs.items():
                yield "pending", e, consumer, len(keys)
        if self.journal is not None:
            for consumer, d in self.journal.records.items():
                for e, keys in d.items():
                    yield "journal", e, consumer, len(keys)

    def recorded_to(self, epoch: int, sid: str) -> List[str]:
        """The consumers (``"c:<id>/0"``, ``"g:<group>/<rank>"``) whose record of ``epoch`` has ``sid``."""
        from v2v_wire.ids import parse_sample_id

        key = parse_sample_id(sid)
        plan = self._plan(epoch)
        recs = plan.records if plan is not None else self.core.sched.pending_records.get(epoch, {})
        return [f"{c[0]}/{c[1]}" for c, ks in recs.items() if key in ks]

    def holders(self, epoch: int, sid: str) -> List[str]:
        """Where the server keeps sample ``sid`` of ``epoch``: the consumers whose record has it
        (open plan or pending), ``live`` (in a batch or the shuffle buffer), or ``unknown``."""
        from v2v_wire.ids import parse_sample_id

        key = parse_sample_id(sid)
        s = self.core.sched
        plan = self._plan(epoch)
        if plan is None:
            recs = s.pending_records.get(epoch, {})
            out = [f"{c[0]}/{c[1]} (pending)" for c, ks in recs.items() if key in ks]
            return out or [f"no plan (next epoch {s.next_epoch})"]
        gone = "" if epoch in s.plans else " (forgotten)"
        out = [f"{c[0]}/{c[1]}{gone}" for c, ks in plan.records.items() if key in ks]
        if key in plan.live:
            out.append("live")
        return out or ["nobody"]

    def next_epoch(self) -> int:
        return self.core.sched.next_epoch

    def excused(self, epoch: int, corpus: Corpus) -> Optional[Set[str]]:
        """Sample ids of ``corpus`` that ``epoch`` does not hold, as its plan says, for a cause the
        run injected: a bad window (``corpus.bad``), a file's truncation (the window its pass stops
        in and those past it), and what worker crashes failed or gave up in a job every one of whose
        crashes the run injected (a drawn death, or a drawn hang the task timeout ended). Any other
        failure (a task expired while its worker was not hung: the server not reading it) is not
        excused, so the checks find what it costs. None when the epoch is not open here."""
        plan = self.core.sched.plans.get(epoch)
        if plan is None:
            return None
        out = set()
        for v, j in plan.jobs.items():
            crashes_injected = j.crashes <= self.injected_losses.get((epoch, v), 0)
            stop = corpus.truncated.get(v)
            n = corpus.windows.get(v, 0)
            out |= {k.sample_id() for k in j.failed
                    if crashes_injected or (v, k.window) in corpus.bad or k.window == stop}
            if j.samples is not None:
                first = j.samples if crashes_injected else max(j.samples, n if stop is None else stop + 1)
                out |= {SampleKey(v, k).sample_id() for k in range(first, n)}
        return out


def _show(msg) -> str:
    """A message in a trace line, its resume state summed up."""
    if isinstance(msg, Hello):
        r = msg.resume
        return (f"hello consumer={msg.consumer!r} credits={msg.credits} rank={msg.rank}/{msg.world_size} "
                f"group={msg.group} completed={r.completed_epoch} "
                f"delivered={ {e: len(ks) for e, ks in r.delivered.items()} } hello_id={msg.hello_id}"
                + (f" queued={r.queued}" if r.queued else ""))
    if isinstance(msg, EpochDone):
        return f"epoch_done {msg.epoch} batches={msg.batches}"
    if isinstance(msg, Welcome):  # its info names the server by a random id: not in a trace that must replay
        return f"welcome hello_id={msg.hello_id}"
    return repr(msg)

"""The delivery core: the epoch scheduler, the delivery ledger and the epochs' ends glued
together, still pure.

``DeliveryCore`` takes what workers and clients said (already decoded and schema-checked)
and answers with what to send; it owns no socket, process or clock (``now`` is an argument,
seconds). ``service/`` moves the bytes and reads nothing inside it but through its methods;
``tests/test_delivery_core.py`` and ``tests/test_lease_protocol.py`` drive it through thousands
of interleavings with hypothesis. The protocol it keeps is docs/delivery.md ("The protocol").

Batch payloads are opaque here: ``make_batch(samples)`` builds one from what ``sample()``
was given (``assembly.make_batch`` in the server), and a payload is only asked for
``subset(keep)``; every sample travels with its ``ids.SampleKey``.
"""
from __future__ import annotations

import logging
import uuid
from dataclasses import dataclass
from typing import Callable, Hashable, List, Optional, Sequence, Tuple

from v2v_server.delivery.admission import WAIT, Admission, name_of
from v2v_server.delivery.batcher import SHUFFLES, Batcher
from v2v_server.delivery.closing import EpochEnds
from v2v_server.delivery.feed import WorkerFeed
from v2v_server.delivery.ledger import DeliveryLedger
from v2v_server.delivery.padding import GroupPadding
from v2v_server.delivery.table import STRANDED, BatchRecord
from v2v_server.checks import check_choice, check_float, check_int
from v2v_server.settings import setting
from v2v_wire.ids import SampleKey
from v2v_wire.protocol import MAX_CREDITS, OUTPUTS
from v2v_server.delivery.schedule import MAX_TASK_CRASHES, EpochScheduler, Job
from v2v_wire.messages import Ack, Bye, Credit, Heartbeat, Hello, Hold, Released
from v2v_wire.stream_messages import Granted, Revoke, ServerError, StreamMessage, Welcome
from v2v_wire.worker_messages import Task

log = logging.getLogger("v2v.server")

Msg = Tuple[bytes, StreamMessage]


MAX_SHUFFLE_BUFFER = 4096
#: ``--delivery`` settings (docs/plan.md).
DELIVERY_MODES = ("push", "plan")
#: Seconds after a hello its consumer's older connection (of another reader process) must still
#: speak for the hello to be refused as a second live reader (docs/delivery.md, "Who may say hello").
CLAIM_MARGIN_S = 2.0


@dataclass(frozen=True)
class DeliveryPolicy:
    """Delivery: batches, shuffling, leases, credits and epochs.

    The one owner of these settings' defaults, help and checks (``docs/config.md``'s delivery
    keys are generated from the fields made with ``setting``); ``ops.config.ServeConfig``
    composes it, and fills the fields below that come from the sample recipe.

    Attributes:
        batch_size .. shuffle_buffer: the delivery keys (their help below; seconds; batches;
            samples). ``lease_s``, ``client_timeout_s``, ``revoke_s``, ``max_credits``: see
            ``ledger.DeliveryLedger``; ``shuffle``: ``"epoch"`` hands each epoch's videos out in
            ``batcher.video_order(videos, seed, epoch)`` and spreads samples over the open
            batches of a shuffle buffer (``batcher.Batcher``), ``"none"`` keeps the listing's
            order and the arrival order; ``shuffle_buffer`` is rounded up to whole open batches
            (:attr:`lanes`); ``delivery_mode``: ``"push"`` (this core) or ``"plan"``
            (``plan_feed.PlanFeed``, ``service.plan_server``).
        offered: outputs this server offers (the recipe's ``outputs``).
        max_task_crashes: see ``schedule.EpochScheduler`` (``schedule.MAX_TASK_CRASHES``).
        crops_per_window: samples per window (ids ``path#window.crop`` when > 1, ``ids.py``).
        seed: draws the orders (the recipe's ``seed``).
        max_samples_per_video: windows a file gives at most per epoch (None: no bound known);
            bounds the samples an epoch can still bring before its files' first passes end.

    Raises:
        ValueError: naming the field, for a value out of its range (``shuffle`` not in
            ``batcher.SHUFFLES``, ``shuffle_buffer`` not in 1..4096, ...).
    """

    batch_size: int = setting(12, help="samples per batch (the last batch of an epoch may be smaller)")
    epochs: Optional[int] = setting(None, help="end the stream after this many epochs (default: unbounded)")
    lease_s: float = setting(60.0, help="seconds a sent batch waits for its client's hold before it is asked "
                                        "back (revoke)", flag="--lease")
    client_timeout_s: float = setting(10.0, help="seconds of client silence before it is dropped (what it was sent "
                                                 "and not granted goes back to the queue; its grants wait for its "
                                                 "consumer's next hello)", flag="--client-timeout")
    revoke_s: Optional[float] = setting(None, help="seconds a client may leave a revoke unanswered before it is "
                                                   "dropped (default: the client timeout)", flag="--revoke-timeout")
    max_credits: int = setting(64, help="most batches one client may hold")
    task_timeout_s: float = setting(300.0, help="seconds a worker may send nothing on a task, while the server "
                                                "reads its workers, before the task is reassigned and the worker "
                                                "replaced (time the server does not read them, because enough "
                                                "batches wait for stopped readers, does not count)",
                                    flag="--task-timeout")
    shuffle: str = setting("epoch", help="epoch: each epoch hands the videos out in an order drawn from (seed, "
                                         "epoch) and each made sample joins a random open batch of the shuffle "
                                         "buffer, so batches mix videos whatever the worker count; none: the "
                                         "listing's order, batches in the order samples are made (docs/shuffle.md)",
                           choices=SHUFFLES)
    shuffle_buffer: int = setting(64, help="samples the shuffle buffer holds (shuffle: epoch), rounded "
                                           "up to whole batches: that many samples of server memory "
                                           "(docs/shuffle.md has their size)")
    delivery_mode: str = setting("plan", help="plan: each epoch is a fixed sequence every client fetches positions of, "
                                     "read with V2VStreamDataset (docs/plan.md); push: the server hands batches to "
                                     "its clients and keeps the books of who holds what, read with V2VPushDataset "
                                     "(docs/delivery.md; needed for --shard, --epochs, --state-dir)",
                        flag="--delivery", choices=DELIVERY_MODES)
    offered: Tuple[str, ...] = OUTPUTS
    max_task_crashes: int = MAX_TASK_CRASHES
    crops_per_window: int = 1
    seed: int = 0
    max_samples_per_video: Optional[int] = None

    def __post_init__(self):
        check_int("batch_size", self.batch_size, 1)
        if self.epochs is not None:
            check_int("epochs", self.epochs, 1)
        for name in ("lease_s", "client_timeout_s", "task_timeout_s"):
            object.__setattr__(self, name, check_float(name, getattr(self, name)))
        if self.revoke_s is not None:
            object.__setattr__(self, "revoke_s", check_float("revoke_s", self.revoke_s))
        check_int("max_credits", self.max_credits, 1, MAX_CREDITS, "batches in flight per client")
        check_choice("shuffle", self.shuffle, SHUFFLES)
        check_choice("delivery_mode", self.delivery_mode, DELIVERY_MODES)
        check_int("shuffle_buffer", self.shuffle_buffer, 1, MAX_SHUFFLE_BUFFER, "samples")

    @property
    def lanes(self) -> int:
        """Open batches per epoch: ``ceil(shuffle_buffer / batch_size)`` when shuffling, else 1
        (arrival order)."""
        return -(-self.shuffle_buffer // self.batch_size) if self.shuffle == "epoch" else 1


def consumer_of(ident: bytes, h: Hello) -> Tuple[Hashable, Optional[str]]:
    """``(consumer, group)`` of a hello: ``("g:<group>", rank)`` and the group for a DDP rank,
    else ``("c:<consumer id>", 0)`` (the connection's identity when the hello names none) and None."""
    if h.world_size > 1:
        group = h.group or "default"
        return ("g:" + group, h.rank), group
    return ("c:" + (h.consumer or ident.hex()), 0), None


class DeliveryCore:
    """Scheduler + ledger + batching (:class:`Batcher`) + DDP padding (:class:`GroupPadding`) +
    the epochs' ends (``closing.EpochEnds``), for one server.

    Args:
        videos: corpus-relative paths.
        policy: the delivery settings (:class:`DeliveryPolicy`).
        make_batch: ``samples -> payload`` (``sample()``'s built samples, in batch order).
        journal: ``journal.Journal`` (``--state-dir``) or None.
        stall_s: see ``ledger.DeliveryLedger`` (the server passes ``ledger.STALL_S``).
        end_grace_s: seconds a bounded stream's server stays up with no reader once it is over.
        first_batch_id: its first batch's id, above any a server before it sent (docs/delivery.md, "Transport").
    """

    def __init__(self, videos: Sequence[str], policy: DeliveryPolicy, make_batch: Callable, journal=None,
                 stall_s: Optional[float] = None, end_grace_s: float = 600.0, first_batch_id: int = 0):
        p = self.policy = policy
        self.sched = EpochScheduler(videos, p.epochs, p.max_task_crashes, crops_per_window=p.crops_per_window,
                                    shuffle_seed=p.seed if p.shuffle == "epoch" else None,
                                    max_samples_per_video=p.max_samples_per_video,
                                    first_epoch=0 if journal is None else journal.completed + 1,  # its epochs closed
                                    kept=journal.kept() if journal else None)
        self.ledger = DeliveryLedger(p.lease_s, p.client_timeout_s, p.max_credits, revoke_s=p.revoke_s, stall_s=stall_s)
        self.batcher = Batcher(p.batch_size, make_batch, self.ledger, p.lanes, p.seed, first_batch_id)
        self.padding = GroupPadding()
        self.ends = EpochEnds(self.sched, self.ledger, self.batcher, self.padding, journal, p.lease_s, end_grace_s)
        self.server_id = journal.server_id if journal is not None else uuid.uuid4().hex[:16]  # a welcome's "server"
        self.admission = Admission(self.sched, self.ledger, journal, p, CLAIM_MARGIN_S, self.server_id, self.ends.told_to)
        self.feed = WorkerFeed(self.sched, self.ledger, self.batcher, stall_s)
        self.info: Callable[[], dict] = dict  # the stream info each ``welcome`` carries (its server sets it)
        self._unreachable: set = set()  # connections a message could not reach (forgotten at caught_up)
        self.journal = journal  # told every grant, resume state and closed epoch; read at start
        for consumer, delivered in (journal.records if journal is not None else {}).items():
            self.sched.apply_resume(consumer, -1, delivered)  # in the closed epochs it keeps too
        if journal is not None:  # DDP ranks' grants and counts told (docs/delivery.md, "DDP", "Ends of epochs")
            self.padding.restarted(journal)

    # ------------------------------------------------------------------ workers (``feed.WorkerFeed``)
    def task_for(self, worker: Hashable, now: float, codecs: Sequence[str] = ()) -> Optional[Task]:
        return self.feed.task_for(worker, now, codecs)

    def sample(self, worker: Hashable, task_id, key: SampleKey, now: float, build: Callable) -> bool:
        return self.feed.sample(worker, task_id, key, now, build)

    def done(self, worker: Hashable, task_id, windows, failed: dict, error: Optional[str], cause: str = "") -> Optional[Job]:
        return self.feed.done(worker, task_id, windows, failed, error)  # push fails what a pass lacked: ``cause`` aside

    def worker_lost(self, worker: Hashable) -> Optional[Job]:
        return self.sched.worker_lost(worker)

    def timed_out(self, now: float, reading: bool = True) -> List[Tuple[Hashable, Job]]:
        """Tasks silent ``task_timeout_s`` in loop turns ``reading`` workers (``WorkerFeed.timed_out``): reassigned."""
        return self.feed.timed_out(now, reading, self.policy.task_timeout_s)

    @property
    def outputs(self) -> Optional[tuple]:
        """What workers compute now: the union clients ask for (None before any hello)."""
        return self.feed.outputs

    @property
    def samples_made(self) -> int:
        return self.feed.samples_made

    # ------------------------------------------------------------------ clients
    def hello(self, ident: bytes, h: Hello, now: float) -> List[Msg]:
        """A client says hello (again): refused (an error), held while another reader's connection of its
        consumer is live (``[]``; :meth:`tick` answers it) or welcomed (docs/delivery.md, "Who may say hello")."""
        consumer, group = consumer_of(ident, h)
        verdict = self.admission.check(ident, h, consumer, group, now)
        if verdict == WAIT:
            if ident not in self.admission.pending:
                log.info("client %s waits to read %s (see Who may say hello)", ident.hex(), name_of(consumer))
            self.admission.waits(ident, h, now)
            return []
        heard = min(now, self.admission.forget(ident))
        if verdict is not None:
            log.warning("client %s refused: %s", ident.hex(), verdict.message)
            return [(ident, verdict)]
        return self._welcome(ident, h, consumer, group, now, heard)

    def _welcome(self, ident: bytes, h: Hello, consumer: Hashable, group: Optional[str], now: float,
                 heard: float) -> List[Msg]:
        """Let a hello in: older connections of its reader are fenced, the grants stranded with the
        consumers it speaks for are settled by its resume state (named: the loop got them; else queued
        again), and it replaces their records after the epoch each completed."""
        msgs: List[Msg] = []
        speaks = self.admission.speaks_for(consumer, h)
        for c in self.admission.others(ident, speaks):  # the same reader's: it closed them itself
            self._leave(c.ident, "a newer connection of its reader said hello")
            msgs.append((c.ident, ServerError("a newer connection of this reader took its consumer over", "fenced")))
        self._leave(ident, "it said hello again")
        r, delivered = h.resume, {e: set(ks) for e, ks in h.resume.delivered.items()}
        done = {(name, rank): upto for name, rank, upto in r.supersedes}  # each old rank's completed epoch
        for who in speaks:  # a grant is taken only if named: a reader is told an epoch complete holding
            upto = done.get(who, r.completed_epoch)  # no grant of it, and gives back one of it sent later
            for b in self.ledger.settle(who, lambda b: set(b.keys) <= delivered.get(b.epoch, set()))[1]:
                self._undelivered(who, b)
            if who != consumer:  # a gathered state speaks for it: its later samples are in the state
                self.sched.apply_resume(who, upto, {})
                if self.journal is not None:
                    self.journal.replaced(who, upto, {})
            for e in range(r.completed_epoch + 1, upto + 1) if who == consumer else ():  # its old rank's: kept
                recs = self.sched.plans[e].records if e in self.sched.plans else self.sched.pending_records.get(e, {})
                delivered.setdefault(e, set()).update(recs.get(consumer, ()))
        self.sched.apply_resume(consumer, r.completed_epoch, delivered)
        if self.journal is not None:
            self.journal.replaced(consumer, r.completed_epoch, delivered, r.batches)
        if group is not None:
            self.padding.resized(group, h.world_size)
            self.padding.resumed(group, h.rank, r.completed_epoch, r.batches)
        self.ledger.join(ident, consumer, h.outputs, h.credits, now, group, h.rank, h.world_size,
                         r.completed_epoch, h.ends_on_drained, h.instance, heard, r.queued)
        self.admission.let_in(ident, h, speaks)
        self.feed.drop_delivered()
        if self.outputs is None or any(o not in self.outputs for o in h.outputs):
            log.info("client %s asks for %s: workers now compute %s", ident.hex(), list(h.outputs),
                     list(self.ledger.outputs_wanted()))
        return msgs + [(ident, Welcome(dict(self.info(), server=self.server_id), h.hello_id))]

    def message(self, ident: bytes, msg, now: float) -> List[Msg]:
        """Any client message but hello (``v2v_wire.messages``); its cost is linear in its size."""
        c = self.ledger.touch(ident, now)
        if c is None:
            if ident in self.admission.pending or ident in self.admission.dormant:  # its hello waits (again)
                self.admission.spoke(ident, now, isinstance(msg, Bye))
                return []
            if isinstance(msg, Bye):
                return []
        if c is None or isinstance(msg, Heartbeat) and self.admission.unread_hello(c, msg.hello_id):
            why = ("unknown client, or a hello that never arrived (this server may have restarted, or dropped "
                   "it for silence): say hello first")
            return [(ident, ServerError(why, "unknown_client", msg.hello_id if isinstance(msg, Heartbeat) else 0))]
        if self.admission.pending and isinstance(msg, (Hold, Ack, Released)):
            self.admission.spoke_of(c, msg.batch_ids)
        if isinstance(msg, Hold):
            ok, new = self.ledger.hold(ident, msg.batch_ids, now)
            self._delivered(c, new)  # recorded (and journaled) before the grant leaves
            granted = set(ok)
            return [(ident, Granted(tuple(ok), tuple(b for b in dict.fromkeys(msg.batch_ids) if b not in granted)))]
        if isinstance(msg, Ack):
            self._delivered(c, self.ledger.hold(ident, msg.batch_ids, now)[1])  # acked without a hold: granted now
            self.ledger.ack(ident, msg.batch_ids)
        elif isinstance(msg, Released):
            back, ungranted = self.ledger.released(ident, msg.batch_ids)
            for b in ungranted:
                self._undelivered(c.consumer, b)
            if back:
                log.info("batch(es) %s go back to the queue: the client released them", back)
        elif isinstance(msg, Credit):
            self.ledger.add_credits(ident, msg.credit)
        elif isinstance(msg, Bye):
            self._leave(ident, "it left")
        return self.ends.told_again(ident, c) if c.told_end and not isinstance(msg, Bye) else []  # else it touched c

    def _delivered(self, c, batches: List[BatchRecord]) -> None:
        """Record ``batches`` (granted to client ``c``) delivered to its consumer: in the
        scheduler, the journal and its DDP group's counts."""
        for b in batches:
            plan = self.sched.plans.get(b.epoch)
            if plan is not None:
                plan.served = True  # who has what of it is this server's to know from now on
            self.sched.delivered(c.consumer, b.epoch, b.keys)
            if self.journal is not None:
                self.journal.delivered(c.consumer, b.epoch, b.keys)
            if c.ddp:
                c.granted += 1
                self.padding.acked(c.group, c.rank, b)

    def _undelivered(self, consumer: Hashable, b: BatchRecord) -> None:
        """A batch granted to ``consumer`` went back to the queue unused: its samples leave the
        consumer's record (scheduler, journal, DDP counts)."""
        self.sched.undelivered(consumer, b.epoch, b.keys)
        if self.journal is not None:
            self.journal.undelivered(consumer, b.epoch, b.keys)
        if consumer[0].startswith("g:"):  # a DDP rank
            self.padding.released(consumer[0][2:], consumer[1], b)

    def _leave(self, ident: bytes, why: str) -> None:
        """Connection ``ident`` is gone: what was leased to it goes back to the queue, what was
        granted to it is stranded (its consumer's next hello settles it)."""
        back, stranded = self.ledger.leave(ident)
        if back or stranded:
            log.info("client %s: %s; batch(es) %s go back to the queue%s", ident.hex(), why, back,
                     f", {[b.batch_id for b in stranded]} stay its consumer's" if stranded else "")

    def forget(self, ident: bytes) -> None:
        """A client broke the protocol: it is gone now."""
        self._leave(ident, "it broke the protocol")

    def unreachable(self, ident: bytes) -> None:
        """A message could not reach connection ``ident`` (its socket closed): it is forgotten at
        :meth:`caught_up`, once every message it sent before closing was read (docs/delivery.md, "Messages")."""
        self._unreachable.add(ident)

    def caught_up(self) -> None:
        """Nothing the clients sent is left unread: forget the connections found unreachable."""
        for ident in self._unreachable:
            self.admission.forget(ident)
            if ident in self.ledger.clients:
                self._leave(ident, "it cannot be reached")
        self._unreachable.clear()

    # ------------------------------------------------------------------ time
    def tick(self, now: float) -> Tuple[List[Tuple[bytes, BatchRecord]], List[Msg]]:
        """Batch leftovers, expire leases and clients, lease ready batches, tell the ends of
        epochs and of the stream. Returns ``(sends, messages)``: batches to send (the caller
        calls :meth:`unreachable` for a client it cannot reach), then control messages, in order."""
        msgs: List[Msg] = []
        self.batcher.flush(lambda e: e not in self.sched.plans or not self.sched.plans[e].open_jobs)
        revokes, drops = self.ledger.expire(now)
        self.admission.silent(now, self.policy.client_timeout_s)
        for ident, ids in revokes.items():
            log.info("lease of batch(es) %s expired at client %s; asking for them back", ids, ident.hex())
            msgs.append((ident, Revoke(tuple(ids))))
        for ident, why in drops:
            log.warning("client %s %s; dropping it (its batches go to others)", ident.hex(), why)
            msgs.append((ident, ServerError(f"dropped by the server: {why}; discard what you hold", "dropped")))
        sends, stale = self.ledger.sends(now, self.padding.room)
        for b in stale:
            log.info("batch %d carries %s, which no connected client takes as is; its samples are made again",
                     b.batch_id, sorted(b.outputs))
            self.sched.discarded(b.epoch, b.keys)
        for ident, (h, _) in list(self.admission.pending.items()):  # hellos waiting for an older connection
            msgs += self.hello(ident, h, now)
        waiting = {h.group or "default" for h, _ in self.admission.pending.values() if h.world_size > 1}
        pads, told = self.ends.tell(now, waiting, bool(self.admission.pending), self.admission.dormant.values())
        return sends + pads, msgs + told + self.ends.drained()

    # ------------------------------------------------------------------ views
    def finished(self) -> bool:
        """Every epoch of a bounded stream is complete, nothing is left in the table but grants
        stranded with consumers that left, and no hello waits (its state may reopen an epoch)."""
        return (self.sched.finished() and not self.admission.pending
                and all(b.state == STRANDED for b in self.ledger.batches.values()))

    def exit_due(self, now: float) -> bool:
        """The server may exit (``closing.EpochEnds.exit_due``)."""
        return self.ends.exit_due(now, bool(self.admission.pending))

    def connected(self) -> List[bytes]:
        """The connections said hello and not gone (those whose hello waits included)."""
        return list(self.ledger.clients) + [i for i in self.admission.pending if i not in self.ledger.clients]

    def client_outputs(self, ident: bytes) -> Optional[tuple]:
        """What connection ``ident`` asked for (None: not connected)."""
        return getattr(self.ledger.clients.get(ident), "outputs", None)

    def resume_bound(self, video: str) -> Optional[int]:
        """What a resume state may name of ``video`` (``messages.Bound``, ``Admission.bound``)."""
        return self.admission.bound(video)

    @property
    def resent(self) -> int:
        """Batches given back to the queue so far (the server counts them into its metrics)."""
        return self.ledger.table.resent

    def ready_count(self) -> int:
        """Batches ready to send (the server reads its workers while fewer wait)."""
        return self.ledger.table.ready_count()

    def status(self) -> dict:
        """Plain numbers for status lines and gauges: ``clients`` (ident -> (credits, batches
        held)), ``ready``, ``in_flight``, ``acked``, ``resent``, ``states`` (batches per state),
        ``epoch`` (the newest opened, -1 before any) and its ``progress`` ((videos, done))."""
        t = self.ledger.table
        newest = max(self.sched.plans) if self.sched.plans else None
        return {"clients": {i: (c.credits, t.held_count(i)) for i, c in self.ledger.clients.items()},
                "ready": t.ready_count(), "in_flight": t.in_flight(), "acked": t.acked, "resent": t.resent,
                "states": t.states(), "epoch": -1 if newest is None else newest,
                "progress": self.sched.plans[newest].progress() if newest is not None else (0, 0)}

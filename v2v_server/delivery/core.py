"""The delivery core: the epoch scheduler and the delivery ledger glued together, still pure.

``DeliveryCore`` takes what workers and clients said (already decoded and schema-checked)
and answers with what to send; it owns no socket, process or clock (``now`` is an argument,
seconds). ``server.py`` moves the bytes; ``tests/test_delivery_core.py`` drives this class
through thousands of interleavings with hypothesis.

Batch payloads are opaque here: ``make_batch(samples)`` builds one from what ``sample()``
was given (``assembly.make_batch`` in the server), and a payload is only asked for
``subset(keep)``; every sample travels with its ``ids.SampleKey``.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable, Dict, Hashable, List, Optional, Sequence, Tuple

from v2v_server.delivery.batcher import SHUFFLES, Batcher
from v2v_server.delivery.ledger import BatchRecord, DeliveryLedger
from v2v_server.checks import check_choice, check_float, check_int
from v2v_server.settings import setting
from v2v_wire.ids import SampleKey
from v2v_wire.protocol import MAX_CREDITS, OUTPUTS
from v2v_server.delivery.schedule import MAX_TASK_CRASHES, EpochScheduler, Job
from v2v_wire.messages import Ack, Bye, Credit, Hello, Hold, Released
from v2v_wire.stream_messages import Drained, EpochDone, Granted, Revoke, ServerError, StreamMessage, Welcome
from v2v_wire.worker_messages import Task

log = logging.getLogger("v2v.server")

Msg = Tuple[bytes, StreamMessage]


MAX_SHUFFLE_BUFFER = 4096


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
            (:attr:`lanes`).
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
    lease_s: float = setting(60.0, help="seconds before an unacknowledged batch is sent again", flag="--lease")
    client_timeout_s: float = setting(10.0, help="seconds of client silence before its batches go back to the queue",
                                      flag="--client-timeout")
    revoke_s: Optional[float] = setting(None, help="seconds a client may leave a revoke unanswered before it is "
                                                   "dropped (default: the client timeout)", flag="--revoke-timeout")
    max_credits: int = setting(64, help="most batches one client may hold")
    task_timeout_s: float = setting(300.0, help="seconds a worker may send nothing on a task before the task is "
                                                "reassigned and the worker replaced", flag="--task-timeout")
    shuffle: str = setting("epoch", help="epoch: each epoch hands the videos out in an order drawn from (seed, "
                                         "epoch) and each made sample joins a random open batch of the shuffle "
                                         "buffer, so batches mix videos whatever the worker count; none: the "
                                         "listing's order, batches in the order samples are made (docs/shuffle.md)",
                           choices=SHUFFLES)
    shuffle_buffer: int = setting(64, help="samples the shuffle buffer holds (shuffle: epoch), rounded "
                                           "up to whole batches: that many samples of server memory "
                                           "(docs/shuffle.md has their size)")
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
        check_int("shuffle_buffer", self.shuffle_buffer, 1, MAX_SHUFFLE_BUFFER, "samples")

    @property
    def lanes(self) -> int:
        """Open batches per epoch: ``ceil(shuffle_buffer / batch_size)`` when shuffling, else 1
        (arrival order)."""
        return -(-self.shuffle_buffer // self.batch_size) if self.shuffle == "epoch" else 1


class GroupPadding:
    """What DDP padding needs, per group of ranks (``world_size > 1``): how many batches of
    each epoch each rank yielded, and the group's last acknowledged batch (what a rank that was
    sent nothing repeats). Pure."""

    def __init__(self):
        self.taken: Dict[Tuple[str, int], Dict[int, int]] = {}  # (group, epoch) -> rank -> batches yielded
        self.pad_source: Dict[str, BatchRecord] = {}  # group -> its last acknowledged batch

    def resumed(self, group: str, rank: int, completed_epoch: int, batches: Dict[int, int]) -> None:
        """A rank's resume state: in each epoch after ``completed_epoch`` it yielded
        ``batches[epoch]`` batches (0 where the state names none)."""
        for (g, e), counts in self.taken.items():
            if g == group and e > completed_epoch:
                counts[rank] = batches.get(e, 0)
        for e, n in batches.items():
            if e > completed_epoch:
                self.taken.setdefault((group, e), {})[rank] = n

    def acked(self, group: str, rank: int, batch: BatchRecord) -> None:
        """Rank ``rank`` of ``group`` was granted ``batch`` (it yields it)."""
        counts = self.taken.setdefault((group, batch.epoch), {})
        counts[rank] = counts.get(rank, 0) + 1
        self.pad_source[group] = batch

    def released(self, group: str, rank: int, batch: BatchRecord) -> None:
        """Rank ``rank`` gave back ``batch``, granted and counted before: it yielded it not."""
        counts = self.taken.get((group, batch.epoch), {})
        if counts.get(rank, 0) > 0:
            counts[rank] -= 1

    def epoch_done(self, c, epoch: int) -> Tuple[int, Optional[BatchRecord]]:
        """For the rank of client ``c`` (``ledger.ClientRecord``) once ``epoch`` is complete:
        the batches every rank of its group reaches (the most any of them yielded), and a
        padding batch (batch id -1, a copy of the group's last acknowledged batch) when ``c``
        was never sent a batch and is behind, else None."""
        counts = self.taken.get((c.group, epoch), {})
        most = max(counts.values()) if counts else 0
        src = self.pad_source.get(c.group)
        if c.sent == 0 and counts.get(c.rank, 0) < most and src is not None:
            return most, BatchRecord(-1, epoch, src.keys, src.payload, outputs=src.outputs)
        return most, None

    def prune(self, live_groups: set, forgotten: Callable[[int], bool]) -> None:
        """Forget groups with no client left and epochs ``forgotten(epoch)`` says are gone."""
        for g in [g for g in self.pad_source if g not in live_groups]:
            del self.pad_source[g]
        for key in [k for k in self.taken if forgotten(k[1])]:
            del self.taken[key]


class DeliveryCore:
    """Scheduler + ledger + batching (:class:`Batcher`) + DDP padding (:class:`GroupPadding`),
    for one server.

    Args:
        videos: corpus-relative paths.
        policy: the delivery settings (:class:`DeliveryPolicy`).
        make_batch: ``samples -> payload`` (``sample()``'s built samples, in batch order).
        journal: ``journal.Journal`` (``--state-dir``) or None.
        stall_s: see ``ledger.DeliveryLedger`` (the server passes ``ledger.STALL_S``).
    """

    def __init__(self, videos: Sequence[str], policy: DeliveryPolicy, make_batch: Callable, journal=None,
                 stall_s: Optional[float] = None):
        p = self.policy = policy
        self.sched = EpochScheduler(videos, p.epochs, p.max_task_crashes, crops_per_window=p.crops_per_window,
                                    shuffle_seed=p.seed if p.shuffle == "epoch" else None,
                                    max_samples_per_video=p.max_samples_per_video)
        self.ledger = DeliveryLedger(p.lease_s, p.client_timeout_s, p.max_credits, revoke_s=p.revoke_s,
                                     stall_s=stall_s)
        self.batcher = Batcher(p.batch_size, make_batch, self.ledger, p.lanes, p.seed)
        self.crops_per_window = p.crops_per_window
        self.task_timeout_s = p.task_timeout_s
        self.offered = tuple(p.offered)
        self.task_outputs: Dict[int, tuple] = {}
        self.outputs: Optional[tuple] = None  # what workers compute now: the union clients ask for
        self.padding = GroupPadding()
        self.announced: set = set()
        self.samples_made = 0
        # journal.Journal (``--state-dir``): told every acknowledgement, resume state and complete
        # epoch; its records, read at start, are applied like resume states
        self.journal = journal
        if journal is not None:
            for consumer, delivered in journal.records.items():
                self.sched.apply_resume(consumer, journal.completed, delivered)

    # ------------------------------------------------------------------ workers
    def task_for(self, worker: Hashable, now: float, codecs: Sequence[str] = ()) -> Optional[Task]:
        """The ``task`` message for an idle worker, or None (nothing to do, or no client yet).
        Its ``skip`` lists the ``(window, crop)`` of each sample of the video not to make;
        ``codecs``: what the worker compresses each sample with (those clients asked for)."""
        outs = self.ledger.outputs_wanted()
        if outs:
            self.outputs = tuple(o for o in OUTPUTS if o in outs)
        if self.outputs is None:
            return None
        t = self.sched.next_task(worker, now)
        if t is None:
            return None
        self.task_outputs[t.task_id] = self.outputs
        return Task(t.task_id, t.epoch, t.video, self.outputs, tuple((k.window, k.crop) for k in sorted(t.skip)),
                    tuple(codecs))

    def sample(self, worker: Hashable, task_id, key: SampleKey, now: float, build: Callable) -> bool:
        """A worker sent sample ``key`` of ``task_id``'s video; ``build(lane)`` makes the sample
        object (called only when the sample is wanted, with the open batch it joins,
        ``Batcher.lane``, so the data path can copy it into that batch's buffer; it may raise,
        which drops the sample and makes it owed again). Returns True when the sample was kept."""
        key = self.sched.accept_sample(task_id, worker, key, now)
        if key is None:
            return False
        epoch = self.sched.running[task_id].epoch
        outputs = self.task_outputs.get(task_id, ())
        lane = self.batcher.lane(epoch, outputs, self._to_come(epoch))
        try:
            s = build(lane)
        except Exception:
            self.sched.discarded(epoch, [key])
            raise
        self.samples_made += 1
        self.batcher.add(epoch, outputs, key, s, lane)
        return True

    def done(self, worker: Hashable, task_id, windows, failed: dict, error: Optional[str]) -> Optional[Job]:
        """A worker finished a task: ``windows`` complete windows the file gave, ``failed``
        windows (window -> reason), ``error`` when the pass stopped early (see
        ``EpochScheduler.task_done``). Returns the job (None for a late or stranger copy)."""
        job = self.sched.task_done(task_id, worker, windows, failed, error)
        if job is not None:
            self.task_outputs.pop(task_id, None)
        return job

    def worker_lost(self, worker: Hashable) -> Optional[Job]:
        return self.sched.worker_lost(worker)

    def timed_out(self, now: float) -> List[Tuple[Hashable, Job]]:
        """Tasks silent for ``task_timeout_s``: reassigned; the workers should be replaced."""
        return self.sched.expire(now, self.task_timeout_s)

    def _to_come(self, epoch: int) -> Optional[int]:
        """At most how many more samples ``epoch`` brings after the one just accepted, counted
        only until past the shuffle buffer (``lanes x batch_size``): a number over it means at
        least that many, and ``Batcher.lane`` then picks among every open batch, as when the
        count is unknown. None: unknown, or one lane, where no count changes the choice."""
        if self.batcher.lanes == 1:
            return None
        return self.sched.to_come(epoch, self.batcher.lanes * self.batcher.batch_size)

    def _epoch_ended(self, epoch: int) -> bool:
        """None of ``epoch``'s jobs runs or waits (or the epoch is forgotten)."""
        plan = self.sched.plans.get(epoch)
        return plan is None or not plan.open_jobs

    # ------------------------------------------------------------------ clients
    def consumer_of(self, ident: bytes, h: Hello) -> Tuple[Hashable, Optional[str]]:
        if h.world_size > 1:
            group = h.group or "default"
            return ("g:" + group, h.rank), group
        return ("c:" + (h.consumer or ident.hex()), 0), None

    def hello(self, ident: bytes, h: Hello, now: float, info: Callable[[], dict]) -> List[Msg]:
        """A client says hello (first time or again): refused with an error, or welcomed."""
        missing = [o for o in h.outputs if o not in self.offered]
        if missing:
            return [(ident, ServerError(f"this server offers only {list(self.offered)}; asked for {list(h.outputs)}",
                                        "outputs"))]
        consumer, group = self.consumer_of(ident, h)
        r = h.resume
        self.sched.apply_resume(consumer, r.completed_epoch, {e: set(ks) for e, ks in r.delivered.items()})
        if self.journal is not None:
            self.journal.replaced(consumer, r.completed_epoch, r.delivered)
        if group is not None:
            self.padding.resumed(group, h.rank, r.completed_epoch, r.batches)
        back = self.ledger.join(ident, consumer, h.outputs, h.credits, now, group, h.rank, h.world_size,
                                r.completed_epoch, h.ends_on_drained)
        if back:
            log.info("client %s said hello again; batch(es) %s go back to the queue", ident.hex(), back)
        self._drop_delivered()
        if self.outputs is None or any(o not in self.outputs for o in h.outputs):
            log.info("client %s asks for %s: workers now compute %s", ident.hex(), list(h.outputs),
                     list(self.ledger.outputs_wanted()))
        return [(ident, Welcome(info(), h.hello_id))]

    def message(self, ident: bytes, msg, now: float) -> List[Msg]:
        """Any client message but hello (see ``wire``)."""
        if not self.ledger.touch(ident, now):
            if isinstance(msg, Bye):
                return []
            return [(ident, ServerError("unknown client (this server may have restarted, or dropped it for "
                                        "silence): say hello first", "unknown_client"))]
        c = self.ledger.clients[ident]
        if isinstance(msg, Hold):
            ok, new = self.ledger.hold(ident, msg.batch_ids)
            self._delivered(c, new)  # recorded (and journaled) before the grant leaves
            refused = tuple(b for b in msg.batch_ids if b not in set(ok))
            return [(ident, Granted(tuple(ok), refused))]
        if isinstance(msg, Ack):
            self._delivered(c, self.ledger.hold(ident, msg.batch_ids)[1])  # acked without a hold: granted now
            self.ledger.ack(ident, msg.batch_ids)
        elif isinstance(msg, Released):
            back, ungranted = self.ledger.released(ident, msg.batch_ids)
            for b in ungranted:
                self.sched.undelivered(c.consumer, b.epoch, b.keys)
                if self.journal is not None:
                    self.journal.undelivered(c.consumer, b.epoch, b.keys)
                if c.group is not None and c.world_size > 1:
                    self.padding.released(c.group, c.rank, b)
            if back:
                log.info("batch(es) %s go back to the queue: the client released them", back)
        elif isinstance(msg, Credit):
            self.ledger.add_credits(ident, msg.credit)
        elif isinstance(msg, Bye):
            back = self.ledger.leave(ident)
            if back:
                log.info("client %s left; batch(es) %s go back to the queue", ident.hex(), back)
        return []  # a heartbeat only touched the client

    def _delivered(self, c, batches: List[BatchRecord]) -> None:
        """Record ``batches`` (granted to client ``c``) delivered to its consumer: in the
        scheduler, the journal and its DDP group's counts."""
        for b in batches:
            self.sched.delivered(c.consumer, b.epoch, b.keys)
            if self.journal is not None:
                self.journal.delivered(c.consumer, b.epoch, b.keys)
            if c.group is not None and c.world_size > 1:
                self.padding.acked(c.group, c.rank, b)

    def forget(self, ident: bytes) -> List[int]:
        """A client broke the protocol or cannot be reached: drop it (its batches go back)."""
        return self.ledger.leave(ident)

    def _drop_delivered(self) -> None:
        """Remove from queued batches and pending samples everything some trainer already has."""
        for bid, gone in self.ledger.drop_samples(self.sched.is_delivered):
            b = self.ledger.batches[bid]
            gone_set = set(gone)
            keep = [i for i, k in enumerate(b.keys) if k not in gone_set]
            self.ledger.shrink(bid, keep, b.payload.subset(keep) if keep else None)
            self.sched.discarded(b.epoch, gone)
        for epoch, gone in self.batcher.drop(self.sched.is_delivered):
            self.sched.discarded(epoch, gone)

    # ------------------------------------------------------------------ time
    def tick(self, now: float) -> Tuple[List[Tuple[bytes, BatchRecord]], List[Msg]]:
        """Batch leftovers, expire leases and clients, allocate batches, announce complete
        epochs. Returns ``(sends, messages)``: batches to send (the caller calls
        ``forget`` for a client it cannot reach) and control messages."""
        msgs: List[Msg] = []
        self.batcher.flush(self._epoch_ended)
        revokes, drops = self.ledger.expire(now)
        for ident, ids in revokes.items():
            log.info("lease of batch(es) %s expired at client %s; asking for them back", ids, ident.hex())
            msgs.append((ident, Revoke(tuple(ids))))
        for ident, why in drops:
            log.warning("client %s %s; dropping it (its batches go to others)", ident.hex(), why)
            msgs.append((ident, ServerError(f"dropped by the server: {why}; discard what you hold", "dropped")))
        sends, stale = self.ledger.sends(now)
        for b in stale:
            log.info("batch %d carries %s, which no connected client takes as is; its samples are made again",
                     b.batch_id, sorted(b.outputs))
            self.sched.discarded(b.epoch, b.keys)
        pads, announced = self._announce()
        return sends + pads, msgs + announced + self._drained()

    def _drained(self) -> List[Msg]:
        """``drained`` to each client holding nothing, once, when a bounded stream has nothing
        left to make or send: the rest is held by other clients. A DataLoader worker waiting
        for a batch ends its iteration on it, so the loader (in order) can take the batches
        the other workers hold; it is sent nothing after it (``ClientRecord.takes``), and a batch
        given back later goes to whoever still reads (docs/delivery.md, "Drained")."""
        s = self.sched
        drained = (s.max_epochs is not None and s.next_epoch >= s.max_epochs and not s.queue and not s.running
                   and not self.ledger.ready and not self.batcher.waiting())
        msgs: List[Msg] = []
        for ident, c in self.ledger.clients.items():
            if (not drained or c.held or c.revoked) and c.takes:  # one that ends on drained stays told
                c.told_drained = False
            elif not c.told_drained:
                c.told_drained = True
                msgs.append((ident, Drained()))
        return msgs

    def _announce(self) -> Tuple[List[Tuple[bytes, BatchRecord]], List[Msg]]:
        """``epoch_done`` for each newly complete epoch, in order, once none of its batches is
        granted and unacknowledged (a client may still give one back). A DDP rank that has yielded
        fewer batches of it than the group's most is told how many to reach; one that was never
        sent any batch first gets a padding batch (a copy of the group's last batch, batch id
        -1, every sample flagged) so it has something to repeat."""
        msgs: List[Msg] = []
        pads: List[Tuple[bytes, BatchRecord]] = []
        granted = {b.epoch for b in self.ledger.batches.values()}  # granted and not acknowledged yet
        for e in sorted(self.sched.plans):
            if not self.sched.plans[e].complete:
                self.announced.discard(e)
                break  # in order: a client forgets an epoch's ids once told it is complete
            if e not in self.announced and e in granted:
                break  # a granted batch may still be given back unused: announced once acknowledged
            if e in self.announced:
                continue
            self.announced.add(e)
            for ident, c in self.ledger.clients.items():
                c.completed = max(c.completed, e)
                batches = None
                if c.group is not None and c.world_size > 1:
                    batches, pad = self.padding.epoch_done(c, e)
                    if pad is not None:
                        pads.append((ident, pad))
                        c.sent += 1
                msgs.append((ident, EpochDone(e, batches)))
            log.info("epoch %d complete", e)
            if self.journal is not None:
                self.journal.epoch_complete(e)
        self.sched.prune(self.announced)
        self.padding.prune({c.group for c in self.ledger.clients.values()},
                           lambda e: e not in self.sched.plans and e < self.sched.next_epoch)
        return pads, msgs

    def finished(self) -> bool:
        """Every epoch of a bounded stream is complete and acknowledged."""
        return self.sched.finished() and not self.ledger.batches

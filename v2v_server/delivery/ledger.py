"""The delivery ledger: the connections (credits, liveness, DDP positions) and the one table of
batches they hold (``table.BatchTable``), moved between states only by the table's transitions.

Pure: no sockets, no clock of its own (``now`` is an argument, seconds). The rules it applies
(credits by batch id, leases and revokes, grants never taken back, silence, the server's own
stalls, fair sharing, DDP groups waiting for their ranks) are written once, in docs/delivery.md
("The protocol"); ``core.DeliveryCore`` is its one caller.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Hashable, Iterable, List, Optional, Set, Tuple

from v2v_server.delivery.table import GRANTED, LEASED, REVOKED, BatchRecord, BatchTable

__all__ = ["STALL_S", "BatchRecord", "ClientRecord", "DeliveryLedger"]

#: Seconds between two ``DeliveryLedger.expire`` calls beyond which the server counts itself
#: stalled (its loop runs every 0.1 s): the gap is added to every deadline.
STALL_S = 1.0


@dataclass
class ClientRecord:
    """One connection: who reads on it (``consumer``, its DDP position), what it asked for, its
    credits, when it last spoke (seconds), and what it was told. The batches it holds are the
    table's (``BatchTable.held_by``)."""

    ident: bytes
    consumer: Hashable
    outputs: tuple
    credits: int
    last_seen: float
    group: Optional[str] = None
    rank: int = 0
    world_size: int = 1
    served: int = 0  # round-robin position (the ledger's send counter when last served)
    granted: int = 0  # batches granted to it or sent to it as DDP padding: it yields them (one it can repeat)
    completed: int = -1  # told epochs up to this one are complete: none of them is sent to it
    #: a DataLoader worker's: the newest epoch its loader learned complete, with a batch leased after it was told
    #: that it acknowledged (the loop received it); limit (e) counts from it (``closing.EpochEnds.told_to``)
    known: int = -1
    told_drained: bool = False  # told nothing more is coming unless a batch held elsewhere comes back
    told_end: bool = False  # told the stream ended (it was told its last epoch)
    ends_on_drained: bool = False  # a DataLoader worker: it ends its iteration on ``drained``
    instance: str = ""  # the reader process's token (docs/delivery.md, "Who may say hello")
    heard: float = 0.0  # when it last said something itself (its hello's arrival, then any message)
    heard_from: Optional[float] = None  # its first message since ``Admission`` last cleared this (``_alive``)
    proved: float = float("-inf")  # when the newest batch it named was sent to it: its process lived after
    #: a DataLoader worker's grants its hello named waiting in the loader's queues (batch id -> epoch): their
    #: epochs are not told to it until it acks them (docs/delivery.md, "DataLoader workers")
    queued: Dict[int, int] = field(default_factory=dict)

    @property
    def takes(self) -> bool:
        """It may be sent batches: not a client that ends its iteration on ``drained`` and was
        told it (it is leaving; a batch sent now would bounce back after others were told
        ``drained`` too, and nobody would read it)."""
        return not (self.ends_on_drained and self.told_drained)

    @property
    def ddp(self) -> bool:
        return self.group is not None and self.world_size > 1


class DeliveryLedger:
    """The connections and the batch table (``table``), for one server.

    Args:
        lease_s: seconds a sent batch may stay ungranted before it is revoked.
        client_timeout_s: seconds of silence before a client is dropped.
        max_credits: most credits a client may ask for; more is clamped (``core.DeliveryPolicy``
            owns its default).
        revoke_s: seconds a revoke may stay unanswered before the client is dropped
            (default ``client_timeout_s``).
        group_wait_s: how long a DDP group waits for its missing ranks.
        stall_s: a gap between two ``expire`` calls longer than this is the server's own
            stall, added to every deadline (None: every gap counts, as when a caller jumps
            its clock).
    """

    def __init__(self, lease_s: float, client_timeout_s: float, max_credits: int, revoke_s: Optional[float] = None,
                 group_wait_s: Optional[float] = None, stall_s: Optional[float] = None):
        self.lease_s = lease_s
        self.client_timeout_s = client_timeout_s
        self.revoke_s = client_timeout_s if revoke_s is None else revoke_s
        self.max_credits = max_credits
        self.group_wait_s = client_timeout_s if group_wait_s is None else group_wait_s
        self.clients: Dict[bytes, ClientRecord] = {}
        self.table = BatchTable()
        self.group_since: Dict[str, float] = {}  # group -> time its first current member said hello
        self._tick = 0
        self.stall_s = stall_s
        self._last_expire: Optional[float] = None
        self.stalls = 0  # stalls of the server's own loop added to the deadlines

    # ------------------------------------------------------------------ views
    @property
    def batches(self) -> Dict[int, BatchRecord]:
        """The table's rows (read them; only the table's transitions change them)."""
        return self.table.batches

    @property
    def ready(self) -> List[int]:
        """The ready batches' ids in queue order (a copy)."""
        return self.table.ready()

    def free(self, c: ClientRecord) -> int:
        """Credits of connection ``c`` not taken by batches it holds."""
        return c.credits - self.table.held_count(c.ident)

    def in_flight(self) -> int:
        return self.table.in_flight()

    def outputs_wanted(self) -> Tuple[str, ...]:
        """The union of what connected clients ask for."""
        out: Set[str] = set()
        for c in self.clients.values():
            out.update(c.outputs)
        return tuple(sorted(out))

    # ------------------------------------------------------------------ clients
    def join(self, ident: bytes, consumer: Hashable, outputs: tuple, credits: int, now: float,
             group: Optional[str] = None, rank: int = 0, world_size: int = 1, completed: int = -1,
             ends_on_drained: bool = False, instance: str = "", heard: Optional[float] = None,
             queued: Optional[Dict[int, int]] = None) -> Tuple[List[int], List[BatchRecord]]:
        """A connection says hello (again); ``completed``: the last epoch its resume state calls
        complete (none of those is sent); ``ends_on_drained``: see ``ClientRecord.takes``;
        ``heard``: when its hello arrived (default ``now``); ``queued``: its resume state's (those of
        epochs after ``completed``: ``ClientRecord.queued``). An earlier connection of the same
        identity leaves first (:meth:`leave`; what it returns is returned)."""
        back = self.leave(ident)
        credits = max(1, min(int(credits), self.max_credits))
        c = ClientRecord(ident, consumer, tuple(outputs), credits, now, group, rank, world_size, completed=completed,
                         ends_on_drained=ends_on_drained, instance=instance, heard=now if heard is None else heard,
                         queued={b: e for b, e in (queued or {}).items() if e > completed})
        c.served = self._tick  # a newcomer is served after those waiting longer
        self.clients[ident] = c
        if c.ddp:
            self.group_since.setdefault(group, now)
        return back

    def leave(self, ident: bytes) -> Tuple[List[int], List[BatchRecord]]:
        """Forget a connection (bye, drop, unreachable, a new hello): what was leased or revoked
        to it goes back to the front of the queue (ids returned); what was granted to it is
        stranded (returned): its samples stay its consumer's, whose next hello settles them."""
        c = self.clients.pop(ident, None)
        if c is None:
            return [], []
        back, stranded = [], []
        for bid in self.table.held_by(ident):
            b = self.table.get(bid)
            if b.state == GRANTED:
                self.table.strand(bid)
                stranded.append(b)
            else:
                back.append(bid)
        for bid in sorted(back, reverse=True):
            self.table.requeue(bid)
        if c.ddp and not any(o.group == c.group for o in self.clients.values()):
            self.group_since.pop(c.group, None)
        return sorted(back), stranded

    def touch(self, ident: bytes, now: float) -> Optional[ClientRecord]:
        """The client said something: its record, or None for an unknown client."""
        c = self.clients.get(ident)
        if c is not None:
            c.last_seen = c.heard = now
            c.heard_from = now if c.heard_from is None else c.heard_from
        return c

    def add_credits(self, ident: bytes, n: int) -> None:
        """Give a client ``n`` more credits (an explicit grant, clamped to ``max_credits``)."""
        c = self.clients.get(ident)
        if c is not None and n > 0:
            c.credits = min(self.max_credits, c.credits + n)

    def ready_groups(self, now: float) -> Set[str]:
        """DDP groups whose ranks all said hello (or that waited ``group_wait_s``)."""
        ranks: Dict[str, Set[int]] = {}
        size: Dict[str, int] = {}
        for c in self.clients.values():
            if c.ddp:
                ranks.setdefault(c.group, set()).add(c.rank)
                size[c.group] = c.world_size
        return {g for g, r in ranks.items()
                if len(r) >= size[g] or now - self.group_since.get(g, now) >= self.group_wait_s}

    # ------------------------------------------------------------------ batches
    def add_batch(self, batch: BatchRecord) -> None:
        """A new batch is ready to send (made -> ready)."""
        self.table.add(batch)

    def sends(self, now: float, room=lambda c, epoch: None) -> Tuple[List[Tuple[bytes, BatchRecord]],
                                                                     List[BatchRecord]]:
        """Lease ready batches to clients with free slots (ready -> leased), in queue order,
        skipping batches only busy clients can take, and a DDP rank whose ``room(c, epoch)``
        (``GroupPadding.room``: None, no bound) its batches of that epoch on their way fill. Returns
        ``(sends, stale)``: the caller sends each ``(ident, batch)``; ``stale`` batches lack an output
        every connected client asks for, or every client with a free slot (made before those clients
        came): they left the table and their samples must be made again."""
        out: List[Tuple[bytes, BatchRecord]] = []
        stale: List[BatchRecord] = []
        groups = self.ready_groups(now)
        open_ = {i: c for i, c in self.clients.items()
                 if self.free(c) > 0 and c.takes and (not c.ddp or c.group in groups)}
        for bid in self.table.ready():
            if not open_:
                break
            b = self.table.get(bid)
            fits = [c for c in self.clients.values() if b.epoch > c.completed and set(c.outputs) <= b.outputs]
            if not fits:
                if any(b.epoch > c.completed for c in self.clients.values()):
                    self.table.forget(bid)
                    stale.append(b)
                continue  # else a reopened epoch: it waits for a client that has not completed it
            cand = [c for c in fits if c.ident in open_ and self._has_room(c, b.epoch, room)]
            if not cand:
                if any(b.epoch > c.completed and not set(c.outputs) <= b.outputs for c in open_.values()):
                    self.table.forget(bid)  # a free client lacks an output: made again with it (only busy ones fit,
                    # and a full client may never free)
                    stale.append(b)
                continue
            c = min(cand, key=lambda x: (x.ident == b.avoid, x.served, x.ident))
            self._tick += 1
            c.served = self._tick
            self.table.lease(bid, c.ident, now + self.lease_s, now, c.completed)
            if self.free(c) <= 0:
                del open_[c.ident]
            out.append((c.ident, b))
        return out, stale

    def _has_room(self, c: ClientRecord, epoch: int, room) -> bool:
        """``c`` may be sent one more batch of ``epoch``: not a DDP rank, or one below its ``room``
        counting the batches of ``epoch`` leased or revoked to it (its grants are counted in it)."""
        left = room(c, epoch) if c.ddp else None
        return left is None or left > sum(1 for i in self.table.held_by(c.ident)
                                          if self.table.get(i).epoch == epoch and self.table.get(i).state != GRANTED)

    def hold(self, ident: bytes, batch_ids: Iterable[int], now: float = 0.0) -> Tuple[List[int], List[BatchRecord]]:
        """The client asks for these batches' grants (leased or revoked -> granted). Returns
        ``(ids granted: those it holds, a revoke withdrawn; the batches this call granted: the
        caller records them delivered)``. Each id counts once, however often it is named."""
        c = self.clients.get(ident)
        if c is None:
            return [], []
        ok, new = [], []
        for bid in dict.fromkeys(batch_ids):
            if not self.table.holds(ident, bid):
                if bid in c.queued:  # not acknowledged yet: the client says it (again) while granted
                    ok.append(bid)
                continue
            b = self.table.get(bid)
            if b.state in (LEASED, REVOKED):
                new.append(self.table.grant(bid, c.consumer, now))
            ok.append(bid)
        return ok, new

    def ack(self, ident: bytes, batch_ids: Iterable[int]) -> List[BatchRecord]:
        """The training loop received these granted batches (granted -> gone): their slots are
        freed. Returns them; ids this client does not hold granted are ignored and free no slot
        (an id of ``ClientRecord.queued`` leaves it)."""
        c, done = self.clients.get(ident), []
        for bid in batch_ids if c is not None and c.queued else ():
            c.queued.pop(bid, None)
        for bid in dict.fromkeys(batch_ids):
            if self.table.holds(ident, bid) and self.table.get(bid).state == GRANTED:
                done.append(self.table.retire(bid))
                c.known = max(c.known, done[-1].told)
        return done

    def released(self, ident: bytes, batch_ids: Iterable[int]) -> Tuple[List[int], List[BatchRecord]]:
        """The client gave these batches back unused (-> ready, front of the queue). Returns
        ``(ids queued again, the batches of them that were granted: the caller records them
        undelivered)``."""
        back, ungranted = [], []
        for bid in dict.fromkeys(batch_ids):
            if not self.table.holds(ident, bid):
                continue
            was_granted = self.table.get(bid).state == GRANTED
            b = self.table.requeue(bid)
            back.append(bid)
            if was_granted:
                ungranted.append(b)
        return back, ungranted

    def settle(self, consumer: Hashable, took: "callable") -> Tuple[List[BatchRecord], List[BatchRecord]]:
        """A hello of ``consumer`` settles its stranded batches: those ``took(batch)`` says its
        resume state names leave the table (stranded -> gone: the loop got them), the others go
        back to the queue (stranded -> ready). Returns ``(retired, requeued)``."""
        kept, back = [], []
        for bid in self.table.stranded_of(consumer):
            b = self.table.get(bid)
            if took(b):
                kept.append(self.table.retire(bid))
            else:
                back.append(self.table.requeue(bid))
        return kept, back

    def _skip_stall(self, now: float) -> None:
        """Add a stall of the server's loop (over ``stall_s`` since the last call) to every deadline."""
        gap = 0.0 if self._last_expire is None else now - self._last_expire
        self._last_expire = now
        if self.stall_s is None or gap <= self.stall_s:
            return
        self.stalls += 1
        for c in self.clients.values():
            c.last_seen += gap
            self.table.shift(c.ident, gap)
        self.group_since = {g: t + gap for g, t in self.group_since.items()}

    def expire(self, now: float) -> Tuple[Dict[bytes, List[int]], List[Tuple[bytes, str]]]:
        """Leases and clients past their time. Returns ``(revokes, drops)``: batch ids to ask
        back per client (leased -> revoked), and ``(ident, reason)`` of clients dropped (silent,
        or not answering a revoke), already gone (:meth:`leave`)."""
        self._skip_stall(now)
        revokes: Dict[bytes, List[int]] = {}
        drops: List[Tuple[bytes, str]] = []
        for ident, c in list(self.clients.items()):
            if now - c.last_seen > self.client_timeout_s:
                drops.append((ident, f"silent for {now - c.last_seen:.0f} s"))
                continue
            held = [self.table.get(bid) for bid in self.table.held_by(ident)]
            late = [b.batch_id for b in held if b.state == REVOKED and now > b.deadline]
            if late:
                drops.append((ident, f"did not answer the revoke of batch(es) {late[:4]} within "
                                     f"{self.revoke_s:.0f} s"))
                continue
            for b in held:
                if b.state == LEASED and now > b.deadline:
                    self.table.revoke(b.batch_id, now + self.revoke_s)
                    revokes.setdefault(ident, []).append(b.batch_id)
        for ident, _ in drops:
            self.leave(ident)
        return revokes, drops

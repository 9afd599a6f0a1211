"""The delivery ledger: which batch is where, who may receive what, and when to ask back.

Pure: no sockets, no clock of its own (``now`` is an argument, seconds). ``server.py``
turns its answers into ZeroMQ messages; ``tests/test_delivery_core.py`` drives it directly.

Rules (docs/delivery.md, "Nothing lost, nothing let in"):

* **Credits by batch id.** A client's ``credits`` (how many batches it may hold, fixed at hello, at most
  ``max_credits``) bound the batches it holds. Sending a batch takes a slot; only an ``ack``
  or ``released`` naming a batch id this client holds frees it. Acks for anything else free
  nothing, so re-sends can never inflate a client's credits.
* **Leases and grants.** A batch sent is *leased*: unacknowledged ``lease_s`` after it was
  sent it is revoked (the client is asked to give it back). A revoke that is not answered
  within ``revoke_s`` expires: the client is dropped, everything leased to it goes back to the
  queue, and it is told so. A client hands a batch on only once it is *granted*: its ``hold``
  of a batch it still holds (leased or revoked) makes it the consumer's (``hold`` returns it;
  the caller records it delivered). A granted batch has no lease and is never taken back:
  dropping or forgetting the client forgets it (its samples stay delivered); only the
  client's ``released`` gives it back (``released`` returns it as granted: the caller records
  it undelivered). Its slot is freed by the ``ack`` that follows.
* **Silence.** A client silent for ``client_timeout_s`` is dropped the same way.
* **The server's own stalls do not count.** With ``stall_s`` (the server: ``STALL_S``), time
  the server did not listen (a gap of more than ``stall_s`` between two ``expire`` calls: the
  process was stopped, swapped out, or blocked) is added to every deadline, so a client is never dropped, nor a lease revoked, for
  a silence that was the server's.
* **Fair sharing.** Ready batches go round-robin to the clients with a free slot (least
  recently served first); a batch given back prefers another client.
* **Groups.** Clients of a DDP group (``world_size > 1``) receive nothing until all ranks of
  the group have said hello or ``group_wait_s`` passed since the first one, so every resume
  state is known before a batch of the group is chosen.
* **Bounded.** Batches held = ready (at most ``max_ready`` asked of the worker side) +
  in flight (at most the sum of the credits).
"""
from __future__ import annotations

import collections
from dataclasses import dataclass, field
from typing import Any, Deque, Dict, Hashable, Iterable, List, Optional, Set, Tuple

from v2v_wire.ids import SampleKey

#: Seconds between two ``DeliveryLedger.expire`` calls beyond which the server counts itself
#: stalled (its loop runs every 0.1 s): the gap is added to every deadline.
STALL_S = 1.0


@dataclass
class BatchRecord:
    """A batch made and not yet acknowledged.

    Attributes:
        batch_id: unique id.
        epoch: epoch of every sample in it.
        keys: the ``ids.SampleKey`` of each sample, in batch order.
        payload: opaque to the ledger (``assembly.BatchPayload`` in the server).
        avoid: a client that gave it back (prefer another one).
        outputs: names of the arrays it carries (a client gets it only if it asks for a subset).
    """

    batch_id: int
    epoch: int
    keys: List[SampleKey]
    payload: Any = None
    avoid: Optional[bytes] = None
    outputs: frozenset = frozenset()  # arrays it carries; sent only to clients asking for a subset


@dataclass
class ClientRecord:
    ident: bytes
    consumer: Hashable
    outputs: tuple
    credits: int
    last_seen: float
    group: Optional[str] = None
    rank: int = 0
    world_size: int = 1
    held: Dict[int, float] = field(default_factory=dict)  # batch id -> lease deadline
    revoked: Dict[int, float] = field(default_factory=dict)  # batch id -> revoke deadline
    granted: Dict[int, None] = field(default_factory=dict)  # batch ids granted, not yet acknowledged
    served: int = 0  # round-robin position (ledger's send counter when last served)
    sent: int = 0
    completed: int = -1  # its consumer was told epochs up to this one are complete: none of them is sent
    told_drained: bool = False  # told nothing more is coming unless a batch held elsewhere comes back
    ends_on_drained: bool = False  # a DataLoader worker: it ends its iteration on ``drained``

    @property
    def free(self) -> int:
        return self.credits - len(self.held) - len(self.revoked) - len(self.granted)

    @property
    def takes(self) -> bool:
        """It may be sent batches: not a client that ends its iteration on ``drained`` and was
        told it (it is leaving; a batch sent now would bounce back after others were told
        ``drained`` too, and nobody would read it)."""
        return not (self.ends_on_drained and self.told_drained)

    def holds(self, bid: int) -> bool:
        return bid in self.held or bid in self.revoked or bid in self.granted

    def take(self, bid: int) -> bool:
        """Forget ``bid`` (leased, revoked or granted); False when this client does not hold it."""
        if not self.holds(bid):
            return False
        self.held.pop(bid, None)
        self.revoked.pop(bid, None)
        self.granted.pop(bid, None)
        return True

    def shift(self, gap: float) -> None:
        """Move every deadline ``gap`` seconds later (the server stalled)."""
        self.last_seen += gap
        for d in (self.held, self.revoked):
            for bid in d:
                d[bid] += gap


class DeliveryLedger:
    """Credits, leases, acks, revokes and re-sends for every connected client.

    Args:
        lease_s: seconds a sent batch may stay unacknowledged before it is revoked.
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
        self.batches: Dict[int, BatchRecord] = {}
        self.ready: Deque[int] = collections.deque()
        self.where: Dict[int, bytes] = {}  # batch id -> client holding it
        self.group_since: Dict[str, float] = {}  # group -> time its first current member said hello
        self._tick = 0
        self.stall_s = stall_s
        self._last_expire: Optional[float] = None
        self.stalls = 0  # stalls of the server's own loop added to the deadlines
        self.sent = 0
        self.resent = 0
        self.acked = 0

    # ------------------------------------------------------------------ clients
    def join(self, ident: bytes, consumer: Hashable, outputs: tuple, credits: int, now: float,
             group: Optional[str] = None, rank: int = 0, world_size: int = 1, completed: int = -1,
             ends_on_drained: bool = False) -> List[int]:
        """A client says hello (again); ``completed``: the last epoch its resume state calls complete
        (none of those is sent); ``ends_on_drained``: see ``ClientRecord.takes``. An earlier connection with
        the same identity or consumer is dropped first (its batches go back to the queue; ids returned)."""
        back: List[int] = []
        for other in [c.ident for c in self.clients.values() if c.ident == ident or c.consumer == consumer]:
            back += self.leave(other)
        credits = max(1, min(int(credits), self.max_credits))
        c = ClientRecord(ident, consumer, tuple(outputs), credits, now, group, rank, world_size, completed=completed,
                         ends_on_drained=ends_on_drained)
        c.served = self._tick  # a newcomer is served after those waiting longer
        self.clients[ident] = c
        if group is not None and world_size > 1:
            self.group_since.setdefault(group, now)
        return back

    def leave(self, ident: bytes) -> List[int]:
        """Forget a client (bye, drop, unreachable); what was leased to it goes back to the
        front of the queue (ids returned). What was granted to it is forgotten: its samples
        stay delivered to its consumer (it may have handed them on)."""
        c = self.clients.pop(ident, None)
        if c is None:
            return []
        for bid in c.granted:
            self.batches.pop(bid, None)
            self.where.pop(bid, None)
        back = sorted(set(c.held) | set(c.revoked))
        for bid in reversed(back):
            self.where.pop(bid, None)
            self._requeue(bid, ident)
        if c.group is not None and not any(o.group == c.group for o in self.clients.values()):
            self.group_since.pop(c.group, None)
        return back

    def touch(self, ident: bytes, now: float) -> bool:
        """The client said something; False for an unknown client."""
        c = self.clients.get(ident)
        if c is None:
            return False
        c.last_seen = now
        return True

    def add_credits(self, ident: bytes, n: int) -> None:
        """Give a client ``n`` more credits (an explicit grant, clamped to ``max_credits``)."""
        c = self.clients.get(ident)
        if c is not None and n > 0:
            c.credits = min(self.max_credits, c.credits + n)

    def _group_ready(self, c: ClientRecord, now: float) -> bool:
        if c.group is None or c.world_size <= 1:
            return True
        ranks = {o.rank for o in self.clients.values() if o.group == c.group}
        return len(ranks) >= c.world_size or now - self.group_since.get(c.group, now) >= self.group_wait_s

    # ------------------------------------------------------------------ batches
    def add_batch(self, batch: BatchRecord) -> None:
        """A new batch is ready to send."""
        self.batches[batch.batch_id] = batch
        self.ready.append(batch.batch_id)

    def sends(self, now: float) -> Tuple[List[Tuple[bytes, BatchRecord]], List[BatchRecord]]:
        """Allocate ready batches to clients with free slots (leases start now), in queue order,
        skipping batches only busy clients can take. Returns ``(sends, stale)``: the caller sends
        each ``(ident, batch)``; ``stale`` batches lack an output every connected client asks for
        (made before those clients came): they are forgotten here and their samples must be made
        again."""
        out: List[Tuple[bytes, BatchRecord]] = []
        stale: List[BatchRecord] = []
        for bid in list(self.ready):
            free = [c for c in self.clients.values() if c.free > 0 and c.takes and self._group_ready(c, now)]
            if not free:
                break
            b = self.batches.get(bid)
            if b is None:
                self.ready.remove(bid)
                continue
            fits = [c for c in self.clients.values() if set(c.outputs) <= b.outputs and b.epoch > c.completed]
            if not fits and not [c for c in self.clients.values() if b.epoch > c.completed]:
                continue  # a reopened epoch: wait for a client that has not completed it
            if not fits:
                self.ready.remove(bid)
                del self.batches[bid]
                stale.append(b)
                continue
            cand = [c for c in fits if c.free > 0 and c.takes and self._group_ready(c, now)]
            if not cand:
                continue
            c = min(cand, key=lambda x: (x.ident == b.avoid, x.served, x.ident))
            self.ready.remove(bid)
            self._tick += 1
            c.served = self._tick
            c.sent += 1
            c.held[bid] = now + self.lease_s
            self.where[bid] = c.ident
            self.sent += 1
            out.append((c.ident, b))
        return out, stale

    def hold(self, ident: bytes, batch_ids: Iterable[int]) -> Tuple[List[int], List[BatchRecord]]:
        """The client asks for these batches' grants. Returns ``(ids granted: those it holds,
        a revoke withdrawn; the batches this call granted: the caller records them delivered)``."""
        c = self.clients.get(ident)
        if c is None:
            return [], []
        ok, new = [], []
        for bid in batch_ids:
            if bid in c.granted:
                ok.append(bid)
            elif c.take(bid) and bid in self.batches:
                c.granted[bid] = None
                ok.append(bid)
                new.append(self.batches[bid])
        return ok, new

    def ack(self, ident: bytes, batch_ids: Iterable[int]) -> List[BatchRecord]:
        """The training loop received these granted batches (``hold`` first: the core grants
        what an ack names): their slots are freed and the ledger forgets them. Returns them;
        ids this client does not hold are ignored and free no slot."""
        c = self.clients.get(ident)
        if c is None:
            return []
        done = []
        for bid in batch_ids:
            if c.take(bid):
                self.where.pop(bid, None)
                b = self.batches.pop(bid, None)
                if b is not None:
                    self.acked += 1
                    done.append(b)
        return done

    def released(self, ident: bytes, batch_ids: Iterable[int]) -> Tuple[List[int], List[BatchRecord]]:
        """The client gave these batches back unused: to the front of the queue. Returns ``(ids
        queued again, the batches of them that were granted: the caller records them undelivered)``."""
        c = self.clients.get(ident)
        if c is None:
            return [], []
        back, ungranted = [], []
        for bid in batch_ids:
            was_granted = bid in c.granted
            if c.take(bid) and self.where.pop(bid, None) is not None and self._requeue(bid, ident):
                back.append(bid)
                if was_granted:
                    ungranted.append(self.batches[bid])
        return back, ungranted

    def _requeue(self, bid: int, ident: bytes) -> bool:
        """``bid`` goes to the front of the queue (``ident`` gave it back: another client is
        preferred); False when it is gone."""
        if bid not in self.batches:
            return False
        self.batches[bid].avoid = ident
        self.ready.appendleft(bid)
        self.resent += 1
        return True

    def _skip_stall(self, now: float) -> None:
        """Add a stall of the server's loop (over ``stall_s`` since the last call) to every deadline."""
        gap = 0.0 if self._last_expire is None else now - self._last_expire
        self._last_expire = now
        if self.stall_s is None or gap <= self.stall_s:
            return
        self.stalls += 1
        for c in self.clients.values():
            c.shift(gap)
        self.group_since = {g: t + gap for g, t in self.group_since.items()}

    def expire(self, now: float) -> Tuple[Dict[bytes, List[int]], List[Tuple[bytes, str]]]:
        """Leases and clients past their time. Returns ``(revokes, drops)``: batch ids to ask
        back per client, and ``(ident, reason)`` of clients dropped (silent, or not answering
        a revoke); their batches are already back in the queue."""
        self._skip_stall(now)
        revokes: Dict[bytes, List[int]] = {}
        drops: List[Tuple[bytes, str]] = []
        for ident, c in list(self.clients.items()):
            if now - c.last_seen > self.client_timeout_s:
                drops.append((ident, f"silent for {now - c.last_seen:.0f} s"))
                continue
            late = [bid for bid, t in c.revoked.items() if now > t]
            if late:
                drops.append((ident, f"did not answer the revoke of batch(es) {late[:4]} within "
                                     f"{self.revoke_s:.0f} s"))
                continue
            for bid, t in list(c.held.items()):
                if now > t:
                    del c.held[bid]
                    c.revoked[bid] = now + self.revoke_s
                    revokes.setdefault(ident, []).append(bid)
        for ident, _ in drops:
            self.leave(ident)
        return revokes, drops

    def drop_samples(self, should_drop) -> List[Tuple[int, List[SampleKey]]]:
        """Remove samples for which ``should_drop(epoch, key)`` is true from batches not yet
        sent (a resume state says a trainer has them). Returns ``(epoch, keys removed)`` per
        touched batch; the caller shrinks payloads with ``keep_positions``."""
        out = []
        for bid in list(self.ready):
            b = self.batches.get(bid)
            if b is None:
                continue
            gone = [k for k in b.keys if should_drop(b.epoch, k)]
            if gone:
                out.append((bid, gone))
        return out

    def shrink(self, batch_id: int, keep: List[int], payload: Any) -> None:
        """Keep only the samples at positions ``keep`` of a queued batch (none: forget it)."""
        b = self.batches.get(batch_id)
        if b is None:
            return
        if not keep:
            del self.batches[batch_id]
            try:
                self.ready.remove(batch_id)
            except ValueError:
                pass
            return
        b.keys = [b.keys[i] for i in keep]
        b.payload = payload

    # ------------------------------------------------------------------ views
    def in_flight(self) -> int:
        return sum(len(c.held) + len(c.revoked) + len(c.granted) for c in self.clients.values())

    def outputs_wanted(self) -> Tuple[str, ...]:
        """The union of what connected clients ask for."""
        out: Set[str] = set()
        for c in self.clients.values():
            out.update(c.outputs)
        return tuple(sorted(out))

"""The delivery ledger: which batch is where, who may receive what, and when to ask back.

Pure: no sockets, no clock of its own (``now`` is an argument, seconds). ``server.py``
turns its answers into ZeroMQ messages; ``tests/test_delivery_core.py`` drives it directly.

Rules (README "Nothing lost, nothing let in"):

* **Credits by batch id.** A client's ``credits`` (how many batches it may hold, fixed at hello, at most
  ``max_credits``) bound the batches it holds. Sending a batch takes a slot; only an ``ack``
  or ``released`` naming a batch id this client holds frees it. Acks for anything else free
  nothing, so re-sends can never inflate a client's credits.
* **Leases.** A batch unacknowledged ``lease_s`` after it was sent is revoked (the client is
  asked to give it back). A revoke that is not answered within ``revoke_s`` expires: the
  client is dropped, everything it held goes back to the queue, and it is told so. A batch
  the client says it ``hold``s (handed to a DataLoader's queue, acknowledged when the
  training loop receives it) has no lease: it stays with the client until acknowledged,
  released, or the client leaves or is dropped.
* **Silence.** A client silent for ``client_timeout_s`` is dropped the same way.
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
import math
from dataclasses import dataclass, field
from typing import Any, Deque, Dict, Hashable, Iterable, List, Optional, Set, Tuple

from v2v_wire.ids import SampleKey

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
    served: int = 0  # round-robin position (ledger's send counter when last served)
    sent: int = 0
    completed: int = -1  # its consumer was told epochs up to this one are complete: none of them is sent
    told_drained: bool = False  # told nothing more is coming unless a batch held elsewhere comes back

    @property
    def free(self) -> int:
        return self.credits - len(self.held) - len(self.revoked)


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
    """

    def __init__(self, lease_s: float, client_timeout_s: float, max_credits: int, revoke_s: Optional[float] = None,
                 group_wait_s: Optional[float] = None):
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
        self.sent = 0
        self.resent = 0
        self.acked = 0

    # ------------------------------------------------------------------ clients
    def join(self, ident: bytes, consumer: Hashable, outputs: tuple, credits: int, now: float,
             group: Optional[str] = None, rank: int = 0, world_size: int = 1, completed: int = -1) -> List[int]:
        """A client says hello (again); ``completed`` is the last epoch its resume state calls
        complete (it is sent nothing of those). An earlier connection with the same identity or
        the same consumer is dropped first (its batches go back to the queue; ids returned)."""
        back: List[int] = []
        for other in [c.ident for c in self.clients.values() if c.ident == ident or c.consumer == consumer]:
            back += self.leave(other)
        credits = max(1, min(int(credits), self.max_credits))
        c = ClientRecord(ident, consumer, tuple(outputs), credits, now, group, rank, world_size, completed=completed)
        c.served = self._tick  # a newcomer is served after those waiting longer
        self.clients[ident] = c
        if group is not None and world_size > 1:
            self.group_since.setdefault(group, now)
        return back

    def leave(self, ident: bytes) -> List[int]:
        """Forget a client (bye, drop, unreachable); what it held goes back to the front of
        the queue. Returns those batch ids."""
        c = self.clients.pop(ident, None)
        if c is None:
            return []
        back = sorted(set(c.held) | set(c.revoked))
        for bid in reversed(back):
            self.where.pop(bid, None)
            if bid in self.batches:
                self.batches[bid].avoid = ident
                self.ready.appendleft(bid)
                self.resent += 1
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

    def grant(self, ident: bytes, n: int) -> None:
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
            free = [c for c in self.clients.values() if c.free > 0 and self._group_ready(c, now)]
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
            cand = [c for c in fits if c.free > 0 and self._group_ready(c, now)]
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

    def _take(self, c, bid: int) -> bool:
        """Take ``bid`` off client ``c`` (held or revoked); False when ``c`` does not hold it."""
        if bid not in c.held and bid not in c.revoked:
            return False
        c.held.pop(bid, None)
        c.revoked.pop(bid, None)
        self.where.pop(bid, None)
        return True

    def ack(self, ident: bytes, batch_ids: Iterable[int]) -> List[BatchRecord]:
        """The client handed these batches to its training loop. Returns the batches this
        acknowledgement delivered (only those this client holds; anything else is ignored
        and frees no slot)."""
        c = self.clients.get(ident)
        if c is None:
            return []
        done = []
        for bid in batch_ids:
            if self._take(c, bid):
                b = self.batches.pop(bid, None)
                if b is not None:
                    self.acked += 1
                    done.append(b)
        return done

    def hold(self, ident: bytes, batch_ids: Iterable[int]) -> None:
        """The client handed these batches to its data loader: their leases end (a revoke
        already sent is withdrawn; the client answers it no more)."""
        c = self.clients.get(ident)
        if c is None:
            return
        for bid in batch_ids:
            if bid in c.held or bid in c.revoked:
                c.revoked.pop(bid, None)
                c.held[bid] = math.inf

    def released(self, ident: bytes, batch_ids: Iterable[int]) -> List[int]:
        """The client gave back revoked (or held) batches; they go back to the queue."""
        c = self.clients.get(ident)
        if c is None:
            return []
        back = []
        for bid in batch_ids:
            if self._take(c, bid):
                if bid in self.batches:
                    self.batches[bid].avoid = ident
                    self.ready.appendleft(bid)
                    self.resent += 1
                    back.append(bid)
        return back

    def expire(self, now: float) -> Tuple[Dict[bytes, List[int]], List[Tuple[bytes, str]]]:
        """Leases and clients past their time. Returns ``(revokes, drops)``: batch ids to ask
        back per client, and ``(ident, reason)`` of clients dropped (silent, or not answering
        a revoke); their batches are already back in the queue."""
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
        return sum(len(c.held) + len(c.revoked) for c in self.clients.values())

    def outputs_wanted(self) -> Tuple[str, ...]:
        """The union of what connected clients ask for."""
        out: Set[str] = set()
        for c in self.clients.values():
            out.update(c.outputs)
        return tuple(sorted(out))

"""The server's one table of batches: every batch made and not yet acknowledged, each in exactly
one state, changed only by the transition methods of :class:`BatchTable`.

Pure: no sockets, no clock of its own. The states (:data:`STATES`) and the rules that move a
batch between them are docs/delivery.md ("The server's table"), once; each method below names the
transition it makes. A leased, revoked or granted batch is held by its connection
(``BatchRecord.holder``); a stranded one by none (its ``consumer`` keeps it); a ready one is sent
to another connection than the one that gave it back (``avoid``) first.

An acknowledged batch leaves the table (:meth:`retire`). Besides the table, two indexes kept by
the same methods make every lookup O(1): the ready queue's order and each connection's batches.
"""
from __future__ import annotations

import collections
from dataclasses import dataclass
from typing import Any, Dict, Hashable, Iterator, List, Optional, Tuple

from v2v_wire.ids import SampleKey

READY, LEASED, REVOKED, GRANTED, STRANDED = "ready", "leased", "revoked", "granted", "stranded"
#: Every state a batch of the table can be in (docs/delivery.md).
STATES = (READY, LEASED, REVOKED, GRANTED, STRANDED)


@dataclass(eq=False)
class BatchRecord:
    """A batch made and not yet acknowledged: one row of the :class:`BatchTable`.

    Attributes:
        batch_id: unique id (-1: a DDP padding copy, never in the table).
        epoch: epoch of every sample in it.
        keys: the ``ids.SampleKey`` of each sample, in batch order.
        payload: opaque to the table (``assembly.BatchPayload`` in the server).
        avoid: the connection that gave it back last (another one is preferred).
        outputs: names of the arrays it carries (sent only to clients asking for a subset).
        state: one of :data:`STATES`; set only by :class:`BatchTable`.
        holder: the connection (identity bytes) holding it: leased, revoked or granted.
        consumer: whose its samples are once granted (granted, stranded).
        deadline: seconds (the server's clock): when a lease or a revoke runs out.
        since: when it was granted.
        sent: when it was leased to its holder (a connection that names it later was alive then).
        told: the newest epoch its holder was told complete before it was leased (a DataLoader
            worker's loader learns that epoch complete with it: docs/delivery.md, limit (e)).
    """

    batch_id: int
    epoch: int
    keys: List[SampleKey]
    payload: Any = None
    avoid: Optional[bytes] = None
    outputs: frozenset = frozenset()
    state: str = READY
    holder: Optional[bytes] = None
    consumer: Hashable = None
    deadline: float = 0.0
    since: float = 0.0
    sent: float = 0.0
    told: int = -1


class TransitionError(RuntimeError):
    """A transition asked of a batch in a state it does not leave that way (a bug of the caller)."""


class BatchTable:
    """The batches made and not yet acknowledged (``batches``: id -> :class:`BatchRecord`), their
    states and the transitions between them (module docstring). Counters: ``made``, ``sent``,
    ``resent`` (given back to the queue), ``acked``."""

    def __init__(self):
        self.batches: Dict[int, BatchRecord] = {}
        self._ready: "collections.OrderedDict[int, None]" = collections.OrderedDict()
        self._held: Dict[bytes, Dict[int, None]] = {}  # connection -> ids leased, revoked or granted to it
        self._stranded: Dict[Hashable, Dict[int, None]] = {}  # consumer -> ids stranded
        self.made = self.sent = self.resent = self.acked = 0

    # ------------------------------------------------------------------ views
    def get(self, bid: int) -> Optional[BatchRecord]:
        return self.batches.get(bid)

    def ready(self) -> List[int]:
        """The ready batches' ids in queue order (a copy)."""
        return list(self._ready)

    def ready_count(self) -> int:
        return len(self._ready)

    def held_by(self, ident: bytes) -> List[int]:
        """Ids leased, revoked or granted to connection ``ident`` (a copy, oldest first)."""
        return list(self._held.get(ident, ()))

    def held_count(self, ident: bytes) -> int:
        return len(self._held.get(ident, ()))

    def holds(self, ident: bytes, bid: int) -> bool:
        return bid in self._held.get(ident, ())

    def stranded_of(self, consumer: Hashable) -> List[int]:
        return list(self._stranded.get(consumer, ()))

    def stranded_consumers(self) -> List[Hashable]:
        """The consumers some batch is stranded with."""
        return list(self._stranded)

    def in_state(self, *states: str) -> Iterator[BatchRecord]:
        """The batches in any of ``states`` (O(table))."""
        return (b for b in self.batches.values() if b.state in states)

    def in_flight(self) -> int:
        """Batches leased, revoked or granted to a connection."""
        return sum(len(ids) for ids in self._held.values())

    def states(self) -> Dict[str, int]:
        """Batches per state (status lines, tests)."""
        out = dict.fromkeys(STATES, 0)
        for b in self.batches.values():
            out[b.state] += 1
        return out

    def ready_samples(self, should_drop) -> List[Tuple[int, List[SampleKey]]]:
        """The samples of ready batches for which ``should_drop(epoch, key)`` is true (a resume
        state says a trainer has them), as ``(batch id, keys)`` per touched batch; the caller
        shrinks those batches (:meth:`shrink`)."""
        out = []
        for bid in self._ready:
            b = self.batches[bid]
            gone = [k for k in b.keys if should_drop(b.epoch, k)]
            if gone:
                out.append((bid, gone))
        return out

    # ------------------------------------------------------------------ transitions
    def add(self, b: BatchRecord) -> None:
        """made -> ready (the back of the queue)."""
        if b.batch_id in self.batches:
            raise TransitionError(f"batch {b.batch_id} is in the table already")
        b.state, b.holder, b.consumer = READY, None, None
        self.batches[b.batch_id] = b
        self._ready[b.batch_id] = None
        self.made += 1

    def lease(self, bid: int, ident: bytes, deadline: float, now: float = 0.0, told: int = -1) -> BatchRecord:
        """ready -> leased to ``ident`` (at ``now``, told epochs up to ``told`` complete) until ``deadline``."""
        b = self._expect(bid, READY)
        del self._ready[bid]
        b.state, b.holder, b.deadline, b.sent, b.told = LEASED, ident, deadline, now, told
        self._held.setdefault(ident, {})[bid] = None
        self.sent += 1
        return b

    def revoke(self, bid: int, deadline: float) -> None:
        """leased -> revoked (asked back) until ``deadline``."""
        b = self._expect(bid, LEASED)
        b.state, b.deadline = REVOKED, deadline

    def grant(self, bid: int, consumer: Hashable, now: float) -> BatchRecord:
        """leased or revoked -> granted to ``consumer`` (on the same connection); no deadline."""
        b = self._expect(bid, LEASED, REVOKED)
        b.state, b.consumer, b.since, b.deadline = GRANTED, consumer, now, 0.0
        return b

    def requeue(self, bid: int) -> BatchRecord:
        """leased, revoked, granted or stranded -> ready, at the front of the queue (given back;
        another connection than the last holder is preferred)."""
        b = self._expect(bid, LEASED, REVOKED, GRANTED, STRANDED)
        self._unhold(b)
        b.avoid = b.holder
        b.state, b.holder, b.consumer, b.deadline = READY, None, None, 0.0
        self._ready[bid] = None
        self._ready.move_to_end(bid, last=False)
        self.resent += 1
        return b

    def strand(self, bid: int) -> None:
        """granted -> stranded: its connection is gone; its consumer keeps it."""
        b = self._expect(bid, GRANTED)
        self._unhold(b)
        b.state, b.holder = STRANDED, None
        self._stranded.setdefault(b.consumer, {})[bid] = None

    def retire(self, bid: int) -> BatchRecord:
        """granted or stranded -> gone: acknowledged (the training loop got it)."""
        b = self._expect(bid, GRANTED, STRANDED)
        self._unhold(b)
        del self.batches[bid]
        self.acked += 1
        return b

    def forget(self, bid: int) -> Optional[BatchRecord]:
        """Any state -> gone without acknowledgement (stale, emptied, its samples recorded
        elsewhere); None when it was not in the table."""
        b = self.batches.pop(bid, None)
        if b is not None:
            self._ready.pop(bid, None)
            self._unhold(b)
        return b

    def shrink(self, bid: int, keep: List[int], payload: Any) -> None:
        """A ready batch keeps only the samples at positions ``keep`` (none: it leaves the table)."""
        b = self._expect(bid, READY)
        if not keep:
            self.forget(bid)
            return
        b.keys = [b.keys[i] for i in keep]
        b.payload = payload

    def shift(self, ident: bytes, gap: float) -> None:
        """Move the deadlines of ``ident``'s leased and revoked batches ``gap`` seconds later."""
        for bid in self._held.get(ident, ()):
            b = self.batches[bid]
            if b.state in (LEASED, REVOKED):
                b.deadline += gap

    # ------------------------------------------------------------------ internals
    def _expect(self, bid: int, *states: str) -> BatchRecord:
        b = self.batches.get(bid)
        if b is None or b.state not in states:
            raise TransitionError(f"batch {bid} is {'gone' if b is None else b.state}, not {' or '.join(states)}")
        return b

    def _unhold(self, b: BatchRecord) -> None:
        if b.holder is not None:
            ids = self._held.get(b.holder)
            if ids is not None:
                ids.pop(b.batch_id, None)
                if not ids:
                    del self._held[b.holder]
        if b.state == STRANDED:
            ids = self._stranded.get(b.consumer)
            if ids is not None:
                ids.pop(b.batch_id, None)
                if not ids:
                    del self._stranded[b.consumer]

"""What each connection is told about the ends of epochs and of the stream (``epoch_done``,
``end``, ``drained``), and when the server may exit, pure. The rules, and the bound on how long a
reader sitting on its grants delays the others, are docs/delivery.md ("Ends of epochs and of the
stream"); :class:`EpochEnds` applies them each turn of the server's loop.
"""
from __future__ import annotations

import bisect
import logging
from typing import Dict, Hashable, Iterable, List, Optional, Set, Tuple

from v2v_server.delivery.ledger import ClientRecord, DeliveryLedger
from v2v_server.delivery.padding import GroupPadding
from v2v_server.delivery.schedule import EpochScheduler
from v2v_server.delivery.table import GRANTED, LEASED, REVOKED, STRANDED, BatchRecord
from v2v_wire.messages import Hello
from v2v_wire.stream_messages import Drained, End, EpochDone, StreamMessage

log = logging.getLogger("v2v.server")

Msg = Tuple[bytes, StreamMessage]


class EpochEnds:
    """Tells connections the ends of epochs (with DDP padding), ``drained`` and ``end``, and says
    when the server may exit.

    Args:
        sched, ledger, batcher, padding: the core's parts (read; ``ClientRecord.completed`` and
            ``told_drained`` are set here, and ``EpochPlan.told``).
        journal: ``journal.Journal`` or None: told each epoch closed for good.
        grant_wait_s: seconds another consumer's grant of an epoch may delay a connection's end of
            it (the lease).
        end_grace_s: seconds a bounded stream's server stays up with no reader after it is over.
    """

    def __init__(self, sched: EpochScheduler, ledger: DeliveryLedger, batcher, padding: GroupPadding, journal,
                 grant_wait_s: float, end_grace_s: float):
        self.sched, self.ledger, self.batcher, self.padding, self.journal = sched, ledger, batcher, padding, journal
        self.grant_wait_s, self.end_grace_s = grant_wait_s, end_grace_s
        self.told_upto = -1 if journal is None else journal.told  # the newest epoch told complete to some connection
        self._low: Optional[int] = None  # the oldest epoch every connection was told, at the last full turn
        self.ended = False  # the stream is over (logged once)
        self._idle_since: Optional[float] = None  # over, with no reader connected, since
        #: consumer -> the newest epoch it was told complete (or its resume state said; a DataLoader worker: what
        #: its loader learned, ``ClientRecord.known``), kept for good (one number a consumer, even once its records
        #: are gone): what of an epoch the scheduler forgets it keeps for that consumer, and a resume state further
        #: behind is refused (``Admission.resume_problem``; journaled; docs/delivery.md, limit (e))
        self.told_to: Dict[Hashable, int] = {} if journal is None else dict(journal.told_to)

    # ------------------------------------------------------------------ per tick
    def tell(self, now: float, waiting: Set[str] = frozenset(), hello_waits: bool = False,
             dormant: Iterable[Hello] = ()) -> Tuple[List[Tuple[bytes, BatchRecord]], List[Msg]]:
        """``epoch_done`` for every epoch each connection may now be told (a DDP rank that was
        never sent a batch first gets a padding batch, ``GroupPadding.epoch_done``), then ``end``
        to each connection told its last epoch; a DDP rank only once its group is ready
        (``DeliveryLedger.ready_groups``) and none of its ranks' hellos is ``waiting``, nor
        ``dormant`` (forgotten for its connection's silence) for a rank of the group's world size
        that no connection reads: another rank's resume state may reopen the epoch, and every rank
        must end it alike (docs/delivery.md, "A world size changes"). While any hello waits
        (``hello_waits``) no epoch the scheduler keeps is forgotten: its state may reopen one.
        Returns ``(padding sends, messages)``."""
        pads: List[Tuple[bytes, BatchRecord]] = []
        msgs: List[Msg] = []
        low = min((c.completed for c in self.ledger.clients.values()), default=self.told_upto)
        if low == self._low and not any(self._may_tell(c) for c in self.ledger.clients.values()):
            return pads, msgs  # nothing to tell and nothing to forget: the common turn costs O(connections)
        self._low = low
        own, live, fresh = self._holders(now)
        ready = self.ledger.ready_groups(now) - set(waiting)
        ranks = [c for c in self.ledger.clients.values() if c.ddp and c.group in ready]
        if ranks:  # a forgotten hello holds back only a group about to be told (none: no walk over them)
            read, sizes = {c.consumer for c in ranks}, {c.group: c.world_size for c in ranks}
            for h in dormant:  # its process may live: a pause, or a network that delayed its messages
                g = h.group or "default"
                if h.world_size > 1 and sizes.get(g) == h.world_size and ("g:" + g, h.rank) not in read:
                    ready.discard(g)
        for ident, c in self.ledger.clients.items():
            if c.ddp and c.group not in ready:
                continue
            blocked = sorted({e for e in live if not self._reached(c, e)} | own.get(c.consumer, set())
                             | set(c.queued.values()) | {e for e, who in fresh.items() if who - {c.consumer}})
            while True:
                step = self._next(c, blocked)
                if step is None:
                    break
                e, per_epoch = step
                batches = None
                if per_epoch and c.ddp:
                    batches, pad = self.padding.epoch_done(c, e)
                    if self.journal is not None:
                        self.journal.epoch_told(e, c.group, batches)
                    if pad is not None:
                        pads.append((ident, pad))
                        c.granted += 1
                c.completed = e
                msgs.append((ident, EpochDone(e, batches)))
                self._told(e)
            last = self.sched.max_epochs
            if last is not None and c.completed >= last - 1 and not c.told_end:
                c.told_end = True
                msgs.append((ident, End()))
        self._close_for_good(own, live, hello_waits)
        return pads, msgs

    def told_again(self, ident: bytes, c: ClientRecord) -> List[Msg]:
        """A connection told the stream's end that still speaks did not get it: lost with a broken connection
        behind ZeroMQ's reconnect, which no hello follows. Its last epoch's end (a DDP rank's with the count its
        group was told: the padding it owes comes from it) and ``end``, told again (docs/delivery.md, "Ends of
        epochs and of the stream")."""
        n = self.padding.told.get((c.group, c.completed)) if c.ddp else None
        return ([] if c.ddp and n is None else [(ident, EpochDone(c.completed, n))]) + [(ident, End())]

    def _may_tell(self, c: ClientRecord) -> bool:
        """Connection ``c`` might be told something now: its next epoch is opened and complete
        (or forgotten), or the stream's end."""
        e, s = c.completed + 1, self.sched
        if s.max_epochs is not None and c.completed >= s.max_epochs - 1:
            return not c.told_end
        plan = s.plans.get(e)
        return e < s.next_epoch and (plan is None or plan.complete or self._reached(c, e))

    def _reached(self, c: ClientRecord, e: int) -> bool:
        """DDP rank ``c`` yielded the count of ``e`` its group was told: no batch of ``e`` can go to it
        any more (``GroupPadding.room``), so what of ``e`` is left (reopened by another rank's hello)
        holds its end back no longer (docs/delivery.md, "Ends of epochs")."""
        left = self.padding.room(c, e) if c.ddp else None
        return left is not None and left <= 0

    def _holders(self, now: float):
        """``(own, live, fresh)``: per consumer the epochs it holds grants of; the epochs with a
        batch ready, leased, revoked or waiting in the shuffle buffer; per epoch the consumers
        holding a grant of it younger than ``grant_wait_s``."""
        own: Dict[Hashable, Set[int]] = {}
        live: Set[int] = set()
        fresh: Dict[int, Set[Hashable]] = {}
        for b in self.ledger.table.batches.values():
            if b.state in (GRANTED, STRANDED):
                own.setdefault(b.consumer, set()).add(b.epoch)
                if now - b.since < self.grant_wait_s:
                    fresh.setdefault(b.epoch, set()).add(b.consumer)
            else:
                live.add(b.epoch)
        live.update(self.batcher.waiting_epochs())
        return own, live, fresh

    def _next(self, c: ClientRecord, blocked: List[int]) -> Optional[Tuple[int, bool]]:
        """The epoch connection ``c`` may be told next, and whether it is one epoch told with its
        count (one with its plan, or for a DDP rank one its group's states count: every rank pads
        up to it, docs/delivery.md "Ends of epochs"); else the newest of a run of forgotten or never
        opened epochs, told at once; None."""
        e = c.completed + 1
        s = self.sched
        if e >= s.next_epoch:
            return None
        i = bisect.bisect_left(blocked, e)
        first_blocked = blocked[i] if i < len(blocked) else None
        plan = s.plans.get(e)
        if plan is not None:
            return (e, True) if (plan.complete or self._reached(c, e)) and first_blocked != e else None
        upto = min([p for p in s.plans if p > e] + [s.next_epoch]) - 1  # run of epochs without a plan
        if first_blocked is not None:
            upto = min(upto, first_blocked - 1)
        if c.ddp:  # an epoch its group counts (a started stream never opened it here) is told alone
            counted = [x for x in range(e, upto + 1) if (c.group, x) in self.padding.taken]
            if counted:
                return (e, True) if counted[0] == e else (counted[0] - 1, False)
        return (upto, False) if upto >= e else None

    def _told(self, e: int) -> None:
        plan = self.sched.plans.get(e)
        if plan is not None:
            plan.told = True
        if e > self.told_upto:
            self.told_upto = e
            log.info("epoch %d complete", e)
            if self.journal is not None:
                self.journal.epoch_told(e)

    def _close_for_good(self, own: Dict[Hashable, Set[int]], live: Set[int], hello_waits: bool = False) -> None:
        """Epochs told to every connection may be forgotten by the scheduler (it keeps the newest
        few); those also held by nobody, and every epoch before them, leave the journal (its
        watermark: a restart starts after it). A connection, or a grant, more than the scheduler's
        ``keep_epochs`` behind the newest epoch told holds neither back: a reader sitting on its
        grants never makes the server keep more epochs (what it holds stays in the table). Of an
        epoch forgotten, the records of the consumers told fewer than ``keep_epochs`` newer epochs
        complete stay (a consumer that left before the others ran on may resume into it: limit (e)
        counts in its own epochs)."""
        floor = self.told_upto - self.sched.keep_epochs
        low = max(floor, min((c.completed for c in self.ledger.clients.values()), default=self.told_upto))
        if hello_waits:  # its state may reopen any epoch the scheduler keeps
            low = min(low, floor - 1)
        held = {e for e in live.union(*own.values()) if e > floor} if own else {e for e in live if e > floor}
        done = min(low, min(held) - 1) if held else low
        if self.journal is not None and done > self.journal.completed:
            plans = self.sched.plans
            if all(plans[e].complete for e in plans if e <= done):
                self.journal.epoch_complete(done)
        told = self.told_to
        for c in self.ledger.clients.values():
            seen = c.known if c.ends_on_drained else c.completed
            if seen > told.get(c.consumer, -1):
                told[c.consumer] = seen
                if self.journal is not None:
                    self.journal.consumer_told(c.consumer, seen)
        keep = self.sched.keep_epochs
        self.sched.prune((e for e in self.sched.plans if e <= low), lambda c, e: e > told.get(c, -1) - keep)
        self.padding.prune({c.group for c in self.ledger.clients.values()},
                           lambda e: e not in self.sched.plans and e < self.sched.next_epoch,
                           lambda g, rank, e: told.get(("g:" + g, rank), -1) < e + keep)  # as its records

    def drained(self) -> List[Msg]:
        """``drained`` to each connection, once a session, when a bounded stream has nothing left
        to make, ready, waiting, leased or revoked, at any connection: what is left is granted,
        and a grant comes back only with its holder's ``released`` or to its consumer's next
        session. A DataLoader worker ends its iteration on it, so the loader (in order) can take
        the batches the other workers were granted; it is sent nothing after it
        (``ClientRecord.takes``) (docs/delivery.md, "The protocol", rule 6)."""
        s, table = self.sched, self.ledger.table
        drained = (s.max_epochs is not None and s.next_epoch >= s.max_epochs and not s.queue and not s.running
                   and not table.ready_count() and not self.batcher.waiting()
                   and next(table.in_state(LEASED, REVOKED), None) is None)  # a lease comes back to anyone
        msgs: List[Msg] = []
        for ident, c in self.ledger.clients.items():
            if not drained and c.takes:  # one that ends on drained stays told
                c.told_drained = False
            elif not c.told_drained:
                c.told_drained = True
                msgs.append((ident, Drained()))
        return msgs

    # ------------------------------------------------------------------ the server's life
    def exit_due(self, now: float, waiting: bool = False) -> bool:
        """A bounded stream is over (``EpochScheduler.finished(told=True)``) and no reader was
        connected (nor ``waiting`` to be let in) for ``end_grace_s``: the server may exit."""
        if not self.sched.finished(told=True):
            self.ended, self._idle_since = False, None
            return False
        if not self.ended:
            log.info("all %d epoch(s) delivered; ending the stream (the server stays up %.0f s with no trainer "
                     "connected, for trainers that resume)", self.sched.max_epochs, self.end_grace_s)
            self.ended = True
        if self.ledger.clients or waiting:
            self._idle_since = None
            return False
        if self._idle_since is None:
            self._idle_since = now
        if now - self._idle_since >= self.end_grace_s:
            log.info("no trainer for %.0f s after the end of the stream; exiting", now - self._idle_since)
            return True
        return False

"""The client's book of the batches one connection received and the consumer has neither taken
nor given back (:class:`HeldBatches`): where each stands (leased, asked, granted), and the rules
that make taking and giving back exclusive (docs/delivery.md, "The client's book"). No socket,
no torch, no clock: the simulator and ``tests/test_lease_protocol.py`` drive it directly.
"""
from __future__ import annotations

import logging
import threading
from typing import Callable, Dict, List, Optional, Sequence, Set, Tuple

__all__ = ["HeldBatches", "GRANT_AHEAD", "strip_arrays", "BOOKKEEPING"]

log = logging.getLogger("v2v.client")

#: The entries of a batch item that are not arrays (kept when a batch is given back).
BOOKKEEPING = ("sample_ids", "params", "epoch", "batch_id", "receipt")


def strip_arrays(item: dict) -> None:
    """Free the arrays of a batch that will not be used (keeps its ids for bookkeeping)."""
    for k in [k for k in item if k not in BOOKKEEPING]:
        del item[k]


#: Batches a connection asks to be granted ahead of the consumer (its ``hold``s in flight plus
#: those granted and not yet taken): the grant's round trip overlaps the training steps, and a
#: trainer that dies for good takes at most this many granted batches with it.
GRANT_AHEAD = 2


class HeldBatches:
    """The batches a session received and the consumer has neither taken nor given back
    (batch id -> its queued item), and where each stands: *leased* (the server may take it
    back: a revoke releases it), *asked* (a ``hold`` is on its way: kept until the answer) or
    *granted* (the consumer's for good). The consumer takes a batch only once it is granted
    (:meth:`claim`); a batch is either taken or given back (revoked, refused, discarded,
    released), never both: ``lock`` (a condition the consumer waits on) makes the choice
    exclusive, and a batch given back loses its arrays at once.

    Args:
        endpoint: named in logs.
        ahead: batches asked or granted ahead of the consumer at most (``GRANT_AHEAD``).
    """

    def __init__(self, endpoint: str, ahead: int = GRANT_AHEAD):
        self.endpoint = endpoint
        self.lock = threading.Condition()
        self.current: Dict[int, dict] = {}
        self.asked: Set[int] = set()
        self.granted: Set[int] = set()
        self.ahead = max(1, ahead)
        self.discarded = 0  # batches given up when saying hello again
        self.drained = None  # the ``drained`` told to this book's session (a hello's discard forgets it)
        self.ends: List[object] = []  # epoch ends and DDP padding told to this session, not yet taken by the loop
        self.ends_upto = -1  # the newest epoch told complete to this session, or its hello's state completed

    def add(self, item: dict) -> None:
        """A received batch (a batch given back may come again: this copy is the live one, leased)."""
        with self.lock:
            bid = item["batch_id"]
            self.current.pop(bid, None)
            self.asked.discard(bid)
            self.granted.discard(bid)
            self.current[bid] = item

    def to_ask(self, item: Optional[dict] = None) -> List[int]:
        """Leased batches to ask the server for now, marked asked: ``item`` when it is still
        held and leased, then the oldest leased ones while fewer than ``ahead`` are asked or
        granted. The caller sends them in a ``hold``."""
        with self.lock:
            out = []
            if item is not None and self.current.get(item["batch_id"]) is item and self._leased(item["batch_id"]):
                out.append(item["batch_id"])
                self.asked.add(item["batch_id"])
            for bid in self.current:
                if len(self.asked) + len(self.granted) >= self.ahead:
                    break
                if self._leased(bid):
                    out.append(bid)
                    self.asked.add(bid)
            return out

    def _leased(self, bid: int) -> bool:
        return bid not in self.asked and bid not in self.granted

    def answer(self, granted: Sequence[int], refused: Sequence[int]) -> None:
        """The server's answer to our holds: ``granted`` batches may be taken, ``refused`` ones
        are no longer ours (given back here)."""
        with self.lock:
            for bid in granted:
                if bid in self.asked:
                    self.asked.discard(bid)
                    self.granted.add(bid)
            for bid in refused:
                if bid in self.asked:
                    self._pop_locked(bid)
            self.lock.notify_all()

    def still_asked(self, before: Set[int]) -> Tuple[Set[int], Set[int]]:
        """``(asked then and still unanswered, asked now)``: the I/O thread asks again for what
        stays unanswered a whole heartbeat (a grant lost when a connection broke and ZeroMQ
        reconnected behind it; the server answers a repeated ``hold`` the same)."""
        with self.lock:
            return before & self.asked, set(self.asked)

    def claim(self, item: dict, on_claim: Callable[[], object], wait: Callable[[], bool]) -> Tuple[bool, object]:
        """Take a received batch out for the consumer once it is granted, calling ``on_claim()``
        under the lock (the consumer records its samples there: a hello, which reads that
        record under the same lock, either precedes the claim and discards the batch, or
        follows it and names its samples). Waits for the answer while ``wait()`` is true.
        Returns ``(True, on_claim())``, or ``(False, None)`` when the batch was given back
        meanwhile (revoked before it was asked, refused, or discarded by a new hello)."""
        bid = item["batch_id"]
        with self.lock:
            while self.current.get(bid) is item and bid not in self.granted:
                if not wait():
                    return False, None
                self.lock.wait(0.1)
            if self.current.get(bid) is not item:
                return False, None
            del self.current[bid]
            self.granted.discard(bid)
            return True, on_claim()

    def give_back(self, item: dict) -> Optional[bool]:
        """Release a received batch unused (its arrays freed): None when it was no longer held,
        else whether the server may have granted it (asked or granted: the caller says
        ``released`` either way; a leased one goes back when the lease or the connection ends
        too, but saying so frees its slot at once)."""
        with self.lock:
            bid = item["batch_id"]
            if self.current.get(bid) is not item:
                return None
            maybe_granted = bid in self.asked or bid in self.granted
            self._pop_locked(bid)
        return maybe_granted

    def revoke(self, batch_ids) -> List[int]:
        """Release the leased batches the server asks back; returns those released (asked
        and granted ones stay: the server grants what it was asked for before it reads more)."""
        released = []
        with self.lock:
            for b in batch_ids:
                if isinstance(b, int) and b in self.current and self._leased(b):
                    self._pop_locked(b)
                    released.append(b)
        return released

    def discard(self, why: Optional[str], new_session: bool = False, completed: int = -1) -> List[int]:
        """Give up every batch held (the server re-sends or re-makes them), logging ``why`` (None:
        a connection closing, nothing to say); returns those that were asked or granted (to say
        ``released`` for when the connection closes). ``new_session``: a hello's (its state completed
        epoch ``completed``: the ends told to the new session come after it, :meth:`missed_end`), which
        also forgets the ``drained``, epoch ends and padding told to the session it ends
        (:meth:`ends_on`, :meth:`of_session`)."""
        with self.lock:
            if new_session:
                self.drained, self.ends_upto = None, completed
                self.ends.clear()
            return self._discard_locked(why)

    def told(self, drained):
        """The server told this session ``drained`` (a ``stream_messages.Drained``, returned), which a
        DataLoader worker may end on (:meth:`ends_on`)."""
        with self.lock:
            self.drained = drained
        return drained

    def told_end(self, item):
        """The server told this session an epoch's end or sent it DDP padding (``item``, returned,
        queued for the loop): the loop takes it only while the session lasts (:meth:`of_session`)."""
        with self.lock:
            self.ends.append(item)
        return item

    def missed_end(self, done, epochs: Optional[int] = None) -> bool:
        """True if this ``epoch_done`` (``stream_messages.EpochDone``) has a DDP count and comes after
        an end this session was not told (else it is noted as told), or this ``end`` (``End``, a DDP
        rank's of a stream of ``epochs``) comes before the last epoch's end. The server tells a rank's
        ends in order, an epoch with a count alone, and ``end`` after the last, so the end before it
        (with its padding copy) was lost in a cut ZeroMQ mended, which no hello follows: the session
        says hello again, its state reopens that epoch, and the server tells its end and count again
        (docs/delivery.md, "Ends of epochs")."""
        stream_end = getattr(done, "epoch", None) is None
        with self.lock:
            missed = self.ends_upto + 1
            if stream_end:
                if epochs is None or done.reason is not None or missed >= epochs:
                    return False
            elif done.batches is None or done.epoch <= missed:
                self.ends_upto = max(self.ends_upto, done.epoch)
                return False
        told = "the stream's end" if stream_end else f"the end of epoch {done.epoch}"
        log.warning("v2v stream %s: told %s and not the end of epoch %d before it (lost in a broken connection); "
                    "saying hello again", self.endpoint, told, missed)
        return True

    def of_session(self, item, then: Callable[[bool], object] = lambda current: None) -> bool:
        """The loop takes this epoch end or padding (:meth:`told_end`) off its queue: True if it was
        told to the current session; ``then(that)`` is called under the lock (the consumer records the
        end there: a hello, which reads that record under the same lock, comes wholly before or after).
        One told before the latest hello is about the session that hello ended: that hello's state
        said the epoch open, and the server tells its end and count again
        (a rank that paid padding from the old count, its epoch complete here while the server sent it
        batches of that epoch, gave them back for good or yielded more than its group; docs/delivery.md,
        "Ends of epochs")."""
        with self.lock:
            at = next((i for i, told in enumerate(self.ends) if told is item), None)
            current = at is not None
            if current:
                del self.ends[at]
            then(current)
            return current

    def ends_on(self, drained) -> bool:
        """A DataLoader worker's iteration ends on this ``drained``, taken off its queue: it was told
        to the current session, and nothing received is held. One told before the latest hello is
        about the session that hello ended: the server tells the new one itself (docs/delivery.md,
        "The protocol", rule 6)."""
        with self.lock:
            return drained is not None and drained is self.drained and not self.current

    def __len__(self) -> int:
        with self.lock:
            return len(self.current)

    def _pop_locked(self, bid: int) -> None:
        item = self.current.pop(bid)
        self.asked.discard(bid)
        self.granted.discard(bid)
        strip_arrays(item)
        self.lock.notify_all()

    def _discard_locked(self, why: Optional[str]) -> List[int]:
        if self.current and why is not None:
            log.warning("v2v stream %s: discarding %d batch(es) not yet used: %s", self.endpoint,
                        len(self.current), why)
        ours = sorted(self.asked | self.granted)
        for item in self.current.values():
            strip_arrays(item)
        self.discarded += len(self.current) if why is not None else 0
        self.current.clear()
        self.asked.clear()
        self.granted.clear()
        self.lock.notify_all()
        return ours

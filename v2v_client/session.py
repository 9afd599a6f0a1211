"""The client's side of the protocol with one server, without a socket or torch: a server
message in, items for the consumer and replies for the server out.

:class:`ServerSession` holds what one connection knows of its session with a server: the
hello it last said (and whether the welcome came), the server's stream info, the batches
received and not yet taken or given back, and whether batches come through the server's
shared memory and how they are compressed. The I/O thread of
:class:`~v2v_client.connection.Connection` owns one: it sends ``hello()``, feeds each message
to ``on_message()``, and sends the ``replies()``. The consumer claims the queued batches
from its :class:`HeldBatches` (``held``). It imports numpy, ``v2v_wire`` and ``handoff`` only (no torch, no socket),
so a host with ``pip install .`` (no torch) reads a stream through it as numpy arrays.
"""
from __future__ import annotations

import logging
import queue
import threading
from typing import Callable, Dict, List, Optional, Sequence, Set, Tuple

from v2v_wire.codecs import decode_batch_arrays
from v2v_wire.messages import Hold, Released
from v2v_wire.outputs import ARRAYS
from v2v_wire import stream_messages as sm
from v2v_wire.protocol import MAX_BATCH_BYTES, MAX_CLIENT_MSG, ProtocolError, output_of, pack, unpack
from v2v_wire.stream_messages import stream_message

from .handoff import ShmReader, check_shm_dir, shm_dir_problem

__all__ = ["ServerSession", "HeldBatches", "GRANT_AHEAD", "StreamError", "StreamTimeout", "EpochDone", "Drained", "LoopAbandoned", "ServerPadding",
           "MAX_SERVER_MSG", "strip_arrays"]

log = logging.getLogger("v2v.client")

#: Largest message accepted from the server, bytes (ZMQ_MAXMSGSIZE).
MAX_SERVER_MSG = MAX_BATCH_BYTES

#: The entries of a batch item that are not arrays (kept when a batch is given back).
BOOKKEEPING = ("sample_ids", "params", "epoch", "batch_id", "receipt")

#: ``convert(arrays, flow_size, flow_dtype)``: a batch's wire arrays (name -> numpy array) as
#: the consumer's arrays (``tensors.batch_to_torch`` with the stream's options, for the dataset).
Convert = Callable[[Dict, Optional[Tuple[int, int]], str], Dict]


class StreamError(RuntimeError):
    """The server sent an error, broke the protocol, or went silent (the message says which)."""


class StreamTimeout(StreamError, TimeoutError):
    """No message from the server within ``timeout_s``."""


class ServerPadding:
    """A DDP padding batch the server sent (``item``: not leased, never acknowledged)."""

    def __init__(self, item: dict):
        self.item = item


class Drained:
    """The server has nothing left to send this connection unless a batch held elsewhere comes back."""


class LoopAbandoned:
    """A DataLoader worker's iteration is over: the training loop left it (``break``, a new
    ``for``) and the loader discarded what this worker had queued, so no receipt will come for
    the batches still held; the iteration ends and they go back to the server."""


class EpochDone:
    """The server declared ``epoch`` complete; ``batches``: with DDP, the batches every rank of
    the group must yield in it (None without DDP)."""

    def __init__(self, epoch: int, batches: Optional[int] = None):
        self.epoch = epoch
        self.batches = batches


def strip_arrays(item: dict) -> None:
    """Free the arrays of a batch that will not be used (keeps its ids for bookkeeping)."""
    for k in [k for k in item if k not in BOOKKEEPING]:
        del item[k]


def _as_received(arrays: Dict, flow_size, flow_dtype) -> Dict:
    return dict(arrays)


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

    def discard(self, why: Optional[str]) -> List[int]:
        """Give up every batch held (the server re-sends or re-makes them), logging ``why`` (None:
        a connection closing, nothing to say); returns those that were asked or granted (to say
        ``released`` for when the connection closes)."""
        with self.lock:
            return self._discard_locked(why)

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


class ServerSession:
    """One connection's session with one server: protocol state, no socket, no torch.

    Args:
        endpoint: the server's endpoint (named in errors and logs).
        outputs: the outputs the hello asks for; a batch lacking one is a protocol error.
        hello_header: makes the hello message (dict: outputs, credits, consumer, resume state);
            called for every (re-)hello.
        welcomed: given the server's stream info; returns why the consumer refuses this
            server (the stream then ends with a :class:`StreamError`), or None.
        convert: a batch's wire arrays to the consumer's (``Convert``); None keeps the numpy
            arrays (views of the received message).
        raw: whether ``convert`` keeps the received memory (then a shared-memory batch is
            copied out of the server's buffer before ``convert``).
        shm: ask for batches through the server's shared memory (same host).
        keep: private buffers a shared-memory reader keeps (the credits plus a few).
        compression: the compression asked for ("none", "lz4", "zstd"); ``compression_auto``:
            chosen by default, so a server lacking the codec is asked again without it.

    Items queued on ``items`` for the consumer: batch dicts (arrays as ``convert`` makes them,
    ``sample_ids``, ``params``, ``epoch``, ``batch_id``), :class:`ServerPadding`,
    :class:`EpochDone`, :class:`Drained`, ``StopIteration`` (the end) and :class:`StreamError`.
    """

    def __init__(self, endpoint: str, outputs: Sequence[str], hello_header: Callable[[], dict], *,
                 welcomed: Callable[[dict], Optional[str]] = lambda info: None, convert: Optional[Convert] = None,
                 raw: bool = False, shm: bool = False, keep: int = 4, compression: str = "none",
                 compression_auto: bool = False):
        self.endpoint = endpoint
        self.outputs = tuple(outputs)
        self._hello_header, self._welcomed = hello_header, welcomed
        self._convert = convert or _as_received
        self._copy_shm = raw or convert is None  # the items keep the memory they are given
        self.items: "queue.Queue" = queue.Queue()
        self.info: Optional[dict] = None
        self.held = HeldBatches(endpoint)
        self._replies: List[bytes] = []
        self._hello_seq = 0
        self._awaiting: Optional[int] = None  # id of our last hello until its welcome arrives
        self._torn_ids: Dict[int, int] = {}  # shared-memory batches found gone, by batch id
        self.shm = shm
        self._shm = ShmReader(keep=keep) if shm else None
        self.compression, self._compression_auto = compression, compression_auto

    # -- the I/O thread's side --

    def hello(self, new_socket: bool = False) -> bytes:
        """A (re-)hello: whatever this session still holds is discarded first, since the server
        takes the resume state as the truth and re-sends the rest. On a ``new_socket`` no
        message of an older session can arrive, so no welcome is awaited.

        Raises:
            StreamError: the hello (its resume state) is larger than the server takes.
        """
        with self.held.lock:  # the resume state and the discard as one step (``HeldBatches.claim``)
            self.held.discard("saying hello again")
            header = self._hello_header()
        self._hello_seq += 1
        self._awaiting = self._hello_seq
        h = dict(header, hello_id=self._hello_seq)
        if self.shm:
            h["shm"] = True
        if self.compression != "none":
            h["compression"] = self.compression
        data = pack(h)
        limit = (self.info or {}).get("max_hello_bytes", MAX_CLIENT_MSG)
        if len(data) > limit:
            n = sum(len(v) for v in h.get("resume", {}).get("delivered", {}).values())
            raise StreamError(f"the resume state is too large to send: {len(data)} bytes, the server at "
                              f"{self.endpoint} takes at most {limit} ({n} characters of sample ids in open epochs). "
                              f"Checkpoint after the epoch completes, or split the corpus into shards")
        if new_socket:
            self._awaiting = None
        return data

    def replies(self) -> List[bytes]:
        """The messages the last ``on_message`` calls owe the server, in order (then forgotten)."""
        out, self._replies = self._replies, []
        return out

    def on_message(self, frames) -> Optional[str]:
        """Handle one server message (its frames: header, then array frames), read at this
        edge as its typed message (``v2v_wire.stream_messages``); "over" when the stream has
        ended or failed (the reason is queued on ``items``; a malformed message names the
        field), "lost" when the server is shutting down, else None."""
        try:
            m = stream_message(unpack(frames[0]))
            rehello = isinstance(m, sm.ServerError) and m.code in ("dropped", "unknown_client")
            if self._awaiting is not None and (isinstance(m, (sm.Batch, sm.Revoke, sm.Granted)) or rehello):
                # sent before the server read our latest hello: about a session that is over
                return None
            if isinstance(m, sm.Batch):
                self._on_batch(m, frames)
            elif isinstance(m, sm.Welcome):
                self._on_welcome(m)
                refusal = self._welcomed(self.info)
                if refusal is not None:
                    self.items.put(StreamError(f"v2v server at {self.endpoint}: {refusal}"))
                    return "over"
            elif isinstance(m, sm.Revoke):
                self._on_revoke(m)
            elif isinstance(m, sm.Granted):
                self.held.answer(m.batch_ids, m.refused)
                self._ask()
            elif isinstance(m, sm.EpochDone):
                self.items.put(EpochDone(m.epoch, m.batches))
            elif isinstance(m, sm.Drained):
                self.items.put(Drained())
            elif isinstance(m, sm.End):
                self.items.put(StopIteration("end of stream" if m.reason is None else m.reason))
                return "over"
            elif isinstance(m, sm.Shutdown):
                return "lost"
            elif isinstance(m, sm.ServerError) and m.code == "compression" and self._compression_auto:
                # the server lacks the codec we picked by default: take the arrays as they are
                log.warning("v2v server at %s: %s; receiving arrays uncompressed", self.endpoint, m.message)
                self.compression = "none"
                self._replies.append(self.hello())
            elif rehello:
                # dropped for silence or an unanswered revoke, or the server restarted behind our socket:
                # whatever we hold goes elsewhere, so hand none of it on; introduce ourselves again
                log.warning("v2v server at %s: %s; saying hello again with the resume state", self.endpoint,
                            m.message)
                self._replies.append(self.hello())
            elif isinstance(m, sm.ServerError):
                self.items.put(StreamError(f"v2v server at {self.endpoint}: {m.message}"))
                return "over"
        except (ProtocolError, KeyError, TypeError, ValueError) as e:
            self.items.put(StreamError(f"bad message from the v2v server at {self.endpoint}: {e}"))
            return "over"
        return None

    def close(self) -> None:
        """Unmap the server's batch files (a shared-memory session)."""
        if self._shm is not None:
            self._shm.close()

    # -- messages --

    def _on_batch(self, m: sm.Batch, frames) -> None:
        """A batch: its arrays (from the frames, or from the server's batch file on the same
        host) checked against the header, converted, and queued for the consumer.

        Raises:
            ProtocolError: arrays missing, of the wrong length, or a hand-off not asked for.
        """
        ref = None if m.shm is None else {"shm": m.shm, "arrays": list(m.arrays)}  # handoff.ShmReader's header
        if ref is not None:  # same host: the arrays are in the server's batch file
            if self._shm is None or len(frames) != 1:
                raise ProtocolError("a shared-memory batch this client did not ask for")
            arrays = self._shm.read(ref, copy=self._copy_shm)
            if arrays is None:
                return self._torn(m.batch_id)
        else:
            arrays = decode_batch_arrays(list(m.arrays), frames[1:], MAX_SERVER_MSG)
        missing = [o for o in self.outputs if o not in {output_of(k) for k in arrays}]
        if missing:
            raise ProtocolError(f"batch {m.batch_id} lacks requested outputs {missing}")
        if any(a.shape[:1] != (len(m.sample_ids),) for a in arrays.values()):
            raise ProtocolError(f"batch {m.batch_id}: sample ids do not match the arrays")
        info = self.info or {}
        crop = info.get("crop_size")
        item = self._convert(arrays, (crop, crop) if isinstance(crop, int) and crop > 0 else None,
                             info.get("flow_dtype", ARRAYS["flow"].dtypes[0]))
        if ref is not None and not self._copy_shm:
            del arrays  # converted from the mapping: check it still held this batch
            if not self._shm.valid(ref):
                return self._torn(m.batch_id)
        item["sample_ids"] = list(m.sample_ids)
        item["params"] = list(m.params)
        item["epoch"] = m.epoch
        item["batch_id"] = m.batch_id
        if m.padding:  # DDP padding from the server: not leased, never acknowledged
            self.items.put(ServerPadding(item))
            return None
        self.held.add(item)
        self.items.put(item)
        self._ask()
        return None

    def _ask(self) -> None:
        """Ask for the grants the consumer will need next (``HeldBatches.to_ask``)."""
        ids = self.held.to_ask()
        if ids:
            self._replies.append(pack(Hold(tuple(ids)).to_wire()))

    def _on_welcome(self, m: sm.Welcome) -> None:
        """The server's answer to our hello: its stream info, and whether we can read its
        batch directory (else we ask again without the same-host hand-off)."""
        if m.hello_id == self._awaiting:
            self._awaiting = None
        self.info = m.info
        if self._shm is not None:
            d = self.info.get("shm_dir")
            why = None if d is None else shm_dir_problem(check_shm_dir(d))
            if why is not None:
                self._socket_instead(f"the server's batch directory {d} {why}")
            else:
                self._shm.set_dir(d)

    def _socket_instead(self, why: str) -> None:
        """Stop reading batches through the server's shared memory: say hello again without it."""
        log.warning("v2v stream %s: %s; asking for batches over the socket", self.endpoint, why)
        self.shm, self._shm = False, None
        self._replies.append(self.hello())

    def _on_revoke(self, m: sm.Revoke) -> None:
        """Batches the server asks back: those still held (not yet handed to the consumer) are
        released, their arrays freed at once."""
        released = self.held.revoke(list(m.batch_ids))
        if released:
            self._replies.append(pack(Released(tuple(released)).to_wire()))

    def _torn(self, bid: int) -> None:
        """A shared-memory batch (id ``bid``) whose buffer the server refilled before we copied
        it: the batch was acknowledged (or dropped) already, so it is not ours; give it back.
        The same batch torn twice means its file is gone while the server still holds it (the
        directory was removed under it): read over the socket from now on, so the batch comes
        as frames instead of the same reference again."""
        self._torn_ids[bid] = self._torn_ids.get(bid, 0) + 1
        if self._torn_ids[bid] >= 2:
            self._socket_instead(f"batch {bid} is gone from the server's shared memory again")
            return None
        log.warning("v2v stream %s: batch %s was gone from the server's shared memory before it was read "
                    "(this process stalled?); giving it back", self.endpoint, bid)
        if bid >= 0:
            self._replies.append(pack(Released((bid,)).to_wire()))
        return None

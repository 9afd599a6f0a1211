"""The client's side of the protocol with one server, without a socket, a thread of its own, a
clock of its own or torch: server messages, the consumer's steps, the loader's receipts and the
time in; every message the client sends out, typed (``v2v_wire.messages``).

:class:`ServerSession` holds what one connection knows of its session with a server: the
hello it last said (and whether the welcome came), the server's stream info, the batches
received and not yet taken or given back (:class:`~v2v_client.held.HeldBatches`), the reader's
record (:class:`~v2v_client.resume.ResumeState`), and in a DataLoader worker the loader's
iteration. It decides every outgoing message: the hello, ``hold`` (and asking again for what
stays unanswered), ``ack`` (on a claim, or on the loop's receipt in a DataLoader worker),
``released`` (revoked, refused, torn, given back, on close), ``heartbeat`` and ``bye``. The I/O
thread of :class:`~v2v_client.connection.Connection` only moves the bytes: it feeds
``on_message``, ``on_loader`` and ``tick`` and sends what ``outgoing()`` returns. The rules are
written once in docs/delivery.md ("The protocol"). Numpy, ``v2v_wire`` and ``handoff`` only, so
a host with ``pip install .`` (no torch) reads a stream through it as numpy arrays.
"""
from __future__ import annotations

import collections
import logging
import queue
import threading
from typing import Callable, Dict, List, Optional, Tuple, Union

from v2v_wire import stream_messages as sm
from v2v_wire.codecs import decode_batch_arrays
from v2v_wire.messages import Ack, Bye, Heartbeat, Hello, Hold, Released
from v2v_wire.outputs import ARRAYS
from v2v_wire.protocol import MAX_BATCH_BYTES, MAX_CLIENT_MSG, ProtocolError, output_of, pack, unpack
from v2v_wire.stream_messages import stream_message

from .handoff import ShmReader, check_shm_dir, shm_dir_problem
from .held import BOOKKEEPING, GRANT_AHEAD, HeldBatches, strip_arrays
from .receipts import Abandon, Receipt
from .resume import ResumeState

__all__ = ["ServerSession", "HeldBatches", "GRANT_AHEAD", "StreamError", "StreamTimeout", "LoopAbandoned",
           "ServerPadding", "MAX_SERVER_MSG", "strip_arrays", "BOOKKEEPING", "Outgoing"]

log = logging.getLogger("v2v.client")

#: Largest message accepted from the server, bytes (ZMQ_MAXMSGSIZE).
MAX_SERVER_MSG = MAX_BATCH_BYTES

#: ``convert(arrays, flow_size, flow_dtype)``: a batch's wire arrays (name -> numpy array) as
#: the consumer's arrays (``tensors.batch_to_torch`` with the stream's options, for the dataset).
Convert = Callable[[Dict, Optional[Tuple[int, int]], str], Dict]

#: What a session sends: the client -> server messages of ``v2v_wire.messages``.
Outgoing = Union[Hello, Hold, Ack, Released, Heartbeat, Bye]


class StreamError(RuntimeError):
    """The server sent an error, broke the protocol, or went silent (the message says which)."""


class StreamTimeout(StreamError, TimeoutError):
    """No message from the server within ``timeout_s``."""


class ServerPadding:
    """A DDP padding batch the server sent (``item``: not leased, never acknowledged)."""

    def __init__(self, item: dict):
        self.item = item


class LoopAbandoned:
    """A DataLoader worker's iteration is over: the training loop left it (``break``, a new
    ``for``) and the loader discarded what this worker had queued, so no receipt will come for
    the batches still held; the iteration ends and they go back to the server."""


def _as_received(arrays: Dict, flow_size, flow_dtype) -> Dict:
    return dict(arrays)


class BatchReader:
    """How one session reads a batch's arrays: from its frames (decompressed), or from the server's
    batch file on the same host (``handoff.ShmReader``), checked against the header and converted
    for the consumer.

    Args:
        outputs: the outputs asked for; a batch lacking one is a protocol error.
        convert: ``Convert`` (None keeps the numpy arrays: views of the received message).
        copy: whether ``convert`` keeps the memory it is given (a shared-memory batch is then
            copied out of the server's buffer first).
        shm: read batches through the server's shared memory; ``keep``: private buffers kept.
    """

    def __init__(self, outputs: Tuple[str, ...], convert: Optional[Convert], copy: bool, shm: bool, keep: int):
        self.outputs = outputs
        self._convert = convert or _as_received
        self._copy = copy or convert is None
        self.shm: Optional[ShmReader] = ShmReader(keep=keep) if shm else None
        self._torn: Dict[int, int] = {}  # shared-memory batches found gone, by batch id

    def read(self, m: sm.Batch, frames, info: dict) -> Optional[dict]:
        """The batch's item (arrays, ``sample_ids``, ``params``, ``epoch``, ``batch_id``), or None
        when its shared-memory buffer was refilled before it was read (:meth:`torn` counts it).

        Raises:
            ProtocolError: arrays missing, of the wrong length, or a hand-off not asked for.
        """
        ref = None if m.shm is None else {"shm": m.shm, "arrays": list(m.arrays)}  # handoff.ShmReader's header
        if ref is not None:  # same host: the arrays are in the server's batch file
            if self.shm is None or len(frames) != 1:
                raise ProtocolError("a shared-memory batch this client did not ask for")
            arrays = self.shm.read(ref, copy=self._copy)
            if arrays is None:
                return None
        else:
            arrays = decode_batch_arrays(list(m.arrays), frames[1:], MAX_SERVER_MSG)
        missing = [o for o in self.outputs if o not in {output_of(k) for k in arrays}]
        if missing:
            raise ProtocolError(f"batch {m.batch_id} lacks requested outputs {missing}")
        if any(a.shape[:1] != (len(m.sample_ids),) for a in arrays.values()):
            raise ProtocolError(f"batch {m.batch_id}: sample ids do not match the arrays")
        crop = info.get("crop_size")
        item = self._convert(arrays, (crop, crop) if isinstance(crop, int) and crop > 0 else None,
                             info.get("flow_dtype", ARRAYS["flow"].dtypes[0]))
        if ref is not None and not self._copy:
            del arrays  # converted from the mapping: check it still held this batch
            if not self.shm.valid(ref):
                return None
        item.update(sample_ids=list(m.sample_ids), params=list(m.params), epoch=m.epoch, batch_id=m.batch_id)
        return item

    def torn(self, bid: int) -> int:
        """Batch ``bid`` was found gone from the shared memory: how often so far."""
        self._torn[bid] = self._torn.get(bid, 0) + 1
        return self._torn[bid]

    def close(self) -> None:
        if self.shm is not None:
            self.shm.close()
            self.shm = None


class Unread:
    """What a connection said of its granted batches (``Ack`` or ``Released``, by batch id) and does
    not know the server read yet (docs/delivery.md, "Messages"): named in each heartbeat's
    ``hold``, forgotten once the server answers ``refused`` (it holds the batch for the connection
    no more, and the ``hold`` came after what was said on the one connection), said again while
    it answers ``granted`` (after a new hello too: its state settled them, and the server answers
    ``refused``). Thread-safe: the consumer's thread says, the I/O thread checks."""

    def __init__(self):
        self._said: Dict[int, type] = {}
        self._lock = threading.Lock()

    def say(self, kind: type, batch_ids: Tuple[int, ...], granted: bool = True):
        """``kind(batch_ids)``, remembered until read if the batches are (or may be) ``granted``."""
        with self._lock:
            self._said.update(dict.fromkeys(batch_ids if granted else (), kind))
        return kind(batch_ids)

    def ids(self) -> set:
        with self._lock:
            return set(self._said)

    def forget(self, bid: int) -> None:
        """Forget batch ``bid``: it was sent to us again, and is the book's now."""
        with self._lock:
            self._said.pop(bid, None)

    def answer(self, granted, refused, book: HeldBatches) -> list:
        """The server's answer to a ``hold``: what to say again; the rest is the ``book``'s
        (``HeldBatches.answer``)."""
        again: Dict[type, List[int]] = {}
        with self._lock:
            for bid in refused:
                self._said.pop(bid, None)
            for bid in granted:
                if bid in self._said:
                    again.setdefault(self._said[bid], []).append(bid)
        book.answer(granted, refused)
        return [kind(tuple(ids)) for kind, ids in again.items()]


#: What the server sent before it read our latest hello is about the session that hello ended: dropped.
OF_AN_ENDED_SESSION = (sm.Batch, sm.Revoke, sm.Granted, sm.Drained, sm.EpochDone, sm.End)


class ServerSession:
    """One connection's session with one server: protocol state, no socket, no thread, no torch.

    Args:
        endpoint: the server's endpoint (named in errors and logs).
        options: the stream's ``options.StreamOptions`` (outputs, credits, DDP position,
            heartbeat, same-host hand-off and compression wanted).
        record: the reader's ``resume.ResumeState``: its resume state goes in every hello, the
            welcome's recipe is checked against it, claims and receipts are recorded in it.
        consumer: the id the hello names the reader by.
        convert: a batch's wire arrays to the consumer's (``Convert``); None keeps the numpy
            arrays (views of the received message).
        ends_on_drained, iteration: a ``StreamLoader`` DataLoader worker: its iteration ends on
            ``drained``; the loader's iteration it serves (``receipts.Abandon`` names it).
        instance: the reader process's token (the dataset's): the server lets one instance read
            a consumer at a time (docs/delivery.md, "Who may say hello").
        welcomed: given the server's stream info, why the reader refuses this server (the stream
            ends with a :class:`StreamError`), or None; default: the record's recipe check.

    Items queued on ``items`` for the consumer: batch dicts (arrays as ``convert`` makes them, ``sample_ids``,
    ``params``, ``epoch``, ``batch_id``), :class:`ServerPadding` and ``stream_messages.EpochDone`` (taken only
    while their session lasts: ``HeldBatches.of_session``), ``Drained``, :class:`LoopAbandoned`, ``StopIteration``
    (the end) and :class:`StreamError`.
    """

    def __init__(self, endpoint: str, options, record: ResumeState, consumer: str, *,
                 convert: Optional[Convert] = None, ends_on_drained: bool = False, iteration: int = 0,
                 instance: str = "", welcomed: Optional[Callable[[dict], Optional[str]]] = None):
        self.endpoint, self.options, self.record, self.consumer = endpoint, options, record, consumer
        self.instance, self.outputs = instance, tuple(options.outputs)
        self._welcomed = welcomed or (lambda info: record.check_recipe(info.get("recipe")))
        self.items: "queue.Queue" = queue.Queue()
        self.info: Optional[dict] = None
        self.held = HeldBatches(endpoint)
        self._out: "collections.deque[Outgoing]" = collections.deque()  # appended by both threads, in order
        self._hello_seq, self._awaiting = 0, None  # our last hello's id; it again until its welcome arrives
        self.reader = BatchReader(self.outputs, convert, options.raw, options.wants_shm(endpoint), options.credits + 2)
        self.compression, self._compression_auto = options.compression_for(endpoint)
        self.ends_on_drained, self.iteration = ends_on_drained, iteration
        self.abandoned, self._next_beat = False, None  # the loader left this iteration; the next heartbeat's time
        self._asked: set = set()  # holds unanswered at the last heartbeat
        self.unread = Unread()  # acks and releases of granted batches the server may not have read

    # ------------------------------------------------------------------ what goes out
    def outgoing(self) -> List[Outgoing]:
        """The messages decided since the last call, in order (then forgotten)."""
        out = []
        while self._out:
            out.append(self._out.popleft())
        return out

    def hello(self, new_socket: bool = False, at: float = 0.0) -> None:
        """Say hello (again), numbered above the last and ``at`` (the host's monotonic clock, s) in us:
        the server refuses a hello of this reader older than one it let in. What the session holds
        is discarded first (re-sent from the resume state); a ``new_socket`` awaits no welcome.

        Raises:
            StreamError: the hello (its resume state) is larger than the server takes.
        """
        o = self.options
        with self.held.lock:  # the resume state and the discard as one step (``HeldBatches.claim``)
            resume = self.record.hello_resume()
            self.held.discard("saying hello again", new_session=True, completed=resume.completed_epoch)
        self._hello_seq = max(self._hello_seq + 1, int(at * 1e6))
        self._awaiting = None if new_socket else self._hello_seq
        h = Hello(self.outputs, o.credits, self.consumer, resume, o.group if o.world_size > 1 else None, o.rank,
                  o.world_size, self._hello_seq, self.reader.shm is not None, self.compression, self.ends_on_drained,
                  self.instance)
        size = len(pack(h.to_wire()))
        limit = (self.info or {}).get("max_hello_bytes", MAX_CLIENT_MSG)
        if size > limit:
            n = sum(len(s) for ids in resume.delivered.values() for s in ids)
            raise StreamError(f"the resume state is too large to send: {size} bytes, the server at "
                              f"{self.endpoint} takes at most {limit} ({n} characters of sample ids in open epochs). "
                              f"Checkpoint after the epoch completes, or split the corpus into shards")
        self._out.append(h)

    def tick(self, now: float) -> None:
        """Time passed (seconds, the caller's clock): a heartbeat naming our latest hello every ``heartbeat_s``,
        and with it a ``hold`` again for every grant asked for and unanswered a whole heartbeat (lost
        when a connection broke behind ZeroMQ's reconnect; the server answers a repeated hold the same)."""
        if self._next_beat is None:
            self._next_beat = now + self.options.heartbeat_s
        if now < self._next_beat:
            return
        self._next_beat = now + self.options.heartbeat_s
        self._out.append(Heartbeat(self._hello_seq))
        again, self._asked = self.held.still_asked(self._asked)
        again |= self.unread.ids()  # and what we said of granted batches, until it is known read
        if again:
            self._out.append(Hold(tuple(sorted(again))))

    def closing(self, unreceived: bool = False) -> List[Outgoing]:
        """The last messages of a connection that closes: the batches asked for or granted and
        not taken go back (``released``; in a DataLoader worker whose iteration was abandoned,
        or with ``unreceived``, also those waiting in the loader's queues), then ``bye``. The
        book is empty after it: a consumer waiting for a grant wakes."""
        ours = self.held.discard(None)
        if self.ends_on_drained and (self.abandoned or unreceived):
            ours += self.record.pipeline_ids()  # granted, queued in the loader, dropped by it
        if ours:
            self._out.append(Released(tuple(ours)))
        self._out.append(Bye())
        return self.outgoing()

    # ------------------------------------------------------------------ the consumer's steps
    def take(self, item: dict, on_claim: Callable[[], object], wait: Callable[[], bool] = lambda: False,
             ack: bool = True) -> Tuple[bool, object]:
        """Claim a received batch for the training loop once granted (``HeldBatches.claim``, with
        ``on_claim``; its ``hold`` is asked for first if it was not), waiting while ``wait()``,
        and ``ack`` it (a DataLoader worker acks on the loop's receipt instead); then ask for the
        grants the consumer needs next. Returns ``(True, on_claim())``, or ``(False, None)``
        when it was given back meanwhile or is not granted yet and ``wait()`` said stop."""
        self._ask(item)
        ok, result = self.held.claim(item, on_claim, wait)
        if ok and ack:
            self._out.append(self.unread.say(Ack, (item["batch_id"],)))
        self._ask()
        return ok, result

    def give_back(self, item: dict) -> None:
        """Return a received batch unused (e.g. of an epoch this reader already completed): out
        of the book first, then ``released`` (rule 4 of docs/delivery.md)."""
        maybe_granted = self.held.give_back(item)
        if maybe_granted is not None:
            self._out.append(self.unread.say(Released, (item["batch_id"],), maybe_granted))

    def ack(self, batch_ids) -> None:
        """Acknowledge batches this connection took (the loop received them, or they held nothing new for it)."""
        if batch_ids:
            self._out.append(self.unread.say(Ack, tuple(batch_ids)))

    def _ask(self, item: Optional[dict] = None) -> None:
        ids = self.held.to_ask(item)
        if ids:
            self._out.append(Hold(tuple(ids)))

    # ------------------------------------------------------------------ the loader (a DataLoader worker)
    def on_loader(self, msg: Union[Receipt, Abandon]) -> None:
        """What ``StreamLoader`` in the main process said: the loop received these batches
        (recorded, acknowledged), or it left this iteration (:class:`LoopAbandoned` for the
        consumer: no receipt will come, what is held goes back at close)."""
        if isinstance(msg, Abandon):
            if msg.iteration == self.iteration and not self.abandoned:
                self.abandoned = True
                self.items.put(LoopAbandoned())
            return
        self.ack(self.record.received(msg.batch_ids))

    def lingering_done(self) -> bool:
        """A worker's connection kept open for the batches in the loader's queues may close:
        every one was received, or the loop left."""
        return self.abandoned or not self.record.pipeline_ids()

    # ------------------------------------------------------------------ what comes in
    def on_message(self, frames) -> Optional[str]:
        """Handle one server message (its frames: header, then array frames), read at this
        edge as its typed message (``v2v_wire.stream_messages``); "over" when the stream has
        ended or failed (the reason is queued on ``items``; a malformed message names the
        field), "lost" when the server is shutting down, else None."""
        try:
            m = stream_message(unpack(frames[0]))
            rehello = isinstance(m, sm.ServerError) and m.code in ("dropped", "unknown_client")
            if self._awaiting is not None and (isinstance(m, OF_AN_ENDED_SESSION)
                                               or (rehello and m.hello_id != self._awaiting)):
                return None  # said before the server read our latest hello (docs/delivery.md, rule 5)
            if isinstance(m, sm.Batch):
                self._on_batch(m, frames)
            elif isinstance(m, sm.Welcome):
                return self._on_welcome(m)
            elif isinstance(m, sm.Revoke):
                released = self.held.revoke(list(m.batch_ids))  # leased ones go back, arrays freed
                if released:
                    self._out.append(Released(tuple(released)))
            elif isinstance(m, sm.Granted):  # also an answer about what we said (``Unread``)
                self._out.extend(self.unread.answer(m.batch_ids, m.refused, self.held))
                self._ask()
            elif isinstance(m, (sm.EpochDone, sm.End)) and self.held.missed_end(
                    m, (self.info or {}).get("epochs") if self.options.world_size > 1 else None):
                self.hello()  # an end before it was lost: told again to the new session
            elif isinstance(m, sm.EpochDone):
                self.items.put(self.held.told_end(m))
            elif isinstance(m, sm.Drained):
                self.items.put(self.held.told(m) if self.ends_on_drained else m)
            elif isinstance(m, sm.End):
                self.items.put(StopIteration("end of stream" if m.reason is None else m.reason))
                return "over"
            elif isinstance(m, sm.Shutdown):
                return "lost"
            elif isinstance(m, sm.ServerError):
                return self._on_error(m, rehello)
        except (ProtocolError, KeyError, TypeError, ValueError) as e:
            self.items.put(StreamError(f"bad message from the v2v server at {self.endpoint}: {e}"))
            return "over"
        return None

    def _on_error(self, m: sm.ServerError, rehello: bool) -> Optional[str]:
        if m.code == "compression" and self._compression_auto:
            # the server lacks the codec we picked by default: take the arrays as they are
            log.warning("v2v server at %s: %s; receiving arrays uncompressed", self.endpoint, m.message)
            self.compression = "none"
            self.hello()
            return None
        if rehello:
            # dropped for silence or an unanswered revoke, or the server restarted behind our socket:
            # whatever we hold goes elsewhere, so hand none of it on; introduce ourselves again
            log.warning("v2v server at %s: %s; saying hello again with the resume state", self.endpoint, m.message)
            self.hello()
            return None
        self.items.put(StreamError(f"v2v server at {self.endpoint}: {m.message}"))
        return "over"

    def close(self) -> None:
        """Unmap the server's batch files (a shared-memory session)."""
        self.reader.close()

    def _on_batch(self, m: sm.Batch, frames) -> None:
        """A batch: read (``BatchReader.read``), queued for the consumer and asked for; DDP
        padding (not leased, never acknowledged) is handed on as :class:`ServerPadding`."""
        item = self.reader.read(m, frames, self.info or {})
        if item is None:
            return self._torn(m.batch_id)
        if m.padding:
            self.items.put(self.held.told_end(ServerPadding(item)))
            return None
        self.unread.forget(m.batch_id)  # given back, then sent to us again: the book's from now on
        self.held.add(item)
        self.items.put(item)
        self._ask()

    def _on_welcome(self, m: sm.Welcome) -> Optional[str]:
        """The server's answer to our hello: its stream info, checked by ``welcomed``, and
        whether we can read its batch directory (else we ask again without the same-host
        hand-off). "over" when the reader refuses this server."""
        if m.hello_id == self._awaiting:
            self._awaiting = None
        self.info = m.info
        self.record.welcomed(self.info.get("server"))
        refusal = self._welcomed(self.info)
        if refusal is not None:
            self.items.put(StreamError(f"v2v server at {self.endpoint}: {refusal}"))
            return "over"
        if self.reader.shm is not None:
            d = self.info.get("shm_dir")
            why = None if d is None else shm_dir_problem(check_shm_dir(d))
            if why is not None:
                self._socket_instead(f"the server's batch directory {d} {why}")
            else:
                self.reader.shm.set_dir(d)
        return None

    def _socket_instead(self, why: str) -> None:
        """Stop reading batches through the server's shared memory: say hello again without it."""
        log.warning("v2v stream %s: %s; asking for batches over the socket", self.endpoint, why)
        self.reader.close()
        self.hello()

    def _torn(self, bid: int) -> None:
        """A shared-memory batch (id ``bid``) whose buffer the server refilled before we copied
        it: the batch was acknowledged (or dropped) already, so it is not ours; give it back.
        The same batch torn twice means its file is gone while the server still holds it (the
        directory was removed under it): read over the socket from now on, so the batch comes
        as frames instead of the same reference again."""
        if self.reader.torn(bid) >= 2:
            self._socket_instead(f"batch {bid} is gone from the server's shared memory again")
            return None
        log.warning("v2v stream %s: batch %s was gone from the server's shared memory before it was read "
                    "(this process stalled?); giving it back", self.endpoint, bid)
        if bid >= 0:
            self._out.append(Released((bid,)))

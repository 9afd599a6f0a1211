"""One connection to one ``v2v-serve``: a DEALER socket served by a background I/O thread.

The thread says ``hello`` (the outputs wanted, its ``credits``, who it is and the resume
state), receives batches, answers revokes, sends heartbeats, and forwards an ``ack`` naming
each batch as it is handed to the training loop (the ack frees exactly that batch's credit). So
the server never has more than ``credits`` batches in flight to this connection, and a slow
trainer never grows anybody's memory. ``V2VStreamDataset`` (``dataset.py``) owns the
connections and the resume state.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
import uuid
import warnings
from typing import Dict, Optional, Tuple

import numpy as np
import torch
import zmq

from v2v_wire.codecs import decode_batch_arrays
from v2v_wire.outputs import ARRAYS
from v2v_wire.protocol import MAX_CLIENT_MSG, ProtocolError, is_ipv6, output_of, pack, unpack

from .flowgrid import expand_flow_grid
from .handoff import ShmReader, check_shm_dir, shm_dir_problem

log = logging.getLogger("v2v.client")

#: Largest message accepted from the server, bytes (ZMQ_MAXMSGSIZE).
MAX_SERVER_MSG = 1 << 31


class StreamError(RuntimeError):
    """The server sent an error, broke the protocol, or went silent (the message says which)."""


class StreamTimeout(StreamError, TimeoutError):
    """No message from the server within ``timeout_s``."""


def _view(a: np.ndarray) -> torch.Tensor:
    """A tensor sharing ``a``'s memory (the received message's buffer, read-only)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="The given NumPy array is not writable")
        return torch.from_numpy(a)


def batch_to_torch(arrays: Dict[str, np.ndarray], raw: bool = False, flow_size: Optional[Tuple[int, int]] = None,
                   flow_dtype: str = ARRAYS["flow"].dtypes[0], compact_flow: bool = False) -> Dict[str, torch.Tensor]:
    """Convert wire arrays of one batch to tensors, as their ``outputs.ArraySpec`` says.

    With ``raw=False``: ``voxels`` float32 (B, L, num_bins, H, W) event counts; ``frames``
    float32 in [0, 1] (B, L + 1, 1, H, W); ``flow`` float32 (B, L, 2, H, W), pixels;
    ``polarity_counts`` float32 (B, L, 2, num_bins, H, W) counts (one conversion pass per
    array on this host). With ``raw=True`` the wire dtypes are kept (voxels int8/int16/int32,
    frames uint8 with the channel axis, flow float16, polarity counts uint8) and nothing is
    copied: the tensors view the received message and must be treated as read-only
    (``.to(device)`` and ``.float()`` copy); convert on the GPU.

    A tracked flow option's flow arrives as ``flow_grid`` float32 (B, L, 2, n, n), its values
    at the tracking grid's points: with ``compact_flow`` it is kept so (a float32 tensor;
    expand it on the GPU with ``flowgrid.expand_flow_grid``), else it becomes ``flow``
    (B, L, 2, *flow_size*) with the server's own bilinear taps (``flowgrid``): float32, or
    ``flow_dtype`` (the server's dense flow dtype) with ``raw``, equal to the dense flow the
    server would have sent.

    Raises:
        ProtocolError: an unknown array, a ``flow_grid`` of the wrong shape, or one with no
            ``flow_size`` to expand it to.
    """
    out = {}
    for name, a in arrays.items():
        spec = ARRAYS.get(name)
        if spec is None:
            raise ProtocolError(f"unknown array {name!r} in a batch; known: {list(ARRAYS)}")
        if spec.insert_channel:
            a = np.expand_dims(a, spec.channel_axis + 1)  # + 1: the batch axis
        if spec.expand:
            out.update(_expand(name, a, raw, flow_size, flow_dtype, compact_flow))
        elif raw:
            out[name] = _view(a)
        elif spec.float_divisor is not None:
            out[name] = torch.from_numpy(np.multiply(a, np.float32(1.0 / spec.float_divisor), dtype=np.float32))
        else:
            out[name] = torch.from_numpy(a.astype(np.float32))
    return out


def _expand(name: str, a: np.ndarray, raw: bool, flow_size, flow_dtype: str, compact: bool) -> Dict[str, torch.Tensor]:
    """A compact array (``flow_grid`` float32 (B, L, 2, n, n)) as a tensor: kept compact, or
    expanded to the dense output it carries (see :func:`batch_to_torch`)."""
    spec = ARRAYS[name]
    if a.ndim != 5 or a.shape[2] != 2 or a.shape[3] != a.shape[4] or a.shape[3] < 2 or a.dtype.name not in spec.dtypes:
        raise ProtocolError(f"array {name!r} must be {spec.dtypes[0]} (B, L, 2, n, n), got {a.dtype}{list(a.shape)}")
    if compact:
        return {name: _view(a) if raw else torch.from_numpy(a.copy())}
    if flow_size is None:
        raise ProtocolError(f"a {name!r} array, but the server's welcome named no crop_size to expand it to")
    dense = ARRAYS[spec.output].dtypes  # the dense output's wire dtypes: torch has the same names
    dtype = getattr(torch, flow_dtype) if raw and flow_dtype in dense else torch.float32
    return {spec.output: expand_flow_grid(_view(a), flow_size, dtype)}


class _ServerMessages:
    """The I/O thread's half of a :class:`Connection` that reads the server's messages: batches
    (checked, converted, queued for the consumer), welcomes, revokes, the stream's end and
    errors. Replies go to ``_replies``; the socket loop (:class:`_ServerIO`) sends them."""

    def _on_message(self, frames) -> Optional[str]:
        """Handle one server message; "over" when the stream has ended or failed, "lost"
        when the server is shutting down."""
        try:
            h = unpack(frames[0])
            kind = h["type"]
            if self._awaiting is not None and (kind in ("batch", "revoke") or (
                    kind == "error" and h.get("code") in ("dropped", "unknown_client"))):
                # sent before the server read our latest hello: about a session that is over
                return None
            if kind == "batch":
                self._on_batch(h, frames)
            elif kind == "welcome":
                self._on_welcome(h)
                refusal = self.ds.welcomed(self.info)
                if refusal is not None:
                    self.items.put(StreamError(f"v2v server at {self.endpoint}: {refusal}"))
                    return "over"
            elif kind == "revoke":
                self._on_revoke(h)
            elif kind == "epoch_done":
                n = h.get("batches")
                self.items.put(_EpochDone(int(h["epoch"]), n if isinstance(n, int) else None))
            elif kind == "drained":
                self.items.put(_Drained())
            elif kind == "end":
                self.items.put(StopIteration(h.get("reason", "end of stream")))
                return "over"
            elif kind == "shutdown":
                return "lost"
            elif kind == "error" and h.get("code") == "compression" and self._compression_auto:
                # the server lacks the codec we picked by default: take the arrays as they are
                log.warning("v2v server at %s: %s; receiving arrays uncompressed", self.endpoint, h.get("message"))
                self.compression = "none"
                self._replies.append(self._hello())
            elif kind == "error" and h.get("code") in ("dropped", "unknown_client"):
                # dropped for silence or an unanswered revoke, or the server restarted behind our socket:
                # whatever we hold goes elsewhere, so hand none of it on; introduce ourselves again
                log.warning("v2v server at %s: %s; saying hello again with the resume state", self.endpoint,
                            h.get("message"))
                self._replies.append(self._hello())
            elif kind == "error":
                self.items.put(StreamError(f"v2v server at {self.endpoint}: {h.get('message')}"))
                return "over"
        except (ProtocolError, KeyError, TypeError, ValueError) as e:
            self.items.put(StreamError(f"bad message from the v2v server at {self.endpoint}: {e}"))
            return "over"
        return None

    def _on_batch(self, h: dict, frames) -> None:
        """A batch: its arrays (from the frames, or from the server's batch file on the same
        host) checked against the header, converted, and queued for the loop.

        Raises:
            ProtocolError: arrays missing, of the wrong length, or a hand-off not asked for.
        """
        shm = h.get("shm") is not None
        if shm:  # same host: the arrays are in the server's batch file
            if self._shm is None or len(frames) != 1:
                raise ProtocolError("a shared-memory batch this client did not ask for")
            arrays = self._shm.read(h, copy=self.ds.raw)
            if arrays is None:
                return self._torn(h)
        else:
            arrays = decode_batch_arrays(h.get("arrays"), frames[1:], MAX_SERVER_MSG)
        missing = [o for o in self.ds.outputs if o not in {output_of(k) for k in arrays}]
        if missing:
            raise ProtocolError(f"batch {h.get('batch_id')} lacks requested outputs {missing}")
        ids = h["sample_ids"]
        if not isinstance(ids, list) or any(a.shape[:1] != (len(ids),) for a in arrays.values()):
            raise ProtocolError(f"batch {h.get('batch_id')}: sample ids do not match the arrays")
        info = self.info or {}
        crop = info.get("crop_size")
        item = batch_to_torch(arrays, self.ds.raw, (crop, crop) if isinstance(crop, int) and crop > 0 else None,
                              info.get("flow_dtype", ARRAYS["flow"].dtypes[0]), self.ds.compact_flow)
        if shm and not self.ds.raw:
            del arrays  # converted from the mapping: check it still held this batch
            if not self._shm.valid(h):
                return self._torn(h)
        item["sample_ids"] = list(ids)
        item["params"] = list(h["params"])
        item["epoch"] = int(h["epoch"])
        item["batch_id"] = int(h["batch_id"])
        if h.get("padding") is True:  # DDP padding from the server: not leased, never acknowledged
            item["padding"] = torch.ones(len(ids), dtype=torch.bool)
            self.items.put(_Padding(item))
            return None
        with self.lock:  # a batch we gave back may come back to us: this copy is the live one
            self.current[item["batch_id"]] = item
        self.items.put(item)
        return None

    def _on_welcome(self, h: dict) -> None:
        """The server's answer to our hello: its stream info, and whether we can read its
        batch directory (else we ask again without the same-host hand-off)."""
        if h.get("hello_id") == self._awaiting:
            self._awaiting = None
        self.info = h.get("info", {})
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
        self._replies.append(self._hello())

    def _on_revoke(self, h: dict) -> None:
        """Batches the server asks back: those still held (not yet handed to the loop) are
        released, their arrays freed at once."""
        ids = h.get("batch_ids") if isinstance(h.get("batch_ids"), list) else []
        released = []
        with self.lock:
            for b in ids:
                item = self.current.pop(b, None) if isinstance(b, int) else None
                if item is not None:
                    _strip(item)
                    released.append(b)
        if released:
            self._replies.append(pack({"type": "released", "batch_ids": released}))

    def _torn(self, h: dict) -> None:
        """A shared-memory batch whose buffer the server refilled before we copied it: the
        batch was acknowledged (or dropped) already, so it is not ours; give it back. The
        same batch torn twice means its file is gone while the server still holds it (the
        directory was removed under it): read over the socket from now on, so the batch comes
        as frames instead of the same reference again."""
        bid = h.get("batch_id")
        self._torn_ids[bid] = self._torn_ids.get(bid, 0) + 1
        if self._torn_ids[bid] >= 2:
            self._socket_instead(f"batch {bid} is gone from the server's shared memory again")
            return None
        log.warning("v2v stream %s: batch %s was gone from the server's shared memory before it was read "
                    "(this process stalled?); giving it back", self.endpoint, bid)
        if isinstance(bid, int) and not isinstance(bid, bool) and bid >= 0:
            self._replies.append(pack({"type": "released", "batch_ids": [bid]}))
        return None


class _ServerIO(_ServerMessages):
    """The I/O thread's half of a :class:`Connection` that owns the socket: hello (with the
    dataset's resume state), the poll loop, heartbeats, acknowledgements and receipts
    forwarded, reconnection, and ``bye``."""

    def _discard_locked(self, why: str) -> None:
        if self.current:
            log.warning("v2v stream %s: discarding %d batch(es) not yet used: %s", self.endpoint,
                        len(self.current), why)
        for item in self.current.values():
            _strip(item)
        self.discarded += len(self.current)
        self.current.clear()

    def _socket(self) -> zmq.Socket:
        sock = self._ctx.socket(zmq.DEALER)
        sock.setsockopt(zmq.IDENTITY, self._ident)
        sock.setsockopt(zmq.LINGER, 1000)
        sock.setsockopt(zmq.MAXMSGSIZE, MAX_SERVER_MSG)
        sock.setsockopt(zmq.RCVHWM, 0)
        if is_ipv6(self.endpoint):
            sock.setsockopt(zmq.IPV6, 1)
        if self.ds.curve is not None:
            pub, sec, server_pub = self.ds.curve
            sock.curve_publickey, sock.curve_secretkey, sock.curve_serverkey = pub, sec, server_pub
        sock.connect(self.endpoint)
        _send(sock, self._hello())
        self._awaiting = None  # a new socket carries no message of an older session
        return sock

    def _poller(self, sock: zmq.Socket) -> zmq.Poller:
        poller = zmq.Poller()
        poller.register(sock, zmq.POLLIN)
        poller.register(self._ack_recv, zmq.POLLIN)
        if self._receipts is not None:
            poller.register(self._receipts.fileno(), zmq.POLLIN)
        return poller

    def _take_receipts(self, sock: zmq.Socket) -> None:
        """Batches the training loop received (written by ``StreamLoader`` in the main
        process): acknowledged to the server, and recorded by the stream."""
        while self._receipts is not None and self._receipts.poll(0):
            try:
                ids = unpack(self._receipts.recv_bytes())["batch_ids"]
            except (EOFError, OSError):  # the main process is gone
                self._receipts = None
                return
            mine = self.ds.received(ids)
            if mine:
                _send(sock, pack({"type": "ack", "batch_ids": mine}))

    def _hello(self) -> bytes:
        """A (re-)hello: whatever this connection still holds is discarded first, since the
        server takes the resume state as the truth and re-sends the rest."""
        with self.lock:
            self._discard_locked("saying hello again")
        self._hello_seq += 1
        self._awaiting = self._hello_seq
        h = dict(self.ds._hello_header(), hello_id=self._hello_seq)
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
        return data

    def _forward_acks(self, sock: zmq.Socket) -> None:
        while True:
            try:
                _send(sock, self._ack_recv.recv(zmq.NOBLOCK))
            except zmq.Again:
                return

    def _run(self) -> None:
        """The I/O thread: the loop over the socket; any failure goes to the consumer as a
        :class:`StreamError`, and the socket always closes with ``bye``."""
        self._sock = None
        try:
            self._sock = self._socket()
            self._serve()
        except Exception as e:  # never die silently: hand the error to the consumer
            self.items.put(StreamError(f"stream from {self.endpoint} failed: {type(e).__name__}: {e}"))
        finally:
            self._finish(self._sock)

    def _serve(self) -> None:
        """Poll the socket, the acknowledgements and the receipts; receive messages, heartbeat,
        and on a lost server reconnect (``ds.reconnect``) or end the stream with an error."""
        sock = self._sock
        give_up_at = None
        last_heard = time.monotonic()
        next_beat = last_heard + self.ds.heartbeat_s
        poller = self._poller(sock)
        while not self._closing.is_set():
            events = dict(poller.poll(100))
            now = time.monotonic()
            if self.silent_too_long(now):
                # suspended longer than the server waits for us: it has dropped us; start afresh
                log.warning("v2v stream %s: this process was silent for %.0f s; saying hello again",
                            self.endpoint, now - self.last_io)
                _send(sock, self._hello())
            self.last_io = now
            if self._ack_recv in events:
                self._forward_acks(sock)
            self._take_receipts(sock)
            if self._lingering and not self.ds.in_loader():
                return  # every batch handed to the DataLoader was received: bye
            lost = None
            if sock in events:
                verdict, heard = self._receive(sock)
                if heard:
                    last_heard, give_up_at = now, None
                if verdict == "over":
                    return
                if verdict == "lost":
                    lost = "the server shut down"
            if lost is None and now - last_heard > self.ds.timeout_s:
                lost = f"no message for {self.ds.timeout_s:.0f} s"
            if lost is not None:
                give_up_at = self._lost(lost, now, give_up_at)
                if give_up_at is None:
                    return
                sock.close(0)
                sock = self._sock = self._socket()
                poller = self._poller(sock)
                last_heard = now
                continue
            if now >= next_beat:
                _send(sock, pack({"type": "heartbeat"}))
                next_beat = now + self.ds.heartbeat_s

    def _receive(self, sock: zmq.Socket) -> Tuple[Optional[str], bool]:
        """Handle every message waiting on ``sock`` and send the replies they call for:
        (``_on_message``'s "over" or "lost" verdict, else None; whether any message came)."""
        heard = False
        while True:
            try:
                frames = sock.recv_multipart(zmq.NOBLOCK, copy=False)
            except zmq.Again:
                return None, heard
            heard = True
            verdict = self._on_message(frames)
            for r in self._replies:
                _send(sock, r)
            self._replies.clear()
            if verdict in ("over", "lost"):
                return verdict, heard

    def _lost(self, why: str, now: float, give_up_at: Optional[float]) -> Optional[float]:
        """The server went away (``why``): the time to stop reconnecting at (``ds.reconnect``),
        or None when the stream ends here (the error is queued for the consumer)."""
        if not self.ds.reconnect:
            what = "no answer" if self.info is None else "no message"
            if why.startswith("no message"):
                self.items.put(StreamTimeout(
                    f"{what} from the v2v server at {self.endpoint} for {self.ds.timeout_s:.0f} s "
                    f"(is v2v-serve running and reachable?)"))
            else:
                self.items.put(StreamError(
                    f"the v2v server at {self.endpoint} shut down mid-stream; restart it and resume "
                    f"with state_dict(), or use reconnect=True"))
            return None
        if give_up_at is None:
            log.warning("lost the v2v server at %s (%s); reconnecting for up to %.0f s",
                        self.endpoint, why, self.ds.reconnect_timeout_s)
            return now + self.ds.reconnect_timeout_s
        if now > give_up_at:
            self.items.put(StreamTimeout(f"could not reconnect to the v2v server at {self.endpoint} "
                                         f"within {self.ds.reconnect_timeout_s:.0f} s"))
            return None
        return give_up_at

    def _finish(self, sock: Optional[zmq.Socket]) -> None:
        """Close the I/O thread's sockets: acknowledgements of batches the training loop took
        and its receipts go out before ``bye``."""
        if sock is not None:
            try:
                self._forward_acks(sock)
                self._take_receipts(sock)
                sock.send(pack({"type": "bye"}), zmq.NOBLOCK)
            except zmq.ZMQError:
                pass
            sock.close()
        self._ack_recv.close(0)
        if self._shm is not None:
            self._shm.close()


class Connection(_ServerIO):
    """One DEALER connection to one endpoint and its I/O thread.

    The thread owns the socket: it says hello (with the dataset's resume state), receives
    batches, answers revokes, heartbeats, and forwards the acknowledgements the consumer
    queues through an inproc pair (flushed before ``bye`` when the iterator closes). It hands
    the consumer decoded batches and control items through ``items``. A fan-in wrapper may
    create one per endpoint; the dataset ``ds`` supplies settings and the resume state.

    A batch is either taken by the training loop (``take``: acknowledged) or given back to the
    server (revoked after its lease, the epoch already complete here, or everything held when
    the server dropped this client or this process was silent longer than the server's client
    timeout), never both: ``lock`` makes the choice exclusive, and a batch given back loses its
    arrays at once, so a stalled trainer's memory stays bounded by its credits.
    """

    #: Fraction of the server's client timeout after which a silent process assumes it was dropped.
    SILENCE_FRACTION = 0.8

    def __init__(self, ds, endpoint: Optional[str] = None):
        self.ds = ds
        self.endpoint = endpoint or ds.endpoint
        self.items: "queue.Queue" = queue.Queue()
        self.info: Optional[dict] = None
        self._replies: list = []
        self._closing = threading.Event()
        self._ctx = zmq.Context.instance()
        self._ident = uuid.uuid4().bytes
        self._ack_addr = f"inproc://v2v-ack-{uuid.uuid4().hex}"
        self._ack_recv = self._ctx.socket(zmq.PAIR)
        self._ack_recv.bind(self._ack_addr)
        self._ack_send = self._ctx.socket(zmq.PAIR)
        self._ack_send.connect(self._ack_addr)
        self.lock = threading.Lock()
        self.current: Dict[int, dict] = {}  # batch id -> its live queued item (not taken, not given back)
        self.last_io = time.monotonic()
        self.discarded = 0
        self._hello_seq = 0
        self._awaiting: Optional[int] = None  # id of our last hello until its welcome arrives
        self._lingering = False
        self._torn_ids: Dict[int, int] = {}  # shared-memory batches found gone, by batch id
        self._receipts = getattr(ds, "receipts", None)  # DataLoader worker: what the training loop received
        self.shm = ds.wants_shm(self.endpoint)  # ask for batches through the server's shared memory
        self.compression, self._compression_auto = ds.compression_for(self.endpoint)
        self._shm = ShmReader(keep=ds.credits + 2) if self.shm else None
        self._thread = threading.Thread(target=self._run, name="v2v-stream-io", daemon=True)
        self._thread.start()

    # consumer side -------------------------------------------------------
    def silent_too_long(self, now: float) -> bool:
        """True when the I/O thread has not run for most of the server's client timeout (the
        process was suspended): the server has, or is about to have, dropped this client."""
        limit = (self.info or {}).get("client_timeout_s")
        return isinstance(limit, (int, float)) and now - self.last_io > self.SILENCE_FRACTION * limit

    def _claim(self, item: dict) -> bool:
        """Take a received batch out of ``current`` for the consumer; False when it was given
        back meanwhile (its lease expired, or this client was dropped or silent too long)."""
        bid = item["batch_id"]
        with self.lock:
            if self.current.get(bid) is not item:
                return False
            if self.silent_too_long(time.monotonic()):
                self._discard_locked("this process was silent longer than the server's client timeout")
                return False
            del self.current[bid]
        return True

    def take(self, item: dict) -> bool:
        """Claim a received batch for the training loop and acknowledge it; False when it was
        given back meanwhile (its lease expired, or this client was dropped)."""
        if not self._claim(item):
            return False
        self._queue_for_server({"type": "ack", "batch_ids": [item["batch_id"]]})
        return True

    def hold(self, item: dict) -> bool:
        """Claim a received batch for a DataLoader worker's queue: like :meth:`take`, but the
        server is told the batch is held (no lease) rather than acknowledged; :meth:`ack`
        follows when the training loop receives it, else closing the connection gives it back."""
        if not self._claim(item):
            return False
        self._queue_for_server({"type": "hold", "batch_ids": [item["batch_id"]]})
        return True

    def ack(self, batch_ids) -> None:
        """Acknowledge batches this connection holds (the training loop received them)."""
        if batch_ids:
            self._queue_for_server({"type": "ack", "batch_ids": list(batch_ids)})

    def give_back(self, item: dict) -> None:
        """Return a received batch to the server unused (e.g. an epoch this consumer already completed)."""
        bid = item["batch_id"]
        with self.lock:
            if self.current.get(bid) is not item:
                return
            del self.current[bid]
            _strip(item)
        self._queue_for_server({"type": "released", "batch_ids": [bid]})

    def _queue_for_server(self, msg: dict) -> None:
        """Hand ``msg`` to the I/O thread, which sends it. Dropped once that thread has ended
        (the server shut down or the connection closed: nobody would receive it), so taking a
        batch still queued here never blocks on a pipe nobody reads."""
        data = pack(msg)
        while not self._closing.is_set() and self._thread.is_alive():
            try:
                self._ack_send.send(data, zmq.NOBLOCK)
                return
            except zmq.Again:  # the pipe is full, or the I/O thread is ending: look again
                time.sleep(0.001)

    def linger(self) -> None:
        """The iteration ended with batches still in a DataLoader's queues: keep taking their
        receipts, and close once none is left (or at :meth:`close`)."""
        self._lingering = True

    def close(self) -> None:
        """Stop the I/O thread: acknowledgements already queued are sent, then ``bye``."""
        if self._closing.is_set():
            return
        self._closing.set()
        self._thread.join(5.0)
        self._ack_send.close(0)
        self.items.put(StopIteration("closed"))  # wake an iterator blocked on this connection

def _send(sock: zmq.Socket, data: bytes) -> bool:
    """Send without blocking the I/O thread; False when no connection to the server is up
    (nothing is queued then: the resume state and re-sends cover what was not said)."""
    try:
        sock.send(data, zmq.NOBLOCK)
        return True
    except zmq.Again:
        return False


def _strip(item: dict) -> None:
    """Free the arrays of a batch that will not be used (keeps its ids for bookkeeping)."""
    for k in [k for k, v in item.items() if isinstance(v, torch.Tensor)]:
        del item[k]


class _Padding:
    def __init__(self, item: dict):
        self.item = item


class _Drained:
    """The server has nothing left to send this connection unless a batch held elsewhere comes back."""


class _EpochDone:
    def __init__(self, epoch: int, batches: Optional[int] = None):
        self.epoch = epoch
        self.batches = batches  # DDP: batches every rank of the group must yield in this epoch


def _select(item: dict, keep: list) -> dict:
    """The samples at positions ``keep`` of a batch."""
    idx = torch.as_tensor(keep, dtype=torch.long)
    out = dict(item)
    for k, v in item.items():
        if isinstance(v, torch.Tensor):
            out[k] = v.index_select(0, idx)
    out["sample_ids"] = [item["sample_ids"][i] for i in keep]
    out["params"] = [item["params"][i] for i in keep]
    return out


def load_curve_keys(client_secret_file: str, server_public_file: str) -> tuple:
    """(client public, client secret, server public) Z85 keys from ``v2v-keygen`` files.

    Raises:
        ValueError: naming the file, when it is missing or holds no key of the right kind.
    """
    import zmq.auth

    try:
        pub, sec = zmq.auth.load_certificate(client_secret_file)
    except (OSError, ValueError) as e:
        raise ValueError(f"client key {client_secret_file}: {e}") from None
    if not sec:
        raise ValueError(f"client key {client_secret_file}: holds no secret key (use the .key_secret file)")
    try:
        server_pub, _ = zmq.auth.load_certificate(server_public_file)
    except (OSError, ValueError) as e:
        raise ValueError(f"server key {server_public_file}: {e}") from None
    return pub, sec, server_pub

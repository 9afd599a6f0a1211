"""``V2VStreamDataset``: a torch IterableDataset reading batches from ``v2v-serve``.

Each iterator owns one DEALER connection (:class:`Connection`) served by a background I/O
thread. The thread says ``hello`` (the outputs wanted, its window of ``credits``, who it is and
the resume state), receives batches, answers revokes, sends heartbeats, and forwards an
``ack`` naming each batch as it is handed to the training loop (the ack frees exactly that
batch's slot). So the server never has more than ``credits`` batches in flight to this
iterator, and a slow trainer never grows anybody's memory.

Sharing one stream: the server hands every batch to exactly one connection. Each DataLoader
worker process (``num_workers > 0``) and each DDP rank opens its own connection when it
starts iterating, so they split the stream between them without duplicates. DDP ranks pass
``rank``/``world_size`` (or let them default from ``torch.distributed``) so that each rank
yields the same number of batches per epoch (see ``V2VStreamDataset``).
"""
from __future__ import annotations

import collections
import logging
import os
import queue
import threading
import time
import uuid
import warnings
from typing import Dict, Iterator, List, Optional, Sequence, Set, Tuple, Union

import numpy as np
import torch
import zmq

from v2v_server.protocol import OUTPUTS, ProtocolError, decode_arrays, pack, unpack

from .fanin import FanInStream, read_state, resolve_endpoints, split_endpoints
from .handoff import ShmReader, check_shm_dir
from .metrics import TrainerMetrics

log = logging.getLogger("v2v.client")

#: Largest message accepted from the server, bytes (ZMQ_MAXMSGSIZE).
MAX_SERVER_MSG = 1 << 31


def padding_copy(batch: dict, epoch: int) -> dict:
    """A DDP padding batch of ``epoch`` repeating ``batch``: its tensors cloned, every sample
    flagged in ``padding`` (bool (B,), all True: the loss must ignore them), ``batch_id`` -1."""
    out = {k: (v.clone() if isinstance(v, torch.Tensor) else v) for k, v in batch.items()}
    out.update(padding=torch.ones(len(batch["sample_ids"]), dtype=torch.bool), epoch=epoch, batch_id=-1,
               sample_ids=list(batch["sample_ids"]), params=list(batch["params"]))
    return out


class StreamError(RuntimeError):
    """The server sent an error, broke the protocol, or went silent (the message says which)."""


class StreamTimeout(StreamError, TimeoutError):
    """No message from the server within ``timeout_s``."""


def _view(a: np.ndarray) -> torch.Tensor:
    """A tensor sharing ``a``'s memory (the received message's buffer, read-only)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="The given NumPy array is not writable")
        return torch.from_numpy(a)


def batch_to_torch(arrays: Dict[str, np.ndarray], raw: bool = False) -> Dict[str, torch.Tensor]:
    """Convert wire arrays of one batch to tensors.

    With ``raw=False``: ``voxels`` float32 (B, L, num_bins, H, W) event counts; ``frames``
    float32 in [0, 1] (B, L + 1, 1, H, W); ``flow`` float32 (B, L, 2, H, W), pixels (one
    conversion pass per array on this host).
    With ``raw=True`` the wire dtypes are kept (voxels int8/int16/int32, frames uint8 with
    the channel axis, flow float16) and nothing is copied: the tensors view the received
    message and must be treated as read-only (``.to(device)`` and ``.float()`` copy);
    convert on the GPU.
    """
    out = {}
    for name, a in arrays.items():
        if name == "frames":
            a = a[:, :, None]
        if raw:
            out[name] = _view(a)
        elif name == "frames":
            out[name] = torch.from_numpy(np.multiply(a, np.float32(1.0 / 255.0), dtype=np.float32))
        else:
            out[name] = torch.from_numpy(a.astype(np.float32))
    return out


class Connection:
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

    def __init__(self, ds: "V2VStreamDataset", endpoint: Optional[str] = None):
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
        self.taken: "collections.OrderedDict[int, None]" = collections.OrderedDict()  # recent, bounded
        self.last_io = time.monotonic()
        self.discarded = 0
        self._hello_seq = 0
        self._awaiting: Optional[int] = None  # id of our last hello until its welcome arrives
        self.shm = ds.wants_shm(self.endpoint)  # ask for batches through the server's shared memory
        self._shm = ShmReader(keep=ds.credits + 2) if self.shm else None
        self._thread = threading.Thread(target=self._run, name="v2v-stream-io", daemon=True)
        self._thread.start()

    # consumer side -------------------------------------------------------
    def silent_too_long(self, now: float) -> bool:
        """True when the I/O thread has not run for most of the server's client timeout (the
        process was suspended): the server has, or is about to have, dropped this client."""
        limit = (self.info or {}).get("client_timeout_s")
        return isinstance(limit, (int, float)) and now - self.last_io > self.SILENCE_FRACTION * limit

    def take(self, item: dict) -> bool:
        """Claim a received batch for the training loop and acknowledge it; False when it was
        given back meanwhile (its lease expired, or this client was dropped)."""
        bid = item["batch_id"]
        with self.lock:
            if self.current.get(bid) is not item:
                return False
            if self.silent_too_long(time.monotonic()):
                self._discard_locked("this process was silent longer than the server's client timeout")
                return False
            del self.current[bid]
            self.taken[bid] = None
            while len(self.taken) > 4096:
                self.taken.popitem(last=False)
        self._queue_for_server({"type": "ack", "batch_ids": [bid]})
        return True

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
        if not self._closing.is_set():
            self._ack_send.send(pack(msg))

    def close(self) -> None:
        """Stop the I/O thread: acknowledgements already queued are sent, then ``bye``."""
        if self._closing.is_set():
            return
        self._closing.set()
        self._thread.join(5.0)
        self._ack_send.close(0)
        self.items.put(StopIteration("closed"))  # wake an iterator blocked on this connection

    # I/O thread ------------------------------------------------------------
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
        return poller

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
        return pack(h)

    def _forward_acks(self, sock: zmq.Socket) -> None:
        while True:
            try:
                _send(sock, self._ack_recv.recv(zmq.NOBLOCK))
            except zmq.Again:
                return

    def _run(self) -> None:
        sock = None
        give_up_at = None
        try:
            sock = self._socket()
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
                lost = None
                if sock in events:
                    while True:
                        try:
                            frames = sock.recv_multipart(zmq.NOBLOCK, copy=False)
                        except zmq.Again:
                            break
                        last_heard = now
                        give_up_at = None
                        verdict = self._on_message(frames)
                        for r in self._replies:
                            _send(sock, r)
                        self._replies.clear()
                        if verdict == "over":
                            return
                        if verdict == "lost":
                            lost = "the server shut down"
                            break
                if lost is None and now - last_heard > self.ds.timeout_s:
                    lost = f"no message for {self.ds.timeout_s:.0f} s"
                if lost is not None:
                    if not self.ds.reconnect:
                        what = "no answer" if self.info is None else "no message"
                        if lost.startswith("no message"):
                            self.items.put(StreamTimeout(
                                f"{what} from the v2v server at {self.endpoint} for {self.ds.timeout_s:.0f} s "
                                f"(is v2v-serve running and reachable?)"))
                        else:
                            self.items.put(StreamError(
                                f"the v2v server at {self.endpoint} shut down mid-stream; restart it and resume "
                                f"with state_dict(), or use reconnect=True"))
                        return
                    if give_up_at is None:
                        give_up_at = now + self.ds.reconnect_timeout_s
                        log.warning("lost the v2v server at %s (%s); reconnecting for up to %.0f s",
                                    self.endpoint, lost, self.ds.reconnect_timeout_s)
                    elif now > give_up_at:
                        self.items.put(StreamTimeout(f"could not reconnect to the v2v server at {self.endpoint} "
                                                     f"within {self.ds.reconnect_timeout_s:.0f} s"))
                        return
                    sock.close(0)
                    sock = self._socket()
                    poller = self._poller(sock)
                    last_heard = now
                    continue
                if now >= next_beat:
                    _send(sock, pack({"type": "heartbeat"}))
                    next_beat = now + self.ds.heartbeat_s
        except Exception as e:  # never die silently: hand the error to the consumer
            self.items.put(StreamError(f"stream from {self.endpoint} failed: {type(e).__name__}: {e}"))
        finally:
            if sock is not None:
                try:
                    self._forward_acks(sock)  # acks of batches the training loop took go out before bye
                    sock.send(pack({"type": "bye"}), zmq.NOBLOCK)
                except zmq.ZMQError:
                    pass
                sock.close()
            self._ack_recv.close(0)
            if self._shm is not None:
                self._shm.close()

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
            elif kind == "revoke":
                self._on_revoke(h)
            elif kind == "epoch_done":
                n = h.get("batches")
                self.items.put(_EpochDone(int(h["epoch"]), n if isinstance(n, int) else None))
            elif kind == "end":
                self.items.put(StopIteration(h.get("reason", "end of stream")))
                return "over"
            elif kind == "shutdown":
                return "lost"
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
            arrays = decode_arrays(h.get("arrays"), frames[1:], MAX_SERVER_MSG)
        missing = [o for o in self.ds.outputs if o not in arrays]
        if missing:
            raise ProtocolError(f"batch {h.get('batch_id')} lacks requested outputs {missing}")
        ids = h["sample_ids"]
        if not isinstance(ids, list) or any(a.shape[:1] != (len(ids),) for a in arrays.values()):
            raise ProtocolError(f"batch {h.get('batch_id')}: sample ids do not match the arrays")
        item = batch_to_torch(arrays, self.ds.raw)
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
            if d is not None and not os.access(check_shm_dir(d), os.R_OK | os.X_OK):
                log.warning("v2v stream %s: cannot read the server's batch directory %s (another user?); "
                            "asking for batches over the socket", self.endpoint, d)
                self.shm, self._shm = False, None
                self._replies.append(self._hello())
            else:
                self._shm.set_dir(d)

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
        batch was acknowledged (or dropped) already, so it is not ours; give it back."""
        bid = h.get("batch_id")
        log.warning("v2v stream %s: batch %s was gone from the server's shared memory before it was read "
                    "(this process stalled?); giving it back", self.endpoint, bid)
        if isinstance(bid, int) and not isinstance(bid, bool) and bid >= 0:
            self._replies.append(pack({"type": "released", "batch_ids": [bid]}))
        return None


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


class V2VStreamDataset(torch.utils.data.IterableDataset):
    """Batches of V2V training data streamed from a ``v2v-serve`` endpoint.

    Args:
        endpoint: ZeroMQ endpoint of the server, e.g. ``tcp://127.0.0.1:5555``; or several
            servers (shards, ``v2v-serve --shard I/N``): a list, a comma-separated string, or
            a ``tcp://NAME:PORT`` whose name resolves to several addresses (a Kubernetes
            headless Service). Then one connection per server is read and the batches are
            merged (``v2v_client.fanin``): ``credits`` is split between the servers, each
            reconnects on its own, the stream ends when every server ended it and
            ``state_dict()`` covers them all. ``rank``/``world_size`` apply to each server.
        outputs: which of ``"voxels"``, ``"frames"``, ``"flow"`` to receive; the server's
            workers compute the union of what its connected clients ask for.
        credits: batches the server may have in flight to this iterator (prefetch depth);
            the server refuses more than its ``max_credits`` (default 64) with a clear error.
        timeout_s: seconds without any message from the server (batches or heartbeats)
            before iteration raises ``StreamTimeout``; also bounds the wait for the first
            answer, so an absent server gives a clear error, never a hang. A heartbeating
            server that has nothing to send yet (a hung worker, ranks still joining) is
            waited for.
        heartbeat_s: seconds between heartbeats to the server.
        raw: keep wire dtypes (int8/int16 voxels, uint8 frames, float16 flow) for
            conversion on the GPU.
        reconnect: on a silent or restarting server, reconnect (with the delivered-sample
            state, so nothing is repeated) for up to ``reconnect_timeout_s`` seconds
            instead of raising.
        curve_keys: ``(client_secret_file, server_public_file)`` from ``v2v-keygen`` to talk
            to a server that requires CurveZMQ.
        rank, world_size: DDP position; by default taken from ``torch.distributed`` when it
            is initialised, else 0 and 1. With ``world_size > 1`` the ranks form one group
            on the server (``group``, default ``"default"``; give each DDP job on one server
            its own): nothing is sent until every rank said hello (or the server's client
            timeout passed), and every rank yields the same number of batches per epoch —
            a rank that got fewer repeats its last batch with every sample flagged in
            ``padding`` (see below). Use ``num_workers=0`` with DDP.
        group: name of the DDP group (see ``rank``).
        shm: same-host hand-off. ``"auto"`` (default): for an ``ipc://`` endpoint, ask the
            server to leave each batch in its shared-memory batch file (``/dev/shm``) and send
            only a reference; the arrays are then copied out of the file once (no socket copy
            on either side; ``v2v_client.handoff``). The server agrees only when bound to
            ``ipc://``; anything else still arrives as socket frames, and the batches are the
            same either way. ``True`` asks for any endpoint, ``False`` never.

    Yields dicts, one per batch of B samples:
        ``voxels`` float32 (B, L, num_bins, H, W), signed event counts per bin;
        ``frames`` float32 in [0, 1] (B, L + 1, 1, H, W), the frame at each voxel boundary;
        ``flow`` float32 (B, L, 2, H, W), forward optical flow in pixels from frame l to
        l + 1 (channel 0 = x, 1 = y);
        ``padding`` bool (B,): True for a repeated sample the loss must ignore (only DDP
        padding batches have any; their ``sample_ids`` are the repeated ids);
        ``sample_ids`` list of B str; ``params`` list of B dicts (sensor parameters and
        augmentation); ``epoch`` int; ``batch_id`` int (-1 for padding). Only requested
        outputs are present.

    Within an epoch each sample id is yielded once (with ``padding`` False), over all the
    connections (DataLoader workers, DDP ranks) that share the stream: the server hands every
    batch to one connection, takes the resume state as the truth, and the client drops any
    re-sent sample it has already yielded. ``state_dict()`` / ``load_state_dict()``
    (torchdata StatefulDataLoader convention) carry those ids across a trainer restart.

    Use with ``DataLoader(ds, batch_size=None, pin_memory=True)``. Iteration ends when the
    server ends the stream (``--epochs``). Leaving the loop early (``break``) sends the
    acknowledgements of what was taken before saying goodbye. Iterate one dataset object with
    one iterator at a time (the server knows it as one consumer; a new iterator replaces the
    previous connection); DataLoader workers each get their own consumer id.

    Raises (from iteration):
        StreamTimeout: the server is absent or silent for ``timeout_s``.
        StreamError: the server reported an error, broke the protocol or shut down.
        ValueError: at construction, for bad ``outputs``, ``credits``, ``timeout_s``,
            ``rank``/``world_size`` or keys.
    """

    def __init__(self, endpoint: Union[str, Sequence[str]], outputs: Sequence[str] = OUTPUTS, credits: int = 4,
                 timeout_s: float = 30.0, heartbeat_s: float = 1.0, raw: bool = False,
                 reconnect: bool = False, reconnect_timeout_s: float = 300.0,
                 curve_keys: Optional[Tuple[str, str]] = None, rank: Optional[int] = None,
                 world_size: Optional[int] = None, group: str = "default", shm: Union[bool, str] = "auto"):
        super().__init__()
        if isinstance(outputs, str):
            outputs = (outputs,)
        outputs = tuple(outputs)
        bad = [o for o in outputs if o not in OUTPUTS]
        if bad or not outputs:
            raise ValueError(f"outputs must be a non-empty subset of {list(OUTPUTS)}, got {list(outputs)}")
        if isinstance(credits, bool) or not isinstance(credits, int) or not 1 <= credits <= 1024:
            raise ValueError(f"credits must be an int in [1, 1024], got {credits!r}")
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        if rank is None or world_size is None:
            dr, dw = _dist_defaults()
            rank = dr if rank is None else rank
            world_size = dw if world_size is None else world_size
        if isinstance(world_size, bool) or not isinstance(world_size, int) or world_size < 1:
            raise ValueError(f"world_size must be an int >= 1, got {world_size!r}")
        if isinstance(rank, bool) or not isinstance(rank, int) or not 0 <= rank < world_size:
            raise ValueError(f"rank must be an int in [0, world_size={world_size}), got {rank!r}")
        if not isinstance(group, str) or not group or len(group) > 128:
            raise ValueError(f"group must be a non-empty string of at most 128 characters, got {group!r}")
        self.endpoint = endpoint
        self.outputs = tuple(o for o in OUTPUTS if o in outputs)
        self.credits = credits
        self.timeout_s = float(timeout_s)
        self.heartbeat_s = float(heartbeat_s)
        self.raw = raw
        if shm not in (True, False, "auto"):
            raise ValueError(f"shm must be True, False or 'auto', got {shm!r}")
        self.shm = shm
        self.reconnect = bool(reconnect)
        self.reconnect_timeout_s = float(reconnect_timeout_s)
        self._curve_keys = curve_keys  # the key files, for the per-server datasets of a fan-in
        self.curve = load_curve_keys(*curve_keys) if curve_keys else None
        self.rank, self.world_size, self.group = rank, world_size, group
        self.info: Optional[dict] = None
        self._conns: list = []
        self._lock = threading.Lock()
        self._consumer = uuid.uuid4().hex  # who acknowledges: survives reconnects and restarts (state_dict)
        self._delivered: Dict[int, Set[str]] = {}
        self._batches: Dict[int, int] = {}  # batches yielded per open epoch (DDP padding)
        self._completed_epoch = -1
        self._last: Optional[dict] = None  # last batch yielded: the source of DDP padding
        self._pad_debt: Dict[int, int] = {}  # epoch -> padding batches owed with nothing to repeat yet
        # several servers (a list, "a,b", or a DNS name with several addresses): fan-in
        self._fanin: Optional[FanInStream] = None
        self._meter = TrainerMetrics()
        if not isinstance(endpoint, str) or "," in endpoint:
            endpoints = split_endpoints(endpoint)
            if len(endpoints) == 1:
                self.endpoint = endpoints[0]
            else:
                self._fanin = self._make_fanin(endpoints)

    # ------------------------------------------------------------------ fan-in and metrics
    def _make_fanin(self, endpoints) -> FanInStream:
        def child(ep: str, credits: int) -> "V2VStreamDataset":  # one server's dataset: these options, its share
            return V2VStreamDataset(ep, outputs=self.outputs, credits=credits, timeout_s=self.timeout_s,
                                    heartbeat_s=self.heartbeat_s, raw=self.raw, reconnect=self.reconnect,
                                    reconnect_timeout_s=self.reconnect_timeout_s, curve_keys=self._curve_keys,
                                    rank=self.rank, world_size=self.world_size, group=self.group, shm=self.shm)

        fanin = FanInStream(endpoints, child, self.credits)
        fanin.load_state_dict(self.state_dict())
        return fanin

    def metrics(self) -> dict:
        """Trainer-side metrics: batches, samples and tensor bytes handed to the training loop
        (also per server), and seconds it waited for them; see ``v2v_client.metrics``."""
        return self._meter.snapshot()

    def __iter__(self) -> Iterator[dict]:
        if self._fanin is None and isinstance(self.endpoint, str):
            endpoints = resolve_endpoints(self.endpoint)
            if len(endpoints) > 1:  # e.g. a Kubernetes headless Service: one server per address
                self._fanin = self._make_fanin(endpoints)
        inner = iter(self._fanin) if self._fanin is not None else self._iter_stream()
        return self._meter.wrap(inner, self.endpoint if isinstance(self.endpoint, str) else "")

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """Where this consumer stands: epochs the server declared complete, the sample ids
        yielded so far in epochs still open, batches yielded per open epoch, and the consumer
        id the server knows it by. Plain, JSON/torch.save-safe data. With several servers: the
        epoch all of them completed and the ids yielded in later epochs."""
        if getattr(self, "_fanin", None) is not None:
            return self._fanin.state_dict()
        with self._lock:
            return {"version": 1, "consumer": self._consumer, "completed_epoch": self._completed_epoch,
                    "delivered": {str(e): sorted(ids) for e, ids in self._delivered.items()},
                    "batches": {str(e): n for e, n in self._batches.items()}}

    def load_state_dict(self, state: dict) -> None:
        """Restore ``state_dict()`` output; the next iteration resumes the epoch without
        repeating or skipping samples (the server takes this state as the truth: samples
        yielded after it was saved are sent again).

        Raises:
            ValueError: for a state of another format.
        """
        completed, delivered = read_state(state)
        with self._lock:
            self._completed_epoch, self._delivered = completed, delivered
            self._batches = {int(e): int(n) for e, n in state.get("batches", {}).items()}
            if isinstance(state.get("consumer"), str) and state["consumer"]:
                self._consumer = state["consumer"]
        if self._fanin is not None:
            self._fanin.load_state_dict(state)

    def wants_shm(self, endpoint: str) -> bool:
        """Whether a connection to ``endpoint`` asks for batches through the server's shared
        memory: ``shm=True`` always (the server agrees only when bound to ``ipc://``),
        ``"auto"`` for ``ipc://`` endpoints (the server is on this host)."""
        return self.shm is True or (self.shm == "auto" and endpoint.startswith("ipc://"))

    def _hello_header(self) -> dict:
        """The hello message: outputs, credits, who we are, and the resume state."""
        with self._lock:
            resume = {"completed_epoch": self._completed_epoch,
                      "delivered": {str(e): "\n".join(sorted(ids)) for e, ids in self._delivered.items()},
                      "batches": {str(e): n for e, n in self._batches.items()}}
        info = torch.utils.data.get_worker_info()
        consumer = self._consumer if info is None else f"{self._consumer}/{info.id}"
        h = {"type": "hello", "outputs": list(self.outputs), "credits": self.credits, "consumer": consumer,
             "resume": resume}
        if self.world_size > 1:
            h.update(rank=self.rank, world_size=self.world_size, group=self.group)
        return h

    # ------------------------------------------------------------------ iteration
    def _padding_batch(self, epoch: int) -> Optional[dict]:
        return None if self._last is None else padding_copy(self._last, epoch)

    def _epoch_done(self, done: "_EpochDone") -> List[dict]:
        """Forget a complete epoch; with DDP, the padding batches this rank owes for it."""
        pads: List[dict] = []
        with self._lock:
            if done.epoch <= self._completed_epoch:
                return pads
            owed = 0
            if self.world_size > 1 and done.batches is not None:
                owed = max(0, done.batches - self._batches.get(done.epoch, 0))
            self._completed_epoch = done.epoch
            for e in [e for e in self._delivered if e <= done.epoch]:
                del self._delivered[e]
            for e in [e for e in self._batches if e <= done.epoch]:
                del self._batches[e]
        for _ in range(owed):
            p = self._padding_batch(done.epoch)
            if p is None:
                self._pad_debt[done.epoch] = self._pad_debt.get(done.epoch, 0) + 1
            else:
                pads.append(p)
        return pads

    def _iter_stream(self) -> Iterator[dict]:  # one server's stream (iter() adds fan-in, metrics)
        conn = Connection(self)
        self._conns.append(conn)
        try:
            while True:
                try:
                    item = conn.items.get(timeout=1.0)
                except queue.Empty:
                    if not conn._thread.is_alive() and conn.items.empty():
                        raise StreamError(f"the connection to the v2v server at {self.endpoint} ended") from None
                    continue  # the I/O thread decides when the server is gone (timeout_s without a message)
                if isinstance(item, StopIteration):
                    return
                if isinstance(item, BaseException):
                    raise item
                if isinstance(item, _EpochDone):
                    yield from self._epoch_done(item)
                    continue
                if isinstance(item, _Padding):
                    with self._lock:
                        e = item.item["epoch"]
                        if e <= self._completed_epoch:
                            continue
                        self._batches[e] = self._batches.get(e, 0) + 1
                    self._last = item.item
                    yield item.item
                    continue
                self.info = conn.info
                epoch = item["epoch"]
                with self._lock:
                    done_already = epoch <= self._completed_epoch
                if done_already:
                    conn.give_back(item)  # never acknowledge what we would drop
                    continue
                if not conn.take(item):
                    continue  # given back meanwhile (lease expired, or this client was dropped)
                with self._lock:
                    seen = self._delivered.setdefault(epoch, set())
                    keep = [i for i, sid in enumerate(item["sample_ids"]) if sid not in seen]
                    seen.update(item["sample_ids"][i] for i in keep)
                    self._batches[epoch] = self._batches.get(epoch, 0) + 1
                item["padding"] = torch.zeros(len(item["sample_ids"]), dtype=torch.bool)
                if len(keep) < len(item["sample_ids"]):
                    if not keep and self.world_size == 1:
                        continue  # all re-sent duplicates: hand nothing on
                    if keep:
                        item = _select(item, keep)
                    else:  # DDP: keep the batch count equal; every sample is a repeat
                        item["padding"] = torch.ones(len(item["sample_ids"]), dtype=torch.bool)
                for e in sorted(self._pad_debt):
                    for _ in range(self._pad_debt.pop(e)):
                        yield padding_copy(item, e)
                self._last = item
                yield item
        finally:
            conn.close()
            if conn in self._conns:
                self._conns.remove(conn)

    def close(self) -> None:
        """Close every open connection of this dataset (also done when iterators are collected)."""
        if self._fanin is not None:
            self._fanin.close()
        for conn in list(self._conns):
            conn.close()
        self._conns.clear()


def _dist_defaults() -> Tuple[int, int]:
    """(rank, world_size) from ``torch.distributed`` when initialised, else (0, 1)."""
    try:
        import torch.distributed as dist

        if dist.is_available() and dist.is_initialized():
            return dist.get_rank(), dist.get_world_size()
    except Exception:  # noqa: BLE001 - a half-initialised backend is the same as none here
        pass
    return 0, 1

"""``V2VStreamDataset``: a torch IterableDataset reading batches from ``v2v-serve``.

Each iterator owns one DEALER connection served by a background I/O thread. The thread
says ``hello`` (the outputs wanted, the initial credits and the resume state), receives
batches, sends heartbeats, and sends an ``ack`` with one new credit for each batch as it is
handed to the training loop. So the server never has more than ``credits`` batches in flight to this iterator, and
a slow trainer never grows anybody's memory.

Sharing one stream: the server hands every batch to exactly one connection. Each DataLoader
worker process (``num_workers > 0``) and each DDP rank opens its own connection when it
starts iterating, so they split the stream between them without duplicates and without any
sharding arguments; ranks that must see equal batch counts per step should use the same
``batch_size`` and stop on the shortest rank (the last batch of an epoch may be smaller).
"""
from __future__ import annotations

import logging
import queue
import threading
import time
import uuid
import warnings
from typing import Dict, Iterator, Optional, Sequence, Set, Tuple, Union

import numpy as np
import torch
import zmq

from v2v_server.protocol import ProtocolError, decode_arrays, pack, unpack

from .fanin import FanInStream, resolve_endpoints, split_endpoints  # [iss12]
from .metrics import TrainerMetrics  # [iss12]

log = logging.getLogger("v2v.client")

ALL_OUTPUTS = ("voxels", "frames", "flow")
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


class _Connection:
    """One DEALER connection and its I/O thread (internal).

    The thread owns the socket. It hands the consumer decoded batches and control items
    through ``items``; the consumer hands back acknowledgements through an inproc pair.
    """

    def __init__(self, ds: "V2VStreamDataset"):
        self.ds = ds
        self.endpoint = ds.endpoint
        self.items: "queue.Queue" = queue.Queue()
        self.info: Optional[dict] = None
        self._reply: Optional[bytes] = None
        self._closing = threading.Event()
        self._ctx = zmq.Context.instance()
        self._ident = uuid.uuid4().bytes
        self._ack_addr = f"inproc://v2v-ack-{uuid.uuid4().hex}"
        self._ack_recv = self._ctx.socket(zmq.PAIR)
        self._ack_recv.bind(self._ack_addr)
        self._ack_send = self._ctx.socket(zmq.PAIR)
        self._ack_send.connect(self._ack_addr)
        # a batch is either taken by the training loop (and acknowledged) or released back to
        # the server after its lease expired, never both: the lock makes the choice exclusive
        self.lock = threading.Lock()
        self.taken: Set[int] = set()
        self.revoked: Set[int] = set()
        self._thread = threading.Thread(target=self._run, name="v2v-stream-io", daemon=True)
        self._thread.start()

    # consumer side -------------------------------------------------------
    def take(self, batch_id: int) -> bool:
        """Claim a batch for the training loop and acknowledge it; False if it was released."""
        with self.lock:
            if batch_id in self.revoked:
                return False
            self.taken.add(batch_id)
        self.ack(batch_id)
        return True

    def ack(self, batch_id: int) -> None:
        if not self._closing.is_set():
            self._ack_send.send(pack({"type": "ack", "batch_ids": [batch_id], "credit": 1}))

    def close(self) -> None:
        if self._closing.is_set():
            return
        self._closing.set()
        self._thread.join(5.0)
        self._ack_send.close(0)
        self.items.put(StopIteration("closed"))  # [iss12] wake an iterator blocked on this connection

    # I/O thread ------------------------------------------------------------
    def _socket(self) -> zmq.Socket:
        sock = self._ctx.socket(zmq.DEALER)
        sock.setsockopt(zmq.IDENTITY, self._ident)
        sock.setsockopt(zmq.LINGER, 200)
        sock.setsockopt(zmq.MAXMSGSIZE, MAX_SERVER_MSG)
        sock.setsockopt(zmq.RCVHWM, 0)
        if self.ds.curve is not None:
            pub, sec, server_pub = self.ds.curve
            sock.curve_publickey, sock.curve_secretkey, sock.curve_serverkey = pub, sec, server_pub
        sock.connect(self.endpoint)
        sock.send(self._hello())
        return sock

    def _poller(self, sock: zmq.Socket) -> zmq.Poller:
        poller = zmq.Poller()
        poller.register(sock, zmq.POLLIN)
        poller.register(self._ack_recv, zmq.POLLIN)
        return poller

    def _hello(self) -> bytes:
        return pack({"type": "hello", "outputs": list(self.ds.outputs), "credits": self.ds.credits,
                     "resume": self.ds._resume_state()})

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
                if self._ack_recv in events:
                    while True:
                        try:
                            sock.send(self._ack_recv.recv(zmq.NOBLOCK))
                        except zmq.Again:
                            break
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
                        if self._reply is not None:
                            sock.send(self._reply)
                            self._reply = None
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
                    sock.send(pack({"type": "heartbeat"}))
                    next_beat = now + self.ds.heartbeat_s
        except Exception as e:  # never die silently: hand the error to the consumer
            self.items.put(StreamError(f"stream from {self.endpoint} failed: {type(e).__name__}: {e}"))
        finally:
            if sock is not None:
                try:
                    sock.send(pack({"type": "bye"}), zmq.NOBLOCK)
                except zmq.ZMQError:
                    pass
                sock.close()
            self._ack_recv.close(0)

    def _on_message(self, frames) -> Optional[str]:
        """Handle one server message; "over" when the stream has ended or failed, "lost"
        when the server is shutting down."""
        try:
            h = unpack(frames[0])
            kind = h["type"]
            if kind == "batch":
                arrays = decode_arrays(h.get("arrays"), frames[1:], MAX_SERVER_MSG)
                missing = [o for o in self.ds.outputs if o not in arrays]
                if missing:
                    raise ProtocolError(f"batch {h.get('batch_id')} lacks requested outputs {missing}")
                ids = h["sample_ids"]
                if not isinstance(ids, list) or any(a.shape[:1] != (len(ids),) for a in arrays.values()):
                    raise ProtocolError(f"batch {h.get('batch_id')}: sample ids do not match the arrays")
                with self.lock:  # a batch we released may come back to us: take it this time
                    self.revoked.discard(int(h["batch_id"]))
                item = batch_to_torch(arrays, self.ds.raw)
                item["sample_ids"] = list(ids)
                item["params"] = list(h["params"])
                item["epoch"] = int(h["epoch"])
                item["batch_id"] = int(h["batch_id"])
                self.items.put(item)
            elif kind == "welcome":
                self.info = h.get("info", {})
            elif kind == "revoke":
                ids = h.get("batch_ids") if isinstance(h.get("batch_ids"), list) else []
                with self.lock:
                    released = [b for b in ids if isinstance(b, int) and b not in self.taken]
                    self.revoked.update(released)
                if released:
                    self._reply = pack({"type": "released", "batch_ids": released, "credit": len(released)})
            elif kind == "epoch_done":
                self.items.put(_EpochDone(int(h["epoch"])))
            elif kind == "end":
                self.items.put(StopIteration(h.get("reason", "end of stream")))
                return "over"
            elif kind == "shutdown":
                return "lost"
            elif kind == "error" and h.get("code") == "unknown_client" and self.ds.reconnect:
                # the server restarted behind our socket: introduce ourselves again, with our resume state
                log.warning("the v2v server at %s restarted; resuming", self.endpoint)
                self._reply = self._hello()
            elif kind == "error":
                self.items.put(StreamError(f"v2v server at {self.endpoint}: {h.get('message')}"))
                return "over"
        except (ProtocolError, KeyError, TypeError, ValueError) as e:
            self.items.put(StreamError(f"bad message from the v2v server at {self.endpoint}: {e}"))
            return "over"
        return None


class _EpochDone:
    def __init__(self, epoch: int):
        self.epoch = epoch


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
            ``state_dict()`` covers them all.
        outputs: which of ``"voxels"``, ``"frames"``, ``"flow"`` to receive; the server's
            workers compute only these.
        credits: batches the server may have in flight to this iterator (prefetch depth).
        timeout_s: seconds without any message from the server (batches or heartbeats)
            before iteration raises ``StreamTimeout``; also bounds the wait for the first
            answer, so an absent server gives a clear error, never a hang.
        heartbeat_s: seconds between heartbeats to the server.
        raw: keep wire dtypes (int8/int16 voxels, uint8 frames, float16 flow) for
            conversion on the GPU.
        reconnect: on a silent or restarting server, reconnect (with the delivered-sample
            state, so nothing is repeated) for up to ``reconnect_timeout_s`` seconds
            instead of raising.
        curve_keys: ``(client_secret_file, server_public_file)`` from ``v2v-keygen`` to talk
            to a server that requires CurveZMQ.

    Yields dicts, one per batch of B samples:
        ``voxels`` float32 (B, L, num_bins, H, W), signed event counts per bin;
        ``frames`` float32 in [0, 1] (B, L + 1, 1, H, W), the frame at each voxel boundary;
        ``flow`` float32 (B, L, 2, H, W), forward optical flow in pixels from frame l to
        l + 1 (channel 0 = x, 1 = y);
        ``sample_ids`` list of B str; ``params`` list of B dicts (sensor parameters and
        augmentation); ``epoch`` int; ``batch_id`` int. Only requested outputs are present.

    Within an epoch each sample id is yielded once: a batch the server sends again (after a
    lost acknowledgement, a reconnect or a restart) is filtered against the ids already
    yielded. ``state_dict()`` / ``load_state_dict()`` (torchdata StatefulDataLoader
    convention) carry those ids across a trainer restart.

    Use with ``DataLoader(ds, batch_size=None, pin_memory=True)``. Iteration ends when the
    server ends the stream (``--epochs``).

    Raises (from iteration):
        StreamTimeout: the server is absent or silent for ``timeout_s``.
        StreamError: the server reported an error, broke the protocol or shut down.
        ValueError: at construction, for bad ``outputs``, ``credits``, ``timeout_s`` or keys.
    """

    def __init__(self, endpoint: Union[str, Sequence[str]], outputs: Sequence[str] = ALL_OUTPUTS, credits: int = 4,
                 timeout_s: float = 30.0, heartbeat_s: float = 1.0, raw: bool = False,
                 reconnect: bool = False, reconnect_timeout_s: float = 300.0,
                 curve_keys: Optional[Tuple[str, str]] = None):
        # [iss12] every constructor argument but the endpoint, for one dataset per server (fan-in)
        self._child_kwargs = {k: v for k, v in locals().items() if k not in ("self", "endpoint", "__class__")}
        super().__init__()
        if isinstance(outputs, str):
            outputs = (outputs,)
        outputs = tuple(outputs)
        bad = [o for o in outputs if o not in ALL_OUTPUTS]
        if bad or not outputs:
            raise ValueError(f"outputs must be a non-empty subset of {list(ALL_OUTPUTS)}, got {list(outputs)}")
        if isinstance(credits, bool) or not isinstance(credits, int) or not 1 <= credits <= 1024:
            raise ValueError(f"credits must be an int in [1, 1024], got {credits!r}")
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        self.endpoint = endpoint
        self.outputs = tuple(o for o in ALL_OUTPUTS if o in outputs)
        self.credits = credits
        self.timeout_s = float(timeout_s)
        self.heartbeat_s = float(heartbeat_s)
        self.raw = raw
        self.reconnect = bool(reconnect)
        self.reconnect_timeout_s = float(reconnect_timeout_s)
        self.curve = load_curve_keys(*curve_keys) if curve_keys else None
        self.info: Optional[dict] = None
        self._conns: list = []
        self._lock = threading.Lock()
        self._delivered: Dict[int, Set[str]] = {}
        self._completed_epoch = -1
        # [iss12] several servers (a list, "a,b", or a DNS name with several addresses): fan-in
        self._fanin: Optional[FanInStream] = None
        self._meter = TrainerMetrics()
        if not isinstance(endpoint, str) or "," in endpoint:
            endpoints = split_endpoints(endpoint)
            if len(endpoints) == 1:
                self.endpoint = endpoints[0]
            else:
                self._fanin = self._make_fanin(endpoints)

    # ------------------------------------------------------------------ fan-in and metrics [iss12]
    def _make_fanin(self, endpoints) -> FanInStream:
        def child(ep: str, credits: int) -> "V2VStreamDataset":
            return V2VStreamDataset(ep, **dict(self._child_kwargs, credits=credits))

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
        """Where this consumer stands: epochs the server declared complete, and the sample ids
        yielded so far in epochs still open. Plain, JSON/torch.save-safe data. With several
        servers: the epoch all of them completed and the ids yielded in later epochs."""
        if self._fanin is not None:  # [iss12]
            return self._fanin.state_dict()
        with self._lock:
            return {"version": 1, "completed_epoch": self._completed_epoch,
                    "delivered": {str(e): sorted(ids) for e, ids in self._delivered.items()}}

    def load_state_dict(self, state: dict) -> None:
        """Restore ``state_dict()`` output; the next iteration resumes the epoch without
        repeating or skipping samples.

        Raises:
            ValueError: for a state of another format.
        """
        if not isinstance(state, dict) or state.get("version") != 1:
            raise ValueError("state must come from V2VStreamDataset.state_dict() (version 1)")
        with self._lock:
            self._completed_epoch = int(state.get("completed_epoch", -1))
            self._delivered = {int(e): set(ids) for e, ids in state.get("delivered", {}).items()}
        if self._fanin is not None:  # [iss12]
            self._fanin.load_state_dict(state)

    def _resume_state(self) -> dict:
        with self._lock:
            return {"completed_epoch": self._completed_epoch,
                    "delivered": {str(e): sorted(ids) for e, ids in self._delivered.items()}}

    # ------------------------------------------------------------------ iteration
    def _iter_stream(self) -> Iterator[dict]:  # [iss12] was __iter__; unchanged
        conn = _Connection(self)
        self._conns.append(conn)
        try:
            while True:
                try:
                    item = conn.items.get(timeout=self.timeout_s + (self.reconnect_timeout_s if self.reconnect else 0)
                                          + 5.0)
                except queue.Empty:
                    raise StreamTimeout(f"no batch from the v2v server at {self.endpoint} "
                                        f"for {self.timeout_s:.0f} s") from None
                if isinstance(item, StopIteration):
                    return
                if isinstance(item, BaseException):
                    raise item
                if isinstance(item, _EpochDone):
                    with self._lock:
                        self._completed_epoch = max(self._completed_epoch, item.epoch)
                        for e in [e for e in self._delivered if e <= item.epoch]:
                            del self._delivered[e]
                    continue
                self.info = conn.info
                if not conn.take(item["batch_id"]):
                    continue  # its lease expired while queued here; the server sends it elsewhere
                epoch = item["epoch"]
                with self._lock:
                    seen = self._delivered.setdefault(epoch, set())
                    keep = [i for i, sid in enumerate(item["sample_ids"]) if sid not in seen]
                    if epoch <= self._completed_epoch:
                        keep = []
                    seen.update(item["sample_ids"][i] for i in keep)
                if not keep:  # all re-sent duplicates: hand nothing on
                    continue
                if len(keep) < len(item["sample_ids"]):
                    item = _select(item, keep)
                yield item
        finally:
            conn.close()
            if conn in self._conns:
                self._conns.remove(conn)

    def close(self) -> None:
        """Close every open connection of this dataset (also done when iterators are collected)."""
        if self._fanin is not None:  # [iss12]
            self._fanin.close()
        for conn in list(self._conns):
            conn.close()
        self._conns.clear()

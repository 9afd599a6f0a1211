"""``V2VStreamDataset``: a torch IterableDataset reading batches from ``v2v-serve``.

Each iterator owns one DEALER connection served by a background I/O thread. The thread
says ``hello`` (the outputs wanted and the initial credits), receives batches, answers
heartbeats, and sends an ``ack`` with one new credit for each batch the training loop has
taken. So the server never has more than ``credits`` batches in flight to this iterator, and
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
from typing import Dict, Iterator, Optional, Sequence

import numpy as np
import torch
import zmq

from v2v_server.protocol import ProtocolError, decode_arrays, pack, unpack

log = logging.getLogger("v2v.client")

ALL_OUTPUTS = ("voxels", "frames", "flow")
#: Largest message accepted from the server, bytes (ZMQ_MAXMSGSIZE).
MAX_SERVER_MSG = 1 << 31


class StreamError(RuntimeError):
    """The server sent an error, broke the protocol, or went silent (the message says which)."""


class StreamTimeout(StreamError, TimeoutError):
    """No message from the server within ``timeout_s``."""


def batch_to_torch(arrays: Dict[str, np.ndarray], raw: bool = False) -> Dict[str, torch.Tensor]:
    """Convert wire arrays of one batch to tensors.

    With ``raw=False``: ``voxels`` float32 (B, L, num_bins, H, W) event counts; ``frames``
    float32 in [0, 1] (B, L + 1, 1, H, W); ``flow`` float32 (B, L, 2, H, W), pixels.
    With ``raw=True`` the wire dtypes are kept (voxels int8/int16/int32, frames uint8 with
    the channel axis, flow float16), for conversion on the GPU.
    """
    out = {}
    for name, a in arrays.items():
        if name == "frames":
            a = a[:, :, None]
        if raw:
            out[name] = torch.from_numpy(np.array(a, copy=True))
        elif name == "frames":
            t = torch.from_numpy(a.astype(np.float32))
            out[name] = t.mul_(1.0 / 255.0)
        else:
            out[name] = torch.from_numpy(a.astype(np.float32))
    return out


class _Connection:
    """One DEALER connection and its I/O thread (internal)."""

    def __init__(self, endpoint: str, outputs: Sequence[str], credits: int, timeout_s: float,
                 heartbeat_s: float, raw: bool):
        self.endpoint, self.outputs, self.credits = endpoint, list(outputs), credits
        self.timeout_s, self.heartbeat_s, self.raw = timeout_s, heartbeat_s, raw
        self.items: "queue.Queue" = queue.Queue()
        self.info: Optional[dict] = None
        self._closing = threading.Event()
        self._ctx = zmq.Context.instance()
        self._ack_addr = f"inproc://v2v-ack-{uuid.uuid4().hex}"
        self._ack_recv = self._ctx.socket(zmq.PAIR)
        self._ack_recv.bind(self._ack_addr)
        self._ack_send = self._ctx.socket(zmq.PAIR)
        self._ack_send.connect(self._ack_addr)
        self._thread = threading.Thread(target=self._run, name="v2v-stream-io", daemon=True)
        self._thread.start()

    # consumer side -------------------------------------------------------
    def ack(self, batch_id: int) -> None:
        if not self._closing.is_set():
            self._ack_send.send(pack({"type": "ack", "batch_ids": [batch_id], "credit": 1}))

    def close(self) -> None:
        if self._closing.is_set():
            return
        self._closing.set()
        self._thread.join(5.0)
        self._ack_send.close(0)

    # I/O thread ------------------------------------------------------------
    def _run(self) -> None:
        sock = self._ctx.socket(zmq.DEALER)
        sock.setsockopt(zmq.IDENTITY, uuid.uuid4().bytes)
        sock.setsockopt(zmq.LINGER, 200)
        sock.setsockopt(zmq.MAXMSGSIZE, MAX_SERVER_MSG)
        sock.setsockopt(zmq.RCVHWM, 0)
        try:
            sock.connect(self.endpoint)
            sock.send(pack({"type": "hello", "outputs": self.outputs, "credits": self.credits}))
            last_heard = time.monotonic()
            next_beat = last_heard + self.heartbeat_s
            poller = zmq.Poller()
            poller.register(sock, zmq.POLLIN)
            poller.register(self._ack_recv, zmq.POLLIN)
            while not self._closing.is_set():
                events = dict(poller.poll(100))
                now = time.monotonic()
                if self._ack_recv in events:
                    while True:
                        try:
                            sock.send(self._ack_recv.recv(zmq.NOBLOCK))
                        except zmq.Again:
                            break
                if sock in events:
                    while True:
                        try:
                            frames = sock.recv_multipart(zmq.NOBLOCK, copy=False)
                        except zmq.Again:
                            break
                        last_heard = now
                        if self._on_message(frames):
                            return
                if now - last_heard > self.timeout_s:
                    what = "no answer" if self.info is None else "no message"
                    self.items.put(StreamTimeout(
                        f"{what} from the v2v server at {self.endpoint} for {self.timeout_s:.0f} s "
                        f"(is v2v-serve running and reachable?)"))
                    return
                if now >= next_beat:
                    sock.send(pack({"type": "heartbeat"}))
                    next_beat = now + self.heartbeat_s
        except Exception as e:  # never die silently: hand the error to the consumer
            self.items.put(StreamError(f"stream from {self.endpoint} failed: {type(e).__name__}: {e}"))
        finally:
            try:
                sock.send(pack({"type": "bye"}), zmq.NOBLOCK)
            except zmq.ZMQError:
                pass
            sock.close()
            self._ack_recv.close(0)

    def _on_message(self, frames) -> bool:
        """Handle one server message; True when the stream is over."""
        try:
            h = unpack(frames[0])
            kind = h["type"]
            if kind == "batch":
                arrays = decode_arrays(h.get("arrays"), frames[1:], MAX_SERVER_MSG)
                missing = [o for o in self.outputs if o not in arrays]
                if missing:
                    raise ProtocolError(f"batch {h.get('batch_id')} lacks requested outputs {missing}")
                item = batch_to_torch(arrays, self.raw)
                item["sample_ids"] = list(h["sample_ids"])
                item["params"] = list(h["params"])
                item["epoch"] = int(h["epoch"])
                item["batch_id"] = int(h["batch_id"])
                self.items.put(item)
            elif kind == "welcome":
                self.info = h.get("info", {})
            elif kind == "end":
                self.items.put(StopIteration(h.get("reason", "end of stream")))
                return True
            elif kind == "error":
                self.items.put(StreamError(f"v2v server at {self.endpoint}: {h.get('message')}"))
                return True
        except (ProtocolError, KeyError, TypeError, ValueError) as e:
            self.items.put(StreamError(f"bad message from the v2v server at {self.endpoint}: {e}"))
            return True
        return False


class V2VStreamDataset(torch.utils.data.IterableDataset):
    """Batches of V2V training data streamed from a ``v2v-serve`` endpoint.

    Args:
        endpoint: ZeroMQ endpoint of the server, e.g. ``tcp://127.0.0.1:5555``.
        outputs: which of ``"voxels"``, ``"frames"``, ``"flow"`` to receive; the server's
            workers compute only these.
        credits: batches the server may have in flight to this iterator (prefetch depth).
        timeout_s: seconds without any message from the server (batches or heartbeats)
            before iteration raises ``StreamTimeout``; also bounds the wait for the first
            answer, so an absent server gives a clear error, never a hang.
        heartbeat_s: seconds between heartbeats to the server.
        raw: keep wire dtypes (int8/int16 voxels, uint8 frames, float16 flow) for
            conversion on the GPU.

    Yields dicts, one per batch of B samples:
        ``voxels`` float32 (B, L, num_bins, H, W), signed event counts per bin;
        ``frames`` float32 in [0, 1] (B, L + 1, 1, H, W), the frame at each voxel boundary;
        ``flow`` float32 (B, L, 2, H, W), forward optical flow in pixels from frame l to
        l + 1 (channel 0 = x, 1 = y);
        ``sample_ids`` list of B str; ``params`` list of B dicts (sensor parameters and
        augmentation); ``epoch`` int; ``batch_id`` int. Only requested outputs are present.

    Use with ``DataLoader(ds, batch_size=None, pin_memory=True)``. Iteration ends when the
    server ends the stream (``--epochs``).

    Raises (from iteration):
        StreamTimeout: the server is absent or silent for ``timeout_s``.
        StreamError: the server reported an error or broke the protocol.
        ValueError: at construction, for bad ``outputs``, ``credits`` or ``timeout_s``.
    """

    def __init__(self, endpoint: str, outputs: Sequence[str] = ALL_OUTPUTS, credits: int = 4,
                 timeout_s: float = 30.0, heartbeat_s: float = 1.0, raw: bool = False):
        super().__init__()
        if isinstance(outputs, str):
            outputs = (outputs,)
        outputs = tuple(outputs)
        bad = [o for o in outputs if o not in ALL_OUTPUTS]
        if bad or not outputs:
            raise ValueError(f"outputs must be a non-empty subset of {list(ALL_OUTPUTS)}, got {list(outputs)}")
        if not isinstance(credits, int) or not 1 <= credits <= 1024:
            raise ValueError(f"credits must be an int in [1, 1024], got {credits!r}")
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        self.endpoint = endpoint
        self.outputs = tuple(o for o in ALL_OUTPUTS if o in outputs)
        self.credits = credits
        self.timeout_s = float(timeout_s)
        self.heartbeat_s = float(heartbeat_s)
        self.raw = raw
        self.info: Optional[dict] = None
        self._conns: list = []

    def __iter__(self) -> Iterator[dict]:
        conn = _Connection(self.endpoint, self.outputs, self.credits, self.timeout_s, self.heartbeat_s, self.raw)
        self._conns.append(conn)
        try:
            while True:
                try:
                    item = conn.items.get(timeout=self.timeout_s + 5.0)
                except queue.Empty:
                    raise StreamTimeout(f"no batch from the v2v server at {self.endpoint} "
                                        f"for {self.timeout_s:.0f} s") from None
                if isinstance(item, StopIteration):
                    return
                if isinstance(item, BaseException):
                    raise item
                self.info = conn.info
                yield item
                conn.ack(item["batch_id"])
        finally:
            conn.close()
            if conn in self._conns:
                self._conns.remove(conn)

    def close(self) -> None:
        """Close every open connection of this dataset (also done when iterators are collected)."""
        for conn in list(self._conns):
            conn.close()
        self._conns.clear()

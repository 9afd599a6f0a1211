"""The server loop's client side: messages from trainers in, batches and control messages out.

``ClientSide`` decodes each client message with bounds (``v2v_wire.messages``), strikes and
bans peers that send garbage, passes the rest to the delivery core, and sends what the core
says: batches (as shared-memory references to clients on this host that asked for them, else
as frames in the compression each client asked for), revokes, epoch ends and errors.
"""
from __future__ import annotations

import logging
import time
from typing import Dict, List, Optional

import zmq

from v2v_server.delivery.core import DeliveryCore
from v2v_server.ops.config import ServeConfig
from v2v_server.ops.metrics import ServerMetrics
from v2v_server.service.assembly import BatchAssembler
from v2v_wire import codecs
from v2v_wire.messages import BadPeers, Hello, PlanClientMessage, WireError, decode_client
from v2v_wire.protocol import MAX_CLIENT_MSG, pack
from v2v_wire.stream_messages import Batch, EpochDone, Granted, Revoke, ServerError, StreamMessage

log = logging.getLogger("v2v.server")

#: Client messages handled per loop turn (then the workers get their turn).
CLIENT_BURST = 100


class ClientSide:
    """The clients as the server loop sees them.

    Args:
        cfg: the server's ``ServeConfig``.
        core: the delivery core.
        metrics: counters of batches, bytes, leases and bad messages.

    ``attach(frontend, assembler)`` once the socket is bound (``assembler``: the batch
    buffers; its ``files`` are what shared-memory clients read).
    """

    def __init__(self, cfg: ServeConfig, core: DeliveryCore, metrics: ServerMetrics):
        self.cfg, self.core, self.metrics = cfg, core, metrics
        self.assembler: Optional[BatchAssembler] = None
        self.frontend: Optional[zmq.Socket] = None
        self.bad = BadPeers()
        self.shm_clients: set = set()  # idents whose hello asked for shared-memory batches
        self.compression: Dict[bytes, str] = {}  # ident -> the compression its hello asked for

    def attach(self, frontend: zmq.Socket, assembler: BatchAssembler) -> None:
        self.frontend, self.assembler = frontend, assembler

    def socket_codecs(self) -> List[str]:
        """The codecs connected clients asked for over sockets (what workers compress with)."""
        connected = set(self.core.connected())
        return sorted({c for i, c in self.compression.items() if c != "none" and i in connected
                       and i not in self.shm_clients})

    def send_batches(self, now: float) -> None:
        """Ask the core what to send now (batches, revokes, epoch ends) and send it; a
        client that cannot be reached is forgotten (its batches go to others)."""
        sends, msgs = self.core.tick(now)
        for ident, b in sends:
            outputs = self.core.client_outputs(ident)
            if outputs is None:
                continue
            ref = None
            if ident in self.shm_clients and b.batch_id >= 0:  # same host: a reference into the batch file
                ref = b.payload.shm_ref(outputs)
            if ref is not None:
                (specs, shm), frames = ref, []
                nbytes = sum(b.payload.arrays[s["name"]].nbytes for s in specs)
            else:  # compressed arrays are the workers' frames, forwarded as they came
                specs, frames = b.payload.wire(outputs, self.compression.get(ident, "none"))
                nbytes = sum(_nbytes(f) for f in frames)
            # batch id < 0: DDP padding, a repeat for a rank that has nothing to repeat; never acked
            header = Batch(b.batch_id, b.epoch, tuple(b.payload.sample_ids), tuple(b.payload.meta), tuple(specs),
                           shm if ref is not None else None, b.batch_id < 0)
            try:
                b.payload.send(self.frontend, [ident, pack(header.to_wire())], frames)
            except zmq.ZMQError as e:  # peer vanished (ROUTER_MANDATORY)
                log.warning("client %s unreachable (%s); dropping it", ident.hex(), e)
                self.core.unreachable(ident)
                continue
            self.metrics.on_batch_sent(len(b.payload.sample_ids), nbytes)
        self._durable(msgs)
        for ident, msg in msgs:
            if isinstance(msg, Revoke):
                for _ in msg.batch_ids:
                    self.metrics.on_lease_expired()
            self.send(ident, msg)

    def send(self, ident: bytes, msg: StreamMessage) -> None:
        """One control message (``v2v_wire.stream_messages``) to one client (forgotten once its
        last messages are read, if it cannot be reached: ``DeliveryCore.unreachable``)."""
        try:
            self.frontend.send_multipart([ident, pack(msg.to_wire())], zmq.NOBLOCK)
        except zmq.ZMQError:
            self.core.unreachable(ident)

    def read(self, ready: bool) -> None:
        """Read and answer up to :data:`CLIENT_BURST` client messages when the frontend is
        ``ready``; once nothing is left unread, the core forgets the clients found unreachable
        (``DeliveryCore.caught_up``)."""
        drained, replies = not ready, []
        for _ in range(CLIENT_BURST if ready else 0):
            try:
                frames = self.frontend.recv_multipart(zmq.NOBLOCK, copy=False)
            except zmq.Again:
                drained = True
                break
            replies += self.on_message(frames)
        self._durable(replies)
        for to, reply in replies:
            self.send(to, reply)
        if drained:  # what an unreachable client sent before it closed has been read
            self.core.caught_up()

    def _durable(self, msgs: List[tuple]) -> None:
        """What a grant or an epoch's end tells a client is on disk before it leaves
        (``Journal.durable``: one ``fsync`` for the turn's messages), so a host crash never
        takes from the journal what a client holds (docs/delivery.md, "Restarts with a journal")."""
        journal = self.core.journal
        if journal is not None and journal.unsynced and any(isinstance(m, (Granted, EpochDone)) for _, m in msgs):
            journal.durable()

    def broadcast(self, msg: StreamMessage) -> None:
        """One control message to every connected client."""
        for ident in self.core.connected():
            self.send(ident, msg)

    def _bad_peer(self, ident: bytes, why: str, now: float) -> None:
        self.metrics.on_bad_message()
        log_it, banned = self.bad.strike(ident, now)
        if log_it:
            log.warning("dropping client %s: %s", ident.hex(), why)
        if banned:
            log.warning("client %s keeps sending bad messages: ignoring it for %.0f s", ident.hex(), self.bad.ban_s)
        if not self.bad.banned(ident, now) or banned:
            self.send(ident, ServerError(f"protocol error: {why}"))
        self.core.forget(ident)

    def on_message(self, frames) -> List[tuple]:
        """One message from a client (identity frame, message frame): decoded with bounds and
        schema-checked; returns the core's answers, ``[(ident, message)]``, for :meth:`read` to
        send. A bad one strikes its peer (``messages.BadPeers``) and is answered here."""
        ident = frames[0].bytes
        now = time.monotonic()
        if self.bad.banned(ident, now):
            return []
        try:
            if len(frames) != 2:
                raise WireError(f"expected 1 frame after the identity, got {len(frames) - 1}")
            msg = decode_client(frames[1], MAX_CLIENT_MSG, self.cfg.max_credits, self.cfg.crops_per_window,
                                self.core.resume_bound)
        except PlanClientMessage:  # told in the plan protocol's words, which that reader reads
            self.send(ident, ServerError("this server delivers by push (v2v-serve --delivery push)"))
            return []
        except WireError as e:
            self._bad_peer(ident, str(e), now)
            return []
        if isinstance(msg, Hello):
            connected = set(self.core.connected())
            self.shm_clients &= connected  # forget clients gone since
            if msg.shm and self.assembler.files is not None:
                self.shm_clients.add(ident)
            else:
                self.shm_clients.discard(ident)
            for gone in set(self.compression) - connected:
                del self.compression[gone]
            if not codecs.available(msg.compression):
                self.send(ident, ServerError(f"this server cannot compress with {msg.compression!r}: "
                                             f"{msg.compression} needs the 'wire' extra on the server "
                                             f"(pip install 'v2v[wire]'); ask for compression 'none'", "compression"))
                return []
            self.compression[ident] = msg.compression
            return self.core.hello(ident, msg, now)
        return self.core.message(ident, msg, now)


def _nbytes(frame) -> int:
    """Bytes of an outgoing frame (a numpy array, or a worker's compressed frame)."""
    return frame.nbytes if hasattr(frame, "nbytes") else len(frame.buffer if hasattr(frame, "buffer") else frame)

"""One connection to one ``v2v-serve``: a DEALER socket served by a background I/O thread that
only moves bytes and keeps time.

The thread connects, reconnects when the server is lost (``options.reconnect``), declares a
silent server gone after ``timeout_s``, and carries bytes: the server's messages into the
connection's :class:`~v2v_client.session.ServerSession`, a ``StreamLoader``'s receipts into it,
and everything the session decides to send (hello, holds, acks, releases, heartbeats, bye) out
to the socket. What the messages mean and which ones to send is the session's alone
(docs/delivery.md, "The protocol"); neither imports torch (the stream passes
``tensors.batch_to_torch`` as the conversion). ``endpoint.EndpointStream`` owns its connection
and the reader's record; the connection reports to it only through the ``items`` queue.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
import uuid
from typing import Callable, Optional, Tuple

import zmq

from v2v_wire.protocol import is_ipv6, pack

from .receipts import loader_message
from .session import MAX_SERVER_MSG, Convert, ServerSession, StreamError, StreamTimeout

__all__ = ["Connection", "StreamError", "StreamTimeout", "MAX_SERVER_MSG", "load_curve_keys"]

log = logging.getLogger("v2v.client")


def own_stall(gap: float, timeout_s: float) -> float:
    """Seconds of a gap of ``gap`` between two turns of the I/O loop that were this process's
    own stall (stopped, or starved of a core), not the server's silence: all of a gap longer
    than half of ``timeout_s``, none of a shorter one. A client stopped past its timeout wakes,
    reads what came, says a heartbeat (a restarted server answers ``unknown_client``, and it
    says hello again) and raises ``StreamTimeout`` only if the server stays silent while it runs."""
    return gap if gap > timeout_s / 2 else 0.0


class Connection:
    """One DEALER connection to one endpoint and its I/O thread, which owns the socket. It reports
    only through ``items`` (decoded batches and control items) and keeps no protocol state: that
    is its :class:`~v2v_client.session.ServerSession` ``session``. A batch is either taken by the
    loop once granted (``take``) or given back, never both (``session.held``: arrays freed at once).

    Args:
        endpoint: the server's ZeroMQ endpoint.
        options: the stream's ``options.StreamOptions``.
        record: the reader's ``resume.ResumeState`` (thread-safe; see ``ServerSession``).
        consumer: the id the hello names the reader by.
        convert: makes a batch's numpy arrays the consumer's (None keeps numpy arrays).
        receipts, iteration: in a DataLoader worker under ``StreamLoader``, the pipe on which
            the main process says which batches the training loop received, and the loader's
            iteration this connection serves.
        instance: the reader process's token (``ServerSession``).

    Raises:
        ValueError: for ``options.curve_keys`` naming bad key files.
    """

    def __init__(self, endpoint: str, options, record, consumer: str, convert: Optional[Convert] = None,
                 receipts=None, iteration: int = 0, instance: str = ""):
        self.endpoint, self.options, self.record = endpoint, options, record
        self.curve = load_curve_keys(*options.curve_keys) if options.curve_keys else None
        self.session = ServerSession(endpoint, options, record, consumer, convert=convert,
                                     ends_on_drained=receipts is not None, iteration=iteration, instance=instance)
        self._closing = threading.Event()
        self._ctx = zmq.Context.instance()
        self._wake = Wakeup(self._ctx)
        self._lingering, self._receipts = False, receipts  # DataLoader worker: what the training loop received
        self._unreceived = False  # close: the loader dropped what this worker queued
        self._thread = threading.Thread(target=self._run, name="v2v-stream-io", daemon=True)
        self._thread.start()

    @property
    def items(self) -> "queue.Queue":
        """What the I/O thread hands the consumer (see :class:`ServerSession`)."""
        return self.session.items

    @property
    def info(self) -> Optional[dict]:
        """The server's stream info from its welcome (None before it)."""
        return self.session.info

    def held(self) -> int:
        """Batches received and neither taken by the consumer nor given back."""
        return len(self.session.held)

    def ends_on(self, drained) -> bool:
        """A DataLoader worker's iteration ends on this ``drained`` (``HeldBatches.ends_on``)."""
        return self.session.held.ends_on(drained)

    def of_session(self, item, then: Callable[[bool], object] = lambda current: None) -> bool:
        """An epoch end or padding the loop takes was told to the current session (``HeldBatches.of_session``)."""
        return self.session.held.of_session(item, then)

    def ended(self) -> bool:
        """True once the I/O thread has ended and every item it queued was taken."""
        return not self._thread.is_alive() and self.session.items.empty()

    def _open(self) -> bool:
        return not self._closing.is_set() and self._thread.is_alive()

    # consumer side -------------------------------------------------------
    def take(self, item: dict, on_claim: Callable[[], object] = lambda: None, ack: bool = True) -> Tuple[bool, object]:
        """``ServerSession.take`` (waiting for the grant while this connection is open); the I/O
        thread is woken to send what it decided. ``(False, None)`` also when the connection ended."""
        result = self.session.take(item, on_claim, self._open, ack)
        self._wake.ping()
        return result

    def ack(self, batch_ids) -> None:
        """Acknowledge batches this connection took (``ServerSession.ack``)."""
        self.session.ack(batch_ids)
        self._wake.ping()

    def give_back(self, item: dict) -> None:
        """Return a received batch unused (``ServerSession.give_back``)."""
        self.session.give_back(item)
        self._wake.ping()

    def linger(self) -> None:
        """The iteration ended with batches still in a DataLoader's queues: keep taking their
        receipts, and close once none is left (or at :meth:`close`)."""
        self._lingering = True

    def close(self, unreceived: bool = False) -> None:
        """Stop the I/O thread: what the session queued goes out, then its last messages
        (``ServerSession.closing``; ``unreceived``: the loader dropped this worker's batches)."""
        if self._closing.is_set():
            return
        self._unreceived = unreceived
        self._closing.set()
        self._thread.join(5.0)
        self._wake.close_sender()
        self.session.items.put(StopIteration("closed"))  # wake an iterator blocked on this connection

    # the I/O thread ------------------------------------------------------
    def _socket(self) -> zmq.Socket:
        """A new socket, with an identity of its own: what the server sent the old one (batches,
        grants, revokes of the session that was) can never arrive on it, and the server lets the
        new connection in as the same reader's (docs/delivery.md, "Who may say hello")."""
        sock = self._ctx.socket(zmq.DEALER)
        sock.setsockopt(zmq.IDENTITY, uuid.uuid4().bytes)
        sock.setsockopt(zmq.LINGER, 1000)
        sock.setsockopt(zmq.MAXMSGSIZE, MAX_SERVER_MSG)
        sock.setsockopt(zmq.RCVHWM, 0)
        if is_ipv6(self.endpoint):
            sock.setsockopt(zmq.IPV6, 1)
        if self.curve is not None:
            pub, sec, server_pub = self.curve
            sock.curve_publickey, sock.curve_secretkey, sock.curve_serverkey = pub, sec, server_pub
        sock.connect(self.endpoint)
        self.session.hello(new_socket=True, at=time.monotonic())  # a new socket: no message of an older session
        self._send_out(sock)
        return sock

    def _send_out(self, sock: zmq.Socket) -> None:
        """Send what the session decided, in order."""
        for msg in self.session.outgoing():
            _send(sock, pack(msg.to_wire()))

    def _poller(self, sock: zmq.Socket) -> zmq.Poller:
        poller = zmq.Poller()
        poller.register(sock, zmq.POLLIN)
        poller.register(self._wake.receiver, zmq.POLLIN)
        if self._receipts is not None:
            poller.register(self._receipts.fileno(), zmq.POLLIN)
        return poller

    def _take_receipts(self) -> None:
        """Hand what ``StreamLoader`` wrote (``receipts.Receipt``, ``Abandon``) to the session."""
        while self._receipts is not None and self._receipts.poll(0):
            try:
                data = self._receipts.recv_bytes()
            except (EOFError, OSError):  # the main process is gone
                self._receipts = None
                return
            self.session.on_loader(loader_message(data))

    def _run(self) -> None:
        """The I/O thread: the loop over the socket; any failure goes to the consumer as a
        :class:`StreamError`, and the socket always closes with the session's last messages."""
        self._sock = None
        try:
            self._sock = self._socket()
            self._serve()
        except Exception as e:  # never die silently: hand the error to the consumer
            self.session.items.put(StreamError(f"stream from {self.endpoint} failed: {type(e).__name__}: {e}"))
        finally:
            self._finish(self._sock)
            self.session.held.discard(None)  # wakes a consumer waiting for a grant

    def _serve(self) -> None:
        """Poll the socket, the wake-up pipe and the receipts; move bytes both ways; on a lost
        server reconnect (``options.reconnect``) or end the stream with an error."""
        sock = self._sock
        give_up_at = None
        last_heard = last_turn = time.monotonic()
        poller = self._poller(sock)
        while not self._closing.is_set():
            events = dict(poller.poll(100))
            now = time.monotonic()
            last_heard += own_stall(now - last_turn, self.options.timeout_s)
            last_turn = now
            if self._wake.receiver in events:
                self._wake.drain()
            self._take_receipts()
            if self._lingering and self.session.lingering_done():
                return  # every batch handed to the DataLoader was received, or none will be: bye
            lost = None
            if sock in events:
                verdict, heard = self._receive(sock)
                if heard:
                    last_heard, give_up_at = now, None
                if verdict == "over":
                    return
                if verdict == "lost":
                    lost = "the server shut down"
            if lost is None and now - last_heard > self.options.timeout_s:
                lost = f"no message for {self.options.timeout_s:.0f} s"
            if lost is not None:
                give_up_at = self._lost(lost, now, give_up_at)
                if give_up_at is None:
                    return
                sock.close(0)
                sock = self._sock = self._socket()
                poller = self._poller(sock)
                last_heard = now
                continue
            self.session.tick(now)
            self._send_out(sock)

    def _receive(self, sock: zmq.Socket) -> Tuple[Optional[str], bool]:
        """Hand every message waiting on ``sock`` to the session and send what it decided:
        (``ServerSession.on_message``'s "over" or "lost" verdict, else None; whether any message came)."""
        heard = False
        while True:
            try:
                frames = sock.recv_multipart(zmq.NOBLOCK, copy=False)
            except zmq.Again:
                return None, heard
            heard = True
            verdict = self.session.on_message(frames)
            self._send_out(sock)
            if verdict in ("over", "lost"):
                return verdict, heard

    def _lost(self, why: str, now: float, give_up_at: Optional[float]) -> Optional[float]:
        """The server went away (``why``): the time to stop reconnecting at (``options.reconnect``),
        or None when the stream ends here (the error is queued for the consumer)."""
        if not self.options.reconnect:
            what = "no answer" if self.session.info is None else "no message"
            if why.startswith("no message"):
                self.session.items.put(StreamTimeout(
                    f"{what} from the v2v server at {self.endpoint} for {self.options.timeout_s:.0f} s "
                    f"(is v2v-serve running and reachable?)"))
            else:
                self.session.items.put(StreamError(
                    f"the v2v server at {self.endpoint} shut down mid-stream; restart it and resume "
                    f"with state_dict(), or use reconnect=True"))
            return None
        if give_up_at is None:
            log.warning("lost the v2v server at %s (%s); reconnecting for up to %.0f s",
                        self.endpoint, why, self.options.reconnect_timeout_s)
            return now + self.options.reconnect_timeout_s
        if now > give_up_at:
            self.session.items.put(StreamTimeout(f"could not reconnect to the v2v server at {self.endpoint} "
                                                 f"within {self.options.reconnect_timeout_s:.0f} s"))
            return None
        return give_up_at

    def _finish(self, sock: Optional[zmq.Socket]) -> None:
        """Close the I/O thread's sockets: what the session queued and its receipts go out
        before its last messages (``ServerSession.closing``)."""
        if sock is not None:
            try:
                self._take_receipts()
                for msg in self.session.outgoing() + self.session.closing(self._unreceived):
                    sock.send(pack(msg.to_wire()), zmq.NOBLOCK)
            except zmq.ZMQError:
                pass
            sock.close()
        self._wake.close_receiver()
        self.session.close()


class Wakeup:
    """Wakes the I/O thread when the consumer's steps decided messages (``ServerSession.take``,
    ``give_back``, ``ack``): a byte over an inproc PAIR the thread polls. The messages
    themselves wait in the session; a ping dropped on a full pipe is never needed (one is queued)."""

    def __init__(self, ctx: zmq.Context):
        addr = f"inproc://v2v-wake-{uuid.uuid4().hex}"
        self.receiver = ctx.socket(zmq.PAIR)
        self.receiver.bind(addr)
        self._sender = ctx.socket(zmq.PAIR)
        self._sender.connect(addr)
        self._lock = threading.Lock()

    def ping(self) -> None:
        with self._lock:
            if self._sender is None:
                return
            try:
                self._sender.send(b"", zmq.NOBLOCK)
            except zmq.ZMQError:
                pass

    def drain(self) -> None:
        """The I/O thread's side: take every ping waiting."""
        while True:
            try:
                self.receiver.recv(zmq.NOBLOCK)
            except zmq.Again:
                return

    def close_sender(self) -> None:
        with self._lock:
            if self._sender is not None:
                self._sender.close(0)
                self._sender = None

    def close_receiver(self) -> None:
        self.receiver.close(0)


def _send(sock: zmq.Socket, data: bytes) -> bool:
    """Send without blocking the I/O thread; False when no connection to the server is up
    (nothing is queued then: the resume state and re-sends cover what was not said)."""
    try:
        sock.send(data, zmq.NOBLOCK)
        return True
    except zmq.Again:
        return False



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

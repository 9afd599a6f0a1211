"""One connection to one ``v2v-serve``: a DEALER socket served by a background I/O thread.

The thread says ``hello`` (the outputs wanted, its ``credits``, who it is and the resume
state), receives batches, answers revokes, sends heartbeats, and forwards an ``ack`` naming
each batch as it is handed to the training loop (the ack frees exactly that batch's credit). So
the server never has more than ``credits`` batches in flight to this connection, and a slow
trainer never grows anybody's memory. ``endpoint.EndpointStream`` owns its connection and the
consumer's record; the connection reports to it only through the ``items`` queue.

This module is the shell: the socket, the poll loop, heartbeats, reconnection and the pipe
from the consumer. What the messages mean (hello, welcome, batches, revokes, the batches held)
is the connection's :class:`~v2v_client.session.ServerSession`; neither imports torch (the
stream passes ``tensors.batch_to_torch`` as the conversion).
"""
from __future__ import annotations

import functools
import logging
import queue
import threading
import time
import uuid
from typing import Callable, Optional, Tuple

import zmq

from v2v_wire.messages import Ack, Bye, Heartbeat, Hold, Released
from v2v_wire.protocol import is_ipv6, pack, unpack

from .session import MAX_SERVER_MSG, Convert, LoopAbandoned, ServerSession, StreamError, StreamTimeout

__all__ = ["Connection", "ConsumerPipe", "StreamError", "StreamTimeout", "MAX_SERVER_MSG", "load_curve_keys"]

log = logging.getLogger("v2v.client")


class Connection:
    """One DEALER connection to one endpoint and its I/O thread, which owns the socket: it says
    hello (with the consumer's resume state), receives batches, answers revokes, heartbeats,
    and forwards the acknowledgements the consumer queues (flushed before ``bye``). It reports
    only through ``items`` (decoded batches and control items; the protocol itself is the
    :class:`~v2v_client.session.ServerSession` ``session``). A batch is either taken by the loop
    once granted (``take``) or given back, never both (``session.held``: arrays freed at once).

    Args:
        endpoint: the server's ZeroMQ endpoint.
        options: the stream's ``options.StreamOptions``.
        record: the consumer's ``endpoint.ConsumerRecord`` (thread-safe): its resume state goes
            in every hello, the welcome's recipe is checked against it, and a DataLoader
            worker's receipts are recorded in it.
        consumer: the id the hello names the consumer by.
        convert: makes a batch's numpy arrays the consumer's (None keeps numpy arrays).
        receipts, iteration: in a DataLoader worker under ``StreamLoader``, the pipe on which
            the main process says which batches the training loop received, and the loader's
            iteration this connection serves.

    Raises:
        ValueError: for ``options.curve_keys`` naming bad key files.
    """

    def __init__(self, endpoint: str, options, record, consumer: str, convert: Optional[Convert] = None,
                 receipts=None, iteration: int = 0):
        self.endpoint, self.options, self.record = endpoint, options, record
        self.curve = load_curve_keys(*options.curve_keys) if options.curve_keys else None
        compression, auto = options.compression_for(endpoint)
        hello = functools.partial(options.hello, consumer, ends_on_drained=receipts is not None)  # a loader worker
        self.session = ServerSession(endpoint, options.outputs, lambda: hello(record.resume()),
                                     welcomed=lambda info: record.check_recipe(info.get("recipe")),
                                     convert=convert, raw=options.raw,
                                     shm=options.wants_shm(endpoint), keep=options.credits + 2,
                                     compression=compression, compression_auto=auto)
        self._closing = threading.Event()
        self._ctx = zmq.Context.instance()
        self._ident = uuid.uuid4().bytes
        self._pipe = ConsumerPipe(self._ctx)
        self._lingering, self._receipts = False, receipts  # DataLoader worker: what the training loop received
        self._iteration, self._abandoned, self._unreceived = iteration, False, False  # LoaderLink.end_iteration, close
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

    def ended(self) -> bool:
        """True once the I/O thread has ended and every item it queued was taken."""
        return not self._thread.is_alive() and self.session.items.empty()

    # consumer side -------------------------------------------------------
    def take(self, item: dict, on_claim: Callable[[], object] = lambda: None, ack: bool = True) -> Tuple[bool, object]:
        """Claim a received batch for the training loop once granted (``HeldBatches.claim``,
        with ``on_claim``), and ``ack`` it (a DataLoader worker acks on the loop's receipt).
        Returns ``(True, on_claim())``, or ``(False, None)`` when it was given back meanwhile
        (revoked before it was asked, refused, discarded by a new hello) or the connection ended."""
        self._ask(item)
        ok, result = self.session.held.claim(item, on_claim, lambda: not self._closing.is_set()
                                             and self._thread.is_alive())
        if ok and ack:
            self._queue_for_server(Ack((item["batch_id"],)).to_wire())
        self._ask()
        return ok, result

    def _ask(self, item: Optional[dict] = None) -> None:
        """Ask for ``item``'s grant and those ahead of it (``HeldBatches.to_ask``)."""
        ids = self.session.held.to_ask(item)
        if ids:
            self._queue_for_server(Hold(tuple(ids)).to_wire())

    def ack(self, batch_ids) -> None:
        """Acknowledge batches this connection holds (the training loop received them)."""
        if batch_ids:
            self._queue_for_server(Ack(tuple(batch_ids)).to_wire())

    def give_back(self, item: dict) -> None:
        """Return a received batch to the server unused (e.g. an epoch this consumer already completed)."""
        if self.session.held.give_back(item) is not None:
            self._queue_for_server(Released((item["batch_id"],)).to_wire())

    def _queue_for_server(self, msg: dict) -> None:
        """Hand ``msg`` to the I/O thread, which sends it. Dropped once that thread has ended
        (the server shut down or the connection closed: nobody would receive it), so taking a
        batch still queued here never blocks on a pipe nobody reads."""
        self._pipe.send(msg, lambda: not self._closing.is_set() and self._thread.is_alive())

    def linger(self) -> None:
        """The iteration ended with batches still in a DataLoader's queues: keep taking their
        receipts, and close once none is left (or at :meth:`close`)."""
        self._lingering = True

    def close(self, unreceived: bool = False) -> None:
        """Stop the I/O thread: queued acks are sent, batches asked for or granted and not taken
        are given back (``unreceived``: also a DataLoader worker's batches the loader dropped), then ``bye``."""
        if self._closing.is_set():
            return
        self._unreceived = unreceived
        self._closing.set()
        self._thread.join(5.0)
        self._pipe.close_sender()
        self.session.items.put(StopIteration("closed"))  # wake an iterator blocked on this connection

    # the I/O thread ------------------------------------------------------
    def _socket(self) -> zmq.Socket:
        sock = self._ctx.socket(zmq.DEALER)
        sock.setsockopt(zmq.IDENTITY, self._ident)
        sock.setsockopt(zmq.LINGER, 1000)
        sock.setsockopt(zmq.MAXMSGSIZE, MAX_SERVER_MSG)
        sock.setsockopt(zmq.RCVHWM, 0)
        if is_ipv6(self.endpoint):
            sock.setsockopt(zmq.IPV6, 1)
        if self.curve is not None:
            pub, sec, server_pub = self.curve
            sock.curve_publickey, sock.curve_secretkey, sock.curve_serverkey = pub, sec, server_pub
        sock.connect(self.endpoint)
        _send(sock, self.session.hello(new_socket=True))  # a new socket carries no message of an older session
        return sock

    def _poller(self, sock: zmq.Socket) -> zmq.Poller:
        poller = zmq.Poller()
        poller.register(sock, zmq.POLLIN)
        poller.register(self._pipe.receiver, zmq.POLLIN)
        if self._receipts is not None:
            poller.register(self._receipts.fileno(), zmq.POLLIN)
        return poller

    def _take_receipts(self, sock: zmq.Socket) -> None:
        """What ``StreamLoader`` wrote: batches the loop received (acknowledged, and recorded by
        the stream), or the end of this connection's iteration (:class:`LoopAbandoned`)."""
        while self._receipts is not None and self._receipts.poll(0):
            try:
                msg = unpack(self._receipts.recv_bytes())
            except (EOFError, OSError):  # the main process is gone
                self._receipts = None
                return
            if msg.get("type") == "abandon":
                if msg.get("iteration") == self._iteration and not self._abandoned:
                    self._abandoned = True
                    self.session.items.put(LoopAbandoned())
                continue
            mine = self.record.received(msg["batch_ids"])
            if mine:
                _send(sock, pack(Ack(tuple(mine)).to_wire()))

    def _run(self) -> None:
        """The I/O thread: the loop over the socket; any failure goes to the consumer as a
        :class:`StreamError`, and the socket always closes with ``bye``."""
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
        """Poll the socket, the acknowledgements and the receipts; receive messages, heartbeat,
        and on a lost server reconnect (``options.reconnect``) or end the stream with an error."""
        sock = self._sock
        give_up_at = None
        last_heard = time.monotonic()
        next_beat, asked = last_heard + self.options.heartbeat_s, set()
        poller = self._poller(sock)
        while not self._closing.is_set():
            events = dict(poller.poll(100))
            now = time.monotonic()
            if self._pipe.receiver in events:
                self._pipe.forward(sock)
            self._take_receipts(sock)
            if self._lingering and (self._abandoned or not self.record.in_pipeline()):
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
            if now >= next_beat:
                _send(sock, pack(Heartbeat().to_wire()))
                next_beat = now + self.options.heartbeat_s
                again, asked = self.session.held.still_asked(asked)
                if again:
                    _send(sock, pack(Hold(tuple(sorted(again))).to_wire()))

    def _receive(self, sock: zmq.Socket) -> Tuple[Optional[str], bool]:
        """Handle every message waiting on ``sock`` and send the replies they call for:
        (``ServerSession.on_message``'s "over" or "lost" verdict, else None; whether any message came)."""
        heard = False
        while True:
            try:
                frames = sock.recv_multipart(zmq.NOBLOCK, copy=False)
            except zmq.Again:
                return None, heard
            heard = True
            verdict = self.session.on_message(frames)
            for r in self.session.replies():
                _send(sock, r)
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
        """Close the I/O thread's sockets: acknowledgements of batches the training loop took
        and its receipts go out before ``bye``."""
        if sock is not None:
            try:
                self._pipe.forward(sock)
                self._take_receipts(sock)
                ours = self.session.held.discard(None)
                if self._receipts is not None and (self._abandoned or self._unreceived):
                    ours += self.record.pipeline_ids()  # granted, queued in the loader, dropped by it
                if ours:  # asked or granted and never handed on: back to the queue, not lost with us
                    sock.send(pack(Released(tuple(ours)).to_wire()), zmq.NOBLOCK)
                sock.send(pack(Bye().to_wire()), zmq.NOBLOCK)
            except zmq.ZMQError:
                pass
            sock.close()
        self._pipe.close_receiver()
        self.session.close()


class ConsumerPipe:
    """The consumer's messages to the server (acks, holds, releases), carried to the I/O thread
    that owns the socket through an inproc PAIR: the consumer calls ``send``, the I/O thread
    polls ``receiver`` and calls ``forward`` to send what came, in order."""

    def __init__(self, ctx: zmq.Context):
        addr = f"inproc://v2v-ack-{uuid.uuid4().hex}"
        self.receiver = ctx.socket(zmq.PAIR)
        self.receiver.bind(addr)
        self._sender = ctx.socket(zmq.PAIR)
        self._sender.connect(addr)

    def send(self, msg: dict, open_: Callable[[], bool]) -> None:
        """Queue ``msg`` for the I/O thread while ``open_()`` (its thread runs) says anybody will
        read it; never blocks on a pipe nobody reads."""
        data = pack(msg)
        while open_():
            try:
                self._sender.send(data, zmq.NOBLOCK)
                return
            except zmq.Again:  # the pipe is full, or the I/O thread is ending: look again
                time.sleep(0.001)

    def forward(self, sock: zmq.Socket) -> None:
        """Send what the consumer queued to the server (the I/O thread's side)."""
        while True:
            try:
                _send(sock, self.receiver.recv(zmq.NOBLOCK))
            except zmq.Again:
                return

    def close_sender(self) -> None:
        self._sender.close(0)

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

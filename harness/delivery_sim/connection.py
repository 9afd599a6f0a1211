"""A client connection in the simulator: the REAL ``v2v_client.session.ServerSession`` (which
decides every message the client sends) behind a stand-in for ``v2v_client.connection.Connection``,
which only moves bytes and keeps time.

:class:`SimConnection` does what ``Connection``'s I/O thread does, over the simulated network:
it opens a socket with an identity of its own and sends the session's hello, feeds every
server message to ``ServerSession.on_message`` and a ``StreamLoader``'s receipts to
``on_loader``, calls ``tick(now)`` as its poll loop turns, sends whatever ``outgoing()`` holds,
declares the server lost after ``timeout_s`` of silence (then a new socket, a new identity and a
new hello, or ``StreamTimeout``), and on close sends ``outgoing()`` and ``closing()``. Every
decision about what to send is the session's. For the checks it tells the oracle each release of
a batch it asked to hold (``Oracle.released``), and each such batch a hello discarded (the
server's grant until a hello of its consumer is let in: limit (a) if none ever is).
"""
from __future__ import annotations

from typing import Callable, Dict, List, Optional, Set, Tuple

from v2v_client.connection import own_stall
from v2v_client.receipts import loader_message
from v2v_client.session import ServerSession, StreamError, StreamTimeout
from v2v_wire.messages import Hello, Hold, Released
from v2v_wire.protocol import pack, unpack

from harness.delivery_sim.net import Link

ENDPOINT = "tcp://sim-server:5555"


class SimConnection:
    """One connection of one client process, and its I/O thread.

    Args:
        host: the client process (``proc``, ``sim``, ``net``).
        options: ``v2v_client.options.StreamOptions`` (credits, DDP position, timeouts...).
        record: the reader's ``v2v_client.resume.ResumeState``.
        consumer: the id the hello names.
        receipts: a DataLoader worker's receipt pipe (:class:`ReceiptPipe`), else None.
        iteration: the loader's iteration this connection serves.
        instance: the reader process's token (``ServerSession``).
        wake: called when an item may be ready for the consumer.
    """

    def __init__(self, host, options, record, consumer: str, receipts=None, iteration: int = 0,
                 instance: str = "", wake: Callable[[], None] = lambda: None):
        self.host, self.sim, self.net = host, host.sim, host.net
        self.proc = host.proc
        self.options, self.record = options, record
        self.receipts, self.wake = receipts, wake
        self.session = ServerSession(ENDPOINT, options, record, consumer, ends_on_drained=receipts is not None,
                                     iteration=iteration, instance=instance)
        # the consumer as the server keys it (``core.consumer_of``, the oracle's "c:<id>/0", "g:<group>/<rank>")
        self.consumer_key = f"g:{options.group or 'default'}/{options.rank}" if options.world_size > 1 \
            else f"c:{consumer}/0"
        self.asked: Dict[int, Set[Tuple[int, str]]] = {}  # batch id -> samples of a batch it asked to hold
        self.alive = True  # the I/O thread runs
        self.closing = False
        self.lingering = self.unreceived = False
        self._flush_due = False
        self.give_up_at: Optional[float] = None
        self.link: Link = self._socket()
        self.sim.after(options.heartbeat_s, self._poll, proc=self.proc, lane="io")
        if receipts is not None:
            receipts.reader = self

    # ------------------------------------------------------------------ the I/O thread
    def _socket(self) -> Link:
        """``Connection._socket``: a new socket with an identity of its own, and the session's hello."""
        self.ident = self.sim.rng.getrandbits(64).to_bytes(8, "big")
        self.name = f"{self.proc.name}/{self.ident.hex()[:8]}"
        self.link = self.net.connect(self.ident, self)
        self.last_heard = self.last_turn = self.sim.now
        self.session.hello(new_socket=True, at=self.sim.now)  # the simulated host's monotonic clock
        self.session.tick(self.sim.now)  # the poll loop's first turn
        self._send_out()
        return self.link

    def _send_out(self) -> None:
        """What the session decided, in order."""
        for msg in self.session.outgoing():
            self._say(msg)

    def _say(self, msg) -> None:
        """Send ``msg``; a release of a batch it asked to hold (the server may have granted it) is
        told to the oracle: that batch stays its consumer's grant until a server takes it back. So
        is each such batch when a hello is sent: the hello discarded every one not taken, for its
        resume state to settle at the server, which may never let it in (a taken one is in a loop's
        history, which the checks read first, or was a loader worker's, released later)."""
        if isinstance(msg, Hold):
            for bid in msg.batch_ids:
                item = self.session.held.current.get(bid)
                if item is not None:
                    self.asked[bid] = {(item["epoch"], sid) for sid in item["sample_ids"]}
        elif isinstance(msg, Released):
            for bid in msg.batch_ids:
                if bid in self.asked:
                    self.host.run.oracle.released(self.ident, bid, self.consumer_key, self.asked.pop(bid))
        elif isinstance(msg, Hello):
            for bid in list(self.asked):
                self.host.run.oracle.released(self.ident, bid, self.consumer_key, self.asked.pop(bid))
        data = pack(msg.to_wire())
        self.sim.log(self.name, lambda: f"-> {_peek(data)}")
        self.net.send_up(self.link, [data])

    def deliver(self, frames: list) -> None:
        """A server message arrived (``Connection._receive``)."""
        if not self.alive:
            return
        self.last_heard, self.give_up_at = self.sim.now, None
        self.sim.log(self.name, lambda: f"<- {_peek(frames[0])}")
        verdict = self.session.on_message(frames)
        self._send_out()
        self.wake()
        if verdict == "over":
            self._end()
        elif verdict == "lost":
            self._lost("the server shut down")

    def _poll(self, again: int = 0) -> None:
        """A turn of the poll loop with nothing read: receipts, silence, ``tick``."""
        if not self.alive:
            return
        now = self.sim.now
        if again < 3 and now >= self.link.cut_until and any(m.alive and m.t <= now for m in self.link.down):
            # a message came while this process was stopped: the poll reads the socket first
            self.sim.at(now, self._poll, again + 1, proc=self.proc, lane="io")
            return
        self.take_receipts()
        if not self.alive:
            return
        self.last_heard += own_stall(now - self.last_turn, self.options.timeout_s)
        self.last_turn = now
        if now - self.last_heard > self.options.timeout_s:
            self._lost(f"no message for {self.options.timeout_s:.0f} s")
            if not self.alive:
                return
        self.session.tick(now)
        self._send_out()
        self.sim.after(self.options.heartbeat_s, self._poll, proc=self.proc, lane="io")

    def _lost(self, why: str) -> None:
        """``Connection._lost``: a new socket (a new identity) or the end, with an error."""
        o, now = self.options, self.sim.now
        self.sim.log(self.name, f"lost the server: {why}")
        if not o.reconnect:
            if why.startswith("no message"):
                self.session.items.put(StreamTimeout(f"no message from the v2v server for {o.timeout_s:.0f} s"))
            else:
                self.session.items.put(StreamError("the v2v server shut down mid-stream"))
            self._end()
            return
        if self.give_up_at is None:
            self.give_up_at = now + o.reconnect_timeout_s
        elif now > self.give_up_at:
            self.session.items.put(StreamTimeout("could not reconnect to the v2v server"))
            self._end()
            return
        self.net.close(self.link, linger=False)
        self._socket()

    def _end(self) -> None:
        """The I/O thread ends (``Connection._finish``): what the session queued and the
        receipts first, then its last messages (``ServerSession.closing``); the consumer is woken."""
        if not self.alive:
            return
        self._receipts()
        self.alive = False
        self._send_out()
        for msg in self.session.closing(self.unreceived):
            self._say(msg)
        self.net.close(self.link, linger=True)
        if self.receipts is not None and self.receipts.reader is self:
            self.receipts.reader = None
        self.wake()

    def take_receipts(self) -> None:
        """``Connection._take_receipts``: what the main process wrote, to the session; a
        lingering connection ends once every batch was received or the loop left."""
        if self.receipts is None or not self.alive:
            return
        self._receipts()
        if self.lingering and self.session.lingering_done():
            self._end()

    def _receipts(self) -> None:
        if self.receipts is None:
            return
        had = self.session.items.qsize()
        while self.receipts.waiting:
            self.session.on_loader(loader_message(self.receipts.waiting.pop(0)))
        self._send_out()
        if self.session.items.qsize() != had:
            self.wake()  # LoopAbandoned

    def _flush(self) -> None:
        self._flush_due = False
        if self.alive:
            self._send_out()

    def _ping(self) -> None:
        """``Wakeup.ping``: the I/O thread wakes soon and sends what the consumer's step decided."""
        if self.alive and not self._flush_due:
            self._flush_due = True
            self.sim.after(self.sim.uniform(0.0, 0.002), self._flush, proc=self.proc, lane="io")

    # ------------------------------------------------------------------ the consumer's side
    def try_take(self, item: dict, on_claim, ack: bool = True) -> Tuple[str, object]:
        """One try of ``Connection.take`` (``ServerSession.take``): ``("taken", on_claim())``,
        ``("gone", None)`` (given back meanwhile, or the connection ended), or ``("wait", None)``
        (not granted yet: the real consumer blocks here, and tries again when woken)."""
        ok, result = self.session.take(item, on_claim, lambda: False, ack)
        self._ping()
        if ok:
            return "taken", result
        if self.alive and self.session.held.current.get(item["batch_id"]) is item:
            return "wait", None
        return "gone", None

    def ack(self, batch_ids) -> None:
        self.session.ack(batch_ids)
        self._ping()

    def give_back(self, item: dict) -> None:
        self.session.give_back(item)
        self._ping()

    def held(self) -> int:
        return len(self.session.held)

    def ends_on(self, drained) -> bool:
        return self.session.held.ends_on(drained)

    def of_session(self, item, then=lambda current: None) -> bool:
        return self.session.held.of_session(item, then)

    def ended(self) -> bool:
        return not self.alive and self.session.items.empty()

    def linger(self) -> None:
        self.lingering = True
        self.take_receipts()

    def close(self, unreceived: bool = False) -> None:
        """``Connection.close``: the I/O thread finishes; the consumer sees the end."""
        if self.closing:
            return
        self.closing = True
        self.unreceived = unreceived
        self._end()
        self.session.items.put(StopIteration("closed"))

    def killed(self) -> None:
        """The process died: the socket goes with it (the kernel flushes part of what was sent)."""
        self.alive = False
        self.net.killed(self.link)


class ReceiptPipe:
    """A ``StreamLoader`` worker's receipt pipe (``multiprocessing.Pipe``): what the main
    process wrote (in the pipe at once, whether the worker runs or not) and the worker's current
    connection has not read yet."""

    def __init__(self):
        self.waiting: List[bytes] = []
        self.reader: Optional[SimConnection] = None

    def arrive(self, data: bytes) -> None:
        """Written by the main process: in the pipe now."""
        self.waiting.append(data)

    def poke(self) -> None:
        """The reading I/O thread notices the pipe is readable."""
        if self.reader is not None:
            self.reader.take_receipts()

    def close(self) -> None:
        pass


def _peek(data) -> str:
    """A message in a trace line."""
    try:
        h = unpack(data)
    except Exception as e:  # a hostile client's garbage
        return f"<undecodable {len(data)} bytes: {type(e).__name__}>"
    kind = h.get("type")
    if kind == "hello":
        r = h.get("resume") or {}
        return (f"hello consumer={h.get('consumer')!r} id={h.get('hello_id')} completed={r.get('completed_epoch')} "
                f"delivered={ {e: len(str(v).splitlines()) for e, v in (r.get('delivered') or {}).items()} } "
                f"rank={h.get('rank', 0)}/{h.get('world_size', 1)} group={h.get('group')} "
                f"supersedes={r.get('supersedes')}" + (f" queued={r['queued']}" if r.get("queued") else ""))
    if kind == "welcome":  # its info names the server by a random id: not in a trace that must replay
        return f"welcome hello_id={h.get('hello_id')}"
    if kind == "batch":
        return f"batch {h.get('batch_id')} e{h.get('epoch')} {h.get('sample_ids')}{' padding' if h.get('padding') else ''}"
    h.pop("v", None)
    h.pop("type", None)
    return f"{kind} {h}" if h else str(kind)

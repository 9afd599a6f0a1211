"""A client connection in the simulator: the REAL ``v2v_client.session.ServerSession`` (and its
``HeldBatches``) behind a stand-in for ``v2v_client.connection.Connection``'s I/O thread.

:class:`SimConnection` does what ``Connection`` does with its socket and thread, over the
simulated network: it says hello, feeds every server message to ``ServerSession.on_message``
and sends its ``replies()``, heartbeats each ``heartbeat_s`` and asks again for grants left
unanswered a whole heartbeat, declares the server lost after ``timeout_s`` of silence
(reconnecting on a new socket with the same identity, or ending with ``StreamTimeout``), takes
a DataLoader worker's receipts, and on close sends the acknowledgements queued, gives back what
was asked or granted and not taken, then ``bye``. Today ``Connection`` builds those messages
(holds, acks, releases, bye) itself, so this adapter mirrors its decisions line by line; issue
69 moves them into ``ServerSession``, and this adapter then only moves the bytes it is given.
"""
from __future__ import annotations

from typing import Callable, List, Optional, Tuple

from v2v_client.session import LoopAbandoned, ServerSession, StreamError, StreamTimeout
from v2v_wire.messages import Ack, Bye, Heartbeat, Hold, Released
from v2v_wire.protocol import pack, unpack

from harness.delivery_sim.net import Link, Net
from harness.delivery_sim.world import Sim

ENDPOINT = "tcp://sim-server:5555"


class SimConnection:
    """One connection of one client process (``host``: its ``proc``, ``sim``, ``net``).

    Args:
        host: the client process (``proc``, ``sim``, ``net``).
        options: ``v2v_client.options.StreamOptions`` (credits, DDP position, timeouts...).
        record: the consumer's ``v2v_client.endpoint.ConsumerRecord`` (the resume state).
        consumer: the id the hello names.
        receipts: a DataLoader worker's receipt pipe (``ReceiptPipe``), else None.
        iteration: the loader's iteration this connection serves.
        wake: called when an item may be ready for the consumer.
    """

    def __init__(self, host, options, record, consumer: str, receipts=None, iteration: int = 0,
                 wake: Callable[[], None] = lambda: None):
        self.host, self.sim, self.net = host, host.sim, host.net
        self.proc = host.proc
        self.options, self.record, self.consumer = options, record, consumer
        self.receipts, self.iteration, self.wake = receipts, iteration, wake
        hello = lambda: options.hello(consumer, record.resume(), ends_on_drained=receipts is not None)  # noqa: E731
        self.session = ServerSession(ENDPOINT, options.outputs, hello,
                                     welcomed=lambda info: record.check_recipe(info.get("recipe")))
        self.ident = self.sim.rng.getrandbits(64).to_bytes(8, "big")
        self.name = f"{host.proc.name}/{self.ident.hex()[:8]}"
        self.alive = True  # the I/O thread runs
        self.closing = False
        self.lingering = self.abandoned = self.unreceived = False
        self.pipe: List[bytes] = []  # what the consumer queued for the I/O thread
        self._forward_due = False
        self.asked: set = set()
        self.give_up_at: Optional[float] = None
        self.link: Link = self.net.connect(self.ident, self)
        self.last_heard = self.sim.now
        self._send(self.session.hello(new_socket=True))
        self.sim.after(options.heartbeat_s, self._beat, proc=self.proc, lane="io")
        if receipts is not None:
            receipts.reader = self

    # ------------------------------------------------------------------ the I/O thread
    def _send(self, data: bytes) -> None:
        self.sim.log(self.name, lambda: f"-> {_peek(data)}")
        self.net.send_up(self.link, [data])

    def deliver(self, frames: list) -> None:
        """A server message arrived (``Connection._receive``)."""
        if not self.alive:
            return
        self.last_heard, self.give_up_at = self.sim.now, None
        self.sim.log(self.name, lambda: f"<- {_peek(frames[0])}")
        verdict = self.session.on_message(frames)
        for r in self.session.replies():
            self._send(r)
        self.wake()
        if verdict == "over":
            self._end()
        elif verdict == "lost":
            self._lost("the server shut down")

    def _beat(self, again: int = 0) -> None:
        """The poll loop's timers: silence, heartbeat, re-asks, a lingering iteration's end."""
        if not self.alive:
            return
        now = self.sim.now
        if again < 3 and now >= self.link.cut_until and any(m.alive and m.t <= now for m in self.link.down):
            # a message came while this process was stopped: the poll reads the socket first
            self.sim.at(now, self._beat, again + 1, proc=self.proc, lane="io")
            return
        self._forward()
        self.take_receipts()
        if not self.alive:
            return
        if now - self.last_heard > self.options.timeout_s:
            self._lost(f"no message for {self.options.timeout_s:.0f} s")
            if not self.alive:
                return
        else:
            self._send(pack(Heartbeat().to_wire()))
            again, self.asked = self.session.held.still_asked(self.asked)
            if again:
                self._send(pack(Hold(tuple(sorted(again))).to_wire()))
        self.sim.after(self.options.heartbeat_s, self._beat, proc=self.proc, lane="io")

    def _lost(self, why: str) -> None:
        """``Connection._lost``: reconnect on a new socket (same identity) or end with an error."""
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
        self.link = self.net.connect(self.ident, self)
        self.last_heard = now
        self._send(self.session.hello(new_socket=True))

    def _end(self) -> None:
        """The I/O thread ends: ``Connection._finish`` (acks and receipts first, then what is
        asked or granted and not taken goes back, then ``bye``), and the consumer is woken."""
        if not self.alive:
            return
        self.alive = False
        self._forward()
        self.take_receipts()
        ours = self.session.held.discard(None)
        if self.receipts is not None and (self.abandoned or self.unreceived):
            ours += self.record.pipeline_ids()
        if ours:
            self._send(pack(Released(tuple(ours)).to_wire()))
        self._send(pack(Bye().to_wire()))
        self.net.close(self.link, linger=True)
        if self.receipts is not None and self.receipts.reader is self:
            self.receipts.reader = None
        self.wake()

    def take_receipts(self) -> None:
        """``Connection._take_receipts``: the loop received these batches (acknowledged), or
        left this iteration (``LoopAbandoned``)."""
        if self.receipts is None or not self.alive:
            return
        while self.receipts.waiting:
            msg = unpack(self.receipts.waiting.pop(0))
            if msg.get("type") == "abandon":
                if msg.get("iteration") == self.iteration and not self.abandoned:
                    self.abandoned = True
                    self.session.items.put(LoopAbandoned())
                    self.wake()
                continue
            mine = self.record.received(msg["batch_ids"])
            if mine:
                self._send(pack(Ack(tuple(mine)).to_wire()))
        if self.lingering and (self.abandoned or not self.record.in_pipeline()):
            self._end()

    def _forward(self) -> None:
        self._forward_due = False
        pipe, self.pipe = self.pipe, []
        for data in pipe:
            self._send(data)

    # ------------------------------------------------------------------ the consumer's side
    def queue_for_server(self, msg: dict) -> None:
        """``Connection._queue_for_server``: the I/O thread sends it soon (dropped once it ended)."""
        if not self.alive:
            return
        self.pipe.append(pack(msg))
        if not self._forward_due:
            self._forward_due = True
            self.sim.after(self.sim.uniform(0.0, 0.002), self._forward_if_alive, proc=self.proc, lane="io")

    def _forward_if_alive(self) -> None:
        if self.alive:
            self._forward()

    def ask(self, item: Optional[dict] = None) -> None:
        """``Connection._ask``: the grants the consumer needs next."""
        ids = self.session.held.to_ask(item)
        if ids:
            self.queue_for_server(Hold(tuple(ids)).to_wire())

    def try_take(self, item: dict, on_claim, ack: bool = True) -> Tuple[str, object]:
        """One try of ``Connection.take``'s claim after its ``ask(item)``: ``("taken", on_claim())``,
        ``("gone", None)`` (given back meanwhile, or the connection ended), or ``("wait", None)``
        (not granted yet: the real consumer blocks here)."""
        held = self.session.held
        ok, result = held.claim(item, on_claim, lambda: False)
        if not ok and self.alive and held.current.get(item["batch_id"]) is item:
            return "wait", None
        if ok and ack:
            self.queue_for_server(Ack((item["batch_id"],)).to_wire())
        self.ask()
        return ("taken", result) if ok else ("gone", None)

    def ack(self, batch_ids) -> None:
        if batch_ids:
            self.queue_for_server(Ack(tuple(batch_ids)).to_wire())

    def give_back(self, item: dict) -> None:
        if self.session.held.give_back(item) is not None:
            self.queue_for_server(Released((item["batch_id"],)).to_wire())

    def held(self) -> int:
        return len(self.session.held)

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

    def write(self, data: bytes) -> None:
        self.arrive(data)
        self.poke()

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
                f"delivered={ {e: len(str(v).splitlines()) for e, v in (r.get('delivered') or {}).items()} }")
    if kind == "batch":
        return f"batch {h.get('batch_id')} e{h.get('epoch')} {h.get('sample_ids')}{' padding' if h.get('padding') else ''}"
    h.pop("v", None)
    h.pop("type", None)
    return f"{kind} {h}" if h else str(kind)

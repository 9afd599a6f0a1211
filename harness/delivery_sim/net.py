"""The simulated network between clients' DEALER sockets and the server's ROUTER, as ZeroMQ
behaves over TCP.

Each client socket is a :class:`Link` (its identity) with two directions. Within one direction
messages arrive in the order they were sent (ZeroMQ keeps a connection's order); across links
the order is whatever the delays make it (a client's old and new connections race). A message
is lost only when a connection breaks:

* ``blip``: the TCP connection under a socket breaks and ZeroMQ reconnects behind it: the
  oldest messages in flight each way (those in the kernel's buffers) are lost, the rest go on
  (a message already at the receiving host waits in its socket, even for a stopped process);
  for ``gap`` seconds the ROUTER has no route to the identity (a send is unreachable,
  ``ROUTER_MANDATORY``) and the client's sends wait in its queue.
* ``cut`` (a partition): nothing moves either way until it heals; then everything arrives.
* a client's socket closed (linger): what it sent still arrives, nothing reaches it.
* a client process killed: the kernel flushes part of what it sent; nothing reaches it.
* the server process killed: what it had not read is lost, and what it sent that had not
  reached its client's host; clients' sockets reconnect to the next server, to which their
  queued messages then go.

Faults beyond ZeroMQ's model, on request: ``dup`` delivers a message twice in a row (an
at-least-once transport), ``spike`` delays a message by up to ``spike_s`` (its successors wait
behind it).
"""
from __future__ import annotations

import collections
from dataclasses import dataclass
from typing import Deque, Dict, List, Optional

from harness.delivery_sim.world import Proc, Sim


@dataclass
class NetFaults:
    """Rates of the network's faults (per message) and its delays (seconds)."""

    latency_s: float = 0.0005
    jitter_s: float = 0.001
    spike: float = 0.0
    spike_s: float = 1.0
    dup: float = 0.0
    reconnect_s: float = 0.1  # ZeroMQ's reconnect interval
    connect_s: float = 0.1  # most seconds a new socket takes to connect (its first messages wait in ZeroMQ's queue)


class Msg:
    __slots__ = ("frames", "alive", "t")

    def __init__(self, frames: list, t: float):
        self.frames, self.alive, self.t = frames, True, t


class Link:
    """One client socket (identity ``ident``) connected to the server endpoint.

    ``client``: the receiving object (``proc`` and ``deliver(frames)``)."""

    def __init__(self, ident: bytes, client):
        self.ident, self.client = ident, client
        self.up: Deque[Msg] = collections.deque()
        self.down: Deque[Msg] = collections.deque()
        self.up_last = self.down_last = 0.0
        self.closed = False
        self.cut_until = 0.0
        self.routable_at = 0.0
        self.waiting: List[list] = []  # sent while no server listens: go when one does


class Net:
    """The network of one simulated deployment (one server endpoint).

    ``server``: the listening server (``proc`` and ``receive(ident, frames)``), None while it is down.
    """

    def __init__(self, sim: Sim, faults: NetFaults):
        self.sim, self.f = sim, faults
        self.links: Dict[bytes, Link] = {}
        self.server = None
        self.sent = self.lost = self.duplicated = 0

    # ------------------------------------------------------------------ sockets
    def connect(self, ident: bytes, client) -> Link:
        """A client socket connects (its identity must be new: a reconnect keeps its Link)."""
        link = Link(ident, client)
        link.routable_at = self.sim.now + self.f.connect_s * self.sim.rng.random()
        self.links[ident] = link
        return link

    def close(self, link: Link, linger: bool = True) -> None:
        """The client closes its socket: with ``linger`` what it sent still arrives (ZeroMQ's
        linger), else a random tail of it is lost; nothing more reaches it."""
        if link.closed:
            return
        link.closed = True
        self._drop(link.down, len(link.down))
        if not linger:
            n = len(link.up)
            self._drop_tail(link.up, self.sim.rng.randint(0, n))
            link.waiting.clear()

    def killed(self, link: Link) -> None:
        """The client's process died: the kernel sends part of what it had written to a
        connected socket; what waited for the connection (in ZeroMQ's queue) is lost."""
        if link.closed:
            return
        link.closed = True
        self._drop(link.down, len(link.down))
        link.down.clear()
        connected = self.sim.now >= link.routable_at
        self._drop_tail(link.up, self.sim.rng.randint(0, len(link.up)) if connected else 0)
        link.waiting.clear()

    # ------------------------------------------------------------------ faults
    def blip(self, link: Link, gap: float) -> None:
        """The connection under ``link`` breaks and ZeroMQ reconnects after ``gap`` s."""
        rng = self.sim.rng
        for queue in (link.up, link.down):
            flying = self._in_flight(queue)
            self._drop(flying, rng.randint(0, len(flying)))
        link.routable_at = max(link.routable_at, self.sim.now + gap)
        self.sim.log("net", f"blip {link.ident.hex()[:8]} for {gap:.2f} s")

    def cut(self, link: Link, until: float) -> None:
        """A partition: nothing moves on ``link`` before ``until``."""
        link.cut_until = max(link.cut_until, until)
        self.sim.log("net", f"cut {link.ident.hex()[:8]} until {until:.2f}")

    def server_down(self) -> None:
        """The server process died: what it had not read is lost, and what it sent and had not
        reached its client's host yet."""
        self.server = None
        for link in self.links.values():
            self._drop(link.up, len(link.up))
            link.up.clear()
            flying = self._in_flight(link.down)
            self._drop(flying, len(flying))

    def server_up(self, server) -> None:
        """A server listens again: every open socket reconnects, and what it queued meanwhile goes."""
        self.server = server
        for link in self.links.values():
            if link.closed:
                continue
            link.routable_at = max(link.routable_at, self.sim.now + self.f.reconnect_s)
            waiting, link.waiting = link.waiting, []
            for frames in waiting:
                self.send_up(link, frames)

    # ------------------------------------------------------------------ moving messages
    def _delay(self, last: float, link: Link, extra: float = 0.0) -> float:
        f, rng = self.f, self.sim.rng
        d = f.latency_s + rng.random() * f.jitter_s + extra
        if f.spike and rng.random() < f.spike:
            d += rng.random() * f.spike_s
        return max(self.sim.now + d, last, link.cut_until)

    def send_up(self, link: Link, frames: list) -> None:
        """A client sends ``frames`` to the server (queued while no server listens)."""
        if link.closed:
            return
        if self.server is None:
            link.waiting.append(frames)
            return
        t = self._delay(link.up_last, link)
        t = max(t, link.routable_at)
        link.up_last = t
        self._push(link, link.up, frames, t, self._arrive_up, self.server.proc, "main")

    def send_down(self, ident: bytes, frames: list) -> bool:
        """The server sends ``frames`` to ``ident``; False when ZeroMQ has no route to it
        (closed, dead, or reconnecting: the ROUTER's send fails)."""
        link = self.links.get(ident)
        if link is None or self.sim.now < link.routable_at:
            return False
        if link.closed or link.client.proc.dead:
            # the peer's close (its FIN) reaches the ROUTER after what it sent before closing: until
            # that is read, a send is queued (and goes nowhere)
            return any(m.alive for m in link.up)
        t = self._delay(link.down_last, link)
        link.down_last = t
        self._push(link, link.down, frames, t, self._arrive_down, link.client.proc, "io")
        return True

    def _push(self, link: Link, queue: Deque[Msg], frames: list, t: float, arrive, proc: Proc, lane: str) -> None:
        self.sent += 1
        copies = 2 if self.f.dup and self.sim.rng.random() < self.f.dup else 1
        self.duplicated += copies - 1
        for _ in range(copies):
            m = Msg(frames, t)
            queue.append(m)
            self.sim.at(t, arrive, link, m, proc=proc, lane=lane)

    def _arrive_up(self, link: Link, m: Msg) -> None:
        if self._held_back(link, m, self._arrive_up, self.server.proc if self.server else None, "main"):
            return
        if m.alive and self.server is not None:
            self.server.receive(link.ident, m.frames)

    def _arrive_down(self, link: Link, m: Msg) -> None:
        if self._held_back(link, m, self._arrive_down, link.client.proc, "io"):
            return
        if m.alive and not link.closed:
            link.client.deliver(m.frames)

    def _held_back(self, link: Link, m: Msg, arrive, proc: Optional[Proc], lane: str) -> bool:
        """A message due while its link is cut waits for the heal (keeping its place)."""
        if m.alive and self.sim.now < link.cut_until:
            self.sim.at(link.cut_until, arrive, link, m, proc=proc, lane=lane)
            return True
        queue = link.up if arrive == self._arrive_up else link.down
        if queue and queue[0] is m:
            queue.popleft()
        else:
            try:
                queue.remove(m)
            except ValueError:
                pass
        return False

    def _in_flight(self, queue: Deque[Msg]) -> List[Msg]:
        """The messages of ``queue`` not yet at the receiving host (those past it wait in its
        socket for a stopped process to read them)."""
        now = self.sim.now
        return [m for m in queue if m.t > now]

    def _drop(self, queue, n: int) -> None:
        """Lose the ``n`` oldest messages in flight of ``queue``."""
        for m in list(queue)[:n]:
            if m.alive:
                m.alive = False
                self.lost += 1

    def _drop_tail(self, queue: Deque[Msg], keep: int) -> None:
        """Lose what is in flight in ``queue`` after its ``keep`` oldest messages."""
        for m in list(queue)[keep:]:
            if m.alive:
                m.alive = False
                self.lost += 1

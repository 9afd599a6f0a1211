"""Hostile and careless clients: they speak the wire protocol (packed messages on their own
socket) but not honestly. The server must stay exact for the honest trainers beside them.

Behaviours (``Hostile(kind=...)``):

* ``sitter``: asks for the grant of every batch it gets and never acknowledges one, heartbeating
  forever (a stuck loop, an hour of validation, or malice);
* ``claim``: says hello with a resume state claiming ``ids`` of ``epoch`` it was never sent;
* ``completed``: says hello claiming ``completed_epoch`` (``epoch``) on a fresh server;
* ``huge``: says hello with a resume state of ``n`` ids of one video (a few MB), then leaves;
* ``repeat``: asks for each batch's grant naming its id ``width`` times, ``repeats`` times, then
  acknowledges it. Its cost (linear in the message since issue 69; 33.6 s for 60 x 4096 before)
  is a real server's to measure (``bench.faults``); the simulator checks safety, with a width
  that keeps a seed fast.

What the server grants a hostile client is that client's for good (docs/delivery.md, rule 2):
its samples count as reached its "loop" (a dishonest lineage) when the grant comes, so the
server handing them to anyone else is a double.
"""
from __future__ import annotations

from typing import Optional, Sequence

from v2v_wire.ids import compact_ids
from v2v_wire.protocol import pack, unpack

from harness.delivery_sim.world import Proc


class Hostile:
    """One hostile client process with one connection.

    Args:
        run: the deployment.
        name: its process's and consumer's name.
        kind: the behaviour (module docstring).
        epoch, ids, n, repeats, width: the behaviour's parameters.
        leave_after: seconds after which it says ``bye`` and closes (None: never).
    """

    def __init__(self, run, name: str, kind: str, epoch: int = 0, ids: Sequence[str] = (), n: int = 0,
                 repeats: int = 60, leave_after: Optional[float] = None, credits: int = 4, width: int = 4096):
        self.run, self.sim, self.net = run, run.sim, run.net
        self.proc = Proc(name)
        self.name, self.kind = name, kind
        self.epoch, self.ids, self.n, self.repeats, self.credits = epoch, list(ids), n, repeats, credits
        self.width = width
        self.ident = f"hostile-{name}".encode()
        self.batches: dict = {}  # batch id -> (epoch, sample ids) received
        run.oracle.lineage(name, honest=False)  # what it acknowledges reached its "loop"
        self.link = self.net.connect(self.ident, self)
        self.sim.after(0.0, self._hello, proc=self.proc)
        self.sim.after(1.0, self._beat, proc=self.proc)
        if leave_after is not None:
            self.sim.after(leave_after, self._leave, proc=self.proc)

    def _send(self, msg: dict) -> None:
        self.sim.log(self.name, lambda: f"-> {msg.get('type')} {str(msg)[:120]}")
        self.net.send_up(self.link, [pack(msg)])

    def _hello(self) -> None:
        if self.run.oracle.lineages[self.name].history:  # its state names none of what it was granted
            self.run.oracle.rolled_back(self.name, 0)
        resume: dict = {"completed_epoch": -1, "delivered": {}, "batches": {}}
        if self.kind == "claim":
            resume["delivered"] = {str(self.epoch): compact_ids(self.ids)}
        elif self.kind == "completed":
            resume["completed_epoch"] = self.epoch
        elif self.kind == "huge":
            resume["delivered"] = {str(self.epoch): compact_ids([f"{self.ids[0]}#{i}" for i in range(self.n)])}
        self._send({"type": "hello", "outputs": ["voxels"], "credits": self.credits, "consumer": self.name,
                    "resume": resume, "hello_id": 1, "instance": self.name})

    def _beat(self) -> None:
        if self.link.closed:
            return
        self._send({"type": "heartbeat"})
        self.sim.after(1.0, self._beat, proc=self.proc)

    def _leave(self) -> None:
        self._send({"type": "bye"})
        self.net.close(self.link, linger=True)

    def deliver(self, frames: list) -> None:
        h = unpack(frames[0])
        kind = h.get("type")
        if kind == "batch" and not h.get("padding"):
            bid = h["batch_id"]
            self.batches[bid] = (h["epoch"], h["sample_ids"])
            if self.kind == "repeat":
                for _ in range(self.repeats):
                    self._send({"type": "hold", "batch_ids": [bid] * self.width})
                self._send({"type": "ack", "batch_ids": [bid]})
            elif self.kind != "silent":
                self._send({"type": "hold", "batch_ids": [bid]})
        elif kind == "granted":
            for bid in h.get("batch_ids", ()):
                got = self.batches.pop(bid, None)
                if got is not None:
                    epoch, sids = got
                    self.run.oracle.yielded(self.name, {"epoch": epoch, "sample_ids": sids,
                                                        "padding": [False] * len(sids)})
        elif kind == "error" and h.get("code") in ("dropped", "unknown_client") and not self.link.closed:
            self._hello()

    # what the oracle asks of a client process (it holds nothing the oracle counts)
    def alive(self) -> bool:
        return False

    def pending(self):
        return ()

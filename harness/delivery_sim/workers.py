"""Decode workers simulated at the task level: a task makes its samples one by one (a sample is
its id: the simulator is about delivery, not pixels), and a worker can die mid-task, hang, or
keep sending after the server replaced it (late copies, which the scheduler must ignore).

A worker's messages reach the server over its backend socket (``ipc://``): an event of the
server's process, lost if that process is dead when it comes.
"""
from __future__ import annotations

from dataclasses import dataclass

from v2v_wire.ids import SampleKey

from harness.delivery_sim.world import Proc


@dataclass
class WorkerFaults:
    """Per-sample chances that a worker dies (SIGKILL), hangs (sends nothing until the task
    timeout replaces it), or, once replaced, goes on sending its task's samples (late copies)."""

    die: float = 0.0
    hang: float = 0.0
    late: float = 0.0


class SimWorker:
    """One worker process of a server incarnation."""

    def __init__(self, server, ident: bytes):
        self.server, self.ident = server, ident
        self.sim = server.sim
        self.proc = Proc(ident.decode())
        self.idle = True
        self.faults: WorkerFaults = server.cfg.worker_faults
        self.hung = False
        self.late = False
        self._where = None  # (task, window, failed) where it hung

    def start(self, task) -> None:
        """Make ``task``'s samples (``worker_messages.Task``), then say it is done."""
        self.idle = False
        self.sim.after(self._dt(), self._step, task, 0, {}, proc=self.proc)

    def _dt(self) -> float:
        lo, hi = self.server.cfg.sample_s
        return self.sim.uniform(lo, hi)

    def _tell(self, msg: tuple) -> None:
        srv = self.server
        self.sim.after(self.sim.uniform(0.0, 0.001), srv.from_worker, msg, proc=srv.proc)

    def _step(self, task, k: int, failed: dict) -> None:
        sim, f = self.sim, self.faults
        if self.hung:
            return
        if not self.late:
            if sim.chance(f.die):
                sim.log(self.proc.name, f"dies in task {task.task} at window {k}")
                self.proc.dead = True
                return
            if sim.chance(f.hang):
                sim.log(self.proc.name, f"hangs in task {task.task} at window {k}")
                self.hung = True
                self._where = (task, k, failed)
                return
        corpus = self.server.cfg.corpus
        v = task.video
        n = corpus.windows[v]
        stop = corpus.truncated.get(v)
        if stop is not None and k >= stop:
            self._tell(("done", self.ident, task.task, k, dict(failed), f"decoding failed in window {k}: truncated"))
            return
        if k >= n:
            self._tell(("done", self.ident, task.task, n, dict(failed), None))
            return
        if (v, k) in corpus.bad:
            failed[k] = "the frame size changes inside the window"
        elif (k, 0) not in set(task.skip):
            self._tell(("sample", self.ident, task.task, SampleKey(v, k)))
        sim.after(self._dt(), self._step, task, k + 1, failed, proc=self.proc)

    def replaced(self) -> None:
        """The server gave this worker's task to another and kills it; with the ``late`` fault
        it goes on sending first (what its socket held), and the server must ignore it."""
        if self.hung and self.sim.chance(self.faults.late):
            self.hung, self.late = False, True
            self.sim.log(self.proc.name, "replaced; sends late copies")
            self.sim.after(self._dt(), self._step, *self._where, proc=self.proc)
            return
        self.proc.dead = True

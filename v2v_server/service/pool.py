"""The worker pool: spawn worker processes, notice deaths, replace dead or hung ones, stop them.

The pool owns processes only; which task a worker runs is the server's decision
(``delivery/plan_schedule.py``), and messages travel on the server's backend socket. With ``shm`` on, it
also owns each worker's shared-memory slot ring (``shm.SlotRing``): created before the
spawn, unlinked by the worker once mapped (and by the pool when the worker dies or stops),
unmapped here when the worker is gone. A restarted worker gets a fresh ring, so a crash never
touches another worker's slots.
"""
from __future__ import annotations

import logging
import multiprocessing as mp
import os
import signal
import time
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Tuple

from v2v_server.faults import cause_of, warn_once
from v2v_server.service.shm import SlotRing, create_ring
from v2v_server.service.worker import WorkerSetup, worker_main

log = logging.getLogger("v2v.server")


@dataclass
class WorkerProc:
    """One worker process: its position in the pool (0 .. size - 1, kept across restarts),
    its restart generation and ZeroMQ identity ``w<position>.<generation>``."""

    position: int
    generation: int
    ident: bytes
    proc: mp.Process
    idle: bool = False  # said ready and holds no task
    ring: Optional[SlotRing] = None  # its shared-memory slots (None: arrays come as frames)
    started: float = 0.0  # time.monotonic() at its spawn
    ready: bool = False  # it said ready (``worker_messages.Ready``)


class WorkerPool:
    """``size`` spawned worker processes connected to ``endpoint``.

    Args:
        setup: what each worker is given (``worker.worker_config(cfg)``: the sample recipe, the
            log format).
        corpus: what each worker builds its corpus from (``worker.worker_main``'s ``corpus``).
        endpoint: the server's worker endpoint (ipc).
        size: number of workers.
        target: process entry point (``worker_main``; tests may pass another), called as
            ``target(setup, corpus, endpoint, identity, parent_pid[, ring_spec])``; the sixth
            argument, ``SlotRing.spec``, only when the worker has a ring.
        shm: give each worker a shared-memory slot ring (where ``/dev/shm`` allows; the
            worker falls back to sending frames otherwise).
    """

    def __init__(self, setup: WorkerSetup, corpus, endpoint: str, size: int, target: Callable = worker_main,
                 shm: bool = True):
        self.setup, self.corpus, self.endpoint, self.size, self.target = setup, corpus, endpoint, size, target
        self.shm = shm
        self.workers: Dict[bytes, WorkerProc] = {}
        self.restarts = 0

    def start(self) -> None:
        for position in range(self.size):
            self._spawn(position, 0)

    def _spawn(self, position: int, generation: int) -> None:
        ident = f"w{position}.{generation}".encode()
        r = self.setup.recipe
        ring = create_ring(r.sequence_length, r.num_bins, r.crop_size) if self.shm else None
        args = (self.setup, self.corpus, self.endpoint, ident, os.getpid())
        proc = mp.get_context("spawn").Process(target=self.target, args=args + ((ring.spec,) if ring else ()),
                                               name=f"v2v-worker-{position}", daemon=True)
        try:
            proc.start()
        except BaseException:
            _drop_ring(ring)
            raise
        self.workers[ident] = WorkerProc(position, generation, ident, proc, ring=ring, started=time.monotonic())

    def get(self, ident: bytes):
        return self.workers.get(ident)

    def idle(self) -> List[WorkerProc]:
        return [w for w in self.workers.values() if w.idle]

    def reap(self) -> List[Tuple[bytes, object]]:
        """Replace every worker that died; returns ``(ident, exit code)`` of the dead."""
        dead = []
        for ident, w in list(self.workers.items()):
            if w.proc.is_alive():
                continue
            dead.append((ident, w.proc.exitcode))
            del self.workers[ident]
            _drop_ring(w.ring)
            self.restarts += 1
            self._spawn(w.position, w.generation + 1)
        return dead

    def replace(self, ident: bytes) -> None:
        """Kill a hung (or stopped) worker and start a fresh one in its slot."""
        w = self.workers.pop(ident, None)
        if w is None:
            return
        try:
            os.kill(w.proc.pid, signal.SIGKILL)  # works on a SIGSTOPped process too
        except (OSError, TypeError):
            pass
        w.proc.join(2.0)
        _drop_ring(w.ring)
        self.restarts += 1
        self._spawn(w.position, w.generation + 1)

    def stop(self, send_stop: Callable[[bytes], None], grace_s: float = 3.0) -> None:
        """Ask every worker to stop, then terminate and kill what is left after ``grace_s``."""
        for w in self.workers.values():
            if w.proc.is_alive():
                send_stop(w.ident)
        deadline = time.monotonic() + grace_s
        for w in self.workers.values():
            w.proc.join(max(0.0, deadline - time.monotonic()))
            if w.proc.is_alive():
                w.proc.terminate()
                w.proc.join(1.0)
            if w.proc.is_alive():
                w.proc.kill()
                w.proc.join(1.0)
            _drop_ring(w.ring)


def _drop_ring(ring: Optional[SlotRing]) -> None:
    """Unlink (if the worker never did) and unmap a gone worker's ring."""
    if ring is not None:
        try:
            ring.unlink()
        except OSError as e:  # a failing tmpfs: the file stays until the next server's sweep
            warn_once(log, ("ring unlink", cause_of(e)), "cannot remove the slot ring %s: %s", ring.path, e)
        ring.close()

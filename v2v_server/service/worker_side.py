"""The server loop's worker side: tasks out, samples and reports in, dead and hung workers replaced.

``WorkerSide`` reads the messages of the backend socket (``ready``, ``sample``, ``done``: typed and
checked at the edge, ``v2v_wire.worker_messages``), asks
the scheduler (``delivery.plan_schedule.PlanScheduler``) what each means, gives slots back, hands idle
workers their tasks, and logs once per (file, reason) why a file, or the rest of it, is skipped
this epoch. It decides nothing itself: the scheduler does; it owns no process: the pool does.
"""
from __future__ import annotations

import logging
import time
from typing import Dict, List, Optional

import zmq

from v2v_server.delivery.plan_schedule import PlanScheduler
from v2v_server.ops.config import ServeConfig
from v2v_server.ops.metrics import ServerMetrics
from v2v_server.service.assembly import sample_from_slot, sample_from_worker
from v2v_server.service.pool import WorkerPool
from v2v_server.sources.source import VideoSource
from v2v_wire.protocol import ProtocolError, pack, unpack
from v2v_wire.worker_messages import Done, Failure, Ready, Sample, Slot, Stop, worker_message

log = logging.getLogger("v2v.server")

#: Seconds a worker may take from its spawn to saying it is ready (a cold start imports numpy,
#: OpenCV, PyAV and numba: seconds) before it is taken for hung and replaced; a larger
#: ``task_timeout_s`` is the bound instead.
START_S = 30.0


class WorkerSide:
    """The workers as the server loop sees them.

    Args:
        cfg: the server's ``ServeConfig``.
        source: the corpus's ``sources.source.VideoSource`` (where a video lives, for log lines).
        scheduler: the scheduler the reports go to.
        metrics: counters of samples, restarts, timeouts and skipped files.

    ``attach(backend, pool)`` once the socket is bound and the pool started.
    """

    def __init__(self, cfg: ServeConfig, source: VideoSource, scheduler: PlanScheduler, metrics: ServerMetrics):
        self.cfg, self.source, self.scheduler, self.metrics = cfg, source, scheduler, metrics
        self.backend: Optional[zmq.Socket] = None
        self.pool: Optional[WorkerPool] = None
        self.skipped_files: Dict[str, str] = {}  # video -> the first reason it was skipped for
        self.logged_failures: set = set()
        self.seen = False  # some worker said ready (/readyz)

    def attach(self, backend: zmq.Socket, pool: WorkerPool) -> None:
        self.backend, self.pool = backend, pool

    def stop(self) -> None:
        """Ask every worker to stop (then the pool terminates what is left)."""
        def send_stop(ident):
            try:
                self.backend.send_multipart([ident, pack(Stop().to_wire())], zmq.NOBLOCK)
            except zmq.ZMQError:
                pass
        self.pool.stop(send_stop)

    def watch(self, now: float) -> None:
        """Replace dead workers (their tasks go back to the queue) and hung ones: silent on a task
        for ``task_timeout_s``, or not ready ``max(START_S, task_timeout_s)`` seconds after their
        spawn (a worker stopped or stuck before its first message holds no task to time out, and
        would serve nothing for good). Called once per loop turn."""
        for ident, code in self.pool.reap():
            self.metrics.on_worker_restarted()
            run = self.scheduler.worker_lost(ident)
            if run is not None:
                log.warning("worker %s died (exit code %s); restarting; re-queued %s epoch %d", ident.decode(),
                            code, run.video, run.epoch)
                if run.error:
                    self.log_failure(run.video, run.error)
            else:
                log.warning("worker %s died (exit code %s); restarting", ident.decode(), code)
        for ident, run in self.scheduler.timed_out(now):
            self.metrics.on_task_timed_out()
            log.warning("worker %s sent nothing on %s epoch %d for %.0f s; task reassigned, worker restarted",
                        ident.decode(), run.video, run.epoch, self.cfg.task_timeout_s)
            self.pool.replace(ident)
            self.metrics.on_worker_restarted()
        limit = max(START_S, self.cfg.task_timeout_s)
        for w in [w for w in self.pool.workers.values() if not w.ready and now - w.started > limit]:
            log.warning("worker %s said nothing in the %.0f s since it started; restarted", w.ident.decode(), limit)
            self.pool.replace(w.ident)
            self.metrics.on_worker_restarted()

    def on_message(self, frames) -> None:
        """One message from a worker (identity frame, header, array frames), checked at the edge
        (``worker_messages.worker_message``): ``Ready``, ``Sample`` or ``Done``."""
        ident = frames[0].bytes
        w = self.pool.get(ident)
        try:
            h = unpack(frames[1])
        except ProtocolError as e:
            log.error("bad message from worker %s: %s", ident, e)
            return
        if w is None:
            return  # a replaced worker's last words
        try:
            msg = worker_message(h, self.cfg.crops_per_window)
        except ProtocolError as e:
            log.error("bad message from worker %s: %s", ident, e)
            slot = h.get("slot")
            if h.get("type") == "sample" and isinstance(slot, int) and not isinstance(slot, bool):
                self.give_slot(ident, slot)  # a malformed header never costs the worker a slot
            return
        now = time.monotonic()
        if isinstance(msg, (Sample, Done)):
            self.metrics.on_worker_message(msg)  # stage seconds, a task's cuts and store reads
        if isinstance(msg, Ready):
            if w.ring is not None and not msg.ring:
                log.warning("worker %s could not map its slot ring; it sends arrays as socket frames", ident.decode())
            w.idle = w.ready = True
            self.seen = True  # /readyz: a worker is up
        elif isinstance(msg, Sample):
            cpw = self.cfg.crops_per_window
            if msg.slot is not None and w.ring is not None:  # arrays in the worker's shared memory
                build = lambda: sample_from_slot(msg, w.ring, frames[2:], cpw)  # noqa: E731
            else:
                build = lambda: sample_from_worker(msg, frames[2:], cpw)  # noqa: E731
            try:
                kept = self.scheduler.sample(ident, msg.task, msg.key, now, build)
            except (ProtocolError, KeyError, TypeError, ValueError) as e:
                log.error("bad sample from worker %s: %s", ident, e)
                return
            finally:
                if msg.slot is not None:  # copied out (or not wanted): the worker may write it again
                    self.give_slot(ident, msg.slot)
            if kept:
                self.metrics.on_sample_made(msg.meta)
        else:
            self.on_done(w, msg)

    def give_slot(self, ident: bytes, slot: int) -> None:
        """Tell worker ``ident`` that ``slot`` of its ring may be written again."""
        try:
            self.backend.send_multipart([ident, pack(Slot(slot).to_wire())], zmq.NOBLOCK)
        except zmq.ZMQError:
            pass

    def on_done(self, w, msg: Done) -> None:
        """A worker's task ended: the scheduler is told; failed windows and a pass stopped early are
        logged (an exception with its type and where it was raised)."""
        run = self.scheduler.done(w.ident, msg.task, msg.windows, msg.failed, msg.error, msg.cause)
        if run is None:
            return
        w.idle = True
        for k, why in sorted(msg.failed.items()):
            self.log_failure(run.video, f"window {k}: {why}")
        if msg.error:
            self.log_failure(run.video, msg.error, served=msg.windows, failure=msg.failure, cause=msg.cause)

    def log_failure(self, video: str, reason: str, served: int = 0, failure: Optional[Failure] = None,
                    cause: str = "") -> None:
        """Log once per (file, reason) why a file, or the rest of it after ``served``
        windows, is skipped this epoch: the file's verdict, the reason the Ray engine gives too;
        with the worker's ``failure`` (the exception that stopped the pass), its type, where it
        was raised and its traceback on a debug line (``--log-level DEBUG``). ``cause``: the
        reason's code (``worker_messages.CAUSES``): a ``"short"`` clip is logged at INFO, a
        property of the clip, not a fault."""
        if video not in self.skipped_files:
            self.metrics.on_file_skipped()
        self.skipped_files.setdefault(video, reason)
        if (video, reason) not in self.logged_failures and len(self.logged_failures) < 100000:
            self.logged_failures.add((video, reason))
            if failure is not None:
                log.debug("%s raised %s:\n%s", failure.exc_type, failure.where, failure.traceback)
            if served:
                log.warning("%s: %s in window %d; windows 0-%d were served, the rest of the file is skipped this "
                            "epoch", self.source.where(video), reason, served, served - 1)
            else:  # a clip too short for one window (cause "short") is no fault of the file: not a warning
                log.log(logging.INFO if cause == "short" else logging.WARNING, "skipped %s: %s",
                        self.source.where(video), reason)

    def dispatch(self, now: float, codecs: List[str]) -> None:
        """A task for each idle worker while there are tasks; ``codecs``: what the workers
        compress each sample with (the codecs connected clients asked for over sockets)."""
        for w in self.pool.idle():
            task = self.scheduler.task_for(w.ident, now, codecs)
            if task is None:
                return
            w.idle = False
            self.backend.send_multipart([w.ident, pack(task.to_wire())])

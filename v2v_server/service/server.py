"""The v2v server loop: wires the worker pool, the epoch scheduler and the delivery ledger to ZeroMQ.

Topology::

    workers (DEALER) --ipc--> [backend ROUTER]  server loop  [frontend ROUTER] <--tcp-- clients (DEALER)

The decisions live in small pure modules, tested directly (``tests/test_delivery_core.py``):

* ``schedule.EpochScheduler``: which samples are owed in which epoch, which task makes them,
  resume states (authoritative), per-epoch failures of single samples, task timeouts;
* ``ledger.DeliveryLedger`` and its ``table.BatchTable``: the one table of batches and their
  states, credits by batch id, leases, revokes that expire, re-sends, fair sharing, DDP groups;
* ``core.DeliveryCore``: the two glued together with batching, the ends of epochs and of the
  stream, and the connections found unreachable (still pure; this module reads it only through
  its methods);
* ``v2v_wire.messages``: bounded decoding and typed messages from clients; ``pool.WorkerPool``:
  processes.

This module only moves bytes: its loop reads the sockets, hands worker messages to
``worker_side.WorkerSide`` and client messages to ``client_side.ClientSide`` (which ask those
modules and send what they say), and owns the server's life: start, exit (when the core says
the stream is over), status, shutdown. A batch's arrays stay an opaque ``assembly.BatchPayload``.
"""
from __future__ import annotations

import logging
import signal
import threading
import time
from typing import Dict, List, Optional, Tuple

import zmq

from v2v_server.ops.config import ServeConfig
from v2v_server.ops.startup import corpus_fingerprint
from v2v_server.disk_cache import UsageScan
from v2v_server.frames.host_caches import HostCaches
from v2v_server.sources.source import VideoSource
from v2v_server.delivery.journal import Journal
from v2v_server.flow.options import check_option
from v2v_server.delivery.ledger import STALL_S
from v2v_server.delivery.core import DeliveryCore
from v2v_server.service.client_side import ClientSide
from v2v_server.service.assembly import BatchAssembler, make_batch
from v2v_server.service.shm import BatchDir
from v2v_server.ops.metrics import ServerMetrics
from v2v_server.service.pool import WorkerPool
from v2v_server.service.worker import worker_config
from v2v_server.service.sockets import ServerSockets
from v2v_server.service.worker_side import WorkerSide
from v2v_wire.protocol import MAX_CLIENT_MSG, PROTOCOL_VERSION
from v2v_wire.stream_messages import Heartbeat, ServerError, Shutdown

log = logging.getLogger("v2v.server")

#: Seconds between scans of the frame cache's folder for its bytes and entries (gauges).
FRAME_CACHE_SCAN_S = 5.0


class V2VServer:
    """Serve V2V batches from the videos of ``root``.

    Args:
        cfg: validated ``ServeConfig``.
        source: the corpus (``sources.source.VideoSource``, a folder or an object-store
            prefix, built at the server's start); the server only opens the videos listed in
            ``videos``, and its workers build the same source from ``source.spec()``.
        caches: the host's frame cache and corpus index (``frames.host_caches.HostCaches``),
            passed beside ``source``; its workers build the same from ``caches.spec()``.
        videos: sample-id paths of the videos, relative to ``root`` (POSIX strings).
        corpus: the fingerprint of the whole listing before sharding (``ops.startup.corpus_fingerprint``).
        epoch_samples: samples an epoch holds, when known at start (``frames.known.known_windows``).
        skipped: videos of the listing not served, known to give no window -> ``(cause, reason)``
            (``frames.known.KnownWindows.empty``): logged and counted as a skip found by reading them would be.

    Call ``run()`` (blocks until ``--epochs`` are delivered or ``stop()`` is called).

    Raises:
        ValueError: for an empty ``videos`` list.
    """

    def __init__(self, cfg: ServeConfig, source: VideoSource, caches: HostCaches, videos: List[str],
                 corpus: Optional[str] = None,
                 epoch_samples: Optional[int] = None, skipped: Optional[Dict[str, Tuple[str, str]]] = None):
        if not videos:
            raise ValueError(f"no video files under {source.root}")
        self.cfg = cfg
        self.source, self.caches = source, caches
        fc = caches.frame_cache
        self.frame_cache_scan = UsageScan(fc.disk, FRAME_CACHE_SCAN_S) if fc is not None else None
        self.root = self.source.root
        self.videos = list(videos)
        self.corpus = corpus or corpus_fingerprint(self.videos)  # of the listing before sharding
        self.recipe = cfg.recipe.fingerprint()
        self._stop = threading.Event()
        self.metrics = ServerMetrics()
        #: Samples an epoch holds, when known at start (the corpus index knew every video); None otherwise.
        self.epoch_samples = epoch_samples
        if epoch_samples is not None:
            self.metrics.set_epoch_samples(epoch_samples, cfg.delivery.epochs)
        self.journal = (Journal(cfg.state_dir, self.recipe, crops_per_window=cfg.crops_per_window,
                                on_error=lambda path, e: self.metrics.on_fs_error("journal", path, e))
                        if cfg.state_dir is not None else None)  # JournalError: another recipe's journal
        if self.journal is not None and self.journal.records:
            log.info("%s: %d consumer record(s) of open epochs after epoch %d; nothing in them is sent again",
                     self.journal.path, len(self.journal.records), self.journal.completed)
        # a stall of this loop (stopped, swapped out) is not its clients' silence: ledger.STALL_S; batch ids
        # from the start time in ns, above any a server before it sent (docs/delivery.md, "Transport")
        self.core = DeliveryCore(self.videos, cfg.delivery, make_batch, self.journal, stall_s=STALL_S,
                                 end_grace_s=cfg.end_grace_s, first_batch_id=time.time_ns())
        self.core.info = self.stream_info
        self.bound_endpoint: Optional[str] = None
        self.pool: Optional[WorkerPool] = None
        self.assembler: Optional[BatchAssembler] = None  # built once the bind says where its buffers live
        self._resent_seen = 0  # batches given back to the queue already counted
        self.workers = WorkerSide(cfg, self.source, self.core, self.metrics)
        for video, (cause, why) in (skipped or {}).items():  # known to give no window: logged and counted as if read
            self.workers.log_failure(video, f"{why} (known from the corpus index: not opened)", cause=cause)
        self.clients = ClientSide(cfg, self.core, self.metrics)

    # ------------------------------------------------------------------ lifecycle
    def stop(self) -> None:
        """Ask the loop to stop (thread- and signal-safe)."""
        self._stop.set()

    def run(self, ready_event: Optional[threading.Event] = None) -> int:
        """Run until the stream ends or ``stop()``; returns a process exit code."""
        self.sockets = ServerSockets()
        self.frontend, self.backend = self.sockets.frontend, self.sockets.backend
        try:
            if self.cfg.metrics_port is not None:
                self.metrics.serve(self.cfg.metrics_host, self.cfg.metrics_port)
            self.bound_endpoint = self.sockets.bind(self.cfg)
            # shared-memory samples go straight into batch rows; for trainers on this host
            # (ipc://) the batch buffers are files in /dev/shm they read
            self.assembler = BatchAssembler(self.cfg.batch_size, files=BatchDir.create() if self.bound_endpoint
                                            .startswith("ipc://") else None,
                                            on_error=lambda path, e: self.metrics.on_fs_error("shm", path, e))
            corpus = {"source": self.source.spec(), "caches": self.caches.spec()}
            self.pool = WorkerPool(worker_config(self.cfg), corpus, self.sockets.backend_endpoint,
                                   self.cfg.workers)
            self.workers.attach(self.backend, self.pool, self.assembler)
            self.clients.attach(self.frontend, self.assembler)
            self.pool.start()
            rings = any(w.ring is not None for w in self.pool.workers.values())
            log.info("serving %d video(s) from %s on %s with %d worker(s); samples travel %s",
                     len(self.videos), self.root, self.bound_endpoint, self.cfg.workers,
                     "through shared-memory slot rings" if rings else "as socket frames")
            if self.assembler.files is not None:
                log.info("batch buffers in %s: trainers on this host that ask for it (V2VPushDataset shm='auto') "
                         "read batches from there instead of the socket", self.assembler.files.path)
            if ready_event is not None:
                ready_event.set()
            return self._loop()
        finally:
            self._shutdown()

    def _shutdown(self) -> None:
        if self.pool is not None:
            self.workers.stop()
        if getattr(self, "sockets", None) is not None:
            self.sockets.close()
        if self.assembler is not None:
            self.assembler.close()  # the batch files in /dev/shm go, also after a crash of the loop
        if self.journal is not None:
            self.journal.close()
        self._count_resent()
        self.metrics.close()
        m = self.metrics.totals()
        log.info("stopped: %d batches sent (%d re-sent), %d samples made, %d worker restart(s), "
                 "%d task timeout(s), %d skipped file(s)", m["batches_sent"], m["batches_resent"],
                 m["samples_made"], m["workers_restarted"], m["tasks_timed_out"], m["files_skipped"])

    # ------------------------------------------------------------------ main loop
    def _loop(self) -> int:
        next_beat = 0.0
        next_status = time.monotonic() + 30.0
        try:
            while not self._stop.is_set():
                poller = zmq.Poller()
                poller.register(self.frontend, zmq.POLLIN)
                reading = self.core.ready_count() < self.cfg.prefetch_batches  # else back-pressure
                if reading:
                    poller.register(self.backend, zmq.POLLIN)
                events = dict(poller.poll(100))
                self.clients.read(self.frontend in events)
                if self.backend in events:
                    for _ in range(16):
                        if self.core.ready_count() >= self.cfg.prefetch_batches:
                            break
                        try:
                            frames = self.backend.recv_multipart(zmq.NOBLOCK, copy=False)
                        except zmq.Again:
                            break
                        self.workers.on_message(frames)
                now = time.monotonic()
                if self._stop.is_set():  # workers that exit now were signalled with the server, not crashed
                    break
                self.workers.watch(now, reading)  # a task's silence counts only in turns that read its worker
                self.workers.dispatch(now, self.clients.socket_codecs())
                self.clients.send_batches(now)
                self._count_resent()
                self.metrics.tick(self._metrics_state)  # gauges + liveness, at most 4 times a second
                if self.journal is not None:
                    self.journal.sync(now)
                if now >= next_beat:
                    self.clients.broadcast(Heartbeat())
                    next_beat = now + self.cfg.heartbeat_s
                if now >= next_status:
                    self._log_status()
                    next_status = now + 30.0
                if self.core.exit_due(now):
                    return 0
                if self._corpus_empty():
                    msg = (f"no usable video under {self.root}: "
                           + "; ".join(f"{k}: {v}" for k, v in sorted(self.workers.skipped_files.items())))
                    log.error(msg)
                    self.clients.broadcast(ServerError(msg))
                    return 2
        except Exception as e:  # a bug of ours: say so to every client before going down
            log.exception("server loop failed: %s", e)
            self.clients.broadcast(Shutdown())
            raise
        # graceful stop: batches still unacknowledged stay with their trainers' resume state
        # (a restarted server re-makes whatever they did not take); tell clients to wait or resume
        self.clients.broadcast(Shutdown())
        return 0

    # ------------------------------------------------------------------ status
    def _log_status(self) -> None:
        self._count_resent()
        m = self.metrics.totals()
        st = self.core.status()
        held, capacity = self.core.batcher.fill()
        log.info("status: %d client(s), %d batches sent (%d re-sent, %d acknowledged), %d samples made, "
                 "%d ready, %d in flight, shuffle buffer %d/%d samples, %d worker restart(s), %d task timeout(s), "
                 "%d file failure(s), %d bad message(s) (%d log lines suppressed)",
                 len(st["clients"]), m["batches_sent"], m["batches_resent"], st["acked"],
                 m["samples_made"], st["ready"], st["in_flight"], held, capacity,
                 m["workers_restarted"],
                 m["tasks_timed_out"], len(self.workers.skipped_files), m["bad_messages"], self.clients.bad.suppressed)
        usage = self._frame_cache_usage()
        if usage is not None:
            log.info("frame cache: %s", self.metrics.frame_cache_line(*usage))

    def _count_resent(self) -> None:
        """Count the batches given back to the queue into the metrics (the core requeues them
        inside its pure decisions; this is where the loop learns of them)."""
        resent = self.core.resent
        for _ in range(resent - self._resent_seen):
            self.metrics.on_batch_resent()
        self._resent_seen = resent

    def _metrics_state(self) -> dict:  # the gauges, as plain numbers
        alive = [w for w in (self.pool.workers.values() if self.pool else ()) if w.proc.is_alive()]
        st = self.core.status()
        held, capacity = self.core.batcher.fill()
        return {"clients": {i.hex()[:12]: v for i, v in st["clients"].items()},
                "queue_batches": st["ready"], "inflight_batches": st["in_flight"],
                "workers": len(alive), "workers_busy": sum(1 for w in alive if not w.idle),
                "epoch": st["epoch"], "epoch_videos": st["progress"][0], "epoch_videos_done": st["progress"][1],
                "shuffle_samples": held, "shuffle_capacity": capacity,
                **({} if (fc := self._frame_cache_usage()) is None else self.metrics.frame_cache_state(*fc)),
                "ready": self.bound_endpoint is not None and bool(alive) and self.workers.seen}

    def _frame_cache_usage(self) -> Optional[Tuple[int, int, int]]:
        """The host's frame cache as ``(bytes, entries, budget)`` (``disk_cache.UsageScan``); None
        when there is none. A failed scan is counted and logged once (``ServerMetrics.on_fs_error``)."""
        if self.frame_cache_scan is None:
            return None
        usage, err = self.frame_cache_scan.read(time.monotonic())
        if err is not None:
            self.metrics.on_fs_error("frame_cache", self.frame_cache_scan.disk.folder, err)
        return usage

    def _corpus_empty(self) -> bool:
        """Every file failed and nothing was ever made: no epoch can hold a sample."""
        sched = self.core.sched
        return (self.core.samples_made == 0 and all(v in sched.file_failures for v in self.videos) and
                any(p.complete for p in sched.plans.values()))

    # ------------------------------------------------------------------ clients
    def stream_info(self) -> dict:
        c = self.cfg
        return {"sequence_length": c.sequence_length, "num_bins": c.num_bins, "crop_size": c.crop_size,
                "batch_size": c.batch_size, "frames_per_bin": c.frames_per_bin, "seed": c.seed,
                "epochs": c.epochs, "videos": len(self.videos), "outputs": list(self.core.outputs or c.outputs),
                "offered_outputs": list(c.outputs), "flow_preset": c.flow_preset, "flow_dtype": c.flow_dtype,
                "flow_grid_points": _grid_points(c.flow_preset),
                "protocol": PROTOCOL_VERSION,
                "lease_s": c.lease_s, "client_timeout_s": c.client_timeout_s, "max_credits": c.max_credits,
                "shm_dir": self.assembler.files.path if self.assembler.files is not None else None,
                # identity: a fan-in checks its servers form one sharding of one corpus under one
                # recipe, and a resume state is refused under another recipe
                "shard": "%d/%d" % c.serving.shard_spec, "corpus": self.corpus, "recipe": self.recipe,
                "max_hello_bytes": MAX_CLIENT_MSG}


def _grid_points(flow_preset: str) -> int:
    """Points per side of the grid a tracked flow option sends its flow at (``flow_grid``), 0 for
    an option that sends dense ``flow``: a client makes padding of the form its batches have."""
    option = check_option(flow_preset)
    return option.track.grid if option.method == "tracked" else 0


def install_signal_handlers(server: V2VServer) -> List[int]:
    """SIGINT/SIGTERM stop the server cleanly (finish the loop, stop workers, close sockets).
    Returns the list the signal that stopped it is appended to (``v2v-serve`` then exits with
    128 + its number, as a shell reports a process a signal ended)."""
    stopped_by: List[int] = []

    def handler(signum, _frame):
        if not stopped_by:
            log.info("%s: shutting down", signal.Signals(signum).name)
        stopped_by.append(signum)
        server.stop()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stopped_by

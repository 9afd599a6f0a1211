"""The v2v server loop: wires the worker pool, the epoch scheduler and the delivery ledger to ZeroMQ.

Topology::

    workers (DEALER) --ipc--> [backend ROUTER]  server loop  [frontend ROUTER] <--tcp-- clients (DEALER)

The decisions live in small pure modules, tested directly (``tests/test_delivery_core.py``):

* ``schedule.EpochScheduler``: which samples are owed in which epoch, which task makes them,
  resume states (authoritative), per-epoch failures of single samples, task timeouts;
* ``ledger.DeliveryLedger``: credits by batch id, leases, revokes that expire, re-sends, fair
  sharing, DDP groups;
* ``core.DeliveryCore``: the two glued together with batching (still pure);
* ``wire``: bounded decoding and typed messages from clients; ``pool.WorkerPool``: processes.

This module only moves bytes: it reads sockets, asks those modules, and sends what they say.
A batch's arrays stay an opaque ``datapath.BatchPayload``.
"""
from __future__ import annotations

import logging
import signal
import threading
import time
from typing import Dict, List, Optional

import zmq

from v2v_wire import codecs
from v2v_server.ops.config import ServeConfig
from v2v_server.videos.corpus import corpus_fingerprint
from v2v_server.videos.source import source_from_spec
from v2v_server.delivery.journal import Journal
from v2v_server.delivery.core import DeliveryCore, DeliveryPolicy
from v2v_server.service.datapath import BatchAssembler, BatchDir, make_batch, sample_from_slot, sample_from_worker
from v2v_server.ops.metrics import ServerMetrics
from v2v_server.service.pool import WorkerPool
from v2v_server.service.worker import worker_config
from v2v_server.service.sockets import ServerSockets
from v2v_wire.protocol import MAX_CLIENT_MSG, PROTOCOL_VERSION, ProtocolError, pack, unpack
from v2v_wire.messages import BadPeers, Hello, WireError, decode_client

log = logging.getLogger("v2v.server")

#: Times a task may kill its worker before its file is given up for that epoch.
MAX_TASK_CRASHES = 3
#: Client messages handled per loop turn (then the workers get their turn).
CLIENT_BURST = 100


class V2VServer:
    """Serve V2V batches from the videos of ``root``.

    Args:
        cfg: validated ``ServeConfig``.
        root: corpus folder or ``videos.source.VideoSource`` (an object-store prefix); the
            server only opens the videos listed in ``videos``.
        videos: sample-id paths of the videos, relative to ``root`` (POSIX strings).

    Call ``run()`` (blocks until ``--epochs`` are delivered or ``stop()`` is called).

    Raises:
        ValueError: for an empty ``videos`` list.
    """

    def __init__(self, cfg: ServeConfig, root, videos: List[str], corpus: Optional[str] = None):
        if not videos:
            raise ValueError(f"no video files under {root}")
        self.cfg = cfg
        self.source = source_from_spec(root)
        self.root = self.source.root
        self.videos = list(videos)
        self.corpus = corpus or corpus_fingerprint(self.videos)  # of the listing before sharding
        self.recipe = cfg.fingerprint()
        self.skipped_files: Dict[str, str] = {}  # video -> the first reason it was skipped for
        self._stop = threading.Event()
        self.journal = (Journal(cfg.state_dir, self.recipe)
                        if cfg.state_dir is not None else None)  # JournalError: another recipe's journal
        if self.journal is not None and self.journal.records:
            log.info("%s: %d consumer record(s) of open epochs after epoch %d; nothing in them is sent again",
                     self.journal.path, len(self.journal.records), self.journal.completed)
        self.core = DeliveryCore(self.videos, DeliveryPolicy.from_config(cfg, MAX_TASK_CRASHES), make_batch,
                                 self.journal)
        self.sched, self.ledger = self.core.sched, self.core.ledger
        self.bad = BadPeers()
        self.logged_failures: set = set()
        self.ended = False  # every epoch delivered (at least once)
        self._told_end: set = set()  # connections told the stream ended
        self._ended_at: Optional[float] = None  # since when the stream ended with no trainer connected
        self.bound_endpoint: Optional[str] = None
        self.pool: Optional[WorkerPool] = None
        self.assembler = BatchAssembler(cfg.batch_size)  # shared-memory samples go straight into batch rows
        self.metrics = ServerMetrics()
        self._resent_seen = 0  # ledger.resent already counted
        self._worker_seen = False  # some worker said ready
        self._shm_clients: set = set()  # idents whose hello asked for shared-memory batches
        self._codecs: Dict[bytes, str] = {}  # ident -> the compression its hello asked for

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
            if self.bound_endpoint.startswith("ipc://"):  # trainers on this host: batch buffers in /dev/shm
                self.assembler.files = BatchDir.create()
            self.pool = WorkerPool(worker_config(self.cfg), self.source.spec(), self.sockets.backend_endpoint,
                                   self.cfg.workers)
            self.pool.start()
            rings = any(w.ring is not None for w in self.pool.workers.values())
            log.info("serving %d video(s) from %s on %s with %d worker(s); samples travel %s",
                     len(self.videos), self.root, self.bound_endpoint, self.cfg.workers,
                     "through shared-memory slot rings" if rings else "as socket frames")
            if self.assembler.files is not None:
                log.info("batch buffers in %s: trainers on this host that ask for it (V2VStreamDataset shm='auto') "
                         "read batches from there instead of the socket", self.assembler.files.path)
            if ready_event is not None:
                ready_event.set()
            return self._loop()
        finally:
            self._shutdown()

    def _shutdown(self) -> None:
        if self.pool is not None:
            def send_stop(ident):
                try:
                    self.backend.send_multipart([ident, pack({"type": "stop"})], zmq.NOBLOCK)
                except zmq.ZMQError:
                    pass
            self.pool.stop(send_stop)
        if getattr(self, "sockets", None) is not None:
            self.sockets.close()
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
    def _end_of_stream(self, now: float) -> bool:
        """With ``--epochs``: once every epoch is delivered, tell each connected trainer the
        stream ended (once per connection), and stay up ``end_grace_s`` with no trainer
        connected so that one resuming from an older checkpoint still gets the samples it
        lacks (its resume state reopens those epochs, ``schedule.apply_resume``). True when
        the server may exit."""
        if not self.core.finished():
            self._ended_at = None
            self._told_end.clear()
            return False
        if not self.ended:
            log.info("all %d epoch(s) delivered; ending the stream (the server stays up %.0f s with no trainer "
                     "connected, for trainers that resume)", self.cfg.epochs, self.cfg.end_grace_s)
            self.ended = True
        for ident in list(self.ledger.clients):  # a send to a peer gone drops it from the ledger
            if ident not in self._told_end:
                self._told_end.add(ident)
                self._send_client(ident, {"type": "end"})
        if self.ledger.clients:
            self._ended_at = None
            return False
        if self._ended_at is None:
            self._ended_at = now
        if now - self._ended_at >= self.cfg.end_grace_s:
            log.info("no trainer for %.0f s after the end of the stream; exiting", now - self._ended_at)
            return True
        return False

    def _loop(self) -> int:
        next_beat = 0.0
        next_status = time.monotonic() + 30.0
        try:
            while not self._stop.is_set():
                poller = zmq.Poller()
                poller.register(self.frontend, zmq.POLLIN)
                if len(self.ledger.ready) < self.cfg.prefetch_batches:
                    poller.register(self.backend, zmq.POLLIN)
                events = dict(poller.poll(100))
                if self.frontend in events:
                    for _ in range(CLIENT_BURST):
                        try:
                            frames = self.frontend.recv_multipart(zmq.NOBLOCK, copy=False)
                        except zmq.Again:
                            break
                        self._on_client(frames)
                if self.backend in events:
                    for _ in range(16):
                        if len(self.ledger.ready) >= self.cfg.prefetch_batches:
                            break
                        try:
                            frames = self.backend.recv_multipart(zmq.NOBLOCK, copy=False)
                        except zmq.Again:
                            break
                        self._on_worker(frames)
                now = time.monotonic()
                self._watch_workers(now)
                self._dispatch(now)
                self._send_batches(now)
                self.metrics.tick(self._metrics_state)  # gauges + liveness, at most 4 times a second
                if self.journal is not None:
                    self.journal.sync(now)
                if now >= next_beat:
                    self._broadcast({"type": "heartbeat"})
                    next_beat = now + self.cfg.heartbeat_s
                if now >= next_status:
                    self._log_status()
                    next_status = now + 30.0
                if self._end_of_stream(now):
                    return 0
                if self._corpus_empty():
                    msg = (f"no usable video under {self.root}: "
                           + "; ".join(f"{k}: {v}" for k, v in sorted(self.skipped_files.items())))
                    log.error(msg)
                    self._broadcast({"type": "error", "message": msg})
                    return 2
        except Exception as e:  # a bug of ours: say so to every client before going down
            log.exception("server loop failed: %s", e)
            self._broadcast({"type": "shutdown"})
            raise
        # graceful stop: batches still unacknowledged stay with their trainers' resume state
        # (a restarted server re-makes whatever they did not take); tell clients to wait or resume
        self._broadcast({"type": "shutdown"})
        return 0

    # ------------------------------------------------------------------ workers
    def _watch_workers(self, now: float) -> None:
        for ident, code in self.pool.reap():
            self.metrics.on_worker_restarted()
            job = self.core.worker_lost(ident)
            if job is not None:
                log.warning("worker %s died (exit code %s); restarting; re-queued %s epoch %d", ident.decode(),
                            code, job.video, job.epoch)
                if job.error:
                    self._log_failure(job.video, job.error)
            else:
                log.warning("worker %s died (exit code %s); restarting", ident.decode(), code)
        for ident, job in self.core.timed_out(now):
            self.metrics.on_task_timed_out()
            log.warning("worker %s sent nothing on %s epoch %d for %.0f s; task reassigned, worker restarted",
                        ident.decode(), job.video, job.epoch, self.cfg.task_timeout_s)
            self.pool.replace(ident)
            self.metrics.on_worker_restarted()

    def _on_worker(self, frames) -> None:
        ident = frames[0].bytes
        w = self.pool.get(ident)
        try:
            h = unpack(frames[1])
        except ProtocolError as e:
            log.error("bad message from worker %s: %s", ident, e)
            return
        if w is None:
            return  # a replaced worker's last words
        self.metrics.on_worker_message(h)  # stage seconds
        kind = h["type"]
        now = time.monotonic()
        if kind == "ready":
            if w.ring is not None and h.get("ring") is False:
                log.warning("worker %s could not map its slot ring; it sends arrays as socket frames", ident.decode())
            w.idle = True
            self._worker_seen = True  # /readyz: a worker is up
        elif kind == "sample":
            slot = h.get("slot")
            if slot is not None and w.ring is not None:  # arrays in the worker's shared memory
                build = lambda: sample_from_slot(h, w.ring, self.assembler, frames[2:])  # noqa: E731
            else:
                build = lambda: sample_from_worker(h, frames[2:])  # noqa: E731
            try:
                kept = self.core.sample(ident, h.get("task"), h.get("index"), now, build)
            except (ProtocolError, KeyError, TypeError, ValueError) as e:
                log.error("bad sample from worker %s: %s", ident, e)
                return
            finally:
                if slot is not None:  # copied out (or not wanted): the worker may write it again
                    try:
                        self.backend.send_multipart([ident, pack({"type": "slot", "slot": slot})], zmq.NOBLOCK)
                    except zmq.ZMQError:
                        pass
            if kept:
                self.metrics.on_sample_made()
        elif kind == "done":
            failed = h.get("failed") if isinstance(h.get("failed"), dict) else {}
            job = self.core.done(ident, h.get("task"), h.get("windows", 0), failed, h.get("error"))
            if job is None:
                return
            w.idle = True
            for k, why in sorted(failed.items()):
                self._log_failure(job.video, f"window {k}: {why}")
            if h.get("error"):
                n = h.get("windows", 0) if isinstance(h.get("windows"), int) else 0
                self._log_failure(job.video, h["error"], served=n)

    def _log_failure(self, video: str, reason: str, served: int = 0) -> None:
        """Log once per (file, reason) why a file, or the rest of it after ``served``
        windows, is skipped this epoch."""
        if video not in self.skipped_files:
            self.metrics.on_file_skipped()
        self.skipped_files.setdefault(video, reason)
        if (video, reason) not in self.logged_failures and len(self.logged_failures) < 100000:
            self.logged_failures.add((video, reason))
            if served:
                log.warning("%s: %s in window %d; windows 0-%d were served, the rest of the file is skipped this "
                            "epoch", self.source.where(video), reason, served, served - 1)
            else:
                log.warning("skipped %s: %s", self.source.where(video), reason)

    def _dispatch(self, now: float) -> None:
        for w in self.pool.idle():
            msg = self.core.task_for(w.ident, now)
            if msg is None:
                return
            # what workers compress with: each codec a connected client asked for (over sockets)
            msg["codecs"] = sorted({c for i, c in self._codecs.items() if c != "none" and i in self.ledger.clients
                                    and i not in self._shm_clients})
            w.idle = False
            self.backend.send_multipart([w.ident, pack(msg)])

    # ------------------------------------------------------------------ batches
    def _send_batches(self, now: float) -> None:
        sends, msgs = self.core.tick(now)
        for ident, b in sends:
            c = self.ledger.clients.get(ident)
            if c is None:
                continue
            ref = None
            if ident in self._shm_clients and b.batch_id >= 0:  # same host: a reference into the batch file
                ref = b.payload.shm_ref(c.outputs)
            if ref is not None:
                (specs, shm), frames = ref, []
                nbytes = sum(b.payload.arrays[s["name"]].nbytes for s in specs)
            else:  # compressed arrays are the workers' frames, forwarded as they came
                specs, frames = b.payload.wire(c.outputs, self._codecs.get(ident, "none"))
                nbytes = sum(_nbytes(f) for f in frames)
            header = {"type": "batch", "batch_id": b.batch_id, "epoch": b.epoch,
                      "sample_ids": b.payload.sample_ids, "params": b.payload.meta, "arrays": specs}
            if ref is not None:
                header["shm"] = shm
            if b.batch_id < 0:
                header["padding"] = True  # DDP: a repeat for a rank that has nothing to repeat; never acked
            try:
                self.frontend.send_multipart([ident, pack(header)] + frames, copy=False)
            except zmq.ZMQError as e:  # peer vanished (ROUTER_MANDATORY)
                log.warning("client %s unreachable (%s); dropping it", ident.hex(), e)
                self.core.forget(ident)
                continue
            self.metrics.on_batch_sent(len(b.payload.sample_ids), nbytes)
        for ident, msg in msgs:
            if msg.get("type") == "revoke":
                for _ in msg.get("batch_ids", ()):
                    self.metrics.on_lease_expired()
            self._send_client(ident, msg)
        self._count_resent()

    def _log_status(self) -> None:
        self._count_resent()
        m = self.metrics.totals()
        log.info("status: %d client(s), %d batches sent (%d re-sent, %d acknowledged), %d samples made, "
                 "%d ready, %d in flight, %d worker restart(s), %d task timeout(s), %d file failure(s), "
                 "%d bad message(s) (%d log lines suppressed)",
                 len(self.ledger.clients), m["batches_sent"], m["batches_resent"], self.ledger.acked,
                 m["samples_made"], len(self.ledger.ready), self.ledger.in_flight(), m["workers_restarted"],
                 m["tasks_timed_out"], len(self.skipped_files), m["bad_messages"], self.bad.suppressed)

    def _count_resent(self) -> None:
        """Count the ledger's re-queued batches into the metrics (the ledger re-queues them
        inside its pure decisions; this is where the loop learns of them)."""
        for _ in range(self.ledger.resent - self._resent_seen):
            self.metrics.on_batch_resent()
        self._resent_seen = self.ledger.resent

    def _metrics_state(self) -> dict:  # the gauges, as plain numbers
        alive = [w for w in (self.pool.workers.values() if self.pool else ()) if w.proc.is_alive()]
        newest = max(self.sched.plans) if self.sched.plans else None
        plan = self.sched.plans.get(newest) if newest is not None else None
        return {"clients": {c.ident.hex()[:12]: (c.credits, len(c.held)) for c in self.ledger.clients.values()},
                "queue_batches": len(self.ledger.ready), "inflight_batches": self.ledger.in_flight(),
                "workers": len(alive), "workers_busy": sum(1 for w in alive if not w.idle),
                "epoch": newest if newest is not None else -1,
                "epoch_videos": len(plan.jobs) if plan else 0,
                "epoch_videos_done": sum(1 for j in plan.jobs.values() if j.state == "done") if plan else 0,
                "ready": self.bound_endpoint is not None and bool(alive) and self._worker_seen}

    def _corpus_empty(self) -> bool:
        """Every file failed and nothing was ever made: no epoch can hold a sample."""
        return (self.core.samples_made == 0 and all(v in self.sched.file_failures for v in self.videos) and
                any(p.complete for p in self.sched.plans.values()))

    # ------------------------------------------------------------------ clients
    def _send_client(self, ident: bytes, msg: dict) -> None:
        try:
            self.frontend.send_multipart([ident, pack(msg)], zmq.NOBLOCK)
        except zmq.ZMQError:
            self.core.forget(ident)

    def _broadcast(self, msg: dict) -> None:
        for ident in list(self.ledger.clients):
            self._send_client(ident, msg)

    def stream_info(self) -> dict:
        c = self.cfg
        return {"sequence_length": c.sequence_length, "num_bins": c.num_bins, "crop_size": c.crop_size,
                "batch_size": c.batch_size, "frames_per_bin": c.frames_per_bin, "seed": c.seed,
                "epochs": c.epochs, "videos": len(self.videos), "outputs": list(self.core.outputs or c.outputs),
                "offered_outputs": list(c.outputs), "flow_preset": c.flow_preset, "flow_dtype": c.flow_dtype,
                "protocol": PROTOCOL_VERSION,
                "lease_s": c.lease_s, "client_timeout_s": c.client_timeout_s, "max_credits": c.max_credits,
                "shm_dir": self.assembler.files.path if self.assembler.files is not None else None,
                # identity: a fan-in checks its servers form one sharding of one corpus under one
                # recipe, and a resume state is refused under another recipe
                "shard": "%d/%d" % c.shard_spec, "corpus": self.corpus, "recipe": self.recipe,
                "max_hello_bytes": MAX_CLIENT_MSG}

    def _bad_peer(self, ident: bytes, why: str, now: float) -> None:
        self.metrics.on_bad_message()
        log_it, banned = self.bad.strike(ident, now)
        if log_it:
            log.warning("dropping client %s: %s", ident.hex(), why)
        if banned:
            log.warning("client %s keeps sending bad messages: ignoring it for %.0f s", ident.hex(), self.bad.ban_s)
        if not self.bad.banned(ident, now) or banned:
            self._send_client(ident, {"type": "error", "message": f"protocol error: {why}"})
        self.core.forget(ident)

    def _on_client(self, frames) -> None:
        ident = frames[0].bytes
        now = time.monotonic()
        if self.bad.banned(ident, now):
            return
        try:
            if len(frames) != 2:
                raise WireError(f"expected 1 frame after the identity, got {len(frames) - 1}")
            msg = decode_client(frames[1], MAX_CLIENT_MSG, self.cfg.max_credits, self.cfg.crops_per_window)
        except WireError as e:
            self._bad_peer(ident, str(e), now)
            return
        if isinstance(msg, Hello):
            self._shm_clients &= set(self.ledger.clients)  # forget clients gone since
            if msg.shm and self.assembler.files is not None:
                self._shm_clients.add(ident)
            else:
                self._shm_clients.discard(ident)
            for gone in set(self._codecs) - set(self.ledger.clients):
                del self._codecs[gone]
            if not codecs.available(msg.compression):
                self._send_client(ident, {"type": "error", "code": "compression",
                                          "message": f"this server cannot compress with {msg.compression!r}: "
                                                     f"{msg.compression} needs the 'wire' extra on the server "
                                                     f"(pip install 'v2v[wire]'); ask for compression 'none'"})
                return
            self._codecs[ident] = msg.compression
            replies = self.core.hello(ident, msg, now, self.stream_info)
        else:
            replies = self.core.message(ident, msg, now)
        for to, reply in replies:
            self._send_client(to, reply)


def _nbytes(frame) -> int:
    """Bytes of an outgoing frame (a numpy array, or a worker's compressed frame)."""
    return frame.nbytes if hasattr(frame, "nbytes") else len(frame.buffer if hasattr(frame, "buffer") else frame)


def install_signal_handlers(server: V2VServer) -> None:
    """SIGINT/SIGTERM stop the server cleanly (finish the loop, stop workers, close sockets)."""

    def handler(signum, _frame):
        log.info("signal %d: shutting down", signum)
        server.stop()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)

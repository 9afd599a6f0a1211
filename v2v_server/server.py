"""The v2v server: a worker pool that makes samples, and a credit-based ZeroMQ stream of batches.

Topology::

    workers (DEALER) --ipc--> [backend ROUTER]  server loop  [frontend ROUTER] <--tcp-- clients (DEALER)

* A task is one video of one epoch. Idle workers get the next task; a worker streams one
  message per sample, then ``done``.
* The server stacks samples of the same epoch into batches of ``batch_size`` (the last batch
  of an epoch may be smaller) and sends a batch only to a client holding a credit; a client
  grants credits when it acknowledges a batch. It reads from the workers only while fewer
  than ``prefetch_batches`` assembled batches wait, so memory stays bounded however slow the
  trainers are.
* An unacknowledged batch goes back to the queue when its lease expires or its client goes
  silent or says ``bye``; a dead worker is replaced and its unfinished windows are made again.
"""
from __future__ import annotations

import collections
import itertools
import logging
import multiprocessing as mp
import os
import shutil
import signal
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Deque, Dict, List, Optional, Set

import zmq

from .config import ALL_OUTPUTS, ServeConfig, is_loopback
from .datapath import BatchPayload, make_batch, sample_from_worker
from .metrics import ServerMetrics  # [iss12 metrics]
from .protocol import PROTOCOL_VERSION, ProtocolError, pack, unpack
from .sampler import parse_sample_id
from .worker import worker_main

log = logging.getLogger("v2v.server")

#: Largest message accepted from a client, bytes (ZMQ_MAXMSGSIZE); a resume hello lists the
#: sample ids a trainer already has, about 30 bytes each.
MAX_CLIENT_MSG = 16 * 1024 * 1024
#: Times a task may kill its worker before its video is skipped.
MAX_TASK_CRASHES = 3


@dataclass
class Task:
    task_id: int
    epoch: int
    video: str
    received: Set[int] = field(default_factory=set)  # sample indices received (sampler.parse_sample_id)
    worker: Optional[bytes] = None
    crashes: int = 0


@dataclass
class Batch:
    batch_id: int
    epoch: int
    payload: BatchPayload  # the data path's business (datapath.py)
    avoid: Optional[bytes] = None  # the client that gave it back: prefer another one

    @property
    def sample_ids(self) -> List[str]:
        return self.payload.sample_ids


@dataclass
class ClientState:
    ident: bytes
    outputs: tuple
    credits: int = 0
    last_seen: float = 0.0
    inflight: Set[int] = field(default_factory=set)


@dataclass
class WorkerState:
    slot: int
    ident: bytes
    proc: mp.Process
    task: Optional[int] = None
    idle: bool = False


@dataclass
class EpochState:
    epoch: int
    open_tasks: Set[int] = field(default_factory=set)
    pending: list = field(default_factory=list)  # SamplePayloads not yet batched
    unacked: Set[int] = field(default_factory=set)  # batch ids made but not acknowledged
    samples: int = 0
    complete: bool = False  # every task done and the last batch made
    announced: bool = False  # clients told that every batch of it was acknowledged


@dataclass
class ServerStats:
    batches_sent: int = 0
    batches_acked: int = 0
    batches_resent: int = 0
    samples_made: int = 0
    workers_restarted: int = 0
    bad_messages: int = 0
    skipped_files: Dict[str, str] = field(default_factory=dict)


class V2VServer:
    """Serve V2V batches from the videos under ``root``.

    Args:
        cfg: validated ``ServeConfig``.
        root: corpus folder; the server only opens the files listed in ``videos`` under it.
        videos: video paths relative to ``root`` (POSIX strings).

    Call ``run()`` (blocks until ``--epochs`` are delivered or ``stop()`` is called).
    """

    def __init__(self, cfg: ServeConfig, root: Path, videos: List[str]):
        if not videos:
            raise ValueError(f"no video files under {root}")
        self.cfg = cfg
        self.root = Path(root)
        self.videos = list(videos)
        self.stats = ServerStats()
        self._stop = threading.Event()
        self._ids = itertools.count()
        self._batch_ids = itertools.count()
        self.tasks: Dict[int, Task] = {}
        self.task_queue: Deque[int] = collections.deque()
        self.epochs: Dict[int, EpochState] = {}
        self.next_epoch = 0
        self.ready: Deque[Batch] = collections.deque()
        self.batches: Dict[int, Batch] = {}  # made and not yet acknowledged
        self.inflight: Dict[int, tuple] = {}  # batch_id -> (client ident, lease deadline)
        self.clients: Dict[bytes, ClientState] = {}
        self.workers: Dict[bytes, WorkerState] = {}
        self.outputs: Optional[tuple] = None  # fixed by the first client's hello
        self.exclude: Dict[int, Dict[str, Set[int]]] = {}  # epoch -> video -> sample indices trainers already have
        self.ended = False
        self.bound_endpoint: Optional[str] = None
        self.metrics = ServerMetrics()  # [iss12 metrics]

    # ------------------------------------------------------------------ lifecycle
    def stop(self) -> None:
        """Ask the loop to stop (thread- and signal-safe)."""
        self._stop.set()

    def run(self, ready_event: Optional[threading.Event] = None) -> int:
        """Run until the stream ends or ``stop()``; returns a process exit code."""
        self._ctx = zmq.Context()
        self._tmp = tempfile.mkdtemp(prefix="v2v-")
        self.frontend = self._ctx.socket(zmq.ROUTER)
        self.frontend.setsockopt(zmq.LINGER, 500)
        self.frontend.setsockopt(zmq.MAXMSGSIZE, MAX_CLIENT_MSG)
        self.frontend.setsockopt(zmq.ROUTER_MANDATORY, 1)
        self.frontend.setsockopt(zmq.SNDHWM, 0)  # credits bound what is queued
        self.backend = self._ctx.socket(zmq.ROUTER)
        self.backend.setsockopt(zmq.LINGER, 0)
        self.backend.setsockopt(zmq.RCVHWM, 4)
        self.backend_endpoint = f"ipc://{self._tmp}/workers"
        self._auth = None
        try:
            if self.cfg.metrics_port is not None:  # [iss12 metrics]
                self.metrics.serve(self.cfg.metrics_host, self.cfg.metrics_port)
            if self.cfg.curve_secret_key is not None:
                self._setup_curve()
            elif not is_loopback(self.cfg.bind):
                log.warning("binding %s WITHOUT authentication or encryption (--insecure): anyone who can "
                            "reach it can read the stream", self.cfg.bind)
            self.frontend.bind(self.cfg.bind)
            self.bound_endpoint = self.frontend.getsockopt_string(zmq.LAST_ENDPOINT)
            self.backend.bind(self.backend_endpoint)
            for slot in range(self.cfg.workers):
                self._spawn_worker(slot)
            log.info("serving %d video(s) from %s on %s with %d worker(s)",
                     len(self.videos), self.root, self.bound_endpoint, self.cfg.workers)
            if ready_event is not None:
                ready_event.set()
            return self._loop()
        finally:
            self._shutdown()

    def _setup_curve(self) -> None:
        """CurveZMQ on the client socket: our key pair, and a ZAP authenticator that admits
        only the public keys found in ``curve_allow``."""
        import zmq.auth
        from zmq.auth.thread import ThreadAuthenticator

        public, secret = zmq.auth.load_certificate(self.cfg.curve_secret_key)
        if not secret:
            raise ValueError(f"curve_secret_key {self.cfg.curve_secret_key}: holds no secret key")
        self._auth = ThreadAuthenticator(self._ctx, log=logging.getLogger("v2v.auth"))
        self._auth.start()
        self._auth.configure_curve(domain="*", location=str(self.cfg.curve_allow))
        self.frontend.curve_secretkey = secret
        self.frontend.curve_publickey = public
        self.frontend.curve_server = True
        allowed = len(list(Path(self.cfg.curve_allow).glob("*.key")))
        log.info("CurveZMQ on: %d allowed client key(s) in %s", allowed, self.cfg.curve_allow)

    def _spawn_worker(self, slot: int, generation: int = 0) -> None:
        ident = f"w{slot}.{generation}".encode()
        ctx = mp.get_context("spawn")
        proc = ctx.Process(
            target=worker_main,
            args=(self.cfg.to_dict(), str(self.root), self.backend_endpoint, ident, os.getpid()),
            name=f"v2v-worker-{slot}", daemon=True,
        )
        proc.start()
        self.workers[ident] = WorkerState(slot, ident, proc)

    def _shutdown(self) -> None:
        for w in self.workers.values():
            if w.proc.is_alive():
                try:
                    self.backend.send_multipart([w.ident, pack({"type": "stop"})], zmq.NOBLOCK)
                except zmq.ZMQError:
                    pass
        deadline = time.monotonic() + 3.0
        for w in self.workers.values():
            w.proc.join(max(0.0, deadline - time.monotonic()))
            if w.proc.is_alive():
                w.proc.terminate()
                w.proc.join(1.0)
            if w.proc.is_alive():
                w.proc.kill()
                w.proc.join(1.0)
        for s in (getattr(self, "frontend", None), getattr(self, "backend", None)):
            if s is not None:
                s.close()
        if getattr(self, "_auth", None) is not None:
            self._auth.stop()
        if getattr(self, "_ctx", None) is not None:
            self._ctx.term()
        shutil.rmtree(getattr(self, "_tmp", ""), ignore_errors=True)
        self.metrics.close()  # [iss12 metrics]
        log.info("stopped: %d batches sent (%d re-sent), %d samples made, %d worker restart(s), "
                 "%d skipped file(s)", self.stats.batches_sent, self.stats.batches_resent,
                 self.stats.samples_made, self.stats.workers_restarted, len(self.stats.skipped_files))

    # ------------------------------------------------------------------ main loop
    def _loop(self) -> int:
        next_beat = 0.0
        next_status = time.monotonic() + 30.0
        while not self._stop.is_set():
            poller = zmq.Poller()
            poller.register(self.frontend, zmq.POLLIN)
            if len(self.ready) < self.cfg.prefetch_batches:
                poller.register(self.backend, zmq.POLLIN)
            events = dict(poller.poll(100))
            if self.frontend in events:
                for _ in range(100):
                    try:
                        frames = self.frontend.recv_multipart(zmq.NOBLOCK)
                    except zmq.Again:
                        break
                    self._on_client(frames)
            if self.backend in events:
                for _ in range(16):
                    if len(self.ready) >= self.cfg.prefetch_batches:
                        break
                    try:
                        frames = self.backend.recv_multipart(zmq.NOBLOCK, copy=False)
                    except zmq.Again:
                        break
                    self._on_worker(frames)
            now = time.monotonic()
            self._check_workers()
            self._expire(now)
            self._dispatch()
            self._send_batches(now)
            if now >= next_beat:
                self._heartbeat()
                next_beat = now + self.cfg.heartbeat_s
            if now >= next_status:
                self._log_status()
                next_status = now + 30.0
            self._announce_epochs()
            self.metrics.tick(self._metrics_state)  # [iss12 metrics] gauges + liveness, at most 4 times a second
            if self._finished():
                self._broadcast({"type": "end"})
                log.info("all %d epoch(s) delivered; ending the stream", self.cfg.epochs)
                self.ended = True
                return 0
            if self._corpus_empty():
                msg = (f"no usable video under {self.root}: "
                       + "; ".join(f"{k}: {v}" for k, v in sorted(self.stats.skipped_files.items())))
                log.error(msg)
                self._broadcast({"type": "error", "message": msg})
                return 2
        # graceful stop: batches still unacknowledged stay with their trainers' resume state
        # (a restarted server re-makes whatever they did not take); tell clients to wait or resume
        self._broadcast({"type": "shutdown"})
        return 0

    # ------------------------------------------------------------------ workers
    def _check_workers(self) -> None:
        for ident, w in list(self.workers.items()):
            if w.proc.is_alive():
                continue
            code = w.proc.exitcode
            del self.workers[ident]
            self.stats.workers_restarted += 1
            self.metrics.on_worker_restarted()  # [iss12 metrics]
            gen = int(ident.decode().split(".")[1]) + 1
            if w.task is not None:
                t = self.tasks[w.task]
                t.worker = None
                t.crashes += 1
                if t.crashes >= MAX_TASK_CRASHES:
                    self._skip_file(t.video, f"worker crashed {t.crashes} times while processing it")
                    self._task_finished(t)
                else:
                    self.task_queue.appendleft(t.task_id)
                log.warning("worker %s died (exit code %s); restarting; re-queued %s epoch %d "
                            "(%d window(s) already received)", ident.decode(), code, t.video, t.epoch,
                            len(t.received))
            else:
                log.warning("worker %s died (exit code %s); restarting", ident.decode(), code)
            self._spawn_worker(w.slot, gen)

    def _on_worker(self, frames) -> None:
        ident = frames[0].bytes
        w = self.workers.get(ident)
        try:
            h = unpack(frames[1])
        except ProtocolError as e:
            log.error("bad message from worker %s: %s", ident, e)
            return
        self.metrics.on_worker_message(h)  # [iss12 metrics] stage seconds
        if w is None:
            return  # a replaced worker's last words
        kind = h["type"]
        if kind == "ready":
            w.idle = True
        elif kind == "sample":
            t = self.tasks.get(h.get("task"))
            if t is None or t.worker != ident or h["index"] in t.received:
                return
            if h["index"] in self._excluded(t.epoch, t.video):
                t.received.add(h["index"])
                return
            sample = sample_from_worker(h, frames[2:])
            t.received.add(h["index"])
            ep = self.epochs[t.epoch]
            ep.pending.append(sample)
            ep.samples += 1
            self.stats.samples_made += 1
            self.metrics.on_sample_made()  # [iss12 metrics]
            if len(ep.pending) >= self.cfg.batch_size:
                self._make_batch(ep)
        elif kind == "done":
            t = self.tasks.get(h.get("task"))
            if t is None or t.worker != ident:
                return
            w.task, w.idle = None, True
            if h.get("error"):
                self._skip_file(t.video, h["error"])
            self._task_finished(t)

    def _skip_file(self, video: str, reason: str) -> None:
        if video not in self.stats.skipped_files:
            self.stats.skipped_files[video] = reason
            self.metrics.on_file_skipped()  # [iss12 metrics]
            log.warning("skipped %s: %s", self.root / video, reason)

    def _task_finished(self, t: Task) -> None:
        ep = self.epochs[t.epoch]
        ep.open_tasks.discard(t.task_id)
        del self.tasks[t.task_id]
        if not ep.open_tasks:
            if ep.pending:
                self._make_batch(ep)
            ep.complete = True
            log.info("epoch %d made: %d samples", ep.epoch, ep.samples)

    def _new_epoch(self) -> bool:
        if self.cfg.epochs is not None and self.next_epoch >= self.cfg.epochs:
            return False
        e = self.next_epoch
        self.next_epoch += 1
        ep = EpochState(e)
        self.epochs[e] = ep
        for video in self.videos:
            if video in self.stats.skipped_files:
                continue
            tid = next(self._ids)
            self.tasks[tid] = Task(tid, e, video)
            ep.open_tasks.add(tid)
            self.task_queue.append(tid)
        if not ep.open_tasks:
            ep.complete = True
        return True

    def _dispatch(self) -> None:
        if self.outputs is None:
            return  # no client yet: nothing to make
        for w in self.workers.values():
            if not w.idle or w.task is not None:
                continue
            if not self.task_queue and not self._new_epoch():
                return
            if not self.task_queue:
                return
            t = self.tasks[self.task_queue.popleft()]
            t.worker = w.ident
            w.task, w.idle = t.task_id, False
            msg = {"type": "task", "task": t.task_id, "epoch": t.epoch, "video": t.video,
                   "outputs": list(self.outputs), "skip": sorted(t.received | self._excluded(t.epoch, t.video))}
            self.backend.send_multipart([w.ident, pack(msg)])

    # ------------------------------------------------------------------ batches
    def _make_batch(self, ep: EpochState) -> None:
        items = ep.pending[: self.cfg.batch_size]
        del ep.pending[: self.cfg.batch_size]
        b = Batch(next(self._batch_ids), ep.epoch, make_batch(items))
        self.batches[b.batch_id] = b
        ep.unacked.add(b.batch_id)
        self.ready.append(b)

    def _send_batches(self, now: float) -> None:
        if not self.ready:
            return
        while self.ready:
            eligible = [c for c in self.clients.values() if c.credits > 0]
            if not eligible:
                return
            b = self.ready[0]
            # spread batches over the clients; a batch given back goes elsewhere when it can
            c = max(eligible, key=lambda x: (x.ident != b.avoid, x.credits))
            self.ready.popleft()
            specs, frames = b.payload.wire(c.outputs)
            header = {"type": "batch", "batch_id": b.batch_id, "epoch": b.epoch, "sample_ids": b.sample_ids,
                      "params": b.payload.meta, "arrays": specs}
            try:
                self.frontend.send_multipart([c.ident, pack(header)] + frames, copy=False)
            except zmq.ZMQError as e:  # peer vanished (ROUTER_MANDATORY)
                log.warning("client %s unreachable (%s); dropping it", c.ident.hex(), e)
                self.ready.appendleft(b)
                self._drop_client(c.ident)
                return
            c.credits -= 1
            c.inflight.add(b.batch_id)
            self.inflight[b.batch_id] = (c.ident, now + self.cfg.lease_s)
            self.stats.batches_sent += 1
            self.metrics.on_batch_sent(len(b.sample_ids), sum(f.nbytes for f in frames))  # [iss12 metrics]

    def _requeue(self, batch_id: int, why: str) -> None:
        ident, _ = self.inflight.pop(batch_id, (None, None))
        c = self.clients.get(ident)
        if c is not None:
            c.inflight.discard(batch_id)
        b = self.batches.get(batch_id)
        if b is not None:
            self.ready.appendleft(b)
            self.stats.batches_resent += 1
            self.metrics.on_batch_resent()  # [iss12 metrics]
            log.info("batch %d goes back to the queue: %s", batch_id, why)

    def _expire(self, now: float) -> None:
        for bid, (ident, deadline) in list(self.inflight.items()):
            if now > deadline:
                # ask the client to give it back; it answers "released" unless its training loop
                # already took the batch (then its ack is on the way). A silent client is dropped
                # below, which re-queues everything it held.
                self.inflight[bid] = (ident, float("inf"))
                self.metrics.on_lease_expired()  # [iss12 metrics]
                log.info("lease of batch %d expired at client %s; asking for it back", bid, ident.hex())
                self._send_client(ident, {"type": "revoke", "batch_ids": [bid]})
        for ident, c in list(self.clients.items()):
            if now - c.last_seen > self.cfg.client_timeout_s:
                log.warning("client %s silent for %.0f s; dropping it", ident.hex(), now - c.last_seen)
                self._drop_client(ident)

    def _drop_client(self, ident: bytes) -> None:
        c = self.clients.pop(ident, None)
        if c is None:
            return
        for bid in sorted(c.inflight):
            self._requeue(bid, f"client {ident.hex()} left")

    def _announce_epochs(self) -> None:
        for ep in self.epochs.values():
            if ep.complete and not ep.unacked and not ep.announced:
                ep.announced = True
                self._broadcast({"type": "epoch_done", "epoch": ep.epoch})

    def _log_status(self) -> None:
        st = self.stats
        log.info("status: %d client(s), %d batches sent (%d re-sent, %d acknowledged), %d samples made, "
                 "%d ready, %d in flight, %d worker restart(s), %d skipped file(s), %d bad message(s)",
                 len(self.clients), st.batches_sent, st.batches_resent, st.batches_acked, st.samples_made,
                 len(self.ready), len(self.inflight), st.workers_restarted, len(st.skipped_files),
                 st.bad_messages)

    def _metrics_state(self) -> dict:  # [iss12 metrics] the gauges, as plain numbers
        newest = self.epochs.get(self.next_epoch - 1)
        alive = [w for w in self.workers.values() if w.proc.is_alive()]
        return {"clients": {c.ident.hex()[:12]: (c.credits, len(c.inflight)) for c in self.clients.values()},
                "queue_batches": len(self.ready), "inflight_batches": len(self.inflight),
                "workers": len(alive), "workers_busy": sum(1 for w in alive if w.task is not None),
                "epoch": newest.epoch if newest else -1,
                "epoch_videos": len(self.videos) if newest else 0,
                "epoch_videos_done": (len(self.videos) - len(newest.open_tasks)) if newest else 0,
                "ready": self.bound_endpoint is not None and any(w.idle or w.task is not None for w in alive)}

    def _excluded(self, epoch: int, video: str) -> Set[int]:
        return self.exclude.get(epoch, {}).get(video, set())

    def _apply_resume(self, resume) -> None:
        """Take a trainer's resume state: epochs it completed and sample ids it already has.
        Those samples are never made or sent again (by any client)."""
        if not isinstance(resume, dict):
            return
        completed = resume.get("completed_epoch", -1)
        delivered = resume.get("delivered", {})
        if not isinstance(completed, int) or not isinstance(delivered, dict):
            return
        if not self.epochs and completed + 1 > self.next_epoch:
            self.next_epoch = completed + 1  # a fresh server picks up where the trainer stands
            log.info("resuming at epoch %d", self.next_epoch)
        known = set(self.videos)
        added = 0
        for e, ids in delivered.items():
            try:
                e = int(e)
            except (TypeError, ValueError):
                continue
            if not isinstance(ids, list):
                continue
            for sid in ids:
                try:
                    video, k = parse_sample_id(sid, self.cfg.crops_per_window)
                except ValueError:
                    continue
                if video in known:
                    self.exclude.setdefault(e, {}).setdefault(video, set()).add(k)
                    added += 1
        if added:
            log.info("resume state: %d sample(s) already delivered will not be made or sent again", added)
            self._filter_ready()

    def _filter_ready(self) -> None:
        kept = collections.deque()
        for b in self.ready:
            keys = [parse_sample_id(sid, self.cfg.crops_per_window) for sid in b.sample_ids]
            keep = [i for i, (video, k) in enumerate(keys) if k not in self._excluded(b.epoch, video)]
            if len(keep) == len(b.sample_ids):
                kept.append(b)
                continue
            if not keep:
                self.batches.pop(b.batch_id, None)
                self.epochs[b.epoch].unacked.discard(b.batch_id)
                continue
            b.payload = b.payload.subset(keep)
            kept.append(b)
        self.ready = kept

    def _finished(self) -> bool:
        if self.cfg.epochs is None or self.next_epoch < self.cfg.epochs:
            return False
        return all(ep.complete and not ep.unacked for ep in self.epochs.values())

    def _corpus_empty(self) -> bool:
        return bool(self.epochs) and len(self.stats.skipped_files) >= len(self.videos) and \
            all(ep.complete for ep in self.epochs.values()) and not self.batches

    # ------------------------------------------------------------------ clients
    def _send_client(self, ident: bytes, msg: dict) -> None:
        try:
            self.frontend.send_multipart([ident, pack(msg)], zmq.NOBLOCK)
        except zmq.ZMQError:
            self._drop_client(ident)

    def _broadcast(self, msg: dict) -> None:
        for ident in list(self.clients):
            self._send_client(ident, msg)

    def _heartbeat(self) -> None:
        self._broadcast({"type": "heartbeat"})

    def stream_info(self) -> dict:
        c = self.cfg
        return {"sequence_length": c.sequence_length, "num_bins": c.num_bins, "crop_size": c.crop_size,
                "batch_size": c.batch_size, "frames_per_bin": c.frames_per_bin, "seed": c.seed,
                "epochs": c.epochs, "videos": len(self.videos), "outputs": list(self.outputs or c.outputs),
                "flow_preset": c.flow_preset, "protocol": PROTOCOL_VERSION}

    def _on_client(self, frames) -> None:
        ident = frames[0]
        try:
            if len(frames) != 2:
                raise ProtocolError(f"expected 1 frame after the identity, got {len(frames) - 1}")
            h = unpack(frames[1], max_bytes=MAX_CLIENT_MSG)
        except ProtocolError as e:
            self.stats.bad_messages += 1
            self.metrics.on_bad_message()  # [iss12 metrics]
            log.warning("dropping client %s: %s", ident.hex(), e)
            self._send_client(ident, {"type": "error", "message": f"protocol error: {e}"})
            self._drop_client(ident)
            return
        now = time.monotonic()
        kind = h["type"]
        c = self.clients.get(ident)
        if kind == "hello":
            self._on_hello(ident, h, now)
            return
        if c is None:
            # e.g. a client of a previous run of this server, reconnected by ZeroMQ on its own
            self._send_client(ident, {"type": "error", "code": "unknown_client",
                                      "message": "unknown client (this server may have restarted): say hello first"})
            return
        c.last_seen = now
        if kind == "ack":
            for bid in h.get("batch_ids", []) if isinstance(h.get("batch_ids"), list) else []:
                if self.inflight.get(bid, (None,))[0] == ident:
                    self.inflight.pop(bid)
                    c.inflight.discard(bid)
                    b = self.batches.pop(bid, None)
                    if b is not None:
                        self.epochs[b.epoch].unacked.discard(bid)
                        self.stats.batches_acked += 1
            c.credits += self._credit(h.get("credit", 0))
        elif kind == "released":
            ids = h.get("batch_ids") if isinstance(h.get("batch_ids"), list) else []
            for bid in ids:
                if self.inflight.get(bid, (None,))[0] == ident:
                    self._requeue(bid, "its lease expired and the client released it")
                    if bid in self.batches:
                        self.batches[bid].avoid = ident
            c.credits += self._credit(h.get("credit", 0))
        elif kind == "credit":
            c.credits += self._credit(h.get("credit", 0))
        elif kind == "heartbeat":
            pass
        elif kind == "bye":
            self._drop_client(ident)
        else:
            self.stats.bad_messages += 1
            self.metrics.on_bad_message()  # [iss12 metrics]
            log.warning("dropping client %s: unknown message type %r", ident.hex(), kind)
            self._send_client(ident, {"type": "error", "message": f"unknown message type {kind!r}"})
            self._drop_client(ident)

    @staticmethod
    def _credit(v) -> int:
        return v if isinstance(v, int) and 0 <= v <= 1024 else 0

    def _on_hello(self, ident: bytes, h: dict, now: float) -> None:
        outs = h.get("outputs")
        if not isinstance(outs, list) or not outs or any(o not in ALL_OUTPUTS for o in outs):
            self._send_client(ident, {"type": "error", "message": f"outputs must be a non-empty list from "
                                                                   f"{list(ALL_OUTPUTS)}, got {outs!r}"})
            return
        allowed = self.outputs or self.cfg.outputs
        missing = [o for o in outs if o not in allowed]
        if missing:
            why = "this server does not offer" if self.outputs is None else "this stream already makes only"
            self._send_client(ident, {"type": "error", "message": f"{why} {list(allowed)}; asked for {outs}"})
            return
        if self.outputs is None:
            self.outputs = tuple(o for o in ALL_OUTPUTS if o in outs)
            log.info("first client asks for %s: workers compute only these", list(self.outputs))
        self._apply_resume(h.get("resume"))
        self._drop_client(ident)  # a reconnect with the same identity: its in-flight batches go back
        self.clients[ident] = ClientState(ident, tuple(outs), self._credit(h.get("credits", 0)), now)
        self._send_client(ident, {"type": "welcome", "info": self.stream_info()})


def install_signal_handlers(server: V2VServer) -> None:
    """SIGINT/SIGTERM stop the server cleanly (finish the loop, stop workers, close sockets)."""

    def handler(signum, _frame):
        log.info("signal %d: shutting down", signum)
        server.stop()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)

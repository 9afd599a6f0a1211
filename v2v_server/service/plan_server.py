"""The server loop (``v2v-serve``, docs/delivery.md): stateless compute over the worker pool.

Topology::

    workers (DEALER) --ipc--> [backend ROUTER]  server loop  [frontend ROUTER] <--tcp-- readers (DEALER)

The decisions are ``delivery.plan_schedule.PlanScheduler``'s (pure); this loop moves bytes: client
messages (``v2v_wire.plan_messages``: ``plan_ask``, ``fetch``) in, ``plan`` / ``rows`` /
``refused`` out; worker messages through ``worker_side.WorkerSide``. Workers are read whatever the clients do, so their task clock counts only
their own silence. The server keeps no record of any client: a fetch names its rows, and a
server restarted or another one serving the same manifest and recipe answers it alike.
"""
from __future__ import annotations

import logging
import signal
import threading
import time
import uuid
from typing import Dict, Hashable, List, Optional, Sequence, Tuple

import numpy as np
import zmq

from v2v_server.delivery.plan_orders import Order
from v2v_server.delivery.plan_schedule import PlanScheduler, Row
from v2v_server.disk_cache import UsageScan
from v2v_server.frames.host_caches import HostCaches
from v2v_server.ops.config import ServeConfig
from v2v_server.ops.metrics import ServerMetrics
from v2v_server.ops.plan_record import plan_changes
from v2v_server.service.pool import WorkerPool
from v2v_server.service.sockets import ServerSockets
from v2v_server.service.worker import worker_config
from v2v_server.service.worker_side import WorkerSide
from v2v_server.sources.source import VideoSource
from v2v_wire.batches import encode_batch, frame_size, stack_arrays
from v2v_wire.codecs import COMPRESSIONS, available
from v2v_wire.outputs import narrowest, wire_row
from v2v_wire.plan import Manifest, PlanIdentity
from v2v_wire.plan_messages import (MANIFEST_PART, BadPeers, Make, ManifestAsk, ManifestPart, Moved, OldClient, PlanAsk,
                                     PlanInfo, Refused, Rows, WireError, Withdraw, decode_plan_client,
                                     old_client_answer)
from v2v_wire.protocol import MAX_BATCH_BYTES, MAX_CLIENT_MSG, encode_arrays, output_of, pack

log = logging.getLogger("v2v.server")

#: Seconds a task may send nothing while a fetch waits on it before a second worker takes it too.
HEDGE_S = 10.0
#: Seconds workers keep compressing each sample with a codec after the last fetch that asked for it.
CODEC_KEEP_S = 120.0
#: Seconds between scans of the frame cache's folder for its bytes and entries (gauges).
FRAME_CACHE_SCAN_S = 5.0


class PlanServer:
    """Serve the plan of ``manifest`` from the videos of ``source``.

    Args:
        cfg: validated ``ServeConfig`` (its recipe, seed, shuffle buffer, workers, bind,
            task timeout).
        source, caches: the corpus (``sources.source.VideoSource``) and the host's caches.
        manifest: the videos served, with the slots the corpus index knows
            (``ops.plan_start.plan_manifest``); the others' are learned from their decodes.
        corpus: the fingerprint of the whole listing before sharding
            (``ops.startup.corpus_fingerprint``): readers of several shards check it is one corpus.
        skipped: the videos the corpus index knows to give no window -> ``(cause, reason)``
            (``ops.startup.Startup.skipped``): never opened, each named once with its reason and
            counted as a skipped file, as a decode that found it unusable would be.

    Call :meth:`run` (blocks until :meth:`stop`).
    """

    def __init__(self, cfg: ServeConfig, source: VideoSource, caches: HostCaches, manifest: Manifest,
                 corpus: Optional[str] = None, skipped: Optional[Dict[str, Tuple[str, str]]] = None):
        self.cfg, self.source, self.caches, self.manifest, self.corpus = cfg, source, caches, manifest, corpus
        d = cfg.delivery
        # made ahead: a shuffle buffer of samples; kept once fetched: a batch, for
        # a fetch asked again after a lost reply
        self.scheduler = PlanScheduler(manifest, cfg.seed, d.shuffle_buffer, cfg.outputs, lookahead=d.shuffle_buffer,
                                       keep_samples=d.batch_size, hedge_s=min(HEDGE_S, d.task_timeout_s),
                                       task_timeout_s=d.task_timeout_s)
        self.identity = PlanIdentity(manifest.fingerprint(), cfg.recipe.fingerprint(), cfg.seed, d.shuffle_buffer,
                                     changes=plan_changes(caches.cache_dir, manifest))
        self.metrics = ServerMetrics()
        fc = caches.frame_cache
        self.frame_cache_scan = UsageScan(fc.disk, FRAME_CACHE_SCAN_S) if fc is not None else None
        self.workers = WorkerSide(cfg, source, self.scheduler, self.metrics)
        self.skipped = dict(skipped or {})
        self.bad = BadPeers()
        self.codecs: Dict[str, float] = {}  # codec -> when a fetch last asked for it
        self._stop = threading.Event()
        self.bound_endpoint: Optional[str] = None
        self.instance = uuid.uuid4().hex  # this process's name in its plan info: one host under two names is read once

    def stop(self) -> None:
        """Ask the loop to stop (thread- and signal-safe)."""
        self._stop.set()

    def stream_info(self) -> dict:
        """The recipe's shapes and outputs, as a client needs them to read rows; the shard served
        (``"I/N"``, None for the whole corpus), the listing's and the recipe's fingerprints, which a
        reader of several shards checks (``v2v_client.endpoints.check_servers``); ``feed``, what a
        trainer needs to say what would feed it (``trainer.feed_report``): the workers, the frame
        cache's GiB, the samples made so far (and of each of the latest epochs: its digits -> count)
        and the workers' busy seconds per stage."""
        c = self.cfg
        return {"sequence_length": c.sequence_length, "num_bins": c.num_bins, "crop_size": c.crop_size,
                "frames_per_bin": c.frames_per_bin, "outputs": list(c.outputs), "flow_preset": c.flow_preset,
                "flow_dtype": c.flow_dtype, "crops_per_window": c.crops_per_window, "videos": len(self.manifest.slots),
                "batch_size": c.delivery.batch_size, "shard": c.shard, "corpus": self.corpus,
                "recipe": self.identity.recipe, "codecs": [k for k in COMPRESSIONS if available(k)],
                "feed": {"workers": c.workers, "frame_cache_gb": c.frame_cache_gb,
                         "samples_made": self.metrics.totals()["samples_made"],
                         "samples_made_by_epoch": {str(e): n for e, n in self.scheduler.epoch_made.items()},
                         "busy_s": {k: round(v, 3) for k, v in self.metrics.busy_seconds().items()}}}

    def run(self, ready_event: Optional[threading.Event] = None) -> int:
        """Run until :meth:`stop`; returns a process exit code."""
        self.sockets = ServerSockets()
        pool = None
        try:
            if self.cfg.metrics_port is not None:
                self.metrics.serve(self.cfg.metrics_host, self.cfg.metrics_port)
            self.bound_endpoint = self.sockets.bind(self.cfg)
            corpus = {"source": self.source.spec(), "caches": self.caches.spec()}
            pool = WorkerPool(worker_config(self.cfg), corpus, self.sockets.backend_endpoint, self.cfg.workers)
            self.workers.attach(self.sockets.backend, pool)
            pool.start()
            for video, (cause, why) in sorted(self.skipped.items()):  # known to give no window: named as if read
                self.workers.log_failure(video, f"{why} (known from the corpus index: not opened)", cause=cause)
            counted = sum(1 for _, n in self.manifest.slots if n is not None)
            rings = any(w.ring is not None for w in pool.workers.values())
            log.info("serving by plan %s: %d video(s) (%d counted: %s samples per epoch), from %s on %s with %d "
                     "worker(s); samples travel %s", self.identity.manifest, len(self.manifest.slots), counted,
                     "unknown yet" if self.manifest.samples is None else self.manifest.samples, self.source.root,
                     self.bound_endpoint, self.cfg.workers,
                     "through shared-memory slot rings" if rings else "as socket frames")
            if ready_event is not None:
                ready_event.set()
            return self._loop()
        finally:
            if pool is not None:
                self.workers.stop()
            self.sockets.close()
            self.metrics.close()
            m = self.metrics.totals()
            log.info("stopped: %d fetches answered, %d samples made, %d worker restart(s), %d task timeout(s), "
                     "%d skipped file(s), %d epoch plan(s) built", m["batches_sent"], m["samples_made"],
                     m["workers_restarted"], m["tasks_timed_out"], m["files_skipped"], self.scheduler.plans_built)

    def _loop(self) -> int:
        front, back = self.sockets.frontend, self.sockets.backend
        poller = zmq.Poller()
        poller.register(front, zmq.POLLIN)
        poller.register(back, zmq.POLLIN)
        while not self._stop.is_set():
            events = dict(poller.poll(100))
            if front in events:
                for _ in range(64):
                    try:
                        ident, frame = front.recv_multipart(zmq.NOBLOCK, copy=False)[:2]
                    except zmq.Again:
                        break
                    except ValueError:  # a message of one frame
                        continue
                    self._client(ident.bytes, frame)
            if back in events:
                for _ in range(64):
                    try:
                        self.workers.on_message(back.recv_multipart(zmq.NOBLOCK, copy=False))
                    except zmq.Again:
                        break
            now = time.monotonic()
            if self._stop.is_set():  # workers that exit now were signalled with the server, not crashed
                break
            self.workers.watch(now)
            self.workers.dispatch(now, sorted(k for k, t in self.codecs.items() if now - t < CODEC_KEEP_S))
            answers = self.scheduler.answer(now)
            queued = self.scheduler.queued() if answers else 0  # once for the answers sent together
            for f, rows in answers:
                self._send_rows(f, rows, queued)
            self.metrics.tick(self._metrics_state)
        return 0

    def _client(self, ident: bytes, frame) -> None:
        now = time.monotonic()
        if self.bad.banned(ident, now):
            return
        try:
            msg = decode_plan_client(frame, MAX_CLIENT_MSG)
        except OldClient as e:  # told at its own version, which that client reads
            self._send(ident, old_client_answer(e))
            if self.bad.strike(ident, now)[0]:
                log.warning("client %s: %s", ident.hex()[:12], e)
            return
        except WireError as e:
            self.metrics.on_bad_message()
            self._send(ident, Refused(-1, f"bad message: {e}", "bad").to_wire())
            log_it, _ = self.bad.strike(ident, now)
            if log_it:
                log.warning("bad message from client %s: %s", ident.hex()[:12], e)
            return
        if isinstance(msg, PlanAsk):
            self._send(ident, PlanInfo(self.identity, self._samples(0), self.stream_info(), self.instance,
                                       self.scheduler.queued(),
                                       self.metrics.capacity(self.cfg.workers, time.monotonic()), True).to_wire())
            return
        if isinstance(msg, Withdraw):  # its connection's make: another host's copy came first
            self.scheduler.withdraw(lambda client: client[0] == ident, msg.request)
            return
        if isinstance(msg, ManifestAsk):
            self._send(ident, self._manifest_part(msg.offset).to_wire())
            return
        problem = self.identity.problem(msg.plan)
        missing = [o for o in msg.outputs if o not in self.cfg.outputs]
        if problem or missing or not available(msg.compression):
            code, why = (("plan", f"fetch under {problem}") if problem else
                         ("outputs", f"outputs {missing} are not served here (--outputs)") if missing else
                         ("compression", f"compression {msg.compression}: this server lacks its library (pip install "
                          f"'v2v[wire]')"))
            self._send(ident, Refused(msg.request, why, code).to_wire())
            return
        rows = msg.stop - msg.start if not isinstance(msg, Make) else len(msg.ordinals or ())
        too_big = self._too_big(rows, msg.outputs)
        if too_big:
            self._send(ident, Refused(msg.request, too_big, "too_big").to_wire())
            return
        if msg.compression != "none":
            self.codecs[msg.compression] = now
        if isinstance(msg, Make):
            new, answers = take_make(self.scheduler, (ident, msg.outputs, msg.compression), msg, now)
            for client, answer in answers:
                self._send(client[0], answer.to_wire())
            self.metrics.on_make(new)
            return
        self.scheduler.fetch((ident, msg.outputs, msg.compression), msg.request, msg.epoch, msg.start, msg.stop, now,
                             msg.outputs)

    def _too_big(self, rows: int, outputs: Sequence[str]) -> Optional[str]:
        """Why a fetch of ``rows`` rows of ``outputs`` is refused: an array of the batch the reader
        makes of it (padding rows included, as zeros) would pass ``MAX_BATCH_BYTES``, the most a
        reader takes; None when it would not."""
        for o in outputs:
            shape, dtype = _wire_row(o, self.cfg)
            row = int(np.prod(shape)) * np.dtype(dtype).itemsize
            if rows * row > MAX_BATCH_BYTES:
                return (f"fetch of {rows} rows: its {o} would be {rows * row} bytes, over the batch limit of "
                        f"{MAX_BATCH_BYTES} (MAX_BATCH_BYTES); fetch at most {MAX_BATCH_BYTES // row} rows of it")
        return None

    def _manifest_part(self, offset: int) -> ManifestPart:
        """The manifest's videos from ``offset`` on (``MANIFEST_PART`` at most), each with its tag
        and the slots this server knows now (the corpus index's, or learned from its decodes)."""
        part = self.manifest.slots[offset:offset + MANIFEST_PART]
        tags = list(self.manifest.tags[offset:offset + MANIFEST_PART]) if self.manifest.tags else [None] * len(part)
        return ManifestPart(offset, len(self.manifest.slots), self.manifest.crops_per_window, [v for v, _ in part],
                            tags, [self.scheduler.slots.windows.get(v) for v, _ in part], bool(self.manifest.tags))

    def _samples(self, epoch: int) -> Optional[int]:
        """The epoch's samples (every epoch lists the same), or None while the plan unfolds."""
        plan = self.scheduler.plans.get(epoch)
        if plan is not None and plan.complete:
            return len(plan)
        return self.scheduler.slots.epoch_samples

    def _send(self, ident: bytes, header: dict, frames: Sequence = ()) -> None:
        try:
            self.sockets.frontend.send_multipart([ident, pack(header), *frames], copy=False)
        except zmq.ZMQError:  # the client is gone (ROUTER_MANDATORY): it asks again if it comes back
            for client in {f.client for f in self.scheduler.pending + self.scheduler.orders.waiting if f.client[0] == ident}:
                self.scheduler.forget(client)

    def _send_rows(self, f, rows: List[Row], queued: int) -> None:
        """Answer fetch or make ``f`` (``plan_schedule.Pending`` or ``Order``) with ``rows``;
        ``queued``: the samples the makes waiting ask (a make's answer says it)."""
        ident, outputs, codec = f.client
        real = [r for r in rows if r.sample is not None]
        specs, frames = self._encoded(real, outputs, codec)
        ids = [r.key.sample_id(self.manifest.crops_per_window) if r.key is not None else None for r in rows]
        params = [r.sample.meta if r.sample is not None else {"padding": r.reason or "past the epoch's end"}
                  for r in rows]
        made = isinstance(f, Order)
        head = Rows(f.request, f.epoch, 0 if made else f.start, ids, [r.padding for r in rows], params, specs,
                    self._samples(f.epoch), self.scheduler.slots.windows.get(f.video) if made else None,
                    self.metrics.capacity(self.cfg.workers, time.monotonic()) if made else None,
                    queued if made else None).to_wire()
        self._send(ident, head, frames)
        self.metrics.on_batch_sent(len(real), sum(frame_size(fr) for fr in frames))

    def _encoded(self, real: List[Row], outputs: Tuple[str, ...], codec: str) -> Tuple[List[dict], List]:
        """The array specs and frames of the rows ``real`` (those holding a sample: a padding row
        costs no payload, ``Rows``): plain, or (``codec``) each array as one compressed frame per
        row, the workers' frames forwarded as they are (``batches.encode_batch``); an array some
        sample has no frame of (made before its codec was asked for) goes plain. No row: each
        output's wire shape with 0 rows, so a reader knows the shapes and dtypes of its zeros."""
        if not real:
            return encode_arrays({o: _wire_zeros(o, 0, self.cfg) for o in outputs})
        if codec == "none":
            return encode_arrays(self._arrays(real, outputs))
        shapes = {k: a.shape for k, a in real[0].sample.arrays.items()}
        return encode_batch(shapes, outputs, [r.sample.packed for r in real], codec,
                            lambda: self._arrays(real, outputs))

    def _arrays(self, real: List[Row], outputs: Tuple[str, ...]) -> Dict[str, np.ndarray]:
        """The arrays of ``outputs`` of the rows ``real`` (each holding a sample), stacked (one copy)."""
        return {name: narrowest(name, stack_arrays([r.sample.arrays[name] for r in real]))
                for name in real[0].sample.arrays if output_of(name) in outputs}

    def _metrics_state(self) -> dict:
        alive = [w for w in self.workers.pool.workers.values() if w.proc.is_alive()] if self.workers.pool else []
        return {"pending_fetches": len(self.scheduler.pending), "workers": len(alive),
                "workers_busy": sum(1 for w in alive if not w.idle), "epoch_videos": len(self.manifest.slots),
                "epoch_samples": self._samples(0), "shuffle_samples": len(self.scheduler.store),
                "shuffle_capacity": self.scheduler.keep_samples + self.scheduler.lookahead,
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


def take_make(scheduler: PlanScheduler, client: Hashable, msg: Make, now: float
              ) -> Tuple[bool, List[Tuple[Hashable, object]]]:
    """A reader's ``Make`` (checked against the plan and the server's outputs already) taken by
    ``scheduler`` for ``client``: placed (``PlanScheduler.place``: made here, or ``Moved`` to where
    a reader placed it first, so it is made once; a move off this host takes every reader's make
    of it waiting here along) and else queued (``PlanScheduler.make``; refused ``"make"`` where it
    names what the manifest does not hold).

    Returns:
        ``(samples newly asked here, [(client, answer)])``: the samples the make queued here that
        no make of the client waiting here named (``Orders.add``; 0 where it was placed
        elsewhere or refused), and the answers to send now, ``Moved`` or ``Refused``, each to
        the client (its first item the connection) whose make it answers."""
    to, moved = scheduler.place(msg.epoch, msg.video, msg.route, now, msg.move)
    answers: List[Tuple[Hashable, object]] = [(o.client, Moved(o.request, to)) for o in moved]
    if to is not None:  # another reader placed it there first: made once
        return 0, answers + [(client, Moved(msg.request, to))]
    try:
        new = scheduler.make(client, msg.request, msg.epoch, msg.video, msg.ordinals, now, msg.outputs, msg.position)
    except ValueError as e:
        return 0, answers + [(client, Refused(msg.request, str(e), "make"))]
    return new, answers


def _wire_row(output: str, c: ServeConfig) -> Tuple[tuple, str]:
    """(shape, dtype) of one row of ``output`` as the wire carries a sample's array (a Ray row's has
    the channel axis the client inserts)."""
    return wire_row(output, c.sequence_length, c.num_bins, c.crop_size, c.flow_dtype)


def _wire_zeros(output: str, rows: int, c: ServeConfig) -> np.ndarray:
    """``rows`` rows of zeros of ``output`` in its wire shape and dtype (:func:`_wire_row`): a
    reply of padding rows only carries them with 0 rows, so the reader knows the shapes and
    dtypes of the zeros it makes."""
    shape, dtype = _wire_row(output, c)
    return np.zeros((rows, *shape), dtype)


def install_signal_handlers(server: PlanServer) -> List[int]:
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

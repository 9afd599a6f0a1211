"""Worker process: decodes videos and runs V2V for the tasks the server hands it.

A worker connects a DEALER socket to the server's worker endpoint, says ``ready``, and for
each ``task`` (one video of one epoch) streams one ``sample`` message per sample (named by its
``ids.SampleKey``, ``"key": [video, window, crop]``), then a ``done`` message with the complete
windows the file gave, the windows that failed and the reason the pass stopped early, if any. Sends block
at a small high-water mark, so a worker never runs ahead of what the server is willing to
hold. A worker whose parent has gone exits by itself.

With a shared-memory slot ring (``shm.SlotRing``, given by the pool at spawn) a sample's
arrays go into a free slot and the ``sample`` header names the slot (no array frames); the
server answers with a ``Slot`` message once it has copied the slot out (the messages:
``v2v_wire.worker_messages``). With every slot
taken the worker blocks until one comes back. Without a ring (no ``/dev/shm``) or for a sample
too large for a slot, the arrays travel as frames.
"""
from __future__ import annotations

import logging
import os
import signal
import sys
import time
from dataclasses import dataclass
from typing import Optional, Union

import numpy as np
import zmq

from v2v_wire import codecs
from v2v_server.ops.config import SampleRecipe, ServeConfig
from v2v_server.sources.source import VideoSource
from v2v_server.frames.host_caches import HostCaches
from v2v_server.sources.source_spec import source_from_spec
from v2v_server.service.shm import SlotRing
from v2v_server.ops.logs import setup_logging
from v2v_wire.outputs import wire_dtype
from v2v_wire.protocol import ProtocolError, encode_arrays, pack, unpack
from v2v_wire.worker_messages import Done, Failure, Ready, Sample, Slot, Stop, Task, server_message
from v2v_server.flow.estimate import FlowEstimator, to_float16
from v2v_wire.ids import SampleKey
from v2v_server.samples.make import SamplePass, video_samples
from v2v_server.frames.video_read import as_verdict

log = logging.getLogger("v2v.worker")

#: Messages a worker may have queued towards the server before its sends block.
WORKER_HWM = 2


def _parent_alive(parent_pid: int) -> bool:
    return os.getppid() == parent_pid


class _Inbox:
    """The worker's side of its socket's incoming messages (``worker_messages.server_message``):
    ``Slot`` messages give slots back to the ring at once; ``Task`` and ``Stop`` wait for the
    main loop, in order; a malformed message is logged and dropped."""

    def __init__(self, sock: zmq.Socket, ring: Optional[SlotRing]):
        self.sock, self.ring, self.waiting = sock, ring, []

    def _take(self, frames) -> None:
        try:
            msg = server_message(unpack(frames[0]))
        except ProtocolError as e:
            log.error("bad message from the server: %s", e)
            return
        if isinstance(msg, Slot):
            i = msg.slot
            if self.ring is not None and i < self.ring.slots and i not in self.ring.free:
                self.ring.free.append(i)
        else:
            self.waiting.append(msg)

    def next(self, parent_pid: int) -> Optional[Union[Task, Stop]]:
        """The next non-slot message, or None after a second without one."""
        while not self.waiting:
            if not self.sock.poll(1000):
                if not _parent_alive(parent_pid):
                    raise SystemExit(0)
                return None
            self._take(self.sock.recv_multipart())
        return self.waiting.pop(0)

    def slot(self, parent_pid: int) -> int:
        """A free slot of the ring, waiting (in bounded steps) for the server to give one back;
        exits if the server process has gone or asks this worker to stop."""
        while not self.ring.free:
            if self.sock.poll(1000):
                self._take(self.sock.recv_multipart())
                if any(isinstance(m, Stop) for m in self.waiting):
                    raise SystemExit(0)
            elif not _parent_alive(parent_pid):
                raise SystemExit(0)
        return self.ring.free.pop(0)


def _send(sock: zmq.Socket, frames, parent_pid: int) -> None:
    """Send, waiting in bounded steps for room; exit if the server process has gone."""
    while not sock.poll(1000, zmq.POLLOUT):
        if not _parent_alive(parent_pid):
            raise SystemExit(0)
    sock.send_multipart(frames, copy=False)


def wire_arrays(recipe: SampleRecipe, arrays: dict) -> dict:
    """A sample's arrays in their wire dtypes (``outputs.wire_dtype``: voxels the narrowest
    int that holds every count, frames and polarity counts uint8, dense flow ``recipe.flow_dtype``,
    a tracked option's ``flow_grid`` float32). Counts that arrive narrowed by their producer
    (``simulate_voxels(narrow=True)``) are not scanned again; float16 is made by the vectorised
    ``flow.estimate.to_float16`` (bit-identical to numpy's cast)."""
    out = {}
    for name, a in arrays.items():
        dt = wire_dtype(name, a, recipe.flow_dtype)
        out[name] = to_float16(a) if dt == np.float16 else a.astype(dt, copy=False)
    return out


def pack_arrays(arrays: dict, names) -> tuple:
    """A sample's arrays compressed with each codec of ``names`` (``codecs.COMPRESSIONS``, those
    connected clients asked for; "none" and codecs this machine lacks are skipped): the
    header's ``packed`` list (``{"codec", "name", "nbytes"}`` per frame) and the frames, sent
    after the sample's array frames. The server forwards them to the clients of that codec."""
    specs, frames = [], []
    for name in names:
        if name == "none" or name not in codecs.COMPRESSIONS or not codecs.available(name):
            continue
        for k, b in codecs.pack(name, arrays).items():
            specs.append({"codec": name, "name": k, "nbytes": len(b)})
            frames.append(b)
    return specs, frames


class _StageClock:
    """Seconds a worker spends per stage (decode, simulate, flow, serialize, send) since its
    previous message. Simulate and flow are what the sample pass reports it spent
    (``samples.make.SamplePass.seconds``, read after each sample); decode is the rest of the
    time spent making a sample (decoding, cropping, planning); send includes waiting for the
    server to take the message (back-pressure)."""

    def __init__(self, run: SamplePass):
        self.run = run
        self.t = time.perf_counter()
        self.acc = {"decode": 0.0, "simulate": 0.0, "flow": 0.0, "serialize": 0.0, "send": 0.0}
        self.seen = run.seconds  # the pass's running total at the previous reading

    def _lap(self) -> float:
        now = time.perf_counter()
        dt, self.t = now - self.t, now
        return dt

    def made(self) -> None:
        dt = self._lap()
        total = self.run.seconds
        d, self.seen = total - self.seen, total
        self.acc["simulate"] += d.simulate
        self.acc["flow"] += d.flow
        self.acc["decode"] += max(0.0, dt - (d.simulate + d.flow))

    def serialized(self) -> None:
        self.acc["serialize"] += self._lap()

    def sent(self) -> None:
        self.acc["send"] += self._lap()

    def report(self) -> dict:
        out = {k: round(v, 6) for k, v in self.acc.items()}
        self.acc = dict.fromkeys(self.acc, 0.0)
        return out


def run_task(recipe: SampleRecipe, source: VideoSource, caches: HostCaches, task: Task, sock: zmq.Socket,
             parent_pid: int, flows: dict, inbox: Optional[_Inbox] = None, worker: str = "?") -> None:
    """Make every sample of one task of ``source`` (its frames through the host's ``caches``) and
    send it (through ``inbox``'s slot ring when it has one), then send ``done``. A failure, of the
    pass or of this worker's work on a sample, is the file's verdict (``video_read.as_verdict``),
    not the worker's death: it goes in ``done`` as a ``worker_messages.Failure`` saying it was
    raised in ``worker`` (its identity) on what."""
    failure = last = None
    preset = recipe.flow_preset
    flow = flows.setdefault(preset, FlowEstimator(preset)) if "flow" in task.outputs else None
    skip = [SampleKey(task.video, w, c) for w, c in task.skip]
    # a tracked option's flow goes as its grid (~20 KB, not 2.6 MB); clients expand it
    with video_samples(recipe, source, task.video, task.epoch, task.outputs, skip, flow, flow_grid=True,
                       caches=caches, handler=as_verdict) as run:
        clock = _StageClock(run)  # seconds per stage, reported with each message
        for key, arrays, meta in run:
            clock.made()
            arrays = wire_arrays(recipe, arrays)
            specs, frames = encode_arrays(arrays)
            packed_specs, packed = pack_arrays(arrays, task.codecs)
            clock.serialized()
            slot = None
            if inbox is not None and inbox.ring is not None:  # waiting for a slot counts as send (back-pressure)
                slot = inbox.slot(parent_pid)
                if inbox.ring.put(slot, dict(zip((s["name"] for s in specs), frames))) is None:
                    inbox.ring.free.insert(0, slot)  # too large for a slot: frames instead
                    slot = None
                else:
                    frames = []
            header = Sample(task.task, key, meta, tuple(specs), tuple(packed_specs), slot, clock.report())
            _send(sock, [pack(header.to_wire())] + frames + packed, parent_pid)
            clock.sent()
            last = key
    if run.error is not None:
        after = "before its first sample" if last is None else f"after sample {last.sample_id(recipe.crops_per_window)}"
        failure = Failure.of(run.error, f"in worker {worker}, pid {os.getpid()}, while making {task.video} in epoch "
                                        f"{task.epoch}, {after}")
    found = run.record()
    clock.made()  # decoding after the last window
    cause, reason = found.cause(recipe.windows)  # the file's verdict, failed windows aside
    done = Done(task.task, found.windows,
                {str(k): str(v) for k, v in found.failed.items()},  # window -> reason, one by one
                reason, failure, found.frames, len(found.cuts), found.dropped,  # shot cuts found, windows they removed
                clock.report(), {**source.take_stats(), **caches.take_stats()},  # store reads, frame-cache counters
                cause)
    _send(sock, [pack(done.to_wire())], parent_pid)


@dataclass(frozen=True)
class WorkerSetup:
    """What a worker process is given (it pickles to the spawned process): the sample recipe and
    the server's log format (``"text"`` or ``"json"``); nothing of transport, security or delivery."""

    recipe: SampleRecipe
    log_format: str = "text"


def worker_config(cfg: ServeConfig) -> WorkerSetup:
    """The :class:`WorkerSetup` of the server configured by ``cfg``."""
    return WorkerSetup(cfg.recipe, cfg.log_format)


def exit_on_sigterm() -> None:
    """A worker's signals: SIGINT ignored (the server decides when workers stop; Ctrl-C reaches
    the whole process group), SIGTERM ends the process at once with status 0. ``os._exit``
    rather than ``SystemExit``: an exception raised wherever the signal lands (inside numba's
    compiler or a decoder callback) would be caught and printed there as a traceback on a
    clean shutdown. A worker holds nothing to flush: its batch slots belong to the server."""
    def _exit(*_):
        try:
            sys.stderr.flush()
        finally:
            os._exit(0)

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _exit)


def worker_main(setup: WorkerSetup, corpus: dict, endpoint: str, identity: bytes, parent_pid: int,
                ring: Optional[dict] = None) -> None:
    """Entry point of a worker process (started with the ``spawn`` method).

    Args:
        setup: the recipe and log format (``worker_config(cfg)``).
        corpus: ``{"source": VideoSource.spec(), "caches": HostCaches.spec()}``: the corpus
            (``sources.source``) and the host's caches beside it (``frames.host_caches``), built
            here once.
        ring: ``SlotRing.spec`` of this worker's shared-memory slots (the file is unlinked as
            soon as it is mapped), or None to send arrays as frames.
    """
    exit_on_sigterm()
    import cv2

    cv2.setNumThreads(1)
    recipe = setup.recipe
    if setup.log_format == "json":  # one format for the whole server's stderr
        setup_logging("INFO", "json", "v2v-worker")
    else:
        logging.basicConfig(level=logging.INFO, format="v2v-worker %(process)d: %(message)s")
    ctx = zmq.Context()
    sock = ctx.socket(zmq.DEALER)
    sock.setsockopt(zmq.IDENTITY, identity)
    sock.setsockopt(zmq.SNDHWM, WORKER_HWM)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(endpoint)
    slots = None
    if ring is not None:
        try:
            slots = SlotRing.attach(ring)  # unlinks the file: nothing leaks if either side dies later
        except (OSError, ValueError) as e:
            log.warning("cannot map slot ring %s (%s): sending arrays over the socket", ring.get("path"), e)
    inbox = _Inbox(sock, slots)
    source = source_from_spec(corpus["source"])  # the corpus folder, or the object store (one client per worker)
    caches = HostCaches.from_spec(corpus["caches"])
    flows: dict = {}
    try:
        _send(sock, [pack(Ready(slots is not None).to_wire())], parent_pid)
        while True:
            msg = inbox.next(parent_pid)
            if isinstance(msg, Stop):
                return
            if isinstance(msg, Task):
                run_task(recipe, source, caches, msg, sock, parent_pid, flows, inbox, identity.decode())
    finally:
        sock.close(0)
        ctx.term()
        if slots is not None:
            slots.close()

"""The server's data path, batch assembly: how sample arrays travel from a worker to a client's socket.

This module is the one seam between the data path (owned by the speed work: copies, batch
assembly, wire layout) and the control logic in ``server.py`` (credits, leases, acks, epochs),
which treats a :class:`BatchPayload` as opaque: it asks only for its sample ids, their
parameters, its size, a subset of its samples, and its wire frames.

Two ways in, one copy each:

* **Shared memory** (the default where ``/dev/shm`` exists): each worker writes a sample's
  arrays into a free slot of its own :class:`SlotRing` (a file in ``/dev/shm`` that the pool
  creates and the worker unlinks as soon as it has mapped it) and sends only the header with
  the slot number. The relay copies the slot into the next row of an open batch buffer
  (:class:`BatchAssembler`; the one copy) and gives the slot back at once, so a ring of a few
  slots suffices however long samples wait for their batch. When a batch is made of
  consecutive rows of one buffer (the normal case) its arrays *are* that buffer: nothing is
  stacked, and ZeroMQ sends it zero-copy. The sample bytes never cross the worker's socket,
  which removes one kernel copy of every byte from the relay.
* **Socket frames** (fallback; also used for a sample too large for a slot): a worker's
  ``sample`` message is received zero-copy (``recv_multipart(copy=False)``); a
  :class:`SamplePayload` holds read-only numpy views of the received ZeroMQ frames, and a
  batch is stacked lazily, the first time it is sent, into one ``np.empty((B, ...))`` (the
  one copy), kept for re-sends, and handed to ZeroMQ zero-copy.

**Compressed frames** (``codecs``): a worker asked for codecs in its task sends each array
compressed as extra frames after the sample's array frames (``packed_frames``); the sample
keeps them as received, and :meth:`BatchPayload.wire` with a codec sends them, one frame per
sample, by reference: the relay never compresses, decompresses or copies them.

Batches whose samples did not land in consecutive rows of one buffer (samples of two epochs
interleaved at an epoch boundary, voxels narrowed differently, a resume ``subset``) fall back
to the lazy stacking copy from the samples' views.

**Hand-off to a trainer on the same host.** A server bound to ``ipc://`` keeps its batch
buffers in files of a private directory (:class:`BatchDir`, ``/dev/shm/v2v-batches-<pid>-*``,
removed at shutdown; a dead server's directory is removed by the next one). For a client that
asked for it in its hello, a batch that *is* consecutive rows of one such buffer goes as a
header only (:meth:`BatchPayload.shm_ref`: file name, generation, byte offsets); the client
maps the file and copies the arrays out (``v2v_client.dataset``) before it acknowledges, so
neither side pays the kernel's socket copies. Each file starts with a 64-byte header holding
the buffer's generation (uint64, little-endian), bumped whenever an idle buffer is refilled:
a client that finds another generation after its copy knows the batch was already gone.
"""
from __future__ import annotations

import logging
import math
import mmap
import os
import struct
import weakref
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import zmq

from v2v_server.service.shm import SLOT_ALIGN, BatchDir, SlotRing
from v2v_wire.batches import encode_batch, frame_size, stack_arrays
from v2v_wire.outputs import narrowest
from v2v_wire.protocol import BATCH_FILE_HEADER, MAX_BATCH_BYTES, ProtocolError, decode_arrays, output_of
from v2v_wire.worker_messages import Sample

log = logging.getLogger("v2v.datapath")


@dataclass
class SamplePayload:
    """One sample as received from a worker.

    Attributes:
        sample_id: stable id (``ids.make_sample_id``).
        meta: per-sample parameters (msgpack-able dict).
        arrays: name -> read-only array viewing the received frame, or the batch-buffer row
            the sample was copied into (voxels int8/int16/int32 ``(L, B, H, W)``, frames
            uint8 ``(L + 1, H, W)``, flow float16/float32 ``(L, 2, H, W)``); the views keep
            the ZeroMQ frames (or the buffer) alive.

    A sample in a batch buffer holds a lease on it (:meth:`_BatchBuffer.lease`) until it is
    dropped: the buffer is not refilled while the sample exists.
    """

    sample_id: str
    meta: dict
    arrays: Dict[str, np.ndarray]
    #: the batch buffer and row the arrays were copied into (shared-memory path), else None / -1
    buffer: Optional["_BatchBuffer"] = field(default=None, repr=False)
    row: int = -1
    #: codec -> array name -> (dtype the worker sent it in, its compressed frame) (``codecs``),
    #: kept as received and forwarded by reference to the clients that asked for that codec
    packed: Dict[str, Dict[str, tuple]] = field(default_factory=dict, repr=False)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.arrays.values())


def sample_from_worker(msg: Sample, frames: Sequence, crops_per_window: int = 1) -> SamplePayload:
    """Build a :class:`SamplePayload` from a worker's ``sample`` message (its header ``msg``, then
    raw frames, ``zmq.Frame`` or bytes, then its compressed frames), without copying the arrays.
    ``crops_per_window``: the server's, for the sample's id (``ids.SampleKey.sample_id``).

    Raises:
        ProtocolError: when the frames do not match the header's array specs.
    """
    n = len(msg.arrays)
    s = SamplePayload(msg.key.sample_id(crops_per_window), msg.meta, decode_arrays(list(msg.arrays), frames[:n]))
    s.packed = packed_frames(msg.packed, frames[n:], s.arrays)
    return s


#: Largest compressed frame accepted from a worker, bytes (a sample's largest array, uncompressed,
#: is at most ``slot_bytes``; a compressed one can exceed it only by the codec's small overhead).
MAX_PACKED_BYTES = MAX_BATCH_BYTES


def packed_frames(specs: Sequence[dict], frames: Sequence,
                  arrays: Dict[str, np.ndarray]) -> Dict[str, Dict[str, tuple]]:
    """The compressed frames of a worker's ``sample`` message (``specs``, its ``packed`` list:
    codec, array name and size of each frame after the array frames), by codec and array name, each with
    the dtype of the array it compresses; the frames themselves are kept as they are (never
    decompressed here).

    Raises:
        ProtocolError: for a list that does not match the frames, or names no array of the sample.
    """
    if len(specs) != len(frames):
        raise ProtocolError(f"sample header lists {len(specs)} compressed frames, message has {len(frames)}")
    out: Dict[str, Dict[str, object]] = {}
    for spec, fr in zip(specs, frames):
        if not isinstance(spec, dict) or spec.get("name") not in arrays or not isinstance(spec.get("codec"), str):
            raise ProtocolError(f"bad compressed frame spec {spec!r:.200}")
        size = frame_size(fr)
        if size != spec.get("nbytes") or size > MAX_PACKED_BYTES:
            raise ProtocolError(f"compressed frame of {spec['name']!r}: {size} bytes, spec says {spec.get('nbytes')!r}")
        out.setdefault(spec["codec"], {})[spec["name"]] = (arrays[spec["name"]].dtype, fr)
    return out


class _BatchBuffer:
    """One batch's arrays, ``(batch_size, ...)`` each, filled row by row as samples arrive;
    in a :class:`BatchDir` file (``file``, byte ``offsets`` of the arrays, ``gen``) or in
    private memory (``file`` None).

    Who uses the rows is counted, never inferred: each sample or batch viewing them holds a
    lease (:meth:`lease`, returned when that holder is dropped), and each zero-copy send of
    them holds its ZeroMQ tracker (:meth:`sent`) until the kernel has the bytes. The buffer
    is refilled only when :meth:`idle`."""

    __slots__ = ("arrays", "next", "sealed", "file", "offsets", "gen", "_mm", "leases", "sends")

    def __init__(self, arrays: Dict[str, np.ndarray], file: Optional[str] = None,
                 offsets: Optional[Dict[str, int]] = None, mm: Optional[mmap.mmap] = None):
        self.arrays, self.next, self.sealed = arrays, 0, False
        self.file, self.offsets, self._mm, self.gen = file, offsets or {}, mm, 0
        self.leases = 0  # samples and batches viewing the rows, not yet dropped
        self.sends: list = []  # zmq.MessageTracker of zero-copy sends of the rows, maybe in flight
        self.bump()

    def bump(self) -> None:
        """A new generation: the buffer is about to be refilled (no lease or send is out)."""
        self.gen += 1
        if self._mm is not None:
            struct.pack_into("<Q", self._mm, 0, self.gen)

    def lease(self, holder: object) -> None:
        """Count ``holder`` (a :class:`SamplePayload` or :class:`BatchPayload` viewing rows)
        as a user of the buffer until it is dropped (its last reference gone)."""
        self.leases += 1
        weakref.finalize(holder, self._release)

    def _release(self) -> None:
        self.leases -= 1

    def sent(self, tracker) -> None:
        """A zero-copy send of rows is in flight until ``tracker`` (``zmq.MessageTracker``) is done."""
        self.sends.append(tracker)

    def idle(self) -> bool:
        """True when no lease is out and every zero-copy send of the rows has completed."""
        if self.sends:
            self.sends = [t for t in self.sends if not t.done]
        return self.leases == 0 and not self.sends


class BatchAssembler:
    """Copies arriving samples straight into batch buffers (the one copy of the shared-memory
    path): consecutive samples with the same array names, dtypes and shapes fill consecutive
    rows of one ``(batch_size, ...)`` buffer per array, so :func:`make_batch` finds the batch
    already assembled.

    Buffers are reused once idle (no sample or batch holds a lease on them and no zero-copy
    send of them is in flight: :meth:`BatchPayload.send`), so the relay does not map, fault
    in and zero fresh pages for every batch; at most ``spare`` idle buffers per layout are
    kept, the rest go back to the allocator.

    Args:
        batch_size: rows per buffer (``ServeConfig.batch_size``).
        spare: idle buffers kept per layout for reuse.
        files: where buffers live as files a same-host client maps (:class:`BatchDir`), or
            None for private memory.
        on_error: told ``(path, OSError)`` when a batch file cannot be made or removed (the
            server counts it and logs it once); default: a warning in the log.

    Raises:
        ValueError: for ``batch_size`` < 1.
    """

    def __init__(self, batch_size: int, spare: int = 2, files: Optional[BatchDir] = None,
                 on_error: Optional[Callable[[str, OSError], None]] = None):
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.batch_size, self.spare, self.files = batch_size, spare, files
        self.on_error = on_error or (lambda path, e: log.warning("batch buffer %s: %s: batches go as socket "
                                                                 "frames", path, e))
        self._open: Dict[tuple, _BatchBuffer] = {}  # (layout, lane) -> buffer being filled
        self._used: Dict[tuple, List[_BatchBuffer]] = {}  # handed out, maybe still viewed
        self.reused = 0

    def _new(self, arrays: Dict[str, np.ndarray]) -> _BatchBuffer:
        """A buffer for ``batch_size`` rows like ``arrays``: in a file of ``files`` when given
        (anonymous memory when the file cannot be made), else anonymous memory."""
        shapes = {k: (self.batch_size,) + a.shape for k, a in arrays.items()}
        if self.files is not None:
            offsets, end = {}, BATCH_FILE_HEADER
            for k, a in arrays.items():
                offsets[k] = end
                end = -(-(end + math.prod(shapes[k]) * a.dtype.itemsize) // SLOT_ALIGN) * SLOT_ALIGN
            try:
                name, mm = self.files.new_file(end)
            except OSError as e:
                self.on_error(self.files.path, e)
            else:
                views = {k: np.ndarray(shapes[k], a.dtype, buffer=mm, offset=offsets[k]) for k, a in arrays.items()}
                return _BatchBuffer(views, name, offsets, mm)
        return _BatchBuffer({k: np.empty(shapes[k], a.dtype) for k, a in arrays.items()})

    def _forget(self, buf: _BatchBuffer) -> None:
        if buf.file is not None and self.files is not None:
            try:
                self.files.unlink(buf.file)
            except OSError as e:  # the directory gone or unwritable: its files go with it at shutdown
                self.on_error(os.path.join(self.files.path, buf.file), e)

    def close(self) -> None:
        """Forget every buffer and remove the batch directory (the server's shutdown)."""
        self._open.clear()
        self._used.clear()
        if self.files is not None:
            self.files.remove()

    def _fresh(self, sig: tuple, arrays: Dict[str, np.ndarray]) -> _BatchBuffer:
        """An idle buffer of layout ``sig`` to refill, else a new one; forgets idle buffers
        beyond ``spare`` (and every idle buffer of another layout: outputs or dtypes changed)."""
        for other in list(self._used):
            if other != sig:
                busy = [b for b in self._used[other] if not b.idle()]
                for b in self._used[other]:
                    if b not in busy:
                        self._forget(b)
                if busy:
                    self._used[other] = busy
                else:
                    del self._used[other]
        # open buffers left idle (their open batch was flushed or dropped) are no lane's any more
        for key in [k for k, b in self._open.items() if b.idle()]:
            del self._open[key]
        used = self._used.setdefault(sig, [])
        idle = [b for b in used if b.idle()]
        busy = [b for b in used if not b.idle()]
        if idle:
            buf = idle.pop()
            buf.next, buf.sealed = 0, False
            buf.bump()
            self.reused += 1
        else:
            buf = self._new(arrays)
        for b in idle[self.spare:]:
            self._forget(b)
        self._used[sig] = busy + idle[: self.spare] + [buf]
        return buf

    def place(self, sample_id: str, meta: dict, arrays: Dict[str, np.ndarray], lane: int = 0) -> SamplePayload:
        """Copy ``arrays`` (e.g. views of a slot) into the next free row of the open buffer of
        their layout and ``lane`` (the open batch the sample joins, ``delivery.batcher.Batcher.lane``:
        one buffer per open batch, so a full batch is consecutive rows of one buffer); returns
        the sample viewing that row (read-only)."""
        sig = tuple((k, a.dtype.str, a.shape) for k, a in arrays.items())
        buf = self._open.get((sig, lane))
        if buf is None or buf.sealed or buf.next >= self.batch_size:
            self._open.pop((sig, lane), None)
            buf = self._open[(sig, lane)] = self._fresh(sig, arrays)
        row = buf.next
        buf.next += 1
        if buf.next >= self.batch_size:
            del self._open[(sig, lane)]  # full: the lane's next batch gets another buffer
        views = {}
        for k, a in arrays.items():
            dst = buf.arrays[k][row]
            np.copyto(dst, a, casting="no")
            v = dst.view()
            v.flags.writeable = False
            views[k] = v
        s = SamplePayload(sample_id, meta, views, buf, row)
        buf.lease(s)
        return s


def sample_from_slot(msg: Sample, ring: SlotRing, assembler: BatchAssembler, frames: Sequence = (),
                     lane: int = 0, crops_per_window: int = 1) -> SamplePayload:
    """Build a :class:`SamplePayload` from a worker's ``sample`` header ``msg`` naming a slot of
    ``ring``: the slot's arrays are copied into ``assembler``'s batch buffer of ``lane`` (the
    open batch the sample joins; after this returns the slot may be given back to the worker);
    ``frames``, the message's frames after the header, are its compressed frames
    (``packed_frames``); ``crops_per_window``: the server's, for the sample's id.

    Raises:
        ProtocolError: for a slot out of range, array specs that do not fit a slot, or
            compressed frames that do not match the header.
    """
    views = ring.arrays(msg.slot, list(msg.arrays))
    packed = packed_frames(msg.packed, frames, views)
    try:
        s = assembler.place(msg.key.sample_id(crops_per_window), msg.meta, views, lane)
    finally:
        del views
    s.packed = packed
    return s


@dataclass
class BatchPayload:
    """The arrays of one batch, samples stacked on a leading axis.

    Attributes:
        sample_ids: ids in batch order.
        meta: per-sample parameters in batch order.
        samples: the :class:`SamplePayload` of each sample (views of the workers' frames)
            until the batch is stacked, then None (the frames are released: a batch is held
            once, never twice).

    A batch that is rows of a batch buffer holds a lease on it until it is dropped (acked,
    shrunk or its epoch dropped), and each of its zero-copy sends until ZeroMQ is done with
    it (:meth:`send`): the rows stay untouched while either is out.
    """

    sample_ids: List[str]
    meta: List[dict]
    samples: Optional[List[SamplePayload]]
    _stacked: Optional[Dict[str, np.ndarray]] = field(default=None, repr=False)
    #: (buffer, first row) when the arrays are consecutive rows of one batch buffer
    _rows: Optional[Tuple["_BatchBuffer", int]] = field(default=None, repr=False)
    #: each sample's compressed frames (``SamplePayload.packed``), in batch order
    packed: List[Dict[str, Dict[str, tuple]]] = field(default_factory=list, repr=False)

    @property
    def arrays(self) -> Dict[str, np.ndarray]:
        """name -> stacked (B, ...) array; voxels in the narrowest int type that holds every
        sample's counts (each sample arrives narrowed by its worker). Built on first use."""
        if self._stacked is None:
            self._stacked = {name: stack_arrays([s.arrays[name] for s in self.samples])
                             for name in self.samples[0].arrays}
            self.samples = None
        return self._stacked

    @property
    def nbytes(self) -> int:
        if self._stacked is not None:
            return sum(a.nbytes for a in self._stacked.values())
        return sum(s.nbytes for s in self.samples)

    def subset(self, keep: Sequence[int]) -> "BatchPayload":
        """A payload holding only the samples at positions ``keep`` (in that order)."""
        keep = list(keep)
        ids, meta = [self.sample_ids[i] for i in keep], [self.meta[i] for i in keep]
        packed = [self.packed[i] for i in keep] if self.packed else []
        if self._stacked is None:
            return BatchPayload(ids, meta, [self.samples[i] for i in keep], packed=packed)
        arrays = {k: v[keep] for k, v in self._stacked.items()}  # a copy; only on resume
        return BatchPayload(ids, meta, None, {k: narrowest(k, v) for k, v in arrays.items()}, packed=packed)

    def wire(self, outputs: Sequence[str], codec: str = "none") -> Tuple[List[dict], List]:
        """Array specs for the batch header and the frames to send (zero-copy), for the arrays
        that carry ``outputs`` (``protocol.output_of``): one frame per array, or with a
        ``codec`` (``codecs.COMPRESSIONS``) whose compressed frames every sample has for an
        array, those frames, one per sample, forwarded as the workers sent them (spec
        ``codecs.packed_specs``)."""
        if self._stacked is not None:
            shapes = {k: v.shape[1:] for k, v in self._stacked.items()}
        else:
            shapes = {k: a.shape for k, a in self.samples[0].arrays.items()}
        return encode_batch(shapes, outputs, self.packed, codec, lambda: self.arrays)

    def shm_ref(self, outputs: Sequence[str]) -> Optional[Tuple[List[dict], dict]]:
        """Where a same-host client finds this batch's arrays in ``outputs``: ``(specs, ref)``
        with ``ref = {"file", "gen", "offsets"}`` (file name inside the server's
        :class:`BatchDir`, the buffer's generation, byte offset of each array in the file, in
        the order of ``specs``), or None when the arrays are not consecutive rows of a
        file-backed buffer (send :meth:`wire` frames instead). The rows stay untouched while
        this payload exists (it holds a lease on them)."""
        if self._rows is None or self._rows[0].file is None:
            return None
        buf, r0 = self._rows
        specs, offsets = [], []
        for k, v in self.arrays.items():
            if output_of(k) in outputs:
                full = buf.arrays[k]
                specs.append({"name": k, "dtype": v.dtype.name, "shape": list(v.shape)})
                offsets.append(buf.offsets[k] + r0 * (full.nbytes // full.shape[0]))
        return specs, {"file": buf.file, "gen": buf.gen, "offsets": offsets}

    def send(self, socket, head: Sequence, frames: Sequence) -> None:
        """Send ``head`` (frames of the message before the arrays: identity, header) then
        ``frames`` (from :meth:`wire`, sent zero-copy) as one message on ``socket`` (a
        ``zmq.Socket``); when the arrays are rows of a batch buffer, the buffer is not
        refilled before ZeroMQ has released every array frame of this send (a worker's
        compressed frames, sent as received, view no buffer).

        Raises:
            zmq.ZMQError: as ``socket.send_multipart`` does (e.g. an unreachable peer on a
                ROUTER with ``ROUTER_MANDATORY``); nothing is then in flight.
        """
        if self._rows is None:
            socket.send_multipart(list(head) + list(frames), copy=False)
            return
        parts = [zmq.Frame(f, track=True) if isinstance(f, np.ndarray) else f for f in frames]
        socket.send_multipart(list(head) + parts, copy=False)
        trackers = [p.tracker for p, f in zip(parts, frames) if p is not f]
        if trackers:
            self._rows[0].sent(zmq.MessageTracker(*trackers))


def make_batch(samples: Sequence[SamplePayload]) -> BatchPayload:
    """A :class:`BatchPayload` of ``samples``: the rows of their batch buffer when they fill
    consecutive rows of one (nothing is copied), else stacked when first sent.

    Raises:
        ValueError: for no samples, or samples whose array names differ.
    """
    if not samples:
        raise ValueError("a batch needs at least one sample")
    names = set(samples[0].arrays)
    for s in samples[1:]:
        if set(s.arrays) != names:
            raise ValueError(f"sample {s.sample_id} has arrays {sorted(s.arrays)}, expected {sorted(names)}")
    ids, meta = [s.sample_id for s in samples], [s.meta for s in samples]
    buf, r0 = samples[0].buffer, samples[0].row
    packed = [s.packed for s in samples] if any(s.packed for s in samples) else []
    if buf is not None and all(s.buffer is buf and s.row == r0 + i for i, s in enumerate(samples)):
        buf.sealed = True  # later samples start a fresh buffer; these rows are the batch's
        batch = BatchPayload(ids, meta, None, {k: v[r0:r0 + len(samples)] for k, v in buf.arrays.items()},
                             (buf, r0), packed)
        buf.lease(batch)
        return batch
    return BatchPayload(ids, meta, list(samples), packed=packed)




__all__ = ["SamplePayload", "BatchPayload", "BatchAssembler", "sample_from_worker", "sample_from_slot", "make_batch",
           "packed_frames"]

"""The server's data path: how sample arrays travel from a worker to a client's socket.

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

Batches whose samples did not land in consecutive rows of one buffer (samples of two epochs
interleaved at an epoch boundary, voxels narrowed differently, a resume ``subset``) fall back
to the lazy stacking copy from the samples' views.
"""
from __future__ import annotations

import logging
import math
import mmap
import os
import sys
import tempfile
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from .protocol import WIRE_DTYPES, ProtocolError, decode_arrays, encode_arrays, narrow_int_dtype

log = logging.getLogger("v2v.datapath")

#: Where slot rings live (a tmpfs on Linux). The environment variable ``V2V_SHM_DIR`` overrides
#: it for the server's workers; set it empty to send arrays over the socket instead.
SHM_DIR = "/dev/shm"
#: Slots per worker ring. The relay copies a slot out and gives it back as soon as the sample
#: arrives, so a worker needs only enough to keep writing while one message is in flight.
RING_SLOTS = 3
#: Byte alignment of each array inside a slot.
SLOT_ALIGN = 64


@dataclass
class SamplePayload:
    """One sample as received from a worker.

    Attributes:
        sample_id: stable id (``sampler.make_sample_id``).
        meta: per-sample parameters (msgpack-able dict).
        arrays: name -> read-only array viewing the received frame, or the batch-buffer row
            the sample was copied into (voxels int8/int16/int32 ``(L, B, H, W)``, frames
            uint8 ``(L + 1, H, W)``, flow float16/float32 ``(L, 2, H, W)``); the views keep
            the ZeroMQ frames (or the buffer) alive.
    """

    sample_id: str
    meta: dict
    arrays: Dict[str, np.ndarray]
    #: the batch buffer and row the arrays were copied into (shared-memory path), else None / -1
    buffer: Optional["_BatchBuffer"] = field(default=None, repr=False)
    row: int = -1

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.arrays.values())


def sample_from_worker(header: dict, frames: Sequence) -> SamplePayload:
    """Build a :class:`SamplePayload` from a worker's ``sample`` message (header + raw frames,
    ``zmq.Frame`` or bytes), without copying the arrays.

    Raises:
        ProtocolError: when the frames do not match the header's array specs.
    """
    return SamplePayload(header["sample_id"], header["meta"], decode_arrays(header["arrays"], frames))


def slot_layout(specs) -> Tuple[List[int], int]:
    """Byte offsets of the arrays described by ``specs`` (the header's ``arrays`` list) inside
    one slot, each aligned to ``SLOT_ALIGN``, and the bytes they span. Worker and relay both
    derive the layout from the specs, so the header carries no offsets.

    Raises:
        ProtocolError: for a malformed spec (name, dtype not in ``WIRE_DTYPES``, shape).
    """
    if not isinstance(specs, list):
        raise ProtocolError("array specs must be a list")
    offsets, end = [], 0
    for spec in specs:
        if not isinstance(spec, dict):
            raise ProtocolError("array spec must be a map")
        dtype, shape = spec.get("dtype"), spec.get("shape")
        if not isinstance(spec.get("name"), str) or dtype not in WIRE_DTYPES:
            raise ProtocolError(f"bad array spec {spec!r}")
        if not isinstance(shape, list) or not all(isinstance(d, int) and d >= 0 for d in shape) or len(shape) > 8:
            raise ProtocolError(f"bad shape in array spec {spec!r}")
        start = -(-end // SLOT_ALIGN) * SLOT_ALIGN
        offsets.append(start)
        end = start + math.prod(shape) * np.dtype(dtype).itemsize  # Python ints: no overflow
    return offsets, end


def slot_bytes(sequence_length: int, num_bins: int, crop_size: int) -> int:
    """Bytes of one slot: the largest sample the config can make (voxels int32
    ``(L, num_bins, S, S)``, frames up to 2 bytes ``(L + 1, S, S)``, flow float32
    ``(L, 2, S, S)``), rounded up to whole pages. The file is sparse on tmpfs: only the
    bytes a worker writes take memory."""
    px = crop_size * crop_size
    need = (sequence_length * num_bins * px * 4 + (sequence_length + 1) * px * 2
            + sequence_length * 2 * px * 4 + 3 * SLOT_ALIGN)
    return -(-need // mmap.PAGESIZE) * mmap.PAGESIZE


class SlotRing:
    """A worker's ring of ``slots`` fixed-size slots in one shared-memory file.

    The pool :meth:`create` s it before spawning the worker and passes :attr:`spec`; the worker
    :meth:`attach` es and unlinks the file at once, so nothing is left in ``/dev/shm`` when
    either side dies later (the pool unlinks it too when the worker dies first). Slot
    ownership travels in messages: the worker writes only slots it holds, names the slot in
    its ``sample`` header, and the relay gives it back with a ``slot`` message after copying
    it out. A ring belongs to one worker process; a restarted worker gets a new file.

    Raises (``create``/``attach``):
        OSError: when the file cannot be created, opened or mapped; ``ValueError`` when its
        size does not match ``slots * slot_size``.
    """

    def __init__(self, path: str, slots: int, slot_size: int, mm: mmap.mmap):
        self.path, self.slots, self.slot_size, self._mm = path, slots, slot_size, mm
        self.free = list(range(slots))  # the worker's side: slots it may write

    @property
    def spec(self) -> dict:
        """What a worker needs to :meth:`attach` (msgpack/pickle-able)."""
        return {"path": self.path, "slots": self.slots, "slot_size": self.slot_size}

    @classmethod
    def create(cls, slots: int, slot_size: int, directory: Optional[str] = SHM_DIR) -> "SlotRing":
        fd, path = tempfile.mkstemp(prefix="v2v-slots-", dir=directory)
        try:
            os.ftruncate(fd, slots * slot_size)
            mm = mmap.mmap(fd, slots * slot_size)
        except BaseException:
            os.unlink(path)
            raise
        finally:
            os.close(fd)
        return cls(path, slots, slot_size, mm)

    @classmethod
    def attach(cls, spec: dict, unlink: bool = True) -> "SlotRing":
        path, slots, slot_size = spec["path"], int(spec["slots"]), int(spec["slot_size"])
        try:
            fd = os.open(path, os.O_RDWR)
            try:
                size = os.fstat(fd).st_size
                if size != slots * slot_size:
                    raise ValueError(f"slot ring {path}: {size} bytes, expected {slots} x {slot_size}")
                mm = mmap.mmap(fd, size)
            finally:
                os.close(fd)
        finally:
            if unlink:
                _unlink(path)
        return cls(path, slots, slot_size, mm)

    def unlink(self) -> None:
        """Remove the file (mappings stay valid); a no-op once it is gone."""
        _unlink(self.path)

    def close(self) -> None:
        try:
            self._mm.close()
        except BufferError:  # a view still exists; the mapping goes with it
            pass

    def put(self, slot: int, arrays: Dict[str, np.ndarray]) -> Optional[List[dict]]:
        """Worker side: write ``arrays`` (C-contiguous wire dtypes) into ``slot``; returns their
        specs, or None when they do not fit a slot (send them as frames instead)."""
        specs = [{"name": k, "dtype": a.dtype.name, "shape": list(a.shape)} for k, a in arrays.items()]
        offsets, end = slot_layout(specs)
        if end > self.slot_size:
            return None
        base = slot * self.slot_size
        for (name, a), off in zip(arrays.items(), offsets):
            dst = np.frombuffer(self._mm, a.dtype, a.size, base + off).reshape(a.shape)
            np.copyto(dst, a, casting="no")
        return specs

    def arrays(self, slot, specs) -> Dict[str, np.ndarray]:
        """Relay side: read-only views of the arrays a worker wrote into ``slot``.

        Raises:
            ProtocolError: for a slot number out of range or specs that overrun a slot.
        """
        if not isinstance(slot, int) or isinstance(slot, bool) or not 0 <= slot < self.slots:
            raise ProtocolError(f"slot {slot!r} outside the ring of {self.slots}")
        offsets, end = slot_layout(specs)
        if end > self.slot_size:
            raise ProtocolError(f"arrays of {end} bytes overrun a slot of {self.slot_size}")
        base = slot * self.slot_size
        out = {}
        for spec, off in zip(specs, offsets):
            dt = np.dtype(spec["dtype"])
            a = np.frombuffer(self._mm, dt, math.prod(spec["shape"]), base + off)
            a = a.reshape(spec["shape"])
            a.flags.writeable = False
            out[spec["name"]] = a
        return out


def _unlink(path: str) -> None:
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass


def create_ring(sequence_length: int, num_bins: int, crop_size: int,
                directory: Optional[str] = None) -> Optional[SlotRing]:
    """A :class:`SlotRing` of ``RING_SLOTS`` slots sized for the config in ``directory``
    (default: ``$V2V_SHM_DIR``, else ``SHM_DIR``), or None where shared memory is unavailable
    or switched off (``V2V_SHM_DIR=""``; a failure logs one line): the worker then sends its
    arrays as frames."""
    if directory is None:
        directory = os.environ.get("V2V_SHM_DIR", SHM_DIR)
    if not directory or not os.path.isdir(directory):
        return None
    try:
        return SlotRing.create(RING_SLOTS, slot_bytes(sequence_length, num_bins, crop_size), directory)
    except OSError as e:
        log.warning("no shared-memory slot ring in %s (%s): workers send arrays over the socket", directory, e)
        return None


class _BatchBuffer:
    """One batch's arrays, ``(batch_size, ...)`` each, filled row by row as samples arrive."""

    __slots__ = ("arrays", "next", "sealed")

    def __init__(self, arrays: Dict[str, np.ndarray]):
        self.arrays, self.next, self.sealed = arrays, 0, False


    def idle(self) -> bool:
        """True when nothing outside this object views the arrays (no sample, batch or
        ZeroMQ message in flight: a zero-copy send holds a reference until the kernel has the
        bytes)."""
        for a in self.arrays.values():
            if sys.getrefcount(a) > 3:  # the dict, the loop variable and the call's argument
                return False
        return True


class BatchAssembler:
    """Copies arriving samples straight into batch buffers (the one copy of the shared-memory
    path): consecutive samples with the same array names, dtypes and shapes fill consecutive
    rows of one ``(batch_size, ...)`` buffer per array, so :func:`make_batch` finds the batch
    already assembled.

    Buffers are reused once idle (no sample, batch or in-flight zero-copy send views them),
    so the relay does not map, fault in and zero fresh pages for every batch; at most
    ``spare`` idle buffers per layout are kept, the rest go back to the allocator.

    Args:
        batch_size: rows per buffer (``ServeConfig.batch_size``).
        spare: idle buffers kept per layout for reuse.
    """

    def __init__(self, batch_size: int, spare: int = 2):
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.batch_size, self.spare = batch_size, spare
        self._open: Dict[tuple, _BatchBuffer] = {}
        self._used: Dict[tuple, List[_BatchBuffer]] = {}  # handed out, maybe still viewed
        self.reused = 0

    def _fresh(self, sig: tuple, arrays: Dict[str, np.ndarray]) -> _BatchBuffer:
        """An idle buffer of layout ``sig`` to refill, else a new one; forgets idle buffers
        beyond ``spare`` (and every idle buffer of another layout: outputs or dtypes changed)."""
        for other in list(self._used):
            if other != sig:
                busy = [b for b in self._used[other] if not b.idle()]
                if busy:
                    self._used[other] = busy
                else:
                    del self._used[other]
        used = self._used.setdefault(sig, [])
        idle = [b for b in used if b.idle()]
        busy = [b for b in used if not b.idle()]
        if idle:
            buf = idle.pop()
            buf.next, buf.sealed = 0, False
            self.reused += 1
        else:
            buf = _BatchBuffer({k: np.empty((self.batch_size,) + a.shape, a.dtype) for k, a in arrays.items()})
        self._used[sig] = busy + idle[: self.spare] + [buf]
        return buf

    def place(self, sample_id: str, meta: dict, arrays: Dict[str, np.ndarray]) -> SamplePayload:
        """Copy ``arrays`` (e.g. views of a slot) into the next free row of the open buffer of
        their layout; returns the sample viewing that row (read-only)."""
        sig = tuple((k, a.dtype.str, a.shape) for k, a in arrays.items())
        buf = self._open.get(sig)
        if buf is None or buf.sealed or buf.next >= self.batch_size:
            self._open[sig] = None  # the open buffer is not idle while we hold it here
            buf = self._open[sig] = self._fresh(sig, arrays)
        row = buf.next
        buf.next += 1
        views = {}
        for k, a in arrays.items():
            dst = buf.arrays[k][row]
            np.copyto(dst, a, casting="no")
            v = dst.view()
            v.flags.writeable = False
            views[k] = v
        return SamplePayload(sample_id, meta, views, buf, row)


def sample_from_slot(header: dict, ring: SlotRing, assembler: BatchAssembler) -> SamplePayload:
    """Build a :class:`SamplePayload` from a worker's ``sample`` header naming a slot of
    ``ring``: the slot's arrays are copied into ``assembler``'s batch buffer (after this
    returns the slot may be given back to the worker).

    Raises:
        ProtocolError: for a slot out of range or array specs that do not fit a slot.
    """
    views = ring.arrays(header["slot"], header["arrays"])
    try:
        return assembler.place(header["sample_id"], header["meta"], views)
    finally:
        del views


def _stack(arrays: Sequence[np.ndarray], dtype) -> np.ndarray:
    """One (B, ...) array filled from B same-shape arrays: a single copy (with a widening
    cast where a sample came narrower than the batch)."""
    out = np.empty((len(arrays),) + arrays[0].shape, dtype)
    for i, a in enumerate(arrays):
        if a.shape != arrays[0].shape:
            raise ValueError(f"sample arrays of shapes {arrays[0].shape} and {a.shape} cannot share a batch")
        np.copyto(out[i], a, casting="safe")
    return out


@dataclass
class BatchPayload:
    """The arrays of one batch, samples stacked on a leading axis.

    Attributes:
        sample_ids: ids in batch order.
        meta: per-sample parameters in batch order.
        samples: the :class:`SamplePayload` of each sample (views of the workers' frames)
            until the batch is stacked, then None (the frames are released: a batch is held
            once, never twice).
    """

    sample_ids: List[str]
    meta: List[dict]
    samples: Optional[List[SamplePayload]]
    _stacked: Optional[Dict[str, np.ndarray]] = field(default=None, repr=False)

    @property
    def arrays(self) -> Dict[str, np.ndarray]:
        """name -> stacked (B, ...) array; voxels in the narrowest int type that holds every
        sample's counts (each sample arrives narrowed by its worker). Built on first use."""
        if self._stacked is None:
            out = {}
            for name in self.samples[0].arrays:
                parts = [s.arrays[name] for s in self.samples]
                out[name] = _stack(parts, np.result_type(*[p.dtype for p in parts]))
            self._stacked = out
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
        if self._stacked is None:
            return BatchPayload(ids, meta, [self.samples[i] for i in keep])
        arrays = {k: v[keep] for k, v in self._stacked.items()}  # a copy; only on resume
        return BatchPayload(ids, meta, None, {k: narrow_voxels(k, v) for k, v in arrays.items()})

    def wire(self, outputs: Sequence[str]) -> Tuple[List[dict], List]:
        """Array specs for the batch header and the frames to send (zero-copy, one per
        array), for the arrays in ``outputs``."""
        return encode_arrays({k: v for k, v in self.arrays.items() if k in outputs})


def narrow_voxels(name: str, a: np.ndarray) -> np.ndarray:
    """``a`` narrowed to the smallest int type that holds it when ``name`` is "voxels"."""
    return a.astype(narrow_int_dtype(a), copy=False) if name == "voxels" else a


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
    if buf is not None and all(s.buffer is buf and s.row == r0 + i for i, s in enumerate(samples)):
        buf.sealed = True  # later samples start a fresh buffer; these rows are the batch's
        return BatchPayload(ids, meta, None, {k: v[r0:r0 + len(samples)] for k, v in buf.arrays.items()})
    return BatchPayload(ids, meta, list(samples))


__all__ = ["SamplePayload", "BatchPayload", "BatchAssembler", "SlotRing", "sample_from_worker", "sample_from_slot",
           "make_batch", "narrow_voxels", "create_ring", "slot_bytes", "slot_layout"]

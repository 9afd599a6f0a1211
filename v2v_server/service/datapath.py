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

import fcntl
import logging
import math
import mmap
import os
import shutil
import stat
import struct
import sys
import tempfile
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from v2v_server.faults import cause_of, warn_once
from v2v_wire.codecs import packed_specs
from v2v_wire.outputs import max_sample_bytes, narrowest
from v2v_wire.protocol import (BATCH_DIR_RE, BATCH_FILE_HEADER, WIRE_DTYPES, ProtocolError, decode_arrays, encode_arrays,
                       output_of)

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
        sample_id: stable id (``ids.make_sample_id``).
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
    #: codec -> array name -> (dtype the worker sent it in, its compressed frame) (``codecs``),
    #: kept as received and forwarded by reference to the clients that asked for that codec
    packed: Dict[str, Dict[str, tuple]] = field(default_factory=dict, repr=False)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.arrays.values())


def sample_from_worker(header: dict, frames: Sequence) -> SamplePayload:
    """Build a :class:`SamplePayload` from a worker's ``sample`` message (header + raw frames,
    ``zmq.Frame`` or bytes, then its compressed frames), without copying the arrays.

    Raises:
        ProtocolError: when the frames do not match the header's array specs.
    """
    n = len(header["arrays"]) if isinstance(header["arrays"], list) else 0
    s = SamplePayload(header["sample_id"], header["meta"], decode_arrays(header["arrays"], frames[:n]))
    s.packed = packed_frames(header, frames[n:], s.arrays)
    return s


#: Largest compressed frame accepted from a worker, bytes (a sample's largest array, uncompressed,
#: is at most ``slot_bytes``; a compressed one can exceed it only by the codec's small overhead).
MAX_PACKED_BYTES = 1 << 31


def packed_frames(header: dict, frames: Sequence, arrays: Dict[str, np.ndarray]) -> Dict[str, Dict[str, tuple]]:
    """The compressed frames of a worker's ``sample`` message (its ``packed`` list: codec, array
    name and size of each frame after the array frames), by codec and array name, each with
    the dtype of the array it compresses; the frames themselves are kept as they are (never
    decompressed here).

    Raises:
        ProtocolError: for a list that does not match the frames, or names no array of the sample.
    """
    specs = header.get("packed", [])
    if not isinstance(specs, list) or len(specs) != len(frames):
        raise ProtocolError(f"sample header lists {len(specs) if isinstance(specs, list) else '?'} compressed "
                            f"frames, message has {len(frames)}")
    out: Dict[str, Dict[str, object]] = {}
    for spec, fr in zip(specs, frames):
        if not isinstance(spec, dict) or spec.get("name") not in arrays or not isinstance(spec.get("codec"), str):
            raise ProtocolError(f"bad compressed frame spec {spec!r:.200}")
        size = len(fr.buffer) if hasattr(fr, "buffer") else len(fr)
        if size != spec.get("nbytes") or size > MAX_PACKED_BYTES:
            raise ProtocolError(f"compressed frame of {spec['name']!r}: {size} bytes, spec says {spec.get('nbytes')!r}")
        out.setdefault(spec["codec"], {})[spec["name"]] = (arrays[spec["name"]].dtype, fr)
    return out


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
    """Bytes of one slot: the largest sample of the default outputs the config can make
    (``outputs.max_sample_bytes``: each at its widest wire dtype; a sample with an opt-in output
    too may travel as frames), rounded up to whole pages. The file is sparse on
    tmpfs: only the bytes a worker writes take memory."""
    need = max_sample_bytes(sequence_length, num_bins, crop_size, SLOT_ALIGN)
    return -(-need // mmap.PAGESIZE) * mmap.PAGESIZE


def shm_bytes(workers: int, sequence_length: int, num_bins: int, crop_size: int) -> int:
    """Bytes of /dev/shm a server's slot rings reserve: ``workers x RING_SLOTS x slot_bytes``
    (about 57 MB per worker for L = 40, 5 bins, 128 x 128 crops). A server bound to ``ipc://``
    also keeps its batch buffers there (``(prefetch_batches + credits in flight + 2) x`` one
    batch, plus one batch per open batch of the shuffle buffer: ``shuffle_buffer`` rounded up to
    whole batches, docs/shuffle.md). Size a container's /dev/shm (Docker ``shm_size``, a Kubernetes memory-backed
    ``emptyDir``) at least this; with less, rings are refused at start and workers send
    arrays over the socket."""
    return workers * RING_SLOTS * slot_bytes(sequence_length, num_bins, crop_size)


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
        self._lock_fd: Optional[int] = None  # the creating server's flock on the file

    @property
    def spec(self) -> dict:
        """What a worker needs to :meth:`attach` (msgpack/pickle-able)."""
        return {"path": self.path, "slots": self.slots, "slot_size": self.slot_size}

    @classmethod
    def create(cls, slots: int, slot_size: int, directory: Optional[str] = SHM_DIR) -> "SlotRing":
        """A new ring file with every page reserved now (``posix_fallocate``): a /dev/shm too
        small for it (Docker's default is 64 MiB) fails here with ``OSError`` instead of
        killing the worker with SIGBUS at a later write. The server holds an ``flock`` on it
        until :meth:`close`, so the next server's start can tell a left-over ring from a live
        one (:func:`remove_stale_shm`)."""
        remove_stale_shm(directory)
        fd, path = tempfile.mkstemp(prefix="v2v-slots-", dir=directory)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            _reserve(fd, slots * slot_size)
            mm = mmap.mmap(fd, slots * slot_size)
        except BaseException:
            os.close(fd)
            os.unlink(path)
            raise
        ring = cls(path, slots, slot_size, mm)
        ring._lock_fd = fd
        return ring

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
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None
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


def _reserve(fd: int, nbytes: int) -> None:
    """Size the file ``fd`` to ``nbytes`` with its pages reserved (``posix_fallocate``; a plain
    ``ftruncate`` on file systems without it)."""
    try:
        os.posix_fallocate(fd, 0, nbytes)
    except OSError as e:
        if e.errno not in (95, 22):  # EOPNOTSUPP / EINVAL: a file system without fallocate
            raise
        os.ftruncate(fd, nbytes)


#: Name of the lock file a live server holds (``flock``) in its batch directory.
LOCK_FILE = ".lock"
#: A batch directory without its lock file is a server's that is starting for this long at most.
STARTING_S = 60.0


def _unlocked(path: str) -> bool:
    """True when nobody holds an ``flock`` on ``path`` (we could take it): what a server that
    died leaves. Locks are held on the file, not by a pid, so this holds across PID namespaces
    (containers sharing /dev/shm) and for a server that is PID 1."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0))
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except BlockingIOError:
        return False
    finally:
        os.close(fd)


def remove_stale_shm(root: Optional[str]) -> List[str]:
    """Remove what servers that died without cleaning up (SIGKILL, power loss, killed while
    starting) left under ``root``: batch directories whose lock file nobody holds, and slot-ring
    files nobody holds. Never a live server's (it holds its locks), never a symlink or someone
    else's file. Returns the paths removed."""
    gone: List[str] = []
    try:
        names = os.listdir(root) if root else []
    except OSError:
        return gone
    uid = os.getuid()
    for name in names:
        path = os.path.join(root, name)
        try:
            st = os.lstat(path)
        except OSError:
            continue
        if st.st_uid != uid or stat.S_ISLNK(st.st_mode):
            continue
        lock = os.path.join(path, LOCK_FILE)
        try:
            if BATCH_DIR_RE.fullmatch(name) and stat.S_ISDIR(st.st_mode) and (
                    _unlocked(lock) if os.path.exists(lock) else time.time() - st.st_mtime > STARTING_S):
                shutil.rmtree(path, ignore_errors=True)
            elif name.startswith("v2v-slots-") and stat.S_ISREG(st.st_mode) and _unlocked(path):
                _unlink(path)
            else:
                continue
        except OSError as e:  # a read-only or failing tmpfs: left there, the server goes on
            warn_once(log, ("sweep", cause_of(e)), "cannot remove %s (%s), left by a v2v server that no longer runs",
                      path, e)
            continue
        gone.append(path)
        log.info("removed %s, left by a v2v server that no longer runs", path)
    return gone


class BatchDir:
    """A server's private directory (mode 0700) of batch-buffer files in shared memory.

    :meth:`create` removes dead servers' directories first; :meth:`remove` (called by the
    server's shutdown, also after a crash of its loop) deletes it with every file. Files are
    named ``b<N>`` with ``N`` counting up, so a name is never reused within one directory.
    """

    def __init__(self, path: str):
        self.path = path
        self._next = 0
        # held while the server lives: the next server's start tells a live directory by it
        self._lock = os.open(os.path.join(path, LOCK_FILE), os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o600)
        fcntl.flock(self._lock, fcntl.LOCK_EX | fcntl.LOCK_NB)

    @classmethod
    def create(cls, root: Optional[str] = None) -> Optional["BatchDir"]:
        """A fresh directory under ``root`` (default: ``$V2V_SHM_DIR``, else ``SHM_DIR``), or
        None where shared memory is unavailable or switched off (``V2V_SHM_DIR=""``)."""
        if root is None:
            root = os.environ.get("V2V_SHM_DIR", SHM_DIR)
        if not root or not os.path.isdir(root):
            return None
        remove_stale_shm(root)
        try:
            return cls(tempfile.mkdtemp(prefix=f"v2v-batches-{os.getpid()}-", dir=root))
        except OSError as e:
            log.warning("no shared-memory batch directory in %s (%s): batches go as socket frames", root, e)
            return None

    def new_file(self, nbytes: int) -> Tuple[str, mmap.mmap]:
        """A new file of ``nbytes`` (pages reserved now, so a full tmpfs fails here with OSError
        rather than with SIGBUS on a later write), mapped read-write."""
        name = f"b{self._next}"
        self._next += 1
        path = os.path.join(self.path, name)
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o600)
        try:
            _reserve(fd, nbytes)
            # MAP_POPULATE: the pages are mapped now, not by one fault per 4 KiB at the first fill
            mm = mmap.mmap(fd, nbytes, flags=mmap.MAP_SHARED | getattr(mmap, "MAP_POPULATE", 0))
        except BaseException:
            _unlink(path)
            raise
        finally:
            os.close(fd)
        return name, mm

    def unlink(self, name: str) -> None:
        _unlink(os.path.join(self.path, name))

    def remove(self) -> None:
        """Delete the directory and its files (mappings stay valid while viewed)."""
        shutil.rmtree(self.path, ignore_errors=True)
        if self._lock is not None:
            os.close(self._lock)
            self._lock = None


class _BatchBuffer:
    """One batch's arrays, ``(batch_size, ...)`` each, filled row by row as samples arrive;
    in a :class:`BatchDir` file (``file``, byte ``offsets`` of the arrays, ``gen``) or in
    private memory (``file`` None)."""

    __slots__ = ("arrays", "next", "sealed", "file", "offsets", "gen", "_mm")

    def __init__(self, arrays: Dict[str, np.ndarray], file: Optional[str] = None,
                 offsets: Optional[Dict[str, int]] = None, mm: Optional[mmap.mmap] = None):
        self.arrays, self.next, self.sealed = arrays, 0, False
        self.file, self.offsets, self._mm, self.gen = file, offsets or {}, mm, 0
        self.bump()

    def bump(self) -> None:
        """A new generation: the buffer is about to be refilled (nothing views it any more)."""
        self.gen += 1
        if self._mm is not None:
            struct.pack_into("<Q", self._mm, 0, self.gen)


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

    def __init__(self, batch_size: int, spare: int = 2, files: Optional[BatchDir] = None):
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.batch_size, self.spare, self.files = batch_size, spare, files
        #: told ``(path, OSError)`` when a batch file cannot be made or removed (the server
        #: counts it and logs it once); default: a warning in the log
        self.on_error = lambda path, e: log.warning("batch buffer %s: %s: batches go as socket frames", path, e)
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
                # np.ndarray over the mapping (base: the mmap), so every row view references
                # these very arrays and the reference count in idle() sees it
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
        for key in [k for k, b in self._open.items() if b is not None and b.idle()]:
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
            self._open[(sig, lane)] = None  # the open buffer is not idle while we hold it here
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
        return SamplePayload(sample_id, meta, views, buf, row)


def sample_from_slot(header: dict, ring: SlotRing, assembler: BatchAssembler, frames: Sequence = (),
                     lane: int = 0) -> SamplePayload:
    """Build a :class:`SamplePayload` from a worker's ``sample`` header naming a slot of
    ``ring``: the slot's arrays are copied into ``assembler``'s batch buffer of ``lane`` (the
    open batch the sample joins; after this returns the slot may be given back to the worker);
    ``frames``, the message's frames after the header, are its compressed frames
    (``packed_frames``).

    Raises:
        ProtocolError: for a slot out of range, array specs that do not fit a slot, or
            compressed frames that do not match the header.
    """
    views = ring.arrays(header["slot"], header["arrays"])
    packed = packed_frames(header, frames, views)
    try:
        s = assembler.place(header["sample_id"], header["meta"], views, lane)
    finally:
        del views
    s.packed = packed
    return s


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
    #: (buffer, first row) when the arrays are consecutive rows of one batch buffer
    _rows: Optional[Tuple["_BatchBuffer", int]] = field(default=None, repr=False)
    #: each sample's compressed frames (``SamplePayload.packed``), in batch order
    packed: List[Dict[str, Dict[str, tuple]]] = field(default_factory=list, repr=False)

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
        packed = [self.packed[i] for i in keep] if self.packed else []
        if self._stacked is None:
            return BatchPayload(ids, meta, [self.samples[i] for i in keep], packed=packed)
        arrays = {k: v[keep] for k, v in self._stacked.items()}  # a copy; only on resume
        return BatchPayload(ids, meta, None, {k: narrow_voxels(k, v) for k, v in arrays.items()}, packed=packed)

    def wire(self, outputs: Sequence[str], codec: str = "none") -> Tuple[List[dict], List]:
        """Array specs for the batch header and the frames to send (zero-copy), for the arrays
        that carry ``outputs`` (``protocol.output_of``): one frame per array, or with a
        ``codec`` (``codecs.COMPRESSIONS``) whose compressed frames every sample has for an
        array, those frames, one per sample, forwarded as the workers sent them (spec
        ``codecs.packed_specs``)."""
        names = [k for k in (self._stacked if self._stacked is not None else self.samples[0].arrays)
                 if output_of(k) in outputs]
        use = {}
        if codec != "none" and self.packed:
            for k in names:
                parts = [p.get(codec, {}).get(k) for p in self.packed]
                if all(q is not None for q in parts):
                    use[k] = parts
        plain = {k: v for k, v in self.arrays.items() if k in names and k not in use} if len(use) < len(names) else {}
        pspecs, pframes = encode_arrays(plain)
        plain_by = {s["name"]: (s, f) for s, f in zip(pspecs, pframes)}
        specs, frames = [], []
        for k in names:
            if k in use:
                parts = use[k]
                first = self.samples[0].arrays[k] if self.samples is not None else self._stacked[k][0]
                dtype = np.result_type(*[d for d, _ in parts]).name
                specs.append(packed_specs(k, dtype, [len(parts)] + list(first.shape), codec,
                                          [(d.name, _size(f)) for d, f in parts]))
                frames.extend(f for _, f in parts)
            else:
                spec, f = plain_by[k]
                specs.append(spec)
                frames.append(f)
        return specs, frames

    def shm_ref(self, outputs: Sequence[str]) -> Optional[Tuple[List[dict], dict]]:
        """Where a same-host client finds this batch's arrays in ``outputs``: ``(specs, ref)``
        with ``ref = {"file", "gen", "offsets"}`` (file name inside the server's
        :class:`BatchDir`, the buffer's generation, byte offset of each array in the file, in
        the order of ``specs``), or None when the arrays are not consecutive rows of a
        file-backed buffer (send :meth:`wire` frames instead). The rows stay untouched while
        this payload exists (a buffer is refilled only once nothing views it)."""
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


def narrow_voxels(name: str, a: np.ndarray) -> np.ndarray:
    """``a`` narrowed to the smallest dtype that holds it when its spec narrows by counts
    (``outputs.narrowest``: voxels); other arrays as they are."""
    return narrowest(name, a)


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
        return BatchPayload(ids, meta, None, {k: v[r0:r0 + len(samples)] for k, v in buf.arrays.items()},
                            (buf, r0), packed)
    return BatchPayload(ids, meta, list(samples), packed=packed)


def _size(frame) -> int:
    return len(frame.buffer) if hasattr(frame, "buffer") else len(frame)


__all__ = ["SamplePayload", "BatchPayload", "BatchAssembler", "BatchDir", "SlotRing", "remove_stale_shm", "sample_from_worker", "sample_from_slot",
           "make_batch", "narrow_voxels", "create_ring", "slot_bytes", "slot_layout"]

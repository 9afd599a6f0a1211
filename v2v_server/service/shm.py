"""Shared memory of the server's data path: the workers' slot rings and the sweep of what dead
servers left.

* **Slot rings** (:class:`SlotRing`): each worker writes a sample's arrays into a free slot of
  its own ring (a file in ``/dev/shm`` that the pool creates and the worker unlinks as soon as
  it has mapped it) and sends only the header with the slot number; the relay copies the slot
  out (``assembly.sample_from_slot``) and gives it back at once, so a ring of a few slots
  suffices however long samples wait for their fetch.
* **The sweep** (:func:`remove_stale_shm`): a live server holds an ``flock`` on its ring files;
  what nobody holds was left by a server that died, and the
  next server's start removes it.
"""
from __future__ import annotations

import fcntl
import logging
import math
import mmap
import os
import stat
import tempfile
from typing import Dict, List, Optional, Tuple

import numpy as np

from v2v_server.faults import cause_of, warn_once
from v2v_wire.outputs import max_sample_bytes
from v2v_wire.protocol import ProtocolError, array_spec

log = logging.getLogger("v2v.datapath")

#: Where slot rings live (a tmpfs on Linux). The environment variable ``V2V_SHM_DIR`` overrides
#: it for the server's workers; set it empty to send arrays over the socket instead.
SHM_DIR = "/dev/shm"
#: Slots per worker ring. The relay copies a slot out and gives it back as soon as the sample
#: arrives, so a worker needs only enough to keep writing while one message is in flight.
RING_SLOTS = 3
#: Byte alignment of each array inside a slot.
SLOT_ALIGN = 64

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
        _, dtype, shape = array_spec(spec)
        start = -(-end // SLOT_ALIGN) * SLOT_ALIGN
        offsets.append(start)
        end = start + math.prod(shape) * dtype.itemsize  # Python ints: no overflow
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
    (about 57 MB per worker for L = 40, 5 bins, 128 x 128 crops). Size a container's /dev/shm (Docker ``shm_size``, a Kubernetes memory-backed
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


def shm_root() -> Optional[str]:
    """The folder of this process's shared memory: ``$V2V_SHM_DIR``, else ``SHM_DIR``; None when
    it is switched off (``V2V_SHM_DIR=""``) or is not a folder, which a variable set to one
    names in one warning (arrays then go over the socket)."""
    root = os.environ.get("V2V_SHM_DIR", SHM_DIR)
    if root and not os.path.isdir(root):
        if "V2V_SHM_DIR" in os.environ:
            warn_once(log, ("V2V_SHM_DIR", root), "V2V_SHM_DIR=%s is not a folder: no shared memory, arrays go "
                      "over the socket", root)
        return None
    return root or None


def create_ring(sequence_length: int, num_bins: int, crop_size: int,
                directory: Optional[str] = None) -> Optional[SlotRing]:
    """A :class:`SlotRing` of ``RING_SLOTS`` slots sized for the config in ``directory``
    (default: ``$V2V_SHM_DIR``, else ``SHM_DIR``), or None where shared memory is unavailable
    or switched off (``V2V_SHM_DIR=""``; a failure logs one line): the worker then sends its
    arrays as frames."""
    if directory is None:
        directory = shm_root()
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
    starting) left under ``root``: slot-ring files nobody holds. Never a live server's (it holds its locks), never a symlink or someone
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
        try:
            if name.startswith("v2v-slots-") and stat.S_ISREG(st.st_mode) and _unlocked(path):
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


__all__ = ["SlotRing", "create_ring", "remove_stale_shm", "shm_bytes", "slot_bytes", "slot_layout",
           "RING_SLOTS", "SHM_DIR", "SLOT_ALIGN"]

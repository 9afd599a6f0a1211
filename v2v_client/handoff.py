"""Same-host batch hand-off: read a batch from the server's shared-memory batch file.

A client connected over ``ipc://`` that asked for it (hello ``"shm": true``) receives batches
that sit in one of the server's batch buffers as a header only: ``"shm": {"file", "gen",
"offsets"}`` next to the usual ``"arrays"`` specs, and no array frames (see
``v2v_server.service.shm``). :class:`ShmReader` maps the file (read-only; mappings cached per
file), checks every offset and size against the file, and copies the arrays out into memory
of its own (one memcpy; no socket copy on either side) before the batch is acknowledged,
after which the server may refill the buffer. A buffer refilled before the copy ended (the
batch was already acknowledged elsewhere, e.g. after this process stalled past its lease) is
detected by the generation stamped at the start of the file: :meth:`ShmReader.read` then
returns None and the caller gives the batch back.

The copies go into a small pool of reused memory blocks (fresh pages would cost the kernel a
page fault and zeroing per 4 KiB, as much again as the copy). A block is lent as one array over
it; every array and tensor made from the copies references that array, so the block comes back
to the pool when the array is collected, and never while anything still views it.
"""
from __future__ import annotations

import collections
import math
import mmap
import os
import stat
import struct
import threading
import weakref
from typing import Dict, List, Optional

import numpy as np

from v2v_wire.protocol import BATCH_DIR_RE, BATCH_FILE_HEADER, BATCH_FILE_RE, ProtocolError, array_spec

#: Mapped batch files kept open per connection (the server keeps a few buffers per layout).
MAX_MAPPINGS = 16
#: Byte alignment of each array inside a private copy.
ALIGN = 64


def check_shm_dir(path) -> str:
    """The server's batch directory from its welcome: an absolute path whose last part is a
    v2v batch directory name.

    Raises:
        ProtocolError: naming ``info.shm_dir`` otherwise.
    """
    if not isinstance(path, str) or not os.path.isabs(path) or BATCH_DIR_RE.fullmatch(os.path.basename(path)) is None \
            or os.path.normpath(path) != path:
        raise ProtocolError(f"field 'info.shm_dir' is not a v2v batch directory: {path!r:.80}")
    return path


def shm_dir_problem(path: str) -> Optional[str]:
    """Why this process must not read batches from the directory ``path`` (None when it may):
    it is a symbolic link, or its real path differs (a parent is a link), or it is not a
    directory of this user or root, or it cannot be read."""
    try:
        st = os.lstat(path)
    except OSError as e:
        return f"cannot be looked at ({e.strerror or e})"
    if stat.S_ISLNK(st.st_mode):
        return "is a symbolic link"
    if not stat.S_ISDIR(st.st_mode) or os.path.realpath(path) != path:
        return "is not a plain directory at that path"
    if st.st_uid not in (os.getuid(), 0):
        return f"belongs to another user (uid {st.st_uid})"
    if not os.access(path, os.R_OK | os.X_OK):
        return "cannot be read by this user"
    return None


def shm_layout(specs, ref, file_size: int) -> List[tuple]:
    """``(name, dtype, shape, offset, nbytes)`` per array of a shared-memory batch header,
    every array inside the file after its header.

    Raises:
        ProtocolError: naming the field (``arrays``, ``shm.offsets[i]``, ...) that is malformed
        or points outside the file.
    """
    if not isinstance(specs, list) or not isinstance(ref.get("offsets"), list) or len(ref["offsets"]) != len(specs):
        raise ProtocolError("fields 'arrays' and 'shm.offsets' must be lists of the same length")
    out = []
    for i, (spec, off) in enumerate(zip(specs, ref["offsets"])):
        name, dt, shape = array_spec(spec)
        nbytes = math.prod(shape) * dt.itemsize  # Python ints: no overflow
        if isinstance(off, bool) or not isinstance(off, int) or off < BATCH_FILE_HEADER or off % dt.itemsize \
                or off + nbytes > file_size:
            raise ProtocolError(f"field 'shm.offsets[{i}]' = {off!r:.40} with {nbytes} bytes of {name!r} lies "
                                f"outside the batch file of {file_size} bytes")
        out.append((name, dt, tuple(shape), off, nbytes))
    return out


class _Pool:
    """Reused private memory for the copies out of the batch files: at most ``keep`` idle
    blocks (anonymous mappings) are kept, each lent as a uint8 array over it whose collection
    gives the block back (``weakref.finalize``): numpy views and ``torch.from_numpy`` tensors of
    the copies reference that array (a block's array owns no data, so no view skips it), so
    nothing that still views a block can see it refilled."""

    def __init__(self, keep: int):
        self.keep = keep
        self.idle: List[mmap.mmap] = []
        self._lock = threading.Lock()  # a block comes back in whichever thread drops its array

    def get(self, nbytes: int) -> np.ndarray:
        """A uint8 array of ``nbytes`` over a block nothing else holds (an idle one when one
        of that size is kept)."""
        with self._lock:
            block = next((b for b in self.idle if len(b) == nbytes), None)
            if block is not None:
                self.idle.remove(block)
        if block is None:
            block = mmap.mmap(-1, max(nbytes, 1))
        lent = np.frombuffer(block, np.uint8, count=nbytes)
        weakref.finalize(lent, self._back, block)
        return lent

    def _back(self, block: mmap.mmap) -> None:
        with self._lock:
            if len(self.idle) < self.keep:
                self.idle.append(block)


class ShmReader:
    """Reads shared-memory batches of one connection (see the module docstring).

    Args:
        keep: private buffers kept for reuse (the connection's credits plus a few).
    """

    def __init__(self, keep: int = 8):
        self.dir: Optional[str] = None
        self._maps: "collections.OrderedDict[str, mmap.mmap]" = collections.OrderedDict()
        self._pool = _Pool(keep)

    def set_dir(self, path: Optional[str]) -> None:
        """The server's batch directory (None: the server offers none); a new one drops the
        cached mappings."""
        path = None if path is None else check_shm_dir(path)
        if path != self.dir:
            self.close()
            self.dir = path

    def _map(self, name: str) -> mmap.mmap:
        mm = self._maps.get(name)
        if mm is not None:
            self._maps.move_to_end(name)
            return mm
        fd = os.open(os.path.join(self.dir, name), os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0)
                     | getattr(os, "O_CLOEXEC", 0))
        try:
            st = os.fstat(fd)
            if not stat.S_ISREG(st.st_mode) or st.st_size < BATCH_FILE_HEADER:
                raise ProtocolError(f"field 'shm.file' {name!r} is not a batch file")
            # read-only; MAP_POPULATE maps every page now instead of one fault per 4 KiB later
            mm = mmap.mmap(fd, st.st_size, flags=mmap.MAP_SHARED | getattr(mmap, "MAP_POPULATE", 0),
                           prot=mmap.PROT_READ)
        finally:
            os.close(fd)
        self._maps[name] = mm
        while len(self._maps) > MAX_MAPPINGS:
            _close(self._maps.popitem(last=False)[1])
        # forget mappings of files the server removed (their pages stay allocated while mapped)
        for other in [k for k in self._maps if k != name and not os.path.exists(os.path.join(self.dir, k))]:
            _close(self._maps.pop(other))
        return mm

    def read(self, h: dict, copy: bool = True) -> Optional[Dict[str, np.ndarray]]:
        """The arrays of the batch header ``h``: private copies (``copy=True``, in one pooled
        buffer), else read-only views of the mapping, valid only until the batch is
        acknowledged (convert them before). None when the server's buffer already holds
        another generation (the batch is gone: give it back).

        Raises:
            ProtocolError: for a malformed reference, a file name that is not a batch file of
            the server's directory, or arrays outside the file.
        """
        ref = h.get("shm")
        if self.dir is None:
            raise ProtocolError("a shared-memory batch, but the welcome named no 'shm_dir'")
        if not isinstance(ref, dict) or not isinstance(ref.get("file"), str) \
                or BATCH_FILE_RE.fullmatch(ref["file"]) is None:
            raise ProtocolError(f"field 'shm.file' must name a batch file, got {ref!r:.80}")
        gen = ref.get("gen")
        if isinstance(gen, bool) or not isinstance(gen, int) or not 0 < gen < 2 ** 64:
            raise ProtocolError(f"field 'shm.gen' must be a positive integer, got {gen!r:.40}")
        try:
            mm = self._map(ref["file"])
        except FileNotFoundError:
            return None  # removed: the buffer was idle, so the batch was acknowledged already
        layout = shm_layout(h.get("arrays"), ref, len(mm))
        if struct.unpack_from("<Q", mm, 0)[0] != gen:
            return None
        out = {}
        if copy:
            total, starts = 0, []
            for *_, nbytes in layout:
                starts.append(total)
                total += -(-nbytes // ALIGN) * ALIGN
            dst = self._pool.get(total)
            for (name, dt, shape, off, nbytes), start in zip(layout, starts):
                a = dst[start:start + nbytes].view(dt).reshape(shape)
                np.copyto(a, np.ndarray(shape, dt, buffer=mm, offset=off), casting="no")
                out[name] = a
        else:
            for name, dt, shape, off, _ in layout:
                out[name] = np.ndarray(shape, dt, buffer=mm, offset=off)
        if copy and not self.valid(h):  # refilled while we copied: torn
            return None
        return out

    def valid(self, h: dict) -> bool:
        """True while the batch file of header ``h`` (read before) still holds its generation:
        whatever was read or converted from it so far is that batch's."""
        mm = self._maps.get(h["shm"]["file"])
        return mm is not None and not mm.closed and struct.unpack_from("<Q", mm, 0)[0] == h["shm"]["gen"]

    def close(self) -> None:
        """Unmap every cached file."""
        while self._maps:
            _close(self._maps.popitem()[1])


def _close(mm: mmap.mmap) -> None:
    try:
        mm.close()
    except BufferError:  # a view is still alive (raw=False conversion in progress); it goes with it
        pass

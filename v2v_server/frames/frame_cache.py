"""Decode once, read every epoch: a host's cache of decoded frames.

The first time any process of a host decodes a video it stores what the sample cutter reads:
every decoded frame's kept region (the top rows, display rotation applied) at full range
(uint8, or uint16 for deeper sources), plus the stream's frame size, frame rate and declared
frame count. Later epochs replay those frames instead of decoding; the cutter
(``samples.make``) sees the same arrays either way, so samples are bit-identical cached or
decoded (``tests/test_frame_cache.py``).

An entry is one file (``disk_cache.DiskCache`` under ``cache_dir/frames``: atomic rename,
byte budget, policy ``keep``), named by the corpus, the video's id path and the key
of what the pass reads (:func:`entry_name_settings`); its trailer records the identity of
the source it was decoded from (``VideoSource.identity``: size, modification time, change time
and inode of a file; ETag of an object; a tar member's offset and size within its shard's
identity). A different identity is a miss (``changed``), the entry is removed and the video
decoded again, never a stale hit. A source whose identity cannot vouch for its bytes (a file
changed within its file system's timestamp resolution of now, git's racy rule; an object with
no version tag) is a miss (``unverified``): decoded and not stored. Layout::

    frame 0 | frame 1 | ... | trailer (JSON) | trailer bytes (u64) | trailer CRC-32 (u32) | MAGIC

(raw frames padded to ``ALIGN`` bytes).

Two formats (``FORMATS``, measured in docs/frame_cache.md, ``python -m bench.frame_cache``):

* ``raw``: frames as they are, read through a memory map (pages shared by every process of the
  host), each checked against its checksum (:func:`sum64`) as it is read;
* ``zstd``: each frame Zstandard-compressed (level 1, with its content checksum) as its
  difference to the previous frame (modulo 2^8 or 2^16), the first frame of each window stride
  and any frame whose size changes whole: about half the bytes, a little more CPU per read.

A truncated, bit-flipped or unreadable entry raises :class:`CorruptEntry` at the first bad
frame: the caller removes it and decodes the video from there (``samples.make``).
"""
from __future__ import annotations

import hashlib
import json
import logging
import mmap
import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Tuple

import numpy as np

from v2v_server.faults import cause_of, warn_once
from v2v_server.disk_cache import DiskCache, is_disk_full, remove_quietly

log = logging.getLogger("v2v.frame_cache")

#: Entry formats (module docstring).
FORMATS = ("raw", "zstd")
#: The format of entries unless one is asked for (raw: memory-mapped, the fastest, docs/frame_cache.md).
DEFAULT_FORMAT = "raw"
#: Version of the entry layout, of the frames it holds (the luma conversion of ``frames.decode``)
#: and of how its name is made (``entry_name_settings``): a change makes every older entry a
#: miss under a name no lookup makes again, left to the budget's eviction.
VERSION = 4
MAGIC = b"V2VFRM1\n"
_FOOTER = struct.Struct("<QI")
#: Miss causes counted (``FrameCache.take_stats``).
MISS_CAUSES = ("absent", "changed", "corrupt", "unverified")
#: Why a decoded video was not stored.
SKIP_CAUSES = ("budget", "disk_full", "write_error", "incomplete")


#: Byte alignment of each raw frame in an entry.
ALIGN = 64


def sum64(a: np.ndarray) -> int:
    """A raw frame's checksum: the sum of its bytes taken as little-endian 64-bit words (the
    last, partial word zero-padded), modulo 2^64. It changes with any flipped bit or any error
    within one word, at memory speed (about 15x faster than CRC-32 here, which cost a cached
    sample 18 % of its CPU); reordered words, which a damaged disk block does not make, pass."""
    b = a.reshape(-1).view(np.uint8)
    n = b.size // 8 * 8
    total = int(b[:n].view("<u8").sum(dtype=np.uint64)) if n else 0
    if n < b.size:
        total += int.from_bytes(b[n:].tobytes(), "little")
    return total % (1 << 64)


class CorruptEntry(RuntimeError):
    """An entry that cannot be read whole: truncated, bit-flipped, or gone (the message says which
    frame and why)."""


def entry_name_settings(pass_key: str) -> dict:
    """What, beside the corpus and the video, names an entry: this format's :data:`VERSION` and
    ``pass_key``, the key of what the pass reads (``pass_record.PassRecord.key``: decoder
    shortcut, scale, rows kept, window layout, detector and motion versions)."""
    return {"v": VERSION, "pass": pass_key}


@dataclass
class CachedVideo:
    """An entry opened for reading. ``meta``: its trailer, the stream facts stored with it
    (``info``: the stream's ``decode.VideoInfo`` as a dict; ``declared``: the container's frame
    count, 0 when it gives none) and where each frame lies; ``frames``: frames stored, which
    :meth:`read` gives."""

    meta: dict
    buf: object  # mmap of the whole file
    data_end: int

    @property
    def frames(self) -> int:
        return len(self.meta["offsets"])

    def read(self) -> Iterator[np.ndarray]:
        """Every stored frame, in order, as (H', W) arrays of the stored dtype (read-only; a raw
        entry's are views of the map, valid until :meth:`close`).

        Raises:
            CorruptEntry: a frame fails its checksum or lies outside the file.
        """
        m = self.meta
        dtype = np.dtype(m["dtype"])
        shapes = _expand_runs(m["shapes"], self.frames)
        offsets, sizes, sums = m["offsets"], m["sizes"], m["sums"]
        zstd = m["format"] == "zstd"
        dec = None
        if zstd:
            import zstandard

            dec = zstandard.ZstdDecompressor()
        prev = None
        keys = set(m["keys"])  # zstd: the frames stored whole; the others are differences to the previous
        for i in range(self.frames):
            o, n = offsets[i], sizes[i]
            if o + n > self.data_end:
                raise CorruptEntry(f"frame {i} lies past the end of the data")
            raw = memoryview(self.buf)[o:o + n]
            h, w = shapes[i]
            if zstd:
                try:
                    a = np.frombuffer(dec.decompress(raw, max_output_size=h * w * dtype.itemsize), dtype)
                except Exception as e:  # zstandard.ZstdError: a flipped bit or a cut frame
                    raise CorruptEntry(f"frame {i}: {e}") from None
                if a.size != h * w:
                    raise CorruptEntry(f"frame {i}: {a.size} values, expected {h * w}")
                a = a.reshape(h, w)
                if i not in keys:
                    a = a + prev  # modular: the stored difference wraps as the dtype does
                prev = a
            else:
                a = np.frombuffer(raw, dtype)
                if sum64(a) != sums[i]:
                    raise CorruptEntry(f"frame {i} fails its checksum")
                a = a.reshape(h, w)
            yield a

    def close(self) -> None:
        try:
            self.buf.close()
        except (BufferError, ValueError):
            pass  # a view still held by the caller: the map goes with it


def _expand_runs(runs: List[list], n: int) -> List[Tuple[int, int]]:
    """Per-frame (h, w) from runs ``[[first frame, h, w], ...]``."""
    out: List[Tuple[int, int]] = []
    for j, (first, h, w) in enumerate(runs):
        end = runs[j + 1][0] if j + 1 < len(runs) else n
        out += [(int(h), int(w))] * (end - first)
    return out


class EntryWriter:
    """Writes one video's frames into a temporary file as they are decoded; :meth:`finish`
    commits the entry, :meth:`abort` drops it. A write error (full disk, the folder deleted)
    stops the writing, never the decoding: the video is served decoded and the cause counted.
    """

    def __init__(self, cache: "FrameCache", name: str, identity: str, header: dict, stride: int):
        self.cache, self.name, self.identity, self.header, self.stride = cache, name, identity, header, stride
        #: What became of the entry: "" while it is written; ``"stored"``, ``"exists"`` (another
        #: process stored it first) or a cause of ``SKIP_CAUSES``.
        self.outcome = ""
        #: Bytes the entry took on disk once stored, else 0.
        self.stored_bytes = 0
        self.tmp: Optional[Path] = None
        self.f = None
        self.failed: Optional[str] = None
        self.offsets: List[int] = []
        self.sizes: List[int] = []
        self.sums: List[int] = []  # raw frames' sum64 (zstd frames carry their own checksum)
        self.keys: List[int] = []
        self.runs: List[list] = []
        self.dtype: Optional[str] = None
        self.prev: Optional[np.ndarray] = None
        self.pos = 0
        self.zstd = None
        if cache.format == "zstd":
            import zstandard

            self.zstd = zstandard.ZstdCompressor(level=1, write_checksum=True)
        try:
            self.tmp = cache.disk.temporary(name)
            self.f = open(self.tmp, "wb")
        except OSError as e:
            self._fail(e)

    def _fail(self, e: BaseException) -> None:
        self.failed = "disk_full" if is_disk_full(e) else "write_error"
        warn_once(log, ("not storing", self.failed, cause_of(e)), "frame cache: not storing %s (%s: %s); "
                  "further videos not stored for this cause are counted only", self.header.get("video"), self.failed, e)
        self.abort()

    @property
    def writing(self) -> bool:
        """Whether the entry is still being written: neither committed nor dropped (a failed
        write, a budget refused, an abort)."""
        return self.f is not None

    def add(self, frame: np.ndarray) -> None:
        """Append the next frame (full range, (H', W) uint8 or uint16)."""
        if self.f is None:
            return
        i = len(self.offsets)
        a = np.ascontiguousarray(frame)
        if self.dtype is None:
            self.dtype = a.dtype.str
        if not self.runs or self.runs[-1][1:] != [a.shape[0], a.shape[1]]:
            self.runs.append([i, int(a.shape[0]), int(a.shape[1])])
        if self.zstd is not None:
            whole = self.prev is None or self.prev.shape != a.shape or i % self.stride == 0
            if whole:
                self.keys.append(i)
            data = self.zstd.compress(a if whole else a - self.prev)
            self.prev = a.copy()
        else:
            data = a.data
            self.sums.append(sum64(a))
        n = len(data) if isinstance(data, bytes) else a.nbytes
        pad = -(self.pos + n) % ALIGN if self.zstd is None else 0  # raw frames start on cache lines
        try:
            self.f.write(data)
            if pad:
                self.f.write(bytes(pad))
        except OSError as e:
            self._fail(e)
            return
        self.offsets.append(self.pos)
        self.sizes.append(n)
        self.pos += n + pad
        if i % self.stride == 0 and i:
            try:
                fits = self.cache.disk.fits(self.pos)
            except OSError as e:  # the folder cannot be scanned (replaced, unmounted, EIO)
                self._fail(e)
                return
            if not fits:
                self.failed = "budget"
                self.abort()

    def finish(self, facts: Optional[dict] = None) -> None:
        """The decode ended cleanly: write the trailer, with ``facts`` the pass found (e.g. its
        shot cuts) beside the header's, and commit the entry (counted)."""
        if self.f is None:
            self.outcome = self.failed or "write_error"
            self.cache.skipped[self.outcome] += 1
            return
        meta = dict(self.header, **(facts or {}), identity=self.identity, format=self.cache.format, dtype=self.dtype or "|u1",
                    shapes=self.runs, offsets=self.offsets, sizes=self.sizes, sums=self.sums, keys=self.keys)
        try:
            trailer = json.dumps(meta, separators=(",", ":")).encode("utf-8")
            self.f.write(trailer)
            self.f.write(_FOOTER.pack(len(trailer), zlib.crc32(trailer)) + MAGIC)
            self.f.flush()
            os.fsync(self.f.fileno())
            self.f.close()
            self.f = None
            status = self.cache.disk.commit(self.tmp, self.name)
        except OSError as e:
            self._fail(e)
            self.outcome = self.failed
            self.cache.skipped[self.failed] += 1
            return
        if status == "added":
            self.outcome, self.stored_bytes = "stored", self.pos + len(trailer)
            self.cache.stored += 1
            self.cache.bytes_written += self.stored_bytes
        elif status == "budget":
            self.outcome = "budget"
            self.cache.skipped["budget"] += 1
        else:
            self.outcome = "exists"

    def abort(self, incomplete: bool = False) -> None:
        """Drop what was written: a failed write, or (``incomplete``) a pass that did not end
        cleanly (a decoding error, the consumer stopped), counted unless a write had failed."""
        if incomplete and self.f is not None:
            self.outcome = "incomplete"
            self.cache.skipped["incomplete"] += 1
        if self.f is not None:
            try:
                self.f.close()
            except OSError:
                pass
            self.f = None
        remove_quietly(self.tmp)


class FrameCache:
    """The decoded-frame cache of one host: entries under ``folder`` within ``max_bytes``.

    Counters since the last :meth:`take_stats`: ``hits``, ``misses`` by cause
    (``MISS_CAUSES``), ``stored`` entries and ``bytes_written``, and decoded videos not stored
    by cause (``SKIP_CAUSES``).

    Raises:
        ValueError: an unknown ``fmt``.
    """

    def __init__(self, folder, max_bytes: int, fmt: str = DEFAULT_FORMAT):
        if fmt not in FORMATS:
            raise ValueError(f"frame_cache_format must be one of {FORMATS}, got {fmt!r}")
        self.format = fmt
        self.disk = DiskCache(folder, max_bytes, "keep")
        self._reset()

    def _reset(self) -> None:
        self.hits = 0
        self.misses: Dict[str, int] = dict.fromkeys(MISS_CAUSES, 0)
        self.skipped: Dict[str, int] = dict.fromkeys(SKIP_CAUSES, 0)
        self.stored = self.bytes_written = 0

    @staticmethod
    def entry_name(corpus: str, video: str, settings: dict) -> str:
        """The entry's file name: a hash of the corpus, the video's id path and the decode settings."""
        key = json.dumps([corpus, video, settings], sort_keys=True)
        return hashlib.sha256(key.encode("utf-8")).hexdigest()[:32] + ".v2vf"

    def lookup(self, name: str, identity: Optional[str]) -> Optional[CachedVideo]:
        """The entry ``name`` opened for reading if it exists, is whole and was made from a
        source of this ``identity``; else None, the miss counted by cause (a changed or corrupt
        entry is removed). A None ``identity`` (the source cannot vouch for its bytes now) is
        an ``unverified`` miss: no entry is stored from a racy identity, so none can match."""
        if identity is None:
            self.misses["unverified"] += 1
            return None
        path = self.disk.path(name)
        try:
            f = open(path, "rb")
        except FileNotFoundError:
            self.misses["absent"] += 1
            return None
        except OSError as e:  # the folder replaced, unmounted or failing: every video meets it
            warn_once(log, ("open", cause_of(e)), "frame cache: cannot open %s (%s): decoding; further videos "
                      "that meet this are counted only", path, e)
            self.misses["corrupt"] += 1
            return None
        with f:
            try:
                entry = _open_entry(f)
            except CorruptEntry as e:
                log.warning("frame cache: entry %s is corrupt (%s): removed, decoding", path.name, e)
                self.misses["corrupt"] += 1
                self.disk.remove(name)
                return None
        if entry.meta.get("identity") != identity:
            entry.close()
            self.misses["changed"] += 1
            self.disk.remove(name)
            return None
        self.hits += 1
        return entry

    def corrupt(self, name: str, why: str) -> None:
        """An entry found bad while reading: removed and counted (the hit it began as is taken back)."""
        log.warning("frame cache: entry %s is corrupt (%s): removed, decoding", name, why)
        self.hits -= 1
        self.misses["corrupt"] += 1
        self.disk.remove(name)

    def writer(self, name: str, identity: str, header: dict, stride: int) -> EntryWriter:
        """A writer for entry ``name`` (``header``: the stream facts stored with it; ``stride``:
        frames between windows, where a ``zstd`` entry stores a frame whole)."""
        return EntryWriter(self, name, identity, header, stride)

    def take_stats(self) -> dict:
        """The counters since the last call, as a dict; then zero them."""
        out = {"hits": self.hits, "misses": dict(self.misses), "stored": self.stored,
               "bytes_written": self.bytes_written, "not_stored": dict(self.skipped)}
        self._reset()
        return out


def _open_entry(f) -> CachedVideo:
    """Map ``f`` and read its trailer.

    Raises:
        CorruptEntry: too short, no magic, a trailer that fails its CRC-32 or does not parse.
    """
    size = os.fstat(f.fileno()).st_size
    tail = _FOOTER.size + len(MAGIC)
    if size < tail:
        raise CorruptEntry(f"{size} bytes, shorter than a footer")
    try:
        buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    except (OSError, ValueError) as e:
        raise CorruptEntry(f"cannot map: {e}") from None
    if buf[size - len(MAGIC):] != MAGIC:
        buf.close()
        raise CorruptEntry("no end marker (truncated, or not an entry)")
    n, crc = _FOOTER.unpack(buf[size - tail:size - len(MAGIC)])
    start = size - tail - n
    if start < 0 or zlib.crc32(buf[start:size - tail]) != crc:
        buf.close()
        raise CorruptEntry("trailer fails its CRC-32")
    try:
        meta = json.loads(bytes(buf[start:size - tail]))
        _check_trailer(meta, start)
    except (ValueError, TypeError, KeyError, IndexError) as e:
        buf.close()
        raise CorruptEntry(f"trailer does not hold: {e}") from None
    return CachedVideo(meta, buf, start)


#: Largest frame side an entry may claim, pixels (8K video is 7680 wide): what a trailer says
#: sizes a frame's buffer, so it is checked before anything is read or allocated.
MAX_SIDE = 16384
_DTYPES = ("|u1", "<u2")


def _check_trailer(m: dict, data_end: int) -> None:
    """Whether trailer ``m`` describes frames that lie within the first ``data_end`` bytes and
    sizes that a frame of the stored dtype can have: each frame's (h, w) within ``MAX_SIDE``,
    a raw frame's bytes exactly h x w x itemsize; checked before any frame is read, so a
    trailer that passes its CRC but was written wrong (or by another tool) sizes no memory.

    Raises:
        ValueError: naming the field that does not hold.
    """
    def ints(name: str, n: Optional[int] = None) -> list:
        v = m[name]
        if not isinstance(v, list) or not all(type(x) is int and x >= 0 for x in v) or (n is not None and len(v) != n):
            raise ValueError(f"{name} must be {n if n is not None else 'a list of'} non-negative integers")
        return v

    if not isinstance(m, dict) or m.get("format") not in FORMATS or m.get("dtype") not in _DTYPES:
        raise ValueError("format or dtype unknown")
    if not isinstance(m.get("identity"), str) or not isinstance(m.get("info"), dict) or type(m.get("declared")) is not int:
        raise ValueError("identity, info or declared missing")
    offsets = ints("offsets")
    n = len(offsets)
    sizes, keys = ints("sizes", n), ints("keys")
    runs = m["shapes"]
    if not isinstance(runs, list) or (n and not runs) or any(
            not isinstance(r, list) or len(r) != 3 or not all(type(x) is int for x in r) for r in runs):
        raise ValueError("shapes must be runs [first frame, h, w]")
    if runs and runs[0][0] != 0 or any(b[0] <= a[0] for a, b in zip(runs, runs[1:])) or any(
            r[0] >= n or not (0 < r[1] <= MAX_SIDE and 0 < r[2] <= MAX_SIDE) for r in runs):
        raise ValueError(f"shapes: runs out of order, past frame {n}, or a side outside 1..{MAX_SIDE}")
    itemsize = np.dtype(m["dtype"]).itemsize
    raw = m["format"] == "raw"
    if raw:
        ints("sums", n)
    for (h, w), o, k in zip(_expand_runs(runs, n), offsets, sizes):
        if o + k > data_end or (raw and k != h * w * itemsize):
            raise ValueError(f"a frame of {k} bytes at {o} does not fit its {h} x {w} shape or the data")
    if any(i >= n for i in keys):
        raise ValueError("keys name frames past the end")



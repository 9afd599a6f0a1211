"""Entries on a host's local disk, shared by every process of the host: the one implementation
of atomic writes, byte budgets and eviction behind both caches of the decode path, whole store
objects (``store_io.ObjectCache``) and decoded frames (``frame_cache.FrameCache``).

An entry is written under a temporary name (``NAME.PID-N.tmp``) and renamed into place when it is
complete, so a reader never sees a torn entry and a process killed mid-write leaves only a
temporary file, which a later commit of any process removes once its writer is gone. Commits
take an exclusive ``flock`` on a lock file beside the folder (``.NAME.lock``), so the budget check and the rename are one
step for all processes of the host: two writers of the same entry leave one entry, and the
budget holds however many processes commit at once.

Two policies for a corpus larger than the budget:

* ``lru``: the least recently used entries are removed until the new one fits (the object
  cache: what was read recently is read again soon);
* ``keep``: admit until full, then keep what is there and refuse new entries. Every epoch
  reads the whole corpus in a new order, so LRU would evict exactly the entries the next
  epoch needs before it reaches them (a corpus 2x the budget would never hit); keeping a fixed
  part makes that part hit every epoch.
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import itertools
import os
import tempfile
from pathlib import Path
from typing import Iterator, List, Optional, Tuple

#: Eviction policies (module docstring).
POLICIES = ("lru", "keep")
#: Suffix of entries being written.
TMP_SUFFIX = ".tmp"
_SERIAL = itertools.count()


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/v2v`` (``~/.cache/v2v``): manifests and the object cache when no
    ``cache_dir`` is given."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "v2v"


def cache_folder(cache_dir: Optional[str]) -> str:
    """The folder of the host's caches: ``cache_dir`` as configured, else :func:`default_cache_dir`.
    The one rule, applied where a folder enters: the configuration's (``ops.config.source_from_config``,
    run by the start-up path ``ops.startup``), or a source's built without a configuration
    (``source_spec.open_source``, ``VideoSource``); everything below takes the resolved folder."""
    return str(cache_dir) if cache_dir else str(default_cache_dir())


class CacheDirError(ValueError):
    """A cache that is on cannot be kept in ``cache_dir`` (the message names the folder)."""


def check_cache_folders(cache_dir: str, folders: List[Path]) -> None:
    """At start: each folder of a cache that is on (a source's object cache, the frame cache)
    can be made and written. A cache asked for and unusable is a setting to fix, not a run to
    make at a fraction of the speed: ``v2v-serve`` exits with this one line. (While serving, the
    same faults are served by reading without the cache: docs/faults.md.)

    Raises:
        CacheDirError: naming ``cache_dir`` and the folder, with the system's reason.
    """
    for folder in folders:
        try:
            folder.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryFile(dir=folder):
                pass
        except OSError as e:
            raise CacheDirError(f"--cache-dir {cache_dir}: cannot keep a cache in {folder}: "
                                f"{e.strerror or e}") from None


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _live_bytes(e: os.DirEntry) -> int:
    """Bytes of the temporary file ``e`` (``NAME.PID-N.tmp``) while its writer is alive; a dead
    writer's file is removed (0)."""
    try:
        pid = int(e.name[:-len(TMP_SUFFIX)].rsplit(".", 1)[1].split("-")[0])
        size = e.stat().st_size
    except (ValueError, IndexError, OSError):
        return 0
    if _pid_alive(pid):
        return size
    with contextlib.suppress(OSError):
        os.unlink(e.path)
    return 0


class DiskCache:
    """A folder of entries under a byte budget, safe to share between processes of one host.

    Args:
        folder: where the entries live (made on first write).
        max_bytes: the budget, bytes, for complete entries and those being written together.
        policy: ``lru`` or ``keep`` (module docstring).

    Raises:
        ValueError: an unknown ``policy`` or a negative budget.
    """

    def __init__(self, folder, max_bytes: int, policy: str = "lru"):
        if policy not in POLICIES:
            raise ValueError(f"cache policy must be one of {POLICIES}, got {policy!r}")
        if max_bytes < 0:
            raise ValueError(f"cache budget must be >= 0 bytes, got {max_bytes!r}")
        self.folder, self.max_bytes, self.policy = Path(folder), int(max_bytes), policy

    def path(self, name: str) -> Path:
        """Where the complete entry ``name`` lives (it may not exist)."""
        return self.folder / name

    def temporary(self, name: str) -> Path:
        """A temporary path, unique to this process and call, to write entry ``name`` into
        (``NAME.PID-N.tmp``; folder made).

        Raises:
            OSError: the folder cannot be made (read-only or full disk).
        """
        self.folder.mkdir(parents=True, exist_ok=True)
        return self.folder / f"{name}.{os.getpid()}-{next(_SERIAL)}{TMP_SUFFIX}"

    @contextlib.contextmanager
    def _locked(self) -> Iterator[None]:
        self.folder.mkdir(parents=True, exist_ok=True)
        with open(self.folder.parent / f".{self.folder.name}.lock", "a+b") as lock:  # beside: the folder holds entries only
            fcntl.flock(lock, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(lock, fcntl.LOCK_UN)

    def entries(self) -> List[Tuple[float, int, Path]]:
        """``(mtime, bytes, path)`` of every complete entry (temporary files and the lock left out)."""
        return self._scan()[0]

    def _scan(self, writers: bool = False, keep: Optional[Path] = None) -> Tuple[List[Tuple[float, int, Path]], int]:
        """One pass over the folder: every complete entry (:meth:`entries`) and, with ``writers``,
        the bytes of the temporary files other than ``keep`` whose writer is alive; those of dead
        writers are removed."""
        out: List[Tuple[float, int, Path]] = []
        writing = 0
        try:
            it = list(os.scandir(self.folder))
        except FileNotFoundError:
            return out, 0
        for e in it:
            if e.name.endswith(TMP_SUFFIX):
                if writers and Path(e.path) != keep:
                    writing += _live_bytes(e)
                continue
            if e.name.startswith("."):
                continue
            try:
                st = e.stat()
            except OSError:
                continue  # removed meanwhile
            out.append((st.st_mtime, st.st_size, Path(e.path)))
        return out, writing

    def usage(self) -> Tuple[int, int]:
        """``(bytes, entries)`` of the complete entries."""
        ents = self.entries()
        return sum(e[1] for e in ents), len(ents)

    def fits(self, nbytes: int) -> bool:
        """Whether an entry of ``nbytes`` more could be admitted now (a hint for a writer that
        stops early; :meth:`commit` decides)."""
        if self.policy == "lru":
            return nbytes <= self.max_bytes
        return self.usage()[0] + nbytes <= self.max_bytes

    def commit(self, tmp: Path, name: str) -> str:
        """Rename the finished temporary file ``tmp`` to entry ``name`` if the budget allows.

        Returns:
            ``"added"``; ``"exists"`` (another process committed it first: ``tmp`` removed);
            ``"budget"`` (refused under ``keep``, or larger than the whole budget: ``tmp``
            removed).

        Raises:
            OSError: the rename failed (``tmp`` removed).
        """
        dest = self.path(name)
        try:
            size = tmp.stat().st_size
            with self._locked():
                if dest.exists():
                    tmp.unlink(missing_ok=True)
                    return "exists"
                if size > self.max_bytes:
                    tmp.unlink(missing_ok=True)
                    return "budget"
                ents, writing = self._scan(writers=True, keep=tmp)
                used = sum(e[1] for e in ents) + writing
                if used + size > self.max_bytes:
                    if self.policy == "keep":
                        tmp.unlink(missing_ok=True)
                        return "budget"
                    for _, esize, p in sorted(ents, key=lambda e: e[0]):
                        if used + size <= self.max_bytes:
                            break
                        with contextlib.suppress(OSError):
                            p.unlink()
                        used -= esize
                os.replace(tmp, dest)
                return "added"
        except BaseException:
            with contextlib.suppress(OSError):
                tmp.unlink()
            raise

    def touch(self, name: str) -> None:
        """Mark entry ``name`` recently used (``lru``)."""
        with contextlib.suppress(OSError):
            os.utime(self.path(name))

    def remove(self, name: str) -> None:
        """Remove entry ``name`` (a corrupt or stale one); a missing entry is fine."""
        with contextlib.suppress(OSError):
            self.path(name).unlink()


def is_disk_full(e: BaseException) -> bool:
    """Whether ``e`` is the error of a full disk or an exceeded quota."""
    return isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT)


def remove_quietly(path: Optional[Path]) -> None:
    """Remove ``path`` if it exists (a temporary file being abandoned)."""
    if path is not None:
        with contextlib.suppress(OSError):
            path.unlink()


class UsageScan:
    """A disk cache's ``(bytes, entries, budget)`` for gauges, its folder scanned at most every
    ``interval_s`` seconds (a scan lists the whole folder; a server asks four times a second).

    Args:
        disk: the cache whose folder is scanned.
        interval_s: seconds between scans.
    """

    def __init__(self, disk: "DiskCache", interval_s: float = 5.0):
        self.disk, self.interval_s = disk, interval_s
        self._when, self._usage = float("-inf"), (0, 0)

    def read(self, now: float) -> Tuple[Tuple[int, int, int], Optional[OSError]]:
        """``((bytes, entries, budget), error)`` at monotonic time ``now`` (seconds): a folder
        that cannot be scanned (a file in its place, a vanished mount, EIO) keeps the last
        values and returns the ``OSError`` of that scan for the caller to count; ``error`` is
        None otherwise."""
        err = None
        if now - self._when >= self.interval_s:
            try:
                self._usage = self.disk.usage()
            except OSError as e:
                err = e
            self._when = now
        return (*self._usage, self.disk.max_bytes), err

"""The host's caches of what passes read, passed beside a source: the decoded-frame cache
(``frame_cache.FrameCache``, under ``cache_dir/frames``) and the corpus index
(``corpus_index.CorpusIndex``, ``cache_dir/corpus_index.sqlite``).

A source (``sources.source.VideoSource``) says where a video's bytes come from; what passes made
of them is kept here, so a new cache is added on this side without touching a source. Like a
source, the caches are built once per process at its edge (the start-up path, each worker, each
pool process and Ray actor) from plain settings or from another process's :meth:`HostCaches.spec`.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

from v2v_server.disk_cache import cache_folder, check_cache_folders
from v2v_server.frames.corpus_index import CorpusIndex, index_path
from v2v_server.frames.frame_cache import DEFAULT_FORMAT, FrameCache


class HostCaches:
    """The frame cache and the corpus index of one host's cache folder.

    Args:
        cache_dir: the folder of the host's caches (None: the host's default,
            ``disk_cache.cache_folder``).
        frame_cache: the decoded-frame cache; None: off (frames are decoded every pass).
        corpus_index: whether the corpus index is read and written; False also after a fault
            of it met by the process that built these caches (it warned once).
    """

    def __init__(self, cache_dir: Optional[str] = None, frame_cache: Optional[FrameCache] = None,
                 corpus_index: bool = True):
        self.cache_dir = cache_folder(cache_dir)
        #: The host's decoded-frame cache, None when off: what ``frame_pass.open_frames`` reads.
        self.frame_cache: Optional[FrameCache] = frame_cache
        self._index: Optional[CorpusIndex] = None  # opened at the first use in this process
        self._index_off = not corpus_index

    @classmethod
    def open(cls, cache_dir: Optional[str] = None, frame_cache_gb: float = 0.0,
             frame_cache_format: str = DEFAULT_FORMAT, corpus_index: bool = True) -> "HostCaches":
        """The caches under ``cache_dir``: a frame cache of ``frame_cache_gb`` GiB in
        ``frame_cache_format`` (none at 0) and the corpus index (unless ``corpus_index`` is False).

        Raises:
            ValueError: an unknown ``frame_cache_format``.
        """
        cache_dir = cache_folder(cache_dir)
        frame_cache = None
        if frame_cache_gb > 0:
            frame_cache = FrameCache(Path(cache_dir) / "frames", int(frame_cache_gb * (1 << 30)), frame_cache_format)
        return cls(cache_dir, frame_cache, corpus_index)

    @classmethod
    def from_spec(cls, spec: dict) -> "HostCaches":
        """The caches a process builds from another's :meth:`spec`."""
        fc = spec.get("frame_cache")
        return cls(spec["cache_dir"], FrameCache(**fc) if fc is not None else None, spec.get("corpus_index", True))

    def spec(self) -> dict:
        """What another process needs to build the same caches (:meth:`from_spec`): plain values
        that pickle. A corpus index left off here (a fault met) is left off there too."""
        spec: dict = {"cache_dir": self.cache_dir, "corpus_index": not self._index_off}
        if self.frame_cache is not None:
            fc = self.frame_cache
            spec["frame_cache"] = {"folder": str(fc.disk.folder), "max_bytes": fc.disk.max_bytes, "fmt": fc.format}
        return spec

    def corpus_index(self) -> Optional[CorpusIndex]:
        """The host's corpus index: what passes learned about the corpus's videos, answered
        without decoding while a video's identity holds. Opened at the first call in this
        process; None when it is off (a fault met: one warning names the file and why, and the
        videos are read as if never seen)."""
        if self._index is None and not self._index_off:
            self._index = CorpusIndex(index_path(self.cache_dir))
        if self._index is not None and self._index.fault is not None:
            self._index_off = True
        return None if self._index_off else self._index

    def check_cache_dir(self) -> None:
        """At start: the frame cache's folder (``cache_dir/frames`` with ``frame_cache_gb`` > 0)
        can be kept (``disk_cache.check_cache_folders``).

        Raises:
            CacheDirError: naming ``cache_dir`` and the folder, with the system's reason.
        """
        check_cache_folders(self.cache_dir, [self.frame_cache.disk.folder] if self.frame_cache is not None else [])

    def take_stats(self) -> dict:
        """The frame cache's counters since the last call under ``frame_cache``
        (``FrameCache.take_stats``); empty without one."""
        return {"frame_cache": self.frame_cache.take_stats()} if self.frame_cache is not None else {}


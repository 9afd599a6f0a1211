"""A corpus and the host's caches beside it, as a worker holds them, for tests that read through
the frame cache."""
from __future__ import annotations

from typing import NamedTuple

from v2v_server.frames.host_caches import HostCaches
from v2v_server.sources.source import VideoSource
from v2v_server.sources.source_spec import open_source


class Cached(NamedTuple):
    """``source`` read through ``caches`` (its frame cache and corpus index)."""

    source: VideoSource
    caches: HostCaches

    @property
    def frame_cache(self):
        return self.caches.frame_cache

    def take_stats(self) -> dict:
        """Reads since the last call, as a worker reports them: the source's (a store's bytes,
        reads...) and the frame cache's counters under ``frame_cache``."""
        return {**self.source.take_stats(), **self.caches.take_stats()}


def cached(root, cache_dir, gb: float = 1.0, fmt: str = "raw", **source_options) -> Cached:
    """The corpus at ``root`` (a folder or URL, ``open_source``) with a frame cache of ``gb`` GiB
    in format ``fmt`` and the corpus index under ``cache_dir``."""
    return Cached(open_source(str(root), cache_dir=str(cache_dir), **source_options),
                  HostCaches.open(str(cache_dir), frame_cache_gb=gb, frame_cache_format=fmt))

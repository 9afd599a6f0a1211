"""The service's start-up path: from a ``ServeConfig`` to the videos this server serves.

One sequence, called by every way of running the service, so that none skips a step:
``v2v-serve`` (``cli.main``), the in-process server (``service.local.local_server``) and the
Ray engine (``ray_data.scan_corpus_windows``). In order:

1. the cache folder: ``cache_dir`` as configured, else the host's default
   (``disk_cache.cache_folder``), resolved here once and carried by the returned config;
2. the source the config describes (``config.source_from_config``: the store's options and
   settings, the video list and its table settings, the manifest), and the host's caches beside
   it (``config.caches_from_config``: the frame cache, the corpus index);
3. ``VideoSource.check``: the folder exists, or the store answers;
4. ``VideoSource.check_cache_dir``, ``HostCaches.check_cache_dir``: the caches that are on (a
   store's object cache, the frame cache) can be kept in the cache folder;
5. the listing (``VideoSource.list_videos``): the videos, and the entries refused with why (a
   table's rows too short for a window among them, by the frames side's rule the source was
   given, ``WindowSettings.short_of``);
6. the listing's fingerprint (:func:`corpus_fingerprint`), which servers sharding one corpus
   compare, then this server's shard of it (``shard: I/N``, :func:`select_shard`);
7. what the host's corpus index knows of the shard's videos (``frames.known.known_windows``):
   those known to give no window are not served, and an epoch's size when it knows them all.
"""
from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple, Union

from v2v_server.disk_cache import cache_folder
from v2v_server.frames.host_caches import HostCaches
from v2v_server.frames.known import KnownWindows, known_windows
from v2v_server.ops.config import ServeConfig, caches_from_config, source_from_config
from v2v_server.sources.source import VideoSource

log = logging.getLogger("v2v.serve")

#: The bundled demo corpus (see sample_videos/SOURCES.md): served when no corpus is given.
SAMPLE_VIDEOS = Path(__file__).resolve().parents[1] / "sample_videos"


@dataclass(frozen=True)
class Startup:
    """What a service starts from.

    Attributes:
        config: the configuration as given, its ``cache_dir`` resolved to the folder used.
        source: the corpus, checked (``check`` and ``check_cache_dir`` passed).
        caches: the host's frame cache and corpus index, passed beside ``source``
            (``check_cache_dir`` passed).
        videos: the sample-id paths of this server's shard of the corpus's videos, in listing
            order (what ``--check`` and ``--warm-cache`` read).
        rejected: ``(path, reason)`` for each entry of the corpus that is not served.
        corpus: the fingerprint of the whole listing before sharding (:func:`corpus_fingerprint`).
        listed: how many videos the whole listing holds.
        known: what the host's corpus index knows of :attr:`videos` (``frames.known.KnownWindows``).
    """

    config: ServeConfig
    source: VideoSource
    caches: HostCaches
    videos: List[str]
    rejected: List[Tuple[str, str]]
    corpus: str
    listed: int
    known: KnownWindows

    @property
    def skipped(self) -> Dict[str, Tuple[str, str]]:
        """The shard's videos the corpus index knows to give no window -> ``(cause, reason)``:
        not opened while their identity holds."""
        return self.known.empty

    @property
    def served(self) -> List[str]:
        """The videos the server hands out: :attr:`videos` less :attr:`skipped`."""
        return [v for v in self.videos if v not in self.known.empty]

    @property
    def epoch_samples(self) -> Optional[int]:
        """Samples an epoch holds, when the corpus index knows every video of the shard; None
        otherwise."""
        if self.known.known != len(self.videos):
            return None
        return self.config.recipe.epoch_samples(self.known.samples)


def resolve_config(cfg: ServeConfig) -> ServeConfig:
    """``cfg`` with ``cache_dir`` set to the folder the host's caches use (step 1)."""
    if cfg.cache_dir is not None:
        return cfg
    return ServeConfig.from_dict({**cfg.to_dict(), "cache_dir": cache_folder(None)}, source="configuration")


def start_source(cfg: ServeConfig, videos: Union[str, Path, None] = None) -> Startup:
    """Run the start-up path (module docstring) for the corpus ``videos`` (default
    ``cfg.videos``, else the bundled clips :data:`SAMPLE_VIDEOS`).

    Raises:
        StoreError: the folder does not exist, or the store cannot be reached or listed (naming it).
        disk_cache.CacheDirError: a cache that is on cannot be kept in the cache folder (naming it).
        FileNotFoundError, ValueError: the video list file is missing or does not parse.
        KeyboardInterrupt: Ctrl-C while a store or a table is read.
    """
    cfg = resolve_config(cfg)
    where: Optional[str] = str(videos) if videos is not None else cfg.videos
    source = source_from_config(cfg, where or str(SAMPLE_VIDEOS))
    caches = caches_from_config(cfg)
    source.check()
    source.check_cache_dir()
    caches.check_cache_dir()
    found, rejected = source.list_videos(cfg.video_extensions)
    index, count = cfg.serving.shard_spec
    mine = select_shard(found, index, count)
    if count > 1:
        log.info("shard %d/%d: %d of %d video file(s)", index, count, len(mine), len(found))
    known = known_windows(cfg.recipe.windows, cfg.recipe.decode, source, mine, caches)
    return Startup(cfg, source, caches, mine, rejected, corpus_fingerprint(found), len(found), known)


def shard_of(rel_path: str, count: int) -> int:
    """The shard (0 .. count - 1) that serves the video at ``rel_path`` (POSIX, relative to the
    corpus root).

    A stable hash: the first 8 bytes of BLAKE2b(``rel_path`` as UTF-8), big-endian, modulo
    ``count``. It depends on nothing but the path (not on Python's per-process ``hash``
    salt, the host or the order of the scan), so N servers started with ``--shard 0/N`` ..
    ``--shard N-1/N`` on copies of one corpus split it into disjoint parts that together
    hold every file once. Content is untouched: a sample stays a function of (seed, epoch,
    sample id), whichever shard serves it.

    Raises:
        ValueError: ``count`` < 1.
    """
    if count < 1:
        raise ValueError(f"shard count must be >= 1, got {count}")
    digest = hashlib.blake2b(rel_path.encode("utf-8"), digest_size=8).digest()
    return int.from_bytes(digest, "big") % count


def select_shard(videos: List[str], index: int, count: int) -> List[str]:
    """The videos of ``videos`` (relative POSIX paths) that shard ``index`` of ``count`` serves,
    in their original order (see :func:`shard_of`).

    Raises:
        ValueError: ``index`` outside ``[0, count)``.
    """
    if not 0 <= index < count:
        raise ValueError(f"shard index must be in [0, {count}), got {index}")
    if count == 1:
        return list(videos)
    return [v for v in videos if shard_of(v, count) == index]


def corpus_fingerprint(videos: List[str]) -> str:
    """A short hash of a corpus listing (relative POSIX paths, any order): servers sharding one
    corpus must have listed the same files, or a file only one of them sees may fall in the
    other's shard and never be served."""
    h = hashlib.sha256()
    for v in sorted(videos):
        h.update(v.encode("utf-8") + b"\n")
    return h.hexdigest()[:16]

"""The service's start-up path: from a ``ServeConfig`` to the listed corpus a service serves.

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
5. the listing (``VideoSource.list_videos``): the videos, and the entries refused with why.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Tuple, Union

from v2v_server.frames.host_caches import HostCaches
from v2v_server.ops.config import ServeConfig, caches_from_config, source_from_config
from v2v_server.sources.listing import SAMPLE_VIDEOS
from v2v_server.disk_cache import cache_folder
from v2v_server.sources.source import VideoSource


@dataclass(frozen=True)
class Startup:
    """What a service starts from.

    Attributes:
        config: the configuration as given, its ``cache_dir`` resolved to the folder used.
        source: the corpus, checked (``check`` and ``check_cache_dir`` passed).
        caches: the host's frame cache and corpus index, passed beside ``source``
            (``check_cache_dir`` passed).
        videos: the sample-id paths of the corpus's videos, in listing order.
        rejected: ``(path, reason)`` for each entry of the corpus that is not served.
    """

    config: ServeConfig
    source: VideoSource
    caches: HostCaches
    videos: List[str]
    rejected: List[Tuple[str, str]]


def resolve_config(cfg: ServeConfig) -> ServeConfig:
    """``cfg`` with ``cache_dir`` set to the folder the host's caches use (step 1)."""
    if cfg.cache_dir is not None:
        return cfg
    return ServeConfig.from_dict({**cfg.to_dict(), "cache_dir": cache_folder(None)}, source="configuration")


def start_source(cfg: ServeConfig, videos: Union[str, Path, None] = None) -> Startup:
    """Run the start-up path (module docstring) for the corpus ``videos`` (default
    ``cfg.videos``, else the bundled clips ``listing.SAMPLE_VIDEOS``).

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
    return Startup(cfg, source, caches, found, rejected)

"""Building a ``VideoSource`` from what names a corpus: a folder, a URL or a brace pattern of tar
shards (:func:`open_source`, which works out what the source needs of its own: the manifest of a
store's listing, the table settings of its video list; ``ops.config.source_from_config`` reads a
``ServeConfig``'s keys into it), or the picklable ``VideoSource.spec()`` a process hands to its
workers (:func:`source_from_spec`).

A source is built once per process, at the process's edge, and the built source is handed to
every stage below: the start-up path (``ops.startup.start_source``, run by ``v2v-serve``, the
in-process ``service.local.local_server`` and the Ray engine's scan) at server start, each
worker process at its start (``service.worker.worker_main``), the pools of ``--check`` and
``--warm-cache`` once per pool process (:func:`map_videos`), and each Ray actor (``ray_data``).
"""
from __future__ import annotations

from pathlib import Path
from typing import List, Optional, Union

from v2v_server.sources.local import LocalSource
from v2v_server.disk_cache import cache_folder
from v2v_server.sources.shards import split_pattern
from v2v_server.sources.source import VideoSource
from v2v_server.sources.manifest import manifest_path
from v2v_server.sources.store import StoreSettings, StoreSource, manifest_key
from v2v_server.sources.names import is_url
from v2v_server.sources.video_tables import TableSettings


def open_source(videos: Union[str, Path, None], *, storage_options: Optional[dict] = None,
                video_list: Optional[str] = None, table: TableSettings = TableSettings(),
                manifest: Optional[str] = None, keep_manifest: bool = False,
                refresh_manifest: bool = False, settings: StoreSettings = StoreSettings(),
                names: Optional[List[str]] = None, cache_dir: Optional[str] = None) -> VideoSource:
    """The source of a corpus given as a folder, a URL, or a brace pattern / path of tar shards
    or zip parts, with its video list read as ``table`` says (a table's path column and filter).

    Args:
        cache_dir: the folder of a store's manifests and object cache (the host's default when
            None, ``disk_cache.cache_folder``).
        settings: how a store is read (ignored for a folder).
        manifest: the file that keeps a store's listing (a process rebuilding another's
            source gets it in the spec); None: with ``keep_manifest``, the one kept for this
            listing in the cache folder (``manifest.manifest_path`` of ``store.manifest_key``),
            else none.
    """
    cache_dir = cache_folder(cache_dir)
    if names is None:
        videos, names = split_pattern(str(videos))
    if is_url(str(videos)):
        if manifest is None and keep_manifest:
            manifest = str(manifest_path(manifest_key(str(videos), bool(names), video_list), cache_dir))
        return StoreSource(str(videos), storage_options=storage_options, video_list=video_list, manifest=manifest,
                           refresh_manifest=refresh_manifest, settings=settings, names=names, cache_dir=cache_dir,
                           table=table)
    return LocalSource(videos, video_list, names, cache_dir, table)


def source_from_spec(spec: dict) -> VideoSource:
    """The source a process builds from another's :meth:`VideoSource.spec` (at its start: see
    the module docstring)."""
    spec = dict(spec)
    return open_source(spec.pop("root"), **spec)

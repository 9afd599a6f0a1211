"""Building a ``VideoSource`` from what names a corpus: a folder, a URL or a brace pattern of tar
shards (:func:`open_source`; ``ops.config.source_from_config`` reads a ``ServeConfig``'s keys into it), or the picklable
``VideoSource.spec()`` a process hands to its workers (:func:`source_from_spec`).

A source is built once per process, at the process's edge, and the built source is handed to
every stage below: the start-up path (``ops.startup.start_source``, run by ``v2v-serve``, the
in-process ``service.local.local_server`` and the Ray engine's scan) at server start, each
worker process at its start (``service.worker.worker_main``), the pools of ``--check`` and
``--warm-cache`` once per pool process (:func:`map_videos`), and each Ray actor (``ray_data``).
"""
from __future__ import annotations

import multiprocessing as mp
from pathlib import Path
from typing import Callable, List, Optional, Sequence, Tuple, TypeVar, Union

from v2v_server.videos.frame_cache import DEFAULT_FORMAT, FrameCache
from v2v_server.videos.local import LocalSource
from v2v_server.videos.manifest import cache_folder
from v2v_server.videos.shards import split_pattern
from v2v_server.videos.source import VideoSource
from v2v_server.videos.store import StoreSettings, StoreSource
from v2v_server.videos.video_list import is_url

T = TypeVar("T")


def open_source(videos: Union[str, Path, None], *, storage_options: Optional[dict] = None,
                video_list: Optional[str] = None, manifest: Optional[str] = None, refresh_manifest: bool = False,
                settings: StoreSettings = StoreSettings(), names: Optional[List[str]] = None,
                cache_dir: Optional[str] = None, frame_cache_gb: float = 0.0, frame_cache_format: str = DEFAULT_FORMAT,
                frame_cache: Optional[FrameCache] = None) -> VideoSource:
    """The source of a corpus given as a folder, a URL, or a brace pattern / path of tar shards.
    Its frame cache is ``frame_cache`` when given, else with ``frame_cache_gb`` > 0 the host's
    frame cache under ``cache_dir/frames`` within that many GiB, else none (``cache_dir``: the
    host's default when None, ``manifest.cache_folder``). ``settings``: how a store is read
    (ignored for a folder)."""
    cache_dir = cache_folder(cache_dir)
    if frame_cache is None and frame_cache_gb > 0:
        folder = Path(cache_dir) / "frames"
        frame_cache = FrameCache(folder, int(frame_cache_gb * (1 << 30)), frame_cache_format)
    if names is None:
        videos, names = split_pattern(str(videos))
    if is_url(str(videos)):
        return StoreSource(str(videos), storage_options=storage_options, video_list=video_list, manifest=manifest,
                           refresh_manifest=refresh_manifest, settings=settings, names=names,
                           frame_cache=frame_cache, cache_dir=cache_dir)
    return LocalSource(videos, video_list, names, frame_cache, cache_dir)


def source_from_spec(spec: dict) -> VideoSource:
    """The source a process builds from another's :meth:`VideoSource.spec` (at its start: see
    the module docstring)."""
    spec = dict(spec)
    fc = spec.pop("frame_cache", None)
    index_on = spec.pop("corpus_index", True)
    source = open_source(spec.pop("root"), frame_cache=FrameCache(**fc) if fc is not None else None, **spec)
    if not index_on:
        source.leave_corpus_index_off()
    return source


#: A pool process's job of :func:`map_videos`: the function, its leading arguments and the source
#: built once at the process's start (building a source opens its filesystem client and reads
#: its manifest and tar indexes: not once per video).
_job: Optional[Tuple[Callable, tuple, VideoSource]] = None


def _start_job(fn: Callable, args: tuple, spec: dict) -> None:
    global _job
    _job = (fn, args, source_from_spec(spec))


def _run_job(rel: str):
    fn, args, source = _job
    return fn(*args, source, rel)


def map_videos(fn: Callable[..., T], args: tuple, source: VideoSource, videos: Sequence[str],
               processes: int) -> List[T]:
    """``[fn(*args, source, rel) for rel in videos]`` in ``processes`` spawned processes, each of
    which builds the source once from ``source.spec()`` (``fn`` and ``args`` must pickle); in
    this process, through ``source`` itself, when ``processes`` <= 1 or there is one video."""
    if processes <= 1 or len(videos) <= 1:
        return [fn(*args, source, rel) for rel in videos]
    with mp.get_context("spawn").Pool(min(processes, len(videos)), _start_job, (fn, args, source.spec())) as pool:
        return pool.map(_run_job, videos, chunksize=1)

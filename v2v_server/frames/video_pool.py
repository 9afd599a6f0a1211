"""One function over many videos in a pool of processes, each of which builds the source and
the host's caches once, at its start (building a source opens its filesystem client and reads
its manifest and archive indexes: not once per video). ``--check`` and ``--warm-cache`` use it.
"""
from __future__ import annotations

import multiprocessing as mp
import signal
from typing import Callable, List, Optional, Sequence, Tuple, TypeVar

from v2v_server.frames.host_caches import HostCaches
from v2v_server.sources.source import VideoSource
from v2v_server.sources.source_spec import source_from_spec

T = TypeVar("T")

#: A pool process's job: the function, its leading arguments, the source and the caches built once
#: at the process's start.
_job: Optional[Tuple[Callable, tuple, VideoSource, HostCaches]] = None


def _start_job(fn: Callable, args: tuple, source_spec: dict, caches_spec: dict) -> None:
    global _job
    _job = (fn, args, source_from_spec(source_spec), HostCaches.from_spec(caches_spec))


def _run_job(rel: str):
    fn, args, source, caches = _job
    return fn(*args, source, rel, caches=caches)


def map_videos(fn: Callable[..., T], args: tuple, source: VideoSource, caches: HostCaches, videos: Sequence[str],
               processes: int) -> List[T]:
    """``[fn(*args, source, rel, caches=caches) for rel in videos]`` in ``processes`` spawned processes,
    each of which builds the source and the caches once from ``source.spec()`` and
    ``caches.spec()`` (``fn`` and ``args`` must pickle); in this process, through ``source`` and
    ``caches`` themselves, when ``processes`` <= 1 or there is one video.

    The processes start with Ctrl-C ignored (a terminal sends it to the whole process group):
    this process answers it, and leaving the pool stops them."""
    if processes <= 1 or len(videos) <= 1:
        return [fn(*args, source, rel, caches=caches) for rel in videos]
    was = signal.signal(signal.SIGINT, signal.SIG_IGN)  # inherited by the processes started now
    try:
        pool = mp.get_context("spawn").Pool(min(processes, len(videos)), _start_job,
                                            (fn, args, source.spec(), caches.spec()))
    finally:
        signal.signal(signal.SIGINT, was)
    with pool:
        return pool.map(_run_job, videos, chunksize=1)

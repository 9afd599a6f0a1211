"""One pass over a video's frames for the sample cutter: replayed from the host's frame cache
(``frame_cache``) when it holds the video, else decoded (``decode``) and, with a cache, stored
as they pass.

Either way the cutter gets ``(codes, expand)`` per frame, as ``decode.decode_codes`` yields them:
decoded frames carry the stream's code -> full-range map, cached ones are already full range
(``expand`` is ``decode.full_range``, the identity). Expansion is per pixel, so the cutter's samples are the same.
"""
from __future__ import annotations

import contextlib
import itertools
import os
from dataclasses import asdict, dataclass
from typing import Callable, Iterator, Optional, Tuple

import numpy as np

from v2v_server.videos.decode import Rows, VideoInfo, decode_codes, full_range, open_video
from v2v_server.videos.frame_cache import CachedVideo, CorruptEntry, EntryWriter, FrameCache

Frame = Tuple[np.ndarray, Callable[[np.ndarray], np.ndarray]]


@dataclass
class FramePass:
    """A video opened for one pass: ``info`` (the stream's facts), ``declared`` (the container's
    frame count, 0 when it gives none), ``frames`` (an iterator of ``(codes, expand)``, at most
    ``limit_of(declared)`` of them), ``cached`` (replayed from the frame cache), ``writer``
    (storing the decoded frames into the frame cache; None when replayed or the cache is off)."""

    info: VideoInfo
    declared: int
    frames: Iterator[Frame]
    cached: bool
    writer: Optional[EntryWriter] = None

    @property
    def storing(self) -> bool:
        """Whether the pass is still storing the video: then it must read ``frames`` to their end
        for the entry to be committed (stopping early drops it)."""
        return self.writer is not None and self.writer.writing


def corpus_key(source) -> str:
    """The corpus as an entry name's part: the URL, or the folder's absolute path."""
    root = str(source.root)
    return root if "://" in root else os.path.abspath(root)


def lookup_entry(cache: FrameCache, source, rel: str, settings: dict
                 ) -> Tuple[str, Optional[str], Optional[CachedVideo]]:
    """Video ``rel`` of ``source`` in its frame cache ``cache``: the entry's name (by the corpus,
    ``rel`` and the decode ``settings``), the source's identity (None: it cannot vouch for the
    video's bytes now, ``VideoSource.identity``), and the entry opened for reading
    when it holds the video, else None (``FrameCache.lookup``: the miss counted, a stale or
    damaged entry removed).

    Raises:
        VideoError: the source's identity cannot be read (``source.identity``).
    """
    identity = source.identity(rel)
    name = cache.entry_name(corpus_key(source), rel, settings)
    return name, identity, cache.lookup(name, identity)


@contextlib.contextmanager
def open_frames(source, rel: str, rows: Rows, threads: int, fast: str, settings: dict,
                limit_of: Callable[[int], int], stride: int) -> Iterator[FramePass]:
    """The frames of video ``rel`` of ``source`` (a ``videos.source.VideoSource``), from its
    frame cache (``source.frame_cache``, None when off) or decoded with ``threads`` and
    ``fast`` (``decode.open_video``), top ``rows`` kept. ``settings``: the decode settings
    that name the entry (``frame_cache.decode_settings``); ``limit_of(declared)``: frames the
    pass needs; ``stride``: frames between windows.

    Raises:
        VideoError: the video cannot be opened or decoded (as ``source.open``, ``open_video``).
    """
    cache: Optional[FrameCache] = getattr(source, "frame_cache", None)
    name = identity = None
    if cache is not None:
        name, identity, entry = lookup_entry(cache, source, rel, settings)
        if entry is not None:
            declared = int(entry.meta["declared"])
            limit = limit_of(declared)

            def redecode(start: int) -> Iterator[Frame]:
                with source.open(rel) as path:
                    container, stream, _ = open_video(path, threads, fast)
                    yield from itertools.islice(decode_codes(container, stream, rows), start, limit)

            try:
                yield FramePass(VideoInfo(**entry.meta["info"]), declared, _replay(cache, name, entry, limit, redecode),
                                True)
            finally:
                entry.close()
            return
    with source.open(rel) as path:
        container, stream, info = open_video(path, threads, fast)
        declared = int(getattr(stream, "frames", 0) or 0)
        writer = None
        if cache is not None and identity is not None:  # a racy identity is never stored
            writer = cache.writer(name, identity, {"video": rel, "info": asdict(info), "declared": declared}, stride)
        yield FramePass(info, declared, _decoded(decode_codes(container, stream, rows), limit_of(declared), writer), False,
                        writer)


def _replay(cache: FrameCache, name: str, entry: CachedVideo, limit: int,
            redecode: Callable[[int], Iterator[Frame]]) -> Iterator[Frame]:
    """The entry's frames; from the first bad one on (truncated, bit-flipped), the entry is
    removed and the rest decoded."""
    i = 0
    try:
        for a in entry.read():
            if i >= limit:
                return
            yield a, full_range
            i += 1
        return
    except CorruptEntry as e:
        cache.corrupt(name, f"{e}; frames {i}.. decoded")
    yield from redecode(i)


def _decoded(frames: Iterator[Frame], limit: int, writer: Optional[EntryWriter]) -> Iterator[Frame]:
    """The first ``limit`` decoded frames, each stored by ``writer`` (at full range) as it passes;
    the entry is committed only when the pass ends cleanly."""
    done = False
    try:
        for codes, expand in itertools.islice(frames, limit):
            if writer is not None:
                writer.add(expand(codes))
            yield codes, expand
        done = True
    finally:
        if writer is not None:  # a decoding error, or the consumer stopped: nothing partial is kept
            writer.finish() if done else writer.abort(incomplete=True)

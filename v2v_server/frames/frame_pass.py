"""The frames of one pass over a video, as each part of a pass reads them (``video_read.read_video``
opens them, the one way into a video): the sample pass's (:func:`open_frames`) replayed from the
host's frame cache (``frame_cache``) when it holds the video, else decoded (``decode``) and, with
a cache, written as they pass, the entry stored when the pass's owner commits it
(``FramePass.commit``), once the pass is whole; ``--check``'s, decoded and timed
(:func:`open_timed`); the Ray scan's count, demuxed packets only (:func:`open_packets`).

Either way the cutter gets ``(codes, expand, cut)`` per frame (``PassFrame``), the first two as
``decode.decode_codes`` yields them:
decoded frames carry the stream's code -> full-range map, cached ones are already full range
(``expand`` is ``decode.full_range``, the identity). Expansion is per pixel, so the cutter's samples are the same.

How frames are decoded (kept rows, scale, threads, shortcut) is this stage's
:class:`DecodeSettings`; where windows lie, and so how many frames a pass reads, is
``windows.WindowSettings``; both together name a frame-cache entry (:func:`entry_settings`).
"""
from __future__ import annotations

import contextlib
import itertools
import math
from dataclasses import asdict, dataclass
from typing import Callable, Iterator, NamedTuple, Optional, Tuple

import numpy as np

from v2v_server.checks import check_choice, check_int
from v2v_server.frames.decode import (DECODE_FAST, DecodedFrame, VideoInfo, decode_codes, decode_frames, full_range,
                                      open_video)
from v2v_server.frames.frame_cache import CachedVideo, CorruptEntry, EntryWriter, FrameCache, entry_name_settings
from v2v_server.frames.pass_record import PassRecord
from v2v_server.sources.segments import split_segment
from v2v_server.frames.shots import DETECTOR_VERSION, ShotDetector
from v2v_server.frames.windows import WindowSettings
from v2v_server.settings import setting

Frame = Tuple[np.ndarray, Callable[[np.ndarray], np.ndarray]]

#: Largest frame_height (8K UHD).
MAX_FRAME_HEIGHT = 4320


@dataclass(frozen=True)
class DecodeSettings:
    """How a pass decodes a video's frames, wherever its windows lie. This class declares its
    keys once (default, help, checks); the sample recipe (``v2v_server.samples.recipe.SampleRecipe``)
    composes it.

    Attributes:
        keep_top_fraction: share of a displayed frame's height kept from the top, in (0, 1].
        frame_height: scale decoded frames to this height, pixels (0 = as decoded, at most
            ``MAX_FRAME_HEIGHT``).
        decode_threads: FFmpeg threads per pass (>= 1).
        decode_fast: the decoder shortcut, ``decode.DECODE_FAST``.

    Raises:
        ValueError: naming the field, for a value out of its range.
    """

    keep_top_fraction: float = setting(0.54, help="fraction of each frame's height, from the top, that crops come "
                                                  "from (WebVid's watermark; 1.0 for clips without one)")
    frame_height: int = setting(0, help="scale every decoded frame to this height in pixels (width keeps the aspect "
                                        "ratio; OpenCV INTER_AREA on full-range luma) before the kept region, the "
                                        "frame cache and the crops; 0 = frames as decoded (docs/frame_scale.md)")
    decode_threads: int = setting(1, help="FFmpeg decoding threads per worker")
    decode_fast: str = setting("off", help="skip H.264's deblocking filter on some frames: off | noref | bidir | all "
                                           "(faster decoding, measured error: docs/decode_fast.md)",
                               choices=tuple(DECODE_FAST))

    def __post_init__(self):
        if not isinstance(self.keep_top_fraction, (int, float)) or isinstance(self.keep_top_fraction, bool) \
                or not (0 < self.keep_top_fraction <= 1):
            raise ValueError(f"keep_top_fraction must be in (0, 1], got {self.keep_top_fraction!r}")
        check_int("frame_height", self.frame_height, 0, MAX_FRAME_HEIGHT, "pixels; 0 = no scaling")
        check_int("decode_threads", self.decode_threads, 1)
        check_choice("decode_fast", self.decode_fast, tuple(DECODE_FAST))

    def kept_rows(self, height: int) -> int:
        """Rows kept from the top of a displayed frame of ``height`` pixels (:func:`kept_rows`)."""
        return kept_rows(self.keep_top_fraction, height)


def entry_settings(decode: DecodeSettings, windows: WindowSettings) -> dict:
    """What, with the corpus and the video, names a frame-cache entry: the entry format's version
    and the key of what a pass decoding as ``decode`` over ``windows`` reads
    (``pass_record.PassRecord.key``: decoder, scale, rows kept, window layout, detector and
    motion versions). With ``shot_cuts: avoid`` the entry holds the frames up to the last window
    and the cuts the detector found; with ``static_windows: skip``, the frames of the windows
    that replace static ones."""
    return entry_name_settings(PassRecord.of(decode, windows).key)


class PassFrame(NamedTuple):
    """One frame of a pass: ``codes`` and ``expand`` as ``decode.decode_codes`` yields them
    (``codes`` None for a frame counted from its packet, not decoded), ``cut``: it starts a
    new shot (False without detection), and ``size``: the ``(height, width)`` in pixels a
    failure names when the frame's size changes (``--check``'s: the displayed height,
    ``decode.DecodedFrame.shown_height``; None: the codes' own shape)."""

    codes: Optional[np.ndarray]
    expand: Optional[Callable[[np.ndarray], np.ndarray]]
    cut: bool = False
    size: Optional[Tuple[int, int]] = None


class FramePass:
    """A video opened for one pass, built once with its frames (``replayed``, ``decoded``, or
    any iterator of :class:`PassFrame`).

    The pass ends in one of three ways: its frames run out, or the consumer says :meth:`end`
    (it has what it needs): the pass is whole, and its owner stores the entry it wrote with
    :meth:`commit`; or it is closed (:meth:`close`) without a commit, which drops the entry (a
    decoding error, a consumer that stopped early: nothing partial is stored).

    Attributes:
        info: the stream's facts (``decode.VideoInfo``).
        declared: the container's frame count, 0 when it gives none.
        frames: an iterator of :class:`PassFrame`, at most ``limit_of(declared)`` of them
            (``open_frames``); with shot detection each says whether it starts a shot (a
            replayed pass gives the cuts stored with its entry).
        cached: replayed from the frame cache.
        writer: storing the frames into the frame cache as they pass (full range; None when
            replayed or the cache is off); ``EntryWriter.outcome`` says what became of the entry.
        detector: the shot detector scoring the frames (None without detection); the cuts it
            found are stored with the entry.
        times: presentation times (seconds, None for a frame without one) of the frames given
            so far, for a timed pass (:func:`open_timed`); None otherwise.
    """

    def __init__(self, info: VideoInfo, declared: int, frames: Iterator[PassFrame], cached: bool = False,
                 writer: Optional[EntryWriter] = None, detector: Optional[ShotDetector] = None,
                 times: Optional[list] = None):
        self.info, self.declared, self.cached, self.writer, self.detector = info, declared, cached, writer, detector
        self.times = times
        self._source = frames
        self._state = "reading"  # -> "whole" (ran out, or ended) -> "committed"; "closed" from any
        self.frames: Iterator[PassFrame] = self._passed(frames)

    @classmethod
    def replayed(cls, info: VideoInfo, declared: int, cache: FrameCache, name: str, entry: CachedVideo, limit: int,
                 redecode: Callable[[int], Iterator[Frame]], cuts: frozenset) -> "FramePass":
        """A pass over the first ``limit`` frames of the frame-cache entry ``entry`` (named
        ``name``; ``cuts``: the frames that start a shot); from its first bad frame on
        (truncated, bit-flipped) the entry is removed, :attr:`damaged` set, and the rest
        decoded by ``redecode(first_frame)``."""
        return cls(info, declared, _Replay(cache, name, entry, limit, redecode, cuts), True)

    @classmethod
    def decoded(cls, info: VideoInfo, declared: int, frames: Iterator[Frame], limit: int,
                writer: Optional[EntryWriter], detect: bool) -> "FramePass":
        """A pass over the first ``limit`` decoded ``frames``, each stored by ``writer`` (at
        full range) as it passes and, with ``detect``, scored for a cut before it is given
        (``shots.ShotDetector``)."""
        detector = ShotDetector() if detect else None
        return cls(info, declared, _detected(frames, limit, detector), False, writer, detector)

    @property
    def damaged(self) -> bool:
        """A replayed entry was found damaged, removed, and the rest of the video decoded (not stored)."""
        return isinstance(self._source, _Replay) and self._source.damaged

    @property
    def whole(self) -> bool:
        """Whether the pass is whole (its frames ran out, or :meth:`end`), committed or not."""
        return self._state in ("whole", "committed")

    @property
    def storing(self) -> bool:
        """Whether the pass is still storing the video: then it must read ``frames`` to their end
        (or :meth:`end`) and be committed for the entry to be stored (stopping early drops it)."""
        return self.writer is not None and self.writer.writing

    def end(self) -> None:
        """The consumer has what it needs: the frames given so far are the whole pass. The
        frames are closed; the entry being stored waits for :meth:`commit`. Call it between
        frames, not while ``frames`` is running."""
        if self._state == "reading":
            self._state = "whole"
        self._stop()

    def commit(self) -> None:
        """Store the entry this pass wrote in the frame cache, with the shot cuts found (nothing
        to do without one): the step that makes an entry, taken by the pass's owner once the
        pass is whole (its frames ran out, or :meth:`end`). Once per pass.

        Raises:
            RuntimeError: the pass is not whole (it is still reading, was closed, or was
                committed already): a partial entry is never stored.
        """
        if self._state != "whole":
            raise RuntimeError(f"cannot commit the frame-cache entry of a pass that is {self._state}: only a whole "
                               "pass (its frames run out, or end()) is stored")
        self._state = "committed"
        if self.writer is not None:
            self.writer.finish(None if self.detector is None else
                               {"shots": {"detector": DETECTOR_VERSION, "cuts": self.detector.cuts}})

    def close(self) -> None:
        """Finish with the pass: the frames are closed, and an entry not committed is dropped
        (counted as incomplete, ``EntryWriter.abort``)."""
        self._stop()
        if self._state != "committed":
            self._state = "closed"
            if self.writer is not None:
                self.writer.abort(incomplete=True)

    def _stop(self) -> None:
        """Close the frames and what they are read from (a decoder, an entry's replay)."""
        self.frames.close()
        close = getattr(self._source, "close", None)  # any iterator may be given: a generator has close()
        if close is not None:
            close()

    def _passed(self, frames: Iterator[PassFrame]) -> Iterator[PassFrame]:
        """``frames``, each stored by :attr:`writer` (at full range) before it is given; the pass
        is whole once they run out."""
        writer = self.writer
        try:
            for f in frames:
                if writer is not None:
                    writer.add(f.expand(f.codes))
                yield f
            if self._state == "reading":
                self._state = "whole"
        finally:  # stopped early or failed: the source stops with it
            close = getattr(frames, "close", None)
            if close is not None:
                close()


def _detected(frames: Iterator[Frame], limit: int, detector: Optional[ShotDetector]) -> Iterator[PassFrame]:
    """The first ``limit`` of ``frames`` as :class:`PassFrame`, each scored by ``detector`` for a cut
    (no cuts without one)."""
    for codes, expand in itertools.islice(frames, limit):
        yield PassFrame(codes, expand, detector is not None and detector.score(codes, expand))


class _Replay:
    """The first ``limit`` frames of the frame-cache entry ``entry`` (named ``name`` in ``cache``)
    as :class:`PassFrame` (full range; ``cuts``: the frames that start a shot); from its first
    bad frame on the entry is removed, :attr:`damaged` set, and the rest decoded by
    ``redecode(first_frame)``. An iterator; :meth:`close` stops it."""

    def __init__(self, cache: FrameCache, name: str, entry: CachedVideo, limit: int,
                 redecode: Callable[[int], Iterator[Frame]], cuts: frozenset):
        self.damaged = False
        self._frames = self._read(cache, name, entry, limit, redecode, cuts)

    def __iter__(self) -> "_Replay":
        return self

    def __next__(self) -> PassFrame:
        return next(self._frames)

    def close(self) -> None:
        self._frames.close()

    def _read(self, cache: FrameCache, name: str, entry: CachedVideo, limit: int,
              redecode: Callable[[int], Iterator[Frame]], cuts: frozenset) -> Iterator[PassFrame]:
        i = 0
        try:
            for a in entry.read():
                if i >= limit:
                    return
                yield PassFrame(a, full_range, i in cuts)
                i += 1
            return
        except CorruptEntry as e:
            cache.corrupt(name, f"{e}; frames {i}.. decoded")
            self.damaged = True
        for j, (codes, expand) in enumerate(redecode(i), i):
            yield PassFrame(codes, expand, j in cuts)


def kept_rows(keep_top_fraction: float, height: int) -> int:
    """Rows kept from the top of a displayed frame of ``height`` pixels: ``floor(height x
    keep_top_fraction)``, at least 1 (the WebVid recipe keeps the top 54 %, above the watermark)."""
    return max(1, int(math.floor(height * keep_top_fraction)))


def corpus_key(source) -> str:
    """The corpus as an entry name's part: the source's own name for it (``VideoSource.location``:
    the URL, or the folder's absolute path)."""
    return source.location


def lookup_entry(cache: FrameCache, source, rel: str, settings: dict
                 ) -> Tuple[str, Optional[str], Optional[CachedVideo]]:
    """Video ``rel`` of ``source`` in the host's frame cache ``cache``: the entry's name (by the corpus,
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
def open_frames(source, rel: str, decode: DecodeSettings, windows: WindowSettings,
                frame_cache: Optional[FrameCache] = None) -> Iterator[FramePass]:
    """The frames of video ``rel`` of ``source`` (a ``sources.source.VideoSource``) that a pass
    over ``windows`` reads (``WindowSettings.frame_limit`` of the declared count), from the host's
    ``frame_cache`` (``HostCaches.frame_cache``, None when off; the entry named by :func:`entry_settings`) or
    decoded as ``decode`` says (``decode.open_video``, ``decode.decode_codes``: scaled to
    ``frame_height`` rows when not 0, the kept rows of that). With ``shot_cuts: avoid`` the shot
    cuts are found (``shots.ShotDetector`` on the kept rows; stored with the entry, so a replay
    finds none again).

    The block that opens the pass owns the entry it stores: once the pass is whole (its frames
    run out, or ``FramePass.end``) the block calls ``FramePass.commit`` to store it; leaving the
    block without that (an error, a consumer that stopped early) drops it.

    Raises:
        VideoError: the video cannot be opened or decoded (as ``source.open``, ``open_video``).
    """
    rows, threads, fast, height = decode.kept_rows, decode.decode_threads, decode.decode_fast, decode.frame_height
    limit_of, detect = windows.frame_limit, windows.avoid_cuts
    cache = frame_cache
    name = identity = None
    segment = split_segment(rel)[1]  # a segment: its time range of the video
    if cache is not None:
        name, identity, entry = lookup_entry(cache, source, rel, entry_settings(decode, windows))
        if entry is not None:
            declared = int(entry.meta["declared"])
            limit = limit_of(declared)

            def redecode(start: int) -> Iterator[Frame]:
                with source.open(rel) as path:
                    container, stream, _ = open_video(path, threads, fast)
                    yield from itertools.islice(decode_codes(container, stream, rows, height, segment=segment), start,
                                                limit)

            # an entry written with detection holds its cuts (the settings name the detector)
            cuts = frozenset(int(c) for c in entry.meta.get("shots", {}).get("cuts", ())) if detect else frozenset()
            fp = FramePass.replayed(VideoInfo(**entry.meta["info"]), declared, cache, name, entry, limit, redecode,
                                    cuts)
            try:
                yield fp
            finally:
                fp.close()
                entry.close()
            return
    with source.open(rel) as path:
        container, stream, info = open_video(path, threads, fast)
        declared = 0 if segment else int(getattr(stream, "frames", 0) or 0)  # a segment: unknown
        writer = None
        if cache is not None and identity is not None:  # a racy identity is never stored
            writer = cache.writer(name, identity, {"video": rel, "info": asdict(info), "declared": declared},
                                  windows.window_stride)
        fp = FramePass.decoded(info, declared, decode_codes(container, stream, rows, height, segment=segment),
                               limit_of(declared), writer, detect)
        try:
            yield fp
        finally:
            fp.close()  # an entry the owner did not commit is dropped


@contextlib.contextmanager
def open_timed(source, rel: str, decode: DecodeSettings, detect: bool = True) -> Iterator[FramePass]:
    """The frames of video ``rel`` of ``source`` as ``--check`` reads them: decoded (never from the
    frame cache, which keeps no times), each with its presentation time (``FramePass.times``) and
    named, when its size changes, by the displayed frame's (``PassFrame.size``: the displayed
    height, ``decode.DecodedFrame.shown_height``); the kept rows and frame scale of ``decode``,
    the decoder's defaults otherwise; with ``detect``, scored for shot cuts (``shots.ShotDetector``).
    All of them: the container's frame count is not taken on trust.

    Raises:
        VideoError: the video cannot be opened or decoded (as ``source.open``, ``open_video``).
    """
    with source.open(rel) as path:
        container, stream, info = open_video(path)
        times: list = []
        decoded = decode_frames(container, stream, decode.kept_rows, decode.frame_height, split_segment(rel)[1])
        fp = FramePass(info, 0, _timed(decoded, ShotDetector() if detect else None, times), times=times)
        try:
            yield fp
        finally:
            fp.close()


def _timed(decoded: Iterator[DecodedFrame], detector: Optional[ShotDetector], times: list) -> Iterator[PassFrame]:
    """The pass frames of ``decoded``, scored by ``detector`` (no cuts without one), each named by
    its displayed size; each frame's presentation time is appended to ``times``."""
    for d in decoded:
        times.append(d.time)
        cut = detector is not None and detector.score(d.codes, d.expand)
        yield PassFrame(d.codes, d.expand, cut, (d.shown_height, d.codes.shape[1]))


@contextlib.contextmanager
def open_packets(source, rel: str) -> Iterator[FramePass]:
    """The frames of video ``rel`` of ``source`` counted from its video packets, demuxed and not
    decoded (about 1/50 of a decode pass): a :class:`PassFrame` without codes per packet that
    holds data, all of them. Packets before a demuxing error count; the error stops the pass only
    when no packet came (then it is the video's).

    Raises:
        VideoError: the video cannot be opened (as ``source.open``, ``open_video``).
    """
    with source.open(rel) as path:
        container, stream, info = open_video(path)
        fp = FramePass(info, 0, _packets(container, stream))
        try:
            yield fp
        finally:
            fp.close()
            container.close()


def _packets(container, stream) -> Iterator[PassFrame]:
    """A codeless :class:`PassFrame` per video packet of ``container`` that holds data (see
    :func:`open_packets` for a demuxing error)."""
    counted = 0
    try:
        for packet in container.demux(stream):
            if packet.size:
                counted += 1
                yield PassFrame(None, None)
    except Exception:  # av raises many error types; the packets demuxed so far are the stream's
        if counted == 0:
            raise

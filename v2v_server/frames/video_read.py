"""The one way into a video: :func:`read_video` opens a pass over one video of a source for every
reader (the sample pass, ``--check``, ``--warm-cache``, the Ray scan), with the host's caches and
an error policy passed in, and ends it the same way for all of them.

A read takes what a pass reads (``pass_record.PassRecord``: how frames are decoded, where windows
lie, whether shot cuts are scored), the host's caches beside the source (``HostCaches``: the frame
cache and the corpus index) and a *handler*, as WebDataset passes its handler to a pipeline: an
exception raised while the video is read, or by the reader's own work on its frames, goes to the
handler, which raises to stop the reader or returns to make it the video's verdict
(:func:`as_verdict`, the default; :func:`reraise`). A reader asks for the part of a pass it needs:

* ``"frames"``: the sample pass's frames (``frame_pass.open_frames``), replayed from the frame
  cache when it holds the video, else decoded and stored; the entry is committed once the window
  pass is whole. A whole pass that scored shot cuts is recorded in the corpus index (unless an
  entry holds already), so the server's next start knows the video's windows without ``--check``;
  it does not time frames, so its entry says ``frame_timing: False``.
* ``"timed"``: ``--check``'s frames (``frame_pass.open_timed``): decoded and timed, a variable
  frame rate reported; answered from the corpus index while the video's identity holds and the
  entry was timed, else recorded there once read without an error.
* ``"packets"``: the video's packets counted, nothing decoded (``frame_pass.open_packets``), for
  a count of windows that do not depend on the frames (the Ray scan); nothing is cached.

Every part goes through the same window pass (``window_pass.WindowPass``), so a video's windows,
its record (``window_pass.VideoPass``) and its verdict (``corpus_index.Verdict``) are the same
whoever read it.
"""
from __future__ import annotations

import dataclasses
from typing import Callable, Iterator, Optional, TypeVar

from v2v_server.frames.corpus_index import Verdict, layout_key
from v2v_server.frames.decode import frame_intervals
from v2v_server.frames.frame_pass import FramePass, open_frames, open_packets, open_timed
from v2v_server.frames.host_caches import HostCaches
from v2v_server.frames.pass_record import PassRecord
from v2v_server.frames.window_pass import VideoPass, WindowFrame, WindowPass
from v2v_server.frames.windows import WindowSettings
from v2v_server.sources.errors import VideoError
from v2v_server.sources.source import VideoSource

T = TypeVar("T")

#: The parts of a pass a reader can ask for (module docstring).
PARTS = ("frames", "timed", "packets")

#: Spread of a file's frame intervals (longest less shortest), as a share of the median one, above
#: which a timed read reports a variable frame rate (timestamp rounding stays far below it).
VFR_SPREAD = 0.1


def as_verdict(error: Exception) -> None:
    """The default error policy: a failure reading one video is that video's verdict (the read
    keeps it as ``VideoRead.error``); one bad file never stops the reader."""


def reraise(error: Exception) -> None:
    """The error policy that stops the reader: the failure propagates."""
    raise error


class VideoRead:
    """One read of video ``rel`` of ``source`` (built by :func:`read_video`; see the module
    docstring).

    Use it as a context manager around the reader's work: iterate :attr:`frames` (or, from a
    generator of the reader's own, :meth:`run`); leaving the block ends the read (:meth:`finish`).
    An exception raised in the block or by the frames goes to the handler.

    Attributes:
        source, rel: the video.
        reads: what the pass reads.
        caches: the host's caches (None: none; nothing is cached or recorded).
        part: the part of the pass read (:data:`PARTS`).
        window_pass: the window pass over the frames (``WindowPass``: its shot, motions, record).
        frames: the window pass's frames (``window_pass.WindowFrame``), opened at the first one
            asked for; none when :attr:`known`.
        frame_pass: the pass's frames once opened (``frame_pass.FramePass``: cached, damaged,
            its cache writer), else None.
        known: the verdict the corpus index holds (a timed read whose video's identity holds):
            nothing is read.
        error: what stopped the read (kept by the handler), or None.
    """

    def __init__(self, source: VideoSource, rel: str, reads: PassRecord, caches: Optional[HostCaches] = None,
                 part: str = "frames", handler: Callable[[Exception], None] = as_verdict):
        if part not in PARTS:
            raise ValueError(f"part must be one of {list(PARTS)}, got {part!r}")
        self.source, self.rel, self.reads, self.caches, self.part, self.handler = source, rel, reads, caches, part, handler
        self.window_pass = WindowPass(reads)
        self.frame_pass: Optional[FramePass] = None
        self.error: Optional[Exception] = None
        self.known: Optional[Verdict] = None
        self._identity: Optional[str] = None  # the video's identity before a timed read: what its verdict is of
        self._finished = False
        index = self._index()
        if part == "timed" and index is not None:
            self._identity = _identity(source, rel)
            known = index.lookup(source.where(rel), self._identity, self._layout)
            if known is not None and known.frame_timing:  # a sample pass's entry lacks the timing
                self.known = dataclasses.replace(known, path=rel)
        self.frames: Iterator[WindowFrame] = self._frames()

    @property
    def _layout(self) -> str:
        """The corpus index's key of this read's layout (``corpus_index.layout_key``)."""
        return layout_key(self.reads.windows, self.reads.decode)

    def _index(self):
        return self.caches.corpus_index() if self.caches is not None else None

    def _open(self):
        """The context manager of the frames of :attr:`part`."""
        if self.part == "frames":
            frame_cache = self.caches.frame_cache if self.caches is not None else None
            return open_frames(self.source, self.rel, self.reads.decode, self.reads.windows, frame_cache)
        if self.part == "timed":
            return open_timed(self.source, self.rel, self.reads.decode, self.reads.scores_cuts)
        return open_packets(self.source, self.rel)

    def _frames(self) -> Iterator[WindowFrame]:
        if self.known is not None:
            return
        with self._open() as fp:
            self.frame_pass = fp
            yield from self.window_pass.over(fp)
            fp.commit()  # the window pass is whole: the entry it wrote (if any) is stored

    def __enter__(self) -> "VideoRead":
        return self

    def __exit__(self, kind, error, tb) -> bool:
        if isinstance(error, Exception):
            self.finish(error)  # the handler raises, or keeps it as the verdict
            return True
        if error is None:
            self.finish()
        else:  # Ctrl-C, a process told to exit, a generator closed: nothing is finished or recorded
            self.frames.close()
        return False

    def run(self, items: Optional[Iterator[T]] = None) -> Iterator[T]:
        """``items`` (default :attr:`frames`), a generator of the reader's own over :attr:`frames`,
        then :meth:`finish`: an exception it raises (decoding, or the reader's work) goes to the
        handler and, handled, ends it. Closed early, the read ends without a verdict or record."""
        try:
            try:
                yield from (self.frames if items is None else items)
            except Exception as e:  # the handler decides: raised on, or the video's verdict
                self.finish(e)
                return
            self.finish()
        finally:
            self.frames.close()

    def finish(self, error: Optional[Exception] = None) -> None:
        """End the read (once; later calls only add an error): ``error`` goes to the handler,
        which raises it on or keeps it as :attr:`error`; the frames are closed (an entry not
        committed is dropped); a whole read without an error is recorded in the corpus index
        (module docstring)."""
        if error is not None and self.error is None:
            self.error = error
        try:
            if error is not None:
                self.handler(error)
        finally:
            if not self._finished:
                self._finished = True
                self.frames.close()
                self._record()

    def _record(self) -> None:
        """Keep what a whole read found in the host's corpus index (module docstring); an index
        that cannot be written is one warning, the read is unaffected."""
        index = self._index()
        fp = self.frame_pass
        if index is None or self.error is not None or fp is None or not fp.whole or self.part == "packets":
            return
        where = self.source.where(self.rel)
        if self.part == "timed":
            index.record(where, self._identity, self._layout, self.verdict())
            return
        if not self.reads.scores_cuts:  # an entry holds the cuts, as --check's do
            return
        identity = self.source.listed_identity(self.rel)
        if identity is not None and index.lookup(where, identity, self._layout) is None:
            index.record(where, identity, self._layout, dataclasses.replace(self.verdict(), frame_timing=False))

    @property
    def storing(self) -> bool:
        """Whether the read is still storing the video in the frame cache (``FramePass.storing``):
        a reader that stops early then drops the entry."""
        return self.frame_pass is not None and self.frame_pass.storing

    def record(self) -> VideoPass:
        """What the read found so far (``window_pass.VideoPass``), its :attr:`error` included."""
        return self.window_pass.record(self.error)

    def verdict(self) -> Verdict:
        """The video's verdict (``corpus_index.Verdict``): :attr:`known`, else made from
        :meth:`record` (windows before a failure still count); a timed read says whether its
        frames were unevenly spaced."""
        if self.known is not None:
            return self.known
        out = pass_verdict(self.reads.windows, self.rel, self.record())
        times = self.frame_pass.times if self.frame_pass is not None else None
        gaps = frame_intervals(times) if times and self.error is None else None
        if gaps and gaps[2] - gaps[0] > VFR_SPREAD * gaps[1]:
            out = dataclasses.replace(out, variable_rate=(
                f"variable frame rate: frame intervals {gaps[0] * 1e3:.3g}-{gaps[2] * 1e3:.3g} ms, taken as if "
                f"evenly spaced at the average {self.frame_pass.info.fps:.3g} fps"))
        return out


def read_video(source: VideoSource, rel: str, reads: PassRecord, caches: Optional[HostCaches] = None, *,
               part: str = "frames", handler: Callable[[Exception], None] = as_verdict) -> VideoRead:
    """A read of video ``rel`` of ``source`` (a :class:`VideoRead`, a context manager): ``part`` of
    the pass ``reads`` describes (:data:`PARTS`), through the host's ``caches`` (None: none),
    failures handled by ``handler`` (:func:`as_verdict`: the video's verdict; :func:`reraise`).
    Nothing is opened until its first frame is asked for.

    Raises:
        ValueError: an unknown ``part``.
    """
    return VideoRead(source, rel, reads, caches, part, handler)


def pass_verdict(windows: WindowSettings, rel: str, record: VideoPass) -> Verdict:
    """The verdict of the video at ``rel`` from a window pass's ``record``
    (``window_pass.VideoPass``), frame timing aside (``cause``: the reason's code,
    ``window_pass.judged``; windows before a failure still count)."""
    count, failed, cause, reason = record.judged(windows)
    return Verdict(path=rel, usable=count > 0, windows=count, frames=record.frames, reason=reason or "", cause=cause,
                   cuts=tuple(record.cuts), dropped=record.dropped, stream=record.stream(),
                   failed_windows=tuple(failed), static=record.static, more=record.complete)


def _identity(source: VideoSource, rel: str) -> Optional[str]:
    """The identity of the video at ``rel`` now (``VideoSource.identity``), None when it is
    missing or unreadable (reading it says why)."""
    try:
        return source.identity(rel)
    except VideoError:
        return None

"""The window pass: what one pass over a video's frames makes of its windows, and what the video
is worth. The one rule that every reader of a video applies, through the one way into a video
(``video_read.read_video``): the sample pass (``samples.make.video_samples``), ``v2v-serve
--check`` (``check.check_video``), ``--warm-cache`` (``ops.warm``) and the Ray scan
(``ray_data.count_windows``).

Windows lie where ``shots.WindowLayout`` places them, fed with each frame's shot cut. A cut inside
the window in progress drops it (its index goes to the next window, so any failure recorded for it
is forgotten); a frame whose size differs from its window's first frame fails that window (the
first such frame names the reason). The pass stops reading once every window the layout allows is
complete.

:meth:`WindowPass.over` is the generator: it yields every frame read with what it does to the
windows (:class:`WindowFrame`). :meth:`WindowPass.record` gives, at the end or wherever the reader
stopped, the frozen per-video record (:class:`VideoPass`: frames, fps, cuts, windows, the layout
they follow, and the verdict).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Dict, Iterator, List, Mapping, NamedTuple, Optional, Tuple

import numpy as np

from v2v_server.sources.errors import VideoError
from v2v_server.frames.frame_pass import FramePass
from v2v_server.frames.motion import STATIC_MOTION, MotionMeter
from v2v_server.frames.pass_record import PassRecord
from v2v_server.frames.windows import WindowSettings

#: Words of the reason a file with too few frames for one window gets.
SHORT_CLIP = "shorter than one window of"


def error_reason(error: BaseException) -> str:
    """What stopped a reading, in a verdict's words: a ``VideoError`` gives its message, anything
    else ``"TypeName: message"``."""
    return str(error) if isinstance(error, VideoError) else f"{type(error).__name__}: {error}"


def verdict(w: WindowSettings, frames: int, failed: Optional[Mapping[int, str]] = None,
            error: Optional[BaseException] = None, windows: Optional[int] = None,
            cuts: int = 0, static: int = 0) -> Tuple[int, List[int], Optional[str]]:
    """What a file is worth, from what reading it found.

    Args:
        frames: frames read (decoded, or counted from packets) before the end or ``error``.
        failed: windows that cannot be made -> why (e.g. the frame size changes inside one).
        error: what stopped the reading, if anything: a ``VideoError`` gives its message,
            anything else ``"TypeName: message"``.
        windows: complete windows the reading found (``shots.WindowLayout``); None: as many as
            ``frames`` holds (``w.windows_in``, the layout without cuts).
        cuts: shot cuts the reading found (named when they leave no window).
        static: windows given up as static (named when they leave none).

    Returns:
        ``(windows, failed_windows, reason)``: samples per epoch (the complete windows less the
        failed ones), the failed windows among them (sorted), and why the file gives none or
        fewer (None when nothing is wrong): the failed windows' reasons, else the error's, else
        too few frames.
    """
    windows, bad, _, reason = judged(w, frames, failed, error, windows, cuts, static)
    return windows, bad, reason


def judged(w: WindowSettings, frames: int, failed: Optional[Mapping[int, str]] = None,
           error: Optional[BaseException] = None, windows: Optional[int] = None,
           cuts: int = 0, static: int = 0) -> Tuple[int, List[int], str, Optional[str]]:
    """:func:`verdict` with its reason's cause as a code: ``(windows, failed_windows, cause,
    reason)``, ``cause`` one of ``worker_messages.CAUSES`` (``"failed"``: windows that cannot be
    made; ``"error"``: what stopped the reading; ``"static"``: every window static; ``"short"``:
    too few frames for a window, or every shot too short, a property of the clip, not a fault;
    ``""``: nothing is wrong)."""
    failed = failed or {}
    whole = w.windows_in(frames) if windows is None else windows
    bad = sorted(k for k in failed if k < whole)
    windows = whole - len(bad)
    if bad:
        cause, reason = "failed", "; ".join(failed[k] for k in bad)
    elif error is not None:
        cause, reason = "error", error_reason(error)
    elif windows == 0 and static:
        cause, reason = "static", (f"{frames} frames: every window is static ({static} skipped: motion below "
                                   f"{STATIC_MOTION} log-intensity a frame, static_windows: skip)")
    elif windows == 0 and cuts and w.avoid_cuts:
        cause, reason = "short", (f"{frames} frames, {cuts} shot cut(s): every shot is {SHORT_CLIP} "
                                  f"{w.frames_per_sample} frames")
    elif windows == 0:
        cause, reason = "short", f"{frames} frames, {SHORT_CLIP} {w.frames_per_sample} frames"
    else:
        cause, reason = "", None
    return windows, bad, cause, reason


class WindowFrame(NamedTuple):
    """One frame of a window pass and what it does to the windows, in this order: ``drops``
    (the window in progress that a cut at this frame abandons), ``fails`` (the window that this
    frame, of another size, fails: the one it ends or continues), ``ends`` (the window this frame
    completes, as its last frame), ``starts`` (the window this frame starts); each an index or
    None; ``skips``: the window this frame would complete, given up as static. ``offset``: the frame's place in the window in progress after it (0 where it starts
    one; None when none is). ``index``: the frame's number from 0; ``codes``, ``expand``: as
    ``frame_pass.PassFrame``. A tuple: one is made per frame read."""

    index: int
    codes: Optional[np.ndarray]
    expand: Optional[Callable[[np.ndarray], np.ndarray]]
    drops: Optional[int]
    fails: Optional[int]
    ends: Optional[int]
    starts: Optional[int]
    offset: Optional[int]
    skips: Optional[int] = None


@dataclass(frozen=True, kw_only=True)
class StreamFacts:
    """A video stream's facts as a pass opened it: ``width``, ``height`` (int, pixels),
    ``codec``, ``pix_fmt`` (FFmpeg's names) and ``fps`` (float, Hz, as the container gives it:
    29.97... stays 29.97...)."""

    width: int
    height: int
    codec: str
    pix_fmt: str
    fps: float

    def text(self) -> str:
        """``"WxH codec pix_fmt FPS fps"``, the frame rate to 3 digits: how ``--check`` prints
        it (for people; a reader takes the fields)."""
        return f"{self.width}x{self.height} {self.codec} {self.pix_fmt} {self.fps:.3g} fps"


@dataclass(frozen=True, kw_only=True)
class VideoPass:
    """What one window pass over a video found: the record its readers report from (a worker's
    ``Done``, ``--check``'s line, the Ray engine's verdict) and a corpus index can keep.

    Attributes:
        frames: frames read.
        width, height: the stream's frame size, pixels (0 when it was not opened).
        fps: its frame rate, Hz (0.0 when it was not opened).
        codec, pix_fmt: the stream's codec and pixel format names ('' when it was not opened).
        motions: each complete window's motion, in window order (``motion``: the mean change of
            log intensity per frame pair; 0.0 where frames were counted, not decoded).
        static: windows given up as static (``static_windows: skip``).
        layout: the key of what the pass read (``pass_record.PassRecord.key``: decoding, window
            layout, detector and motion versions; the corpus index's layout key).
        cuts: the frames that start a shot, in order (none without detection).
        starts: the first frame of each complete window, failed ones included, in window order.
        dropped: windows a cut fell inside.
        failed: window -> why it cannot be made (a frame of another size inside it).
        complete: every window the layout allows is complete: the pass stopped there (the video
            may hold more frames).
        error: what stopped the pass, or None.
    """

    frames: int = 0
    width: int = 0
    height: int = 0
    fps: float = 0.0
    layout: str = ""
    cuts: Tuple[int, ...] = ()
    starts: Tuple[int, ...] = ()
    dropped: int = 0
    failed: Mapping[int, str] = field(default_factory=dict)
    complete: bool = False
    error: Optional[BaseException] = None
    codec: str = ""
    pix_fmt: str = ""
    motions: Tuple[float, ...] = ()
    static: int = 0

    @property
    def windows(self) -> int:
        """Complete windows, failed ones included."""
        return len(self.starts)

    def stream(self) -> Optional[StreamFacts]:
        """The stream's facts (:class:`StreamFacts`); None when the stream was not opened."""
        if not self.codec:
            return None
        return StreamFacts(width=self.width, height=self.height, codec=self.codec, pix_fmt=self.pix_fmt, fps=self.fps)

    def verdict(self, w: WindowSettings) -> Tuple[int, List[int], Optional[str]]:
        """:func:`verdict` of what the pass found, failed windows included (``--check``):
        ``(windows, failed_windows, reason)``; a failed window's reason names it."""
        windows, bad, _, reason = self.judged(w)
        return windows, bad, reason

    def judged(self, w: WindowSettings) -> Tuple[int, List[int], str, Optional[str]]:
        """:meth:`verdict` with its reason's cause as a code (:func:`judged`): ``(windows,
        failed_windows, cause, reason)``."""
        failed = {k: f"window {k}: {why}" for k, why in self.failed.items()}
        return judged(w, self.frames, failed, self.error, self.windows, len(self.cuts), self.static)

    def to_dict(self) -> dict:
        """The record as JSON-safe values, as a corpus index keeps it: every attribute, ``failed``
        keyed by the window as a string, ``error`` as its reason (``verdict``'s words) or None."""
        d = {k: getattr(self, k) for k in ("frames", "width", "height", "fps", "codec", "pix_fmt", "layout", "dropped",
                                           "complete")}
        d.update(cuts=list(self.cuts), starts=list(self.starts), failed={str(k): v for k, v in self.failed.items()},
                 motions=list(self.motions), static=self.static,
                 error=None if self.error is None else error_reason(self.error))
        return d

    def reason(self, w: WindowSettings) -> Optional[str]:
        """Why the pass gave fewer windows than it should, failed windows aside (they are
        reported one by one): the error's reason, or too few frames; None when nothing is wrong."""
        return self.cause(w)[1]

    def cause(self, w: WindowSettings) -> Tuple[str, Optional[str]]:
        """:meth:`reason` with its cause as a code (:func:`judged`): ``(cause, reason)``."""
        return judged(w, self.frames, None, self.error, self.windows, len(self.cuts), self.static)[2:]


def frame_shape(codes: np.ndarray) -> Tuple[int, int]:
    """A frame's size as the windows compare it: its ``(rows, columns)``."""
    return codes.shape[0], codes.shape[1]


class WindowPass:
    """The windows of one pass over a video's frames (explicit state, no I/O of its own).

    Args:
        reads: what the pass reads (``pass_record.PassRecord``): its ``windows``
            (``windows.WindowSettings``: span, window count, shot cuts) lay the windows out, and
            the verdict names its key (``VideoPass.layout``).

    A frame's size, as compared and named in a failure, is its ``PassFrame.size`` when the
    decoder gave one (``--check``: the displayed height), else its codes' (:func:`frame_shape`).
    """

    def __init__(self, reads: PassRecord):
        self.settings, self.reads = reads.windows, reads
        self.layout = self.settings.layout()
        self.frame_pass: Optional[FramePass] = None  # the pass :meth:`over` reads
        self.info = None
        self.frames = 0
        self.cuts: List[int] = []
        self.starts: List[int] = []
        self.motions: List[float] = []  # each complete window's motion (``motion``: mean change per frame pair)
        self.failed: Dict[int, str] = {}
        self.current: Optional[int] = None  # first frame of the window in progress
        self.shape: Optional[Tuple[int, int]] = None  # its first frame's size

    @property
    def shot(self) -> Tuple[int, int]:
        """The shot at hand: its index in the video (the cuts before it) and its first frame."""
        return len(self.cuts), self.cuts[-1] if self.cuts else 0

    def over(self, fp: FramePass) -> Iterator[WindowFrame]:
        """Every frame of ``fp`` (a ``frame_pass.FramePass``) with what it does to the windows, laid
        out for its declared frame count (``WindowSettings.layout``); once every window is
        complete, ``fp.end()`` (the frames are closed: the pass is whole, and its owner may
        commit the entry it wrote, ``FramePass.commit``) and stop.

        Raises:
            what reading ``fp.frames`` raises (``VideoError``); :meth:`record` keeps what came before.
        """
        self.frame_pass, self.info = fp, fp.info
        layout = self.layout = self.settings.layout(fp.declared)
        meter, change = MotionMeter(), 0.0  # change: of the window in progress, summed over its frame pairs
        for i, f in enumerate(fp.frames):
            self.frames = i + 1
            if f.cut:
                self.cuts.append(i)
            step = meter.score(f.codes, f.expand)  # every frame: the next one is measured against it
            if layout.current is not None:
                change += step
            motion = change / layout.stride
            ev = layout.step(i, f.cut, motion < STATIC_MOTION)
            if ev.drops is not None or ev.skips is not None:
                self.failed.pop(ev.drops if ev.drops is not None else ev.skips, None)  # the index goes to the next window
            # the window this frame belongs to, other than one it starts: the one it ends, or the one in progress
            k = ev.ends if ev.ends is not None else layout.completed if ev.starts is None and layout.current is not None \
                else None
            size = None if f.codes is None else f.size or frame_shape(f.codes)
            fails = None
            if k is not None and size != self.shape and k not in self.failed:
                fails = k
                self.failed[k] = (f"frame size changed from {self.shape[1]}x{self.shape[0]} to "
                                  f"{size[1]}x{size[0]} at frame {i}")
            if ev.ends is not None:
                self.starts.append(self.current)
                self.motions.append(motion)
            if ev.starts is not None:
                self.shape = size
            if layout.current is None or ev.starts is not None:
                change = 0.0
            self.current = layout.current
            yield WindowFrame(i, f.codes, f.expand, ev.drops, fails, ev.ends, ev.starts,
                              None if layout.current is None else i - layout.current, ev.skips)
            if layout.done:  # every window is made: the rest of the video serves nothing
                fp.end()
                return

    def record(self, error: Optional[BaseException] = None) -> VideoPass:
        """What the pass found so far (``error``: what stopped it, if anything)."""
        info = self.info
        return VideoPass(frames=self.frames, width=info.width if info else 0, height=info.height if info else 0,
                         fps=float(info.fps) if info else 0.0, layout=self.reads.key, cuts=tuple(self.cuts),
                         starts=tuple(self.starts), dropped=self.layout.dropped, failed=dict(self.failed),
                         complete=self.layout.done, error=error, codec=info.codec if info else "",
                         pix_fmt=info.pix_fmt if info else "", motions=tuple(self.motions), static=self.layout.static)

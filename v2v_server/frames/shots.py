"""Shots: where a video cuts from one scene to another, and the windows that fit inside one shot.

An event camera never sees a cut, and no optical flow exists across one, so a sample must not
span one (docs/corpora.md). The decode pass that cuts samples finds the cuts from the luma it
already has (:class:`ShotDetector`, on 48x27 thumbnails with the camera's motion taken out), and
:class:`WindowLayout` places the windows: at each shot's first frame + k x ``stride`` while a
whole window fits before the shot ends (``shot_cuts: avoid``), or at k x ``stride`` whatever
they hold (``shot_cuts: off``, the authors' loader, HYLZ-2019/V2V ``data/v2v_datasets.py``).

The detector is causal (it decides on frame i when frame i arrives), so the cutter needs no
look-ahead buffer; a false cut only loses a window, a missed one makes a bad sample, so it leans
to cutting. Measured on labelled transitions (a real edited video, hard cuts, fades through black,
dissolves, fast pans, a flash) beside TransNetV2: ``python -m bench.shots`` (docs/shots.md).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Callable, List, Optional, Tuple

import numba
import numpy as np

#: ``shot_cuts`` values: ``avoid`` places windows inside shots; ``off`` ignores cuts.
SHOT_CUTS = ("avoid", "off")
#: Thumbnail a frame is scored on, (rows, columns): TransNetV2's and Panda-70M's 48x27 (block
#: means of the kept region).
THUMB = (27, 48)
#: Largest camera shift between two frames the score looks through, in thumbnail pixels (x; half
#: of it in y): 8 of 48 columns is 107 px a frame at 640 columns.
SHIFT = 8
#: What names the detector in a frame-cache entry: a cached entry's cuts are reused only by
#: the same detector.
DETECTOR_VERSION = "shift48-2"


def code_table(expand: Callable[[np.ndarray], np.ndarray], dtype) -> np.ndarray:
    """``expand`` (a stream's code -> full-range map, ``decode.decode_codes``) as a table on
    the 8-bit scale: float32 (256,) for uint8 codes, (65536,) for uint16 codes."""
    n = 256 if np.dtype(dtype) == np.uint8 else 65536
    ramp = np.arange(n, dtype=dtype).reshape(1, -1)
    out = np.asarray(expand(ramp), dtype=np.float32).ravel()
    return out * np.float32(1.0 / 257.0) if n == 65536 else out


@numba.njit(cache=True, nogil=True)
def _thumbnail(codes, table, out):  # pragma: no cover - compiled
    h, w = codes.shape
    rows, n = out.shape
    cols = 4 * n  # one sample row per block (a row read costs a run of cache lines), 4 samples in it
    out[:, :] = 0.0
    for i in range(rows):
        y = (2 * i + 1) * h // (2 * rows)
        for j in range(cols):
            x = (2 * j + 1) * w // (2 * cols)
            out[i, j // 4] += table[codes[y, x]]
    for i in range(rows):
        for j in range(n):
            out[i, j] *= 0.25


@numba.njit(cache=True, nogil=True)
def _mean(thumb):  # pragma: no cover - compiled
    m = 0.0
    for i in range(thumb.shape[0]):
        for j in range(thumb.shape[1]):
            m += thumb[i, j]
    return m / thumb.size


@numba.njit(cache=True, nogil=True)
def _shifted_difference(thumb, prev, dy, dx, step):  # pragma: no cover - compiled
    """Mean |thumb - prev| where they overlap with ``prev`` moved by (dy, dx), on every
    ``step``-th row and column."""
    h, w = thumb.shape
    s = 0.0
    n = 0
    for y in range(max(0, dy), min(h, h + dy), step):
        for x in range(max(0, dx), min(w, w + dx), step):
            s += abs(thumb[y, x] - prev[y - dy, x - dx])
            n += 1
    return s / n


@numba.njit(cache=True, nogil=True)
def _difference(thumb, prev, enough, shift):  # pragma: no cover - compiled
    """Mean |thumb - prev| (8-bit scale) at the camera shift that makes it least: within
    +-``shift`` columns and +-``shift`` // 2 rows. Shifts are tried only when the unshifted
    difference reaches ``enough`` (below it no shift matters to the rule); they are compared on
    every other row and column, and the best one and its neighbours scored on all pixels."""
    best = _shifted_difference(thumb, prev, 0, 0, 1)
    if best < enough:
        return best
    coarse, by, bx = best, 0, 0
    for dy in range(-(shift // 2), shift // 2 + 1):
        for dx in range(-shift, shift + 1):
            v = _shifted_difference(thumb, prev, dy, dx, 2)
            if v < coarse:
                coarse, by, bx = v, dy, dx
    for dy in range(max(-(shift // 2), by - 1), min(shift // 2, by + 1) + 1):
        for dx in range(max(-shift, bx - 1), min(shift, bx + 1) + 1):
            best = min(best, _shifted_difference(thumb, prev, dy, dx, 1))
    return best


def thumbnail(codes: np.ndarray, table: np.ndarray) -> np.ndarray:
    """A frame's ``THUMB`` block values on the 8-bit scale: float32 (27, 48), 0..255.

    ``codes``: a frame as ``decode.decode_codes`` yields it, (H, W) uint8 or uint16 codes, any
    strides; ``table``: its :func:`code_table`. Each block is the mean of 4 samples along the
    block's middle row: the cost does not grow with the frame size (27 rows are read,
    docs/shots.md), and averaging makes the score less sensitive to texture moving inside a block.
    """
    out = np.empty(THUMB, np.float32)
    _thumbnail(codes, table, out)
    return out


def difference(thumb: np.ndarray, prev: np.ndarray, enough: float = 0.0) -> float:
    """How much ``thumb`` differs from ``prev`` (two :func:`thumbnail` arrays) once the camera's
    motion between them is taken out: the least mean absolute difference (8-bit scale) over the
    shifts of ``prev`` by up to ``SHIFT`` columns and ``SHIFT`` // 2 rows. A pan scores what its
    borders and parallax change, a cut what the whole frame does. Shifts are tried only when the
    unshifted difference reaches ``enough`` (a smaller one is returned as it is)."""
    return float(_difference(thumb, prev, float(enough), SHIFT))


class ShotDetector:
    """Finds hard cuts, fades through black and the end of a dissolve, one frame at a time.

    Feed every frame's :func:`thumbnail` to :meth:`update`, in order; it returns True when the
    frame starts a new shot (a cut between it and the previous frame). Rules, on the
    motion-compensated difference ``d`` of consecutive thumbnails (:func:`difference`):

    * hard cut: ``d >= threshold`` and ``d >= ratio`` x the mean of the shot's last ``history``
      differences (a moving scene raises that mean; a cut stands out of it);
    * flash: a frame within ``flash`` frames of the last cut that matches the frame before that
      cut (``d < threshold``) ends a camera flash, not a shot: it is no second cut;
    * fade through black: the first frame that is not dark (thumbnail mean above ``dark``)
      after one or more dark frames;
    * end of a gradual transition: after a hard cut, when the next frame's ``d`` is still at least
      ``settle`` x the cut's own (the change goes on: a dissolve the hard rule caught part way,
      not a cut, after which the frames match again), the new shot starts at the second frame in
      a row whose ``d`` falls below that (a dissolve's last step, into its first clean frame, can
      still be large). A second cut there keeps the transition's later steps out of every window;
      a run still raised ``longest`` frames after the cut is the new shot's own motion: no cut.

    Camera motion up to ``SHIFT`` thumbnail pixels a frame is taken out of ``d``, so fast pans stay
    one shot while cuts between shots of one setting and palette stand out (docs/shots.md: the
    labelled real clip). A dissolve is found only where its steps reach the hard-cut rule: one
    between shots that differ little per frame beside their own motion gives no cut
    (docs/shots.md measures the multi-frame rules tried for it and why none is kept).
    ``cuts`` lists the frames found (indices from 0). Pure: no I/O, no clock.
    """

    def __init__(self, threshold: float = 14.0, ratio: float = 2.5, history: int = 8, dark: float = 10.0,
                 flash: int = 3, settle: float = 0.5, longest: int = 25):
        self.threshold, self.ratio, self.dark, self.flash = float(threshold), float(ratio), float(dark), int(flash)
        self.settle, self.longest = float(settle), int(longest)
        self.diffs: deque = deque(maxlen=int(history))
        self.prev: Optional[np.ndarray] = None
        self.before_cut: Optional[np.ndarray] = None  # the frame before the last cut
        # the hard cut whose following frames are watched for a transition still under way:
        # (its frame, its d, whether a later d stayed raised, calm frames in a row since), or None
        self.run: Optional[Tuple[int, float, bool, int]] = None
        self.was_dark = False
        self.frames = 0
        self.cuts: List[int] = []
        self.tables: dict = {}  # a stream's code map -> its code_table

    def score(self, codes: np.ndarray, expand: Callable[[np.ndarray], np.ndarray]) -> bool:
        """:meth:`update` with the next frame as ``decode.decode_codes`` yields it: ``codes`` and
        its code -> full-range map ``expand`` (whose :func:`code_table` is made once per map)."""
        table = self.tables.get(expand)
        if table is None:
            table = self.tables[expand] = code_table(expand, codes.dtype)
        return self.update(thumbnail(codes, table))

    def _transition_ends(self, i: int, d: float) -> bool:
        """Follow the frames after the last hard cut (``run``): True at the frame a transition
        still under way at that cut has settled (the gradual-transition rule of the class)."""
        at, cut_d, raised, calm = self.run
        if i - at > self.longest:
            self.run = None  # raised this long: the new shot's motion, not a transition
        elif d >= self.settle * cut_d:
            self.run = (at, cut_d, True, 0)
        elif not raised:
            self.run = None  # the frame after the cut matches: a hard cut
        elif calm == 0:
            self.run = (at, cut_d, True, 1)  # the first calm frame may be the transition's last step
        else:
            self.run = None
            return True
        return False

    def update(self, thumb: np.ndarray) -> bool:
        """Score the next frame's thumbnail; True when it starts a new shot (appended to ``cuts``)."""
        i = self.frames
        self.frames += 1
        dark = float(_mean(thumb)) <= self.dark
        cut = False
        if self.prev is not None:
            d = difference(thumb, self.prev, self.threshold)
            past = sum(self.diffs) / len(self.diffs) if self.diffs else 0.0
            hard = d >= self.threshold and d >= self.ratio * past
            cut = hard or (self.was_dark and not dark)
            if cut and self.cuts and i - self.cuts[-1] <= self.flash and self.before_cut is not None \
                    and difference(thumb, self.before_cut, self.threshold) < self.threshold:
                cut = False  # back to the frame before the last cut: that was a flash
                self.run = None
            elif cut:
                self.run = (i, d, False, 0) if hard else None
            elif self.run is not None:
                cut = self._transition_ends(i, d)
            if cut:
                self.before_cut = self.prev
                self.diffs.clear()  # the new shot's motion is measured against the cut's own difference
            self.diffs.append(d)
        self.prev, self.was_dark = thumb, dark
        if cut:
            self.cuts.append(i)
        return cut


@dataclass
class LayoutEvent:
    """What one frame does to the windows: ``ends`` (the window that this frame completes, or
    None), ``drops`` (the window in progress that a cut at this frame abandons, or None),
    ``starts`` (the window index this frame starts, or None), ``skips`` (the window this frame
    would complete, given up as static, or None)."""

    ends: Optional[int] = None
    drops: Optional[int] = None
    starts: Optional[int] = None
    skips: Optional[int] = None


class WindowLayout:
    """Where windows lie in a video, frame by frame (pure; every reader of a video uses it).

    Windows are ``span`` frames long and follow each other ``stride`` = ``span`` - 1 frames
    apart (a window's last frame is the next one's first). With ``avoid_cuts`` they start at
    each shot's first frame + k x ``stride``; a window a cut falls inside is dropped, and the
    next shot starts its own windows at the cut. Without, at k x ``stride``. Windows are
    numbered 0, 1, 2... in the order they complete, so a video's window indices are always
    0 .. n - 1 and a window's index is a pure function of the frames and cuts before it. With
    ``skip_static``, a window its last frame finds static (``step(static=True)``) is given up as
    a cut's is: its index goes to the next window. At most ``max_windows`` windows; :attr:`done`
    once they are complete.
    """

    def __init__(self, span: int, max_windows: int, avoid_cuts: bool = True, skip_static: bool = False):
        self.span, self.stride, self.max_windows = int(span), int(span) - 1, int(max_windows)
        self.avoid_cuts, self.skip_static = bool(avoid_cuts), bool(skip_static)
        self.shot_start = 0
        self.current: Optional[int] = None  # first frame of the window in progress
        self.completed = 0  # complete windows
        self.dropped = 0  # windows a cut fell inside
        self.static = 0  # windows given up as static
        self.cuts = 0

    @property
    def done(self) -> bool:
        """Every window the layout may give is complete: later frames serve nothing."""
        return self.completed >= self.max_windows

    def ends_at(self, i: int) -> bool:
        """Whether frame ``i``, unless it starts a shot, completes the window in progress."""
        return self.current is not None and i == self.current + self.stride

    def step(self, i: int, cut: bool = False, static: bool = False) -> LayoutEvent:
        """Frame ``i`` (in order from 0); ``cut``: it starts a new shot; ``static``: the window
        it completes, if any, is static (given up with ``skip_static``). Returns what it does."""
        ev = LayoutEvent()
        if cut:
            self.cuts += 1
            if self.avoid_cuts:
                self.shot_start = i
                if self.current is not None and i > self.current:
                    ev.drops = self.completed
                    self.dropped += 1
                    self.current = None
        if self.ends_at(i):
            if static and self.skip_static:
                ev.skips = self.completed
                self.static += 1
            else:
                ev.ends = self.completed
                self.completed += 1
            self.current = None
        if self.current is None and not self.done and (i - self.shot_start) % self.stride == 0:
            self.current = i
            ev.starts = self.completed
        return ev


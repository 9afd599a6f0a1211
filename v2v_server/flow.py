"""Optical flow for samples and for motion-compensated interpolation: the one place for it.

A sample's flow is the forward optical flow between the frames at consecutive voxel
boundaries, ``B * frames_per_bin`` source frames apart (5 by default). Plain DIS at that
spacing (Kroeger et al., ECCV 2016, OpenCV ``DISOpticalFlow``) loses large motion: on a
128 x 128 crop its pyramid has only two or three levels, so displacements beyond about
12-25 px per voxel fall back towards zero. The V2V paper (Lou et al. 2025) uses RAFT (Teed &
Deng, ECCV 2020). The options here (``FLOW_OPTIONS``, the one preset table) trade speed for
accuracy on large motion; ``python -m bench.flow`` measures them against rendered clips with
known motion (docs/flow.md):

* ``direct``: DIS between the two boundary frames (the three OpenCV presets keep their names,
  "ultrafast", "fast", "medium"); with ``temporal=True`` the previous voxel's flow of the
  same sample initialises DIS (temporal propagation).
* ``chained``: DIS between every pair of consecutive frames inside the voxel (motion per
  pair is 1/5 of the voxel's), on frames reduced ``downscale`` times, composed by sampling:
  ``F = f_1 + f_2(x + f_1) + ...`` (bilinear ``cv2.remap``), then scaled back to full size;
  optionally refined by one more DIS at the voxel spacing initialised with the composed flow.
* ``tracked``: a grid of points tracked frame by frame through the voxel with pyramidal
  Lucas-Kanade (Bouguet's KLT, OpenCV ``calcOpticalFlowPyrLK``), the first pair of a voxel
  searched from zero over the pyramid, later pairs started from the point's previous
  one-frame motion, and pairs of a fast zoom tracked in the next frame resized by the
  predicted scale (``TrackParams.zoom``); the voxel's flow at a grid point is where it ended
  minus where it started, made dense by bilinear interpolation between the grid points. Tracking composes exactly
  (no resampling of intermediate flows) and a point's flow is measured at the point itself,
  so rotation and zoom are not shrunk towards the patch centres as DIS's densification does
  near the crop border.
* ``raft``: torchvision's RAFT when its weights are on this machine (``V2V_RAFT_WEIGHTS``, or
  torchvision's cache); never downloaded. Without them it raises ``FlowUnavailable``.

Reuse policy: a ``FlowEstimator`` creates its DIS objects once per (settings, frame size,
with or without an initial flow) and reuses them for every call. A reused OpenCV DIS object
gives bit-identical flow to a fresh one for the same input, except that (OpenCV 5.0) an object
once given an initial flow returns different flow on later calls without one; hence the third
key. ``tests/test_flow.py`` checks reuse against fresh objects for every DIS option, since a
sample's content must not depend on which samples a worker made before it. DIS objects are not
thread-safe: one estimator per process or thread (``estimator(name)`` keeps one per process
and option).

Flow convention everywhere: pixels, ``(dx, dy)`` with ``a(x) ~ b(x + flow(x))``.
"""
from __future__ import annotations

import functools
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional

import cv2
import numba
import numpy as np

__all__ = [
    "DEFAULT_FLOW", "DIS_PRESETS", "DISParams", "FLOW_OPTIONS", "FlowEstimator", "FlowOption",
    "FlowUnavailable", "TrackParams", "MIN_CHAIN_SIDE", "MIN_DIS_SIDE", "check_option", "compose_flows", "dis_flow", "estimator", "raft_weights",
    "unavailable_reason",
]

log = logging.getLogger("v2v.flow")

#: OpenCV DIS presets by name (``cv2.DISOPTICAL_FLOW_PRESET_*``).
DIS_PRESETS = {"ultrafast": 0, "fast": 1, "medium": 2}
#: Frames smaller than this (px, each side) are edge-padded for DIS (OpenCV needs >= 12).
MIN_DIS_SIDE = 16
#: Chained options reduce frames no further than this (px, shorter side).
MIN_CHAIN_SIDE = 32


class FlowUnavailable(RuntimeError):
    """The option needs something this machine lacks (RAFT weights or torchvision)."""


@dataclass(frozen=True)
class DISParams:
    """One OpenCV DIS configuration: a preset and optional overrides of its settings.

    Attributes:
        preset: "ultrafast", "fast" or "medium".
        finest_scale: finest pyramid level computed (0 = full resolution; a level coarser than
            the coarsest one OpenCV builds for the frame size is clamped to it).
        patch_size, patch_stride: pixels.
        gd_iterations: gradient-descent iterations per patch.
        vr_iterations: variational refinement iterations (0 = off).
    """

    preset: str = "medium"
    finest_scale: Optional[int] = None
    patch_size: Optional[int] = None
    patch_stride: Optional[int] = None
    gd_iterations: Optional[int] = None
    vr_iterations: Optional[int] = None

    def __post_init__(self):
        if self.preset not in DIS_PRESETS:
            raise ValueError(f"DIS preset must be one of {list(DIS_PRESETS)}, got {self.preset!r}")
        for name in ("finest_scale", "patch_size", "patch_stride", "gd_iterations", "vr_iterations"):
            v = getattr(self, name)
            low = 1 if name in ("patch_size", "patch_stride", "gd_iterations") else 0
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < low):
                raise ValueError(f"DIS {name} must be an integer >= {low} or None, got {v!r}")

    def create(self, shape) -> "cv2.DISOpticalFlow":
        """A DIS object for frames of ``shape`` (H, W)."""
        d = cv2.DISOpticalFlow_create(DIS_PRESETS[self.preset])
        if self.patch_size is not None:
            d.setPatchSize(self.patch_size)
        if self.patch_stride is not None:
            d.setPatchStride(self.patch_stride)
        if self.gd_iterations is not None:
            d.setGradientDescentIterations(self.gd_iterations)
        if self.vr_iterations is not None:
            d.setVariationalRefinementIterations(self.vr_iterations)
        fs = d.getFinestScale() if self.finest_scale is None else self.finest_scale
        # OpenCV's own coarsest level for this size; a finest level above it makes DIS slow
        # (10-50x) without being more accurate, so clamp
        coarsest = max(0, int(math.log2(max(shape) / (4.0 * d.getPatchSize())) + 0.5))
        d.setFinestScale(int(min(fs, coarsest)))
        return d


@dataclass(frozen=True)
class TrackParams:
    """Settings of a ``tracked`` option: a ``grid`` x ``grid`` lattice of points over the crop
    (corners and borders included) tracked with OpenCV pyramidal Lucas-Kanade
    (``calcOpticalFlowPyrLK``; Bouguet 2001, "Pyramidal implementation of the Lucas Kanade
    feature tracker").

    Attributes:
        grid: points per side (>= 2); the dense flow is bilinear between them, so it resolves
            motion at about ``crop / (grid - 1)`` px.
        window: LK window side, px (odd, >= 3).
        levels: pyramid levels above full resolution for a pair searched from zero (the first
            pair of each voxel, and the pair after a pause); each level doubles the motion
            found, about ``window / 2 * 2**levels`` px per frame.
        prior_levels: pyramid levels for a pair started from the point's previous one-frame
            motion (constant-velocity prediction); points LK loses that way are searched again
            from zero with ``levels``.
        iterations, eps: LK stopping rule per level (at most ``iterations``; or a step under
            ``eps`` px).
        zoom: scale change per frame, as ``|log s|``, above which pairs are tracked
            zoom-compensated (None: never). LK follows a translating window; when the view
            shrinks or grows by more than a few per cent per frame, the window's content
            changes scale and LK drifts or drops the point (a 5 % scale change per frame is
            1.28x per 5-frame voxel). A compensated pair resizes the second frame by the
            inverse of the scale predicted from the previous pair (a similarity fitted to its
            points' motion, ``_zoom_fit``), starts LK from the positions the similarity
            predicts, searched over ``compensated_levels`` levels, and maps the points back.
            The scale is checked once per voxel, on the pair that moves the points off the
            grid (entering: that pair is tracked again, compensated by its own fit, and kept
            if the fit explains the points' motion as a whole, ``ZOOM_INLIERS``); while
            compensated, on every pair, and the mode carries into the next voxel while the
            scale change stays above ``zoom``.
        compensated_levels: pyramid levels above full resolution for a compensated pair (the
            motion left after the prediction is small).
    """

    grid: int = 8
    window: int = 9
    levels: int = 2
    prior_levels: int = 0
    iterations: int = 5
    eps: float = 0.03
    zoom: Optional[float] = 0.05
    compensated_levels: int = 0

    def __post_init__(self):
        for name, low in (("grid", 2), ("window", 3), ("levels", 0), ("prior_levels", 0), ("iterations", 1),
                          ("compensated_levels", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ValueError(f"tracking {name} must be an integer >= {low}, got {v!r}")
        if self.window % 2 == 0:
            raise ValueError(f"tracking window must be odd, got {self.window}")
        if not (isinstance(self.eps, (int, float)) and self.eps > 0):
            raise ValueError(f"tracking eps must be a positive number (px), got {self.eps!r}")
        if self.zoom is not None and (isinstance(self.zoom, bool) or not isinstance(self.zoom, (int, float))
                                      or not self.zoom > 0):
            raise ValueError(f"tracking zoom must be None or a positive number (|log scale| per frame), "
                             f"got {self.zoom!r}")


@dataclass(frozen=True)
class FlowOption:
    """One way of computing a sample's flow (see the module doc).

    Attributes:
        name: the key in ``FLOW_OPTIONS`` (the config's ``flow_preset``).
        method: "direct", "chained", "tracked" or "raft".
        dis: DIS settings (direct: at the voxel spacing; chained: per one-frame pair).
        temporal: direct only: initialise DIS with the previous voxel's flow of the sample.
        downscale: chained only: frames are reduced this many times (area averaging) for
            the one-frame flows (1, 2, 4); less for small crops (``FlowEstimator.downscale_for``).
        refine: chained only: DIS settings of a final voxel-spacing pass initialised with the
            composed flow (None: none).
        hop: chained only: source frames per link of the chain (1: every consecutive pair;
            2: frames 0, 2, 4, 5 of a 5-frame voxel).
        raft: raft only: "small" or "large".
        track: tracked only: the tracking settings (``TrackParams``).
        summary: one line for docs and logs.
    """

    name: str
    method: str
    dis: DISParams = DISParams()
    temporal: bool = False
    downscale: int = 1
    refine: Optional[DISParams] = None
    hop: int = 1
    raft: str = "small"
    track: TrackParams = TrackParams()
    summary: str = ""

    def __post_init__(self):
        if self.method not in ("direct", "chained", "tracked", "raft"):
            raise ValueError(f"flow option {self.name!r}: method must be direct, chained, tracked or raft, "
                             f"got {self.method!r}")
        if not isinstance(self.track, TrackParams):
            raise ValueError(f"flow option {self.name!r}: track must be TrackParams, got {self.track!r}")
        if self.downscale not in (1, 2, 4):
            raise ValueError(f"flow option {self.name!r}: downscale must be 1, 2 or 4, got {self.downscale!r}")
        if self.method != "chained" and (self.downscale != 1 or self.refine is not None):
            raise ValueError(f"flow option {self.name!r}: downscale and refine apply to chained flow only")
        if self.temporal and self.method != "direct":
            raise ValueError(f"flow option {self.name!r}: temporal initialisation applies to direct flow only")
        if isinstance(self.hop, bool) or not isinstance(self.hop, int) or self.hop < 1:
            raise ValueError(f"flow option {self.name!r}: hop must be an integer >= 1, got {self.hop!r}")
        if self.hop != 1 and self.method != "chained":
            raise ValueError(f"flow option {self.name!r}: hop applies to chained flow only")
        if self.raft not in ("small", "large"):
            raise ValueError(f"flow option {self.name!r}: raft must be small or large, got {self.raft!r}")


def _opts(*options: FlowOption) -> Dict[str, FlowOption]:
    return {o.name: o for o in options}


#: The one flow preset table: the config's ``flow_preset`` names a key. Measured in
#: docs/flow.md (``python -m bench.flow``).
FLOW_OPTIONS: Dict[str, FlowOption] = _opts(
    FlowOption("ultrafast", "direct", DISParams("ultrafast"), summary="DIS ultrafast at the voxel spacing"),
    FlowOption("fast", "direct", DISParams("fast"), summary="DIS fast at the voxel spacing"),
    FlowOption("medium", "direct", DISParams("medium"), summary="DIS medium at the voxel spacing (the default before)"),
    FlowOption("medium-fine", "direct", DISParams("medium", finest_scale=0),
               summary="DIS medium down to full resolution at the voxel spacing"),
    FlowOption("medium-temporal", "direct", DISParams("medium"), temporal=True,
               summary="DIS medium at the voxel spacing, initialised with the previous voxel's flow"),
    FlowOption("chained-quarter-hop2", "chained", DISParams("ultrafast", finest_scale=0), downscale=4, hop=2,
               summary="DIS ultrafast on quarter-size frames over links of 2 frames (0-2-4-5), composed"),
    FlowOption("chained-quarter", "chained", DISParams("ultrafast", finest_scale=0), downscale=4,
               summary="DIS ultrafast on quarter-size frames per one-frame pair, composed over the voxel"),
    FlowOption("chained-quarter-s5", "chained", DISParams("ultrafast", finest_scale=0, patch_stride=5), downscale=4,
               summary="as chained-quarter with patch stride 5 (fewer patches)"),
    FlowOption("chained-quarter-s6", "chained", DISParams("ultrafast", finest_scale=0, patch_stride=6), downscale=4,
               summary="as chained-quarter with patch stride 6 (fewer patches)"),
    FlowOption("chained-quarter-p4", "chained", DISParams("ultrafast", finest_scale=0, patch_size=4, patch_stride=2),
               downscale=4, summary="as chained-quarter with 4 x 4 patches at stride 2"),
    FlowOption("chained-half", "chained", DISParams("ultrafast", finest_scale=0), downscale=2,
               summary="DIS ultrafast on half-size frames per one-frame pair, composed"),
    FlowOption("chained-half-fast", "chained", DISParams("fast", finest_scale=0), downscale=2,
               summary="DIS fast on half-size frames per one-frame pair, composed"),
    FlowOption("chained-medium", "chained", DISParams("medium"),
               summary="DIS medium per one-frame pair at full size, composed"),
    FlowOption("chained-quarter+fast", "chained", DISParams("ultrafast", finest_scale=0), downscale=4,
               refine=DISParams("fast"),
               summary="chained-quarter, then DIS fast at the voxel spacing initialised with it"),
    FlowOption("chained-half+medium", "chained", DISParams("ultrafast", finest_scale=0), downscale=2,
               refine=DISParams("medium"),
               summary="chained-half, then DIS medium at the voxel spacing initialised with it"),
    FlowOption("tracked", "tracked", track=TrackParams(grid=8),
               summary="an 8 x 8 grid of points tracked frame by frame with pyramidal Lucas-Kanade, bilinear between them"),
    FlowOption("tracked-g6", "tracked", track=TrackParams(grid=6),
               summary="as tracked with a 6 x 6 grid (cheaper, coarser)"),
    FlowOption("tracked-g12", "tracked", track=TrackParams(grid=12),
               summary="as tracked with a 12 x 12 grid (finer, dearer)"),
    FlowOption("raft-small", "raft", raft="small", summary="torchvision RAFT small at the voxel spacing (local weights only)"),
    FlowOption("raft-large", "raft", raft="large", summary="torchvision RAFT large at the voxel spacing (local weights only)"),
)

#: The option samples use unless ``flow_preset`` says otherwise (chosen in docs/flow.md).
DEFAULT_FLOW = "tracked"


def check_option(name) -> FlowOption:
    """The option called ``name`` (case-insensitive).

    Raises:
        ValueError: naming ``flow_preset`` and the known options, for an unknown name.
    """
    key = str(name).lower()
    if key not in FLOW_OPTIONS:
        raise ValueError(f"flow_preset must be one of {list(FLOW_OPTIONS)}, got {name!r}")
    return FLOW_OPTIONS[key]


def _to_u8(frame: np.ndarray) -> np.ndarray:
    if frame.dtype == np.uint8:
        return np.ascontiguousarray(frame)  # DIS asserts contiguous frames
    if frame.dtype == np.uint16:
        return (frame >> 8).astype(np.uint8)
    raise ValueError(f"flow: frames must be uint8 or uint16, got {frame.dtype}")


def compose_flows(flows: List[np.ndarray]) -> np.ndarray:
    """Compose consecutive forward flows: ``F(x) = f_1(x) + f_2(x + f_1(x)) + ...``.

    Args:
        flows: list of float32 (H, W, 2) flows in pixels, ``f_k`` from frame k-1 to frame k.

    Returns:
        float32 (H, W, 2), the flow from frame 0 to frame K. Points carried outside the frame
        read the nearest border flow (``BORDER_REPLICATE``).
    """
    total = np.array(flows[0], dtype=np.float32, copy=True)
    if len(flows) == 1:
        return total
    grid = _pixel_grid(total.shape[:2])
    where = np.empty_like(total)
    for f in flows[1:]:
        np.add(grid, total, out=where)
        total += cv2.remap(f, where, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return total


#: Zoom compensation (``TrackParams.zoom``) starts only when the fitted similarity explains at
#: least this fraction of the points' motion (to 1 px, or 10 % of a point's motion).
ZOOM_INLIERS = 0.75
#: ... and only up to 2x per frame (``|log s| <= log 2``): a larger fitted scale is not a zoom
#: but points lost in one place.
ZOOM_MAX = math.log(2.0)

_GRIDS: Dict[tuple, np.ndarray] = {}


def _pixel_grid(shape) -> np.ndarray:
    """float32 (H, W, 2) pixel coordinates (x, y), made once per frame size (read-only)."""
    key = tuple(shape)
    g = _GRIDS.get(key)
    if g is None:
        h, w = key
        g = np.dstack(np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32)))
        g.setflags(write=False)
        g = _GRIDS[key] = g
    return g


_TRACK_GRIDS: Dict[tuple, tuple] = {}


def _track_grid(n: int, h: int, w: int):
    """The ``n`` x ``n`` tracking grid of an (h, w) crop, corners included (grid point k of a
    row sits at x = k (w - 1) / (n - 1)): float32 points (n * n, 1, 2) (x, y), and the
    bilinear interpolation matrices ``wy`` (h, n) and ``wx_t`` (n, w), so that
    ``wy @ g @ wx_t`` is the (h, w) field of an (n, n) grid field ``g``. Made once, read-only."""
    key = (n, h, w)
    g = _TRACK_GRIDS.get(key)
    if g is None:
        xs = np.linspace(0, w - 1, n, dtype=np.float32)
        ys = np.linspace(0, h - 1, n, dtype=np.float32)
        pts = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 1, 2).astype(np.float32)

        def weights(size):  # (size, n): hat functions of the n grid points
            u = np.arange(size, dtype=np.float64) * ((n - 1) / max(size - 1, 1))
            return np.maximum(0.0, 1.0 - np.abs(u[:, None] - np.arange(n)[None, :])).astype(np.float32)

        wy, wx_t = weights(h), np.ascontiguousarray(weights(w).T)
        for a in (pts, wy, wx_t):
            a.setflags(write=False)
        g = _TRACK_GRIDS[key] = (pts, wy, wx_t)
    return g


def to_float16(a: np.ndarray) -> np.ndarray:
    """float32 array of any shape -> float16 (round to nearest even, as ``a.astype(np.float16)``,
    bit for bit; overflow gives +-inf), via OpenCV's vectorised conversion: about 3.5x faster
    than numpy's cast (6 ms -> 1.7 ms for a sample's flow, 40 x 2 x 128 x 128). float16 is
    returned as it is; other dtypes go through numpy."""
    if a.dtype == np.float16:
        return a
    if a.dtype != np.float32 or a.ndim < 1 or a.size == 0:
        return a.astype(np.float16)
    flat = np.ascontiguousarray(a).reshape(-1, a.shape[-1])
    return cv2.multiply(flat, 1.0, dtype=cv2.CV_16F).reshape(a.shape)


_EXPAND_TABLES: Dict[tuple, tuple] = {}


def _expand_tables(n: int, h: int, w: int):
    """The two non-zero weights of each row of ``_track_grid``'s ``wy`` and column of its
    ``wx_t`` (hat functions: at most two grid points touch a pixel): int64 (h,) first grid
    row and float32 (h,) weights of it and the next row, the same for the columns (w,)."""
    key = (n, h, w)
    t = _EXPAND_TABLES.get(key)
    if t is None:
        _, wy, wx_t = _track_grid(n, h, w)

        def pairs(m):  # (size, n) -> first index, its weight, the next one's weight
            first = np.minimum(np.argmax(m > 0, axis=1), n - 2)
            rows = np.arange(m.shape[0])
            return first.astype(np.int64), m[rows, first].copy(), m[rows, first + 1].copy()
        t = _EXPAND_TABLES[key] = pairs(wy) + pairs(np.ascontiguousarray(wx_t.T))
    return t


@numba.njit(cache=True, error_model="numpy")
def _expand_grids(grids, i0, a0, a1, j0, b0, b1, out):
    """Dense flow ``out`` float32 (V, 2, h, w) from grid flows ``grids`` float32 (V, n, n, 2),
    bilinear between the grid points: ``wy @ g @ wx_t`` of ``_track_grid`` with only its two
    non-zero terms per row and column (``_expand_tables``), in float32."""
    n = grids.shape[1]
    w = j0.shape[0]
    tmp = np.empty((n, w), np.float32)
    for v in range(grids.shape[0]):
        for c in range(2):
            for i in range(n):
                for x in range(w):
                    tmp[i, x] = b0[x] * grids[v, i, j0[x], c] + b1[x] * grids[v, i, j0[x] + 1, c]
            for y in range(i0.shape[0]):
                r0, r1 = tmp[i0[y]], tmp[i0[y] + 1]
                wa, wb = a0[y], a1[y]
                row = out[v, c, y]
                for x in range(w):
                    row[x] = wa * r0[x] + wb * r1[x]


_FILL_TABLES: Dict[tuple, tuple] = {}


def _fill_lost(grid_flow: np.ndarray, ok: np.ndarray, sigma: float = 2.0, ridge: float = 1e-2,
               support: float = 0.1) -> np.ndarray:
    """Grid flows (V, n, n, 2) with the points not ``ok`` (V, n, n) replaced by a local affine
    fit of the valid points of the same grid: for each lost point, weighted least squares of
    ``flow = a0 + a1 x + a2 y`` over the valid points with Gaussian weights of ``sigma`` grid
    steps around it, the slopes damped by ``(ridge * sum(weights) + support) * (a1^2 + a2^2)``,
    evaluated at the lost point, then kept within the valid points' range of the grid widened
    by that range on each side. An affine fit extends rotation and zoom, where the points LK
    drops are mostly those that left the crop, whose flow keeps growing with the radius. The
    damping makes a fit the valid points do not determine (one valid point, or a few far away:
    LK drops most points of a blurred fast pan) fall back towards their weighted mean instead
    of extrapolating a slope across the crop. A grid without any valid point becomes zero."""
    lost = ~ok.reshape(ok.shape[0], -1)
    if not lost.any():
        return grid_flow
    n = ok.shape[-1]
    key = (n, sigma)
    wts = _FILL_TABLES.get(key)
    if wts is None:
        yy, xx = np.divmod(np.arange(n * n, dtype=np.float64), n)
        wts = _FILL_TABLES[key] = np.exp(-((xx[:, None] - xx[None, :]) ** 2 + (yy[:, None] - yy[None, :]) ** 2)
                                          / (2 * sigma * sigma))
    out = np.ascontiguousarray(grid_flow, dtype=np.float32).reshape(grid_flow.shape[0], n * n, 2).copy()
    _fill_lost_core(out, np.ascontiguousarray(lost), wts, n, float(ridge), float(support))
    return out.reshape(grid_flow.shape)


@numba.njit(cache=True)
def _fill_lost_core(flow, lost, wts, n, ridge, support):
    """``_fill_lost`` in place on ``flow`` float32 (V, n * n, 2), ``lost`` bool (V, n * n),
    ``wts`` float64 (n * n, n * n) Gaussian weights; float64 sums, each lost point's 3 x 3
    normal equations solved by Gaussian elimination with partial pivoting."""
    m = n * n
    a = np.empty((3, 3))
    r = np.empty((3, 2))
    for v in range(flow.shape[0]):
        nlost = 0
        lo0 = lo1 = np.inf
        hi0 = hi1 = -np.inf
        for k in range(m):
            if lost[v, k]:
                nlost += 1
            else:
                f0, f1 = float(flow[v, k, 0]), float(flow[v, k, 1])
                lo0, hi0 = min(lo0, f0), max(hi0, f0)
                lo1, hi1 = min(lo1, f1), max(hi1, f1)
        if nlost == 0:
            continue
        if nlost == m:  # no valid point: zero
            for k in range(m):
                flow[v, k, 0] = 0.0
                flow[v, k, 1] = 0.0
            continue
        # the valid range widened by itself on each side
        c0lo, c0hi = 2 * lo0 - hi0, 2 * hi0 - lo0
        c1lo, c1hi = 2 * lo1 - hi1, 2 * hi1 - lo1
        fills = np.empty((m, 2))
        for q in range(m):
            if not lost[v, q]:
                continue
            # weighted moments of the valid points around q: 1, x, y, xx, xy, yy and 1, x, y times the flow
            s0 = sx = sy = sxx = sxy = syy = 0.0
            b0 = b1 = bx0 = bx1 = by0 = by1 = 0.0
            for k in range(m):
                if lost[v, k]:
                    continue
                wk = wts[q, k]
                x, y = float(k % n), float(k // n)
                f0, f1 = float(flow[v, k, 0]), float(flow[v, k, 1])
                s0 += wk
                sx += wk * x
                sy += wk * y
                sxx += wk * x * x
                sxy += wk * x * y
                syy += wk * y * y
                b0 += wk * f0
                b1 += wk * f1
                bx0 += wk * x * f0
                bx1 += wk * x * f1
                by0 += wk * y * f0
                by1 += wk * y * f1
            d = ridge * s0 + support  # the slopes' damping
            a[0, 0], a[0, 1], a[0, 2] = s0, sx, sy
            a[1, 0], a[1, 1], a[1, 2] = sx, sxx + d, sxy
            a[2, 0], a[2, 1], a[2, 2] = sy, sxy, syy + d
            r[0, 0], r[0, 1], r[1, 0], r[1, 1], r[2, 0], r[2, 1] = b0, b1, bx0, bx1, by0, by1
            for c in range(3):  # elimination with partial pivoting
                piv = c
                for i in range(c + 1, 3):
                    if abs(a[i, c]) > abs(a[piv, c]):
                        piv = i
                if piv != c:
                    for j in range(3):
                        a[c, j], a[piv, j] = a[piv, j], a[c, j]
                    for j in range(2):
                        r[c, j], r[piv, j] = r[piv, j], r[c, j]
                for i in range(c + 1, 3):
                    g = a[i, c] / a[c, c]
                    for j in range(c, 3):
                        a[i, j] -= g * a[c, j]
                    for j in range(2):
                        r[i, j] -= g * r[c, j]
            for c in range(2, -1, -1):
                for j in range(2):
                    t = r[c, j]
                    for i in range(c + 1, 3):
                        t -= a[c, i] * r[i, j]
                    r[c, j] = t / a[c, c]
            x, y = float(q % n), float(q // n)
            fills[q, 0] = min(max(r[0, 0] + r[1, 0] * x + r[2, 0] * y, c0lo), c0hi)
            fills[q, 1] = min(max(r[0, 1] + r[1, 1] * x + r[2, 1] * y, c1lo), c1hi)
        for q in range(m):
            if lost[v, q]:
                flow[v, q, 0] = fills[q, 0]
                flow[v, q, 1] = fills[q, 1]


@numba.njit(cache=True)
def _same_as_previous(frames, repeats):
    """bool (N,): frame k equals frame k - 1 pixel for pixel (True where ``repeats`` says so,
    without looking; False for frame 0). Stops at the first differing pixel of a pair."""
    n = frames.shape[0]
    out = np.zeros(n, np.bool_)
    flat = frames.reshape(n, -1)
    for k in range(1, n):
        if repeats[k]:
            out[k] = True
            continue
        eq = True
        for q in range(flat.shape[1]):
            if flat[k, q] != flat[k - 1, q]:
                eq = False
                break
        out[k] = eq
    return out


@numba.njit(cache=True)
def _dropped_inside(st, ok, nxt, w, h, out):
    """Mark in ``out`` (bool (m,)) the points LK dropped (``st`` uint8 (m, 1) == 0) that were
    ``ok`` until now and whose last position ``nxt`` (float32 (m, 1, 2)) is still inside the
    (h, w) crop; returns how many (one pass instead of seven numpy operations per pair)."""
    n = 0
    for k in range(st.shape[0]):
        x, y = nxt[k, 0, 0], nxt[k, 0, 1]
        r = st[k, 0] == 0 and ok[k] and x >= 0 and x <= w - 1 and y >= 0 and y <= h - 1
        out[k] = r
        n += r
    return n


@numba.njit(cache=True)
def _fit_once(p, q, use):
    """Least-squares similarity of the points ``use`` selects: (ok, a, b, tx, ty, sp, sq), with
    sp, sq the spreads (sums of squared distances to their means) of those points of p and q."""
    n = 0
    mpx = mpy = mqx = mqy = 0.0
    for k in range(p.shape[0]):
        if use[k]:
            n += 1
            mpx += p[k, 0]
            mpy += p[k, 1]
            mqx += q[k, 0]
            mqy += q[k, 1]
    if n < 2:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    mpx /= n
    mpy /= n
    mqx /= n
    mqy /= n
    den = sq = sa = sb = 0.0
    for k in range(p.shape[0]):
        if use[k]:
            px, py = p[k, 0] - mpx, p[k, 1] - mpy
            qx, qy = q[k, 0] - mqx, q[k, 1] - mqy
            den += px * px + py * py
            sq += qx * qx + qy * qy
            sa += px * qx + py * qy
            sb += px * qy - py * qx
    if den <= 1e-9:
        return False, 0.0, 0.0, 0.0, 0.0, den, sq
    a, b = sa / den, sb / den
    return True, a, b, mqx - (a * mpx - b * mpy), mqy - (b * mpx + a * mpy), den, sq


@numba.njit(cache=True, inline="always")
def _residual(a, b, tx, ty, p, q, k):
    """Distance (px) between point k of q and where the similarity (a, b, tx, ty) takes p's."""
    return math.hypot(a * p[k, 0] - b * p[k, 1] + tx - q[k, 0], b * p[k, 0] + a * p[k, 1] + ty - q[k, 1])


@numba.njit(cache=True)
def _zoom_fit(p, q, good, zoom, whole, inliers, out):
    """The similarity taking points ``p`` to ``q`` (float (m, 2), px) over the points ``good``,
    written to ``out`` (float64 (2, 3)) when it changes scale by more than ``zoom`` and at most
    ``ZOOM_MAX`` (|log s|; ``zoom`` negative: any) and, with ``whole``, brings at least the
    fraction ``inliers`` of the good points within max(1 px, 10 % of their motion). Returns
    whether it did. The common case (no zoom) ends after one pass: the spread of the points
    about their mean grows by the scale of a similarity."""
    m = p.shape[0]
    n = 0
    for k in range(m):
        n += good[k]
    if n < 4:
        return False
    ok, a, b, tx, ty, sp, sq = _fit_once(p, q, good)
    if not ok or (zoom >= 0.0 and abs(0.5 * math.log(max(sq, 1e-12) / sp)) <= zoom):
        return False
    # refit once without the points the first fit leaves far off (points LK kept on the wrong
    # match, or on an object moving otherwise): residual over max(1 px, 3 x the median)
    res = np.empty(n)
    j = 0
    for k in range(m):
        if good[k]:
            res[j] = _residual(a, b, tx, ty, p, q, k)
            j += 1
    cut = max(1.0, 3.0 * np.median(res))
    keep = good.copy()
    kept = 0
    j = 0
    for k in range(m):
        if good[k]:
            keep[k] = res[j] <= cut
            kept += keep[k]
            j += 1
    if 3 <= kept < n:
        ok2, a2, b2, tx2, ty2, _, _ = _fit_once(p, q, keep)
        if ok2:
            a, b, tx, ty = a2, b2, tx2, ty2
    if zoom >= 0.0 and not zoom < abs(0.5 * math.log(max(a * a + b * b, 1e-12))) <= ZOOM_MAX:
        return False
    if whole:
        fit = 0
        for k in range(m):
            if good[k]:
                fit += _residual(a, b, tx, ty, p, q, k) <= max(1.0, 0.1 * math.hypot(q[k, 0] - p[k, 0], q[k, 1] - p[k, 1]))
        if fit < inliers * n:
            return False
    out[0, 0], out[0, 1], out[0, 2] = a, -b, tx
    out[1, 0], out[1, 1], out[1, 2] = b, a, ty
    return True


@numba.njit(cache=True)
def _to_resized(p, sim, fx, fy, dw, dh, w, h, out):
    """Zoom compensation, forward: the positions ``sim`` predicts for points ``p`` (float32
    (m, 1, 2)) in frame b, expressed in b resized to (dh, dw) (``cv2.resize``'s pixel centres:
    b's x = (x' + 0.5) * fx - 0.5), written to ``out`` relative to the top-left corner
    (ox, oy) of the w x h window of the resized b that is centred on them (kept inside it when
    it is larger). Returns (ox, oy)."""
    m = p.shape[0]
    sx = sy = 0.0
    for k in range(m):
        x, y = p[k, 0, 0], p[k, 0, 1]
        u = (sim[0, 0] * x + sim[0, 1] * y + sim[0, 2] + 0.5) / fx - 0.5
        v = (sim[1, 0] * x + sim[1, 1] * y + sim[1, 2] + 0.5) / fy - 0.5
        out[k, 0, 0], out[k, 0, 1] = u, v
        sx += u
        sy += v
    ox = min(max(int(round(sx / m - (w - 1) / 2.0)), 0), max(dw - w, 0))
    oy = min(max(int(round(sy / m - (h - 1) / 2.0)), 0), max(dh - h, 0))
    for k in range(m):
        out[k, 0, 0] -= ox
        out[k, 0, 1] -= oy
    return ox, oy


@numba.njit(cache=True)
def _from_resized(r, ox, oy, fx, fy, w, h, st):
    """Zoom compensation, back: points ``r`` (float32 (m, 1, 2)) found in the window at (ox, oy)
    of the resized b, in place to b's pixels; a point that lands outside b (what the resized
    window shows there is reflected, not seen) is marked lost in ``st``."""
    for k in range(r.shape[0]):
        x = (r[k, 0, 0] + ox + 0.5) * fx - 0.5
        y = (r[k, 0, 1] + oy + 0.5) * fy - 0.5
        r[k, 0, 0], r[k, 0, 1] = x, y
        if not (0.0 <= x <= w - 1 and 0.0 <= y <= h - 1):
            st[k] = False


def _similarity_fit(p: np.ndarray, q: np.ndarray) -> Optional[np.ndarray]:
    """Least-squares similarity (scale, rotation, translation) taking points ``p`` to ``q``
    (float (k, 2) each, pixels, k >= 4): float64 (2, 3) ``[[a, -b, tx], [b, a, ty]]`` with
    ``q ~ M[:, :2] @ p + M[:, 2]`` (the closed form of Umeyama 1991 without reflection), refit
    once without the points whose residual exceeds ``max(1 px, 3 x the median)`` (points LK
    kept on the wrong match, or on an object moving otherwise). None when the points have no
    spread (all in one place) or are fewer than 4. The tracker calls ``_zoom_fit`` directly."""
    p, q = np.ascontiguousarray(p, np.float64), np.ascontiguousarray(q, np.float64)
    out = np.empty((2, 3))
    return out if _zoom_fit(p, q, np.ones(len(p), np.bool_), -1.0, False, 0.0, out) else None


def raft_weights(size: str = "small") -> Optional[Path]:
    """Path of local RAFT weights for torchvision's ``raft_<size>``, or None.

    Looks at ``$V2V_RAFT_WEIGHTS`` (a ``.pth`` state dict), then torchvision's cache
    (``$TORCH_HOME/hub/checkpoints/raft_<size>*.pth``). Never downloads.
    """
    env = os.environ.get("V2V_RAFT_WEIGHTS")
    if env:
        return Path(env) if Path(env).is_file() else None
    home = Path(os.environ.get("TORCH_HOME", Path.home() / ".cache" / "torch"))
    hits = sorted((home / "hub" / "checkpoints").glob(f"raft_{size}*.pth"))
    return hits[0] if hits else None


def unavailable_reason(name) -> Optional[str]:
    """Why option ``name`` cannot run on this machine (RAFT without torchvision or local
    weights), or None when it can. Loads nothing."""
    o = check_option(name)
    if o.method != "raft":
        return None
    try:
        import importlib.util

        if importlib.util.find_spec("torchvision") is None:
            return "RAFT needs torchvision, which is not installed"
    except (ImportError, ValueError):
        return "RAFT needs torchvision, which cannot be imported"
    if raft_weights(o.raft) is None:
        return (f"no local RAFT {o.raft} weights (set V2V_RAFT_WEIGHTS or put raft_{o.raft}*.pth in "
                f"torchvision's cache); they are never downloaded")
    return None


class _Raft:
    """torchvision RAFT on (H, W) uint8/uint16 frames (padded to multiples of 8), on the CPU,
    grey replicated to 3 channels scaled to [-1, 1] (torchvision's RAFT input range)."""

    def __init__(self, size: str):
        why = unavailable_reason(f"raft-{size}")
        if why:
            raise FlowUnavailable(why)
        import torch
        from torchvision.models import optical_flow as of

        path = raft_weights(size)
        log.info("RAFT %s weights from %s", size, path)
        net = of.raft_small(weights=None) if size == "small" else of.raft_large(weights=None)
        net.load_state_dict(torch.load(path, map_location="cpu"))
        self.torch, self.net = torch, net.eval()

    def __call__(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        t = self.torch
        h, w = a.shape
        ph, pw = -h % 8, -w % 8

        def prep(x):
            x = np.pad(_to_u8(x), ((0, ph), (0, pw)), mode="edge").astype(np.float32) / 127.5 - 1.0
            return t.from_numpy(x)[None, None].expand(1, 3, -1, -1).contiguous()

        with t.inference_mode():
            flow = self.net(prep(a), prep(b))[-1][0, :, :h, :w]
        return flow.numpy().transpose(1, 2, 0).astype(np.float32)


class FlowEstimator:
    """Flow of one option (``FLOW_OPTIONS``), with its DIS objects created once and reused.

    ``voxel_flows(frames, step)`` is what samples use; ``__call__(a, b)`` (the former
    ``sampler.FlowEstimator`` API) is the flow between two frames only (for a chained option,
    a chain of one link: reduced frames, its DIS settings, scaled back, refined if it says so;
    for a tracked option, the grid tracked over that one pair). A tracked option keeps no
    state between calls.

    Raises:
        ValueError: for an unknown option name (naming ``flow_preset``).
        FlowUnavailable: for RAFT without torchvision or local weights.
    """

    def __init__(self, option="medium"):
        self.option = option if isinstance(option, FlowOption) else check_option(option)
        self.preset = self.option.name
        self._dis: Dict[tuple, "cv2.DISOpticalFlow"] = {}
        self._raft = _Raft(self.option.raft) if self.option.method == "raft" else None

    def _get(self, params: DISParams, shape, with_init: bool = False) -> "cv2.DISOpticalFlow":
        # objects given an initial flow are kept apart: in OpenCV 5.0 a DIS object that has
        # been given one returns different flow on later calls without one
        key = (params, tuple(shape), with_init)
        d = self._dis.get(key)
        if d is None:
            d = self._dis[key] = params.create(shape)
        return d

    def _calc(self, params: DISParams, a: np.ndarray, b: np.ndarray, init: Optional[np.ndarray] = None) -> np.ndarray:
        """DIS flow (H, W, 2) with ``params``; frames under ``MIN_DIS_SIDE`` px (OpenCV refuses
        frames under 12 px) are padded by edge replication and the flow cropped back."""
        a, b = _to_u8(a), _to_u8(b)
        h, w = a.shape
        ph, pw = max(0, MIN_DIS_SIDE - h), max(0, MIN_DIS_SIDE - w)
        if ph or pw:
            a, b = (cv2.copyMakeBorder(x, 0, ph, 0, pw, cv2.BORDER_REPLICATE) for x in (a, b))
            if init is not None:
                init = cv2.copyMakeBorder(np.asarray(init, np.float32), 0, ph, 0, pw, cv2.BORDER_REPLICATE)
        d = self._get(params, a.shape, init is not None)
        f = d.calc(a, b, None if init is None else np.array(init, np.float32, copy=True))
        return np.ascontiguousarray(f[:h, :w]) if (ph or pw) else f

    def pair(self, a: np.ndarray, b: np.ndarray, init: Optional[np.ndarray] = None) -> np.ndarray:
        """float32 (H, W, 2) flow from ``a`` to ``b`` (uint8/uint16 (H, W)) with this option's
        DIS settings (RAFT for a raft option, the tracking of a tracked one), optionally
        initialised with ``init`` (H, W, 2; DIS only).

        Raises:
            ValueError: ``init`` given to a tracked option."""
        if self._raft is not None:
            return self._raft(a, b)
        if self.option.method == "tracked":
            if init is not None:
                raise ValueError(f"flow option {self.preset!r}: tracked flow takes no initial flow")
            return np.ascontiguousarray(self.voxel_flows(np.stack([a, b]), 1)[0].transpose(1, 2, 0))
        return self._calc(self.option.dis, a, b, init)

    def __call__(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """float32 (2, H, W) flow from ``a`` to ``b``: channel 0 is x (u), channel 1 y (v), pixels."""
        if self.option.method in ("chained", "tracked"):
            return self.voxel_flows(np.stack([a, b]), 1)[0]
        return np.ascontiguousarray(self.pair(a, b).transpose(2, 0, 1))

    def voxel_flows(self, frames: np.ndarray, step: int, repeats: Optional[np.ndarray] = None,
                    dtype="float32") -> np.ndarray:
        """Flow between the frames ``step`` apart at the voxel boundaries of a sequence.

        Args:
            frames: uint8/uint16 (N, H, W) with ``(N - 1) % step == 0``: every source frame of
                the sample (repeated frames of pauses included), boundaries at ``l * step``.
            step: frames per voxel grid (B * frames_per_bin), >= 1.
            repeats: optional bool (N,), True where frame k is the same frame as frame k - 1
                (a pause; equal content is what matters): chained options then skip the DIS
                call between them, whose flow is exactly zero. The result is the same with or
                without it.

            dtype: "float32" or "float16" (the wire's ``flow_dtype``): the float32 flow is
                converted at the end (``to_float16``: round to nearest even, as numpy's cast),
                so the sample needs no conversion afterwards.

        Returns:
            (L, 2, H, W) in ``dtype``, L = (N - 1) // step: pixels from frame ``l * step`` to
            ``(l + 1) * step``, channel 0 x, channel 1 y.

        Raises:
            ValueError: for a bad shape or step, ``repeats`` of the wrong shape, or another dtype.
        """
        if not isinstance(frames, np.ndarray) or frames.ndim != 3 or step < 1 or (frames.shape[0] - 1) % step:
            raise ValueError(f"flow: frames must be (L * step + 1, H, W), got {getattr(frames, 'shape', None)} "
                             f"for step {step}")
        if repeats is not None and np.shape(repeats) != (frames.shape[0],):
            raise ValueError(f"flow: repeats must be a bool array of shape ({frames.shape[0]},), got {np.shape(repeats)}")
        if np.dtype(dtype) not in (np.float32, np.float16):
            raise ValueError(f"flow: dtype must be float32 or float16, got {dtype!r}")
        o = self.option
        n_vox = (frames.shape[0] - 1) // step
        h, w = frames.shape[1:]
        if o.method == "tracked":
            return self._tracked(frames, step, repeats, np.empty((n_vox, 2, h, w), dtype))
        f = self._voxel_flows32(frames, step, repeats, np.empty((n_vox, 2, h, w), np.float32))
        return f if np.dtype(dtype) == np.float32 else to_float16(f)

    def _voxel_flows32(self, frames, step, repeats, out):
        o = self.option
        n_vox = out.shape[0]
        h, w = frames.shape[1:]
        if o.method == "chained":
            s = self.downscale_for((h, w))
            sh, sw = max(1, h // s), max(1, w // s)
            # a frame marked as a repeat of the previous one (a pause) shares its reduced
            # frame, and a link between one reduced frame and itself is exactly zero: DIS
            # returns +0.0 everywhere for two identical frames (tests/test_flow.py checks it
            # for every chained option), so that call is skipped, bit for bit the same flow
            small = []
            for k, f in enumerate(frames):
                if k and repeats is not None and repeats[k]:
                    small.append(small[-1])
                else:
                    small.append(_to_u8(f) if s == 1 else cv2.resize(_to_u8(f), (sw, sh), interpolation=cv2.INTER_AREA))
            scale = np.array([w / sw, h / sh], np.float32)
            zero = np.zeros((sh, sw, 2), np.float32)
            zero.setflags(write=False)
            if min(sh, sw) >= MIN_DIS_SIDE:  # no padding: the reused DIS object directly
                dis = self._get(o.dis, (sh, sw))
                link = lambda a, b: zero if a is b else dis.calc(a, b, None)  # noqa: E731
            else:
                link = lambda a, b: zero if a is b else self._calc(o.dis, a, b)  # noqa: E731
            for l in range(n_vox):
                k0 = l * step
                links = list(range(k0, k0 + step, o.hop)) + [k0 + step]
                f = compose_flows([link(small[i], small[j]) for i, j in zip(links[:-1], links[1:])])
                if s > 1:
                    f = cv2.resize(f, (w, h), interpolation=cv2.INTER_LINEAR)
                    if o.refine is None:  # scaled straight into the output, channels first
                        np.multiply(f.transpose(2, 0, 1), scale[:, None, None], out=out[l])
                        continue
                    f = f * scale
                if o.refine is not None:
                    f = self._calc(o.refine, frames[k0], frames[k0 + step], f)
                out[l] = f.transpose(2, 0, 1)
            return out
        prev = None
        for l in range(n_vox):
            f = self.pair(frames[l * step], frames[(l + 1) * step], prev if o.temporal else None)
            out[l] = f.transpose(2, 0, 1)
            prev = f
        return out

    def _tracked(self, frames: np.ndarray, step: int, repeats: Optional[np.ndarray], out: np.ndarray) -> np.ndarray:
        """``voxel_flows`` of a ``tracked`` option (see ``TrackParams``). Per voxel the grid
        points are tracked over its one-frame pairs. A pair of equal frames (a pause, marked in
        ``repeats`` or not) moves nothing and costs no LK call; the pair after it is searched
        from zero. A point LK drops (status 0: it left the crop, or its window is flat or lost
        its match) stops there and takes a local affine fit of the other points' flows at the
        end of the voxel (``_fill_lost``); one dropped inside the crop while started from its
        previous motion is first searched once more from zero. While the view zooms faster
        than ``TrackParams.zoom`` per frame, pairs are tracked zoom-compensated (see there)."""
        t = self.option.track
        n_vox = out.shape[0]
        h, w = frames.shape[1:]
        f8 = _to_u8(frames)  # (N, H, W) contiguous uint8; LK takes its frames as views
        u8 = list(f8)
        same = _same_as_previous(f8, np.zeros(len(f8), bool) if repeats is None else np.asarray(repeats, bool)).tolist()
        g0 = _track_grid(t.grid, h, w)[0]
        m = len(g0)
        # OpenCV pyramidal LK (one call per pair, on the whole grid): from zero with ``levels``,
        # or from a guess (OPTFLOW_USE_INITIAL_FLOW) with ``prior_levels``
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, t.iterations, float(t.eps))
        lk = functools.partial(cv2.calcOpticalFlowPyrLK, winSize=(t.window, t.window), criteria=crit)
        guess_flag = cv2.OPTFLOW_USE_INITIAL_FLOW

        def compensated(a, b, p, sim):
            # LK from a to b resized by 1 / (the predicted scale), started from the predicted
            # positions (see ``_to_resized``); a w x h window of the resized b over the
            # predicted points is searched (reflected where it is smaller). A resize costs
            # about a fifth of a warpAffine of the same frame.
            s = math.hypot(sim[0, 0], sim[1, 0])
            dw, dh = max(1, int(round(w / s))), max(1, int(round(h / s)))
            guess = np.empty_like(p)
            ox, oy = _to_resized(p, sim, w / dw, h / dh, dw, dh, w, h, guess)
            bs = cv2.resize(b, (dw, dh), interpolation=cv2.INTER_LINEAR)[oy:oy + h, ox:ox + w]
            if bs.shape != (h, w):
                bs = cv2.copyMakeBorder(bs, 0, h - bs.shape[0], 0, w - bs.shape[1], cv2.BORDER_REFLECT101)
            r, st, _ = lk(a, np.ascontiguousarray(bs), p, guess, maxLevel=t.compensated_levels, flags=guess_flag)
            st = st[:, 0].view(bool)
            _from_resized(r, ox, oy, w / dw, h / dh, w, h, st)  # in place: r to b's pixels, st
            return r, st

        def zoom_fit(p, nxt, good, whole):
            # the pair's similarity if it zooms more than t.zoom (and, with ``whole``, explains
            # the points' motion as a whole: mixed motion, objects or parallax, that merely
            # spreads the points is left to plain tracking), else None
            sim = np.empty((2, 3))
            return sim if _zoom_fit(p[:, 0], nxt[:, 0], good, t.zoom, whole, ZOOM_INLIERS, sim) else None

        grid_flows = np.empty((n_vox, m, 2), np.float32)
        valid = np.empty((n_vox, m), bool)
        redo = np.empty(m, bool)
        sim = None  # the predicted one-frame similarity (2, 3) while zoom-compensated
        for l in range(n_vox):
            # every point is tracked over every pair (a dropped one too: cheaper than picking
            # the others out); ``ok`` remembers which were never dropped
            p, ok, v = g0, np.ones(m, bool), None  # v: the points' last one-frame motion
            for i in range(l * step, (l + 1) * step):
                if same[i + 1]:  # a pause: nothing moves; the next pair starts from zero
                    v = None
                    continue
                a, b = u8[i], u8[i + 1]
                check = t.zoom is not None and (sim is not None or p is g0)
                if sim is not None:
                    nxt, st = compensated(a, b, p, sim)
                elif v is None:
                    nxt, st, _ = lk(a, b, p, None, maxLevel=t.levels)
                    st = st[:, 0].view(bool)
                else:
                    nxt, st, _ = lk(a, b, p, p + v, maxLevel=t.prior_levels, flags=guess_flag)
                    if _dropped_inside(st, ok, nxt, w, h, redo):  # those are searched again from zero
                        again, st2, _ = lk(a, b, p[redo], None, maxLevel=t.levels)
                        nxt[redo], st[redo] = again, st2
                    st = st[:, 0].view(bool)
                if check:  # once per voxel, or every pair while compensated
                    if sim is None:
                        # a zoom? this pair once more, compensated by its own fit (plain LK
                        # drifts under strong zoom), kept if the view zooms as a whole
                        fit = zoom_fit(p, nxt, st & ok, False)
                        if fit is not None:
                            nxt2, st2 = compensated(a, b, p, fit)
                            sim = zoom_fit(p, nxt2, st2 & ok, True)
                            if sim is not None:
                                nxt, st = nxt2, st2
                    else:
                        sim = zoom_fit(p, nxt, st & ok, True)
                v, p = nxt - p, nxt
                ok &= st
            grid_flows[l] = (p - g0)[:, 0]
            valid[l] = ok
        n = t.grid
        grids = _fill_lost(grid_flows.reshape(n_vox, n, n, 2), valid.reshape(n_vox, n, n))
        # bilinear between grid points, written in out's dtype (float16 without a float32 pass)
        # bilinear between grid points (float32), then the wire's dtype
        f32 = out if out.dtype == np.float32 else np.empty(out.shape, np.float32)
        _expand_grids(grids, *_expand_tables(n, h, w), f32)
        return out if f32 is out else to_float16(f32)

    def downscale_for(self, shape) -> int:
        """The reduction a chained option applies to frames of ``shape`` (H, W): its
        ``downscale``, halved until the reduced frames keep ``MIN_CHAIN_SIDE`` px on their
        shorter side (so a 64 px crop is reduced 2x, a 32 px crop not at all)."""
        s = self.option.downscale
        while s > 1 and min(shape) // s < MIN_CHAIN_SIDE:
            s //= 2
        return s


_CACHE: Dict[tuple, FlowEstimator] = {}


def estimator(name) -> FlowEstimator:
    """The estimator of option ``name`` for this process (created once; DIS objects are
    reused, see the module doc on why that is safe). Not for sharing between threads."""
    key = (os.getpid(), str(name).lower())
    est = _CACHE.get(key)
    if est is None:
        est = _CACHE[key] = FlowEstimator(name)
    return est


def dis_flow(a: np.ndarray, b: np.ndarray, preset: str = "medium") -> np.ndarray:
    """Dense optical flow from frame ``a`` to frame ``b`` with OpenCV DIS (one pair).

    Args:
        a, b: (H, W) uint8 or uint16 luma frames (uint16 is reduced to its top 8 bits).
        preset: "ultrafast", "fast" or "medium" (``cv2.DISOPTICAL_FLOW_PRESET_*``).

    Returns:
        float32 (H, W, 2) flow in pixels, ``(dx, dy)``: ``a(x) ~ b(x + flow(x))``.

    Raises:
        ValueError: for an unknown preset.
    """
    if preset not in DIS_PRESETS:
        raise ValueError(f"flow preset must be one of {sorted(DIS_PRESETS)}, got {preset!r}")
    return estimator(preset).pair(a, b)

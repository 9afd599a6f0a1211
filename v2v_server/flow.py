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
import numpy as np

from .tracking import (ZOOM_INLIERS, _dropped_inside, _expand_grids, _expand_tables, _fill_lost, _from_resized,
                       _same_as_previous, _to_resized, _track_grid, _zoom_fit)

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
            points' motion, ``tracking._zoom_fit``), starts LK from the positions the similarity
            predicts, searched over ``compensated_levels`` levels, and maps the points back.
            The scale is checked once per voxel, on the pair that moves the points off the
            grid (entering: that pair is tracked again, compensated by its own fit, and kept
            if the fit explains the points' motion as a whole, ``tracking.ZOOM_INLIERS``); while
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
        f = self._flows32(frames, step, repeats)
        return f if np.dtype(dtype) == np.float32 else to_float16(f)

    def _flows32(self, frames, step, repeats):
        o = self.option
        n_vox = (frames.shape[0] - 1) // step
        h, w = frames.shape[1:]
        out = np.empty((n_vox, 2, h, w), np.float32)
        if o.method == "tracked":
            return self._tracked(frames, step, repeats, out)
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
        # bilinear between grid points
        _expand_grids(grids, *_expand_tables(n, h, w), out)
        return out

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

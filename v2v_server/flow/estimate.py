"""Optical flow for samples, and the DIS flow of a frame pair for motion-compensated
interpolation.

A sample's flow is the forward optical flow between the frames at consecutive voxel
boundaries, ``B * frames_per_bin`` source frames apart (5 by default). The options
(``options.FLOW_OPTIONS``, the one table) trade speed for accuracy on large motion;
``python -m bench.flow`` measures them against rendered clips with known motion (docs/flow.md):

* ``tracked``: a grid of points tracked frame by frame through the voxel with pyramidal
  Lucas-Kanade (Bouguet's KLT, OpenCV ``calcOpticalFlowPyrLK``), the first pair of a voxel
  searched from zero over the pyramid, later pairs started from the point's previous
  one-frame motion, and pairs of a fast zoom tracked in the next frame resized by the
  predicted scale (``TrackParams.zoom``); the voxel's flow at a grid point is where it ended
  minus where it started, made dense by bilinear interpolation between the grid points.
  Tracking composes exactly (no resampling of intermediate flows) and a point's flow is
  measured at the point itself, so rotation and zoom are not shrunk towards the patch centres
  as DIS's densification does near the crop border.
* ``direct``: DIS (Kroeger et al., ECCV 2016, OpenCV ``DISOpticalFlow``) between the two
  boundary frames. On a 128 x 128 crop its pyramid has only two or three levels, so
  displacements beyond about 12-25 px per voxel fall back towards zero.
* ``raft``: torchvision's RAFT (Teed & Deng, ECCV 2020; the V2V paper's choice) when its
  weights are on this machine (``V2V_RAFT_WEIGHTS``, or torchvision's cache); never
  downloaded. Without them it raises ``FlowUnavailable``.

Reuse policy: DIS objects are created once per process and (settings, frame size) and reused
for every call. A reused OpenCV DIS object gives bit-identical flow to a fresh one for the same
input (``tests/test_flow.py`` checks it), since a sample's content must not depend on which
samples a worker made before it. DIS objects are not thread-safe: one process or thread each.

Flow convention everywhere: pixels, ``(dx, dy)`` with ``a(x) ~ b(x + flow(x))``.
"""
from __future__ import annotations

import functools
import logging
import math
import os
from typing import Dict, Optional

import cv2
import numpy as np

from v2v_server.flow.options import (DEFAULT_FLOW, DIS_PRESETS, DISParams, FlowOption, FlowUnavailable, check_option,
                           load_raft, raft_weights, unavailable_reason)
from v2v_server.luma import to_uint8
from v2v_wire.flowgrid import expand_grids
from v2v_server.flow.tracking import (ZOOM_INLIERS, _dropped_inside, _fill_lost, _from_resized,
                       _same_as_previous, _to_resized, _track_grid, _zoom_fit)

__all__ = ["FlowEstimator", "MIN_DIS_SIDE", "dis_flow", "expand_grids", "to_float16"]

log = logging.getLogger("v2v.flow")

#: Frames smaller than this (px, each side) are edge-padded for DIS (OpenCV needs >= 12).
MIN_DIS_SIDE = 16


def _to_u8(frame: np.ndarray) -> np.ndarray:
    """``frame`` as contiguous uint8 (DIS asserts contiguous frames): uint16 rounded by
    :func:`v2v_server.luma.to_uint8`, as the sample's ground-truth frames are."""
    if frame.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"flow: frames must be uint8 or uint16, got {frame.dtype}")
    return np.ascontiguousarray(to_uint8(frame))


def _create_dis(params: DISParams, shape) -> "cv2.DISOpticalFlow":
    """A DIS object with ``params`` for frames of ``shape`` (H, W)."""
    d = cv2.DISOpticalFlow_create(DIS_PRESETS[params.preset])
    if params.patch_size is not None:
        d.setPatchSize(params.patch_size)
    if params.patch_stride is not None:
        d.setPatchStride(params.patch_stride)
    if params.gd_iterations is not None:
        d.setGradientDescentIterations(params.gd_iterations)
    if params.vr_iterations is not None:
        d.setVariationalRefinementIterations(params.vr_iterations)
    fs = d.getFinestScale() if params.finest_scale is None else params.finest_scale
    # OpenCV's own coarsest level for this size; a finest level above it makes DIS slow
    # (10-50x) without being more accurate, so clamp
    coarsest = max(0, int(math.log2(max(shape) / (4.0 * d.getPatchSize())) + 0.5))
    d.setFinestScale(int(min(fs, coarsest)))
    return d


_DIS: Dict[tuple, "cv2.DISOpticalFlow"] = {}


def _dis(params: DISParams, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """float32 (H, W, 2) DIS flow from ``a`` to ``b`` with ``params``, the process's DIS object
    for (params, size) reused; frames under ``MIN_DIS_SIDE`` px (OpenCV refuses frames under
    12 px) are padded by edge replication and the flow cropped back."""
    a, b = _to_u8(a), _to_u8(b)
    h, w = a.shape
    ph, pw = max(0, MIN_DIS_SIDE - h), max(0, MIN_DIS_SIDE - w)
    if ph or pw:
        a, b = (cv2.copyMakeBorder(x, 0, ph, 0, pw, cv2.BORDER_REPLICATE) for x in (a, b))
    key = (os.getpid(), params, a.shape)
    d = _DIS.get(key)
    if d is None:
        d = _DIS[key] = _create_dis(params, a.shape)
    f = d.calc(a, b, None)
    return np.ascontiguousarray(f[:h, :w]) if (ph or pw) else f


def dis_flow(a: np.ndarray, b: np.ndarray, preset: str = "medium") -> np.ndarray:
    """Dense optical flow of one frame pair with OpenCV DIS, for motion-compensated
    interpolation (``refine.py``, ``reference.py``); a sample's flow comes from
    ``FlowEstimator.voxel_flows``.

    Args:
        a, b: (H, W) uint8 or uint16 luma frames (uint16 rounded to 8 bits, ``v2v_server.luma.to_uint8``).
        preset: "ultrafast", "fast" or "medium" (``cv2.DISOPTICAL_FLOW_PRESET_*``).

    Returns:
        float32 (H, W, 2) flow in pixels, ``(dx, dy)``: ``a(x) ~ b(x + flow(x))``.

    Raises:
        ValueError: for an unknown preset.
    """
    if preset not in DIS_PRESETS:
        raise ValueError(f"flow preset must be one of {sorted(DIS_PRESETS)}, got {preset!r}")
    return _dis(DISParams(preset), a, b)


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


class _Raft:
    """torchvision RAFT on (H, W) uint8/uint16 frames (padded to multiples of 8), on the CPU,
    grey replicated to 3 channels scaled to [-1, 1] (torchvision's RAFT input range)."""

    def __init__(self, size: str):
        why = unavailable_reason(f"raft-{size}")
        if why:
            raise FlowUnavailable(why)
        import torch

        self.torch, self.net = torch, load_raft(size)
        log.info("RAFT %s weights from %s", size, raft_weights(size))

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


def _compensated_lk(lk, t, a: np.ndarray, b: np.ndarray, p: np.ndarray, sim: np.ndarray):
    """LK (``lk``, the tracked loop's partial) from ``a`` to ``b`` resized by 1 / (the scale of
    the predicted similarity ``sim``), started from the predicted positions of the points ``p``
    (see ``tracking._to_resized``); a w x h window of the resized ``b`` over the predicted points
    is searched (reflected where it is smaller). A resize costs about a fifth of a warpAffine of
    the same frame. Returns the points in ``b``'s pixels and their status (bool)."""
    h, w = a.shape
    s = math.hypot(sim[0, 0], sim[1, 0])
    dw, dh = max(1, int(round(w / s))), max(1, int(round(h / s)))
    guess = np.empty_like(p)
    ox, oy = _to_resized(p, sim, w / dw, h / dh, dw, dh, w, h, guess)
    bs = cv2.resize(b, (dw, dh), interpolation=cv2.INTER_LINEAR)[oy:oy + h, ox:ox + w]
    if bs.shape != (h, w):
        bs = cv2.copyMakeBorder(bs, 0, h - bs.shape[0], 0, w - bs.shape[1], cv2.BORDER_REFLECT101)
    r, st, _ = lk(a, np.ascontiguousarray(bs), p, guess, maxLevel=t.compensated_levels,
                  flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    st = st[:, 0].view(bool)
    _from_resized(r, ox, oy, w / dw, h / dh, w, h, st)  # in place: r to b's pixels, st
    return r, st


def _zoom_similarity(t, p: np.ndarray, nxt: np.ndarray, good: np.ndarray, whole: bool) -> Optional[np.ndarray]:
    """The pair's similarity (2, 3) if it zooms more than ``t.zoom`` (and, with ``whole``,
    explains the points' motion as a whole: mixed motion, objects or parallax, that merely
    spreads the points is left to plain tracking), else None."""
    sim = np.empty((2, 3))
    return sim if _zoom_fit(p[:, 0], nxt[:, 0], good, t.zoom, whole, ZOOM_INLIERS, sim) else None


class FlowEstimator:
    """A sample's flows with one option of ``options.FLOW_OPTIONS``.

    A tracked option keeps no state between calls; DIS objects are the process's (see the
    module doc).

    Raises:
        ValueError: for an unknown option name (naming ``flow_preset``).
        FlowUnavailable: for RAFT without torchvision or local weights.
    """

    def __init__(self, option=DEFAULT_FLOW):
        self.option = option if isinstance(option, FlowOption) else check_option(option)
        self.preset = self.option.name
        self._raft = _Raft(self.option.raft) if self.option.method == "raft" else None

    def voxel_flows(self, frames: np.ndarray, step: int, repeats: Optional[np.ndarray] = None,
                    dtype="float32") -> np.ndarray:
        """Flow between the frames ``step`` apart at the voxel boundaries of a sequence.

        Args:
            frames: uint8/uint16 (N, H, W) with ``(N - 1) % step == 0``: every source frame of
                the sample (repeated frames of pauses included), boundaries at ``l * step``.
            step: frames per voxel grid (B * frames_per_bin), >= 1.
            repeats: optional bool (N,), True where frame k is the same frame as frame k - 1
                (a pause): tracked options then skip that pair, whose flow is exactly zero.
                The result is the same with or without it.
            dtype: "float32" or "float16" (the wire's ``flow_dtype``): the float32 flow is
                converted at the end (``to_float16``: round to nearest even, as numpy's cast),
                so the sample needs no conversion afterwards.

        Returns:
            (L, 2, H, W) in ``dtype``, L = (N - 1) // step: pixels from frame ``l * step`` to
            ``(l + 1) * step``, channel 0 x, channel 1 y. For a tracked option this is
            ``expand_grids(voxel_flow_grids(...))``.

        Raises:
            ValueError: for a bad shape or step, ``repeats`` of the wrong shape, or another dtype.
        """
        self._check(frames, step, repeats)
        if np.dtype(dtype) not in (np.float32, np.float16):
            raise ValueError(f"flow: dtype must be float32 or float16, got {dtype!r}")
        n_vox = (frames.shape[0] - 1) // step
        if self.option.method == "tracked":
            out = expand_grids(self._tracked(frames, step, repeats).transpose(0, 3, 1, 2), frames.shape[1:])
        else:
            out = np.empty((n_vox, 2) + frames.shape[1:], np.float32)
            pair = self._raft if self._raft is not None else functools.partial(_dis, self.option.dis)
            for l in range(n_vox):
                out[l] = pair(frames[l * step], frames[(l + 1) * step]).transpose(2, 0, 1)
        return out if np.dtype(dtype) == np.float32 else to_float16(out)

    def voxel_flow_grids(self, frames: np.ndarray, step: int, repeats: Optional[np.ndarray] = None) -> np.ndarray:
        """A tracked option's flow before it is made dense: the flow at its grid points, what
        the wire carries as ``flow_grid`` (``protocol.flow_grid_taps`` makes it dense, bit for
        bit as ``voxel_flows``).

        Args: as ``voxel_flows``.

        Returns:
            float32 (L, 2, n, n), ``n = TrackParams.grid``: pixels from frame ``l * step`` to
            ``(l + 1) * step`` of the grid point in row i, column j, which sits at
            ``(j (W - 1) / (n - 1), i (H - 1) / (n - 1))``; channel 0 x, channel 1 y.

        Raises:
            ValueError: for an option that is not tracked, a bad shape or step, or ``repeats``
                of the wrong shape.
        """
        if self.option.method != "tracked":
            raise ValueError(f"flow: option {self.preset!r} has no grid (only tracked options do)")
        self._check(frames, step, repeats)
        return np.ascontiguousarray(self._tracked(frames, step, repeats).transpose(0, 3, 1, 2))

    @staticmethod
    def _check(frames, step, repeats) -> None:
        if not isinstance(frames, np.ndarray) or frames.ndim != 3 or step < 1 or (frames.shape[0] - 1) % step:
            raise ValueError(f"flow: frames must be (L * step + 1, H, W), got {getattr(frames, 'shape', None)} "
                             f"for step {step}")
        if repeats is not None and np.shape(repeats) != (frames.shape[0],):
            raise ValueError(f"flow: repeats must be a bool array of shape ({frames.shape[0]},), got {np.shape(repeats)}")

    def _tracked(self, frames: np.ndarray, step: int, repeats: Optional[np.ndarray]) -> np.ndarray:
        """The grid flows float32 (L, n, n, 2) of a ``tracked`` option (see ``TrackParams``). Per voxel the grid
        points are tracked over its one-frame pairs. A pair of equal frames (a pause, marked in
        ``repeats`` or not) moves nothing and costs no LK call; the pair after it is searched
        from zero. A point LK drops (status 0: it left the crop, or its window is flat or lost
        its match) stops there and takes a local affine fit of the other points' flows at the
        end of the voxel (``_fill_lost``); one dropped inside the crop while started from its
        previous motion is first searched once more from zero. While the view zooms faster
        than ``TrackParams.zoom`` per frame, pairs are tracked zoom-compensated (see there)."""
        t = self.option.track
        n_vox = (frames.shape[0] - 1) // step
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
                    nxt, st = _compensated_lk(lk, t, a, b, p, sim)
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
                        fit = _zoom_similarity(t, p, nxt, st & ok, False)
                        if fit is not None:
                            nxt2, st2 = _compensated_lk(lk, t, a, b, p, fit)
                            sim = _zoom_similarity(t, p, nxt2, st2 & ok, True)
                            if sim is not None:
                                nxt, st = nxt2, st2
                    else:
                        sim = _zoom_similarity(t, p, nxt, st & ok, True)
                v, p = nxt - p, nxt
                ok &= st
            grid_flows[l] = (p - g0)[:, 0]
            valid[l] = ok
        n = t.grid
        return _fill_lost(grid_flows.reshape(n_vox, n, n, 2), valid.reshape(n_vox, n, n))

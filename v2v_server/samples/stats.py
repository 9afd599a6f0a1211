"""A sample's event statistics, measured on its own arrays where the worker makes it.

Stoffregen et al. (ECCV 2020, "Reducing the Sim-to-Real Gap for Event Cameras") match a
simulator's contrast thresholds to a target sensor by its events per pixel per second; these are
the numbers a user needs for that, computed once per sample from the arrays the worker already
holds (pure numpy, no second simulation) and carried in the sample's params under ``"stats"``:

* ``rate_pos``, ``rate_neg``: signal events per pixel per second by polarity, the voxels' positive
  and negative counts summed over the sample, divided by the pixels and the sample's duration
  (``L x B x frames_per_bin`` frame intervals at the source's ``video_fps``: a pause is time in
  which the scene stands still, so it counts). With one frame pair per bin and no refinement (the
  default recipe) a bin holds either N+ or N- of its pixel, so the sums are the event counts
  exactly; when bins sum several pairs or sub-frames, opposite events in one bin cancel and the
  sums are a lower bound (``exact`` says which). ``polarity_counts``, when served, gives N+ and N-
  themselves (saturating at 255 per bin).
* ``grid_rates``: events per pixel per second of each of the L voxel grids (both polarities): the
  unit a network sees, and short enough (B frame intervals) to compare with a short recording.
* ``active_fraction``: the fraction of pixels with at least one event in the sample.
* ``flow_mag``: mean optical-flow magnitude, pixels per frame (the flow between voxel boundaries
  divided by the frame intervals it spans). A tracked option's flow is measured at its grid
  points, the form both engines make it in (``v2v-serve``'s workers send the grid, the Ray engine
  expands it after the statistics), so one sample has one value whichever engine made it; its
  mean is the dense flow's up to the bilinear expansion's weighting.
* ``motion``: the window's mean change of log intensity per frame pair, on its source frames
  (``frames.motion``: what ``static_windows`` compares with ``STATIC_MOTION``); a property of
  the window, the same for every crop of it.
* the noise events' share is **not** counted: the kernel adds the background noise to each
  pixel's potential before the threshold crossing, so an event has no single cause; counting it
  would need a second, noise-free simulation of the window (twice the kernel's cost).

The drawn thresholds and noise (``pos_threshold``, ``neg_threshold``, ``noise_std``, hot pixels),
the window's source span (``src_start_frame``, ``src_frames``) are in the params already;
:func:`add_stats` adds the window's shot (``shot``, ``shot_start_frame``) when shots are detected.
"""
from __future__ import annotations

from typing import Dict, Optional

import numpy as np

#: Significant digits kept of each statistic (the params travel with every sample).
DIGITS = 5


def _round(x: float) -> float:
    return float(f"{float(x):.{DIGITS}g}")


def event_stats(voxels: Optional[np.ndarray], counts: Optional[np.ndarray], flow: Optional[np.ndarray],
                video_fps: float, num_bins: int, frames_per_bin: int, exact: bool) -> Dict[str, object]:
    """Event and flow statistics of one sample (pure).

    Args:
        voxels: (L, B, H, W) signed event counts (any integer dtype), or None.
        counts: ``polarity_counts`` uint8 (L, 2, B, H, W), N+ and N- per bin, or None; used in
            place of ``voxels`` when given.
        flow: (L, 2, H, W) or a tracked grid (L, 2, n, n), pixels from one voxel boundary to the
            next (float16/32), or None.
        video_fps: the source's frame rate, Hz (> 0).
        num_bins, frames_per_bin: the recipe's B and frame pairs per bin (a voxel grid, and the
            flow's step, span ``B x frames_per_bin`` frame intervals).
        exact: the voxels hold each pixel's events of a bin without cancellation (one frame pair
            per bin, no refinement); ignored when ``counts`` is given (exact but saturating).

    Returns:
        dict of floats: ``rate_pos``, ``rate_neg`` (events / pixel / s), ``grid_rates`` (list of
        L, events / pixel / s), ``active_fraction`` (0..1), ``flow_mag`` (px / frame), and
        ``exact`` (bool); the event keys only with voxels or counts, ``flow_mag`` only with flow.

    Raises:
        ValueError: ``video_fps`` not > 0, or arrays not of the shapes above.
    """
    if not video_fps > 0:
        raise ValueError(f"video_fps must be > 0, got {video_fps!r}")
    out: Dict[str, object] = {}
    grid_s = num_bins * frames_per_bin / float(video_fps)  # seconds per voxel grid
    if counts is not None:
        if counts.ndim != 5 or counts.shape[1] != 2:
            raise ValueError(f"polarity_counts must be (L, 2, B, H, W), got {counts.shape}")
        L, h, w = counts.shape[0], counts.shape[3], counts.shape[4]
        per = counts.reshape(L, 2, -1).sum(axis=2, dtype=np.int64)  # (L, 2)
        pos, neg = int(per[:, 0].sum()), int(per[:, 1].sum())
        grid = per.sum(axis=1)
        active = np.count_nonzero(counts.reshape(-1, h * w).any(axis=0))
        exact = True
    elif voxels is not None:
        if voxels.ndim != 4:
            raise ValueError(f"voxels must be (L, B, H, W), got {voxels.shape}")
        L, nb, h, w = voxels.shape
        small = voxels.dtype.itemsize == 1
        # |int8| in int16 (-128 has no int8 absolute value); |int16| in int16 unless -32768 is there
        a = np.abs(voxels.reshape(L, -1), dtype=np.int16 if small else None)
        if not small and a.dtype.itemsize < 8 and a.min() < 0:
            a = np.abs(voxels.reshape(L, -1), dtype=np.int64)
        # int8 sums in int32 hold 2^31 / 128 = 16M bins x pixels, far above a sample's; wider in int64
        acc = np.int32 if small else np.int64
        grid = a.sum(axis=1, dtype=acc).astype(np.int64)
        total, net = int(grid.sum()), int(voxels.sum(dtype=acc))
        pos, neg = (total + net) // 2, (total - net) // 2
        flat = voxels.reshape(L * nb, h * w)
        # a pixel is active when any of its bins is non-zero: the max of its bins' bits read as
        # unsigned integers (10x faster than any() over a boolean copy)
        active = np.count_nonzero(flat.view(f"u{voxels.dtype.itemsize}").max(axis=0))
    else:
        L = h = w = 0
    if L:
        npix = h * w
        out.update(rate_pos=_round(pos / npix / (L * grid_s)), rate_neg=_round(neg / npix / (L * grid_s)),
                   grid_rates=[_round(g / npix / grid_s) for g in grid.tolist()],
                   active_fraction=_round(active / npix), exact=bool(exact))
    if flow is not None:
        if flow.ndim != 4 or flow.shape[1] != 2:
            raise ValueError(f"flow must be (L, 2, H, W), got {flow.shape}")
        f = flow.astype(np.float32, copy=False)
        mag = np.sqrt(f[:, 0] * f[:, 0] + f[:, 1] * f[:, 1])
        # from one voxel boundary to the next: B x frames_per_bin frame intervals
        out["flow_mag"] = _round(float(mag.mean(dtype=np.float64)) / (num_bins * frames_per_bin))
    return out


def add_stats(meta: dict, arrays: Dict[str, np.ndarray], recipe, shot: Optional[tuple] = None,
              motion: Optional[float] = None) -> dict:
    """``meta`` (a sample's params, with ``video_fps``) with ``"stats"``: :func:`event_stats` of the
    sample's ``arrays`` (as ``samples.make.make_sample`` returns them) under ``recipe`` (a
    ``SampleRecipe``); given ``shot`` = (shot index in the video, its first frame), also ``shot``
    and ``shot_start_frame``; given ``motion`` (the window's, ``frames.motion``), also the
    statistic ``motion``. Returns a new dict (``meta`` is left as it is).

    Raises:
        ValueError: as :func:`event_stats`.
    """
    exact = recipe.frames_per_bin == 1 and recipe.refine == "off" and not recipe.nonidealities
    meta = dict(meta)
    meta["stats"] = event_stats(arrays.get("voxels"), arrays.get("polarity_counts"),
                                arrays.get("flow", arrays.get("flow_grid")), meta["video_fps"], recipe.num_bins,
                                recipe.frames_per_bin, exact)
    if motion is not None:
        meta["stats"]["motion"] = _round(motion)
    if shot is not None:
        meta.update(shot=int(shot[0]), shot_start_frame=int(shot[1]))
    return meta

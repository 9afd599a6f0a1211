"""Optional sensor non-idealities on top of the V2V step, each off by default.

Config section ``nonidealities:`` (YAML), parsed by :meth:`NonIdealities.from_dict`:

============================  ==========  ==================================================
key                           default     model and source
============================  ==========  ==================================================
``threshold_sigma``           0.0         per-pixel contrast-threshold mismatch: c+ and c- of
                                          each pixel ~ N(c, sigma^2) (log-intensity units),
                                          clipped below at 0.01 c. ESIM
                                          ``contrast_threshold_sigma_{pos,neg}``; v2e
                                          ``--sigma_thres``.
``shot_noise_hz``             0.0         shot-noise events per pixel per second, random
                                          polarity (Poisson, rate / fps per frame pair). v2e
                                          ``--shot_noise_rate_hz``.
``leak_hz``                   0.0         leak events: the reference level drifts so that a
                                          static pixel emits ON events at this rate; dL gains
                                          c+ * leak_hz / fps per frame pair. v2e
                                          ``--leak_rate_hz``.
``refractory_max_events``     0 (off)     refractory cap: at most this many events per pixel
                                          per frame pair; the rest are lost and the reference
                                          level still catches up (a DVS pixel resets to the
                                          current log intensity after its refractory period).
                                          v2e ``--refractory_period_s`` expressed per frame
                                          pair.
``dead_fraction``             0.0         fraction of dead pixels: they never fire.
``stuck_fraction``            0.0         fraction of stuck pixels: they fire one fixed
``stuck_rate_hz``             0.0         polarity at ``stuck_rate_hz`` (Poisson) whatever the
                                          scene. Dead / stuck pixels as in Prophesee's
                                          sensor-defect notions (issue text).
``noise_mode``                per_frame   ``per_frame``: ``noise_std`` and ``hot_pixels`` act
                                          per frame pair (the V2V reference), so noise per
                                          second grows with the source fps;
                                          ``per_second``: they are given at
                                          ``noise_reference_fps`` and rescaled for the clip's
                                          fps, sigma * sqrt(ref / fps) and H * ref / fps, so
                                          background noise and hot-pixel rates per second do
                                          not depend on the source fps.
``noise_reference_fps``       30.0        fps at which ``noise_std`` / ``hot_pixels`` were set.
============================  ==========  ==================================================

Per-clip pixel defects (mismatched thresholds, dead / stuck maps) are drawn once with
:func:`draw_pixel_state` and must be passed to every chunk of the same clip.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Optional, Tuple

import numpy as np

from v2v_server.checks import check_keys
from v2v_server.simulation.kernel import run_kernel
from v2v_server.simulation.simulate import (TESTED, SensorParams, _lut64, check_frames, check_tested, draw_noise_seed,
                                           simulate_voxels, start_state)

__all__ = ["NonIdealities", "PixelState", "add_pixel_events", "draw_pixel_state", "effective_noise",
           "simulate_voxels_nonideal"]

NOISE_MODES = ("per_frame", "per_second")


@dataclass(frozen=True)
class NonIdealities:
    """Switches for the sensor non-idealities (see the module table for models and sources).

    Raises:
        ValueError: naming ``nonidealities.<key>`` for a negative / non-finite value, a
            fraction outside [0, 1], a non-integer cap, an unknown ``noise_mode``, or a
            ``threshold_sigma`` outside what the kernel is tested at (``simulate.check_tested``).
    """

    threshold_sigma: float = 0.0
    shot_noise_hz: float = 0.0
    leak_hz: float = 0.0
    refractory_max_events: int = 0
    dead_fraction: float = 0.0
    stuck_fraction: float = 0.0
    stuck_rate_hz: float = 0.0
    noise_mode: str = "per_frame"
    noise_reference_fps: float = 30.0

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            name = f"nonidealities.{f.name}"
            if f.name == "noise_mode":
                if v not in NOISE_MODES:
                    raise ValueError(f"{name} must be one of {NOISE_MODES}, got {v!r}")
                continue
            if f.name == "refractory_max_events":
                if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
                    raise ValueError(f"{name} must be an int >= 0 (0 = off), got {v!r}")
                continue
            try:
                x = float(v)
            except (TypeError, ValueError):
                raise ValueError(f"{name} must be a finite number >= 0, got {v!r}") from None
            if isinstance(v, bool) or not math.isfinite(x) or x < 0:
                raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
            if f.name.endswith("_fraction") and x > 1:
                raise ValueError(f"{name} must be in [0, 1], got {v!r}")
            if f.name == "noise_reference_fps" and x == 0:
                raise ValueError(f"{name} must be > 0, got {v!r}")
            if f.name in TESTED:
                check_tested(name, f.name, x)
            object.__setattr__(self, f.name, x)

    @classmethod
    def from_dict(cls, d: Optional[dict]) -> "NonIdealities":
        """From the ``nonidealities:`` config mapping (None: all off); unknown keys raise
        ``ValueError`` naming them."""
        if d is None:
            return cls()
        if isinstance(d, NonIdealities):
            return d
        if not isinstance(d, dict):
            raise ValueError(f"nonidealities must be a mapping, got {type(d).__name__}")
        check_keys(d, (f.name for f in fields(cls)), "nonidealities")
        return cls(**d)

    def to_dict(self) -> dict:
        """Plain dict (msgpack / YAML safe), for each sample's params."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @property
    def enabled(self) -> bool:
        """True when anything differs from the plain V2V model."""
        return self != NonIdealities(noise_reference_fps=self.noise_reference_fps)


@dataclass(frozen=True)
class PixelState:
    """Per-clip pixel defects. Arrays are (H, W).

    Attributes:
        pos_threshold, neg_threshold: float64 per-pixel c+, c- (log-intensity units).
        dead: bool mask of dead pixels.
        stuck: int8 polarity of stuck pixels (0 = not stuck, +1 / -1).
    """

    pos_threshold: np.ndarray
    neg_threshold: np.ndarray
    dead: np.ndarray
    stuck: np.ndarray


def draw_pixel_state(nonideal: NonIdealities, params: SensorParams, shape: Tuple[int, int],
                     rng: np.random.Generator) -> PixelState:
    """Draw a clip's per-pixel thresholds and dead / stuck maps (nothing is drawn for a
    switch that is off, so ``rng`` is untouched when all are off).

    Returns:
        :class:`PixelState` of the given (H, W) shape.
    """
    h, w = shape
    cp = np.full((h, w), params.pos_threshold)
    cn = np.full((h, w), params.neg_threshold)
    s = nonideal.threshold_sigma
    if s > 0:
        cp = np.maximum(rng.normal(params.pos_threshold, s, (h, w)), 0.01 * params.pos_threshold)
        cn = np.maximum(rng.normal(params.neg_threshold, s, (h, w)), 0.01 * params.neg_threshold)
    dead = np.zeros((h, w), bool)
    if nonideal.dead_fraction > 0:
        dead = rng.random((h, w)) < nonideal.dead_fraction
    stuck = np.zeros((h, w), np.int8)
    if nonideal.stuck_fraction > 0:
        m = (rng.random((h, w)) < nonideal.stuck_fraction) & ~dead
        stuck[m] = np.where(rng.random(int(m.sum())) < 0.5, 1, -1)
    return PixelState(cp, cn, dead, stuck)


def effective_noise(params: SensorParams, nonideal: NonIdealities, fps: float) -> Tuple[float, Optional[np.ndarray]]:
    """Per-frame-pair noise sigma and hot-pixel map for a clip at ``fps`` (Hz).

    ``per_frame``: unchanged. ``per_second``: sigma * sqrt(ref / fps) (a random walk's
    variance per second sigma^2 * fps stays sigma_ref^2 * ref) and H * ref / fps (drift
    per second stays H_ref * ref), ref = ``noise_reference_fps``.

    Returns:
        ``(sigma, hot)`` in log-intensity units per frame pair; hot is float64 (H, W) or None.
    """
    hot = None if params.hot_pixels is None else params.hot_pixels.astype(np.float64)
    if nonideal.noise_mode == "per_frame":
        return params.noise_std, hot
    r = nonideal.noise_reference_fps / fps
    return params.noise_std * math.sqrt(r), None if hot is None else hot * r


def _log_intensity_path(frames: np.ndarray, full_scale: int, spec, flow_fn, dtype):
    """What the kernel walks: ``(src, lut, pair_of_step, info)``, the frames' codes with the
    log-intensity table when ``spec`` (a ``refine.RefineSpec``) is off, else the refined path
    (``refine.refine_frames``) with its sub-interval to frame-pair map, and ``info`` naming the
    refinement and its mean sub-frames per pair."""
    from v2v_server.simulation.refine import refine_frames

    if spec.mode == "off":
        return frames, _lut64(full_scale, dtype), None, {}
    src, rinfo = refine_frames(frames, spec, flow_fn, compute_dtype=dtype)
    return src, None, rinfo["pair_of_step"], {"refine": str(spec), "subframes_mean": float(rinfo["subframes"].mean())}


def add_pixel_events(npos: np.ndarray, nneg: np.ndarray, nonideal: NonIdealities, state: PixelState, fps: float,
                     rng: np.random.Generator) -> None:
    """The count post-processing of the module table, in place: shot-noise events (Poisson,
    ``shot_noise_hz`` split evenly between the polarities), dead pixels zeroed, stuck pixels'
    counts replaced by Poisson events (``stuck_rate_hz``) of their polarity. Draws from ``rng``
    in that order, and only for switches that are on.

    Args:
        npos, nneg: float64 (P, H, W) N+ and N- per frame pair (``KernelResult.pos`` / ``neg``).
        nonideal: the switches; state: the clip's defects; fps: frame rate in Hz.

    Raises:
        OverflowError: when a count exceeds 2**31 - 1 (the int32 voxel grid).
    """
    shot_rate = nonideal.shot_noise_hz / fps
    if shot_rate > 0:
        npos += rng.poisson(shot_rate / 2, npos.shape)
        nneg += rng.poisson(shot_rate / 2, nneg.shape)
    npos[:, state.dead] = 0
    nneg[:, state.dead] = 0
    stuck_idx = np.nonzero(state.stuck)
    if stuck_idx[0].size:
        k = rng.poisson(nonideal.stuck_rate_hz / fps, (npos.shape[0], stuck_idx[0].size))
        sign = state.stuck[stuck_idx]
        npos[:, stuck_idx[0], stuck_idx[1]] = np.where(sign > 0, k, 0)
        nneg[:, stuck_idx[0], stuck_idx[1]] = np.where(sign < 0, k, 0)
    if max(npos.max(initial=0), nneg.max(initial=0)) > np.iinfo(np.int32).max:
        raise OverflowError("more than 2**31-1 events in one pixel and frame pair")


def simulate_voxels_nonideal(
    frames: np.ndarray,
    params: SensorParams,
    num_bins: int,
    nonideal: NonIdealities,
    *,
    fps: float,
    initial_potential: Optional[np.ndarray] = None,
    rng: Optional[np.random.Generator] = None,
    pixel_state: Optional[PixelState] = None,
    compute_dtype=np.float32,
    refine="off",
    flow_fn=None,
) -> Tuple[np.ndarray, np.ndarray, dict]:
    """V2V discrete voxel grids with the non-idealities switched on in ``nonideal``.

    With every switch off and ``refine="off"`` this is ``simulate_voxels`` (bit-identical,
    same rng draws). Otherwise it is one call of the kernel (``kernel.run_kernel``, Lou et
    al. 2025, Sec. 3) with per-pixel thresholds, the leak drift added to the pair's extra dL
    and the refractory cap on |N| per pair, followed by the count post-processing: shot-noise
    and stuck-pixel events added, dead pixels zeroed (see the module table). ``refine``
    (``refine.parse_refine`` syntax) feeds the kernel the refined log-intensity path, so
    refinement and non-idealities compose.

    Args:
        frames: uint8 / uint16 (N, H, W), N = L * num_bins + 1.
        params, num_bins, initial_potential, rng, compute_dtype: as ``simulate_voxels``.
        nonideal: the switches.
        fps: frame rate of ``frames`` in Hz (> 0), converts the rates in Hz to per pair.
        pixel_state: the clip's defects; drawn from ``rng`` (after the initial potential)
            when None. Pass the same one to every chunk of a clip.
        refine, flow_fn: as ``refine.simulate_voxels_refined``.

    Returns:
        ``(voxels int32 (L, B, H, W), potential float32 (H, W), info)`` with info =
        {"nonidealities": nonideal.to_dict(), "events": int (events emitted, all sources),
        "events_lost_refractory": int} (plus "refine" and "subframes_mean" when refined).

    Raises:
        ValueError: as ``simulate_voxels``; for fps <= 0; for a ``pixel_state`` of the
            wrong shape.
    """
    from v2v_server.simulation.refine import parse_refine

    nonideal = NonIdealities.from_dict(nonideal)
    spec = parse_refine(refine)
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a finite number > 0, got {fps!r}")
    if not nonideal.enabled and spec.mode == "off":
        vox, pot = simulate_voxels(frames, params, num_bins, initial_potential=initial_potential, rng=rng,
                                   compute_dtype=compute_dtype)
        return vox, pot, {"nonidealities": nonideal.to_dict(), "events": int(np.abs(vox, dtype=np.int64).sum()),
                          "events_lost_refractory": 0}
    sigma, hot = effective_noise(params, nonideal, fps)
    full_scale = check_frames(frames, num_bins)
    n, h, w = frames.shape
    if hot is not None and hot.shape != (h, w):
        raise ValueError(f"hot_pixels has shape {hot.shape}, frames are {(h, w)}")
    dtype = np.dtype(compute_dtype)
    rng, potential = start_state(params, (h, w), initial_potential, rng, dtype)
    st = pixel_state if pixel_state is not None else draw_pixel_state(nonideal, params, (h, w), rng)
    if st.pos_threshold.shape != (h, w):
        raise ValueError(f"pixel_state has shape {st.pos_threshold.shape}, frames are {(h, w)}")
    noise_seed = draw_noise_seed(rng)
    extra = np.zeros((h, w)) if hot is None else hot.copy()
    if nonideal.leak_hz > 0:
        extra += st.pos_threshold * (nonideal.leak_hz / fps)
    src, lut, pair_of_step, info = _log_intensity_path(frames, full_scale, spec, flow_fn, dtype)
    res = run_kernel(src, potential, st.pos_threshold, st.neg_threshold, lut=lut, pair_of_step=pair_of_step,
                     extra=extra, noise_std=sigma, noise_seed=noise_seed,
                     refractory_cap=int(nonideal.refractory_max_events), split=True)
    npos, nneg = res.pos, res.neg  # float64 (n - 1, H, W), after the refractory cap
    add_pixel_events(npos, nneg, nonideal, st, fps, rng)
    voxels = (npos - nneg).astype(np.int32)
    info.update(nonidealities=nonideal.to_dict(), events=int(npos.sum() + nneg.sum()),
                events_lost_refractory=res.lost)
    return voxels.reshape((n - 1) // num_bins, num_bins, h, w), potential.astype(np.float32), info

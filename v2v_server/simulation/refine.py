"""Refinement of the V2V step: intermediate frames only where the motion needs them.

V2V (``simulate.py``) assumes the log intensity moves in a straight line between two
frames. Linear interpolation of the log intensity therefore changes nothing (the counts of
a monotonic path are the V2V counts, see ``tests/test_reference.py``); what a refinement
must add is *motion*: intermediate frames by motion-compensated interpolation
(``reference.interpolate_pair(..., "motion")``, OpenCV DIS flow). The V2V step is then run
on every sub-interval and the counts of a frame pair's sub-intervals are summed into its
bin, so a refined sample is still one discrete voxel grid with one frame pair per bin.

Modes (``--refine`` on the server, recorded per sample as ``str(spec)``):

* ``off``: plain V2V (bit-identical to ``simulate_voxels``).
* ``uniform:K``: K sub-intervals per frame pair (K - 1 motion-compensated frames), as v2e
  does with a fixed SuperSloMo upsampling factor.
* ``adaptive:L``: per frame pair, ``n = ceil(max ||flow|| / L)`` sub-intervals (L in
  pixels per sub-interval, ESIM's adaptive rule applied to flow, the rule v2e uses to pick
  its upsampling factor); pairs with ``max ||flow|| <= L`` take the plain V2V step.
* ``adaptive-dl:L``: ``n = ceil(max |L_i - L_{i-1}| / L)`` (L in log-intensity units;
  ESIM's ``dt = lambda / max |dL/dt|``); needs no flow to decide.

``n`` is capped at ``max_subframes`` (default 16).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Optional, Tuple

import numpy as np

from v2v_server.flow.estimate import dis_flow
from v2v_server.flow.options import DIS_PRESETS
from v2v_server.simulation.kernel import run_kernel
from v2v_server.simulation.reference import interpolate_pair
from v2v_server.simulation.simulate import SensorParams, _lut, check_frames, draw_noise_seed, simulate_voxels, start_state

__all__ = ["RefineSpec", "parse_refine", "plan_subframes", "refine_frames", "simulate_voxels_refined"]

MODES = ("off", "uniform", "adaptive", "adaptive-dl")


@dataclass(frozen=True)
class RefineSpec:
    """How many sub-intervals each frame pair gets (see module doc).

    Attributes:
        mode: "off", "uniform", "adaptive" (flow, pixels) or "adaptive-dl" (log intensity).
        k: sub-intervals per pair for "uniform" (int >= 1).
        lam: lambda for the adaptive modes: pixels of motion per sub-interval ("adaptive")
            or log-intensity units per sub-interval ("adaptive-dl"); finite and > 0.
        max_subframes: cap on sub-intervals per pair (int >= 1).
        flow_preset: DIS preset ("ultrafast", "fast", "medium") for flow and interpolation.

    Raises:
        ValueError: naming ``refine``, for an unknown mode or a bad value.
    """

    mode: str = "off"
    k: int = 1
    lam: float = 1.0
    max_subframes: int = 16
    flow_preset: str = "ultrafast"

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"refine mode must be one of {MODES}, got {self.mode!r}")
        if isinstance(self.k, bool) or not isinstance(self.k, (int, np.integer)) or self.k < 1:
            raise ValueError(f"refine: uniform K must be an int >= 1, got {self.k!r}")
        if not (isinstance(self.lam, (int, float)) and math.isfinite(self.lam) and self.lam > 0):
            raise ValueError(f"refine: adaptive lambda must be a finite number > 0, got {self.lam!r}")
        if not isinstance(self.max_subframes, (int, np.integer)) or self.max_subframes < 1:
            raise ValueError(f"refine: max_subframes must be an int >= 1, got {self.max_subframes!r}")
        if self.flow_preset not in DIS_PRESETS:
            raise ValueError(f"refine: flow_preset must be one of {sorted(DIS_PRESETS)}, got {self.flow_preset!r}")

    def __str__(self) -> str:
        if self.mode == "off":
            return "off"
        if self.mode == "uniform":
            return f"uniform:{self.k}"
        return f"{self.mode}:{self.lam:g}"


def parse_refine(text, *, max_subframes: int = 16, flow_preset: str = "ultrafast") -> RefineSpec:
    """Parse ``"off"``, ``"uniform:K"``, ``"adaptive:L"`` or ``"adaptive-dl:L"``.

    A :class:`RefineSpec` passes through unchanged; ``None`` means "off".

    Raises:
        ValueError: message starting with ``refine``, for anything else.
    """
    if isinstance(text, RefineSpec):
        return text
    if text is None:
        return RefineSpec()
    if not isinstance(text, str):
        raise ValueError(f"refine must be a string like 'off', 'uniform:4' or 'adaptive:2', got {text!r}")
    s = text.strip().lower()
    if s == "off":
        return RefineSpec("off", max_subframes=max_subframes, flow_preset=flow_preset)
    mode, sep, arg = s.partition(":")
    if not sep or mode not in MODES[1:]:
        raise ValueError(
            f"refine must be 'off', 'uniform:K', 'adaptive:LAMBDA_PX' or 'adaptive-dl:LAMBDA', got {text!r}"
        )
    try:
        if mode == "uniform":
            k = int(arg)
            if str(k) != arg.strip():
                raise ValueError
            return RefineSpec("uniform", k=k, max_subframes=max(max_subframes, k), flow_preset=flow_preset)
        return RefineSpec(mode, lam=float(arg), max_subframes=max_subframes, flow_preset=flow_preset)
    except ValueError as e:
        if str(e).startswith("refine"):
            raise
        raise ValueError(f"refine {mode}: bad value {arg!r} in {text!r}") from None


FlowFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


def plan_subframes(frames: np.ndarray, spec: RefineSpec, flow_fn: Optional[FlowFn] = None, logs: Optional[np.ndarray] = None):
    """Sub-intervals per frame pair under ``spec``.

    Args:
        frames: uint8 / uint16 (N, H, W) frames.
        spec: the refinement.
        flow_fn: ``(a, b) -> (H, W, 2)`` flow in pixels; DIS with ``spec.flow_preset`` when None.
        logs: (N, H, W) log intensity (only needed for "adaptive-dl"; computed if None).

    Returns:
        ``(ks, forward_flows, max_flow_px)``: int64 (N - 1,) sub-intervals per pair, a list
        of the forward flows computed (None where not computed) and float64 (N - 1,)
        max flow magnitude per pair in pixels (NaN where not computed).
    """
    n = frames.shape[0]
    if flow_fn is None:
        flow_fn = lambda a, b: dis_flow(a, b, spec.flow_preset)  # noqa: E731
    flows = [None] * (n - 1)
    fmax = np.full(n - 1, np.nan)
    if spec.mode == "off":
        return np.ones(n - 1, np.int64), flows, fmax
    if spec.mode == "uniform":
        return np.full(n - 1, spec.k, np.int64), flows, fmax
    if spec.mode == "adaptive-dl":
        if logs is None:
            logs = _lut(check_frames(frames, 1), np.float32)[frames]
        need = np.array([np.abs(logs[i + 1] - logs[i]).max() for i in range(n - 1)], dtype=np.float64)
    else:
        for i in range(n - 1):
            flows[i] = flow_fn(frames[i], frames[i + 1])
            fmax[i] = float(np.sqrt((flows[i].astype(np.float64) ** 2).sum(-1)).max())
        need = fmax
    ks = np.clip(np.ceil(need / spec.lam), 1, spec.max_subframes).astype(np.int64)
    return ks, flows, fmax


def refine_frames(frames: np.ndarray, spec, flow_fn: Optional[FlowFn] = None, *, compute_dtype=np.float32):
    """Refined log-intensity frames of a clip.

    Args:
        frames: uint8 (full scale 255) or uint16 (65535) (N, H, W) luma frames.
        spec: a :class:`RefineSpec` or a string for :func:`parse_refine`.
        flow_fn: optional flow ``(a, b) -> (H, W, 2)`` pixels; DIS by default.
        compute_dtype: precision of the log-intensity table (as ``simulate_voxels``).

    Returns:
        ``(logs, info)``: float64 (M, H, W) log intensity (log-intensity units) with the
        original frames at the pair boundaries and motion-compensated frames between, and
        ``info`` = {"refine": str(spec), "subframes": int64 (N - 1,) sub-intervals per
        pair, "pair_of_step": int64 (M - 1,) frame pair of each sub-interval,
        "max_flow_px": float64 (N - 1,) (NaN where not computed)}.

    Raises:
        ValueError: for a bad spec (naming ``refine``) or bad frames.
    """
    spec = parse_refine(spec)
    if not isinstance(frames, np.ndarray) or frames.ndim != 3 or frames.dtype not in (np.uint8, np.uint16):
        raise ValueError("frames must be a uint8 or uint16 (N, H, W) array")
    full_scale = check_frames(frames, 1)
    base = _lut(full_scale, compute_dtype).astype(np.float64)[frames]
    if flow_fn is None:
        flow_fn = lambda a, b: dis_flow(a, b, spec.flow_preset)  # noqa: E731
    ks, flows, fmax = plan_subframes(frames, spec, flow_fn, base)
    out = [base[:1]]
    for i, k in enumerate(ks.tolist()):
        if k == 1:
            out.append(base[i + 1 : i + 2])
            continue
        f01 = flows[i] if flows[i] is not None else flow_fn(frames[i], frames[i + 1])
        f10 = flow_fn(frames[i + 1], frames[i])
        out.append(interpolate_pair(base[i], base[i + 1], np.arange(1, k + 1) / k, "motion", flow01=f01, flow10=f10))
    info = {
        "refine": str(spec),
        "subframes": ks,
        "pair_of_step": np.repeat(np.arange(ks.size), ks),
        "max_flow_px": fmax,
    }
    return np.concatenate(out), info


def simulate_voxels_refined(
    frames: np.ndarray,
    params: SensorParams,
    num_bins: int,
    refine="off",
    *,
    initial_potential: Optional[np.ndarray] = None,
    rng: Optional[np.random.Generator] = None,
    compute_dtype=np.float32,
    flow_fn: Optional[FlowFn] = None,
) -> Tuple[np.ndarray, np.ndarray, dict]:
    """V2V with refinement: same contract as ``simulate_voxels`` plus an info dict.

    The V2V step (Lou et al. 2025, Sec. 3) runs on each sub-interval; frame pair i's
    noise N_i and the hot-pixel map H are split evenly over its sub-intervals (the event
    reference spreads them linearly, so with K motion sub-frames this equals
    ``reference.simulate_events(..., subframes=K, interpolation="motion")``'s discrete
    voxel exactly); the counts of a pair's sub-intervals are summed into its bin. One call
    of the kernel (``kernel.run_kernel``) with the refined path as its log-intensity input.
    ``rng`` is drawn in the same order as ``simulate_voxels`` (initial potential, then the
    noise seed), so "off" and any refinement share noise under one seed.

    Args:
        frames: uint8 / uint16 (N, H, W), N = L * num_bins + 1.
        params, num_bins, initial_potential, rng, compute_dtype: as ``simulate_voxels``.
        refine: :class:`RefineSpec` or string ("off", "uniform:K", "adaptive:L",
            "adaptive-dl:L").
        flow_fn: optional flow function replacing DIS.

    Returns:
        ``(voxels int32 (L, B, H, W), potential float32 (H, W), info)``; info =
        {"refine": str, "subframes_mean": float, "subframes_max": int, "events": int
        (N+ + N- summed over all sub-intervals, i.e. the event count)}. Record
        ``info["refine"]`` in the sample's params.

    Raises:
        ValueError: as ``simulate_voxels`` and :func:`parse_refine`.
    """
    spec = parse_refine(refine)
    if spec.mode == "off":
        vox, pot = simulate_voxels(frames, params, num_bins, initial_potential=initial_potential, rng=rng,
                                   compute_dtype=compute_dtype)
        return vox, pot, {"refine": "off", "subframes_mean": 1.0, "subframes_max": 1,
                          "events": int(np.abs(vox, dtype=np.int64).sum())}
    check_frames(frames, num_bins)
    n, h, w = frames.shape
    dtype = np.dtype(compute_dtype)
    rng, potential = start_state(params, (h, w), initial_potential, rng, dtype)
    noise_seed = draw_noise_seed(rng)
    logs, info = refine_frames(frames, spec, flow_fn, compute_dtype=dtype)
    ks = info["subframes"]
    res = run_kernel(logs, potential, params.pos_threshold, params.neg_threshold, pair_of_step=info["pair_of_step"],
                     extra=0.0 if params.hot_pixels is None else params.hot_pixels, noise_std=params.noise_std,
                     noise_seed=noise_seed)
    return (
        res.net.reshape((n - 1) // num_bins, num_bins, h, w),
        potential.astype(np.float32),
        {"refine": str(spec), "subframes_mean": float(ks.mean()), "subframes_max": int(ks.max()),
         "events": res.events},
    )

"""Event-level reference simulator and the two voxel representations built from events.

This is the slow, accurate end of the speed/accuracy trade that V2V (``simulate.py``)
shortcuts. From frames and a :class:`~v2v_server.simulation.simulate.SensorParams` it emits events
``(x, y, t, p)`` the way frame-based event simulators do:

* the log intensity ``L = log(1e-3 + (F / full_scale) ** 2.2)`` (same table as V2V);
* optional intermediate frames per frame pair, made either by linear interpolation of
  ``L`` ("linear") or by motion-compensated interpolation ("motion": OpenCV DIS optical
  flow in both directions, both neighbours warped to the intermediate time and blended,
  with SuperSloMo's linear approximation of the intermediate flows, Jiang et al. CVPR 2018,
  the interpolator v2e uses);
* inside every sub-interval ``L`` moves linearly and each pixel fires whenever
  ``L - L_ref`` reaches ``+c+`` or ``-c-`` (ESIM, Rebecq et al. CoRL 2018; v2e, Hu et al.
  CVPRW 2021); the event time is the linear interpolation of the threshold crossing inside
  the sub-interval, and ``L_ref`` moves by one threshold per event;
* the background noise ``N_i`` and hot-pixel map ``H`` of V2V are spread linearly over
  frame pair ``i`` (the noise seed is drawn from ``rng`` in exactly the order
  ``simulate_voxels`` draws it, so a shared seed gives the same noise).

The crossings themselves are counted by the project's one kernel (``kernel.run_kernel``
with ``events=True``), which also reports the fraction of the sub-interval at which each
level was reached; this module builds the path and turns fractions into times.

The state ``dL_hat = L - L_ref`` (residual potential) is the same quantity V2V carries, so
with one sub-interval per frame pair (or any linear interpolation) the event counts per
frame pair equal V2V's counts exactly: the test of the paper's claim lives in
``tests/test_reference.py``.

Voxel grids from events follow the paper (Lou et al. 2025, Sec. 3, Eq. for the two
representations), with ``t`` normalised to [0, 1] over the voxel's time span:

* interpolated voxel grid ``V_intp(b) = sum_k p_k max(0, 1 - |(B - 1) t_k - b|)``;
* discrete voxel grid (SBT) ``V_disc(b) = sum_k p_k 1[b / B <= t_k < (b + 1) / B]``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Sequence, Tuple, Union

import numpy as np

from v2v_server.flow.estimate import dis_flow
from v2v_server.simulation.kernel import full_scale_of, run_kernel
from v2v_server.simulation.simulate import SensorParams, draw_noise_seed, log_intensity_lut

__all__ = [
    "Events",
    "log_frames",
    "interpolate_pair",
    "simulate_events",
    "voxel_discrete",
    "voxel_interpolated",
    "events_to_voxels",
]

FlowFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass
class Events:
    """An event stream, sorted by sub-interval (so by time up to ties inside one).

    Attributes:
        x: int32 (M,) column, pixels.
        y: int32 (M,) row, pixels.
        t: float64 (M,) timestamp, seconds (frame ``i`` is at ``i / fps``).
        p: int8 (M,) polarity, +1 or -1.
    """

    x: np.ndarray
    y: np.ndarray
    t: np.ndarray
    p: np.ndarray

    def __len__(self) -> int:
        return int(self.t.size)


def log_frames(frames: np.ndarray) -> np.ndarray:
    """Log intensity of uint8 / uint16 frames (any shape), float64, log-intensity units.

    Uses the float32 table of ``simulate_voxels``' default ``compute_dtype`` widened to
    float64, so the reference sees bit-identical log intensities.

    Raises:
        ValueError: for any other dtype.
    """
    lut = log_intensity_lut(full_scale_of(frames), np.float32).astype(np.float64)
    return lut[frames]


def _warp(img: np.ndarray, flow: np.ndarray, grid: np.ndarray) -> np.ndarray:
    import cv2

    m = np.ascontiguousarray(grid + flow, dtype=np.float32)
    return cv2.remap(img, m, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _grid(h: int, w: int) -> np.ndarray:
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    return np.stack([xs, ys], axis=-1)


def interpolate_pair(
    l0: np.ndarray,
    l1: np.ndarray,
    ts: Sequence[float],
    method: str = "linear",
    *,
    flow01: Optional[np.ndarray] = None,
    flow10: Optional[np.ndarray] = None,
) -> np.ndarray:
    """Intermediate log-intensity frames between two frames.

    Args:
        l0, l1: (H, W) float log intensity at t = 0 and t = 1 (log-intensity units).
        ts: times in [0, 1] (fractions of the frame interval).
        method: "linear" (``(1 - t) l0 + t l1``) or "motion": both neighbours warped to
            time t along the intermediate flows ``F_t0 = -(1 - t) t F01 + t^2 F10`` and
            ``F_t1 = (1 - t)^2 F01 - t (1 - t) F10`` (SuperSloMo's approximation; t = 0.5
            is "warp both half-way") and blended ``(1 - t) l0(x + F_t0) + t l1(x + F_t1)``.
            t = 0 and t = 1 return ``l0`` and ``l1`` exactly.
        flow01, flow10: (H, W, 2) float32 flows in pixels (required for "motion").

    Returns:
        float64 (len(ts), H, W) log intensity.

    Raises:
        ValueError: for an unknown method or missing flows.
    """
    ts = np.asarray(ts, dtype=np.float64)
    out = np.empty((ts.size,) + l0.shape, dtype=np.float64)
    if method == "linear":
        for j, t in enumerate(ts):
            out[j] = (1.0 - t) * l0 + t * l1
        return out
    if method != "motion":
        raise ValueError(f"interpolation must be 'linear' or 'motion', got {method!r}")
    if flow01 is None or flow10 is None:
        raise ValueError("motion interpolation needs flow01 and flow10")
    grid = _grid(*l0.shape)
    a = np.ascontiguousarray(l0, dtype=np.float64)
    b = np.ascontiguousarray(l1, dtype=np.float64)
    for j, t in enumerate(ts.tolist()):
        if t <= 0.0:
            out[j] = l0
        elif t >= 1.0:
            out[j] = l1
        else:
            ft0 = (-(1 - t) * t) * flow01 + (t * t) * flow10
            ft1 = ((1 - t) ** 2) * flow01 - (t * (1 - t)) * flow10
            out[j] = (1 - t) * _warp(a, ft0, grid) + t * _warp(b, ft1, grid)
    return out


def simulate_events(
    frames: np.ndarray,
    params: SensorParams,
    *,
    subframes: Union[int, Sequence[int]] = 1,
    interpolation: str = "linear",
    flow_preset: str = "medium",
    flow_fn: Optional[FlowFn] = None,
    fps: float = 30.0,
    initial_potential: Optional[np.ndarray] = None,
    rng: Optional[np.random.Generator] = None,
) -> Tuple[Events, np.ndarray]:
    """Event-level reference simulation of a clip (ESIM / v2e style, see module doc).

    Args:
        frames: uint8 or uint16 (N, H, W) luma frames, N >= 2, frame i at time i / fps.
        params: contrast thresholds c+, c- (log-intensity units), noise_std and hot pixels
            as in V2V: noise N_i ~ N(0, sigma^2) and H are added per frame pair, spread
            linearly over the pair.
        subframes: K, sub-intervals per frame pair (K - 1 intermediate frames); an int for
            all pairs or a sequence of N - 1 ints (adaptive refinement).
        interpolation: "linear" (log intensity) or "motion" (DIS flow, see
            :func:`interpolate_pair`). Unused where K = 1.
        flow_preset: DIS preset for "motion" when ``flow_fn`` is None.
        flow_fn: optional ``(a, b) -> (H, W, 2)`` flow in pixels replacing DIS.
        fps: frame rate of ``frames``, Hz; sets the time unit of ``Events.t`` (seconds).
        initial_potential: (H, W) dL_hat(t_0) in log-intensity units; ``None`` draws
            U[-c-, c+] from ``rng`` (float32, as ``simulate_voxels`` does).
        rng: ``numpy.random.Generator`` for the initial potential and the noise.

    Returns:
        ``(events, potential)``: :class:`Events` sorted by sub-interval, and the float64
        (H, W) residual potential after the last frame (log-intensity units).

    Raises:
        ValueError: for bad frames, subframes, interpolation, preset or shapes.
    """
    if not isinstance(params, SensorParams):
        raise ValueError(f"params must be a SensorParams, got {type(params).__name__}")
    if not isinstance(frames, np.ndarray) or frames.ndim != 3 or frames.shape[0] < 2:
        raise ValueError(f"frames must be an (N >= 2, H, W) array, got {getattr(frames, 'shape', frames)!r}")
    n, h, w = frames.shape
    logs = log_frames(frames)
    ks = np.broadcast_to(np.asarray(subframes), (n - 1,)).astype(np.int64)
    if np.any(ks < 1):
        raise ValueError(f"subframes must be >= 1 per frame pair, got {subframes!r}")
    if interpolation not in ("linear", "motion"):
        raise ValueError(f"interpolation must be 'linear' or 'motion', got {interpolation!r}")
    if not (fps > 0):
        raise ValueError(f"fps must be > 0, got {fps!r}")
    if rng is None:
        rng = np.random.default_rng()
    cp, cn = params.pos_threshold, params.neg_threshold
    if initial_potential is None:
        pot = rng.uniform(-cn, cp, size=(h, w)).astype(np.float32).astype(np.float64)
    else:
        initial_potential = np.asarray(initial_potential)
        if initial_potential.shape != (h, w):
            raise ValueError(f"initial_potential has shape {initial_potential.shape}, frames are {(h, w)}")
        pot = initial_potential.astype(np.float64, copy=True)
    noise_seed = draw_noise_seed(rng)  # same order as simulate_voxels: same noise
    hot = params.hot_pixels
    if hot is not None and hot.shape != (h, w):
        raise ValueError(f"hot_pixels has shape {hot.shape}, frames are {(h, w)}")
    if flow_fn is None:
        flow_fn = lambda a, b: dis_flow(a, b, flow_preset)  # noqa: E731
    pair_of_step = np.repeat(np.arange(n - 1), ks)
    res = run_kernel(_subframe_path(frames, logs, ks, interpolation, flow_fn), pot, cp, cn, pair_of_step=pair_of_step,
                     extra=0.0 if hot is None else hot, noise_std=params.noise_std, noise_seed=noise_seed,
                     events=True)
    pix = res.event_pixel
    t = _event_times(res.event_step, res.event_fraction, ks, pair_of_step, fps)
    return Events((pix % w).astype(np.int32), (pix // w).astype(np.int32), t, res.event_polarity.copy()), pot


def _subframe_path(frames: np.ndarray, logs: np.ndarray, ks: np.ndarray, interpolation: str, flow_fn) -> np.ndarray:
    """The log-intensity path the events are simulated along: float64 (1 + sum(ks), H, W), the
    frames' log intensities ``logs`` with ``ks[i] - 1`` intermediate frames between frames i
    and i + 1 (:func:`interpolate_pair`; "motion" asks ``flow_fn`` for both flows of the pair)."""
    path = [logs[:1]]
    for i in range(len(ks)):
        k = int(ks[i])
        ts = np.arange(1, k + 1) / k
        if k == 1 or interpolation == "linear":
            path.append(interpolate_pair(logs[i], logs[i + 1], ts, "linear"))
        else:
            f01 = flow_fn(frames[i], frames[i + 1])
            f10 = flow_fn(frames[i + 1], frames[i])
            path.append(interpolate_pair(logs[i], logs[i + 1], ts, "motion", flow01=f01, flow10=f10))
    return np.concatenate(path)


def _event_times(step: np.ndarray, fraction: np.ndarray, ks: np.ndarray, pair_of_step: np.ndarray,
                 fps: float) -> np.ndarray:
    """float64 event times in seconds from each event's sub-interval ``step`` and its
    ``fraction`` of it: sub-interval j of pair i (of ``ks[i]``) spans
    [(i + j / k) / fps, (i + (j + 1) / k) / fps]; a crossing exactly at the frame time stays in
    its pair (the time is kept below (i + 1) / fps)."""
    first = np.concatenate([[0], np.cumsum(ks)[:-1]])
    i = pair_of_step[step]
    k = ks[i].astype(np.float64)
    j = (step - first[i]).astype(np.float64)
    ta = (i + j / k) / fps
    tb = (i + (j + 1) / k) / fps
    t = ta + fraction * (tb - ta)
    np.minimum(t, np.nextafter((i + 1) / fps, -np.inf), out=t)
    return t


def _normalised_times(events: Events, t_start: float, t_end: float, num_bins: int = 1):
    """Events inside [t_start, t_end] (mask) and their times normalised to [0, 1]; checks
    the span and ``num_bins`` (ValueError)."""
    if num_bins < 1:
        raise ValueError(f"num_bins must be >= 1, got {num_bins}")
    if not t_end > t_start:
        raise ValueError(f"t_end must be > t_start, got [{t_start}, {t_end}]")
    keep = (events.t >= t_start) & (events.t <= t_end)
    u = (events.t[keep] - t_start) / (t_end - t_start)
    return keep, np.clip(u, 0.0, 1.0)


def voxel_discrete(events: Events, num_bins: int, shape: Tuple[int, int], t_start: float, t_end: float) -> np.ndarray:
    """Discrete voxel grid (SBT) ``V_disc(b) = sum p 1[b/B <= t < (b+1)/B]`` (paper Sec. 3).

    Args:
        events: the stream; events outside [t_start, t_end] (seconds) are ignored.
        num_bins: B >= 1.
        shape: (H, W) of the sensor, pixels.
        t_start, t_end: the voxel's time span, seconds; ``t = (t_k - t_start) / (t_end -
            t_start)``. An event at exactly ``t = 1`` counts in the last bin.

    Returns:
        int32 (B, H, W) signed event counts.

    Raises:
        ValueError: for t_end <= t_start or num_bins < 1.
    """
    keep, u = _normalised_times(events, t_start, t_end, num_bins)
    h, w = shape
    b = np.minimum(np.floor(u * num_bins).astype(np.int64), num_bins - 1)
    flat = (b * h + events.y[keep]) * w + events.x[keep]
    v = np.bincount(flat, weights=events.p[keep].astype(np.float64), minlength=num_bins * h * w)
    return np.rint(v).astype(np.int32).reshape(num_bins, h, w)


def voxel_interpolated(events: Events, num_bins: int, shape: Tuple[int, int], t_start: float, t_end: float) -> np.ndarray:
    """Interpolated voxel grid ``V_intp(b) = sum p max(0, 1 - |(B-1) t - b|)`` (paper Sec. 3).

    Args: as :func:`voxel_discrete`.

    Returns:
        float32 (B, H, W); each event splits its polarity between the two bins nearest to
        ``(B - 1) t`` (all of it to bin 0 when B = 1).

    Raises:
        ValueError: for t_end <= t_start or num_bins < 1.
    """
    keep, u = _normalised_times(events, t_start, t_end, num_bins)
    h, w = shape
    pol = events.p[keep].astype(np.float64)
    pix = events.y[keep].astype(np.int64) * w + events.x[keep]
    tb = (num_bins - 1) * u
    lo = np.floor(tb).astype(np.int64)
    frac = tb - lo
    v = np.bincount(lo * h * w + pix, weights=pol * (1 - frac), minlength=(num_bins + 1) * h * w)
    v += np.bincount(np.minimum(lo + 1, num_bins) * h * w + pix, weights=pol * frac, minlength=(num_bins + 1) * h * w)
    return v[: num_bins * h * w].astype(np.float32).reshape(num_bins, h, w)


def events_to_voxels(
    events: Events,
    num_voxels: int,
    num_bins: int,
    shape: Tuple[int, int],
    fps: float,
    *,
    frames_per_bin: int = 1,
    kind: str = "discrete",
) -> np.ndarray:
    """Consecutive voxel grids of a clip, voxel l spanning frames [l B f, (l + 1) B f].

    Args:
        events: from :func:`simulate_events` with the same ``fps``.
        num_voxels: L; num_bins: B; shape: (H, W); fps: Hz.
        frames_per_bin: f, frame intervals per bin (1 = V2V's one frame pair per bin).
        kind: "discrete" (int32) or "interpolated" (float32).

    Returns:
        (L, B, H, W) voxel grids.

    Raises:
        ValueError: for an unknown kind.
    """
    fn = {"discrete": voxel_discrete, "interpolated": voxel_interpolated}.get(kind)
    if fn is None:
        raise ValueError(f"kind must be 'discrete' or 'interpolated', got {kind!r}")
    span = num_bins * frames_per_bin
    # events are sorted by sub-interval, hence by frame pair: slice per voxel
    edges = np.searchsorted(events.t, [l * span / fps for l in range(num_voxels + 1)], side="left")
    out = []
    for l in range(num_voxels):
        lo, hi = edges[l], edges[l + 1] if l + 1 < num_voxels else events.t.size
        sub = Events(events.x[lo:hi], events.y[lo:hi], events.t[lo:hi], events.p[lo:hi])
        out.append(fn(sub, num_bins, shape, l * span / fps, (l + 1) * span / fps))
    return np.stack(out)

"""V2V core: discrete voxel grids computed directly from video frames.

Implements the video-to-voxel simulation of Lou et al., "V2V: Scaling Event-Based
Vision through Efficient Video-to-Voxel Simulation" (NeurIPS 2025), Sec. 3:

* reverse gamma and log intensity: ``I = (F / full_scale) ** 2.2``, ``L = log(eps + I)``
  with ``eps = 1e-3``;
* per frame pair ``i``: ``dL = dL_hat(t_{i-1}) + (L_i - L_{i-1}) + N_i + H`` where
  ``N_i ~ N(0, sigma^2)`` per pixel and ``H`` is the per-clip hot-pixel map;
* ``N+ = max(0, floor(dL / c+))``, ``N- = max(0, floor(-dL / c-))``,
  ``dL_hat = dL - c+ * N+ + c- * N-``; the voxel bin value is ``N+ - N-``;
* ``dL_hat(t_0) ~ U[-c-, c+]``.

All potentials and thresholds are in log-intensity units.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Optional, Tuple

import numpy as np

from v2v_server.checks import check_keys
from v2v_server.simulation.kernel import full_scale_of, run_kernel

#: Offset inside the log, ``L = log(LOG_EPS + I)`` (paper Sec. 3, reference repo).
LOG_EPS = 1e-3
#: Display gamma undone before the log (``I = (F / full_scale) ** GAMMA``).
GAMMA = 2.2

#: What the simulation kernel is tested at, per recipe value that reaches it: ``(lo, hi, what)``
#: (tests/test_stability.py draws contrast thresholds of 1e-3 .. 10 log-intensity units, the ratio
#: of c- to c+ up to 100 either way, noise sigma 0 .. 10 and hot-pixel values up to 100 in
#: magnitude, and checks the residual's range, the conservation law and counts that never wrap).
#: A hot pixel's value is N(0, s^2): ``hot_pixel_std`` up to 20 keeps 5 s inside the tested 100.
#: A pixel's threshold spread (``nonidealities.threshold_sigma``) is a threshold: at most the
#: largest tested. Every configuration's ranges are checked against it when read (YAML, flags,
#: a fitted recipe: :func:`check_tested`, called by ``ParamRanges`` and ``nonideal.NonIdealities``).
TESTED = {
    "threshold": (1e-3, 10.0, "contrast threshold"),
    "ratio": (1.0, 100.0, "threshold ratio"),
    "noise_std": (0.0, 10.0, "noise sigma"),
    "hot_pixel_std": (0.0, 20.0, "hot-pixel spread"),
    "threshold_sigma": (0.0, 10.0, "threshold spread"),
}


def check_tested(name: str, kind: str, *values: float) -> None:
    """Refuse a value outside the range the kernel is tested at (:data:`TESTED`): the one rule
    for a configuration's sensor values, wherever they come from.

    Args:
        name: the key as the user wrote it, for the message (``ranges.threshold``).
        kind: its entry of :data:`TESTED` (``threshold``).
        values: the values to check (a range's lo and hi).

    Raises:
        ValueError: naming ``name``, the value and the bound, e.g. ``ranges.threshold: 1e+308
            is above 10, the largest contrast threshold the simulation kernel is tested at
            (tests/test_stability.py)``.
    """
    lo, hi, what = TESTED[kind]
    for v in values:
        if v > hi:
            raise ValueError(f"{name}: {v:g} is above {hi:g}, the largest {what} the simulation kernel is tested at "
                             f"(tests/test_stability.py)")
        if v < lo:
            raise ValueError(f"{name}: {v:g} is below {lo:g}, the smallest {what} the simulation kernel is tested at "
                             f"(tests/test_stability.py)")


__all__ = [
    "LOG_EPS",
    "GAMMA",
    "TESTED",
    "check_tested",
    "SensorParams",
    "ParamRanges",
    "log_intensity_lut",
    "check_frames",
    "draw_noise_seed",
    "simulate_voxels",
    "polarity_counts",
    "sample_params",
]


def _finite_positive(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return v


@dataclass(frozen=True, eq=False)
class SensorParams:
    """Sensor parameters of one simulated event camera (drawn afresh per sample).

    Attributes:
        pos_threshold: contrast threshold c+ (log-intensity units), finite and > 0.
        neg_threshold: contrast threshold c- (log-intensity units), finite and > 0.
        noise_std: sigma of the per-frame-pair Gaussian background noise N_i
            (log-intensity units), finite and >= 0.
        hot_pixels: per-clip hot-pixel map H, shape (H, W), float; added to dL at every
            frame pair (log-intensity units). ``None`` means no hot pixels. Stored as a
            read-only float32 copy.

    Raises:
        ValueError: naming the field, for a non-finite or non-positive threshold, a
            negative or non-finite ``noise_std``, or a ``hot_pixels`` that is not a finite
            2-D numeric array.
    """

    pos_threshold: float
    neg_threshold: float
    noise_std: float = 0.0
    hot_pixels: Optional[np.ndarray] = field(default=None, repr=False)

    def __post_init__(self):
        object.__setattr__(self, "pos_threshold", _finite_positive("pos_threshold", self.pos_threshold))
        object.__setattr__(self, "neg_threshold", _finite_positive("neg_threshold", self.neg_threshold))
        try:
            sigma = float(self.noise_std)
        except (TypeError, ValueError):
            raise ValueError(f"noise_std must be a finite number >= 0, got {self.noise_std!r}") from None
        if not math.isfinite(sigma) or sigma < 0:
            raise ValueError(f"noise_std must be a finite number >= 0, got {self.noise_std!r}")
        object.__setattr__(self, "noise_std", sigma)
        hp = self.hot_pixels
        if hp is not None:
            if not isinstance(hp, np.ndarray) or hp.ndim != 2:
                raise ValueError(
                    f"hot_pixels must be a 2-D (H, W) float array or None, got "
                    f"{type(hp).__name__}{getattr(hp, 'shape', '')}"
                )
            if not (np.issubdtype(hp.dtype, np.floating) or np.issubdtype(hp.dtype, np.integer)):
                raise ValueError(f"hot_pixels must be a numeric (H, W) array, got dtype {hp.dtype}")
            hp = np.array(hp, dtype=np.float32, copy=True)
            if not np.all(np.isfinite(hp)):
                raise ValueError("hot_pixels must contain only finite values")
            hp.setflags(write=False)
            object.__setattr__(self, "hot_pixels", hp)

    def summary(self) -> dict:
        """Plain-dict description for logs and the wire (msgpack-safe; the hot-pixel map
        is summarised as its count of non-zero pixels and the std of their values)."""
        d = {
            "pos_threshold": self.pos_threshold,
            "neg_threshold": self.neg_threshold,
            "noise_std": self.noise_std,
            "hot_pixel_count": 0,
            "hot_pixel_std": 0.0,
        }
        if self.hot_pixels is not None:
            nz = self.hot_pixels[self.hot_pixels != 0]
            d["hot_pixel_count"] = int(nz.size)
            d["hot_pixel_std"] = float(nz.std()) if nz.size else 0.0
        return d


@dataclass(frozen=True)
class ParamRanges:
    """Ranges of the per-sample sensor randomisation (paper Sec. 3.2; defaults are the
    reference repo's WebVid training ranges).

    Attributes:
        threshold: (lo, hi) of the base contrast threshold t1 ~ U[lo, hi], log-intensity units.
        ratio: (lo, hi) of the threshold ratio r ~ U[lo, hi]; t2 = t1 * r, and a fair coin
            decides whether c+ = t1, c- = t2 or the reverse.
        noise_std: (lo, hi) of sigma ~ U[lo, hi], log-intensity units per frame pair.
        hot_pixel_fraction: (lo, hi) of the fraction of hot pixels ~ U[lo, hi].
        hot_pixel_std: (lo, hi) of s ~ U[lo, hi]; hot-pixel values ~ N(0, s^2),
            log-intensity units per frame pair.

    Raises:
        ValueError: naming the field, when a range is not two finite numbers lo <= hi, or
            lies outside its domain (thresholds > 0, ratio >= 1, the rest >= 0, fraction <= 1)
            or outside what the kernel is tested at (:data:`TESTED`, :func:`check_tested`).
    """

    threshold: Tuple[float, float] = (0.05, 2.0)
    ratio: Tuple[float, float] = (1.0, 1.5)
    noise_std: Tuple[float, float] = (0.0, 0.1)
    hot_pixel_fraction: Tuple[float, float] = (0.0, 0.001)
    hot_pixel_std: Tuple[float, float] = (0.0, 10.0)

    def __post_init__(self):
        domains = {
            "threshold": (0.0, math.inf, False),
            "ratio": (1.0, math.inf, True),
            "noise_std": (0.0, math.inf, True),
            "hot_pixel_fraction": (0.0, 1.0, True),
            "hot_pixel_std": (0.0, math.inf, True),
        }
        for f in fields(self):
            value = getattr(self, f.name)
            try:
                lo, hi = (float(v) for v in value)
            except (TypeError, ValueError):
                raise ValueError(f"ranges.{f.name} must be a pair [lo, hi], got {value!r}") from None
            dmin, dmax, inclusive = domains[f.name]
            ok = math.isfinite(lo) and math.isfinite(hi) and lo <= hi and hi <= dmax
            ok = ok and (lo >= dmin if inclusive else lo > dmin)
            if not ok:
                bound = ">=" if inclusive else ">"
                raise ValueError(
                    f"ranges.{f.name} must be finite with {bound} {dmin} <= lo <= hi <= {dmax}, got {value!r}"
                )
            if f.name in TESTED:
                check_tested(f"ranges.{f.name}", f.name, lo, hi)
            object.__setattr__(self, f.name, (lo, hi))

    @classmethod
    def from_dict(cls, d: Optional[dict]) -> "ParamRanges":
        """Build from a config mapping; unknown keys raise ``ValueError`` naming them."""
        if d is None:
            return cls()
        if isinstance(d, ParamRanges):
            return d
        check_keys(d, (f.name for f in fields(cls)), "ranges")
        return cls(**{k: tuple(v) if isinstance(v, (list, tuple)) else v for k, v in d.items()})

    def to_dict(self) -> dict:
        return {f.name: list(getattr(self, f.name)) for f in fields(self)}


def log_intensity_lut(full_scale: int = 255, dtype=np.float32) -> np.ndarray:
    """Look-up table from pixel value to log intensity.

    Returns an array of shape (full_scale + 1,) and the given dtype with
    ``lut[F] = log(LOG_EPS + (F / full_scale) ** GAMMA)`` (log-intensity units),
    evaluated in float64 then cast.
    """
    f = np.arange(full_scale + 1, dtype=np.float64) / float(full_scale)
    return np.log(LOG_EPS + f**GAMMA).astype(dtype)


_LUTS = {}


def _lut(full_scale: int, dtype) -> np.ndarray:
    key = (full_scale, np.dtype(dtype).str)
    if key not in _LUTS:
        _LUTS[key] = log_intensity_lut(full_scale, dtype)
    return _LUTS[key]


def _lut64(full_scale: int, dtype) -> np.ndarray:
    """The ``dtype`` table's values widened to float64 (what the kernel reads)."""
    key = (full_scale, np.dtype(dtype).str, "64")
    if key not in _LUTS:
        _LUTS[key] = _lut(full_scale, dtype).astype(np.float64)
    return _LUTS[key]


def draw_noise_seed(rng: np.random.Generator) -> int:
    """The background-noise seed of a clip, drawn from ``rng`` right after the initial
    potential (so every simulator sharing a generator shares the noise): int in [0, 2**63)."""
    return int(rng.integers(0, 2**63, dtype=np.int64))


def check_frames(frames, num_bins: int) -> int:
    """Check a clip for the V2V core and return its full scale (255 or 65535).

    Raises:
        ValueError: frames that are not a uint8/uint16 (N, H, W) array with
            N = L * num_bins + 1 (L >= 1), or a bad ``num_bins``.
    """
    if isinstance(num_bins, bool) or not isinstance(num_bins, (int, np.integer)) or num_bins < 1:
        raise ValueError(f"num_bins must be an int >= 1, got {num_bins!r}")
    if not isinstance(frames, np.ndarray) or frames.ndim != 3:
        raise ValueError(
            f"frames must be an (N, H, W) array, got {type(frames).__name__}{getattr(frames, 'shape', '')}"
        )
    full_scale = full_scale_of(frames)
    n = frames.shape[0]
    if n < num_bins + 1 or (n - 1) % num_bins != 0:
        raise ValueError(
            f"frames must hold L * num_bins + 1 frames (num_bins={int(num_bins)}, L >= 1), got N={n}"
        )
    return full_scale


def start_state(params: SensorParams, shape: Tuple[int, int], initial_potential=None,
                rng: Optional[np.random.Generator] = None, dtype=np.float32):
    """Check ``params.hot_pixels`` against ``shape`` and return ``(rng, potential)``: the
    generator to use (a fresh one when ``None``) and dL_hat(t_0) as a ``dtype`` (H, W) copy,
    drawn from U[-c-, c+] when ``initial_potential`` is None (log-intensity units).

    Raises:
        ValueError: a hot-pixel map or initial potential whose shape is not ``shape``.
    """
    h, w = shape
    hot = params.hot_pixels
    if hot is not None and hot.shape != (h, w):
        raise ValueError(f"hot_pixels has shape {hot.shape}, frames are {(h, w)}")
    if rng is None:
        rng = np.random.default_rng()
    if initial_potential is None:
        return rng, rng.uniform(-params.neg_threshold, params.pos_threshold, size=(h, w)).astype(dtype)
    initial_potential = np.asarray(initial_potential)
    if initial_potential.shape != (h, w):
        raise ValueError(f"initial_potential has shape {initial_potential.shape}, frames are {(h, w)}")
    return rng, initial_potential.astype(dtype, copy=True)


def simulate_voxels(
    frames: np.ndarray,
    params: SensorParams,
    num_bins: int,
    *,
    initial_potential: Optional[np.ndarray] = None,
    rng: Optional[np.random.Generator] = None,
    noise_seed: Optional[int] = None,
    first_pair: int = 0,
    compute_dtype=np.float32,
    narrow: bool = False,
    split: bool = False,
) -> Tuple[np.ndarray, ...]:
    """Discrete voxel grids (SBT) of a clip, computed from frames without an event stream.

    Paper: Lou et al. 2025, Sec. 3 (V2V); one frame pair per bin (frames_per_bin = 1). The
    step itself is :func:`v2v_server.simulation.kernel.run_kernel` (the project's one kernel).

    Args:
        frames: uint8 (full scale 255) or uint16 (full scale 65535, for 10- to 16-bit
            sources) array (N, H, W) of luma frames, N = L * num_bins + 1 with L >= 1.
        params: the sensor's contrast thresholds, noise and hot pixels.
        num_bins: B, temporal bins per voxel grid (int >= 1).
        initial_potential: (H, W) float, dL_hat(t_0) in log-intensity units. ``None`` draws
            it from U[-c-, c+] with ``rng``.
        rng: ``numpy.random.Generator`` for the initial potential and, when ``noise_seed``
            is None, the noise seed (:func:`draw_noise_seed`, drawn after the potential); a
            fresh unseeded one when ``None``.
        noise_seed: seed of the kernel's background-noise stream (see ``kernel.py``): frame
            pair j's noise depends only on (noise_seed, first_pair + j).
        first_pair: index of this clip's first frame pair in the noise stream; continue a
            clip with the returned potential, the same ``noise_seed`` and
            ``first_pair + (N - 1)`` and the result equals one call.
        compute_dtype: ``np.float32`` (default) or ``np.float64``: precision of the
            log-intensity table and of the residual potential stored between frame pairs.
            Each step itself is evaluated in float64, so the conservation law c+ sum N+ -
            c- sum N- + dL_hat_end - dL_hat_0 = L_end - L_0 + sum N_i + steps * H holds to
            steps * 2**-24 * max(c+, c-) in float32 (see tests/test_stability.py).
        narrow: voxels in the narrowest of int8, int16, int32 that holds every count (the
            wire's dtype; the kernel tracks the range, see ``run_kernel``), not int32.
        split: also return N+ and N- of every frame pair (the kernel's ``split``; it then
            skips its fast path, so only when asked): float64 (N - 1, H, W) each.

    Returns:
        ``(voxels, potential)``, or with ``split`` ``(voxels, potential, (n_pos, n_neg))``: ``voxels`` int32 (or narrower, ``narrow``) (L, num_bins, H, W), bin b of voxel l is
        N+ - N- of frame pair l * num_bins + b (signed event counts); ``potential`` float32
        (H, W), the residual dL_hat after the last frame (log-intensity units), to continue
        the clip with a later call.

    Raises:
        ValueError: for frames that are not a uint8/uint16 (N, H, W) array with
            N = L * num_bins + 1, a bad ``num_bins``, or a ``hot_pixels`` /
            ``initial_potential`` shape that does not match (H, W).
        OverflowError: when a pixel would need more than 2**31 - 1 events in one frame
            pair (thresholds near 1e-9): counts are never wrapped or clipped.
    """
    if not isinstance(params, SensorParams):
        raise ValueError(f"params must be a SensorParams, got {type(params).__name__}")
    full_scale = check_frames(frames, num_bins)
    n, h, w = frames.shape
    dtype = np.dtype(compute_dtype)
    if dtype not in (np.dtype(np.float32), np.dtype(np.float64)):
        raise ValueError(f"compute_dtype must be float32 or float64, got {dtype}")
    rng, potential = start_state(params, (h, w), initial_potential, rng, dtype)
    if noise_seed is None:
        noise_seed = draw_noise_seed(rng)
    res = run_kernel(frames, potential, params.pos_threshold, params.neg_threshold,
                     lut=_lut64(full_scale, dtype), extra=0.0 if params.hot_pixels is None else params.hot_pixels,
                     noise_std=params.noise_std, noise_seed=noise_seed, first_pair=first_pair, narrow=narrow,
                     split=split)
    voxels = res.net.reshape((n - 1) // num_bins, num_bins, h, w)
    if split:
        return voxels, potential.astype(np.float32), (res.pos, res.neg)
    return voxels, potential.astype(np.float32)


def polarity_counts(n_pos: np.ndarray, n_neg: np.ndarray, sequence_length: int, num_bins: int) -> np.ndarray:
    """The ``polarity_counts`` output: N+ and N- of each bin (Lou et al. 2025, Sec. 3; the
    voxel is their difference), summed over the bin's frame pairs and saturated at 255.

    Args:
        n_pos, n_neg: N+ and N- per frame pair, (P, H, W) non-negative (``simulate_voxels(split=True)``),
            P = sequence_length * num_bins * frames per bin.

    Returns:
        uint8 (sequence_length, 2, num_bins, H, W): channel 0 = positive (N+), 1 = negative (N-).

    Raises:
        ValueError: when P is not a multiple of sequence_length * num_bins, or the shapes differ.
    """
    p, h, w = n_pos.shape
    per_bin, rest = divmod(p, sequence_length * num_bins)
    if n_neg.shape != n_pos.shape or rest or per_bin < 1:
        raise ValueError(f"N+ {n_pos.shape} and N- {n_neg.shape} must be (P, H, W) with P a multiple of "
                         f"sequence_length * num_bins = {sequence_length * num_bins}")
    out = np.empty((sequence_length, 2, num_bins, h, w), np.uint8)
    for c, n in enumerate((n_pos, n_neg)):
        n = n.reshape(sequence_length, num_bins, per_bin, h, w)
        counts = n[:, :, 0] if per_bin == 1 else n.sum(axis=2)
        np.minimum(counts, 255, out=out[:, c], casting="unsafe")  # integral values <= 255: exact
    return out


def sample_params(
    rng: np.random.Generator,
    ranges: Optional[ParamRanges | dict] = None,
    shape: Tuple[int, int] = (128, 128),
) -> SensorParams:
    """Draw one sensor configuration (paper Sec. 3.2; reference repo's WebVid ranges).

    t1 ~ U[threshold], r ~ U[ratio], t2 = t1 * r, a fair coin decides which of t1, t2 is
    c+; sigma ~ U[noise_std]; hot-pixel fraction f ~ U[hot_pixel_fraction] and each pixel
    is hot with probability f, its value ~ N(0, s^2) with s ~ U[hot_pixel_std].

    Args:
        rng: ``numpy.random.Generator`` (the only source of randomness).
        ranges: ``ParamRanges`` or a dict of its fields; ``None`` for the defaults.
        shape: (H, W) of the hot-pixel map, pixels.

    Returns:
        A ``SensorParams``; ``hot_pixels`` is None when no pixel was drawn hot.

    Raises:
        ValueError: for bad ranges (naming the field) or a bad shape.
    """
    ranges = ParamRanges.from_dict(ranges) if not isinstance(ranges, ParamRanges) else ranges
    try:
        h, w = (int(s) for s in shape)
    except (TypeError, ValueError):
        raise ValueError(f"shape must be (H, W), got {shape!r}") from None
    if h < 1 or w < 1:
        raise ValueError(f"shape must be positive, got {shape!r}")
    t1 = rng.uniform(*ranges.threshold)
    t2 = t1 * rng.uniform(*ranges.ratio)
    if rng.random() < 0.5:
        cp, cn = t1, t2
    else:
        cp, cn = t2, t1
    sigma = rng.uniform(*ranges.noise_std)
    frac = rng.uniform(*ranges.hot_pixel_fraction)
    s = rng.uniform(*ranges.hot_pixel_std)
    mask = rng.random((h, w)) < frac
    hot = None
    if mask.any() and s > 0:
        hot = np.zeros((h, w), dtype=np.float32)
        hot[mask] = rng.normal(0.0, s, size=int(mask.sum()))
    return SensorParams(cp, cn, sigma, hot)

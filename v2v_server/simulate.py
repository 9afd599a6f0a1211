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

#: Offset inside the log, ``L = log(LOG_EPS + I)`` (paper Sec. 3, reference repo).
LOG_EPS = 1e-3
#: Display gamma undone before the log (``I = (F / full_scale) ** GAMMA``).
GAMMA = 2.2

__all__ = [
    "LOG_EPS",
    "GAMMA",
    "SensorParams",
    "ParamRanges",
    "log_intensity_lut",
    "simulate_voxels",
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
            lies outside its domain (thresholds > 0, ratio >= 1, the rest >= 0, fraction <= 1).
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
            object.__setattr__(self, f.name, (lo, hi))

    @classmethod
    def from_dict(cls, d: Optional[dict]) -> "ParamRanges":
        """Build from a config mapping; unknown keys raise ``ValueError`` naming them."""
        if d is None:
            return cls()
        if isinstance(d, ParamRanges):
            return d
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown key(s) in ranges: {unknown}; known: {sorted(known)}")
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


def simulate_voxels(
    frames: np.ndarray,
    params: SensorParams,
    num_bins: int,
    *,
    initial_potential: Optional[np.ndarray] = None,
    rng: Optional[np.random.Generator] = None,
    compute_dtype=np.float32,
) -> Tuple[np.ndarray, np.ndarray]:
    """Discrete voxel grids (SBT) of a clip, computed from frames without an event stream.

    Paper: Lou et al. 2025, Sec. 3 (V2V); one frame pair per bin (frames_per_bin = 1).

    Args:
        frames: uint8 (full scale 255) or uint16 (full scale 65535, for 10- to 16-bit
            sources) array (N, H, W) of luma frames, N = L * num_bins + 1 with L >= 1.
        params: the sensor's contrast thresholds, noise and hot pixels.
        num_bins: B, temporal bins per voxel grid (int >= 1).
        initial_potential: (H, W) float, dL_hat(t_0) in log-intensity units. ``None`` draws
            it from U[-c-, c+] with ``rng``.
        rng: ``numpy.random.Generator`` for the initial potential and the noise; a fresh
            unseeded one when ``None``.
        compute_dtype: ``np.float32`` (default) or ``np.float64``: precision of the
            log-intensity table, the noise draws and the stored residual potential. Each
            step itself is evaluated in float64 (float64 accumulation), so the conservation
            law c+ sum N+ - c- sum N- + dL_hat_end - dL_hat_0 = L_end - L_0 + sum N_i +
            steps * H holds to steps * 2**-24 * max(c+, c-) in float32 (see
            tests/test_stability.py); on CPU this costs no time.

    Returns:
        ``(voxels, potential)``: ``voxels`` int32 (L, num_bins, H, W), bin b of voxel l is
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
    if isinstance(num_bins, bool) or not isinstance(num_bins, (int, np.integer)) or num_bins < 1:
        raise ValueError(f"num_bins must be an int >= 1, got {num_bins!r}")
    num_bins = int(num_bins)
    if not isinstance(frames, np.ndarray) or frames.ndim != 3:
        raise ValueError(
            f"frames must be an (N, H, W) array, got {type(frames).__name__}{getattr(frames, 'shape', '')}"
        )
    if frames.dtype == np.uint8:
        full_scale = 255
    elif frames.dtype == np.uint16:
        full_scale = 65535
    else:
        raise ValueError(f"frames must have dtype uint8 or uint16, got {frames.dtype}")
    n, h, w = frames.shape
    if n < num_bins + 1 or (n - 1) % num_bins != 0:
        raise ValueError(
            f"frames must hold L * num_bins + 1 frames (num_bins={num_bins}, L >= 1), got N={n}"
        )
    dtype = np.dtype(compute_dtype)
    if dtype not in (np.dtype(np.float32), np.dtype(np.float64)):
        raise ValueError(f"compute_dtype must be float32 or float64, got {dtype}")
    hot = params.hot_pixels
    if hot is not None and hot.shape != (h, w):
        raise ValueError(f"hot_pixels has shape {hot.shape}, frames are {(h, w)}")
    if rng is None:
        rng = np.random.default_rng()
    cp, cn = params.pos_threshold, params.neg_threshold
    if initial_potential is None:
        potential = rng.uniform(-cn, cp, size=(h, w)).astype(dtype)
    else:
        initial_potential = np.asarray(initial_potential)
        if initial_potential.shape != (h, w):
            raise ValueError(f"initial_potential has shape {initial_potential.shape}, frames are {(h, w)}")
        potential = initial_potential.astype(dtype, copy=True)
    sigma = params.noise_std
    lut = _lut(full_scale, dtype)
    # Overflow guard: int32 counts must never wrap. Without noise |dL| is bounded by the
    # log range + |H| + the residual; only when that bound (plus 40 sigma) comes near the
    # int32 range do we pay for a per-step check (thresholds ~1e-9 or hot pixels ~1e6).
    bound = float(lut[-1] - lut[0]) + max(cp, cn) + (0.0 if hot is None else float(np.abs(hot).max()))
    bound += float(np.abs(potential).max(initial=0.0)) + 40.0 * sigma
    check_overflow = bound / min(cp, cn) > 2**30
    hot = None if hot is None else hot.astype(np.float64)

    n_pairs = n - 1
    voxels = np.empty((n_pairs, h, w), dtype=np.int32)
    # Every step is evaluated in float64 and only the residual is stored in compute_dtype:
    # a float32 step drifts (|conservation error| ~4e-3 log units after 1e5 steps of
    # random frames with c = 1e-3), the float64 step plus float32 storage of a residual
    # bounded by max(c+, c-) keeps it below steps * 2**-24 * max(c+, c-).
    lut64 = lut.astype(np.float64)  # the compute_dtype table's values, widened once
    prev = lut64[frames[0]]
    cur = np.empty((h, w), dtype=np.float64)
    dl = np.empty((h, w), dtype=np.float64)
    pos = np.empty((h, w), dtype=np.float64)
    neg = np.empty((h, w), dtype=np.float64)
    sigma_c = dtype.type(sigma)
    for i in range(n_pairs):
        np.take(lut64, frames[i + 1], out=cur)
        # dL = dL_hat + (L_i - L_{i-1}) + N_i + H
        np.subtract(cur, prev, out=dl)
        dl += potential
        if sigma > 0:
            dl += rng.standard_normal((h, w), dtype=dtype) * sigma_c
        if hot is not None:
            dl += hot
        np.floor(np.divide(dl, cp, out=pos), out=pos)
        np.maximum(pos, 0, out=pos)
        np.floor(np.divide(dl, -cn, out=neg), out=neg)
        np.maximum(neg, 0, out=neg)
        if check_overflow and max(pos.max(), neg.max()) > np.iinfo(np.int32).max:
            raise OverflowError(
                f"frame pair {i}: more than 2**31-1 events in one pixel (thresholds "
                f"c+={cp}, c-={cn} too small for the int32 voxel grid)"
            )
        np.subtract(pos, neg, out=voxels[i], casting="unsafe")
        dl -= pos * cp
        dl += neg * cn
        np.copyto(potential, dl, casting="same_kind")
        prev, cur = cur, prev
    return voxels.reshape(n_pairs // num_bins, num_bins, h, w), potential.astype(np.float32)


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

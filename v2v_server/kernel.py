"""The one simulation kernel: every c+/c- threshold crossing of the project is counted here.

V2V (Lou et al., NeurIPS 2025, Sec. 3), refinement (``refine.py``), sensor non-idealities
(``nonideal.py``) and the event-level reference (``reference.py``) are all calls of
:func:`run_kernel` with different inputs, so they compose (a refined path with per-pixel
thresholds and a refractory cap is one call):

* the log-intensity path: uint8 / uint16 frames through a look-up table (plain V2V), or a
  float64 path with sub-frames between the frames (refinement, the reference);
* ``pair_of_step``: the frame pair each sub-interval belongs to (all 1 for plain V2V);
* per-pixel or scalar thresholds c+, c-; an extra per-pixel dL per frame pair (hot pixels H,
  the leak drift); background noise ``N_i ~ N(0, sigma^2)`` drawn inside from ``noise_seed``;
* the refractory cap on the counts of a frame pair;
* optionally, every event with its sub-interval and the fraction of it at which it fired.

Per sub-interval s of frame pair i with k_i sub-intervals (the V2V step):

    dL   = dL_hat + ((P[s+1] - P[s]) + (N_i + H + D) / k_i)
    N+   = max(0, floor(dL / c+)),   N- = max(0, floor(-dL / c-))
    dL_hat = dL - c+ N+ + c- N-

evaluated in float64 (the residual dL_hat is stored in the dtype of ``potential`` only
between frame pairs), and the counts of a pair's sub-intervals are summed into its bin.

Noise: a counter-based stream. Frame pair ``first_pair + i`` gets its own splitmix64 stream
seeded from ``(noise_seed, first_pair + i)``, and its (H, W) normals are drawn in row-major
order with a 256-layer ziggurat (Marsaglia & Tsang, J. Stat. Softw. 2000) on 32-bit words:
each 64-bit draw of the stream gives two normals (low half first; 8 bits pick the layer, 1 the
sign, 23 the abscissa, as numpy's float32 ziggurat), and the rare wedge/tail cases draw their
extra uniforms from a private stream seeded by the word, so they never shift the others. The noise of a
frame pair therefore depends only on (noise_seed, pair index), so a clip simulated in chunks
(``first_pair``) equals the clip in one call, and :func:`noise_field` replays it.
"""
from __future__ import annotations

import math
from typing import NamedTuple, Optional

import numba
import numpy as np

__all__ = ["KernelResult", "run_kernel", "noise_field", "full_scale_of", "ZIGGURAT_R"]

#: Right edge of the ziggurat's base layer (256 layers; Marsaglia & Tsang 2000).
ZIGGURAT_R = 3.6541528853610088
_ZIGGURAT_V = 0.00492867323399  # area of each layer


def full_scale_of(frames: np.ndarray) -> int:
    """The full-scale rule, in one place: uint8 frames are 0..255, uint16 frames 0..65535
    (10- to 16-bit sources scaled to the full 16-bit range).

    Raises:
        ValueError: for any other dtype (the message names it).
    """
    if frames.dtype == np.uint8:
        return 255
    if frames.dtype == np.uint16:
        return 65535
    raise ValueError(f"frames must have dtype uint8 or uint16, got {frames.dtype}")


def _ziggurat_tables():
    """Layer tables of a 256-layer ziggurat for N(0, 1) with 23-bit abscissae (a 32-bit word
    per normal: two normals per 64-bit draw).

    Layer 0 is the base rectangle plus the tail beyond r; layer i >= 1 spans [0, x_i] between
    heights f(x_i) and f(x_{i+1}), x_1 = r, x_256 = 0, f(x) = exp(-x^2 / 2).
    Returns (k int64 (256,), w float64 (256,), f float64 (257,)).
    """
    r, v = ZIGGURAT_R, _ZIGGURAT_V
    f = lambda x: math.exp(-0.5 * x * x)  # noqa: E731
    x = np.zeros(257)
    x[1] = r
    for i in range(1, 255):
        y = f(x[i]) + v / x[i]
        x[i + 1] = math.sqrt(-2.0 * math.log(y)) if y < 1.0 else 0.0
    x[256] = 0.0
    x[0] = v / f(r)  # width of the base rectangle (its area with the tail is v)
    m = float(2**23)
    w = x[:256] / m
    k = np.zeros(256, np.int64)
    k[0] = math.floor(r / x[0] * m)
    for i in range(1, 256):
        k[i] = math.floor(x[i + 1] / x[i] * m)
    fx = np.array([f(xi) for xi in x])
    fx[0] = f(r)
    fx[256] = 1.0
    return k, w, fx


_ZK, _ZW, _ZF = _ziggurat_tables()

_GOLD = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31 = np.uint64(30), np.uint64(27), np.uint64(31)
_S8, _S9, _S11, _S32 = np.uint64(8), np.uint64(9), np.uint64(11), np.uint64(32)
_B8 = np.uint64(0xFF)
_M32 = np.uint64(0xFFFFFFFF)
_B1 = np.uint64(1)
_INV53 = 1.0 / 9007199254740992.0


@numba.njit(cache=True, inline="always")
def _mix(z):
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@numba.njit(cache=True)
def _uniform(x):
    """(u in (0, 1), advanced counter) from a splitmix64 counter."""
    x += _GOLD
    return (float(_mix(x) >> _S11) + 0.5) * _INV53, x


@numba.njit(cache=True)
def _normal_slow(x, u, zk, zw, zf):
    """The rare ziggurat cases of the 32-bit word ``u`` (about 1 in 80): the tail and the
    wedges, then retries. Extra uniforms come from a private splitmix64 stream seeded by
    (the stream's counter ``x``, ``u``), so the main stream's order does not depend on them."""
    y = _mix(x ^ (u << _S32))
    while True:
        idx = np.int64(u & _B8)
        neg = ((u >> _S8) & _B1) != 0
        rabs = np.int64(u >> _S9)
        v = float(rabs) * zw[idx]
        if rabs < zk[idx]:
            return -v if neg else v
        if idx == 0:  # the tail beyond r (Marsaglia 1964)
            while True:
                u1, y = _uniform(y)
                u2, y = _uniform(y)
                xx = -math.log(u1) / ZIGGURAT_R
                yy = -math.log(u2)
                if yy + yy > xx * xx:
                    return -(ZIGGURAT_R + xx) if neg else ZIGGURAT_R + xx
        else:
            uu, y = _uniform(y)
            if zf[idx] + uu * (zf[idx + 1] - zf[idx]) < math.exp(-0.5 * v * v):
                return -v if neg else v
        y += _GOLD
        u = _mix(y) & _M32


@numba.njit(cache=True)
def _fill_normals(x, out, zk, zw, zf):
    """Fill ``out`` (float64 (n,)) with N(0, 1) draws from the splitmix64 counter ``x``, in
    order, two per 64-bit draw (low word first); returns the advanced counter. The common
    case (98.8 %) is inline and branch-free in the sign (a random branch would mispredict
    half the time); written out twice because a shared inlined helper compiles ~10x slower."""
    n = out.shape[0]
    for q in range((n + 1) // 2):
        x += _GOLD
        r = _mix(x)
        u = r & _M32
        idx = np.int64(u & _B8)
        rabs = np.int64(u >> _S9)  # 23 bits
        if rabs < zk[idx]:
            out[2 * q] = float(rabs) * zw[idx] * (1.0 - 2.0 * float(np.int64((u >> _S8) & _B1)))
        else:
            out[2 * q] = _normal_slow(x, u, zk, zw, zf)
        if 2 * q + 1 == n:
            break
        u = r >> _S32
        idx = np.int64(u & _B8)
        rabs = np.int64(u >> _S9)
        if rabs < zk[idx]:
            out[2 * q + 1] = float(rabs) * zw[idx] * (1.0 - 2.0 * float(np.int64((u >> _S8) & _B1)))
        else:
            out[2 * q + 1] = _normal_slow(x, u, zk, zw, zf)
    return x


@numba.njit(cache=True, inline="always")
def _seed_pair(noise_seed, pair):
    return _mix(np.uint64(noise_seed) ^ _mix(np.uint64(pair) + _GOLD))


@numba.njit(cache=True)
def _noise_field(noise_seed, first_pair, n_pairs, npix, zk, zw, zf, out):
    for i in range(n_pairs):
        _fill_normals(_seed_pair(noise_seed, first_pair + i), out[i], zk, zw, zf)


def noise_field(noise_seed: int, n_pairs: int, shape, first_pair: int = 0) -> np.ndarray:
    """The standard normals the kernel adds (times sigma) at frame pairs
    ``first_pair .. first_pair + n_pairs - 1``: float64 (n_pairs, H, W). For tests and
    conservation checks: the kernel draws exactly these."""
    h, w = shape
    out = np.empty((n_pairs, h * w))
    _noise_field(np.uint64(noise_seed), int(first_pair), int(n_pairs), h * w, _ZK, _ZW, _ZF, out)
    return out.reshape(n_pairs, h, w)


@numba.njit(cache=True)
def _grow(a, n):
    out = np.empty(max(2 * a.shape[0], n), a.dtype)
    out[: a.shape[0]] = a
    return out


@numba.njit(cache=True, error_model="numpy")
def _emit(s, pot0, d, cpa, cna, per_pixel, pos, neg, ev_step, ev_pix, ev_frac, ev_pol, n_ev):
    """Append the events of sub-interval ``s``: the counts ``pos``/``neg`` were decided by the
    step in :func:`_kernel`; here only where inside the sub-interval each level r * c was
    reached, at fraction (r c - dL_hat) / d (d = 0 only when rounding left dL_hat on a level)."""
    for p in range(pot0.shape[0]):
        for q in range(2):
            cnt = np.int64(pos[p]) if q == 0 else np.int64(neg[p])
            if cnt == 0:
                continue
            c = (cpa[p] if per_pixel else cpa[0]) if q == 0 else -(cna[p] if per_pixel else cna[0])
            if n_ev + cnt > ev_step.shape[0]:
                ev_step = _grow(ev_step, n_ev + cnt)
                ev_pix = _grow(ev_pix, n_ev + cnt)
                ev_frac = _grow(ev_frac, n_ev + cnt)
                ev_pol = _grow(ev_pol, n_ev + cnt)
            for r in range(1, cnt + 1):
                fr = (r * c - pot0[p]) / d[p] if d[p] != 0.0 else 0.0
                if not (fr > 0.0):
                    fr = 0.0
                elif fr > 1.0:
                    fr = 1.0
                ev_step[n_ev] = s
                ev_pix[n_ev] = p
                ev_frac[n_ev] = fr
                ev_pol[n_ev] = 1 if q == 0 else -1
                n_ev += 1
    return ev_step, ev_pix, ev_frac, ev_pol, n_ev


@numba.njit(cache=True, error_model="numpy", inline="always")
def _crossings(dl, c1, c2):
    """The V2V step for one pixel, the only place where threshold crossings are counted:
    dL -> (N+, N-, dL_hat) with N+ = max(0, floor(dL / c+)), N- = max(0, floor(-dL / c-)),
    dL_hat = dL - c+ N+ + c- N- (float64; Lou et al. 2025, Sec. 3)."""
    a = max(np.floor(dl / c1), 0.0)
    b = max(np.floor(-dl / c2), 0.0)
    return a, b, dl - a * c1 + b * c2


# error_model="numpy": thresholds are checked > 0, and without the ZeroDivisionError check
# the step loops vectorise (4 pixels per instruction with AVX2)
@numba.njit(cache=True, error_model="numpy")
def _kernel(src, lut, use_lut, pair_of_step, n_pairs, potential, cpa, cna, extra, noise_std, noise_seed,
            first_pair, cap, net, big, pos_out, neg_out, want_split, want_events, zk, zw, zf):
    """Core loop; see :func:`run_kernel`. ``src``: (M, npix) codes (``use_lut``) or float64
    levels; ``cpa``, ``cna``: float64 (npix,) or (1,) (a scalar); ``extra``: float64 (npix,);
    ``net``: int16 or int32 (P, npix), ``big`` the largest count it may hold (a pair needing
    more stops the loop and is reported as ``overflow``)."""
    m = src.shape[0]
    npix = src.shape[1]
    has_noise = noise_std > 0.0
    per_pixel = cpa.shape[0] > 1
    c1s = cpa[0]
    c2s = cna[0]
    k = np.zeros(n_pairs, np.int64)
    for s in range(m - 1):
        k[pair_of_step[s]] += 1
    prev = np.empty(npix)
    cur = np.empty(npix)
    pot = np.empty(npix)
    e = np.empty(npix)
    a_ = np.empty(npix)
    b_ = np.empty(npix)
    psum = np.zeros(npix)
    nsum = np.zeros(npix)
    pot0 = np.empty(npix if want_events else 0)
    dd = np.empty(npix if want_events else 0)
    events = np.int64(0)
    lost = np.int64(0)
    cap_f = float(cap)
    cap_ev = 1024 if want_events else 0
    ev_step = np.empty(cap_ev, np.int64)
    ev_pix = np.empty(cap_ev, np.int64)
    ev_frac = np.empty(cap_ev)
    ev_pol = np.empty(cap_ev, np.int8)
    n_ev = 0
    lo = np.int64(0)  # range of the net counts written
    hi = np.int64(0)
    overflow = -1
    fast = use_lut and not want_split and not want_events and cap == 0
    # bounds for the fast path's overflow test: |dL| <= log range + |extra + noise| + |dL_hat|
    cmin = np.inf
    cmax = 0.0
    for p in range(cpa.shape[0]):
        cmin = min(cmin, cpa[p], cna[p])
        cmax = max(cmax, cpa[p], cna[p])
    potmax = 0.0
    for p in range(npix):
        potmax = max(potmax, abs(potential[p]))
    lrange = 0.0
    if use_lut:
        lrange = lut.max() - lut.min()
        for p in range(npix):
            prev[p] = lut[np.int64(src[0, p])]
    s = 0
    for i in range(n_pairs):
        kk = k[i]
        # the pair's extra dL (hot pixels, drift, noise), spread evenly over its sub-intervals
        emax = 0.0
        # (x / 1 is x: the common one-step pair skips the vector division)
        if has_noise:
            _fill_normals(_seed_pair(noise_seed, first_pair + i), e, zk, zw, zf)
            if kk == 1:
                for p in range(npix):
                    e[p] = extra[p] + e[p] * noise_std
                    emax = max(emax, abs(e[p]))
            else:
                for p in range(npix):
                    e[p] = (extra[p] + e[p] * noise_std) / kk
                    emax = max(emax, abs(e[p]))
        elif kk == 1:
            for p in range(npix):
                e[p] = extra[p]
                emax = max(emax, abs(e[p]))
        else:
            for p in range(npix):
                e[p] = extra[p] / kk
                emax = max(emax, abs(e[p]))
        if fast and kk == 1 and (lrange + emax + 2.0 * max(potmax, cmax)) / cmin < big:
            # plain V2V, no count can overflow: one vectorised pass, residual stored in place
            for p in range(npix):
                cur[p] = lut[np.int64(src[s + 1, p])]
            row = net[i]
            if per_pixel:
                for p in range(npix):
                    a, b, r = _crossings(potential[p] + ((cur[p] - prev[p]) + e[p]), cpa[p], cna[p])
                    potential[p] = r
                    row[p] = np.int64(a - b)
            else:
                for p in range(npix):
                    a, b, r = _crossings(potential[p] + ((cur[p] - prev[p]) + e[p]), c1s, c2s)
                    potential[p] = r
                    row[p] = np.int64(a - b)
            for p in range(npix):  # one sub-interval never mixes polarities: |net| = N+ + N-
                v = np.int64(row[p])
                events += abs(v)
                lo = min(lo, v)
                hi = max(hi, v)
            potmax = max(potmax, cmax)
            prev, cur = cur, prev
            s += 1
            continue
        for p in range(npix):
            pot[p] = potential[p]
            psum[p] = 0.0
            nsum[p] = 0.0
        if use_lut:
            for p in range(npix):
                prev[p] = lut[np.int64(src[s, p])]
        else:
            for p in range(npix):
                prev[p] = src[s, p]
        for _ in range(kk):
            if use_lut:
                for p in range(npix):
                    cur[p] = lut[np.int64(src[s + 1, p])]
            else:
                for p in range(npix):
                    cur[p] = src[s + 1, p]
            if want_events:
                for p in range(npix):
                    pot0[p] = pot[p]
                    dd[p] = (cur[p] - prev[p]) + e[p]
            for p in range(npix):
                dl = pot[p] + ((cur[p] - prev[p]) + e[p])
                if per_pixel:
                    a, b, r = _crossings(dl, cpa[p], cna[p])
                else:
                    a, b, r = _crossings(dl, c1s, c2s)
                pot[p] = r
                a_[p] = a
                b_[p] = b
                psum[p] += a
                nsum[p] += b
            if want_events:
                ev_step, ev_pix, ev_frac, ev_pol, n_ev = _emit(
                    s, pot0, dd, cpa, cna, per_pixel, a_, b_, ev_step, ev_pix, ev_frac, ev_pol, n_ev)
            prev, cur = cur, prev
            s += 1
        for p in range(npix):
            a = psum[p]
            b = nsum[p]
            if a > big or b > big:
                overflow = i
            events += np.int64(a + b)
            if cap > 0:
                if a > cap_f:
                    lost += np.int64(a - cap_f)
                    a = cap_f
                if b > cap_f:
                    lost += np.int64(b - cap_f)
                    b = cap_f
            if a - b > big or b - a > big:
                overflow = i
            else:
                v = np.int64(a - b)
                net[i, p] = v
                lo = min(lo, v)
                hi = max(hi, v)
            if want_split:
                pos_out[i, p] = a
                neg_out[i, p] = b
            potential[p] = pot[p]
        if overflow >= 0:
            break
    return events, lost, overflow, lo, hi, ev_step[:n_ev], ev_pix[:n_ev], ev_frac[:n_ev], ev_pol[:n_ev]


class KernelResult(NamedTuple):
    """What :func:`run_kernel` returns.

    Attributes:
        net: int32 (P, H, W) net count N+ - N- per frame pair (after the refractory cap); with
            ``narrow=True`` int8 or int16 when every count fits.
        potential: (H, W) residual dL_hat after the last pair, dtype of the input potential.
        events: int, N+ + N- summed over every sub-interval (before the cap).
        lost: int, events the refractory cap removed.
        pos, neg: float64 (P, H, W) N+ and N- per pair after the cap (only with
            ``split=True``, else None).
        event_step, event_pixel, event_fraction, event_polarity: the events (only with
            ``events=True``, else None): int64 sub-interval, int64 flat pixel index, float64
            fraction of the sub-interval in [0, 1], int8 polarity; ordered by sub-interval,
            then pixel, then level.
    """

    net: np.ndarray
    potential: np.ndarray
    events: int
    lost: int
    pos: Optional[np.ndarray]
    neg: Optional[np.ndarray]
    event_step: Optional[np.ndarray]
    event_pixel: Optional[np.ndarray]
    event_fraction: Optional[np.ndarray]
    event_polarity: Optional[np.ndarray]


def _per_pixel(name, v, npix, broadcast):
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.size not in (1, npix):
        raise ValueError(f"{name} must be a scalar or an (H, W) array, got {a.size} values for {npix} pixels")
    return np.ascontiguousarray(np.broadcast_to(a, (npix,)) if broadcast else a)


def run_kernel(
    src: np.ndarray,
    potential: np.ndarray,
    pos_threshold,
    neg_threshold,
    *,
    lut: Optional[np.ndarray] = None,
    pair_of_step: Optional[np.ndarray] = None,
    extra=0.0,
    noise_std: float = 0.0,
    noise_seed: int = 0,
    first_pair: int = 0,
    refractory_cap: int = 0,
    split: bool = False,
    events: bool = False,
    narrow: bool = False,
) -> KernelResult:
    """Run the V2V step over a log-intensity path (see the module doc for the equations).

    Args:
        src: (M, H, W) path of M levels: uint8 / uint16 codes when ``lut`` is given, else
            float64 log intensity (log-intensity units). M - 1 sub-intervals.
        potential: (H, W) float32 or float64 dL_hat at the start (log-intensity units);
            updated in place after every frame pair (stored in its dtype).
        pos_threshold, neg_threshold: c+, c- (log-intensity units, > 0): scalars or (H, W).
        lut: float64 (full_scale + 1,) code -> log intensity (``simulate.log_intensity_lut``).
        pair_of_step: int64 (M - 1,) non-decreasing frame pair of each sub-interval, covering
            0..P-1 (default: one sub-interval per pair, P = M - 1).
        extra: extra dL per frame pair (log-intensity units): scalar or (H, W); the hot-pixel
            map plus any drift (leak), spread evenly over the pair's sub-intervals.
        noise_std: sigma of the background noise per frame pair (log-intensity units, >= 0).
        noise_seed: uint64 seed of the noise stream (see the module doc).
        first_pair: index of the first frame pair in the clip's noise stream (for chunks).
        refractory_cap: at most this many events of each polarity per pixel per frame pair
            (0 = no cap); the residual is not affected (the pixel still catches up).
        split: also return N+ and N- per pair (for count post-processing).
        events: also return every event (the event-level reference).
        narrow: return ``net`` in the narrowest of int8, int16, int32 that holds every count
            (the wire's voxel dtype), written int16 by the kernel and narrowed with the range
            it tracked, instead of int32 plus two passes to find the range; a clip that needs
            more than int16 is re-run in int32 from the same potential (same counts).

    Returns:
        :class:`KernelResult`.

    Raises:
        ValueError: for mismatched shapes or a bad ``pair_of_step``.
        OverflowError: when a pixel would need more than 2**31 - 1 events in one frame pair.
    """
    if src.ndim != 3:
        raise ValueError(f"src must be (M, H, W), got shape {src.shape}")
    m, h, w = src.shape
    npix = h * w
    if potential.shape != (h, w) or potential.dtype not in (np.float32, np.float64):
        raise ValueError(f"potential must be a float32/float64 {(h, w)} array, got {potential.dtype}{potential.shape}")
    if pair_of_step is None:
        pair_of_step = np.arange(m - 1, dtype=np.int64)
    pair_of_step = np.ascontiguousarray(pair_of_step, dtype=np.int64)
    if pair_of_step.shape != (m - 1,):
        raise ValueError(f"pair_of_step must have one entry per sub-interval ({m - 1}), got {pair_of_step.shape}")
    n_pairs = int(pair_of_step[-1]) + 1 if m > 1 else 0
    if m > 1 and (pair_of_step[0] != 0 or not np.all(np.isin(np.diff(pair_of_step), (0, 1)))):
        raise ValueError("pair_of_step must start at 0 and step by 0 or 1")
    flat = np.ascontiguousarray(src).reshape(m, npix)
    use_lut = lut is not None
    if use_lut:
        if flat.dtype not in (np.uint8, np.uint16):
            raise ValueError(f"src must be uint8/uint16 codes with a lut, got {flat.dtype}")
        lut_a = np.ascontiguousarray(lut, dtype=np.float64)
    else:
        flat = flat.astype(np.float64, copy=False)
        lut_a = np.zeros(1)
    cpa = _per_pixel("pos_threshold", pos_threshold, npix, False)
    cna = _per_pixel("neg_threshold", neg_threshold, npix, False)
    if cpa.size != cna.size:  # both scalars or both per pixel
        cpa = np.ascontiguousarray(np.broadcast_to(cpa, (npix,)))
        cna = np.ascontiguousarray(np.broadcast_to(cna, (npix,)))
    if np.any(~(cpa > 0)) or np.any(~(cna > 0)) or not (np.all(np.isfinite(cpa)) and np.all(np.isfinite(cna))):
        raise ValueError("contrast thresholds c+ and c- must be finite and > 0")
    ex = _per_pixel("extra", extra, npix, True)
    if not potential.flags.c_contiguous or not potential.flags.writeable:
        raise ValueError("potential must be a writeable C-contiguous array (it is updated in place)")
    pot_flat = potential.reshape(npix)
    pos = np.empty((n_pairs, h, w)) if split else np.empty((0, 1, 1))
    neg = np.empty((n_pairs, h, w)) if split else np.empty((0, 1, 1))
    start = potential.copy() if narrow else None
    for dtype in ((np.int16, np.int32) if narrow else (np.int32,)):
        if dtype is np.int32 and start is not None:
            potential[...] = start  # the int16 attempt overflowed: again, wide
        net = np.empty((n_pairs, h, w), dtype)
        ev, lost, overflow, lo, hi, es, ep, ef, epol = _kernel(
            flat, lut_a, use_lut, pair_of_step, n_pairs, pot_flat, cpa, cna, ex, float(noise_std),
            np.uint64(int(noise_seed) & (2**64 - 1)), int(first_pair), int(refractory_cap),
            net.reshape(n_pairs, npix), float(np.iinfo(dtype).max),
            pos.reshape(pos.shape[0], pos.shape[1] * pos.shape[2]), neg.reshape(neg.shape[0], neg.shape[1] * neg.shape[2]),
            bool(split), bool(events), _ZK, _ZW, _ZF)
        if overflow < 0:
            break
    if narrow and overflow < 0 and -128 <= lo and hi <= 127:
        net = net.astype(np.int8)
    if overflow >= 0:
        raise OverflowError(
            f"frame pair {overflow}: more than 2**31-1 events in one pixel (thresholds too small "
            f"for the int32 voxel grid)")
    return KernelResult(net, potential, int(ev), int(lost), pos if split else None, neg if split else None,
                        es if events else None, ep if events else None, ef if events else None,
                        epol if events else None)

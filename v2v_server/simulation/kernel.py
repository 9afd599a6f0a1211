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

Noise: one stream per frame pair. Frame pair ``first_pair + i`` draws its (H, W) standard
normals from 16 interleaved JSF32 generators (Jenkins' small fast generator, 32-bit, rotations
27 and 17, as randomgen's ``JSF(size=32)``: tested against it) whose states are seeded by
splitmix64 from (noise_seed, first_pair + i, lane), word ``k`` of the pair coming from lane
``k % 16``. The normals are Box-Muller transforms (Box & Muller, Ann. Math. Stat. 1958) of
24-bit uniforms in float32, with log, sine and cosine as fixed polynomials of IEEE operations
(no libm, no fused multiply-add: the same bits on every host): pixel ``j < ceil(n / 2)`` of a
frame of n pixels gets ``r cos(2 pi u2)`` and pixel ``ceil(n / 2) + j`` ``r sin(2 pi u2)``,
``r = sqrt(-2 ln u1)``, ``u1`` from word j and ``u2`` from word ``ceil(n / 2) + j``. The
transform is exact to float32 rounding (relative error under 1e-6) and bounded by
``NOISE_MAX`` = sqrt(50 ln 2) = 5.89 (the 24-bit u1 >= 2**-25; beyond it N(0, 1) has 4e-9
of its mass). Unlike a ziggurat it has no rejection branch, so it vectorises (8 float32
lanes with AVX2): 1.3 ns per normal here (words and transform) against 2.1 for the scalar
ziggurat used before.
The noise of a frame pair therefore depends only on (noise_seed, pair index, frame size), so
a clip simulated in chunks (``first_pair``) equals the clip in one call, and
:func:`noise_field` replays it.
"""
from __future__ import annotations

import math
from typing import NamedTuple, Optional

import numba
import numpy as np

from v2v_wire.commands import interrupt_in

__all__ = ["KernelResult", "run_kernel", "noise_field", "full_scale_of", "NOISE_MAX", "NOISE_LANES"]


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


_GOLD = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S32 = np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(32)
_M32 = np.uint64(0xFFFFFFFF)
_U = np.uint32
_F = np.float32
#: interleaved JSF32 generators per frame pair (two AVX2 vectors of 32-bit words)
NOISE_LANES = 16
_JSF_A = _U(0xF1EA5EED)  # Jenkins' constant first word
_JSF_WARMUP = 20  # Jenkins' warm-up rounds after seeding
#: largest |N(0, 1)| draw of the kernel's Box-Muller transform: sqrt(-2 ln 2**-25)
NOISE_MAX = math.sqrt(50.0 * math.log(2.0))
_NOISE_BOUND = NOISE_MAX * (1.0 + 1e-5)  # with the float32 rounding of the transform

# float32 constants of the transform (Taylor coefficients; the ranges below keep the
# truncation error under float32 rounding)
_LN2 = _F(math.log(2.0))
_SQRT2 = _F(math.sqrt(2.0))
_TWO_PI = _F(2.0 * math.pi)
_TWO_M24 = _F(2.0**-24)
_L1, _L2, _L3, _L4, _L5 = (_F(2.0 / k) for k in (3, 5, 7, 9, 11))
_S3, _S5, _S7, _S9 = (_F(x) for x in (-1 / 6, 1 / 120, -1 / 5040, 1 / 362880))
_C2, _C4, _C6, _C8, _C10 = (_F(x) for x in (-1 / 2, 1 / 24, -1 / 720, 1 / 40320, -1 / 3628800))


@numba.njit(cache=True, inline="always")
def _mix(z):
    """splitmix64's finaliser (Steele et al., OOPSLA 2014): uint64 -> uint64."""
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@numba.njit(cache=True, inline="always")
def _seed_pair(noise_seed, pair):
    return _mix(np.uint64(noise_seed) ^ _mix(np.uint64(pair) + _GOLD))


@numba.njit(cache=True, inline="always")
def _rotl(x, k):
    return (x << _U(k)) | (x >> _U(32 - k))


@numba.njit(cache=True, error_model="numpy")
def _jsf_words(st, out):
    """Fill ``out`` (uint32 (n * NOISE_LANES,)) from the NOISE_LANES JSF32 states ``st``
    (uint32 (4, NOISE_LANES): a, b, c, d), word k from lane k % NOISE_LANES; the states advance.
    JSF32 (Jenkins 2007, the two-rotation version): e = a - rot(b, 27); a = b ^ rot(c, 17);
    b = c + d; c = d + e; d = e + a; output d."""
    sa, sb, sc, sd = st[0], st[1], st[2], st[3]
    for j in range(out.shape[0] // NOISE_LANES):
        for q in range(NOISE_LANES):  # independent lanes: vectorised
            a, b, c, d = sa[q], sb[q], sc[q], sd[q]
            e = a - _rotl(b, 27)
            a = b ^ _rotl(c, 17)
            b = c + d
            c = d + e
            d = e + a
            out[j * NOISE_LANES + q] = d
            sa[q], sb[q], sc[q], sd[q] = a, b, c, d


@numba.njit(cache=True)
def _jsf_seed(key, st, warm):
    """Seed the lanes of ``st`` from the 64-bit ``key``: lane q gets a = 0xf1ea5eed and b, c,
    d from splitmix64 of (key, q), then ``warm`` words are drawn and dropped."""
    for q in range(NOISE_LANES):
        y = _mix(key + np.uint64(q + 1) * _GOLD)
        z = _mix(y + _GOLD)
        st[0, q] = _JSF_A
        st[1, q] = _U(y & _M32)
        st[2, q] = _U(y >> _S32)
        st[3, q] = _U(z & _M32)
    _jsf_words(st, warm)


@numba.njit(cache=True, inline="always", error_model="numpy")
def _ln32(x):
    """Natural log of a float32 x in (0, 1]: x = 2**e m, m in [sqrt(1/2), sqrt(2)),
    ln m = 2 atanh(s), s = (m - 1) / (m + 1), as an odd series to s**11 (|s| <= 0.172)."""
    b = np.float32(x).view(np.int32)
    e = _F((b >> 23) - 127)
    m = np.int32((b & np.int32(0x007FFFFF)) | np.int32(0x3F800000)).view(np.float32)
    big = m > _SQRT2
    m = m * _F(0.5) if big else m
    e = e + _F(1.0) if big else e
    f = m - _F(1.0)
    s = f / (_F(2.0) + f)
    z = s * s
    r = z * (_L1 + z * (_L2 + z * (_L3 + z * (_L4 + z * _L5))))
    return e * _LN2 + (_F(2.0) * s + s * r)


@numba.njit(cache=True, inline="always", error_model="numpy")
def _sincos_turn(u):
    """(sin, cos) of 2 pi u for a float32 u in [0, 1): the nearest quarter turn q / 4 is taken
    out (|2 pi (u - q / 4)| <= pi / 4) and the rest is a Taylor series to the 9th / 10th power."""
    q = np.floor(u * _F(4.0) + _F(0.5))
    r = (u - q * _F(0.25)) * _TWO_PI
    z = r * r
    s = r * (_F(1.0) + z * (_S3 + z * (_S5 + z * (_S7 + z * _S9))))
    c = _F(1.0) + z * (_C2 + z * (_C4 + z * (_C6 + z * (_C8 + z * _C10))))
    qi = np.int32(q)
    odd = (qi & 1) != 0
    sn = c if odd else s
    cs = s if odd else c
    return (sn * (_F(1.0) - _F(2.0) * _F((qi >> 1) & 1)),
            cs * (_F(1.0) - _F(2.0) * _F((qi ^ (qi >> 1)) & 1)))


@numba.njit(cache=True, error_model="numpy")
def _box_muller(words, half, out):
    """out[j] = r cos(2 pi u2), out[half + j] = r sin(2 pi u2) for j < half, r = sqrt(-2 ln u1),
    u1 = (words[j] >> 8 + 1/2) 2**-24, u2 = (words[half + j] >> 8) 2**-24 (float32)."""
    for j in range(half):
        u1 = (_F(words[j] >> _U(8)) + _F(0.5)) * _TWO_M24
        u2 = _F(words[half + j] >> _U(8)) * _TWO_M24
        r = np.sqrt(_F(-2.0) * _ln32(u1))
        sn, cs = _sincos_turn(u2)
        out[j] = r * cs
        out[half + j] = r * sn


@numba.njit(cache=True)
def _noise_work(npix):
    """Buffers of one frame pair's draw: lane states, words, normals (float32, >= npix)."""
    half = (npix + 1) // 2
    nw = -(-2 * half // NOISE_LANES) * NOISE_LANES
    return (np.empty((4, NOISE_LANES), np.uint32), np.empty(nw, np.uint32), np.empty(2 * half, np.float32),
            np.empty(_JSF_WARMUP * NOISE_LANES, np.uint32))


@numba.njit(cache=True)
def _draw_pair(noise_seed, pair, npix, st, words, z, warm):
    """The N(0, 1) draws of frame pair ``pair`` into z[:npix] (float32; see the module doc)."""
    _jsf_seed(_seed_pair(noise_seed, pair), st, warm)
    _jsf_words(st, words)
    _box_muller(words, (npix + 1) // 2, z)


@numba.njit(cache=True)
def _noise_field(noise_seed, first_pair, n_pairs, npix, out):
    st, words, z, warm = _noise_work(npix)
    for i in range(n_pairs):
        _draw_pair(noise_seed, first_pair + i, npix, st, words, z, warm)
        for p in range(npix):
            out[i, p] = z[p]


def noise_field(noise_seed: int, n_pairs: int, shape, first_pair: int = 0) -> np.ndarray:
    """The standard normals the kernel adds (times sigma) at frame pairs
    ``first_pair .. first_pair + n_pairs - 1``: float64 (n_pairs, H, W), each a float32 draw
    (see the module doc). For tests and conservation checks: the kernel draws exactly these."""
    h, w = shape
    out = np.empty((n_pairs, h * w))
    _noise_field(np.uint64(int(noise_seed) & (2**64 - 1)), int(first_pair), int(n_pairs), h * w, out)
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


@numba.njit(cache=True)
def _count_bound(lrange, emax, potmax, cmax, cmin):
    """Bound on any count of a one-step pair of plain V2V: |dL| <= log range ``lrange`` + the
    pair's largest extra dL ``emax`` + |dL_hat|, |dL_hat| <= max(``potmax``, ``cmax``), over
    the smaller threshold ``cmin`` (doubled dL_hat for margin). The kernel's fast path and
    ``run_kernel``'s int8 choice both test it."""
    return (lrange + emax + 2.0 * max(potmax, cmax)) / cmin


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
            first_pair, cap, net, big, pos_out, neg_out, want_split, want_events):
    """Core loop; see :func:`run_kernel`. ``src``: (M, npix) codes (``use_lut``) or float64
    levels; ``cpa``, ``cna``: float64 (npix,) or (1,) (a scalar); ``extra``: float64 (npix,);
    ``net``: int8, int16 or int32 (P, npix), ``big`` the largest count it may hold (a pair needing
    more stops the loop and is reported as ``overflow``)."""
    m = src.shape[0]
    npix = src.shape[1]
    has_noise = noise_std > 0.0
    nst, nwords, nz, nwarm = _noise_work(npix if has_noise else 0)
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
    xmax = 0.0
    for p in range(npix):
        potmax = max(potmax, abs(potential[p]))
        xmax = max(xmax, abs(extra[p]))
    lrange = 0.0
    if use_lut:
        lrange = lut.max() - lut.min()
        for p in range(npix):
            prev[p] = lut[np.int64(src[0, p])]
    s = 0
    for i in range(n_pairs):
        kk = k[i]
        # the pair's extra dL (hot pixels, drift, noise), spread evenly over its sub-intervals
        # (x / 1 is x: the common one-step pair skips the vector division); emax bounds its
        # size from max|extra| and the largest draw, NOISE_MAX, so these loops are plain maps
        emax = (xmax + noise_std * _NOISE_BOUND) / kk if has_noise else xmax / kk
        if has_noise:
            _draw_pair(noise_seed, first_pair + i, npix, nst, nwords, nz, nwarm)
            if kk == 1:
                for p in range(npix):
                    e[p] = extra[p] + nz[p] * noise_std
            else:
                for p in range(npix):
                    e[p] = (extra[p] + nz[p] * noise_std) / kk
        elif kk == 1:
            for p in range(npix):
                e[p] = extra[p]
        else:
            for p in range(npix):
                e[p] = extra[p] / kk
        if fast and kk == 1 and _count_bound(lrange, emax, potmax, cmax, cmin) < big:
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


def _check_path(src: np.ndarray, potential: np.ndarray):
    """(M, H, W) of ``src``, checked against ``potential`` (float32/float64 (H, W), writeable and
    C-contiguous: the kernel updates it in place). Raises ``ValueError`` naming the array."""
    if src.ndim != 3:
        raise ValueError(f"src must be (M, H, W), got shape {src.shape}")
    m, h, w = src.shape
    if potential.shape != (h, w) or potential.dtype not in (np.float32, np.float64):
        raise ValueError(f"potential must be a float32/float64 {(h, w)} array, got {potential.dtype}{potential.shape}")
    if not potential.flags.c_contiguous or not potential.flags.writeable:
        raise ValueError("potential must be a writeable C-contiguous array (it is updated in place)")
    return m, h, w


def _pairs_of_steps(pair_of_step: Optional[np.ndarray], m: int):
    """``(pair_of_step, P)``: the frame pair of each of the M - 1 sub-intervals as contiguous
    int64 (default: one sub-interval per pair) and the number of pairs P. Raises ``ValueError``
    unless it starts at 0 and steps by 0 or 1."""
    if pair_of_step is None:
        pair_of_step = np.arange(m - 1, dtype=np.int64)
    pair_of_step = np.ascontiguousarray(pair_of_step, dtype=np.int64)
    if pair_of_step.shape != (m - 1,):
        raise ValueError(f"pair_of_step must have one entry per sub-interval ({m - 1}), got {pair_of_step.shape}")
    n_pairs = int(pair_of_step[-1]) + 1 if m > 1 else 0
    if m > 1 and (pair_of_step[0] != 0 or not np.all(np.isin(np.diff(pair_of_step), (0, 1)))):
        raise ValueError("pair_of_step must start at 0 and step by 0 or 1")
    return pair_of_step, n_pairs


def _levels(flat: np.ndarray, lut: Optional[np.ndarray]):
    """``(levels, lut, use_lut)`` as the kernel reads them: uint8/uint16 codes with a float64
    look-up table, or float64 log intensities with a placeholder table. Raises ``ValueError``
    for codes of another dtype."""
    if lut is not None:
        if flat.dtype not in (np.uint8, np.uint16):
            raise ValueError(f"src must be uint8/uint16 codes with a lut, got {flat.dtype}")
        return flat, np.ascontiguousarray(lut, dtype=np.float64), True
    return flat.astype(np.float64, copy=False), np.zeros(1), False


def _thresholds(pos_threshold, neg_threshold, npix: int):
    """c+ and c- as float64 arrays of one value or one per pixel (both the same size). Raises
    ``ValueError`` unless every value is finite and > 0."""
    cpa = _per_pixel("pos_threshold", pos_threshold, npix, False)
    cna = _per_pixel("neg_threshold", neg_threshold, npix, False)
    if cpa.size != cna.size:  # both scalars or both per pixel
        cpa = np.ascontiguousarray(np.broadcast_to(cpa, (npix,)))
        cna = np.ascontiguousarray(np.broadcast_to(cna, (npix,)))
    if np.any(~(cpa > 0)) or np.any(~(cna > 0)) or not (np.all(np.isfinite(cpa)) and np.all(np.isfinite(cna))):
        raise ValueError("contrast thresholds c+ and c- must be finite and > 0")
    return cpa, cna


def _int8_holds(lut_a, ex, noise_std, pot_flat, cpa, cna) -> bool:
    """True when no count of the kernel's fast path can exceed 127 (the bound of
    :func:`_count_bound` before the first pair): then int8 straight from the kernel never
    overflows and nothing is re-run."""
    return _count_bound(float(lut_a.max() - lut_a.min()), float(np.abs(ex).max()) + float(noise_std) * _NOISE_BOUND,
                        float(np.abs(pot_flat).max(initial=0.0)), float(max(cpa.max(), cna.max())),
                        float(min(cpa.min(), cna.min()))) < 127


def _narrowed(net: np.ndarray, narrow: bool, overflow: int, lo: int, hi: int) -> np.ndarray:
    """The kernel's counts ``net``, as int8 when ``narrow`` and every count (in [lo, hi]) fits.

    Raises:
        OverflowError: when the widest attempt overflowed at frame pair ``overflow`` (>= 0).
    """
    if overflow >= 0:
        raise OverflowError(
            f"frame pair {overflow}: more than 2**31-1 events in one pixel (thresholds too small "
            f"for the int32 voxel grid)")
    if narrow and net.dtype != np.int8 and -128 <= lo and hi <= 127:
        return net.astype(np.int8)
    return net


def _interruptible(*args):
    """``_kernel(*args)``, with Ctrl-C (or SIGTERM, ``v2v_wire.commands.Terminated``) during the
    compiled call raised as itself: numba's dispatcher reports the pending interrupt as a
    SystemError wrapping it, once per nested dispatcher (four deep here), and
    ``commands.interrupt_in`` finds it at any depth."""
    try:
        return _kernel(*args)
    except SystemError as e:
        interrupt = interrupt_in(e)
        if interrupt is not None:
            raise interrupt from None
        raise


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
            (the wire's voxel dtype), written by the kernel in int8 when no count can exceed
            127 (a bound from the log range, thresholds, extra dL, NOISE_MAX and the starting
            potential; plain V2V with c+, c- above ~0.06 to 0.1), else in int16 and narrowed
            with the range it tracked, instead of int32 plus two passes to find the range; a
            clip that needs more is re-run wider from the same potential (same counts).

    Returns:
        :class:`KernelResult`.

    Raises:
        ValueError: for mismatched shapes or a bad ``pair_of_step``.
        OverflowError: when a pixel would need more than 2**31 - 1 events in one frame pair.
    """
    m, h, w = _check_path(src, potential)
    npix = h * w
    pair_of_step, n_pairs = _pairs_of_steps(pair_of_step, m)
    flat, lut_a, use_lut = _levels(np.ascontiguousarray(src).reshape(m, npix), lut)
    cpa, cna = _thresholds(pos_threshold, neg_threshold, npix)
    ex = _per_pixel("extra", extra, npix, True)
    pot_flat = potential.reshape(npix)
    pos, neg = (np.empty((n_pairs, h, w) if split else (0, 1, 1)) for _ in range(2))
    start = potential.copy() if narrow else None
    int8 = narrow and use_lut and not (split or events or refractory_cap) and n_pairs == m - 1 and \
        _int8_holds(lut_a, ex, noise_std, pot_flat, cpa, cna)
    widths = ((np.int8,) if int8 else ()) + ((np.int16, np.int32) if narrow else (np.int32,))
    for dtype in widths:
        if dtype is not widths[0]:
            potential[...] = start  # the narrower attempt overflowed: again, wider
        net = np.empty((n_pairs, h, w), dtype)
        ev, lost, overflow, lo, hi, es, ep, ef, epol = _interruptible(
            flat, lut_a, use_lut, pair_of_step, n_pairs, pot_flat, cpa, cna, ex, float(noise_std),
            np.uint64(int(noise_seed) & (2**64 - 1)), int(first_pair), int(refractory_cap),
            net.reshape(n_pairs, npix), float(np.iinfo(dtype).max),
            pos.reshape(pos.shape[0], pos.shape[1] * pos.shape[2]), neg.reshape(neg.shape[0], neg.shape[1] * neg.shape[2]),
            bool(split), bool(events))
        if overflow < 0:
            break
    net = _narrowed(net, narrow, overflow, lo, hi)
    return KernelResult(net, potential, int(ev), int(lost), pos if split else None, neg if split else None,
                        es if events else None, ep if events else None, ef if events else None,
                        epol if events else None)

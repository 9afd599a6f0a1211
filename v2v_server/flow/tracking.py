"""The tracked flow's array work (``flow.FlowEstimator`` with a ``tracked`` option): the
tracking grid and its bilinear expansion to a dense field, the fill of points LK lost, the
per-pair decisions (equal frames, points to search again) and the zoom compensation's
similarity fit, as numpy tables and numba loops; ``flow.py`` keeps the options, OpenCV calls
and the tracking loop that wires these together.
"""
from __future__ import annotations

import math
from typing import Dict, Optional

import numba
import numpy as np

from v2v_wire.protocol import flow_grid_taps

#: Zoom compensation (``TrackParams.zoom``) starts only when the fitted similarity explains at
#: least this fraction of the points' motion (to 1 px, or 10 % of a point's motion).
ZOOM_INLIERS = 0.75
#: ... and only up to 2x per frame (``|log s| <= log 2``): a larger fitted scale is not a zoom
#: but points lost in one place.
ZOOM_MAX = math.log(2.0)

_TRACK_GRIDS: Dict[tuple, tuple] = {}


def _track_grid(n: int, h: int, w: int):
    """The ``n`` x ``n`` tracking grid of an (h, w) crop, corners included (grid point k of a
    row sits at x = k (w - 1) / (n - 1)): float32 points (n * n, 1, 2) (x, y), and the
    bilinear interpolation matrices ``wy`` (h, n) and ``wx_t`` (n, w) of
    ``protocol.flow_grid_taps``, so that ``wy @ g @ wx_t`` is the (h, w) field of an (n, n)
    grid field ``g``. Made once, read-only."""
    key = (n, h, w)
    g = _TRACK_GRIDS.get(key)
    if g is None:
        xs = np.linspace(0, w - 1, n, dtype=np.float32)
        ys = np.linspace(0, h - 1, n, dtype=np.float32)
        pts = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 1, 2).astype(np.float32)

        def weights(size):  # (size, n): the two taps of each pixel as a matrix
            first, w0, w1 = flow_grid_taps(n, size)
            m = np.zeros((size, n), np.float32)
            rows = np.arange(size)
            m[rows, first], m[rows, first + 1] = w0, w1
            return m

        wy, wx_t = weights(h), np.ascontiguousarray(weights(w).T)
        for a in (pts, wy, wx_t):
            a.setflags(write=False)
        g = _TRACK_GRIDS[key] = (pts, wy, wx_t)
    return g


_FILL_TABLES: Dict[tuple, tuple] = {}


def _fill_lost(grid_flow: np.ndarray, ok: np.ndarray, sigma: float = 2.0, ridge: float = 1e-2,
               support: float = 0.1) -> np.ndarray:
    """Grid flows (V, n, n, 2) with the points not ``ok`` (V, n, n) replaced by a local affine
    fit of the valid points of the same grid: for each lost point, weighted least squares of
    ``flow = a0 + a1 x + a2 y`` over the valid points with Gaussian weights of ``sigma`` grid
    steps around it, the slopes damped by ``(ridge * sum(weights) + support) * (a1^2 + a2^2)``,
    evaluated at the lost point, then kept within the valid points' range of the grid widened
    by that range on each side. An affine fit extends rotation and zoom, where the points LK
    drops are mostly those that left the crop, whose flow keeps growing with the radius. The
    damping makes a fit the valid points do not determine (one valid point, or a few far away:
    LK drops most points of a blurred fast pan) fall back towards their weighted mean instead
    of extrapolating a slope across the crop. A grid without any valid point becomes zero."""
    lost = ~ok.reshape(ok.shape[0], -1)
    if not lost.any():
        return grid_flow
    n = ok.shape[-1]
    key = (n, sigma)
    wts = _FILL_TABLES.get(key)
    if wts is None:
        yy, xx = np.divmod(np.arange(n * n, dtype=np.float64), n)
        wts = _FILL_TABLES[key] = np.exp(-((xx[:, None] - xx[None, :]) ** 2 + (yy[:, None] - yy[None, :]) ** 2)
                                          / (2 * sigma * sigma))
    out = np.ascontiguousarray(grid_flow, dtype=np.float32).reshape(grid_flow.shape[0], n * n, 2).copy()
    _fill_lost_core(out, np.ascontiguousarray(lost), wts, n, float(ridge), float(support))
    return out.reshape(grid_flow.shape)


@numba.njit(cache=True)
def _fill_lost_core(flow, lost, wts, n, ridge, support):
    """``_fill_lost`` in place on ``flow`` float32 (V, n * n, 2), ``lost`` bool (V, n * n),
    ``wts`` float64 (n * n, n * n) Gaussian weights; float64 sums, each lost point's 3 x 3
    normal equations solved by Gaussian elimination with partial pivoting."""
    m = n * n
    a = np.empty((3, 3))
    r = np.empty((3, 2))
    for v in range(flow.shape[0]):
        nlost = 0
        lo0 = lo1 = np.inf
        hi0 = hi1 = -np.inf
        for k in range(m):
            if lost[v, k]:
                nlost += 1
            else:
                f0, f1 = float(flow[v, k, 0]), float(flow[v, k, 1])
                lo0, hi0 = min(lo0, f0), max(hi0, f0)
                lo1, hi1 = min(lo1, f1), max(hi1, f1)
        if nlost == 0:
            continue
        if nlost == m:  # no valid point: zero
            for k in range(m):
                flow[v, k, 0] = 0.0
                flow[v, k, 1] = 0.0
            continue
        # the valid range widened by itself on each side
        c0lo, c0hi = 2 * lo0 - hi0, 2 * hi0 - lo0
        c1lo, c1hi = 2 * lo1 - hi1, 2 * hi1 - lo1
        for q in range(m):  # lost points read only valid ones: each is written in place
            if not lost[v, q]:
                continue
            # weighted moments of the valid points around q: 1, x, y, xx, xy, yy and 1, x, y times the flow
            s0 = sx = sy = sxx = sxy = syy = 0.0
            b0 = b1 = bx0 = bx1 = by0 = by1 = 0.0
            for k in range(m):
                if lost[v, k]:
                    continue
                wk = wts[q, k]
                x, y = float(k % n), float(k // n)
                f0, f1 = float(flow[v, k, 0]), float(flow[v, k, 1])
                s0 += wk
                sx += wk * x
                sy += wk * y
                sxx += wk * x * x
                sxy += wk * x * y
                syy += wk * y * y
                b0 += wk * f0
                b1 += wk * f1
                bx0 += wk * x * f0
                bx1 += wk * x * f1
                by0 += wk * y * f0
                by1 += wk * y * f1
            d = ridge * s0 + support  # the slopes' damping
            a[0, 0], a[0, 1], a[0, 2] = s0, sx, sy
            a[1, 0], a[1, 1], a[1, 2] = sx, sxx + d, sxy
            a[2, 0], a[2, 1], a[2, 2] = sy, sxy, syy + d
            r[0, 0], r[0, 1], r[1, 0], r[1, 1], r[2, 0], r[2, 1] = b0, b1, bx0, bx1, by0, by1
            for c in range(3):  # elimination with partial pivoting
                piv = c
                for i in range(c + 1, 3):
                    if abs(a[i, c]) > abs(a[piv, c]):
                        piv = i
                if piv != c:
                    for j in range(3):
                        a[c, j], a[piv, j] = a[piv, j], a[c, j]
                    for j in range(2):
                        r[c, j], r[piv, j] = r[piv, j], r[c, j]
                for i in range(c + 1, 3):
                    g = a[i, c] / a[c, c]
                    for j in range(c, 3):
                        a[i, j] -= g * a[c, j]
                    for j in range(2):
                        r[i, j] -= g * r[c, j]
            for c in range(2, -1, -1):
                for j in range(2):
                    t = r[c, j]
                    for i in range(c + 1, 3):
                        t -= a[c, i] * r[i, j]
                    r[c, j] = t / a[c, c]
            x, y = float(q % n), float(q // n)
            flow[v, q, 0] = min(max(r[0, 0] + r[1, 0] * x + r[2, 0] * y, c0lo), c0hi)
            flow[v, q, 1] = min(max(r[0, 1] + r[1, 1] * x + r[2, 1] * y, c1lo), c1hi)


@numba.njit(cache=True)
def _same_as_previous(frames, repeats):
    """bool (N,): frame k equals frame k - 1 pixel for pixel (True where ``repeats`` says so,
    without looking; False for frame 0). Stops at the first differing pixel of a pair."""
    n = frames.shape[0]
    out = np.zeros(n, np.bool_)
    flat = frames.reshape(n, -1)
    for k in range(1, n):
        if repeats[k]:
            out[k] = True
            continue
        eq = True
        for q in range(flat.shape[1]):
            if flat[k, q] != flat[k - 1, q]:
                eq = False
                break
        out[k] = eq
    return out


@numba.njit(cache=True)
def _dropped_inside(st, ok, nxt, w, h, out):
    """Mark in ``out`` (bool (m,)) the points LK dropped (``st`` uint8 (m, 1) == 0) that were
    ``ok`` until now and whose last position ``nxt`` (float32 (m, 1, 2)) is still inside the
    (h, w) crop; returns how many (one pass instead of seven numpy operations per pair)."""
    n = 0
    for k in range(st.shape[0]):
        x, y = nxt[k, 0, 0], nxt[k, 0, 1]
        r = st[k, 0] == 0 and ok[k] and x >= 0 and x <= w - 1 and y >= 0 and y <= h - 1
        out[k] = r
        n += r
    return n


@numba.njit(cache=True)
def _fit_once(p, q, use):
    """Least-squares similarity of the points ``use`` selects: (ok, a, b, tx, ty, sp, sq), with
    sp, sq the spreads (sums of squared distances to their means) of those points of p and q."""
    n = 0
    mpx = mpy = mqx = mqy = 0.0
    for k in range(p.shape[0]):
        if use[k]:
            n += 1
            mpx += p[k, 0]
            mpy += p[k, 1]
            mqx += q[k, 0]
            mqy += q[k, 1]
    if n < 2:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    mpx /= n
    mpy /= n
    mqx /= n
    mqy /= n
    den = sq = sa = sb = 0.0
    for k in range(p.shape[0]):
        if use[k]:
            px, py = p[k, 0] - mpx, p[k, 1] - mpy
            qx, qy = q[k, 0] - mqx, q[k, 1] - mqy
            den += px * px + py * py
            sq += qx * qx + qy * qy
            sa += px * qx + py * qy
            sb += px * qy - py * qx
    if den <= 1e-9:
        return False, 0.0, 0.0, 0.0, 0.0, den, sq
    a, b = sa / den, sb / den
    return True, a, b, mqx - (a * mpx - b * mpy), mqy - (b * mpx + a * mpy), den, sq


@numba.njit(cache=True, inline="always")
def _residual(a, b, tx, ty, p, q, k):
    """Distance (px) between point k of q and where the similarity (a, b, tx, ty) takes p's."""
    return math.hypot(a * p[k, 0] - b * p[k, 1] + tx - q[k, 0], b * p[k, 0] + a * p[k, 1] + ty - q[k, 1])


@numba.njit(cache=True)
def _zoom_fit(p, q, good, zoom, whole, inliers, out):
    """The similarity taking points ``p`` to ``q`` (float (m, 2), px) over the points ``good``,
    written to ``out`` (float64 (2, 3)) when it changes scale by more than ``zoom`` and at most
    ``ZOOM_MAX`` (|log s|; ``zoom`` negative: any) and, with ``whole``, brings at least the
    fraction ``inliers`` of the good points within max(1 px, 10 % of their motion). Returns
    whether it did. The common case (no zoom) ends after one pass: the spread of the points
    about their mean grows by the scale of a similarity."""
    m = p.shape[0]
    n = 0
    for k in range(m):
        n += good[k]
    if n < 4:
        return False
    ok, a, b, tx, ty, sp, sq = _fit_once(p, q, good)
    if not ok or (zoom >= 0.0 and abs(0.5 * math.log(max(sq, 1e-12) / sp)) <= zoom):
        return False
    # refit once without the points the first fit leaves far off (points LK kept on the wrong
    # match, or on an object moving otherwise): residual over max(1 px, 3 x the median)
    res = np.empty(n)
    j = 0
    for k in range(m):
        if good[k]:
            res[j] = _residual(a, b, tx, ty, p, q, k)
            j += 1
    cut = max(1.0, 3.0 * np.median(res))
    keep = good.copy()
    kept = 0
    j = 0
    for k in range(m):
        if good[k]:
            keep[k] = res[j] <= cut
            kept += keep[k]
            j += 1
    if 3 <= kept < n:
        ok2, a2, b2, tx2, ty2, _, _ = _fit_once(p, q, keep)
        if ok2:
            a, b, tx, ty = a2, b2, tx2, ty2
    if zoom >= 0.0 and not zoom < abs(0.5 * math.log(max(a * a + b * b, 1e-12))) <= ZOOM_MAX:
        return False
    if whole:
        fit = 0
        for k in range(m):
            if good[k]:
                fit += _residual(a, b, tx, ty, p, q, k) <= max(1.0, 0.1 * math.hypot(q[k, 0] - p[k, 0], q[k, 1] - p[k, 1]))
        if fit < inliers * n:
            return False
    out[0, 0], out[0, 1], out[0, 2] = a, -b, tx
    out[1, 0], out[1, 1], out[1, 2] = b, a, ty
    return True


@numba.njit(cache=True)
def _to_resized(p, sim, fx, fy, dw, dh, w, h, out):
    """Zoom compensation, forward: the positions ``sim`` predicts for points ``p`` (float32
    (m, 1, 2)) in frame b, expressed in b resized to (dh, dw) (``cv2.resize``'s pixel centres:
    b's x = (x' + 0.5) * fx - 0.5), written to ``out`` relative to the top-left corner
    (ox, oy) of the w x h window of the resized b that is centred on them (kept inside it when
    it is larger). Returns (ox, oy)."""
    m = p.shape[0]
    sx = sy = 0.0
    for k in range(m):
        x, y = p[k, 0, 0], p[k, 0, 1]
        u = (sim[0, 0] * x + sim[0, 1] * y + sim[0, 2] + 0.5) / fx - 0.5
        v = (sim[1, 0] * x + sim[1, 1] * y + sim[1, 2] + 0.5) / fy - 0.5
        out[k, 0, 0], out[k, 0, 1] = u, v
        sx += u
        sy += v
    ox = min(max(int(round(sx / m - (w - 1) / 2.0)), 0), max(dw - w, 0))
    oy = min(max(int(round(sy / m - (h - 1) / 2.0)), 0), max(dh - h, 0))
    for k in range(m):
        out[k, 0, 0] -= ox
        out[k, 0, 1] -= oy
    return ox, oy


@numba.njit(cache=True)
def _from_resized(r, ox, oy, fx, fy, w, h, st):
    """Zoom compensation, back: points ``r`` (float32 (m, 1, 2)) found in the window at (ox, oy)
    of the resized b, in place to b's pixels; a point that lands outside b (what the resized
    window shows there is reflected, not seen) is marked lost in ``st``."""
    for k in range(r.shape[0]):
        x = (r[k, 0, 0] + ox + 0.5) * fx - 0.5
        y = (r[k, 0, 1] + oy + 0.5) * fy - 0.5
        r[k, 0, 0], r[k, 0, 1] = x, y
        if not (0.0 <= x <= w - 1 and 0.0 <= y <= h - 1):
            st[k] = False


def _similarity_fit(p: np.ndarray, q: np.ndarray) -> Optional[np.ndarray]:
    """Least-squares similarity (scale, rotation, translation) taking points ``p`` to ``q``
    (float (k, 2) each, pixels, k >= 4): float64 (2, 3) ``[[a, -b, tx], [b, a, ty]]`` with
    ``q ~ M[:, :2] @ p + M[:, 2]`` (the closed form of Umeyama 1991 without reflection), refit
    once without the points whose residual exceeds ``max(1 px, 3 x the median)`` (points LK
    kept on the wrong match, or on an object moving otherwise). None when the points have no
    spread (all in one place) or are fewer than 4. The tracker calls ``_zoom_fit`` directly."""
    p, q = np.ascontiguousarray(p, np.float64), np.ascontiguousarray(q, np.float64)
    out = np.empty((2, 3))
    return out if _zoom_fit(p, q, np.ones(len(p), np.bool_), -1.0, False, 0.0, out) else None

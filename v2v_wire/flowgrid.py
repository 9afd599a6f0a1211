"""The wire's compact flow made dense: bilinear expansion of tracked grid flows.

The tracked flow options compute a sample's flow at an n x n grid of points per voxel grid
(``flow.FlowEstimator.voxel_flow_grids``, the wire's ``flow_grid``) and make it dense by
bilinear interpolation with the taps of ``protocol.flow_grid_taps``. This numba loop is that
expansion, in float32 with one rounding per product and per sum; the server makes dense flow
with it, and the client expands a CPU batch's ``flow_grid`` with it too (one thread, no
thread pool; ~12x faster than the same taps in torch ops on the CPU, ``bench.wire``), so both
give the same bits. On other devices the client uses torch (``v2v_client.flowgrid``) with the
same taps.

numba is an optional speed-up: without it (a trainer host that installed ``v2v[client]`` only)
the same products and sums run as numpy array operations (``_expand_numpy``), the same float32
bits, slower (``python -m bench.flowgrid`` prints the ratio).
"""
from __future__ import annotations

import numpy as np

from v2v_wire.protocol import flow_grid_taps

try:
    import numba
except ImportError:  # a client-only install: the numpy path below
    numba = None

__all__ = ["expand_grids", "HAVE_NUMBA"]

#: Whether the numba loop is available (else the numpy path, same bits).
HAVE_NUMBA = numba is not None


def _expand_tables(n: int, h: int, w: int):
    """``protocol.flow_grid_taps`` of the rows (h) then the columns (w): int64 first grid
    row and float32 weights of it and the next row, the same for the columns."""
    return flow_grid_taps(n, h) + flow_grid_taps(n, w)


def _expand_grids(grids, i0, a0, a1, j0, b0, b1, out):
    """Dense flow ``out`` float32 (V, 2, h, w) from grid flows ``grids`` float32 (V, n, n, 2),
    bilinear between the grid points: ``wy @ g @ wx_t`` of ``tracking._track_grid`` with only
    its two non-zero terms per row and column (``_expand_tables``), in float32."""
    n = grids.shape[1]
    w = j0.shape[0]
    tmp = np.empty((n, w), np.float32)
    for v in range(grids.shape[0]):
        for c in range(2):
            for i in range(n):
                for x in range(w):
                    tmp[i, x] = b0[x] * grids[v, i, j0[x], c] + b1[x] * grids[v, i, j0[x] + 1, c]
            for y in range(i0.shape[0]):
                r0, r1 = tmp[i0[y]], tmp[i0[y] + 1]
                wa, wb = a0[y], a1[y]
                row = out[v, c, y]
                for x in range(w):
                    row[x] = wa * r0[x] + wb * r1[x]


if HAVE_NUMBA:
    _expand_grids = numba.njit(cache=True, error_model="numpy", nogil=True)(_expand_grids)


def _expand_numpy(g, i0, a0, a1, j0, b0, b1, out):
    """:func:`_expand_grids` as numpy array operations on ``g`` float32 (V, 2, n, n): the same
    float32 products and sums (each rounded once, no fused multiply-add), so the same bits.
    The rows between two grid rows k and k + 1 are one slice (``i0`` is non-decreasing)."""
    tmp = np.ascontiguousarray(b0 * g[..., j0] + b1 * g[..., j0 + 1])  # (V, 2, n, w)
    starts = np.flatnonzero(np.diff(i0, prepend=-1))
    for y0, y1 in zip(starts, list(starts[1:]) + [len(i0)]):
        k = i0[y0]
        np.add(a0[y0:y1, None] * tmp[..., k:k + 1, :], a1[y0:y1, None] * tmp[..., k + 1:k + 2, :],
               out=out[..., y0:y1, :])


def expand_grids(grids: np.ndarray, size, use_numba: bool = HAVE_NUMBA) -> np.ndarray:
    """Dense flow float32 (L, 2, H, W) of tracked grid flows ``grids`` (L, 2, n, n), converted
    to float32 (``FlowEstimator.voxel_flow_grids``, the wire's ``flow_grid``; L may be any
    number of fields) over a ``size`` = (H, W) crop, in pixels (channel 0 x, channel 1 y):
    bilinear between the grid points with ``protocol.flow_grid_taps``; with the numba loop when
    ``use_numba`` (default: when numba is installed), else numpy (the same bits).

    Raises:
        ValueError: for grids that are not (L, 2, n, n) with n >= 2, or a size under 2 px.
    """
    g = np.asarray(grids, np.float32)
    if g.ndim != 4 or g.shape[1] != 2 or g.shape[2] != g.shape[3] or g.shape[2] < 2:
        raise ValueError(f"flow grids must be (L, 2, n, n) with n >= 2, got {g.shape}")
    h, w = (int(s) for s in size)
    out = np.empty((g.shape[0], 2, h, w), np.float32)
    if use_numba and not HAVE_NUMBA:
        raise ValueError("use_numba=True, but numba is not installed (pip install 'v2v[server]')")
    if use_numba:
        _expand_grids(np.ascontiguousarray(g.transpose(0, 2, 3, 1)), *_expand_tables(g.shape[2], h, w), out)
    else:
        _expand_numpy(g, *_expand_tables(g.shape[2], h, w), out)
    return out

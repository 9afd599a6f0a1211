"""The wire's compact flow made dense: bilinear expansion of tracked grid flows.

The tracked flow options compute a sample's flow at an n x n grid of points per voxel grid
(``flow.FlowEstimator.voxel_flow_grids``, the wire's ``flow_grid``) and make it dense by
bilinear interpolation with the taps of ``protocol.flow_grid_taps``. This numba loop is that
expansion, in float32 with one rounding per product and per sum; the server makes dense flow
with it, and the client expands a CPU batch's ``flow_grid`` with it too (one thread, no
thread pool; ~12x faster than the same taps in torch ops on the CPU, ``bench.wire``), so both
give the same bits. On other devices the client uses torch (``v2v_client.flowgrid``) with the
same taps.
"""
from __future__ import annotations

import numba
import numpy as np

from v2v_wire.protocol import flow_grid_taps

__all__ = ["expand_grids"]


def _expand_tables(n: int, h: int, w: int):
    """``protocol.flow_grid_taps`` of the rows (h) then the columns (w): int64 first grid
    row and float32 weights of it and the next row, the same for the columns."""
    return flow_grid_taps(n, h) + flow_grid_taps(n, w)


@numba.njit(cache=True, error_model="numpy", nogil=True)
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


def expand_grids(grids: np.ndarray, size) -> np.ndarray:
    """Dense flow float32 (L, 2, H, W) of tracked grid flows ``grids`` (L, 2, n, n), converted
    to float32 (``FlowEstimator.voxel_flow_grids``, the wire's ``flow_grid``; L may be any
    number of fields) over a ``size`` = (H, W) crop, in pixels (channel 0 x, channel 1 y):
    bilinear between the grid points with ``protocol.flow_grid_taps``.

    Raises:
        ValueError: for grids that are not (L, 2, n, n) with n >= 2, or a size under 2 px.
    """
    g = np.asarray(grids, np.float32)
    if g.ndim != 4 or g.shape[1] != 2 or g.shape[2] != g.shape[3] or g.shape[2] < 2:
        raise ValueError(f"flow grids must be (L, 2, n, n) with n >= 2, got {g.shape}")
    h, w = (int(s) for s in size)
    out = np.empty((g.shape[0], 2, h, w), np.float32)
    _expand_grids(np.ascontiguousarray(g.transpose(0, 2, 3, 1)), *_expand_tables(g.shape[2], h, w), out)
    return out

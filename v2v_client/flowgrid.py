"""Dense optical flow from the compact ``flow_grid`` a tracked flow option sends.

The tracked options (``flow_preset`` ``tracked``, ``tracked-g12``) compute a sample's flow at
an n x n grid of tracked points per voxel grid and make it dense by bilinear interpolation
between them, so the wire carries only the grid (``flow_grid`` float32 (B, L, 2, n, n): 20 KB
per sample for n = 8 against 2.6 MB of dense float16 flow). :func:`expand_flow_grid` makes it
dense again with the very taps the server's expansion uses (``protocol.flow_grid_taps``), with
the same float32 operations (one rounding per product and per sum): on the CPU with the
server's own loop (``v2v_wire.flowgrid``: one thread, so it costs the trainer's torch thread
pool nothing, under 1 ms per default sample with numba, ~7x that with the numpy path of a
client-only install: bench.flowgrid), on other devices in torch; the result equals the server's
dense flow bit for bit.
"""
from __future__ import annotations

from typing import Dict, Tuple

import torch

from v2v_wire.protocol import flow_grid_taps

__all__ = ["expand_flow_grid"]

_TAPS: Dict[tuple, tuple] = {}


def _taps(n: int, size: int, device: torch.device) -> tuple:
    key = (n, size, str(device))
    t = _TAPS.get(key)
    if t is None:
        first, w0, w1 = flow_grid_taps(n, size)
        f = torch.tensor(first, device=device)  # copies: the taps are read-only numpy arrays
        t = _TAPS[key] = (f, f + 1, torch.tensor(w0, device=device), torch.tensor(w1, device=device))
    return t


def expand_flow_grid(grid: torch.Tensor, size: Tuple[int, int], dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Dense flow of tracked grid flows, bilinear between the grid points.

    Args:
        grid: (..., 2, n, n) flow in pixels at the grid points (n >= 2; float32 as on the wire,
            any float dtype is converted to float32 first), on any device: grid point (i, j)
            sits at ``(j (W - 1) / (n - 1), i (H - 1) / (n - 1))`` px.
        size: (H, W) of the dense field, pixels (the crop size).
        dtype: dtype of the result (the float32 field is cast at the end, e.g. ``torch.float16``
            rounds to nearest even as the server's float16 flow).

    Returns:
        (..., 2, H, W) flow in pixels on ``grid``'s device, channel 0 x, channel 1 y.

    Raises:
        ValueError: for a grid that is not (..., 2, n, n) with n >= 2, or a bad size.
    """
    if not isinstance(grid, torch.Tensor) or grid.ndim < 3 or grid.shape[-3] != 2 or \
            grid.shape[-1] != grid.shape[-2] or grid.shape[-1] < 2:
        raise ValueError(f"flow grid must be a tensor (..., 2, n, n) with n >= 2, got "
                         f"{tuple(getattr(grid, 'shape', ())) or type(grid).__name__}")
    h, w = (int(s) for s in size)
    if h < 1 or w < 1:
        raise ValueError(f"flow size must be positive (H, W), got {tuple(size)}")
    n = grid.shape[-1]
    if grid.device.type == "cpu":
        from v2v_wire.flowgrid import expand_grids  # numba when installed (else numpy, the same bits)

        flat = grid.detach().float().reshape(-1, 2, n, n).numpy()
        out = torch.from_numpy(expand_grids(flat, (h, w))).reshape(grid.shape[:-2] + (h, w))
    else:
        out = _expand_torch(grid, h, w)
    return out if dtype == torch.float32 else out.to(dtype)


def _expand_torch(grid: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """:func:`expand_flow_grid` in torch ops on ``grid``'s device, float32 (..., 2, h, w)."""
    n = grid.shape[-1]
    i0, i1, a0, a1 = _taps(n, h, grid.device)
    j0, j1, b0, b1 = _taps(n, w, grid.device)
    g = grid.float().reshape(-1, n, n)
    # along the width: (M, n, W), then along the height: (M, H, W); each a product and a sum in
    # float32 (separate roundings), as the server's expansion
    t = g.index_select(2, j0).mul_(b0)
    t.add_(g.index_select(2, j1).mul_(b1))
    out = torch.mul(t.index_select(1, i0), a0[:, None])
    out.add_(t.index_select(1, i1).mul_(a1[:, None]))
    return out.reshape(grid.shape[:-2] + (h, w))

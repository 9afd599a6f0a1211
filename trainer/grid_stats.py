"""Event statistics on one time grid, the same for a stream's voxel grids and a real recording.

A *grid cell* is one voxel grid's time span (``B x frames_per_bin`` frame intervals of the
source: 0.2 s for the paper's 5 bins at 25 fps) over all the pixels of a crop or a sensor. A
recording is cut into consecutive cells of that duration from its first event, each of B bins of
equal length, so both sides give per cell and per pixel the counts N+ and N- of each bin. Per cell:

* ``rate_signal``: events (N+ + N-) per pixel per second;
* ``rate_net``: sum over the bins of |N+ - N-|, per pixel per second: what a signed voxel grid
  holds (the stream's voxels with one frame pair per bin give N+ or N- of each bin, so there
  signal and net are equal);
* ``active_fraction``: the share of pixels with at least one event in the cell;
* ``polarity_balance``: N+ / (N+ + N-) (None in a cell without events);
* ``events_per_active``: events per active pixel (None in a cell without events);
* ``still_rate``: the rate of *isolated* events, per pixel per second: events at a pixel none of
  whose 8 neighbours fires in the cell. A moving edge fires neighbouring pixels together; an
  event with no neighbour is background activity (the background-activity filter's criterion,
  Delbruck 2008; v2e's noise filters), so this is the rate of the still regions' noise, measured
  the same way on both sides without frames.

Rates are over all the cell's pixels (an active fraction of 1 % with 4 events per active pixel
in 0.2 s is 0.2 events / pixel / s).
"""
from __future__ import annotations

from typing import Dict, Iterator, List

import numpy as np

#: (key, label, unit) of each per-cell statistic, in the order pages and tables show them.
GRID_STATS = (("rate_signal", "events / pixel / s (signal, N+ + N-)", "ev/px/s"),
              ("rate_net", "events / pixel / s (net, |N+ - N-| per bin)", "ev/px/s"),
              ("active_fraction", "fraction of pixels with an event", ""),
              ("polarity_balance", "polarity balance N+ / (N+ + N-)", ""),
              ("events_per_active", "events per active pixel", "ev"),
              ("still_rate", "isolated events / pixel / s (still regions: noise)", "ev/px/s"))


def _isolated(active: np.ndarray) -> np.ndarray:
    """bool (..., H, W): active pixels none of whose 8 neighbours is active."""
    p = np.pad(active, [(0, 0)] * (active.ndim - 2) + [(1, 1), (1, 1)])
    h, w = active.shape[-2:]
    nb = np.zeros(active.shape, np.int8)
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            if dy != 1 or dx != 1:
                nb += p[..., dy:dy + h, dx:dx + w]
    return active & (nb == 0)


def cell_stats(pos: np.ndarray, neg: np.ndarray, cell_s: float) -> List[Dict[str, float]]:
    """The module's statistics of each grid cell (pure).

    Args:
        pos, neg: non-negative integer (C, B, H, W) N+ and N- per cell, bin and pixel.
        cell_s: one cell's duration, seconds (> 0).

    Returns:
        C dicts with the keys of :data:`GRID_STATS` (floats; None for the balance and the events
        per active pixel of a cell without events: JSON's null, which every reader of
        ``stats.json`` parses, where NaN is no JSON).

    Raises:
        ValueError: shapes that differ or are not 4-D, or ``cell_s`` not > 0.
    """
    if pos.shape != neg.shape or pos.ndim != 4:
        raise ValueError(f"pos and neg must be (C, B, H, W) of one shape, got {pos.shape} and {neg.shape}")
    if not cell_s > 0:
        raise ValueError(f"cell_s must be > 0, got {cell_s!r}")
    c, _, h, w = pos.shape
    npix = h * w
    p = pos.astype(np.int64, copy=False)
    n = neg.astype(np.int64, copy=False)
    per_pix = (p + n).sum(axis=1)  # (C, H, W) events
    net = np.abs(p - n).sum(axis=(1, 2, 3))
    active = per_pix > 0
    n_act = active.sum(axis=(1, 2))
    iso = np.where(_isolated(active), per_pix, 0).sum(axis=(1, 2))
    sp, sn = p.sum(axis=(1, 2, 3)), n.sum(axis=(1, 2, 3))
    out = []
    for k in range(c):
        ev = int(sp[k] + sn[k])
        out.append({"rate_signal": ev / npix / cell_s, "rate_net": int(net[k]) / npix / cell_s,
                    "active_fraction": int(n_act[k]) / npix,
                    "polarity_balance": float(sp[k]) / ev if ev else None,
                    "events_per_active": ev / int(n_act[k]) if n_act[k] else None,
                    "still_rate": int(iso[k]) / npix / cell_s})
    return out


def voxel_cell_stats(voxels: np.ndarray, cell_s: float) -> List[Dict[str, float]]:
    """:func:`cell_stats` of a stream sample's voxel grids: signed counts (L, B, H, W) (any
    integer dtype, N+ - N- per bin), each grid one cell of ``cell_s`` seconds. Exact for one
    frame pair per bin without refinement (a bin holds N+ or N- of its pixel, never both); a
    lower bound of the signal otherwise (opposite events in one bin cancel)."""
    v = np.asarray(voxels)
    if v.ndim != 4:
        raise ValueError(f"voxels must be (L, B, H, W), got {v.shape}")
    v = v.astype(np.int64)
    return cell_stats(np.maximum(v, 0), np.maximum(-v, 0), cell_s)


def recording_cells(chunks: Iterator[np.ndarray], width: int, height: int, cell_us: int, bins: int
                    ) -> Iterator[tuple]:
    """Bin a recording's events into consecutive cells of ``cell_us`` microseconds from the
    first event, each of ``bins`` equal bins; yields ``(pos, neg)`` int32 (1, B, H, W) per
    complete cell, empty cells included, the last incomplete cell left out.

    Args:
        chunks: time-ordered :data:`trainer.recordings.EVENT_DTYPE` arrays (``Recording.chunks``).
        width, height: the sensor, pixels; cell_us: > 0; bins: >= 1.
    """
    if cell_us < bins or bins < 1:
        raise ValueError(f"a cell of {cell_us} us cannot hold {bins} bins")
    bin_us = cell_us / bins
    npix = width * height
    acc = np.zeros((2, bins * npix), np.int32)
    t0, cur = None, 0
    for ch in chunks:
        if not len(ch):
            continue
        if t0 is None:
            t0 = int(ch["t"][0])
        rel = ch["t"] - t0
        cell = rel // cell_us
        while True:
            inside = cell == cur
            if inside.any():
                seg = ch[inside]
                b = np.minimum(((rel[inside] - cur * cell_us) / bin_us).astype(np.int64), bins - 1)
                idx = b * npix + seg["y"].astype(np.int64) * width + seg["x"]
                on = seg["p"] > 0
                acc[0] += np.bincount(idx[on], minlength=bins * npix).astype(np.int32)
                acc[1] += np.bincount(idx[~on], minlength=bins * npix).astype(np.int32)
            if cell[-1] <= cur:
                break
            yield acc[0].reshape(1, bins, height, width).copy(), acc[1].reshape(1, bins, height, width).copy()
            acc[:] = 0
            cur += 1


def summarise(cells: List[Dict[str, float]]) -> Dict[str, Dict[str, float]]:
    """Per statistic of :data:`GRID_STATS`: ``n`` (cells with a value), ``median``, ``p10``,
    ``p90`` and ``mean`` over ``cells`` (NaNs left out)."""
    out = {}
    for key, _, _ in GRID_STATS:
        a = np.asarray([c[key] for c in cells if c.get(key) is not None], np.float64)
        a = a[np.isfinite(a)]
        if not a.size:
            out[key] = {"n": 0}
            continue
        p10, p50, p90 = np.percentile(a, [10, 50, 90])
        out[key] = {"n": int(a.size), "median": float(p50), "p10": float(p10), "p90": float(p90),
                    "mean": float(a.mean())}
    return out

"""Real events into voxel grids: the edges of the grids (between frames, fixed windows, or a
fixed number of events each) and the grids themselves, the paper's discrete voxel grid
(signed counts per pixel and bin; the event_cnn_minimal interpolated grid is
``v2v_server.simulation.reference.voxel_interpolated``). Events come as
:data:`trainer.recordings.EVENT_DTYPE` chunks (:meth:`trainer.recordings.Recording.chunks`)."""
from __future__ import annotations

from typing import Iterator, Tuple

import numpy as np

__all__ = ["window_edges", "count_edges", "voxel_grids", "events_to_voxels"]


def window_edges(t_first_us: int, t_last_us: int, window_us: int) -> np.ndarray:
    """Edges of fixed windows ``t_first + k * window_us`` covering [t_first, t_last]: int64
    (K+1,) microseconds; the last window ends after ``t_last``."""
    if window_us <= 0:
        raise ValueError("window_us must be positive")
    k = (int(t_last_us) - int(t_first_us)) // int(window_us) + 1
    return int(t_first_us) + np.arange(k + 1, dtype=np.int64) * int(window_us)


def count_edges(chunks, events_per_grid: int) -> np.ndarray:
    """Edges of voxel grids holding ``events_per_grid`` events each: the timestamps of events
    0, N, 2N, ... and one past the last event, int64 (K+1,) microseconds, strictly increasing
    (events sharing a timestamp with an edge go to the later grid, so a grid can hold a few
    more or fewer than N). Reads ``chunks`` (:meth:`Recording.chunks`) once.

    Raises:
        ValueError: ``events_per_grid`` < 1, or no events.
    """
    n = int(events_per_grid)
    if n < 1:
        raise ValueError("events_per_grid must be >= 1")
    edges, seen, last = [], 0, None
    for ev in chunks:
        first_idx = (-seen) % n  # index in this chunk of the next multiple of n
        edges.append(ev["t"][first_idx::n])
        seen += ev.size
        last = int(ev["t"][-1])
    if last is None:
        raise ValueError("no events")
    return np.unique(np.concatenate(edges + [np.array([last + 1], np.int64)]))


def voxel_grids(chunks, edges_us: np.ndarray, num_bins: int, height: int, width: int
                ) -> Iterator[Tuple[int, np.ndarray, np.ndarray]]:
    """The paper's discrete voxel grids between consecutive edges, built from event chunks: the
    one voxel-grid routine of the trainer (:func:`events_to_voxels` reads whole arrays through it).

    Interval k covers ``[edges[k], edges[k+1])``; an event at t in it goes to bin
    ``floor(B * (t - t0) / (t1 - t0))`` (clipped to B - 1; computed exactly for integer
    microseconds, in float64 for float seconds) and adds its polarity ``p``: +1 for positive,
    -1 for negative, so the bin value is N+ - N-.

    Args:
        chunks: iterable of :data:`trainer.recordings.EVENT_DTYPE` arrays (or anything indexed by
            ``"t"``, ``"x"``, ``"y"``, ``"p"`` with p in {-1, 1} and t in the edges' unit), t
            non-decreasing across chunks (:meth:`Recording.chunks`); events outside every
            interval are ignored.
        edges_us: (K+1,) increasing edges: int64 microseconds (frame timestamps or
            :func:`window_edges`), or float seconds (kept as float64).
        num_bins: B.
        height, width: sensor size, pixels.

    Yields:
        ``(k, voxel int32 (B, H, W), counts int32 (H, W))`` for k = 0..K-1 in order, also for
        intervals without events; counts are the events per pixel (for sparse metrics).
        The arrays are fresh for each k.

    Raises:
        ValueError: edges that do not increase.
    """
    edges = np.asarray(edges_us)
    edges = edges.astype(np.float64 if edges.dtype.kind == "f" else np.int64, copy=False)
    if edges.ndim != 1 or edges.size < 2 or np.any(np.diff(edges) <= 0):
        raise ValueError("edges_us must be an increasing 1-D array of >= 2 timestamps")
    n, hw, nb = edges.size - 1, height * width, int(num_bins)
    k = 0
    vox = np.zeros(nb * hw, np.int64)
    cnt = np.zeros(hw, np.int64)

    def emit():
        return k, vox.reshape(nb, height, width).astype(np.int32), cnt.reshape(height, width).astype(np.int32)

    for ev in chunks:
        if k >= n:
            break
        t = ev["t"]
        k0 = k
        j_last = min(n - 1, int(np.searchsorted(edges, t[-1], "right")) - 1)
        # only the edges this chunk reaches: events of interval j are pos[j - k0]:pos[j - k0 + 1]
        pos = np.searchsorted(t, edges[k0:j_last + 2], "left")
        for j in range(k0, j_last + 1):
            while k < j:
                yield emit()
                vox[:], cnt[:] = 0, 0
                k += 1
            a, b = pos[j - k0], pos[j - k0 + 1]
            if a == b:
                continue
            t0, dt = edges[j], edges[j + 1] - edges[j]
            bins = np.minimum(_bins(nb * (t[a:b] - t0), dt), nb - 1)
            pix = ev["y"][a:b].astype(np.int64) * width + ev["x"][a:b]
            # in place: the cost follows the chunk's events, not the sensor's pixels
            np.add.at(vox, bins * hw + pix, ev["p"][a:b])
            np.add.at(cnt, pix, 1)
    while k < n:
        yield emit()
        vox[:], cnt[:] = 0, 0
        k += 1


def _bins(scaled: np.ndarray, dt) -> np.ndarray:
    """``floor(scaled / dt)`` as int64: exact integer division for integer times, float64
    division then floor for float times."""
    if scaled.dtype.kind in "iu" and isinstance(dt, (int, np.integer)):
        return scaled // dt
    return np.floor(scaled / dt).astype(np.int64)


# -- the event_cnn_minimal H5 layout read whole (the paper protocol's scorer uses it) --

def events_to_voxels(xs: np.ndarray, ys: np.ndarray, ts: np.ndarray, ps: np.ndarray, t_edges: np.ndarray,
                     num_bins: int, height: int, width: int) -> Tuple[np.ndarray, np.ndarray]:
    """Discrete voxel grids between consecutive timestamps.

    Args:
        xs, ys: int pixel coordinates (column, row) of the events, shape (E,).
        ts: event times in seconds, (E,), non-decreasing.
        ps: polarities, (E,), in {0, 1} or {-1, 1} (0 and -1 are negative).
        t_edges: (N,) increasing frame times, seconds; voxel i covers [t_i, t_{i+1}).
        num_bins: B.
        height, width: sensor size, pixels.

    Returns:
        ``(voxels, counts)``: voxels int32 (N-1, B, H, W), bin value N+ - N-; counts int32
        (N-1, H, W), the number of events per pixel in each interval (for sparse metrics).

    Raises:
        ValueError: for unsorted times or edges, or coordinates outside the sensor.
    """
    t_edges = np.asarray(t_edges, np.float64)
    if t_edges.ndim != 1 or t_edges.size < 2 or np.any(np.diff(t_edges) <= 0):
        raise ValueError("t_edges must be an increasing 1-D array of >= 2 timestamps")
    ts = np.asarray(ts, np.float64)
    if ts.size and np.any(np.diff(ts) < 0):
        raise ValueError("event timestamps must be non-decreasing")
    xs = np.asarray(xs, np.int64)
    ys = np.asarray(ys, np.int64)
    if xs.size and (xs.min() < 0 or ys.min() < 0 or xs.max() >= width or ys.max() >= height):
        raise ValueError(f"event coordinates outside the {height}x{width} sensor")
    pol = np.where(np.asarray(ps) > 0, 1, -1).astype(np.int64)
    chunks = [{"t": ts, "x": xs, "y": ys, "p": pol}] if ts.size else []
    voxels = np.empty((t_edges.size - 1, num_bins, height, width), np.int32)
    counts = np.empty((t_edges.size - 1, height, width), np.int32)
    for k, vox, cnt in voxel_grids(chunks, t_edges, num_bins, height, width):
        voxels[k], counts[k] = vox, cnt
    return voxels, counts

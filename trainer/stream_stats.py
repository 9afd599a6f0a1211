"""The statistics ``v2v-stats`` reports: samples' params read from a server or simulated from a
corpus, and the same event statistics measured on a real recording in windows of the samples'
duration.

A sample's statistics are made by the worker (``v2v_server.samples.stats``: events per pixel per
second by polarity over the sample and per voxel grid, active-pixel fraction, flow magnitude);
this module only gathers them into rows, one per sample, and measures a recording the same way:
events per pixel per second by polarity and the fraction of pixels with at least one event, in
consecutive windows of a fixed duration from the first event (the last, incomplete window is left
out). Each row also carries ``cells``, the ``trainer.grid_stats`` statistics of each of its voxel
grids, and :func:`recording_grid` measures a recording on the same grid.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Dict, Iterator, List, Optional

import numpy as np

from trainer.grid_stats import cell_stats, recording_cells, voxel_cell_stats

#: The params copied into a row (besides the sample's ``stats``), when present.
ROW_KEYS = ("sample_id", "pos_threshold", "neg_threshold", "noise_std", "hot_pixel_count", "src_start_frame",
            "src_frames", "video_fps", "pauses", "shot", "shot_start_frame")


class StatsInputError(RuntimeError):
    """An input ``v2v-stats`` cannot use (server, corpus or recording); the message names it."""


def sample_row(params: dict, voxels: Optional[np.ndarray] = None, recipe=None) -> dict:
    """One sample's row: the ``ROW_KEYS`` of its ``params`` and its ``stats`` flattened
    (``grid_rates`` kept as a list); the video is the sample id's path. Given the sample's
    ``voxels`` (L, B, H, W), also ``cells``: ``grid_stats.voxel_cell_stats`` of each voxel
    grid, whose duration is B x frames per bin frame intervals at ``video_fps``: frames per bin
    from the params (``src_frames + pauses`` is the window's L x B x frames_per_bin + 1 frames),
    else from ``recipe`` (a ``SampleRecipe``), else 1."""
    row = {k: params[k] for k in ROW_KEYS if k in params}
    row.update(params.get("stats") or {})
    sid = str(params.get("sample_id", ""))
    row["video"] = sid.rpartition("#")[0] or sid
    fps = params.get("video_fps")
    if voxels is not None and fps:
        L, B = voxels.shape[:2]
        fpb = recipe.frames_per_bin if recipe is not None else 1
        if isinstance(params.get("src_frames"), int) and isinstance(params.get("pauses"), int):
            fpb = max(1, (params["src_frames"] + params["pauses"] - 1) // (L * B))
        row["cells"] = voxel_cell_stats(voxels, B * fpb / float(fps))
    return row


def grid_seconds(recipe, fps: float) -> float:
    """One voxel grid's duration, seconds: ``num_bins x frames_per_bin`` frame intervals at ``fps`` Hz."""
    return recipe.num_bins * recipe.frames_per_bin / float(fps)


@dataclass
class Collected:
    """What was gathered: ``rows`` (one per sample, :func:`sample_row`), ``videos`` (one dict per
    video of a simulated corpus: ``path``, ``width``, ``height``, ``fps``, ``codec``, ``frames``,
    ``windows``, ``shot_lengths`` in frames, ``lower_bound``), ``source`` (what was read, in
    words). The check decodes a video only until the recipe's windows are complete
    (``max_samples_per_video``), as ``v2v-serve --check`` does: with ``lower_bound`` true it
    stopped there, and ``frames`` and the last of ``shot_lengths`` are lower bounds (``--check``
    shows ``9+ frames``)."""

    rows: List[dict] = field(default_factory=list)
    videos: List[dict] = field(default_factory=list)
    source: str = ""


def from_server(endpoint: str, n: int, timeout_s: float, progress: Callable[[int], None], recipe=None) -> Collected:
    """The params of ``n`` samples read from the server at ``endpoint`` (``open_stream``; the
    default outputs: the worker measures what it makes); with ``recipe`` (the
    server's ``SampleRecipe``: bins and frames per bin) each row's grid ``cells`` from its voxels.

    Raises:
        StatsInputError: the server does not answer within ``timeout_s`` or ends the stream
            with an error.
    """
    from v2v_client.plan_dataset import PlanServerError, open_stream

    out = Collected(source=f"server {endpoint}")
    ds = None
    try:
        ds = open_stream(endpoint, timeout_s=timeout_s, raw=True)
        for batch in ds:
            vox = batch.get("voxels")
            for i, params in enumerate(batch["params"]):
                if batch["padding"][i]:
                    continue
                out.rows.append(sample_row(params, None if vox is None else np.asarray(vox[i]), recipe))
                progress(1)
                if len(out.rows) >= n:
                    return out
    except (TimeoutError, PlanServerError) as e:
        raise StatsInputError(f"server {endpoint}: {e}") from None
    finally:
        close = getattr(ds, "close", None)
        if callable(close):
            close()
    return out


def _probe(source, rel: str) -> dict:
    """The codec and frame rate of ``rel`` as its container declares them."""
    import av

    try:
        with source.open(rel) as path, av.open(path if isinstance(path, str) else path) as c:
            s = c.streams.video[0]
            return {"codec": s.codec_context.name, "fps": float(s.average_rate or 0)}
    except Exception as e:  # a probe failure leaves the columns empty: the pass reports the file
        return {"codec": f"? ({type(e).__name__})", "fps": 0.0}


def from_corpus(cfg, videos_arg: str, n: int, progress: Callable[[int], None], epochs: int = 1) -> Collected:
    """``n`` samples simulated from the corpus at ``videos_arg`` (folder, list or bucket, as
    ``v2v-serve --videos``) with ``cfg``'s recipe (a ``ServeConfig``), in epochs 0 .. ``epochs`` - 1
    (each epoch draws every sample's parameters afresh), video by video in the corpus's order;
    each video's windows and shots from ``check.check_video``.

    Raises:
        StatsInputError: the corpus cannot be listed or holds no video.
    """
    from v2v_server.frames.check import check_video
    from v2v_server.ops.startup import start_source
    from v2v_server.samples.make import video_samples
    from v2v_server.sources.errors import StoreError

    try:
        start = start_source(cfg, videos_arg)  # the start-up path v2v-serve runs: the same source and caches
    except (OSError, ValueError, StoreError) as e:
        raise StatsInputError(f"corpus {videos_arg}: {e}") from None
    source, caches, names = start.source, start.caches, start.videos
    if not names:
        raise StatsInputError(f"corpus {videos_arg}: no video (extensions {', '.join(cfg.video_extensions)})")
    recipe = cfg.recipe
    out = Collected(source=f"corpus {videos_arg}")
    usable = []
    for rel in names:
        v = check_video(recipe.windows, recipe.decode, source, rel, caches)
        bounds = [0, *sorted(v.cuts), v.frames]
        width, height = (v.stream.width, v.stream.height) if v.stream is not None else (0, 0)
        out.videos.append({"path": rel, "width": width, "height": height, "frames": v.frames, "windows": v.windows,
                           "reason": v.reason, "shot_lengths": [b - a for a, b in zip(bounds, bounds[1:]) if b > a],
                           "lower_bound": bool(v.more), **_probe(source, rel)})
        if v.usable:
            usable.append(rel)
    for epoch in range(epochs):
        for rel in usable:
            for _key, arrays, meta in video_samples(recipe, source, rel, epoch, ("voxels", "flow"), flow_grid=True,
                                                    caches=caches):
                out.rows.append(sample_row(meta, arrays["voxels"], recipe))
                progress(1)
                if len(out.rows) >= n:
                    return out
    return out


def _windows(chunks: Iterator[np.ndarray], width: int, height: int, window_us: int) -> List[dict]:
    """Per complete window of ``window_us`` from the first event: ``pos``, ``neg`` (events) and
    ``active`` (pixels with an event); windows without any event included."""
    npix = width * height
    out: List[dict] = []
    t0, cur = None, 0
    seen = np.zeros(npix, bool)
    pos = neg = 0
    for ch in chunks:
        if not len(ch):
            continue
        if t0 is None:
            t0 = int(ch["t"][0])
        k = (ch["t"] - t0) // window_us
        starts = np.concatenate([[0], np.flatnonzero(np.diff(k)) + 1, [len(ch)]])
        for a, b in zip(starts[:-1], starts[1:]):
            kk = int(k[a])
            while kk > cur:  # the window in progress is complete (and any empty ones after it)
                out.append({"pos": pos, "neg": neg, "active": int(np.count_nonzero(seen))})
                seen[:] = False
                pos = neg = 0
                cur += 1
            seg = ch[a:b]
            npos = int(np.count_nonzero(seg["p"] > 0))
            pos, neg = pos + npos, neg + len(seg) - npos
            inside = (seg["x"] < width) & (seg["y"] < height)
            seen[seg["y"][inside].astype(np.int64) * width + seg["x"][inside]] = True
    return out


def check_recording(path: str) -> None:
    """Open the recording at ``path`` (its header and size), before any sampling.

    Raises:
        StatsInputError: it cannot be read (``RecordingError``'s message).
    """
    from trainer.recordings import RecordingError, open_recording

    try:
        open_recording(path)
    except RecordingError as e:
        raise StatsInputError(f"recording {e}") from None


def recording_windows(path: str, window_s: float) -> dict:
    """Events per pixel per second by polarity (``rate_pos``, ``rate_neg``) and the active-pixel
    fraction of each complete ``window_s`` window of the recording at ``path`` (any format
    ``trainer.recordings.open_recording`` reads).

    Returns:
        ``{"path", "sensor": "WxH", "format", "window_s", "duration_s", "truncated", "windows":
        [{"rate_pos", "rate_neg", "active_fraction"}...]}``; ``windows`` is empty when the
        recording is shorter than one window; ``truncated``: the file ends inside a packet or
        word (``Recording.truncated``: the events before the cut are measured).

    Raises:
        StatsInputError: the file cannot be read (``RecordingError``'s message).
    """
    from trainer.recordings import RecordingError, open_recording

    try:
        rec = open_recording(path)
        npix = rec.width * rec.height
        first = last = None
        window_us = max(1, int(round(window_s * 1e6)))

        def chunks():
            nonlocal first, last
            for ch in rec.chunks():
                if len(ch):
                    first = int(ch["t"][0]) if first is None else first
                    last = int(ch["t"][-1])
                yield ch

        wins = _windows(chunks(), rec.width, rec.height, window_us)
    except RecordingError as e:
        raise StatsInputError(f"recording {e}") from None
    rows = [{"rate_pos": w["pos"] / npix / window_s, "rate_neg": w["neg"] / npix / window_s,
             "active_fraction": w["active"] / npix} for w in wins]
    return {"path": str(path), "sensor": f"{rec.width}x{rec.height}", "format": rec.format, "window_s": window_s,
            "duration_s": (last - first) / 1e6 if first is not None else 0.0, "truncated": rec.truncated,
            "windows": rows}


def recording_grid(path: str, cell_s: float, bins: int) -> dict:
    """The recording at ``path`` cut into grid cells of ``cell_s`` seconds of ``bins`` bins
    (``grid_stats.recording_cells``) and each cell's ``grid_stats.cell_stats``.

    Returns:
        ``{"path", "sensor": "WxH", "format", "cell_s", "bins", "cells": [...]}``; ``cells`` is
        empty when the recording is shorter than one cell.

    Raises:
        StatsInputError: the file cannot be read (``RecordingError``'s message).
    """
    from trainer.recordings import RecordingError, open_recording

    cells: List[dict] = []
    try:
        rec = open_recording(path)
        for pos, neg in recording_cells(rec.chunks(), rec.width, rec.height, max(bins, int(round(cell_s * 1e6))), bins):
            cells += cell_stats(pos, neg, cell_s)
    except RecordingError as e:
        raise StatsInputError(f"recording {e}") from None
    return {"path": str(path), "sensor": f"{rec.width}x{rec.height}", "format": rec.format, "cell_s": cell_s,
            "bins": bins, "cells": cells}


def summary(values) -> Dict[str, float]:
    """``n``, ``mean`` and the 10th, 50th and 90th percentiles of ``values`` (NaN-free floats)."""
    a = np.asarray([v for v in values if v is not None], dtype=np.float64)
    if not a.size:
        return {"n": 0}
    p10, p50, p90 = np.percentile(a, [10, 50, 90])
    return {"n": int(a.size), "mean": float(a.mean()), "p10": float(p10), "p50": float(p50), "p90": float(p90)}

"""``v2v-serve --warm-cache``: fill this host's frame cache (``frames.frame_cache``) with every
video of the corpus (or of this host's shard) before training starts, so that clusters that
prepare CPU hosts ahead of GPU time serve the first epoch from the cache too; and the cache's
line of ``v2v-serve --check``.

Each video is read the one way every reader reads one, as a worker's sample pass reads it
(``frames.video_read.read_video``, part ``"frames"``): decoded and stored on a miss, read back
(every frame's checksum verified) on a hit, and recorded in the host's corpus index.
"""
from __future__ import annotations

from typing import List, Optional, Sequence

from v2v_server.ops.config import ServeConfig
from v2v_server.frames.frame_cache import SKIP_CAUSES, FrameCache
from v2v_server.frames.host_caches import HostCaches
from v2v_server.frames.frame_pass import entry_settings, lookup_entry
from v2v_server.sources.source import VideoSource
from v2v_server.frames.video_pool import map_videos
from v2v_server.frames.video_read import read_video


def warm_video(cfg: ServeConfig, source: VideoSource, rel: str, caches: HostCaches) -> dict:
    """Read video ``rel`` of ``source`` through the host's frame cache (``caches.frame_cache``): ``{"path", "frames", "state", "bytes"}``, state ``cached`` (already there, read back
    whole), ``stored``, or ``not stored: CAUSE`` (budget, disk_full, write_error, or the
    decoding error)."""
    out = {"path": rel, "frames": 0, "state": "", "bytes": 0}
    with read_video(source, rel, cfg.recipe.reads, caches) as read:  # one bad file never stops the warm-up
        for _ in read.frames:  # the frames the sample pass reads, no more
            pass
    if read.error is not None:
        out["state"] = f"not stored: {type(read.error).__name__}: {read.error}"
    out["frames"] = read.window_pass.frames
    caches.take_stats()  # this video's counters are spent here: the pass says what became of its entry
    fp = read.frame_pass
    writer = fp.writer if fp is not None else None  # what became of the entry this pass wrote
    out["bytes"] = writer.stored_bytes if writer is not None else 0
    if out["state"]:
        return out
    if fp.cached and not fp.damaged:
        out["state"] = "cached"
    elif writer is not None and writer.outcome == "stored":
        out["state"] = "stored"
    elif writer is not None and writer.outcome in SKIP_CAUSES:
        out["state"] = f"not stored: {writer.outcome}"
    else:  # a damaged entry's rest decoded, an identity that cannot vouch, or another process's entry
        out["state"] = "not stored: already stored by another process"
    return out


def warm_cache(cfg: ServeConfig, source: VideoSource, caches: HostCaches, videos: List[str]) -> List[dict]:
    """:func:`warm_video` for every video, in ``cfg.workers`` processes (``source`` and
    ``caches`` themselves in this one, or built once in each of them from their ``spec()``).

    Raises:
        ValueError: the frame cache is off (``frame_cache_gb`` 0).
    """
    if caches.frame_cache is None:
        raise ValueError("--warm-cache needs a frame cache: give frame_cache_gb > 0 (and cache_dir)")
    return map_videos(warm_video, (cfg,), source, caches, videos, cfg.workers)


def cache_line(source: Optional[VideoSource], fc: FrameCache, cfg: Optional[ServeConfig] = None,
               videos: Sequence[str] = ()) -> str:
    """One line on the host's frame cache ``fc``: entries, bytes against the budget, folder;
    with ``source``, ``cfg`` and ``videos``, how many of those videos of ``source`` an epoch would
    cut from it (a stale or damaged entry found here is removed, as a worker would)."""
    nbytes, entries = fc.disk.usage()
    line = (f"frame cache {fc.disk.folder}: {entries} entr{'y' if entries == 1 else 'ies'}, "
            f"{nbytes / (1 << 30):.2f} of {fc.disk.max_bytes / (1 << 30):.2f} GiB ({fc.format})")
    if source is None or cfg is None or not videos:
        return line
    hits = 0
    settings = entry_settings(cfg.recipe.decode, cfg.recipe.windows)
    for rel in videos:
        try:
            entry = lookup_entry(fc, source, rel, settings)[2]
        except Exception:  # the file's verdict says why; it is not cached
            continue
        if entry is not None:
            hits += 1
            entry.close()
    st = fc.take_stats()["misses"]
    causes = ", ".join(f"{c} {n}" for c, n in st.items() if n)
    return line + f"; {hits} of {len(videos)} videos cached ({hits / len(videos):.0%})" + (
        f", misses: {causes}" if causes else "")


def format_warm(results: List[dict], fc: FrameCache) -> str:
    """A table: one line per video with what the warm-up did, then totals and :func:`cache_line`
    of the frame cache ``fc``."""
    lines = [f"{'file':<48} {'frames':>7}  state"]
    for r in results:
        lines.append(f"{r['path']:<48} {r['frames']:>7}  {r['state']}")
    n = {s: sum(1 for r in results if r["state"] == s) for s in ("stored", "cached")}
    rest = len(results) - n["stored"] - n["cached"]
    written = sum(r["bytes"] for r in results)
    lines.append(f"{n['stored']} stored ({written / (1 << 30):.2f} GiB), {n['cached']} already cached, {rest} not stored")
    lines.append(cache_line(None, fc))
    return "\n".join(lines)

"""What is known of a listing before any of its videos is opened, at a server's start: the videos
its video list counts too few frames for one window (:func:`short_entries`), and what the host's
corpus index learned of the rest (:func:`known_windows`)."""
from __future__ import annotations

from typing import Dict, List, NamedTuple, Optional, Sequence, Tuple

from v2v_server.frames.corpus_index import layout_key
from v2v_server.frames.frame_pass import DecodeSettings
from v2v_server.frames.host_caches import HostCaches
from v2v_server.frames.windows import WindowSettings
from v2v_server.sources.source import VideoSource
from v2v_server.sources.video_tables import ListedFrames


def short_entries(windows: WindowSettings, videos: Sequence[str], listed: ListedFrames
                  ) -> Tuple[List[str], List[Tuple[str, str]]]:
    """``(kept, refused)``: the ``videos`` whose video list counts enough frames for one window
    (``WindowSettings.holds_window`` of ``listed``, a table's numbers; a video it gives no count
    for is kept), in their order, and one ``(list, reason)`` naming those it drops, never opened.
    """
    short = [v for v in videos if v in listed.frames and not windows.holds_window(listed.frames[v])]
    if not short:
        return list(videos), []
    dropped = set(short)
    why = (f"{len(short)} row(s) of {listed.video_list} skipped without opening their video: their "
           f"{listed.counted} is below one window's {windows.frames_per_sample} frames (e.g. {', '.join(short[:3])})")
    return [v for v in videos if v not in dropped], [(listed.video_list, why)]


class KnownWindows(NamedTuple):
    """What the corpus index says of a listing at a server's start (:func:`known_windows`):
    ``known``, how many of its videos it knows; ``samples``, their samples per epoch together;
    ``empty``, those known to give no window -> ``(cause, reason)``, the verdict's reason and
    its code (``window_pass.judged``)."""

    known: int
    samples: int
    empty: Dict[str, Tuple[str, str]]


def known_windows(windows: WindowSettings, decode: DecodeSettings, source: VideoSource,
                  videos: Sequence[str], caches: Optional[HostCaches]) -> KnownWindows:
    """What the host's corpus index knows of ``videos`` under the layout of ``windows`` and
    ``decode`` (``corpus_index.layout_key``), each video's identity unchanged
    (``source.listed_identity``: a file's status, a store's listing, no request per object).
    The server reads it at start: an epoch's size when every video is known, and the videos not
    worth opening. Nothing is known without an index (``caches.corpus_index()``)."""
    index = caches.corpus_index() if caches is not None else None
    known, samples, empty = 0, 0, {}
    if index is None:
        return KnownWindows(0, 0, empty)
    for rel, n, cause, reason in index.windows(((rel, source.where(rel), source.listed_identity(rel))
                                                for rel in videos), layout_key(windows, decode)):
        known, samples = known + 1, samples + n
        if n == 0:
            empty[rel] = (cause, reason)
    if index.fault is not None:  # a fault on the way: nothing it answered is trusted
        return KnownWindows(0, 0, {})
    return KnownWindows(known, samples, empty)



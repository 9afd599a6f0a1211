"""What the host's corpus index knows of a listing before any of its videos is opened, at a
server's start (:func:`known_windows`): an epoch's size, and the videos not worth opening."""
from __future__ import annotations

from typing import Dict, NamedTuple, Optional, Sequence, Tuple

from v2v_server.frames.corpus_index import layout_key
from v2v_server.frames.frame_pass import DecodeSettings
from v2v_server.frames.host_caches import HostCaches
from v2v_server.frames.windows import WindowSettings
from v2v_server.sources.source import VideoSource


class KnownWindows(NamedTuple):
    """What the corpus index says of a listing at a server's start (:func:`known_windows`):
    ``known``, how many of its videos it knows; ``samples``, their samples per epoch together;
    ``empty``, those known to give no window -> ``(cause, reason)``, the verdict's reason and
    its code (``window_pass.judged``); ``windows``, each known video's windows."""

    known: int
    samples: int
    empty: Dict[str, Tuple[str, str]]
    windows: Dict[str, int] = {}


def known_windows(windows: WindowSettings, decode: DecodeSettings, source: VideoSource,
                  videos: Sequence[str], caches: Optional[HostCaches]) -> KnownWindows:
    """What the host's corpus index knows of ``videos`` under the layout of ``windows`` and
    ``decode`` (``corpus_index.layout_key``), each video's identity unchanged
    (``source.listed_identity``: a file's status, a store's listing, no request per object).
    The server reads it at start: an epoch's size when every video is known, and the videos not
    worth opening. Nothing is known without an index (``caches.corpus_index()``)."""
    index = caches.corpus_index() if caches is not None else None
    known, samples, empty, counts = 0, 0, {}, {}
    if index is None:
        return KnownWindows(0, 0, empty)
    for rel, n, cause, reason in index.windows(((rel, source.where(rel), source.listed_identity(rel))
                                                for rel in videos), layout_key(windows, decode)):
        known, samples = known + 1, samples + n
        counts[rel] = n
        if n == 0:
            empty[rel] = (cause, reason)
    if index.fault is not None:  # a fault on the way: nothing it answered is trusted
        return KnownWindows(0, 0, {})
    return KnownWindows(known, samples, empty, counts)



"""Sample ids: the one place their format is written and read.

An id is the video's path relative to the corpus root (POSIX), ``#``, the window index and,
when a window gives K > 1 crops (``crops_per_window``), ``.`` and the crop index:
``clips/a.mp4#3`` or ``clips/a.mp4#3.1``. The integer *index* ``window * K + crop`` numbers a
video's samples; the scheduler, the resume states and the workers' skip lists use it.
Pure: no I/O, no numpy.
"""
from __future__ import annotations

from typing import Dict, Iterable, Iterator, List, Tuple


def make_sample_id(rel_path: str, window: int, crop: int = 0, crops_per_window: int = 1) -> str:
    """Stable sample id: the video's path relative to the corpus root (POSIX), ``#``, the
    window index and, when ``crops_per_window`` > 1, ``.`` and the crop index:
    ``clips/a.mp4#3`` (one crop per window: the ids of a run without crops) or
    ``clips/a.mp4#3.1``. The inverse is :func:`parse_sample_id`."""
    if crops_per_window == 1:
        return f"{rel_path}#{window}"
    return f"{rel_path}#{window}.{crop}"


def parse_sample_id(sample_id: str, crops_per_window: int = 1) -> Tuple[str, int]:
    """``(rel_path, index)`` of a sample id made by :func:`make_sample_id`: ``index =
    window * crops_per_window + crop`` is the integer that numbers a video's samples (what
    the server tracks as received, skipped or already delivered).

    Raises:
        ValueError: for an id that is not ``path#window`` (K = 1) or ``path#window.crop``
            (K > 1, crop < K), naming the id.
    """
    if not isinstance(sample_id, str) or len(sample_id) > 4096:
        raise ValueError(f"sample id must be a string of at most 4096 characters, got {sample_id!r:.80}")
    video, sep, tail = sample_id.rpartition("#")
    window, dot, crop = tail.partition(".")
    ok = bool(sep and video and window.isdigit() and window.isascii() and len(window) <= 9 and len(crop) <= 9)
    if crops_per_window == 1:
        ok = ok and not dot
        c = 0
    else:
        ok = ok and bool(dot) and crop.isdigit() and crop.isascii() and int(crop) < crops_per_window
        c = int(crop) if ok else 0
    if not ok:
        form = "path#window" if crops_per_window == 1 else f"path#window.crop (crop < {crops_per_window})"
        raise ValueError(f"sample id {sample_id!r} is not of the form {form}")
    return video, int(window) * crops_per_window + c


def compact_ids(sample_ids: Iterable[str]) -> str:
    """Sample ids as one string, one video per line: ``path#3,4,7`` (``path#3.0,3.1`` with
    crops), sorted. What a resume hello carries: the path is written once per video, so a
    trainer's millions of ids fit in a message. The inverse is :func:`expand_ids`."""
    by_video: Dict[str, List[str]] = {}
    for sid in sample_ids:
        video, _, tail = sid.rpartition("#")
        by_video.setdefault(video, []).append(tail)
    return "\n".join(f"{v}#{','.join(sorted(t, key=_tail_key))}" for v, t in sorted(by_video.items()))


def _tail_key(tail: str):
    w, _, c = tail.partition(".")
    return (int(w) if w.isdigit() else -1, int(c) if c.isdigit() else -1, tail)


def expand_ids(text: str) -> Iterator[str]:
    """The sample ids of :func:`compact_ids` output (one plain id per line is read as is).
    The part after a line's last ``#`` never holds a comma, so paths may."""
    for line in text.split("\n"):
        video, sep, tails = line.rpartition("#")
        if not sep:
            yield line
            continue
        for tail in tails.split(","):
            yield f"{video}#{tail}"

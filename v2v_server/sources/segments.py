"""Segments: a clip given as a time range of a longer video.

Corpora such as Panda-70M, InternVid or Kinetics give their clips as ``video, [start, end]``
rather than as files. A video list line ``path start end`` (seconds, or ``H:MM:SS.sss``) names
the segment ``path#t=start,end`` (the temporal fragment of the W3C Media Fragments URI 1.0
syntax), which the corpus lists as an entry of its own: it is sharded, cached and numbered like
a file, and its sample ids are ``path#t=start,end#window``. A pass over it seeks to the key frame
before ``start`` and keeps the frames whose presentation time lies in ``[start, end)``
(``decode.decode_codes``), so a segment an hour into a video costs what a short file costs.
Pure: no I/O.
"""
from __future__ import annotations

import math
import posixpath
import re
from typing import Optional, Tuple

#: What separates a video's path from its time range in an entry name.
FRAGMENT = "#t="
#: A time: seconds as a decimal (``12.5``), or a clock ``[H:]MM:SS[.fff]`` whose minutes and
#: seconds are below 60 (the npt times of W3C Media Fragments 1.0, which FFmpeg's duration syntax
#: shares); a sign is read so that a negative range is named as such (``range_problem``).
_SECONDS = re.compile(r"-?(?:\d+(?:\.\d*)?|\.\d+)", re.ASCII)
_CLOCK = re.compile(r"(-?)(?:(\d+):)?(\d{1,2}):(\d{2}(?:\.\d*)?)", re.ASCII)
#: What a time's syntax is, for messages.
TIME_SYNTAX = "seconds such as 12.5, or a clock time H:MM:SS.sss"
#: How a segment is named, for a message about a name that holds ``#t=`` but is none.
RANGE_FORM = f"a time range is written path#t=start,end ({TIME_SYNTAX}), or as a list line `path start end`"


def parse_time(text: str) -> float:
    """Seconds from ``text``: a decimal number (``12.5``, ``-3``) or a clock time (``0:01:02.5``,
    ``01:02.5``) whose minute and second fields are below 60. Exponents, ``nan``, ``inf``,
    digit separators and surrounding blanks are not times.

    Raises:
        ValueError: anything else (``'0:00:99'``, ``'1e3'``, ``'nan'``), naming ``text``.
    """
    if _SECONDS.fullmatch(text):
        t = float(text)
        if math.isfinite(t):
            return t
    m = _CLOCK.fullmatch(text)
    if m:
        sign, h, mnt, sec = m.groups()
        if int(mnt) < 60 and float(sec) < 60:
            try:
                t = float(int(h or 0) * 3600 + int(mnt) * 60) + float(sec)
            except OverflowError:  # hours beyond a float
                t = math.inf
            if math.isfinite(t):
                return -t if sign else t
            raise ValueError(f"time {text!r} is not finite")
        raise ValueError(f"time {text!r}: a clock time's minutes and seconds are below 60")
    raise ValueError(f"time {text!r} is not a time ({TIME_SYNTAX})")


def _seconds(t: float) -> str:
    """``t`` in seconds to the millisecond, without trailing zeros: ``12.5``, ``20``."""
    s = f"{t:.3f}".rstrip("0").rstrip(".")
    return "0" if s in ("", "-0") else s


def clean_path(rel: str) -> str:
    """A listed path as a sample-id path: a leading ``/`` dropped and the path folded as POSIX
    ``normpath`` folds it (``./``, ``//``, ``dir/..``), so that one file has one id however a
    list spells it (``clip.mp4``, ``./clip.mp4``, ``sub/../clip.mp4``) and ids match a
    folder's listing. A path that leaves the root keeps its leading ``..``
    (:func:`path_problem` names it); an empty path stays empty."""
    rel = rel.lstrip("/")
    if "//" in rel or "/." in rel or rel.startswith(".") or rel.endswith("/"):  # else normpath keeps it
        rel = posixpath.normpath(rel)
    return "" if rel == "." else rel


def path_problem(rel: str) -> Optional[str]:
    """Why the cleaned listed path ``rel`` (:func:`clean_path`) can name no file of the corpus,
    or None: it holds a NUL byte (no file system allows one), or it leaves the corpus root."""
    if "\0" in rel:
        return "holds a NUL byte, which no file name can"
    if rel == ".." or rel.startswith("../"):
        return "leaves the corpus root (a listed path is relative to it)"
    return None


#: Characters a message shows escaped: control characters, which would break or forge a log line.
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


def printable_name(rel: str) -> str:
    """``rel`` for a message or a report: control characters (a NUL byte, a newline) escaped as
    ``\\x00``, ``\\n``..."""
    return _CONTROL.sub(lambda m: m.group().encode("unicode_escape").decode(), rel)


def segment_name(path: str, start: float, end: float) -> str:
    """The entry name of the segment ``[start, end)`` seconds of ``path``: ``path#t=start,end``."""
    return f"{path}{FRAGMENT}{_seconds(start)},{_seconds(end)}"


def split_segment(rel: str) -> Tuple[str, Optional[Tuple[float, float]]]:
    """``(path, (start, end))`` of a segment's entry name, ``(rel, None)`` for a whole video.

    An entry is a segment only when it ends in ``#t=start,end`` with two times
    (:func:`parse_time`): any other name is a file's own name, read as it is. A file named
    ``clip#t=1,2.mp4`` (its name ends in ``.mp4``, not in a time) is that file, in a folder, a
    bucket, an archive or a list alike; no video name ends in a time, so the two never meet.
    """
    path, sep, times = rel.rpartition(FRAGMENT)
    if not sep:
        return rel, None
    start, comma, end = times.partition(",")
    try:
        return (path, (parse_time(start), parse_time(end))) if comma else (rel, None)
    except ValueError:
        return rel, None


def looks_like_segment(rel: str) -> bool:
    """Whether ``rel`` holds the segment fragment ``#t=`` without being a segment (its range
    does not parse): a message about it then says how a range is written."""
    return FRAGMENT in rel and split_segment(rel)[1] is None


def base_path(rel: str) -> str:
    """The video file an entry reads: ``rel`` without its time range (:func:`split_segment`)."""
    return split_segment(rel)[0]


def range_problem(start: float, end: float) -> Optional[str]:
    """Why ``[start, end)`` seconds names no frame, or None: empty, reversed or negative."""
    if start < 0:
        return f"time range {_seconds(start)}-{_seconds(end)} s starts before the video"
    if end < start:
        return f"time range {_seconds(start)}-{_seconds(end)} s is reversed"
    if end == start:
        return f"time range {_seconds(start)}-{_seconds(end)} s is empty"
    return None

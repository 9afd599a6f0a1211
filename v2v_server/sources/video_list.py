"""Video lists: a file of the V2V authors' format, or a metadata table (``sources.video_tables``),
that selects and orders the videos of a corpus (a local file, or an object beside the corpus in
the store), read by every ``VideoSource``.

A line is ``path``, ``path start end`` (a segment, ``sources.segments``) or the authors'
``path frames [a b]``: the path is everything before the trailing numbers, so it may hold
spaces (``my clip.mp4 0 12``). A trailing field that looks like a number (digits, ``nan``,
``inf``, ``1e309``, ``0:00:99``) is read strictly: a line whose numbers do not parse is refused
and named, never served as a whole video.
"""
from __future__ import annotations

import codecs
import re
from pathlib import Path
from typing import List, NamedTuple, Optional, Tuple

from v2v_server.sources.names import is_url
from v2v_server.sources.segments import clean_path, parse_time, path_problem, printable_name, segment_name
from v2v_server.sources.video_tables import TableSettings, read_table, table_format

#: A field that is meant as a number: what a list line's trailing fields are told apart by.
_NUMBERISH = re.compile(r"[-+]?(?:nan|inf(?:inity)?|[\d.:_eE+-]*\d[\d.:_eE+-]*)", re.IGNORECASE)
#: A number of the authors' lines (a frame count, a score).
_DECIMAL = re.compile(r"\d+(?:\.\d+)?", re.ASCII)
#: The line forms, for messages.
LINE_FORMS = "a line is `path`, `path start end` or `path frames [a b]`"


class VideoList(NamedTuple):
    """What a video list gives: ``videos``, the entry names in the list's order, duplicates
    dropped; ``refused``, ``(path, reason)`` for each line or row not served, each once (the
    reason names the list and the line)."""

    videos: List[str]
    refused: List[Tuple[str, str]]


def _read_bytes(path: str) -> bytes:
    """The bytes of the list file at ``path``, a local path or a URL.

    Raises:
        FileNotFoundError: no file at ``path``, naming it.
        ValueError: it cannot be read (the system's reason), naming it.
    """
    if is_url(path):  # a list kept beside the corpus in the store
        import fsspec

        with fsspec.open(path, "rb") as f:
            return f.read()
    try:
        return Path(path).read_bytes()
    except FileNotFoundError:
        raise FileNotFoundError(f"video_list {path}: no such file") from None
    except OSError as e:
        raise ValueError(f"video_list {path}: cannot be read: {e.strerror or e}") from None


def _lines(data: bytes):
    """``(number, text, bad)`` of each line of a list file's bytes (split at ``\\n``, ``\\r``
    and ``\\r\\n`` only: a name may hold U+2028), counted from 1; ``text`` is None for a line
    that is not UTF-8, ``bad`` then its first undecodable bytes, escaped (``\\xe9``)."""
    for n, raw in enumerate(data.removeprefix(codecs.BOM_UTF8).splitlines(), 1):
        try:
            yield n, raw.decode("utf-8"), ""
        except UnicodeDecodeError as e:
            yield n, None, raw[e.start:e.end].decode("latin-1").encode("unicode_escape").decode()


class LineError(ValueError):
    """A list line that is refused: ``path`` is what it names (the line itself when it names
    no path), the message why."""

    def __init__(self, path: str, why: str):
        super().__init__(why)
        self.path = path


def parse_line(line: str) -> str:
    """The entry one list line (not blank, not a comment) names: its path, or the segment
    ``path#t=start,end`` of a ``path start end`` line. The path is everything before the
    trailing fields that look like numbers (``_NUMBERISH``), so it may hold spaces.

    Raises:
        LineError: the path leaves the corpus root or holds a NUL byte
            (``segments.path_problem``); the trailing numbers do not parse (a time that is not one, ``nan``, an
            authors' field that is not a number) or are more than 3; the message names the field.
    """
    parts = line.split()
    k = 0
    while k < len(parts) - 1 and _NUMBERISH.fullmatch(parts[-1 - k]):
        k += 1
    fields = parts[len(parts) - k:] if k else []
    path = clean_path(line.rsplit(None, k)[0] if k else line)
    if not path:
        raise LineError(printable_name(line), "names no path")
    problem = path_problem(path)
    if problem:
        raise LineError(printable_name(path), f"the path {problem}")
    if len(fields) == 2:
        try:
            return segment_name(path, parse_time(fields[0]), parse_time(fields[1]))
        except ValueError as e:
            raise LineError(path, str(e)) from None
    if len(fields) > 3:
        raise LineError(path, f"{len(fields)} numbers after the path ({LINE_FORMS})")
    bad = [f for f in fields if not _DECIMAL.fullmatch(f)]
    if bad:
        raise LineError(path, f"{bad[0]!r} is not a number ({LINE_FORMS})")
    return path


def read_video_list(path: str, table: Optional[TableSettings] = None) -> VideoList:
    """The videos a list file names, in its order, duplicates dropped, and the lines refused.
    A table (``.csv``, ``.tsv``, ``.jsonl``, ``.json``, ``.parquet``) is read by
    ``video_tables.read_table`` with ``table`` (default ``TableSettings()``).

    The V2V authors' format (HYLZ-2019/V2V ``config/webvid10000_unfiltered.txt``): one video per
    line, its path relative to the corpus root, then the authors' numbers (a frame count and two
    scores, ignored); ``#`` starts a comment line; blank lines are skipped. A line ``path start
    end`` whose numbers are times (seconds, or ``H:MM:SS.sss``: Panda-70M's clip timestamps,
    ``segments.parse_time``) names the segment ``path#t=start,end``; a video may have several.
    The path is everything before the trailing numbers (:func:`parse_line`), folded
    (``segments.clean_path``: ``sub/../clip.mp4`` is ``clip.mp4``, served once). A line whose
    numbers do not parse, whose path leaves the corpus root or holds a NUL byte, or that is not
    UTF-8 is refused with its line number and the rest is served; the same line again is not
    named again. A UTF-8 byte order mark is skipped.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: naming the file: it is a folder or cannot be read, or it lists nothing and
            refuses nothing; for a table,
            naming the setting too (``video_tables.read_table``).
    """
    if not is_url(path) and Path(path).is_dir():
        raise ValueError(f"video_list {path}: is a folder, not a list file")
    if table_format(path):
        table = table or TableSettings()
        out, refused = read_table(path, table)
        if not out and not refused:
            raise ValueError(f"video_list {path}: lists no video"
                             + (f" (no row passes video_list_filter {table.filter!r})" if table.filter else ""))
        return VideoList(out, refused)
    out, seen, refused, named = [], set(), [], set()
    for n, s, bad in _lines(_read_bytes(path)):
        if s is None:  # sample ids are UTF-8: this line names no id; the rest is served
            refused.append((f"(line {n})", f"listed in {path} line {n}: not UTF-8 (bytes {bad}): "
                                           f"save the list as UTF-8"))
            continue
        s = s.strip()
        if not s or s.startswith("#"):
            continue
        try:
            rel = parse_line(s)
        except LineError as e:
            if s not in named:
                named.add(s)
                refused.append((e.path, f"listed in {path} line {n}: {e}"))
            continue
        if rel not in seen:
            seen.add(rel)
            out.append(rel)
    if not out and not refused:
        raise ValueError(f"video_list {path}: lists no video")
    return VideoList(out, refused)

"""What a video and a corpus are called: which names can be sample ids, how a name is written in a
log line, and whether a corpus or a list is given as a URL.

A sample id's path is a video's name as the corpus gives it (a file's path relative to the folder,
a key relative to the prefix, an archive member's ``archive/member`` path); these rules say which
names can be one (valid UTF-8, no control character) and how a name is written in a log line.
"""
from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Optional, Union


def inside(root: Path, path: Path) -> bool:
    """True when ``path`` resolves (symlinks followed) to a file under ``root``."""
    try:
        return path.resolve(strict=True).is_relative_to(Path(root).resolve(strict=True))
    except (OSError, RuntimeError):
        return False


def utf8_name(path: Path) -> bool:
    """Whether ``path`` (as the file system gave it) is valid UTF-8: Python keeps other bytes
    as lone surrogates, which cannot be encoded into a sample id."""
    try:
        str(path).encode("utf-8")
        return True
    except UnicodeEncodeError:
        return False


def printable(path: Path) -> str:
    """``path`` for a log line or a report: bytes that are not UTF-8 escaped (``\\xff``), and
    control characters (``\\n``, ``\\t``...) written as escapes, so that one name is one line."""
    text = os.fsencode(str(path)).decode("utf-8", "backslashreplace")
    return "".join(repr(c)[1:-1] if _CONTROL.match(c) else c for c in text)


#: Control characters (C0, DEL, C1): in a name they would end a log line or a report's line.
_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f]")


def name_problem(name: str, what: str = "file name") -> Optional[str]:
    """Why ``name`` (a file's path as the file system gave it, a key: ``what``) cannot be a
    sample id's path, or None: it is not valid UTF-8 (:func:`utf8_name`), or it holds a
    control character (:func:`control_character`)."""
    if not utf8_name(name):
        return f"{what} is not valid UTF-8 (sample ids are UTF-8): rename it"
    return control_character(name)


def control_character(name: str) -> Optional[str]:
    """Why ``name`` (a file, key or archive member path) cannot be a sample id's path: the
    first control character it holds (a newline, a tab...), escaped, with the reason; None
    when it holds none. Sample ids are written one per line in logs and reports (``--check``'s
    table, the server's log)."""
    m = _CONTROL.search(name)
    if m is None:
        return None
    return (f"name holds the control character {repr(m.group())[1:-1]!s} (sample ids travel one per line): "
            f"rename it")


def is_url(videos: Union[str, Path, None]) -> bool:
    """The one rule for whether a corpus, a list or a table is given as a URL (``s3://``,
    ``gs://``, ``https://``...: read through fsspec) or as a local path (``file://`` URLs
    included: they are local)."""
    return isinstance(videos, str) and "://" in videos and not videos.startswith("file://")


def name_suffix(name: str) -> str:
    """The extension of a file name as ``Path.suffix`` gives it: from its last dot, with the
    dot; ``''`` for none, for a name that only starts with a dot, and for a trailing dot."""
    i = name.rfind(".")
    return name[i:] if 0 < i < len(name) - 1 else ""

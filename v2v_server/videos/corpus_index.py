"""The corpus index: what a pass over a video learned (frames, frame rate, codec, resolution, shot
cuts, windows, verdict), kept on the host's disk so that later passes, later jobs and the Ray
engine's scan answer from it instead of decoding the video again.

One SQLite file, ``cache_dir/corpus_index.sqlite`` (``default_cache_dir()`` when no ``cache_dir``
is given), one row per (video, window layout): the ``sqlite3`` shell, DuckDB
(``SELECT * FROM sqlite_scan('corpus_index.sqlite', 'entries')``) and pandas read it. Several
processes of a host read and write it at once (WAL journal, a busy timeout).

An entry is reused while the video's identity holds (``VideoSource.identity``: size, mtime,
ctime and inode of a file; an object's ETag; a tar or zip member's shard identity with its
offset and size), the frame cache's rule: a video rewritten in place gets a new identity, and a
video whose identity cannot vouch for its content (changed within the file system's timestamp
resolution of now, an object without a version tag) is neither stored nor answered from the
index. The window layout is :func:`layout_key`: every setting that moves a window or changes a
verdict (``frames.entry_settings``, ``shot_cuts``), so one video has one entry per layout it was
read under.
"""
from __future__ import annotations

import hashlib
import json
import re
import sqlite3
import time
from pathlib import Path
from typing import Dict, Iterable, Iterator, Optional, Tuple, Union

from v2v_server.videos.frames import DecodeSettings, entry_settings
from v2v_server.videos.manifest import default_cache_dir
from v2v_server.videos.shots import DETECTOR_VERSION
from v2v_server.videos.windows import WindowSettings

#: The index's file name under the cache folder.
INDEX_FILE = "corpus_index.sqlite"

#: Format of the rows; an index of another version is set aside and written anew.
INDEX_VERSION = 1

_SCHEMA = """
CREATE TABLE IF NOT EXISTS entries (
    location TEXT NOT NULL,      -- where the video lives (VideoSource.where: a path or URL, a member, a segment)
    layout TEXT NOT NULL,        -- layout_key(windows, decode)
    identity TEXT NOT NULL,      -- VideoSource.identity when the entry was written
    frames INTEGER NOT NULL,     -- frames read (decoding stops once the last window is complete)
    windows INTEGER NOT NULL,    -- samples per epoch (windows that can be made)
    usable INTEGER NOT NULL,     -- 1 when the video gives a window
    reason TEXT NOT NULL,        -- why it gives none or fewer ('' when nothing is wrong)
    cuts TEXT NOT NULL,          -- JSON list: the frames that start a shot
    width INTEGER, height INTEGER, codec TEXT, fps REAL,
    result TEXT NOT NULL,        -- JSON: the whole --check verdict (videos.corpus.check_video)
    written_at REAL NOT NULL,    -- Unix time, seconds
    PRIMARY KEY (location, layout)
);
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
"""

#: ``check_video``'s ``size`` field: ``"WxH codec pix_fmt FPS fps"``.
_SIZE = re.compile(r"^(\d+)x(\d+) (\S+) \S+ ([0-9.e+-]+) fps$")


def layout_key(windows: WindowSettings, decode: DecodeSettings) -> str:
    """The window layout of an index entry: a short hash (16 hex digits) of the settings that
    move a window or change a verdict (the frames a pass reads, ``frames.entry_settings``, and
    ``windows.shot_cuts``), and the shot detector (an entry holds the cuts it found, whatever
    ``shot_cuts`` is)."""
    settings = {**entry_settings(decode, windows), "shot_cuts": windows.shot_cuts, "shots": DETECTOR_VERSION}
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]


def index_path(cache_dir: Optional[Union[str, Path]]) -> Path:
    """Where the index of a host lives: ``cache_dir/corpus_index.sqlite``, under
    ``default_cache_dir()`` when ``cache_dir`` is None."""
    return Path(cache_dir or default_cache_dir()) / INDEX_FILE


class CorpusIndex:
    """The corpus index file at ``path`` (made, with its folder, when missing).

    Args:
        path: the SQLite file (:func:`index_path`).
        timeout_s: how long a write waits for another process's write to finish.

    Raises:
        OSError: the folder cannot be made.
        sqlite3.DatabaseError: ``path`` is not an SQLite file (naming it).
    """

    def __init__(self, path: Union[str, Path], timeout_s: float = 30.0):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._db = sqlite3.connect(str(self.path), timeout=timeout_s, isolation_level=None,
                                       check_same_thread=False)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.executescript(_SCHEMA)
            row = self._db.execute("SELECT value FROM meta WHERE key = 'version'").fetchone()
            if row is None:
                self._db.execute("INSERT OR IGNORE INTO meta VALUES ('version', ?)", (str(INDEX_VERSION),))
            elif row[0] != str(INDEX_VERSION):  # written by another format: start afresh
                self._db.execute("DELETE FROM entries")
                self._db.execute("UPDATE meta SET value = ? WHERE key = 'version'", (str(INDEX_VERSION),))
        except sqlite3.DatabaseError as e:
            raise sqlite3.DatabaseError(f"corpus index {self.path}: {e}") from None

    def lookup(self, location: str, identity: Optional[str], layout: str) -> Optional[dict]:
        """The ``--check`` verdict (``videos.corpus.check_video``'s dict) recorded for the video
        at ``location`` under ``layout``, or None: no entry, an entry of another identity (the
        video changed), or ``identity`` None (it cannot vouch for the content)."""
        if identity is None:
            return None
        row = self._db.execute("SELECT identity, result FROM entries WHERE location = ? AND layout = ?",
                               (location, layout)).fetchone()
        if row is None or row[0] != identity:
            return None
        return json.loads(row[1])

    def windows(self, videos: Iterable[Tuple[str, str, Optional[str]]], layout: str,
                chunk: int = 500) -> Iterator[Tuple[str, int, str]]:
        """``(key, windows, reason)``, the samples per epoch and the reason recorded under
        ``layout`` (why it gives none or fewer, '' when nothing is wrong), for each ``(key,
        location, identity)`` of ``videos`` whose entry holds (same identity; None never does),
        read in queries of ``chunk`` locations: memory is bounded by the chunk, not the corpus.
        Nothing is queried when no entry of ``layout`` exists."""
        if self._db.execute("SELECT 1 FROM entries WHERE layout = ? LIMIT 1", (layout,)).fetchone() is None:
            return
        batch: Dict[str, Tuple[str, str]] = {}  # location -> (key, identity)

        def flush():
            marks = ",".join("?" * len(batch))
            rows = self._db.execute(f"SELECT location, identity, windows, reason FROM entries WHERE layout = ? AND "
                                    f"location IN ({marks})", (layout, *batch)).fetchall()
            held = dict(batch)
            batch.clear()
            for loc, ident, n, reason in rows:
                if held[loc][1] == ident:
                    yield held[loc][0], int(n), reason

        for key, location, identity in videos:
            if identity is not None:
                batch[location] = (key, identity)
                if len(batch) >= chunk:
                    yield from flush()
        if batch:
            yield from flush()

    def record(self, location: str, identity: Optional[str], layout: str, result: dict) -> bool:
        """Keep ``result`` (a ``check_video`` verdict) for the video at ``location`` of
        ``identity`` under ``layout``, replacing an older entry; nothing is kept when
        ``identity`` is None. Returns whether it was kept."""
        if identity is None:
            return False
        m = _SIZE.match(result.get("size") or "")
        w, h, codec, fps = (int(m[1]), int(m[2]), m[3], float(m[4])) if m else (None, None, None, None)
        self._db.execute(
            "INSERT OR REPLACE INTO entries VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
            (location, layout, identity, int(result.get("frames", 0)), int(result.get("windows", 0)),
             int(bool(result.get("usable"))), result.get("reason") or "", json.dumps(list(result.get("cuts") or [])),
             w, h, codec, fps, json.dumps(result), time.time()))
        return True

    def __len__(self) -> int:
        return self._db.execute("SELECT COUNT(*) FROM entries").fetchone()[0]

    def close(self) -> None:
        self._db.close()

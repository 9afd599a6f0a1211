"""The corpus index: what a pass over a video learned (frames, frame rate, codec, resolution, shot
cuts, windows, verdict), kept on the host's disk so that later passes, later jobs and the Ray
engine's scan answer from it instead of decoding the video again.

One SQLite file, ``cache_dir/corpus_index.sqlite`` (the resolved cache folder,
``disk_cache.cache_folder``), one row per (video, window layout): the ``sqlite3`` shell, DuckDB
(``SELECT * FROM sqlite_scan('corpus_index.sqlite', 'entries')``) and pandas read it. Several
processes of a host read and write it at once (WAL journal, a busy timeout).

An entry is reused while the video's identity holds (``VideoSource.identity``: size, mtime,
ctime and inode of a file; an object's ETag; a tar or zip member's shard identity with its
offset and size), the frame cache's rule: a video rewritten in place gets a new identity, and a
video whose identity cannot vouch for its content (changed within the file system's timestamp
resolution of now, an object without a version tag) is neither stored nor answered from the
index. The window layout is :func:`layout_key`, the key of what a pass reads
(``pass_record.PassRecord``): every setting that moves a window or changes a verdict, so one
video has one entry per layout it was read under. A server serving by plan keeps each video's
packet count's bound here too, under ``frames.check.PACKETS_LAYOUT`` and the sample pass's key.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import sqlite3
import time
from pathlib import Path
from typing import Callable, Dict, Iterable, Iterator, Optional, Tuple, Union

from v2v_server.faults import warn_once
from v2v_server.frames.frame_pass import DecodeSettings
from v2v_server.frames.pass_record import PassRecord
from v2v_server.frames.window_pass import StreamFacts
from v2v_server.frames.windows import WindowSettings
from v2v_wire.worker_messages import CAUSES

#: The index's file name under the cache folder.
INDEX_FILE = "corpus_index.sqlite"

#: Format of the rows and of their layout keys (``layout_key``); the rows of an index of another
#: version, or whose table has other columns, are deleted at open (the table made anew), and the
#: index written anew.
INDEX_VERSION = 3

#: Seconds a read or write waits for another process's write: a write is one row (milliseconds),
#: so a lock held longer is another program's (a ``sqlite3`` shell in a transaction), and the
#: index is left off rather than every pass waiting on it.
BUSY_TIMEOUT_S = 5.0

log = logging.getLogger("v2v")

_ENTRIES = """
CREATE TABLE IF NOT EXISTS entries (
    location TEXT NOT NULL,      -- where the video lives (VideoSource.where: a path or URL, a member, a segment)
    layout TEXT NOT NULL,        -- layout_key(windows, decode)
    identity TEXT NOT NULL,      -- VideoSource.identity when the entry was written
    frames INTEGER NOT NULL,     -- frames read (decoding stops once the last window is complete)
    windows INTEGER NOT NULL,    -- samples per epoch (windows that can be made)
    usable INTEGER NOT NULL,     -- 1 when the video gives a window
    reason TEXT NOT NULL,        -- why it gives none or fewer ('' when nothing is wrong)
    cause TEXT NOT NULL,         -- that reason as a code (v2v_wire.worker_messages.CAUSES: short, static, ...)
    cuts TEXT NOT NULL,          -- JSON list: the frames that start a shot
    width INTEGER, height INTEGER, codec TEXT,
    fps REAL,                    -- frames per second as the container gives it (29.97002997..., not rounded)
    result TEXT NOT NULL,        -- JSON: the whole --check verdict (Verdict.to_json)
    written_at REAL NOT NULL,    -- Unix time, seconds
    PRIMARY KEY (location, layout)
)"""
_SCHEMA = _ENTRIES + """;
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
"""


def _columns(db: sqlite3.Connection) -> list:
    """The names of the ``entries`` table's columns in ``db``, in order."""
    return [r[1] for r in db.execute("PRAGMA table_info(entries)")]


def _schema_columns() -> list:
    """The columns :data:`_ENTRIES` makes (the schema is their one owner)."""
    db = sqlite3.connect(":memory:")
    try:
        db.execute(_ENTRIES)
        return _columns(db)
    finally:
        db.close()


@dataclasses.dataclass(frozen=True, kw_only=True)
class Verdict:
    """What ``v2v-serve --check`` says of one video (``check.check_video``), as the corpus
    index keeps it.

    Attributes:
        path: the video's id in its corpus (``shard.tar/a.mp4``, ``a.mp4#t=1,2``).
        usable: it gives a window.
        windows: samples per epoch (windows that can be made).
        frames: frames read (decoding stops once the last window is complete: see ``more``).
        reason: why it gives none or fewer ('' when nothing is wrong; failed windows named).
        cause: that reason as a code (``v2v_wire.worker_messages.CAUSES``; '' when none).
        cuts: the frames that start a shot, found whatever ``shot_cuts`` says.
        dropped: windows a cut removed.
        stream: the stream's facts (``window_pass.StreamFacts``), None when it was not opened.
        failed_windows: the windows that cannot be made (a frame of another size inside).
        static: windows given up as static (``static_windows: skip``).
        more: every window is complete: decoding stopped, the video may hold more frames.
        variable_rate: the frames read are unevenly spaced in time: what ``--check`` says of
            it ('' when they are even, or when the pass did not time frames).
        frame_timing: the pass timed frames (``--check``'s); a sample pass's entry does not,
            and ``--check`` decodes the video again for its own line.
    """

    path: str
    usable: bool
    windows: int
    frames: int
    reason: str
    cause: str
    cuts: Tuple[int, ...]
    dropped: int
    stream: Optional[StreamFacts]
    failed_windows: Tuple[int, ...] = ()
    static: int = 0
    more: bool = False
    variable_rate: str = ""
    frame_timing: bool = True

    def to_json(self) -> dict:
        """The verdict as JSON-safe values (the index's ``result`` column): every field, ``stream``
        as an object of its fields or null."""
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, location: str, value) -> "Verdict":
        """The verdict :meth:`to_json` wrote, for the entry of ``location`` (for messages);
        keys it does not name are left aside.

        Raises:
            ValueError: a field is missing or of another type (naming the entry and the field)."""
        if not isinstance(value, dict):
            raise ValueError(f"the entry of {location} holds a result that is not a verdict")
        got = {}
        optional = {f.name for f in dataclasses.fields(cls) if f.default is not dataclasses.MISSING}
        for name, kind in _VERDICT.items():
            if name not in value and name in optional:
                continue
            v = value.get(name)
            if name == "stream":
                got[name] = None if v is None else _stream(location, v)
            elif kind is tuple:
                if not isinstance(v, list) or not all(_count(n) for n in v):
                    raise ValueError(f"the entry of {location} holds {name} {v!r} in its result")
                got[name] = tuple(v)
            elif not isinstance(v, kind) or (kind is int and not _count(v)):
                raise ValueError(f"the entry of {location} holds {name} {v!r} in its result")
            else:
                got[name] = v
        return cls(**got)


def _count(v) -> bool:
    """Whether ``v`` is a non-negative int (a bool is not)."""
    return type(v) is int and v >= 0


def _stream(location: str, v) -> StreamFacts:
    """A verdict's ``stream`` object as :class:`StreamFacts`.

    Raises:
        ValueError: a field is missing or of another type (naming the entry)."""
    ok = (isinstance(v, dict) and all(_count(v.get(k)) for k in ("width", "height"))
          and all(isinstance(v.get(k), str) for k in ("codec", "pix_fmt"))
          and type(v.get("fps")) in (int, float))
    if not ok:
        raise ValueError(f"the entry of {location} holds stream {v!r} in its result")
    return StreamFacts(width=v["width"], height=v["height"], codec=v["codec"], pix_fmt=v["pix_fmt"],
                       fps=float(v["fps"]))


def layout_key(windows: WindowSettings, decode: DecodeSettings) -> str:
    """The window layout of an index entry: the key of what ``--check``'s pass decoding as
    ``decode`` over ``windows`` reads (``pass_record.PassRecord.key``, shot cuts scored whatever
    ``shot_cuts`` says: an entry holds them), so every setting that moves a window or changes a
    verdict is in it once."""
    return check_record(windows, decode).key


def check_record(windows: WindowSettings, decode: DecodeSettings) -> PassRecord:
    """What ``--check``'s pass over ``windows`` decoding as ``decode`` reads: the sample pass's
    record, shot cuts scored whatever ``shot_cuts`` says (``check.check_video`` reports them)."""
    return PassRecord.of(decode, windows, scores_cuts=True)


def index_path(cache_dir: Union[str, Path]) -> Path:
    """Where the index of a host lives: ``cache_dir/corpus_index.sqlite``, ``cache_dir`` the
    resolved cache folder (``disk_cache.cache_folder``, applied by the source)."""
    return Path(cache_dir) / INDEX_FILE


class CorpusIndex:
    """The corpus index file at ``path`` (made, with its folder, when missing).

    The index is a cache: a fault of the file never stops a pass or changes a sample. The
    first fault met (the folder or file cannot be made or opened, its pages are damaged, it
    cannot be written, another process holds its lock past ``timeout_s``, an entry holds a
    value this index never writes) is one warning naming the file and the fault; the index is
    then off in this process (:attr:`fault` says why), and every method answers as an empty
    index does: :meth:`lookup` None, :meth:`windows` nothing, :meth:`record` False.

    Args:
        path: the SQLite file (:func:`index_path`).
        timeout_s: how long a read or write waits for another process's write to finish,
            seconds (a write is one row: far shorter).
    """

    def __init__(self, path: Union[str, Path], timeout_s: float = BUSY_TIMEOUT_S):
        self.path = Path(path)
        #: Why the index is off in this process (the first fault met), None while it serves.
        self.fault: Optional[str] = None
        self._db: Optional[sqlite3.Connection] = None
        self._safely(None, lambda: self._open(timeout_s))

    def _open(self, timeout_s: float) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(str(self.path), timeout=timeout_s, isolation_level=None, check_same_thread=False)
        self._db.execute("PRAGMA journal_mode=WAL")
        # a cache: a power cut may lose the last entries written, never corrupt the file (WAL), and
        # an entry costs no fsync (a manifest's count records one per video)
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._db.executescript(_SCHEMA)
        row = self._db.execute("SELECT value FROM meta WHERE key = 'version'").fetchone()
        if (row is not None and row[0] != str(INDEX_VERSION)) or _columns(self._db) != _schema_columns():
            # written by another format: start afresh, the table too (CREATE TABLE IF NOT EXISTS keeps
            # an existing table's columns, into which this format's rows do not fit)
            self._db.execute("BEGIN IMMEDIATE")
            self._db.execute("DROP TABLE entries")
            self._db.execute(_ENTRIES)
            self._db.execute("COMMIT")
        # a write at every open: a file that cannot be written, or whose lock another process
        # holds, is found here, once, by the process that opens it first (its pool's workers
        # are then told to leave it off), not by each worker at its first entry
        self._db.execute("INSERT OR REPLACE INTO meta VALUES ('version', ?)", (str(INDEX_VERSION),))

    def _safely(self, default, work: Callable):
        """``work()``, or ``default`` when the index is off or ``work`` meets a fault (then off)."""
        if self.fault is not None:
            return default
        try:
            return work()
        except (sqlite3.Error, OSError, ValueError, TypeError, KeyError) as e:
            self._off(e)
            return default

    def _off(self, e: BaseException) -> None:
        """Turn the index off after the fault ``e``: one warning naming the file, the fault and what to do."""
        self.fault = fault_text(e)
        warn_once(log, ("corpus index", str(self.path)), "corpus index %s: %s; the videos are read without it "
                  "(the index is a cache: samples are the same)", self.path, self.fault)
        if self._db is not None:
            try:
                self._db.close()
            except sqlite3.Error:
                pass
            self._db = None

    def lookup(self, location: str, identity: Optional[str], layout: str) -> Optional[Verdict]:
        """The ``--check`` verdict recorded for the video
        at ``location`` under ``layout``, or None: no entry, an entry of another identity (the
        video changed), ``identity`` None (it cannot vouch for the content), or the index off."""
        if identity is None:
            return None

        def read():
            row = self._db.execute("SELECT identity, result FROM entries WHERE location = ? AND layout = ?",
                                   (location, layout)).fetchone()
            return None if row is None or row[0] != identity else stored_verdict(location, row[1])

        return self._safely(None, read)

    def windows(self, videos: Iterable[Tuple[str, str, Optional[str]]], layout: str,
                chunk: int = 500) -> Iterator[Tuple[str, int, str, str]]:
        """``(key, windows, cause, reason)``, the samples per epoch and the reason recorded under
        ``layout`` (why it gives none or fewer, '' when nothing is wrong) with its code
        (``v2v_wire.worker_messages.CAUSES``), for each ``(key,
        location, identity)`` of ``videos`` whose entry holds (same identity; None never does),
        read in queries of ``chunk`` locations: memory is bounded by the chunk, not the corpus.
        Nothing is queried when no entry of ``layout`` exists. A fault met on the way ends
        the answers (:attr:`fault` is then set: what was answered before it is not to be trusted)."""
        if not self._safely(False, lambda: self._db.execute("SELECT 1 FROM entries WHERE layout = ? LIMIT 1",
                                                            (layout,)).fetchone() is not None):
            return
        batch: Dict[str, Tuple[str, str]] = {}  # location -> (key, identity)

        def read() -> list:
            marks = ",".join("?" * len(batch))
            rows = self._db.execute(f"SELECT location, identity, windows, cause, reason FROM entries WHERE layout = ? "
                                    f"AND location IN ({marks})", (layout, *batch)).fetchall()
            return [(batch[loc][0], stored_count(loc, n), stored_cause(loc, cause), str(reason))
                    for loc, ident, n, cause, reason in rows if batch[loc][1] == ident]

        for key, location, identity in videos:
            if identity is not None:
                batch[location] = (key, identity)
                if len(batch) >= chunk:
                    yield from self._safely([], read)
                    batch.clear()
                    if self.fault is not None:
                        return
        if batch:
            yield from self._safely([], read)

    def record(self, location: str, identity: Optional[str], layout: str, result: Verdict) -> bool:
        """Keep ``result`` for the video at ``location`` of ``identity`` under ``layout``,
        replacing an older entry; nothing is kept when ``identity`` is None or the index is
        off. Returns whether it was kept."""
        if identity is None:
            return False
        s = result.stream
        w, h, codec, fps = (s.width, s.height, s.codec, s.fps) if s is not None else (None, None, None, None)
        row = (location, layout, identity, result.frames, result.windows, int(result.usable), result.reason,
               result.cause, json.dumps(list(result.cuts)), w, h, codec, fps, json.dumps(result.to_json()),
               time.time())
        return self._safely(False, lambda: self._db.execute(
            "INSERT OR REPLACE INTO entries VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)", row) is not None)

    def __len__(self) -> int:
        return self._safely(0, lambda: self._db.execute("SELECT COUNT(*) FROM entries").fetchone()[0])

    def close(self) -> None:
        if self._db is not None:
            self._db.close()
            self._db = None


#: The type of each field of a stored verdict (:class:`Verdict`; ``tuple``: a JSON list of counts),
#: in the order they are checked (the first at fault is named).
_VERDICT = {"usable": bool, "windows": int, "frames": int, "reason": str, "cuts": tuple, "dropped": int,
            "stream": dict, "cause": str, "path": str, "failed_windows": tuple, "static": int, "more": bool,
            "variable_rate": str, "frame_timing": bool}


def stored_count(location: str, value) -> int:
    """An entry's ``windows`` column as a count.

    Raises:
        ValueError: it is not a non-negative integer (naming the entry and the value)."""
    if type(value) is not int or value < 0:
        raise ValueError(f"the entry of {location} holds windows {value!r}, not a count")
    return value


def stored_cause(location: str, value) -> str:
    """An entry's ``cause`` column as a code of ``v2v_wire.worker_messages.CAUSES``.

    Raises:
        ValueError: it is not one (naming the entry and the value)."""
    if value not in CAUSES:
        raise ValueError(f"the entry of {location} holds cause {value!r}, not one of {list(CAUSES)}")
    return value


def stored_verdict(location: str, text) -> Verdict:
    """An entry's ``result`` column as a :class:`Verdict`.

    Raises:
        ValueError: it is not JSON of a verdict (naming the entry and the field at fault)."""
    try:
        verdict = json.loads(text)
    except (TypeError, ValueError):
        raise ValueError(f"the entry of {location} holds a result that is not JSON") from None
    return Verdict.from_json(location, verdict)


def fault_text(e: BaseException) -> str:
    """What a fault of the index file means, and what to do: SQLite's own words first."""
    text = str(e) or type(e).__name__
    low = text.lower()
    if "locked" in low or "busy" in low:
        return f"{text} (another process holds its lock)"
    if "unable to open" in low:
        return f"{text} (its folder cannot be written, or the path is not a file)"
    if "readonly" in low or "read-only" in low or isinstance(e, PermissionError):
        return f"{text} (it cannot be written: its permissions or a read-only file system)"
    if "malformed" in low or (isinstance(e, sqlite3.DatabaseError) and not isinstance(e, sqlite3.OperationalError)):
        return f"{text} (the file is damaged: delete it to start a new index)"
    if isinstance(e, (ValueError, TypeError, KeyError)):
        return f"{text} (not written by v2v: delete the file to start a new index)"
    return text

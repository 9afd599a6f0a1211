"""Metadata tables as video lists: a corpus's own table (OpenVid-1M's CSV, Panda-70M's CSV,
VidGen's JSON, a Parquet file) selects and orders its videos, read by DuckDB (extra
``v2v[corpora]``; measured against polars and pyarrow in docs/corpora.md).

* **Formats**, by the file's extension (a trailing ``.gz`` or ``.zst`` allowed): ``.csv``,
  ``.tsv``, ``.jsonl`` / ``.ndjson`` / ``.json`` (JSON Lines or one JSON array), ``.parquet``;
  a local path or a store URL (read through fsspec, credentials from the environment, as a list
  file in the store is).
* **The path** of a row: the column :attr:`TableSettings.column` (default: the first of
  :data:`PATH_COLUMNS` the table has), or a template over columns (``{videoID}.mp4``; a field
  is a column's whole name, dots and brackets included: ``{video.id}``). A cell is text or an
  integer; the path is folded as a list line's is (``segments.clean_path``).
* **Time ranges**: columns ``start`` and ``end`` give one segment per row, Panda-70M's
  ``timestamp`` column (a list of ``[start, end]`` pairs) one per pair; times as in list files
  (``segments.parse_time``), or numbers of seconds, or durations (INTERVAL, TIME). A column of
  that name holding dates or points in time (a ``timestamp`` of when a video was fetched, a
  Unix time) is an ordinary column: its rows are whole videos.
* **Filter**: :attr:`TableSettings.filter`, one SQL expression over the columns (``frame >=
  201 and "motion score" > 0.5``) that DuckDB parses as one expression and nothing else (its
  relation API's ``filter``: a second statement or a clause is refused, never run) and
  evaluates with the table loaded and file access off. Ctrl-C stops a slow one at once.
* **Rows not worth opening by the table's numbers**: a row's ``frame`` (else ``seconds`` x
  ``fps``; for a range, its length x ``fps``) is put to the reader's rule
  (:attr:`TableSettings.unopened`: the frames side's, ``frames.windows.WindowSettings.short_of``,
  a row too short for one window), and the rows it refuses are skipped without opening their
  video, counted in one refused entry (``--check`` shows it, the server logs it once).

A configuration error (no path column, a template's unknown column, a filter that is not one
expression, does not parse or names an unknown column) raises ``ValueError`` naming the file
and the setting. A CSV line that cannot be read (not UTF-8, too many or too few cells, a cell
not of its column's type) is refused with its line number; a row that gives no entry (no path,
a path that leaves the root or holds a NUL byte, a cell of another type, a time that does not
parse) is refused with its path, once; the rest of the table is served.
"""
from __future__ import annotations

import ast
import datetime
import decimal
import json
import logging
import math
import re
import string
import threading
from dataclasses import dataclass
from typing import Callable, Dict, List, NamedTuple, Optional, Sequence, Tuple, TypeVar

from v2v_server.sources.names import is_url
from v2v_server.sources.segments import (TIME_SYNTAX, clean_path, parse_time, path_problem, printable_name, segment_name)

T = TypeVar("T")
log = logging.getLogger("v2v")

#: Table formats by extension: DuckDB's reader of each.
TABLE_FORMATS = {".csv": "read_csv", ".tsv": "read_csv", ".jsonl": "read_json", ".ndjson": "read_json",
                 ".json": "read_json", ".parquet": "read_parquet"}
#: The columns taken as the path, in order, when none is named.
PATH_COLUMNS = ("video", "path", "file")
#: What a refused row without a path is named by.
NO_PATH = "(no path)"
#: Panda-70M's column of ``[start, end]`` pairs.
TIMESTAMP_COLUMN = "timestamp"


def _extension(path: str) -> Optional[str]:
    """The table extension of ``path`` (a trailing ``.gz`` or ``.zst`` aside), None for a list file."""
    name = path.lower().removesuffix(".gz").removesuffix(".zst")
    return next((ext for ext in TABLE_FORMATS if name.endswith(ext)), None)


def table_format(path: str) -> Optional[str]:
    """DuckDB's reader of the table at ``path`` by its extension, None for a list file."""
    ext = _extension(path)
    return TABLE_FORMATS[ext] if ext else None


@dataclass(frozen=True)
class TableSettings:
    """How a table video list is read.

    Attributes:
        column: the path column, or a template over columns (``{videoID}.mp4``); None: the
            first of :data:`PATH_COLUMNS` the table has.
        filter: SQL boolean expression over the columns (DuckDB's dialect); None: every row.
        unopened: the reader's rule for a row it would not open, given the frames the table
            counts for it (rounded as the table rounds them: OpenVid's seconds to 1/100 s): why
            (``"below one window's 201 frames"``), or None to serve it; None: every row is
            served. The frames side's rule, ``frames.windows.WindowSettings.short_of``: a source
            knows nothing of windows.
    """

    column: Optional[str] = None
    filter: Optional[str] = None
    unopened: Optional[Callable[[float], Optional[str]]] = None


def _quote(column: str) -> str:
    return '"' + column.replace('"', '""') + '"'


#: A path template: its pieces, ``(literal text, column or None)`` in order.
Template = List[Tuple[str, Optional[str]]]


def _template(path: str, columns: Sequence[str], column: str) -> Template:
    """The pieces of the path template ``column`` (``{videoID}.mp4``): literal text and the
    columns it names. A field is a column's whole name, dots and brackets included
    (``{video.id}``, ``{clip[0]}``); ``{{`` and ``}}`` are literal braces.

    Raises:
        ValueError: naming ``video_list_column`` (and the file): the template does not parse,
            names no column, formats a column (``{id:05d}``) or names one the table lacks.
    """
    try:
        parts = list(string.Formatter().parse(column))
    except ValueError as e:
        raise ValueError(f"video_list_column {column!r}: not a template ({e})") from None
    pieces: Template = []
    for text, field, spec, conv in parts:
        if field is None:
            pieces.append((text, None))
            continue
        whole = field + (f"!{conv}" if conv else "") + (f":{spec}" if spec else "")  # a name holding ':' or '!'
        if whole not in columns and (not field or spec or conv):
            raise ValueError(f"video_list_column {column!r}: a template names columns only, as '{{videoID}}.mp4'")
        if whole not in columns:
            raise _no_column(path, column, whole, columns)
        pieces.append((text, whole))
    if all(f is None for _, f in pieces):
        raise ValueError(f"video_list_column {column!r}: a template names columns only, as '{{videoID}}.mp4'")
    return pieces


def _path_spec(path: str, columns: Sequence[str], column: Optional[str]) -> Tuple[Optional[Template], List[str]]:
    """``(template, columns)``: how a row's path is made, a template over the columns or (None)
    the one column's value. A setting that is a column's name is that column, braces and all.

    Raises:
        ValueError: naming the file and ``video_list_column``, for a column the table lacks or
            a template that does not parse (:func:`_template`).
    """
    if column is None:
        lower = _by_lower(columns)
        hit = next((lower[c] for c in PATH_COLUMNS if c in lower), None)
        if hit is None:
            raise ValueError(f"video_list {path}: no path column ({', '.join(PATH_COLUMNS)}) among its columns "
                             f"{list(columns)}: name one with video_list_column (--video-list-column), or a "
                             f"template such as '{{videoID}}.mp4'")
        return None, [hit]
    if column in columns or "{" not in column:
        if column not in columns:
            raise _no_column(path, column, column, columns)
        return None, [column]
    pieces = _template(path, columns, column)
    return pieces, list(dict.fromkeys(f for _, f in pieces if f is not None))


def _by_lower(columns: Sequence[str]) -> Dict[str, str]:
    """Column by its lower-case name (DuckDB reads names that differ only in case as distinct
    names: ``Video`` beside ``video`` is ``Video_1``)."""
    lower: Dict[str, str] = {}
    for c in columns:
        lower.setdefault(c.lower(), c)
    return lower


def _no_column(path: str, column: str, name: str, columns: Sequence[str]) -> ValueError:
    """The error for ``video_list_column`` ``column`` naming ``name``, which the table lacks. A
    column whose name differs from another's only in case is read by DuckDB (whose SQL names
    columns case aside) under the name ``Name_1``: the message says so."""
    twin = [c for c in columns if c.lower().startswith(name.lower() + "_") and c[len(name) + 1:].isdigit()]
    hint = (f"; a column whose name differs from another's only in case is read as {twin[0]!r}" if twin else "")
    return ValueError(f"video_list_column {column!r}: video_list {path} has no column {name!r} "
                      f"(columns: {list(columns)}{hint})")


def _connect(path: str):
    """A DuckDB connection that can read ``path`` (a store URL through fsspec).

    Raises:
        ValueError: DuckDB is not installed.
    """
    try:
        import duckdb
    except ImportError:
        raise ValueError(f"video_list {path}: a table video list needs DuckDB: pip install 'v2v[corpora]'") from None
    # no extension is fetched or loaded behind the user's back (an operator such as >>= would ask for
    # one), and no progress bar is drawn on the server's stdout
    con = duckdb.connect(":memory:", config={"autoinstall_known_extensions": False,
                                             "autoload_known_extensions": False})
    con.execute("SET enable_progress_bar = false")
    if is_url(path):
        import fsspec

        # a fresh filesystem: the environment's credentials as they are now, not a cached instance's
        con.register_filesystem(fsspec.filesystem(path.split("://", 1)[0], skip_instance_cache=True))
    return con


def _source(path: str, reader: str, text: Sequence[str] = (), rejects: bool = False) -> str:
    """DuckDB's table function reading ``path``, the columns ``text`` read as text (a CSV
    sniffer would read an id such as ``0012345`` as a number). A CSV row that cannot be read
    (a cell that is not UTF-8, too many or too few cells, a cell not of its column's type) is
    skipped, and with ``rejects`` kept in DuckDB's ``reject_errors`` with its line
    (:func:`_rejected_lines`): one bad row does not stop the table."""
    opts = ""
    if reader == "read_csv":
        opts = ", header = true" + (", delim = '\\t'" if _extension(path) == ".tsv" else "")
        opts += ", store_rejects = true" if rejects else ", ignore_errors = true"
        if text:
            opts += ", types = {" + ", ".join(f"'{c.replace(chr(39), chr(39) * 2)}': 'VARCHAR'" for c in text) + "}"
    return f"{reader}('{path.replace(chr(39), chr(39) * 2)}'{opts})"


def _interruptible(con, query: Callable[[], T]) -> T:
    """``query()``, a DuckDB call on ``con``, run in a thread so that Ctrl-C in this one stops it
    at once (``con.interrupt()``) rather than when it ends.

    Raises:
        KeyboardInterrupt: Ctrl-C while it ran (the query is interrupted first).
        Whatever ``query`` raises.
    """
    done: dict = {}
    ended = threading.Event()

    def run() -> None:
        try:
            done["value"] = query()
        except BaseException as e:  # noqa: BLE001 - handed to the caller's thread
            done["error"] = e
        finally:
            ended.set()

    threading.Thread(target=run, name="v2v-table-query", daemon=True).start()
    try:
        while not ended.wait(0.05):
            pass
    except KeyboardInterrupt:
        con.interrupt()
        ended.wait(10.0)  # DuckDB stops the query within milliseconds; the connection is then free
        raise
    if "error" in done:
        raise done["error"]
    return done["value"]


def _run(con, path: str, sql: str, what: str):
    """``con.execute(sql).fetchall()`` (interruptible), a DuckDB error raised as ``ValueError``
    naming ``path``.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: DuckDB cannot read it as ``what``.
        KeyboardInterrupt: Ctrl-C.
    """
    import duckdb

    try:
        return _interruptible(con, lambda: con.execute(sql).fetchall())
    except duckdb.IOException as e:
        if "No files found" in str(e) or "No such file" in str(e):
            raise FileNotFoundError(f"video_list {path}: no such file") from None
        raise ValueError(f"video_list {path}: cannot be read: {_reason(e)}") from None
    except duckdb.Error as e:
        found = _bad_json_line(path) if what == "json" and "Malformed JSON" in str(e) else None
        raise ValueError(f"video_list {path}: cannot be read as {what}: {found or _reason(e)}") from None


def _bad_json_line(path: str) -> Optional[str]:
    """Where a local, uncompressed JSON Lines file first breaks: ``line N is not JSON: why``
    (DuckDB's message counts one line too many); None when every line parses, or for a
    ``.json`` file (one JSON array may span lines), a compressed or a remote one: DuckDB's
    message stands."""
    if is_url(path) or not path.lower().endswith((".jsonl", ".ndjson")):
        return None
    try:
        with open(path, "rb") as f:
            for n, line in enumerate(f, 1):
                if line.strip():
                    try:
                        json.loads(line)
                    except ValueError as e:
                        return f"line {n} is not JSON: {e}"
    except OSError:
        return None
    return None


def _reason(e: Exception) -> str:
    """DuckDB's message of ``e`` on one line: every line that says what went wrong (a CSV
    error's line number is on its first line, its reason on the third), without the echo of our
    query, the reader's suggestions or the CSV sniffer's list of dialects it tried."""
    text = re.split(r"\nLINE |\nPossible (?:Solution|fixes)|The search space used", str(e).strip())[0]
    return " ".join(line.strip() for line in text.splitlines() if line.strip())


#: The columns the window check reads (:func:`_frames_sql`).
NUMBER_COLUMNS = ("frame", "fps", "seconds")
class _Loaded(NamedTuple):
    """What :func:`_load` found: the table's ``columns``, the DuckDB ``types`` of those loaded, the path
    ``template`` (None: one column) over ``fields``, and the time-range columns ``ranges``."""

    columns: List[str]
    types: Dict[str, str]
    template: Optional[Template]
    fields: List[str]
    ranges: List[str]


def _load(con, path: str, settings: TableSettings) -> Tuple[_Loaded, List[Tuple[str, str]]]:
    """Load the columns of the table at ``path`` that a row's entry and the filter read into
    DuckDB's table ``t`` (its path columns as text), then turn file access off: the filter is an
    expression over ``t``, nothing else.

    The filter's columns are those whose name its text holds (case aside, as DuckDB's
    identifiers): a superset of those it reads, so a caption column the filter does not name is
    not loaded.

    Returns:
        ``(what was loaded, rows refused)``: a CSV row that could not be read, named by its line.

    Raises:
        FileNotFoundError, ValueError: naming the file or the setting.
        KeyboardInterrupt: Ctrl-C.
    """
    reader = table_format(path)
    what = reader[len("read_"):]
    described = _run(con, path, f"DESCRIBE SELECT * FROM {_source(path, reader)}", what)
    columns = [r[0] for r in described]
    template, fields = _path_spec(path, columns, settings.column)
    lower = _by_lower(columns)
    ranges = [lower["start"], lower["end"]] if "start" in lower and "end" in lower else \
        [lower[TIMESTAMP_COLUMN]] if TIMESTAMP_COLUMN in lower else []
    named = [c for c in columns if settings.filter and c.lower() in settings.filter.lower()]
    wanted = list(dict.fromkeys(fields + ranges + [lower[c] for c in NUMBER_COLUMNS if c in lower] + named))
    keep = ", ".join(_quote(c) for c in wanted)
    _run(con, path, f"CREATE TABLE t AS SELECT {keep} FROM {_source(path, reader, fields, rejects=True)}", what)
    refused = _rejected_lines(con, path) if reader == "read_csv" else []
    types = {r[0]: str(r[1]) for r in con.execute("DESCRIBE t").fetchall()}  # a CSV's path columns: text
    con.execute("SET enable_external_access = false")
    con.execute("SET lock_configuration = true")
    return _Loaded(columns, types, template, fields, _time_ranges(ranges, types)), refused


def _time_ranges(ranges: List[str], types: Dict[str, str]) -> List[str]:
    """The columns among ``ranges`` (``start`` and ``end``, or ``timestamp``) that hold clips'
    time ranges by their DuckDB ``types``: a column of dates or points in time (``DATE``,
    ``TIMESTAMP``: when a video was made or fetched) or, for ``timestamp``, of numbers (a Unix
    time) has the name of a range column but is a column like any other, and its rows are whole
    videos; ``[]`` then."""
    def is_date(c: str) -> bool:
        return types.get(c, "").upper().startswith(("DATE", "TIMESTAMP"))

    if len(ranges) == 1:  # Panda-70M's timestamp: a list of [start, end] pairs, or its text
        kind = types.get(ranges[0], "").upper()
        return ranges if kind in ("VARCHAR", "JSON") or kind.endswith("]") else []
    return [] if any(is_date(c) for c in ranges) else ranges


def _rejected_lines(con, path: str) -> List[Tuple[str, str]]:
    """``(path, reason)`` for each CSV line the reader skipped (``_source``), by line number:
    the first path-like cell of the line (or ``(line N)``) and DuckDB's reason."""
    rows = con.execute("SELECT line, min(error_type), min(error_message), min(csv_line) FROM reject_errors "
                       "GROUP BY line ORDER BY line").fetchall()
    out = []
    for line, kind, message, text in rows:
        shown = printable_name(text or "")
        shown = shown if len(shown) <= 80 else shown[:77] + "..."
        out.append((f"(line {line})", f"listed in {path} line {line}: {str(kind).lower()}: {message} ({shown!r})"))
    return out


def _text(cell, column: str, json_typed: bool) -> str:
    """The text of a path column's ``cell`` ("" for NULL): text as it is, an integer in
    decimal (a numeric id), a JSON column's string or integer.

    Raises:
        ValueError: any other type (a float, a list, a struct...), naming the column.
    """
    if cell is None:
        return ""
    if json_typed and isinstance(cell, str):
        try:
            cell = json.loads(cell)
        except ValueError:
            pass
        if cell is None:
            return ""
    if isinstance(cell, str):
        return cell
    if isinstance(cell, int) and not isinstance(cell, bool):
        return str(cell)
    shown = repr(cell)
    raise ValueError(f"{column} {shown if len(shown) <= 60 else shown[:57] + '...'} is a {type(cell).__name__}, "
                     f"not a name (a path column holds text or integers)")


def _seconds_of(cell) -> float:
    """Seconds from a time cell: text as ``segments.parse_time`` reads it, a number (finite),
    a duration (an INTERVAL, a TIME).

    Raises:
        ValueError: anything else (a list, a boolean, NULL...), naming it.
    """
    if isinstance(cell, str):
        return parse_time(cell.strip())
    if isinstance(cell, (int, float, decimal.Decimal)) and not isinstance(cell, bool):
        t = float(cell)
        if math.isfinite(t):
            return t
    if isinstance(cell, datetime.timedelta):
        return cell.total_seconds()
    if isinstance(cell, datetime.time):
        return cell.hour * 3600 + cell.minute * 60 + cell.second + cell.microsecond / 1e6
    raise ValueError(f"time {cell!r} is not a time ({TIME_SYNTAX})")


def _pairs(cell) -> List[Tuple[float, float]]:
    """The ``(start, end)`` seconds of a ``timestamp`` cell: a list of ``[start, end]`` pairs,
    as a list or as its text (JSON or Python literal: Panda-70M writes ``[['0:00:00.000',
    '0:00:04.638'], ...]``).

    Raises:
        ValueError: the cell is not such a list, or a time does not parse.
    """
    if isinstance(cell, str):
        try:
            cell = ast.literal_eval(cell.strip())
        except (ValueError, SyntaxError, MemoryError, RecursionError):
            raise ValueError("not a list of [start, end] pairs") from None
    if not isinstance(cell, (list, tuple)) or not cell:
        raise ValueError("not a list of [start, end] pairs")
    out = []
    for pair in cell:
        if not isinstance(pair, (list, tuple)) or len(pair) != 2 or \
                not all(isinstance(t, (str, int, float)) and not isinstance(t, bool) for t in pair):
            raise ValueError(f"{pair!r} is not a [start, end] pair")
        out.append((_seconds_of(pair[0]), _seconds_of(pair[1])))
    return out


def _frames_sql(lower: Dict[str, str], types: Dict[str, str], ranged: bool) -> str:
    """The SQL of a row's frame count by the table's numbers (NULL when it has none): ``frame``,
    else ``seconds x fps``; for a ranged row its ``fps`` (the range's length is applied later).
    A cell that is no number (text that is not one, a list, a struct) is NULL; a boolean
    column is no count."""
    have = {c for c in NUMBER_COLUMNS if c in lower and types.get(lower[c]) != "BOOLEAN"}

    def num(c: str) -> str:
        return f"TRY_CAST({_quote(lower[c])} AS DOUBLE)"

    if ranged:
        return num("fps") if "fps" in have else "NULL"
    terms = ([num("frame")] if "frame" in have else []) + \
        ([f"{num('seconds')} * {num('fps')}"] if "seconds" in have and "fps" in have else [])
    return f"COALESCE({', '.join(terms)})" if terms else "NULL"


def _select(con, path: str, settings: TableSettings, loaded: _Loaded) -> list:
    """The rows of ``t`` the filter keeps: path fields, range cells, frame number. The filter is
    one SQL expression, given to DuckDB's relation API (``filter``), which parses it as one
    expression and nothing else: a second statement, a clause or a comment's escape is
    refused, never run.

    Raises:
        ValueError: naming ``video_list_filter`` and the file.
        KeyboardInterrupt: Ctrl-C.
    """
    import duckdb

    lower = _by_lower(loaded.columns)
    select = [_quote(f) for f in loaded.fields] + [_quote(c) for c in loaded.ranges] + \
        [_frames_sql(lower, loaded.types, bool(loaded.ranges))]
    if _lean(loaded):  # whether a path may need folding or naming: a superset, that the rule then decides
        select.append(f"{_quote(loaded.fields[0])} = '' OR regexp_matches({_quote(loaded.fields[0])}, "
                      f"'^[./]|//|/[.]|/$|\\x00')")
    where = f"video_list_filter {settings.filter!r} on video_list {path}"
    log.debug("video_list %s: selecting its rows (video_list_filter %r)", path, settings.filter)
    try:
        rel = con.table("t")
        if settings.filter:
            rel = rel.filter(settings.filter)
        return _interruptible(con, rel.project(", ".join(select)).fetchall)
    except duckdb.ParserException as e:
        raise ValueError(f"{where}: not one SQL expression over its columns: {_reason(e)}") from None
    except duckdb.Error as e:
        raise ValueError(f"{where}: {_reason(e)} (columns: {loaded.columns})") from None


def read_table(path: str, settings: TableSettings) -> Tuple[List[str], List[Tuple[str, str]]]:
    """The entries a table video list gives, in the table's order, duplicates dropped, and
    ``(path, reason)`` for each row refused (a CSV line that cannot be read, no path, a path
    that is no file's, a time that does not parse) and, in one entry named by the table, the
    rows the reader's rule leaves unopened (:attr:`TableSettings.unopened`). See the module
    docstring.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: naming the file or the setting (``video_list_column``,
            ``video_list_filter``): no path column, a filter that is not one expression, does
            not parse or names an unknown column, DuckDB missing.
        KeyboardInterrupt: Ctrl-C while DuckDB reads the table (stopped at once).
    """
    con = _connect(path)
    try:
        loaded, refused = _load(con, path, settings)
        rows = _select(con, path, settings, loaded)
    finally:
        con.close()
    out, more = _entries(path, rows, loaded, settings.unopened)
    return out, refused + more


def _entries(path: str, rows: list, loaded: _Loaded, unopened: Optional[Callable[[float], Optional[str]]]
             ) -> Tuple[List[str], List[Tuple[str, str]]]:
    """:func:`read_table`'s entries from the selected ``rows`` (path fields, range cells, frame
    number), and the rows refused; ``unopened``: the reader's rule (:class:`TableSettings`)."""
    out, seen, refused, short, rows_left = [], set(), [], [], []
    why = None  # what the reader's rule said of the rows it left unopened
    fields, ranges, template = loaded.fields, loaded.ranges, loaded.template

    def keep(entry: str, n) -> None:
        nonlocal why
        no = unopened(float(n)) if unopened is not None and n is not None else None
        (short if no else out).append(entry)
        why = why or no
    json_typed = [loaded.types.get(f) == "JSON" for f in fields]

    def refuse(rel: str, why: str) -> None:
        if (rel, why) not in seen:  # a bad row repeated is named once
            seen.add((rel, why))
            refused.append((printable_name(rel) or NO_PATH, f"listed in {path}: {why}"))

    if _lean(loaded):  # one path column of text, whole videos (OpenVid): a path that needs no look is the entry
        for v, n, look in rows:
            if look is not False:  # NULL, empty, or a path to fold or name: the loop below
                rows_left.append((v, n))
            elif v not in seen:
                seen.add(v)
                keep(v, n)
        rows = rows_left
    for row in rows:
        values, cells, frames = row[:len(fields)], row[len(fields):-1], row[-1]
        if template is None and not json_typed[0] and type(values[0]) is str:  # a path column of text
            named = list(values)
            rel = clean_path(values[0])
        else:
            try:
                named = [_text(v, f, j) for v, f, j in zip(values, fields, json_typed)]
            except ValueError as e:
                refuse("", str(e))
                continue
            rel = clean_path(named[0] if template is None else
                             "".join(text + (named[fields.index(f)] if f else "") for text, f in template))
        problem = f"a row with no {' / '.join(fields)}" if not all(named) or not rel else path_problem(rel)
        if problem:
            refuse(rel, problem if problem.startswith("a row") else f"the path {problem}")
            continue
        try:
            spans = _spans(cells, ranges, loaded.types)
        except ValueError as e:
            refuse(rel, f"{' / '.join(ranges)} {_cell(cells)}: {e}")
            continue
        for span in spans:
            n = frames if span is None or frames is None else (span[1] - span[0]) * frames
            entry = rel if span is None else segment_name(rel, *span)
            if entry not in seen:
                seen.add(entry)
                keep(entry, n)
    if short:
        how = "range's length x fps" if ranges else "frame (or seconds x fps)"
        refused.append((path, f"{len(short)} row(s) of {path} skipped without opening their video: their {how} "
                              f"is {why} (e.g. {', '.join(short[:3])})"))
    return out, refused


def _lean(loaded: _Loaded) -> bool:
    """Whether rows are whole videos named by one text column: DuckDB then tells which paths
    need :func:`segments.clean_path` or :func:`segments.path_problem` at all (:func:`_select`)."""
    return loaded.template is None and not loaded.ranges and loaded.types.get(loaded.fields[0]) == "VARCHAR"


def _spans(cells: Sequence, ranges: List[str], types: Dict[str, str]) -> List[Optional[Tuple[float, float]]]:
    """The time ranges of a row's range ``cells`` (``[None]``: the whole video): one per pair
    of a ``timestamp`` cell, or the row's ``start`` and ``end``.

    Raises:
        ValueError: a cell is not a time or a list of pairs (:func:`_pairs`, :func:`_seconds_of`).
    """
    values = [_json_cell(c, types.get(r)) for c, r in zip(cells, ranges)]
    if len(ranges) == 1:
        return _pairs(values[0])
    return [(_seconds_of(values[0]), _seconds_of(values[1]))] if ranges else [None]


def _json_cell(cell, kind: Optional[str]):
    """A cell of a JSON-typed column as its value (DuckDB gives JSON as its text)."""
    if kind == "JSON" and isinstance(cell, str):
        try:
            return json.loads(cell)
        except ValueError:
            return cell
    return cell


def _cell(cells) -> str:
    text = printable_name(" / ".join(repr(c) for c in cells))
    return text if len(text) <= 80 else text[:77] + "..."

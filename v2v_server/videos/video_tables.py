"""Metadata tables as video lists: a corpus's own table (OpenVid-1M's CSV, Panda-70M's CSV,
VidGen's JSON, a Parquet file) selects and orders its videos, read by DuckDB (extra
``v2v[corpora]``; measured against polars and pyarrow in docs/corpora.md).

* **Formats**, by the file's extension (a trailing ``.gz`` or ``.zst`` allowed): ``.csv``,
  ``.tsv``, ``.jsonl`` / ``.ndjson`` / ``.json`` (JSON Lines or one JSON array), ``.parquet``;
  a local path or a store URL (read through fsspec, credentials from the environment, as a list
  file in the store is).
* **The path** of a row: the column :attr:`TableSettings.column` (default: the first of
  :data:`PATH_COLUMNS` the table has), or a template over columns (``{videoID}.mp4``).
* **Time ranges**: columns ``start`` and ``end`` give one segment per row, Panda-70M's
  ``timestamp`` column (a list of ``[start, end]`` pairs) one per pair; times as in list files
  (``segments.parse_time``).
* **Filter**: :attr:`TableSettings.filter`, an SQL expression over the columns (``frame >= 201
  and "motion score" > 0.5``) that DuckDB evaluates, with the table loaded and file access off.
* **Too short by the table's numbers**: a row whose ``frame`` (else ``seconds`` x ``fps``; for
  a range, its length x ``fps``) rounds below one window's frames is skipped without opening
  its video, and counted in one refused entry (``--check`` shows it, the server logs it once).

A configuration error (no path column, a template's unknown column, a filter that does not
parse or names an unknown column) raises ``ValueError`` naming the file and the setting; a row
that cannot be read (no path, a time that does not parse) is refused with its path, once.
"""
from __future__ import annotations

import ast
import string
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

from v2v_server.videos.segments import clean_path, parse_time, segment_name

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
        window_frames: frames one window spans; rows shorter by the table's numbers are skipped
            (0: none are).
    """

    column: Optional[str] = None
    filter: Optional[str] = None
    window_frames: int = 0


def _quote(column: str) -> str:
    return '"' + column.replace('"', '""') + '"'


def _path_spec(path: str, columns: Sequence[str], column: Optional[str]) -> Tuple[Optional[str], List[str]]:
    """``(template, columns)``: how a row's path is made, a template over the columns or (None)
    the one column's value.

    Raises:
        ValueError: naming the file and ``video_list_column``, for a column the table lacks or
            a template that does not parse.
    """
    if column is None:
        lower = {c.lower(): c for c in columns}
        hit = next((lower[c] for c in PATH_COLUMNS if c in lower), None)
        if hit is None:
            raise ValueError(f"video_list {path}: no path column ({', '.join(PATH_COLUMNS)}) among its columns "
                             f"{list(columns)}: name one with video_list_column (--video-list-column), or a "
                             f"template such as '{{videoID}}.mp4'")
        return None, [hit]
    if "{" not in column:
        fields, template = [column], None
    else:
        try:
            parts = list(string.Formatter().parse(column))
        except ValueError as e:
            raise ValueError(f"video_list_column {column!r}: not a template ({e})") from None
        fields = list(dict.fromkeys(f for _, f, _, _ in parts if f is not None))
        if not fields or any(not f or spec or conv for _, f, spec, conv in parts if f is not None):
            raise ValueError(f"video_list_column {column!r}: a template names columns only, as '{{videoID}}.mp4'")
        template = column
    missing = [f for f in fields if f not in columns]
    if missing:
        raise ValueError(f"video_list_column {column!r}: video_list {path} has no column {missing[0]!r} "
                         f"(columns: {list(columns)})")
    return template, fields


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
    if "://" in path and not path.startswith("file://"):
        import fsspec

        # a fresh filesystem: the environment's credentials as they are now, not a cached instance's
        con.register_filesystem(fsspec.filesystem(path.split("://", 1)[0], skip_instance_cache=True))
    return con


def _source(path: str, reader: str, text: Sequence[str] = ()) -> str:
    """DuckDB's table function reading ``path``, the columns ``text`` read as text (a CSV
    sniffer would read an id such as ``0012345`` as a number)."""
    opts = ""
    if reader == "read_csv":
        opts = ", header = true" + (", delim = '\\t'" if _extension(path) == ".tsv" else "")
        if text:
            opts += ", types = {" + ", ".join(f"'{c.replace(chr(39), chr(39) * 2)}': 'VARCHAR'" for c in text) + "}"
    return f"{reader}('{path.replace(chr(39), chr(39) * 2)}'{opts})"


def _run(con, path: str, sql: str, what: str):
    """``con.execute(sql)``, a DuckDB error raised as ``ValueError`` naming ``path``.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: DuckDB cannot read it as ``what``.
    """
    import duckdb

    try:
        return con.execute(sql)
    except duckdb.IOException as e:
        if "No files found" in str(e) or "No such file" in str(e):
            raise FileNotFoundError(f"video_list {path}: no such file") from None
        raise ValueError(f"video_list {path}: cannot be read: {_first_line(e)}") from None
    except duckdb.Error as e:
        raise ValueError(f"video_list {path}: cannot be read as {what}: {_first_line(e)}") from None


def _first_line(e: Exception) -> str:
    return str(e).strip().splitlines()[0]


#: The columns the window check reads (:func:`_frames_sql`).
NUMBER_COLUMNS = ("frame", "fps", "seconds")


def _load(con, path: str, settings: TableSettings) -> Tuple[List[str], Optional[str], List[str], List[str]]:
    """Load the columns of the table at ``path`` that a row's entry and the filter read into
    DuckDB's table ``t`` (its path columns as text), then turn file access off: the filter is an
    expression over ``t``, nothing else.

    The filter's columns are those whose name its text holds (case aside, as DuckDB's
    identifiers): a superset of those it reads, so a caption column the filter does not name is
    not loaded.

    Returns:
        ``(columns of the table, path template, path columns, range columns)``.

    Raises:
        FileNotFoundError, ValueError: naming the file or the setting.
    """
    reader = table_format(path)
    what = reader[len("read_"):]
    columns = [r[0] for r in _run(con, path, f"DESCRIBE SELECT * FROM {_source(path, reader)}", what).fetchall()]
    template, fields = _path_spec(path, columns, settings.column)
    lower = {c.lower(): c for c in columns}
    ranges = [lower["start"], lower["end"]] if "start" in lower and "end" in lower else \
        [lower[TIMESTAMP_COLUMN]] if TIMESTAMP_COLUMN in lower else []
    wanted = fields + ranges + [lower[c] for c in NUMBER_COLUMNS if c in lower] + \
        [c for c in columns if settings.filter and c.lower() in settings.filter.lower()]
    keep = ", ".join(_quote(c) for c in dict.fromkeys(wanted))
    _run(con, path, f"CREATE TABLE t AS SELECT {keep} FROM {_source(path, reader, fields)}", what)
    con.execute("SET enable_external_access = false")
    con.execute("SET lock_configuration = true")
    return columns, template, fields, ranges


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
        out.append((parse_time(str(pair[0])), parse_time(str(pair[1]))))
    return out


def _frames_sql(lower: Dict[str, str], ranged: bool) -> str:
    """The SQL of a row's frame count by the table's numbers (NULL when it has none): ``frame``,
    else ``seconds x fps``; for a ranged row its ``fps`` (the range's length is applied later)."""
    def num(c: str) -> str:
        return f"TRY_CAST({_quote(lower[c])} AS DOUBLE)"

    if ranged:
        return num("fps") if "fps" in lower else "NULL"
    terms = ([num("frame")] if "frame" in lower else []) + \
        ([f"{num('seconds')} * {num('fps')}"] if "seconds" in lower and "fps" in lower else [])
    return f"COALESCE({', '.join(terms)})" if terms else "NULL"


def read_table(path: str, settings: TableSettings) -> Tuple[List[str], List[Tuple[str, str]]]:
    """The entries a table video list gives, in the table's order, duplicates dropped, and
    ``(path, reason)`` for each row refused (no path, a time that does not parse) and, in one
    entry named by the table, the rows too short for a window. See the module docstring.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: naming the file or the setting (``video_list_column``,
            ``video_list_filter``): no path column, a filter that does not parse or names an
            unknown column, DuckDB missing.
    """
    import duckdb

    con = _connect(path)
    columns, template, fields, ranges = _load(con, path, settings)
    lower = {c.lower(): c for c in columns}
    select = [_quote(f) for f in fields] + [_quote(c) for c in ranges] + [_frames_sql(lower, bool(ranges))]
    sql = f"SELECT {', '.join(select)} FROM t" + (f" WHERE ({settings.filter})" if settings.filter else "")
    try:
        rows = con.execute(sql).fetchall()
    except duckdb.Error as e:
        raise ValueError(f"video_list_filter {settings.filter!r} on video_list {path}: {_first_line(e)} "
                         f"(columns: {columns})") from None
    finally:
        con.close()
    return _entries(path, rows, template, fields, ranges, settings.window_frames)


def _entries(path: str, rows: list, template: Optional[str], fields: List[str], ranges: List[str], window_frames: int
             ) -> Tuple[List[str], List[Tuple[str, str]]]:
    """:func:`read_table`'s entries from the selected ``rows`` (path fields, range cells, frame
    number)."""
    out, seen, refused, short = [], set(), [], []
    need = window_frames - 0.5  # the table's numbers are rounded (OpenVid's seconds to 1/100 s)

    def refuse(rel: str, why: str) -> None:
        if (rel, why) not in seen:  # a bad row repeated is named once
            seen.add((rel, why))
            refused.append((rel or NO_PATH, f"listed in {path}: {why}"))

    if template is None and not ranges:  # one path column, whole videos (OpenVid): the loop below, lean
        for v, n in rows:
            rel = "" if v is None else clean_path(str(v))
            if not rel:
                refuse(rel, f"a row with no {fields[0]}")
            elif rel not in seen:
                seen.add(rel)
                (short if n is not None and n < need else out).append(rel)
        rows = []
    for row in rows:
        values, cells, frames = row[:len(fields)], row[len(fields):-1], row[-1]
        named = ["" if v is None else str(v) for v in values]
        rel = clean_path(named[0] if template is None else template.format(**dict(zip(fields, named))))
        try:
            if not all(named) or not rel:
                raise ValueError(f"a row with no {' / '.join(fields)}")
            spans = _pairs(cells[0]) if len(ranges) == 1 else \
                [(parse_time(str(cells[0])), parse_time(str(cells[1])))] if ranges else [None]
        except ValueError as e:
            refuse(rel, f"{' / '.join(ranges)} {_cell(cells)}: {e}" if all(named) and rel else str(e))
            continue
        for span in spans:
            n = frames if span is None or frames is None else (span[1] - span[0]) * frames
            entry = rel if span is None else segment_name(rel, *span)
            if entry not in seen:
                seen.add(entry)
                (short if n is not None and n < need else out).append(entry)
    if short:
        how = "range's length x fps" if ranges else "frame (or seconds x fps)"
        refused.append((path, f"{len(short)} row(s) of {path} skipped without opening their video: their {how} "
                              f"is below one window's {window_frames} frames (e.g. {', '.join(short[:3])})"))
    return out, refused


def _cell(cells) -> str:
    text = " / ".join(repr(c) for c in cells)
    return text if len(text) <= 80 else text[:77] + "..."

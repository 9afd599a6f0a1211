"""``bench/corpus_recipes.py`` at its smallest: every recipe of docs/corpora.md runs on its
corpus, gives samples where its footage holds a window, and names what it skips and why."""
from __future__ import annotations

import json

import pytest

from bench.corpus_recipes import RECIPES, main, recipe


@pytest.mark.timeout(600)  # about 40 CPU-seconds: rendering and encoding the corpora, five v2v-serve --check runs
def test_corpus_recipes_bench_reports_every_recipe(tmp_path, capsys):
    out = tmp_path / "corpus_recipes.json"
    assert main(["--clips", "1", "--hd-height", "240", "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    rows = {row["corpus"]: row for row in r["recipes"]}
    assert list(rows) == list(RECIPES) and r["command"] == "python -m bench.corpus_recipes --clips 1 --hd-height 240 " \
                                                          f"--json {out}"
    for name, row in rows.items():
        assert row["command"] == recipe(name, 1) and row["footage_s"] > 0
        assert row["samples"] > 0 and row["samples_per_clip_hour"] == round(row["samples"] / row["footage_s"] * 3600, 1)
        assert ("--keep-top-fraction 0.54" in row["command"]) == (name == "webvid")
        assert ("--frame-height 336" in row["command"]) == (name in ("openvid", "panda", "phone"))
    # WebVid's montage: every shot shorter than a window
    assert [s[0] for s in rows["webvid"]["skipped"]] == ["webvid_like_596x336.mp4"]
    assert "every shot is shorter than one window" in rows["webvid"]["skipped"][0][2]
    # OpenVid: the CSV's bare names paired with the parts' members; the short row skipped by the
    # table's numbers, the row of a clip in no part named, the low-motion row dropped by the
    # filter: one member served, from its zip part
    openvid = rows["openvid"]
    assert "OpenVid_part{0..0}.zip" in openvid["command"]
    assert openvid["entries"] == 1 and openvid["verdicts"][0][0] == "OpenVid_part0.zip/clip_0000.mp4"
    assert any("no member of" in s[2] and "not_downloaded.mp4" in s[2] for s in openvid["skipped"])
    assert any("skipped without opening their video" in s[2] and "short_0000.mp4" in s[2] for s in openvid["skipped"])
    # Panda: one range per shot; the 4.4 s shot is opened (no fps column) and gives none
    panda = rows["panda"]
    assert panda["entries"] == 3 and panda["usable"] == 2
    assert [s[0] for s in panda["skipped"]] == ["-00Xk9aQ_zY.mp4#t=12.2,16.6"]
    assert rows["webdataset"]["entries"] == 2 and all(".tar/" in v[0] for v in rows["webdataset"]["verdicts"])
    # the phone clip: 30 fps, so a 201-frame window spans 6.7 s; --check names the coded (landscape) size
    assert rows["phone"]["verdicts"][0][:2] == ["IMG_4000.mp4", "1 window(s)"]
    assert "426x240 h264 yuv420p 30 fps" in rows["phone"]["verdicts"][0][2]
    assert "| webvid | 2 | 1 | 2 |" in capsys.readouterr().out

"""``v2v-stats`` (trainer/stats_report.py): the report from a corpus and from a running server,
with a real recording's overlay, opened in headless Chromium as a user would; bad input."""
from __future__ import annotations

import json
import shutil
import subprocess
import tempfile

import numpy as np
import pytest

from harness.data import DAVIS346, EVT2, SAMPLE_VIDEOS
from harness.serve import ServeProcess, free_port
from trainer.stats_report import main

def _screenshot(page, png) -> None:
    chromium = shutil.which("chromium")
    if chromium is None:
        pytest.skip("Chromium is not installed (Debian: apt-get install -y chromium)")
    profile = tempfile.mkdtemp(prefix="v2v-chromium-")
    try:
        subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                        "--disable-background-networking", "--disable-component-update", "--disable-sync",
                        f"--user-data-dir={profile}", "--window-size=1400,4000", f"--screenshot={png}",
                        page.as_uri()], check=True, capture_output=True, timeout=120)
    finally:
        shutil.rmtree(profile, ignore_errors=True)


def test_corpus_report_with_recording_opens_in_chromium(tmp_path, short_recipe, capsys):
    out = tmp_path / "report"
    rc = main(["--videos", str(SAMPLE_VIDEOS), "--config", short_recipe, "--samples", "12",
               "--recording", str(DAVIS346), "--out", str(out)])
    assert rc == 0
    data = json.loads((out / "stats.json").read_text())
    assert len(data["samples"]) == 12 and not data["notes"]
    for row in data["samples"]:
        assert row["rate_pos"] > 0 and 0 < row["active_fraction"] <= 1 and row["flow_mag"] >= 0
        assert len(row["grid_rates"]) == 8 and row["video"] in {v["path"] for v in data["videos"]}
    videos = {v["path"]: v for v in data["videos"]}
    bikes = videos["bikes.mp4"]
    assert videos["bbb_camera_596x336.mp4"]["codec"] == "h264" and (bikes["width"], bikes["height"]) == (640, 272)
    assert sum(videos["bikes.mp4"]["shot_lengths"]) == videos["bikes.mp4"]["frames"]
    # the DAVIS346 file (2.36 s) holds one 1.6 s sample window and eleven 0.2 s grid windows
    rec = data["recording"]
    assert len(rec["sample"]["windows"]) == 1 and len(rec["grid"]["windows"]) == 11
    assert rec["grid"]["window_s"] == pytest.approx(0.2) and rec["grid"]["sensor"] == "346x260"
    assert data["summary"]["recording"]["grid"]["rate"]["n"] == 11
    # the bundled clips move: no sample's window is static, and each carries its motion
    assert data["summary"]["static_windows"] == {"threshold": 0.005, "count": 0, "of": 12}
    assert all(row["motion"] >= 0.005 for row in data["samples"])
    # every statistic on one grid: the stream's 96 voxel grids of 0.2 s, the recording's 11 cells of 0.2 s
    grid = data["summary"]["grid"]
    assert grid["cell_s"] == pytest.approx(0.2) and grid["bins"] == 5 and grid["frames_per_bin"] == 1
    assert grid["stream"]["rate_net"]["n"] == 96 and grid["recording"]["rate_net"]["n"] == 11
    assert grid["recording"]["active_fraction"]["median"] == pytest.approx(0.0155, abs=0.001)
    for key in ("rate_signal", "rate_net", "active_fraction", "polarity_balance", "events_per_active", "still_rate"):
        assert grid["stream"][key]["n"] > 0 and grid["recording"][key]["n"] == 11, key
    assert all(len(r["cells"]) == 8 for r in data["samples"])
    page = out / "index.html"
    text = page.read_text()
    assert "Grid: one voxel grid, 5 bins x 1 frame interval(s) = 0.2 s" in text and "11 cells of 0.2 s" in text
    assert 'src="grid.png"' in text
    for png in ("events.png", "params.png", "videos.png", "grid.png"):
        assert f'src="{png}"' in page.read_text() and (out / png).stat().st_size > 10_000
    shot = tmp_path / "page.png"
    _screenshot(page, shot)
    import matplotlib.image

    img = matplotlib.image.imread(shot)[..., :3]
    # the figures are drawn: matplotlib's blue bars (tab:blue, #1f77b4) are on the page, in quantity
    blue = np.all(np.abs(img - np.array([0x1f, 0x77, 0xb4]) / 255) < 0.12, axis=-1)
    assert blue.sum() > 2000, blue.sum()
    # and the recording beside the stream: matplotlib's second colour (tab:orange, #ff7f0e) at the
    # histograms' alpha 0.6 over white
    orange = np.all(np.abs(img - (0.4 + 0.6 * np.array([0xff, 0x7f, 0x0e]) / 255)) < 0.06, axis=-1)
    assert orange.sum() > 1000, orange.sum()


#: names that mean something to matplotlib (mathtext), HTML, printf and a terminal
HOSTILE_NAMES = ("price_$5_$10.mp4", "a%d<b>&amp;%s.mp4", "new\nline.mp4", "日本語の動画.mp4")


def test_hostile_video_names_are_drawn_and_escaped(tmp_path, short_recipe, capsys):
    corpus = tmp_path / "corpus"
    corpus.mkdir()
    names = list(HOSTILE_NAMES)
    for n in names:
        shutil.copy(SAMPLE_VIDEOS / "bikes.mp4", corpus / n)
    out = tmp_path / "report"
    assert main(["--videos", str(corpus), "--config", short_recipe, "--samples", "2", "--out", str(out)]) == 0
    assert "Traceback" not in capsys.readouterr().err
    data = json.loads((out / "stats.json").read_text())
    # a name holding a control character is refused by the corpus (sample ids travel one per
    # line); the page shows the others as written
    served = [n for n in names if "\n" not in n]
    assert sorted(v["path"] for v in data["videos"]) == sorted(served)
    text = (out / "index.html").read_text()
    assert "<td>a%d&lt;b&gt;&amp;amp;%s.mp4</td>" in text and "<b>&amp;" not in text
    assert "<td>price_$5_$10.mp4</td>" in text and (out / "videos.png").stat().st_size > 5_000
    shot = tmp_path / "page.png"
    _screenshot(out / "index.html", shot)  # the page opens as a user's browser opens it
    assert shot.stat().st_size > 10_000


@pytest.mark.parametrize("case", ["an existing file", "a folder that cannot be made"])
def test_bad_out_is_one_line_before_any_sampling(tmp_path, short_recipe, capsys, case):
    blocker = tmp_path / "taken"
    blocker.write_text("not a folder")
    out = blocker if case == "an existing file" else blocker / "report"
    # an empty corpus would be refused too: --out is checked before the corpus is read
    (tmp_path / "empty").mkdir()
    assert main(["--videos", str(tmp_path / "empty"), "--config", short_recipe, "--out", str(out)]) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"v2v-stats: --out {out}: "), lines
    assert blocker.read_text() == "not a folder"


def test_server_report(tmp_path, short_recipe):
    """``v2v-stats --server`` reads a server's plan: the samples' parameters and grids from the
    voxels it sent."""
    args = ["--videos", str(SAMPLE_VIDEOS), "--workers", "1", "--config", short_recipe]
    with ServeProcess(args) as srv:
        out = tmp_path / "report"
        assert main(["--server", srv.endpoint, "--samples", "4", "--timeout", "60", "--out", str(out)]) == 0
    data = json.loads((out / "stats.json").read_text())
    assert len(data["samples"]) == 4 and data["source"] == f"server {srv.endpoint}"
    assert all(r["rate_pos"] > 0 and "pos_threshold" in r for r in data["samples"])
    # the same grid from the voxels the server sent: 8 voxel grids of 0.2 s a sample
    assert all(len(r["cells"]) == 8 for r in data["samples"]) and data["summary"]["grid"]["stream"]["rate_net"]["n"] == 32
    assert data["videos"] == []  # a server's params do not say a video's format


def test_short_recording_is_named_and_the_report_written(tmp_path, short_recipe, capsys):
    out = tmp_path / "r"
    assert main(["--videos", str(SAMPLE_VIDEOS), "--config", short_recipe, "--samples", "2",
                 "--recording", str(EVT2), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert f"recording {EVT2}" in err and "shorter than one grid window" in err
    data = json.loads((out / "stats.json").read_text())
    assert data["recording"]["grid"]["windows"] == [] and (out / "index.html").exists()
    assert "shorter than one sample window" in (out / "index.html").read_text()
    # a recording cut short is measured up to the cut, and the report says so
    cut = tmp_path / "cut.aedat4"
    cut.write_bytes(DAVIS346.read_bytes()[:DAVIS346.stat().st_size // 2])
    assert main(["--videos", str(SAMPLE_VIDEOS), "--config", short_recipe, "--samples", "2",
                 "--recording", str(cut), "--out", str(tmp_path / "cut")]) == 0
    data = json.loads((tmp_path / "cut" / "stats.json").read_text())
    assert data["recording"]["sample"]["truncated"] is True
    assert any(n.startswith(f"recording {cut} is truncated") for n in data["notes"]), data["notes"]


@pytest.mark.parametrize("case", ["empty corpus", "unreadable recording", "unreachable server"])
def test_bad_input_is_one_line_and_exit_2(tmp_path, short_recipe, capsys, case):
    out = str(tmp_path / "out")
    if case == "empty corpus":
        (tmp_path / "empty").mkdir()
        argv, named = ["--videos", str(tmp_path / "empty")], f"corpus {tmp_path / 'empty'}: no video"
    elif case == "unreadable recording":
        bad = tmp_path / "bad.aedat4"
        bad.write_bytes(b"not an aedat file at all")
        argv, named = ["--videos", str(SAMPLE_VIDEOS), "--recording", str(bad)], f"recording {bad}"
    else:
        ep = f"tcp://127.0.0.1:{free_port()}"
        argv, named = ["--server", ep, "--timeout", "2"], f"server {ep}"
    assert main([*argv, "--config", short_recipe, "--samples", "2", "--out", out]) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("v2v-stats: ")]
    assert len(lines) == 1 and named in lines[0], lines


def test_frames_read_by_a_check_that_stops_early_are_a_lower_bound_everywhere(tmp_path, capsys):
    """The check stops decoding a video once the recipe's windows are complete: a 30-frame clip
    with one 6-frame window a video shows its 6 frames as a lower bound in stats.json, on the page
    and in ``--check`` alike (``6+``), never as the clip's length; uncapped, the true 30."""
    import subprocess
    import sys
    import time

    from harness.corpus import write_video
    from v2v_server.sources.local import RACY_NS

    corpus = tmp_path / "corpus"
    corpus.mkdir()
    write_video(corpus / "clip30.mp4", 30, 128, 96)
    time.sleep(2 * RACY_NS / 1e9)
    for cap, frames, bound in ((1, 6, True), (10, 30, False)):
        recipe = tmp_path / f"cap{cap}.yaml"
        recipe.write_text(f"sequence_length: 1\nbatch_size: 2\nmax_samples_per_video: {cap}\n")
        out = tmp_path / f"report{cap}"
        assert main(["--videos", str(corpus), "--config", str(recipe), "--samples", "1", "--out", str(out)]) == 0
        video = json.loads((out / "stats.json").read_text())["videos"][0]
        assert (video["frames"], video["shot_lengths"], video["lower_bound"]) == (frames, [frames], bound), video
        page = (out / "index.html").read_text()
        assert (f"<td>{frames}+</td>" in page) == bound and (f"<td>{frames}</td>" in page) != bound
        check = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--check", "--videos", str(corpus), "--config",
                                str(recipe), "--cache-dir", str(tmp_path / "cache")], capture_output=True, text=True,
                               timeout=300)
        row = check.stdout.splitlines()[1]
        assert (f" {frames}+ frames" in row and "no cut in the frames read" in row if bound else
                f" {frames} frames" in row and "one shot" in row), check.stdout

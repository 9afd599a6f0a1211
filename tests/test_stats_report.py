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

#: a short recipe (windows of 41 frames: 1.64 s at 25 fps, grids of 0.2 s) so the clips give samples fast
SHORT = "sequence_length: 8\nbatch_size: 2\n"


@pytest.fixture
def short_config(tmp_path):
    p = tmp_path / "short.yaml"
    p.write_text(SHORT)
    return str(p)


def _screenshot(page, png) -> None:
    chromium = shutil.which("chromium")
    if chromium is None:
        pytest.skip("Chromium is not installed (Debian: apt-get install -y chromium)")
    profile = tempfile.mkdtemp(prefix="v2v-chromium-")
    try:
        subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                        "--disable-background-networking", "--disable-component-update", "--disable-sync",
                        f"--user-data-dir={profile}", "--window-size=1400,2400", f"--screenshot={png}",
                        page.as_uri()], check=True, capture_output=True, timeout=120)
    finally:
        shutil.rmtree(profile, ignore_errors=True)


def test_corpus_report_with_recording_opens_in_chromium(tmp_path, short_config, capsys):
    out = tmp_path / "report"
    rc = main(["--videos", str(SAMPLE_VIDEOS), "--config", short_config, "--samples", "12",
               "--recording", str(DAVIS346), "--out", str(out)])
    assert rc == 0
    data = json.loads((out / "stats.json").read_text())
    assert len(data["samples"]) == 12 and not data["notes"]
    for row in data["samples"]:
        assert row["rate_pos"] > 0 and 0 < row["active_fraction"] <= 1 and row["flow_mag"] >= 0
        assert len(row["grid_rates"]) == 8 and row["video"] in {v["path"] for v in data["videos"]}
    videos = {v["path"]: v for v in data["videos"]}
    assert videos["bbb_camera_596x336.mp4"]["codec"] == "h264" and videos["bikes.mp4"]["size"].startswith("640x272")
    assert sum(videos["bikes.mp4"]["shot_lengths"]) == videos["bikes.mp4"]["frames"]
    # the DAVIS346 file (2.36 s) holds one 1.6 s sample window and eleven 0.2 s grid windows
    rec = data["recording"]
    assert len(rec["sample"]["windows"]) == 1 and len(rec["grid"]["windows"]) == 11
    assert rec["grid"]["window_s"] == pytest.approx(0.2) and rec["grid"]["sensor"] == "346x260"
    assert data["summary"]["recording"]["grid"]["rate"]["n"] == 11
    # the bundled clips move: no sample's window is static, and each carries its motion
    assert data["summary"]["static_windows"] == {"threshold": 0.005, "count": 0, "of": 12}
    assert all(row["motion"] >= 0.005 for row in data["samples"])
    page = out / "index.html"
    for png in ("events.png", "params.png", "videos.png"):
        assert f'src="{png}"' in page.read_text() and (out / png).stat().st_size > 10_000
    shot = tmp_path / "page.png"
    _screenshot(page, shot)
    import matplotlib.image

    img = matplotlib.image.imread(shot)[..., :3]
    # the figures are drawn: matplotlib's blue bars (tab:blue, #1f77b4) are on the page, in quantity
    blue = np.all(np.abs(img - np.array([0x1f, 0x77, 0xb4]) / 255) < 0.12, axis=-1)
    assert blue.sum() > 2000, blue.sum()


def test_server_report(tmp_path, short_config):
    args = ["--videos", str(SAMPLE_VIDEOS), "--workers", "1", "--config", short_config, "--max-credits", "4"]
    with ServeProcess(args) as srv:
        out = tmp_path / "report"
        assert main(["--server", srv.endpoint, "--samples", "4", "--timeout", "60", "--out", str(out)]) == 0
    data = json.loads((out / "stats.json").read_text())
    assert len(data["samples"]) == 4 and data["source"] == f"server {srv.endpoint}"
    assert all(r["rate_pos"] > 0 and "pos_threshold" in r for r in data["samples"])
    assert data["videos"] == []  # a server's params do not say a video's format


def test_short_recording_is_named_and_the_report_written(tmp_path, short_config, capsys):
    out = tmp_path / "r"
    assert main(["--videos", str(SAMPLE_VIDEOS), "--config", short_config, "--samples", "2",
                 "--recording", str(EVT2), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert f"recording {EVT2}" in err and "shorter than one grid window" in err
    data = json.loads((out / "stats.json").read_text())
    assert data["recording"]["grid"]["windows"] == [] and (out / "index.html").exists()
    assert "shorter than one sample window" in (out / "index.html").read_text()


@pytest.mark.parametrize("case", ["empty corpus", "unreadable recording", "unreachable server"])
def test_bad_input_is_one_line_and_exit_2(tmp_path, short_config, capsys, case):
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
    assert main([*argv, "--config", short_config, "--samples", "2", "--out", out]) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("v2v-stats: ")]
    assert len(lines) == 1 and named in lines[0], lines

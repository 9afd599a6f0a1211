"""Nothing a command is given as input is ever its output: every command that writes files
(``v2v-calibrate``, ``v2v-stats``, ``v2v-eval``, ``v2v-train``, ``v2v-demo``, ``v2v-keygen``)
refuses, before any work, an output that is one of its inputs (the recording itself, a recipe, a
corpus or one of its videos, a recording a video would be written over) and an output folder it
cannot write, with one line naming it and exit status 2; the input is left as it was."""
from __future__ import annotations

import hashlib
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from harness.data import DAVIS346, EVT3, SAMPLE_VIDEOS

#: A folder nothing can be written to, even as root (procfs).
UNWRITABLE = Path("/proc/v2v-output")


def _digest(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _refused(capsys, prog: str, named: str) -> None:
    captured = capsys.readouterr()
    lines = [ln for ln in captured.err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"{prog}: ") and named in lines[0], lines
    assert "simulation" not in captured.err and "sampling" not in captured.err  # refused before any work


@pytest.mark.parametrize("case", ["the aedat4 recording", "the raw recording", "the recipe", "a video of the corpus",
                                  "the corpus folder", "an unwritable folder"])
def test_calibrate_refuses_an_out_that_is_an_input(tmp_path, short_recipe, capsys, case):
    from trainer.calibrate import main

    corpus = tmp_path / "corpus"
    corpus.mkdir()
    shutil.copy(SAMPLE_VIDEOS / "bikes.mp4", corpus / "bikes.mp4")
    rec = tmp_path / DAVIS346.name
    shutil.copy(DAVIS346, rec)
    args = ["--recipe", short_recipe, "--videos", str(corpus), "--evaluations", "12", "--windows", "2"]
    if case == "the raw recording":
        rec = tmp_path / EVT3.name
        shutil.copy(EVT3, rec)
    out, named = {"the aedat4 recording": (rec, "is the recording (--recording)"),
                  "the raw recording": (rec, "is the recording (--recording)"),
                  "the recipe": (Path(short_recipe), "is the base recipe (--recipe)"),
                  "a video of the corpus": (corpus / "bikes.mp4", "is a video of the corpus (--videos)"),
                  "the corpus folder": (corpus, "is a folder"),
                  "an unwritable folder": (Path("/proc/fitted.yaml"), "cannot be written")}[case]
    before = {p: _digest(p) for p in (rec, Path(short_recipe), corpus / "bikes.mp4")}
    assert main(["--recording", str(rec), *args, "--out", str(out)]) == 2
    _refused(capsys, "v2v-calibrate", f"--out {out}: {named}")
    assert {p: _digest(p) for p in before} == before


def test_stats_refuses_an_out_that_is_an_input(tmp_path, short_recipe, capsys):
    from trainer.stats_report import main

    corpus = tmp_path / "corpus"
    corpus.mkdir()
    shutil.copy(SAMPLE_VIDEOS / "bikes.mp4", corpus / "bikes.mp4")
    assert main(["--videos", str(corpus), "--config", short_recipe, "--out", str(corpus)]) == 2
    _refused(capsys, "v2v-stats", f"--out {corpus}: is the corpus (--videos)")
    report = tmp_path / "report"
    report.mkdir()
    recipe = report / "stats.json"  # a recipe kept where the report writes its numbers
    recipe.write_text(Path(short_recipe).read_text())
    assert main(["--videos", str(corpus), "--config", str(recipe), "--out", str(report)]) == 2
    _refused(capsys, "v2v-stats", f"--out {report}: its stats.json is the recipe (--config)")
    assert recipe.read_text() == Path(short_recipe).read_text()


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    import torch

    from trainer.config import default_config, merge
    from trainer.core import Trainer

    cfg = merge(default_config("e2vid"), {"model": {"num_bins": 5, "base_num_channels": 4}})
    return str(Trainer(cfg, str(tmp_path_factory.mktemp("ck")), torch.device("cpu")).save_checkpoint())


def test_eval_refuses_a_video_written_over_an_input(tmp_path, checkpoint, capsys):
    """A recording without frames is written as ``<stem>.mp4`` in --write-video: a --video input
    of that name there would be overwritten."""
    from trainer.evaluate import main

    clips = tmp_path / "clips"
    clips.mkdir()
    video = clips / f"{EVT3.stem}.mp4"
    shutil.copy(SAMPLE_VIDEOS / "bikes.mp4", video)
    before = _digest(video)
    assert main(["--checkpoint", checkpoint, "--recording", str(EVT3), "--video", str(video), "--device", "cpu",
                 "--write-video", str(clips), "--out", str(tmp_path / "ev")]) == 2
    _refused(capsys, "v2v-eval", f"--write-video {clips}: its {video.name} is an input (--video {video})")
    assert _digest(video) == before
    assert main(["--checkpoint", checkpoint, "--recording", str(EVT3), "--device", "cpu", "--out",
                 checkpoint]) == 2
    _refused(capsys, "v2v-eval", f"--out {checkpoint}: is the checkpoint (--checkpoint)")
    assert main(["--checkpoint", checkpoint, "--recording", str(EVT3), "--device", "cpu", "--out",
                 str(UNWRITABLE)]) == 2
    _refused(capsys, "v2v-eval", f"--out {UNWRITABLE}: cannot be made")


def test_train_refuses_its_own_config_as_input_and_an_unwritable_out(tmp_path, capsys):
    from trainer.train import main

    run = tmp_path / "run"
    run.mkdir()
    config = run / "config.json"
    config.write_text('{"task": "e2vid"}')
    assert main(["--config", str(config), "--out", str(run), "--connect", "tcp://127.0.0.1:9"]) == 2
    _refused(capsys, "v2v-train", f"--out {run}: its config.json is the config (--config)")
    assert config.read_text() == '{"task": "e2vid"}'
    assert main(["--task", "e2vid", "--out", str(UNWRITABLE), "--connect", "tcp://127.0.0.1:9"]) == 2
    _refused(capsys, "v2v-train", f"--out {UNWRITABLE}: cannot be made")


def test_demo_and_keygen_refuse_before_starting(tmp_path):
    corpus = tmp_path / "corpus"
    corpus.mkdir()
    shutil.copy(SAMPLE_VIDEOS / "bikes.mp4", corpus / "bikes.mp4")
    before = _digest(corpus / "bikes.mp4")
    r = subprocess.run([sys.executable, "-m", "v2v_client.demo", "--videos", str(corpus), "--preview",
                        str(corpus / "bikes.mp4")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr == (f"v2v-demo: --preview {corpus / 'bikes.mp4'}: is inside the corpus "
                                              f"(--videos): a command never writes over what it reads\n"), r.stderr
    assert _digest(corpus / "bikes.mp4") == before and "server running" not in r.stdout
    r = subprocess.run([sys.executable, "-m", "v2v_server.ops.keygen", "server", "--out", str(UNWRITABLE)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.startswith(f"v2v-keygen: --out {UNWRITABLE}: cannot be made"), r.stderr

"""Configuration errors of the commands read alike: ``v2v-train``, ``v2v-eval`` and
``v2v-serve`` name the file, the key and the allowed keys, exit 2 and print no traceback."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True, cwd=ROOT, env=env,
                          timeout=timeout)


def _assert_config_error(r: subprocess.CompletedProcess, prog: str, *named: str) -> None:
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr, r.stderr
    line = next(x for x in r.stderr.splitlines() if x.startswith(f"{prog}: configuration error: "))
    for text in named:
        assert text in line, (text, line)


def test_v2v_train_names_the_file_the_key_and_the_allowed_keys(tmp_path):
    cfg = tmp_path / "run.yaml"
    cfg.write_text("task: e2vid\noptim: {learning_rate: 1}\n")
    r = _run("trainer.train", "--config", str(cfg), "--out", str(tmp_path / "out"))
    _assert_config_error(r, "v2v-train", str(cfg), "['learning_rate']", "in optim", "allowed keys:", "'lr'")
    assert not (tmp_path / "out").exists()  # stopped before anything was written
    cfg.write_text("model: {num_bin: 3}\n")
    r = _run("trainer.train", "--config", str(cfg), "--out", str(tmp_path / "out"))
    _assert_config_error(r, "v2v-train", str(cfg), "['num_bin']", "in model", "'num_bins'")
    r = _run("trainer.train", "--set", "optim.learning_rate=1", "--out", str(tmp_path / "out"))
    _assert_config_error(r, "v2v-train", "--set optim.learning_rate=1", "in optim", "'lr'")
    r = _run("trainer.train", "--config", str(tmp_path / "missing.yaml"))
    _assert_config_error(r, "v2v-train", "missing.yaml")


def test_v2v_eval_names_the_checkpoint_whose_configuration_does_not_build(tmp_path):
    torch = pytest.importorskip("torch")
    from trainer.config import default_config

    cfg = default_config("e2vid")
    cfg["model"]["num_bin"] = 3
    ck = tmp_path / "checkpoint_last.pt"
    torch.save({"task": "e2vid", "config": cfg, "model": {}}, ck)
    r = _run("trainer.evaluate", "--checkpoint", str(ck), "--device", "cpu", "--h5", "x.h5")
    _assert_config_error(r, "v2v-eval", str(ck), "['num_bin']", "allowed keys:", "'num_bins'")
    r = _run("trainer.evaluate", "--checkpoint", str(tmp_path / "none.pt"), "--device", "cpu", "--h5", "x.h5")
    _assert_config_error(r, "v2v-eval", "checkpoint not found", "none.pt")


def test_v2v_serve_reads_the_same(tmp_path):
    cfg = tmp_path / "serve.yaml"
    cfg.write_text("nonidealities: {leak_hertz: 1}\n")
    r = _run("v2v_server.cli", "--config", str(cfg))
    _assert_config_error(r, "v2v-serve", str(cfg), "['leak_hertz']", "in nonidealities", "'leak_hz'")


@pytest.mark.parametrize("key, yaml, bound", [
    ("ranges.threshold", "ranges: {threshold: [0.1, 1.0e308]}", "above 10, the largest contrast threshold"),
    ("ranges.noise_std", "ranges: {noise_std: [0.0, 1.0e308]}", "above 10, the largest noise sigma"),
    ("nonidealities.threshold_sigma", "nonidealities: {threshold_sigma: 1.0e308}", "above 10, the largest threshold spread"),
])
def test_a_sensor_value_beyond_what_the_kernel_is_tested_at_is_refused_at_start(tmp_path, key, yaml, bound):
    """A recipe (hand-written or fitted) whose sensor range the simulation kernel is not tested at
    (tests/test_stability.py) stops the server at start with one line naming the key and the
    bound, instead of failing every file while serving: the same rule for serving and ``--check``,
    and for the recipe built in Python."""
    from v2v_server.ops.config import load_config

    cfg = tmp_path / "fit.yaml"
    cfg.write_text(yaml + "\n")
    for mode in (["--check"], []):
        r = _run("v2v_server.cli", "--config", str(cfg), "--bind", "tcp://127.0.0.1:0",
                 *mode,
                 timeout=120)
        _assert_config_error(r, "v2v-serve", str(cfg), f"{key}: 1e+308 is {bound}", "tested at")
    with pytest.raises(ValueError, match=rf"{key}: 1e\+308 is {bound}"):
        load_config(str(cfg))


def test_an_unknown_log_level_is_refused_not_read_as_info():
    from v2v_server.cli import build_parser

    with pytest.raises(SystemExit):
        build_parser().parse_args(["--log-level", "INFOO"])
    assert build_parser().parse_args(["--log-level", "debug"]).log_level == "DEBUG"

"""Declarative configuration (v2v_server/settings.py): flags derived from the models, YAML with
YAML 1.2 floats, field-named errors, and the reference page kept current."""
from __future__ import annotations

import argparse
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import pytest

from v2v_server.ops.config import SampleRecipe, ServeConfig, load_config
from v2v_server.settings import add_flags, documented, flag_values, load_yaml, reference_markdown, setting
from v2v_server.checks import check_choice, check_float, check_int, check_prob

ROOT = Path(__file__).resolve().parents[1]


@dataclass
class Demo:
    """Demo settings."""

    rate: float = setting(0.5, help="a rate")
    count: int = setting(3, help="a count", flag="--n")
    name: Optional[str] = setting(None, help="a name", choices=("a", "b"))
    on: bool = setting(True, help="a switch")
    table: dict = setting(help="YAML only", flag="", factory=dict)


def test_flags_come_from_the_model():
    p = argparse.ArgumentParser()
    add_flags(p, Demo)
    args = p.parse_args(["--rate", "0.25", "--n", "7", "--no-on"])
    assert flag_values(args, Demo) == {"rate": 0.25, "count": 7, "on": False}
    assert flag_values(p.parse_args([]), Demo) == {}  # nothing given: nothing overrides the file
    with pytest.raises(SystemExit):
        p.parse_args(["--name", "c"])
    with pytest.raises(SystemExit):
        p.parse_args(["--table", "x"])
    assert "(default 0.5)" in p.format_help()


def test_every_serve_key_is_a_flag_or_yaml_only_and_the_reference_lists_it():
    p = argparse.ArgumentParser()
    for _, part in ServeConfig.PARTS:
        add_flags(p, part)
    dests = {a.dest for a in p._actions}
    yaml_only = {"ranges", "nonidealities", "degrade_dynamic_range", "video_extensions", "storage_options"}
    names = {f.name for f in documented(ServeConfig)}
    assert names - dests == yaml_only
    md = reference_markdown(ServeConfig, [part for _, part in ServeConfig.PARTS])
    assert all(f"| `{n}` |" in md for n in names)


def test_docs_config_md_is_the_generated_reference():
    out = subprocess.run([sys.executable, "-m", "v2v_server.ops.config", "--markdown"], capture_output=True, text=True,
                         check=True, cwd=ROOT).stdout
    assert (ROOT / "docs" / "config.md").read_text() == out, "re-run: python -m v2v_server.ops.config --markdown > docs/config.md"


def test_yaml_floats_and_errors_name_the_file(tmp_path):
    f = tmp_path / "a.yaml"
    f.write_text("task_timeout_s: 1e2\nkeep_top_fraction: 5e-1\n")
    assert load_yaml(f) == {"task_timeout_s": 100.0, "keep_top_fraction": 0.5}
    cfg = load_config(str(f))
    assert cfg.task_timeout_s == 100.0 and cfg.keep_top_fraction == 0.5
    f.write_text("[1, 2]\n")
    with pytest.raises(ValueError, match="a.yaml: top level must be a mapping"):
        load_yaml(f)
    f.write_text("crop_size: 4\n")
    with pytest.raises(ValueError, match=r"a\.yaml: crop_size must be an integer >= 8"):
        load_config(str(f))
    f.write_text("crop_sise: 64\n")
    with pytest.raises(ValueError, match=r"a\.yaml: unknown key\(s\) \['crop_sise'\]"):
        load_config(str(f))
    with pytest.raises(FileNotFoundError):
        load_yaml(tmp_path / "missing.yaml")


def test_validators_name_the_field():
    assert check_int("n", 3, 1, 5) == 3
    for bad in (0, True, 2.0, 9):
        with pytest.raises(ValueError, match="^n must"):
            check_int("n", bad, 1, 5)
    assert check_float("x", 2) == 2.0
    with pytest.raises(ValueError, match="x must be a finite number > 0"):
        check_float("x", float("inf"))
    with pytest.raises(ValueError, match="p must be a probability"):
        check_prob("p", 1.5)
    with pytest.raises(ValueError, match=r"c must be one of \['a'\]"):
        check_choice("c", "b", ("a",))


def test_the_recipe_is_separate_from_serving():
    cfg = load_config(None, {"seed": 3, "workers": 1, "crop_size": 64})
    r = cfg.recipe
    assert type(r) is SampleRecipe and r.seed == 3 and r.crop_size == 64 and not hasattr(r, "workers")
    assert r.frames_per_sample == cfg.recipe.frames_per_sample == 201


def test_trainer_config_is_declared_once_and_its_reference_is_current():
    from trainer.config import DEFAULTS, TASK_SECTIONS, apply_overrides, default_config
    from trainer.tasks import TASKS

    assert set(TASK_SECTIONS) == set(TASKS) == set(DEFAULTS)
    cfg = default_config("e2vid")
    assert cfg["optim"]["lr"] == 1e-4 and cfg["loss"]["tc_alpha"] == 50.0 and cfg["stream"]["timeout_s"] == 60.0
    assert apply_overrides(cfg, ["optim.lr=3e-4"])["optim"]["lr"] == 3e-4  # YAML 1.2 float from the flag
    for bad, field in (("optim.lr=fast", "optim.lr"), ("log.progress=2", "log.progress"), ("amp=fp16", "amp")):
        with pytest.raises(ValueError, match=field):
            apply_overrides(cfg, [bad])
    out = subprocess.run([sys.executable, "-m", "trainer.config", "--markdown"], capture_output=True, text=True,
                         check=True, cwd=ROOT).stdout
    assert (ROOT / "docs" / "trainer_config.md").read_text() == out


def test_workers_get_the_recipe_only():
    import dataclasses
    import pickle

    from v2v_server.service.worker import worker_config

    cfg = load_config(None, {"seed": 7, "workers": 3, "crops_per_window": 2, "task_timeout_s": 5.0, "shot_cuts": "off",
                             "log_format": "json"})
    w = pickle.loads(pickle.dumps(worker_config(cfg)))  # as the spawned process receives it
    assert [f.name for f in dataclasses.fields(w)] == ["recipe", "log_format"] and w.log_format == "json"
    r = w.recipe
    assert type(r) is SampleRecipe and r == cfg.recipe and r.seed == 7 and r.crops_per_window == 2
    assert r.shot_cuts == r.windows.shot_cuts == "off" and not hasattr(r, "workers") and not hasattr(r, "task_timeout_s")


def test_each_recipe_key_is_declared_once():
    """The recipe composes the frames stage's settings: a key of ``WindowSettings`` or
    ``DecodeSettings`` is declared there only, and reads through the recipe and the config."""
    import dataclasses

    from v2v_server.frames.frame_pass import DecodeSettings
    from v2v_server.frames.windows import WindowSettings

    own = [f.name for f in dataclasses.fields(SampleRecipe) if "help" in f.metadata]
    parts = [f.name for part in (WindowSettings, DecodeSettings) for f in documented(part)]
    assert parts and not set(own) & set(parts)
    keys = [f.name for f in documented(ServeConfig)]
    assert len(keys) == len(set(keys)) and set(own) | set(parts) <= set(keys)
    cfg = load_config(None, {"shot_cuts": "off", "decode_fast": "all", "keep_top_fraction": 0.75, "seed": 2})
    assert (cfg.shot_cuts, cfg.recipe.shot_cuts, cfg.recipe.windows.shot_cuts) == ("off",) * 3
    assert cfg.decode_fast == cfg.recipe.decode.decode_fast == "all" and cfg.recipe.decode.keep_top_fraction == 0.75
    assert cfg.recipe.reads.decode is cfg.recipe.decode and cfg.recipe.reads.windows is cfg.recipe.windows
    with pytest.raises(ValueError, match="shot_cuts must be one of"):
        load_config(None, {"shot_cuts": "sometimes"})


def test_unknown_keys_anywhere_name_the_file_the_section_and_the_allowed_keys(tmp_path):
    f = tmp_path / "serve.yaml"
    for text, section, allowed in (("nonidealities: {leak_hertz: 1}\n", " in nonidealities", "'leak_hz'"),
                                   ("ranges: {treshold: [0.1, 0.2]}\n", " in ranges", "'threshold'"),
                                   ("degrade_dynamic_range: {prob: 1}\n", " in degrade_dynamic_range", "'probability'"),
                                   ("crop_sise: 64\n", "", "'crop_size'")):
        f.write_text(text)
        with pytest.raises(ValueError, match=rf"serve\.yaml: unknown key\(s\) \[.*\]{section}; allowed keys: \[.*"
                                             rf"{allowed}") as e:
            load_config(str(f))
        assert "\n" not in str(e.value)


def test_one_outputs_check_for_the_config_the_dataset_and_the_fetch():
    from v2v_client import V2VStreamDataset
    from v2v_wire.plan import PlanIdentity
    from v2v_wire.plan_messages import Fetch, WireError
    from v2v_wire.protocol import OUTPUTS, check_outputs

    def fetch(outputs):
        return Fetch.from_wire({**Fetch(1, 0, 0, 2, ("voxels",), PlanIdentity("m", "r", 0)).to_wire(),
                                "outputs": outputs})

    assert check_outputs("flow, voxels") == check_outputs(["flow", "voxels", "flow"]) == ("voxels", "flow")
    assert load_config(None, {"outputs": "frames,voxels"}).outputs == ("voxels", "frames")
    assert V2VStreamDataset("tcp://127.0.0.1:1", outputs=["flow", "frames"]).outputs == ("frames", "flow")
    assert fetch(["flow", "frames"]).outputs == ("frames", "flow")
    allowed = str(list(OUTPUTS)).replace("[", r"\[").replace("]", r"\]")
    for bad in ([], ["voxel"], ["voxels", 3], None):
        with pytest.raises(ValueError, match=f"^outputs must be a non-empty list from {allowed}"):
            check_outputs(bad)
        with pytest.raises(ValueError, match=f"^command line: outputs must be a non-empty list from {allowed}"):
            load_config(None, {"outputs": bad if bad is not None else []})
        with pytest.raises(ValueError, match=f"^outputs must be a non-empty list from {allowed}"):
            V2VStreamDataset("tcp://127.0.0.1:1", outputs=bad)
        with pytest.raises(WireError, match=f"^fetch: field 'outputs' must be a non-empty list from {allowed}"):
            fetch(bad)

"""``v2v-eval --protocol v2v-paper`` and ``--select-checkpoint`` (trainer/protocol.py): the
built-in sequence tables against the authors' repository (tests/data/v2v_paper_cuts.json,
derived by harness/paper_cuts.py), the cut, missing files, the table and the selection rule."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.trainer_fixtures import write_mvsec_like_h5
from trainer.config import default_config, merge
from trainer.core import Trainer
from trainer.evaluate import LPIPS_NOT_REPORTED, H5Sequence, main as eval_main
from trainer.models.lpips import STAND_IN
from trainer.protocol import (HQF_SEQUENCES, PAPER_CUTS, cut_sequence, evaluate_paper, paper_files, paper_markdown,
                              select_checkpoint)

REF = json.loads((Path(__file__).parent / "data" / "v2v_paper_cuts.json").read_text())


def test_cut_tables_equal_the_authors():
    for ds in ("ijrr", "mvsec", "evaid"):
        assert {k: list(v) for k, v in PAPER_CUTS[ds].items()} == REF["cuts"][ds], ds
        assert list(PAPER_CUTS[ds]) == REF["test_lists"][ds], ds  # the sequences they test on
    assert list(HQF_SEQUENCES) == REF["test_lists"]["hqf"]


def test_cut_keeps_the_images_in_the_window_and_their_events(tmp_path):
    p = tmp_path / "s.h5"
    write_mvsec_like_h5(p, image_dt=0.05, n_images=8, speed=100.0)  # images at 0, 0.05, ..., 0.35 s
    seq = cut_sequence(H5Sequence(str(p)), 0.1, 0.25)
    np.testing.assert_allclose(seq.image_ts, [0.1, 0.15, 0.2])
    assert seq.ts.min() >= 0.1 and seq.ts.max() <= 0.2 and seq.ts.size > 0
    seq = cut_sequence(H5Sequence(str(p)), 0.1, 0.25 - 0.05, inclusive_end=True)
    np.testing.assert_allclose(seq.image_ts, [0.1, 0.15, 0.2])
    with pytest.raises(ValueError, match="fewer than two images"):
        cut_sequence(H5Sequence(str(p)), 5, 6)


def test_missing_files_are_named_and_the_table_has_dataset_and_mean_rows(tmp_path):
    (tmp_path / "hqf").mkdir()
    (tmp_path / "ijrr").mkdir()
    write_mvsec_like_h5(tmp_path / "hqf" / "boxes.h5")
    write_mvsec_like_h5(tmp_path / "ijrr" / "slider_depth.h5", image_dt=0.5, n_images=8)
    present, missing = paper_files(str(tmp_path))
    assert [(d, n) for d, n, _, _ in present] == [("ijrr", "slider_depth"), ("hqf", "boxes")]
    assert str(tmp_path / "mvsec" / "indoor_flying1.h5") in missing and len(missing) == 7 + 6 + 14 + 11 - 2
    calls = []

    def score(path, cut, inclusive):
        calls.append((Path(path).stem, cut, inclusive))
        v = 0.1 if "slider" in str(path) else 0.3
        return {"mse": [v, v], "ssim": [1 - v] * 2, "lpips": [v / 2] * 2}

    r = evaluate_paper(score, str(tmp_path))
    assert calls == [("slider_depth", (1, 2.5), False), ("boxes", None, False)]
    assert r["datasets"]["ijrr"]["mse"] == pytest.approx(0.1) and r["datasets"]["hqf"]["sequences"] == 1
    assert r["mean"]["lpips"] == pytest.approx((0.05 + 0.15) / 2)
    md = paper_markdown(r)
    assert "| IJRR | 1 | 0.100 | 0.900 | 0.050 |" in md and "| mean |" in md and "Missing (skipped)" in md


def test_select_checkpoint_takes_the_lowest_mean_lpips_over_hqf_and_evaid(tmp_path):
    for name in ("checkpoint_0000100.pt", "checkpoint_0000200.pt", "checkpoint_0000300.pt", "checkpoint_last.pt"):
        (tmp_path / name).write_bytes(b"")
    lp = {"checkpoint_0000100.pt": (0.4, 0.5), "checkpoint_0000200.pt": (0.3, 0.45), "checkpoint_0000300.pt": (0.2, 0.6)}
    seen = []

    def evaluate_checkpoint(ck, datasets):
        seen.append((ck.name, tuple(datasets)))
        h, e = lp[ck.name]
        return {"datasets": {"hqf": {"lpips": h}, "evaid": {"lpips": e}}, "mean": {"lpips": (h + e) / 2}, "missing": []}

    sel = select_checkpoint(str(tmp_path), evaluate_checkpoint)
    assert Path(sel["selected"]).name == "checkpoint_0000200.pt"  # 0.375 < 0.4 < 0.45
    assert [s[0] for s in seen] == sorted(lp) and all(s[1] == ("hqf", "evaid") for s in seen)
    with pytest.raises(ValueError, match="LPIPS"):
        select_checkpoint(str(tmp_path), lambda ck, d: {"datasets": {"hqf": {}}, "mean": {"mse": 0.1}, "missing": []})
    with pytest.raises(ValueError, match="no checkpoint"):
        select_checkpoint(str(tmp_path / "empty"), evaluate_checkpoint)


def test_cli_protocol_on_a_checkpoint(tmp_path, capsys):
    cfg = merge(default_config("e2vid"), {"model": {"num_bins": 5, "base_num_channels": 4}})
    t = Trainer(cfg, str(tmp_path / "run"), torch.device("cpu"))
    ck = t.save_checkpoint()
    (tmp_path / "data" / "hqf").mkdir(parents=True)
    write_mvsec_like_h5(tmp_path / "data" / "hqf" / "desk.h5")
    rc = eval_main(["--checkpoint", str(ck), "--protocol", "v2v-paper", "--data-root", str(tmp_path / "data"),
                    "--out", str(tmp_path / "out"), "--device", "cpu"])
    assert rc == 0
    out = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert list(out["datasets"]) == ["hqf"] and out["per_sequence"]["hqf/desk"]["frames"] == 7
    assert str(tmp_path / "data" / "evaid" / "ball.h5") in out["missing"]
    table = (tmp_path / "out" / "paper_table.md").read_text()
    assert "| HQF | 1 |" in table
    # trained and scored without LPIPS weights: both recorded in the JSON and the table
    assert t.perceptual_term == STAND_IN and torch.load(ck, weights_only=False)["perceptual_term"] == STAND_IN
    assert out["trained_perceptual_term"] == STAND_IN and out["lpips_metric"] == LPIPS_NOT_REPORTED
    assert out["format"] == "v2v-train" and STAND_IN in table and LPIPS_NOT_REPORTED in table


def test_cli_protocol_scores_the_authors_e2vid_plus_plus_checkpoint(tmp_path):
    """``v2v-eval --checkpoint their.pth --model e2vid++`` (a state dict with the keys and shapes
    of their FlowNet, tests/data/zoo_reference.json) scores the baseline row."""
    ref = json.loads((Path(__file__).parent / "data" / "zoo_reference.json").read_text())
    g = torch.Generator().manual_seed(0)
    sd = {"_orig_mod." + k: torch.randn(shape, generator=g) * 0.01 for k, shape in ref["e2vid++"]["state_dict"].items()}
    torch.save({"state_dict": sd}, tmp_path / "reconstruction_model_state_dict.pth")
    (tmp_path / "data" / "hqf").mkdir(parents=True)
    write_mvsec_like_h5(tmp_path / "data" / "hqf" / "desk.h5")
    rc = eval_main(["--checkpoint", str(tmp_path / "reconstruction_model_state_dict.pth"), "--model", "e2vid++",
                    "--protocol", "v2v-paper", "--data-root", str(tmp_path / "data"), "--out", str(tmp_path / "out"),
                    "--device", "cpu"])
    assert rc == 0
    out = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert out["format"] == "authors:e2vid++" and out["trained_perceptual_term"] == "authors' release"
    assert out["per_sequence"]["hqf/desk"]["frames"] == 7 and np.isfinite(out["mean"]["mse"])
    assert (tmp_path / "out" / "paper_table.md").read_text().startswith("**e2vid++ reconstruction_model")
    with pytest.raises(SystemExit):  # their checkpoint named as another network
        eval_main(["--checkpoint", str(tmp_path / "reconstruction_model_state_dict.pth"), "--model", "etnet",
                   "--protocol", "v2v-paper", "--data-root", str(tmp_path / "data"), "--device", "cpu"])


def test_require_lpips_refuses_to_score_without_weights(tmp_path, caplog):
    rc = eval_main(["--checkpoint", str(tmp_path / "x.pt"), "--protocol", "v2v-paper", "--data-root",
                    str(tmp_path), "--require-lpips", "--device", "cpu"])
    assert rc == 2 and "--require-lpips: no LPIPS (Alex) weights" in caplog.text

"""``bench/calibrate.py`` at its smallest: the fit from frames and both fits by statistics run, and
the tables name every statistic with the recording, default and fitted columns."""
from __future__ import annotations

import json

from bench.calibrate import main
from trainer.calibrate_fit import CORPUS_STATS, FRAME_STATS


def test_calibrate_bench_reports_every_statistic(tmp_path, capsys):
    assert main(["--evaluations", "12", "--epochs", "1", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "calibrate.json").read_text())
    assert res["command"] == "python -m bench.calibrate --evaluations 12 --epochs 1"
    fr = res["frames"]
    assert set(fr["fitted_other_draws"]) == set(FRAME_STATS) and fr["simulations"] <= 12 + 5 and fr["seconds"] > 0
    assert [r["recording"] for r in res["corpus"]] == ["davis346_road.aedat4", "prophesee_evk4_evt3.raw"]
    for row in res["corpus"]:
        assert set(row["default"]) == set(row["fitted"]) == set(CORPUS_STATS) and row["samples"] == 24 and row["windows"] == 48
    md = (tmp_path / "calibrate.md").read_text()
    assert md.count("| rate_net |") == 2 and "| corr |" in md and "fitted / rec" in md

"""The documented speed / accuracy command (``python -m bench.tradeoff``, docs/fidelity.md) on a
tiny crop of a real clip: it runs, and its rows say what the docs claim of them."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_tradeoff_command_writes_table_json_and_plot(tmp_path, videos):
    out = subprocess.run([sys.executable, "-m", "bench.tradeoff", "--out", str(tmp_path), "--videos", str(videos),
                          "--clips", "bikes.mp4", "--crop", "48", "--voxels", "1", "--bins", "2", "--repeat", "1",
                          "--lambdas", "4", "--dl-lambdas", "1"], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    data = json.loads((tmp_path / "tradeoff.json").read_text())
    rows = {r["name"]: r for r in data["mean"]}
    assert rows["V2V (every frame), int8 wire"]["speed_vs_v2v"] == 1.0
    # more refinement with the reference's own flow preset gets closer to the reference
    assert rows["uniform:4 (medium)"]["nl1"] < rows["V2V (every frame), int8 wire"]["nl1"]
    assert rows["V2V, 1/4 frames"]["nl1"] >= rows["V2V (every frame), int8 wire"]["nl1"]
    claim = data["results"]["bikes.mp4"]["claim"]
    assert claim["c+ = c-"]["linear_reference_cells_differ"] == 0 == claim["c+ != c-"]["linear_reference_cells_differ"]
    assert claim["c+ = c-"]["max_abs_cumulative_diff"] <= 1
    assert "| reference" in (tmp_path / "tradeoff.md").read_text()
    pytest.importorskip("matplotlib")
    assert (tmp_path / "pareto.png").stat().st_size > 1000

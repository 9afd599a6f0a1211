"""``bench/gpu_feed.py`` in its CPU smoke mode: a live v2v-serve on this host, the cached and
live runs of one model in float32 and bf16, and the table and JSON it writes."""
from __future__ import annotations

import json
import math

from bench.gpu_feed import main


def test_gpu_feed_smoke_run(tmp_path, videos):
    assert main(["--smoke", "--models", "evflow", "--amp", "fp32,bf16", "--workers", "1", "--steps", "2",
                 "--warmup", "1", "--videos", str(videos), "--device", "cpu", "--out", str(tmp_path)]) == 0
    out = json.loads((tmp_path / "gpu_feed.json").read_text())
    assert out["sizes"]["batch"] == 2 and [(r["model"], r["amp"]) for r in out["rows"]] == [("evflow", "fp32"),
                                                                                           ("evflow", "bf16")]
    for r in out["rows"]:
        for run in ("cached", "live"):
            m = r[run]
            assert m["steps_per_s"] > 0 and math.isclose(m["samples_per_s"], 2 * m["steps_per_s"])
            assert 0 <= m["data_wait_fraction"] < 1 and m["peak_mem_gib"] is None  # no GPU memory on a CPU
        assert r["workers_needed"] == "<= 1" or r["workers_needed"] >= 1
    table = (tmp_path / "gpu_feed.md").read_text()
    assert table.count("| evflow |") == 2 and "cpu (smoke: toy sizes)" in table

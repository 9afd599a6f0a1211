"""``bench/frame_scale.py`` on tiny sources: every row measured, the cache bytes those of the
kept region at each size, and the report written (markdown and JSON)."""
from __future__ import annotations

import json
import math

from bench.frame_scale import main


def test_frame_scale_bench_writes_its_report(tmp_path):
    assert main(["--sizes", "64x36,128x72", "--frames", "12", "--height", "40", "--threads", "1,2",
                 "--threads-from", "72", "--rounds", "1", "--min-cpu-s", "0.02", "--out", str(tmp_path)]) == 0
    r = json.loads((tmp_path / "frame_scale.json").read_text())
    assert [row["size"] for row in r["rows"]] == ["64x36", "128x72"]
    for row in r["rows"]:
        assert row["decode_fps_cpu"] > 0 and row["decode_scaled_fps_cpu"] > 0 and row["scale_ms"] > 0
        assert row["decode_scaled_whole_fps_cpu"] > 0 and row["scale_whole_ms"] > 0  # the whole-frame baseline
        # a raw entry holds the kept 54 % of each frame, a little more for its framing
        kept = row["width"] * math.floor(row["height"] * 0.54)
        assert kept <= row["cache_bytes_per_frame"] < kept * 1.1 + 256
        scaled = round(row["width"] * 40 / row["height"]) * math.floor(40 * 0.54)
        assert scaled <= row["cache_bytes_per_frame_scaled"] < scaled * 1.1 + 256
    assert [(t["size"], t["threads"]) for t in r["threads"]] == [("128x72", 1), ("128x72", 2)]
    assert all(t["fps_cpu"] > 0 and t["fps_wall"] > 0 for t in r["threads"])
    md = (tmp_path / "frame_scale.md").read_text()
    assert "python -m bench.frame_scale --sizes 64x36,128x72" in md
    assert "| 128x72 | 2 |" in md and "`frame_height: 40` caches" in md
    assert r["keep"] == 0.54 and "Scaling only the kept rows against scaling the whole frame" in md
    assert len([ln for ln in md.splitlines() if ln.startswith(("| 64x36 |", "| 128x72 |"))]) == 2 + 2 + 2

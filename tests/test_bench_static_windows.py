"""``bench/static_windows.py`` at its smallest: a still picture measures 0 and is static, every
pan and the bundled clips move, and the meter's cost is reported."""
from __future__ import annotations

import json

from bench.static_windows import SPEEDS, main


def test_static_windows_bench_separates_still_from_moving(tmp_path, capsys):
    out = tmp_path / "static.json"
    assert main(["--photos", "1", "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    mats = r["materials"]
    assert mats["still"]["static"] == mats["still"]["windows"] == 4 and mats["still"]["motion_min_max"][1] < 1e-4
    for name in ["still + sensor noise", "bundled clips"] + [f"pan {s:g} px/frame" for s in SPEEDS]:
        assert mats[name]["static"] == 0 and mats[name]["motion_min_max"][0] > r["static_motion"], name
    assert set(r["meter_us_per_frame"]) == {"596x181", "1920x583"} and all(v > 0 for v in r["meter_us_per_frame"].values())
    assert "| still | 4 |" in capsys.readouterr().out

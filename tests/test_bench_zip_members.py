"""``bench/zip_members.py`` on one clip: every mode measured, the bytes a stored member reads
about its size, a deflated one's twice with ``moov`` last and once with it first, and the
report written (markdown and JSON)."""
from __future__ import annotations

import json

from bench.zip_members import main


def test_zip_members_bench_writes_its_report(tmp_path):
    assert main(["--repeat", "1", "--clips", "bikes.mp4", "--out", str(tmp_path)]) == 0
    r = json.loads((tmp_path / "zip_members.json").read_text())
    assert [(row["clip"], row["layout"]) for row in r["rows"]] == [("bikes.mp4", "moov last"),
                                                                   ("bikes.mp4", "moov first")]
    for row in r["rows"]:
        assert row["frames"] == 250 and all(row[f"{m}_cpu_s"] > 0 for m in ("file", "stored", "deflated"))
        assert 1.0 <= row["stored_read_per_byte"] < 1.2 and row["deflated_read_ms"] > 0
    assert [round(row["deflated_read_per_byte"], 2) for row in r["rows"]] == [2.0, 1.0]
    md = (tmp_path / "zip_members.md").read_text()
    assert "python -m bench.zip_members --repeat 1 --clips bikes.mp4" in md and "| bikes.mp4 | moov first | 250 |" in md

"""``bench/sample_cost.py``: a worker's CPU per sample split into simulation, flow and the rest,
against the decode bound of the same run, on the bundled WebVid-like clip (one round)."""
from __future__ import annotations

from bench.sample_cost import measure
from bench.speed import clip_path


def test_sample_cost_splits_a_workers_time():
    r = measure(clip_path(), videos=1, rounds=1)
    assert r["bound"] > 0
    assert set(r["rows"]) == {1, 4}
    for crops, m in r["rows"].items():
        assert m["simulate"] > 0 and m["flow"] > 0 and 0 < m["rest"] < m["total"]
        assert m["ceiling"] > m["share"] > 0
        assert 0 < m["stats"] < m["simulate"]  # the statistics are timed, and cost less than the simulation
    # four crops share one window's decoding: less CPU per sample, a larger share of it simulating
    one, four = r["rows"][1], r["rows"][4]
    assert four["total"] < one["total"] and four["simulate"] / four["total"] > one["simulate"] / one["total"]
    # FFmpeg's grayscale flag never changes the luma (it may or may not skip chroma)
    assert r["gray"]["identical"] and r["gray"]["speed"] > 0

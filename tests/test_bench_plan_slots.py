"""``bench/plan_slots.py`` on one bundled clip: its packet bound holds the windows a full decode
keeps, with and without shot cuts, the corpus's padding is made of its rows, and the index the
decode filled answers the same counts; ``WindowSettings.slots_at_most`` is the bound it uses."""
from __future__ import annotations

import pytest

from bench.plan_slots import measure, padding
from harness.data import SAMPLE_VIDEOS
from v2v_server.samples.recipe import SampleRecipe

#: 41-frame windows: bikes.mp4 (250 frames, cuts at 30, 76, 137, 187, 242) holds several.
SHORT = {"sequence_length": 8}


@pytest.mark.parametrize("keys", [SHORT, {**SHORT, "shot_cuts": "off"}, {**SHORT, "crops_per_window": 3}])
def test_the_packet_bound_holds_the_decoded_windows_of_a_bundled_clip(tmp_path, keys):
    m = measure(SAMPLE_VIDEOS, keys, tmp_path / "cache", ["bikes.mp4"])
    (row,) = m["rows"]
    crops = keys.get("crops_per_window", 1)
    assert row["packets"] == row["frames"] == 250 and not row["more"]
    assert row["bound"] == 6 * crops  # (250 - 1) // 40 windows
    assert 0 < row["windows"] <= row["bound"] and not row["over"] and m["over"] == []
    if keys.get("shot_cuts") == "off":
        assert row["windows"] == row["bound"]  # no cut, no padding: frames = packets here
    else:
        assert row["cuts"] == 5 and row["windows"] < row["bound"]  # shots of 46-61 frames hold one window each
    assert (m["bound"], m["windows"]) == (row["bound"], row["windows"])
    assert m["padding"] == pytest.approx(padding(m["bound"], m["windows"]), abs=1e-4)
    assert m["padding"] == pytest.approx((row["bound"] - row["windows"]) / row["bound"], abs=1e-4)
    assert (m["index_known"], m["index_windows"]) == (1, m["windows"])


def test_slots_at_most_counts_whole_strides_times_crops():
    w = SampleRecipe().windows  # 201 frames, stride 200, at most 10
    assert [w.slots_at_most(n) for n in (0, 200, 201, 400, 401, 2001, 10 ** 6)] == [0, 0, 1, 1, 2, 10, 10]
    assert w.slots_at_most(401, crops_per_window=4) == 8
    assert SampleRecipe(shot_cuts="off").windows.slots_at_most(401) == w.slots_at_most(401)
    with pytest.raises(ValueError, match="frames"):
        w.slots_at_most(-1)
    with pytest.raises(ValueError, match="crops_per_window"):
        w.slots_at_most(401, 0)


def test_padding_is_the_empty_share_of_the_bound():
    assert padding(10, 7) == pytest.approx(0.3) and padding(0, 0) == 0.0 and padding(4, 4) == 0.0

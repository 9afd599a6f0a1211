"""trainer/grid_stats.py: the same-grid statistics, on hand-made counts and on the DAVIS346 recording
(its cells hold exactly its events of the time they cover)."""
from __future__ import annotations

import numpy as np
import pytest

from harness.data import DAVIS346
from trainer.grid_stats import cell_stats, recording_cells, summarise, voxel_cell_stats
from trainer.recordings import open_recording, read_all


def test_cell_stats_by_hand():
    pos = np.zeros((1, 2, 4, 5), np.int32)
    neg = np.zeros_like(pos)
    pos[0, 0, 1, 1] = 3  # a pixel firing 3 ON then 1 OFF in one bin: signal 4, net 2
    neg[0, 0, 1, 1] = 1
    pos[0, 1, 1, 2] = 2  # its neighbour: not isolated
    neg[0, 1, 3, 4] = 1  # alone in its corner: isolated
    (c,) = cell_stats(pos, neg, 0.5)
    assert c["rate_signal"] == pytest.approx(7 / 20 / 0.5) and c["rate_net"] == pytest.approx(5 / 20 / 0.5)
    assert c["active_fraction"] == pytest.approx(3 / 20) and c["polarity_balance"] == pytest.approx(5 / 7)
    assert c["events_per_active"] == pytest.approx(7 / 3) and c["still_rate"] == pytest.approx(1 / 20 / 0.5)
    (empty,) = cell_stats(np.zeros_like(pos), np.zeros_like(neg), 0.5)
    assert empty["rate_signal"] == 0 and empty["polarity_balance"] is None and empty["events_per_active"] is None
    assert summarise([c, empty])["polarity_balance"] == {"n": 1, "median": c["polarity_balance"],
                                                          "p10": c["polarity_balance"], "p90": c["polarity_balance"],
                                                          "mean": c["polarity_balance"]}
    with pytest.raises(ValueError, match="cell_s"):
        cell_stats(pos, neg, 0)


def test_voxel_cells_split_signed_counts():
    vox = np.zeros((2, 1, 3, 3), np.int8)
    vox[0, 0, 0, 0], vox[0, 0, 2, 2] = 2, -1
    a, b = voxel_cell_stats(vox, 0.2)
    assert a["rate_signal"] == a["rate_net"] == pytest.approx(3 / 9 / 0.2) and a["polarity_balance"] == pytest.approx(2 / 3)
    assert a["still_rate"] == a["rate_signal"] and b["active_fraction"] == 0


def test_recording_cells_hold_the_recordings_events():
    rec = open_recording(DAVIS346)
    cells = list(recording_cells(rec.chunks(), rec.width, rec.height, 200_000, 5))
    assert len(cells) == 11  # 2.36 s of events: 11 whole cells of 0.2 s
    ev = read_all(rec)
    t0 = int(ev["t"][0])
    inside = ev[ev["t"] < t0 + 11 * 200_000]
    assert sum(int(p.sum()) for p, _ in cells) == int(np.count_nonzero(inside["p"] > 0))
    assert sum(int(n.sum()) for _, n in cells) == int(np.count_nonzero(inside["p"] < 0))
    # bin 2 of cell 3 holds the events of [t0 + 0.68 s, t0 + 0.72 s)
    k = (inside["t"] >= t0 + 680_000) & (inside["t"] < t0 + 720_000)
    assert int(cells[3][0][0, 2].sum() + cells[3][1][0, 2].sum()) == int(k.sum())
    s = summarise([c for p, n in cells for c in cell_stats(p, n, 0.2)])
    # the DAVIS346 road scene (issue 64): 0.30 net events / pixel / s, 1.5 % of pixels active per 0.2 s
    assert s["rate_net"]["median"] == pytest.approx(0.30, abs=0.01)
    assert s["active_fraction"]["median"] == pytest.approx(0.0155, abs=0.001)


def test_a_samples_grid_duration_comes_from_its_params():
    """Two frame pairs a bin: a voxel grid spans 10 frame intervals (0.4 s at 25 fps), read from the
    sample's own params (what a server's samples carry), with no recipe given."""
    import dataclasses

    from harness.data import SAMPLE_VIDEOS
    from trainer.stream_stats import sample_row
    from v2v_server.samples.make import video_samples
    from v2v_server.samples.recipe import SampleRecipe
    from v2v_server.sources.source_spec import open_source

    recipe = dataclasses.replace(SampleRecipe(), sequence_length=4, frames_per_bin=2, max_samples_per_video=1)
    _key, arrays, meta = next(iter(video_samples(recipe, open_source(SAMPLE_VIDEOS), "bikes.mp4", 0, ("voxels",))))
    row = sample_row(meta, arrays["voxels"])
    vox = arrays["voxels"].astype(np.int64)
    assert meta["video_fps"] == 25 and len(row["cells"]) == 4
    for cell, grid in zip(row["cells"], vox):
        assert cell["rate_net"] * grid[0].size * 0.4 == pytest.approx(np.abs(grid).sum())

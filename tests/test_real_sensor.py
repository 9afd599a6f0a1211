"""bench.real_sensor: its metrics on known cases and its threshold fit on the DAVIS346 recording
shipped in tests/data/events."""
from __future__ import annotations

import numpy as np
import pytest

from bench.real_sensor import DEFAULT, GROUP, fit_thresholds, metrics, real_and_frames
from trainer.event_grids import voxel_grids
from v2v_server.simulation.simulate import SensorParams, simulate_voxels


@pytest.fixture(scope="module")
def recording():
    """``real_and_frames`` of the DAVIS346 recording."""
    return real_and_frames(DEFAULT)


def test_metrics_on_known_cases():
    rng = np.random.default_rng(0)
    real = rng.integers(-2, 3, size=(10, 8, 8))
    moving = np.abs(real) > 1
    same = metrics(real, real, moving, int(np.abs(real).sum()), int(np.abs(real).sum()))
    assert same["corr"] == pytest.approx(1) and same["corr_moving"] == pytest.approx(1)
    assert same["corr_5bin_sum"] == pytest.approx(1) and same["sign_agree"] == 1 and same["nl1"] == 0
    assert same["n_ratio"] == 1
    flipped = metrics(-real, real, moving, 1, 1)
    assert flipped["corr"] == pytest.approx(-1) and flipped["sign_agree"] == 0 and flipped["nl1"] == pytest.approx(2)
    zero = metrics(np.zeros_like(real), real, moving, 1, 0)
    assert np.isnan(zero["corr"]) and np.isnan(zero["sign_agree"]) and zero["nl1"] == 1


def test_threshold_fit_matches_the_sensor_event_counts(recording):
    frames, real, n_pos, n_neg, ts, rec = recording
    assert frames.shape == (56, 260, 346) and real.shape == (55, 260, 346) and n_pos + n_neg == 72741
    assert np.all(np.abs(np.diff(ts) - 40000) <= 1)
    cp, cn = fit_thresholds(frames, n_pos, n_neg)
    pot = np.random.default_rng(0).uniform(-cn, cp, frames.shape[1:])
    _, _, (sp, sn) = simulate_voxels(frames, SensorParams(cp, cn), 1, initial_potential=pot, split=True)
    assert sp.sum() == pytest.approx(n_pos, rel=0.03) and sn.sum() == pytest.approx(n_neg, rel=0.03)


def test_one_pass_gives_the_polarity_counts_and_the_5_bin_grids_sums(recording):
    """``real_and_frames``'s N+ and N- (from one pass through ``voxel_grids``) are the
    recording's polarities counted between the first and last frame, and its per-interval grids
    summed 5 at a time are the paper's 5-bin grids summed over their bins (``corr 5-bin sum``)."""
    frames, real, n_pos, n_neg, ts, rec = recording
    p = np.concatenate([ev["p"] for ev in rec.chunks(int(ts[0]), int(ts[-1]))])
    assert (n_pos, n_neg) == (int((p > 0).sum()), int((p < 0).sum()))
    edges = ts[::GROUP]
    grouped = np.stack([v for _, v, _ in voxel_grids(rec.chunks(int(edges[0]), int(edges[-1])), edges, GROUP,
                                                     rec.height, rec.width)]).astype(np.int64)
    assert grouped.shape == (len(edges) - 1, GROUP, rec.height, rec.width)
    assert np.array_equal(grouped.sum(1), real.reshape(-1, GROUP, *real.shape[1:]).sum(1))

"""bench.real_sensor: its metrics on known cases and its threshold fit on the DAVIS346 recording
(skipped, naming the file, when ../shared/data/events is absent)."""
from __future__ import annotations

import numpy as np
import pytest

from bench.real_sensor import DEFAULT, fit_thresholds, metrics, real_and_frames
from v2v_server.simulation.simulate import SensorParams, simulate_voxels


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


def test_threshold_fit_matches_the_sensor_event_counts():
    if not DEFAULT.is_file():
        pytest.skip(f"missing shared recording {DEFAULT}")
    frames, real, n_pos, n_neg, ts, rec = real_and_frames(DEFAULT)
    assert frames.shape == (56, 260, 346) and real.shape == (55, 260, 346) and n_pos + n_neg == 72741
    assert np.all(np.abs(np.diff(ts) - 40000) <= 1)
    cp, cn = fit_thresholds(frames, n_pos, n_neg)
    pot = np.random.default_rng(0).uniform(-cn, cp, frames.shape[1:])
    _, _, (sp, sn) = simulate_voxels(frames, SensorParams(cp, cn), 1, initial_potential=pot, split=True)
    assert sp.sum() == pytest.approx(n_pos, rel=0.03) and sn.sum() == pytest.approx(n_neg, rel=0.03)

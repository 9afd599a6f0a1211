"""Sensor non-idealities: each off by default, each with its measurable effect."""
from __future__ import annotations

import math

import numpy as np
import pytest

from tests.conftest import read_luma_clip
from v2v_server.simulation.nonideal import NonIdealities, draw_pixel_state, effective_noise, simulate_voxels_nonideal
from v2v_server.simulation.simulate import SensorParams, simulate_voxels

STATIC = np.full((101, 40, 50), 120, np.uint8)  # 100 frame pairs of a static scene


def run(ni, frames=STATIC, params=SensorParams(0.2, 0.2), fps=25.0, seed=0, bins=5):
    return simulate_voxels_nonideal(frames, params, bins, NonIdealities.from_dict(ni), fps=fps,
                                    initial_potential=np.zeros(frames.shape[1:]), rng=np.random.default_rng(seed))


def test_all_off_is_plain_v2v():
    clip = read_luma_clip("bikes.mp4", 11, (48, 64))
    p = SensorParams(0.1, 0.15, 0.05)
    a, pa = simulate_voxels(clip, p, 5, rng=np.random.default_rng(1))
    b, pb, info = simulate_voxels_nonideal(clip, p, 5, NonIdealities(), fps=30.0, rng=np.random.default_rng(1))
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(pa, pb)
    assert not NonIdealities().enabled and NonIdealities.from_dict(None) == NonIdealities()
    assert info["events"] == np.abs(a).sum()


def test_from_dict_rejects_unknown_and_bad_values():
    with pytest.raises(ValueError, match="shot_noise_rate"):
        NonIdealities.from_dict({"shot_noise_rate": 1.0})
    with pytest.raises(ValueError, match="nonidealities.leak_hz"):
        NonIdealities.from_dict({"leak_hz": -1})
    with pytest.raises(ValueError, match="nonidealities.dead_fraction"):
        NonIdealities.from_dict({"dead_fraction": 1.5})
    with pytest.raises(ValueError, match="nonidealities.refractory_max_events"):
        NonIdealities.from_dict({"refractory_max_events": 2.5})
    with pytest.raises(ValueError, match="nonidealities.noise_mode"):
        NonIdealities.from_dict({"noise_mode": "per_hour"})
    ni = NonIdealities.from_dict({"leak_hz": 0.5, "noise_mode": "per_second"})
    assert NonIdealities.from_dict(ni.to_dict()) == ni and ni.enabled


def test_threshold_mismatch_spreads_per_pixel_counts():
    st = draw_pixel_state(NonIdealities(threshold_sigma=0.03), SensorParams(0.2, 0.3), (100, 100),
                          np.random.default_rng(0))
    assert st.pos_threshold.std() == pytest.approx(0.03, rel=0.05)
    assert st.pos_threshold.mean() == pytest.approx(0.2, abs=0.002)
    assert st.neg_threshold.mean() == pytest.approx(0.3, abs=0.002)
    ramp = np.linspace(30, 250, 21).astype(np.uint8)[:, None, None] * np.ones((1, 30, 30), np.uint8)
    plain, _, _ = run({}, ramp, SensorParams(0.05, 0.05))
    ni = NonIdealities(threshold_sigma=0.01)
    st = draw_pixel_state(ni, SensorParams(0.05, 0.05), (30, 30), np.random.default_rng(1))
    mis, _, _ = simulate_voxels_nonideal(ramp, SensorParams(0.05, 0.05), 5, ni, fps=25.0, pixel_state=st,
                                         initial_potential=np.zeros((30, 30)))
    assert plain.sum(axis=(0, 1)).std() == 0  # every pixel sees the same ramp
    # each pixel fires floor(total log change / its own c+) ON events
    from v2v_server.simulation.reference import log_frames

    total = log_frames(ramp[-1:])[0] - log_frames(ramp[:1])[0]
    np.testing.assert_array_equal(mis.sum(axis=(0, 1)), np.floor(total / st.pos_threshold))


def test_shot_noise_rate_in_hz():
    vox, _, info = run({"shot_noise_hz": 5.0}, fps=25.0)  # 100 pairs = 4 s -> 20 events / pixel
    per_pixel = info["events"] / (40 * 50)
    assert per_pixel == pytest.approx(20, rel=0.05)
    assert abs(vox.sum()) < 4 * math.sqrt(info["events"])  # random polarity


def test_leak_events_at_rate_are_on_events():
    vox, _, info = run({"leak_hz": 2.0}, fps=20.0)  # 5 s -> 10 ON events per pixel
    tot = vox.sum(axis=(0, 1))
    assert (vox >= 0).all() and np.abs(tot - 10).max() <= 1


def test_refractory_cap_bounds_counts_and_keeps_residual_in_range():
    flick = np.zeros((21, 8, 8), np.uint8)
    flick[1::2] = 255
    p = SensorParams(0.05, 0.05)
    vox, pot, info = run({"refractory_max_events": 3}, flick, p)
    assert np.abs(vox).max() == 3
    assert info["events_lost_refractory"] > 0
    assert pot.min() >= -0.05 - 1e-6 and pot.max() <= 0.05 + 1e-6


def test_dead_and_stuck_pixels():
    clip = read_luma_clip("bikes.mp4", 21, (48, 64))
    ni = NonIdealities(dead_fraction=0.1, stuck_fraction=0.05, stuck_rate_hz=10.0)
    st = draw_pixel_state(ni, SensorParams(0.1, 0.1), (48, 64), np.random.default_rng(5))
    vox, _, _ = simulate_voxels_nonideal(clip, SensorParams(0.1, 0.1), 5, ni, fps=20.0, pixel_state=st,
                                         rng=np.random.default_rng(5))
    assert st.dead.mean() == pytest.approx(0.1, abs=0.02)
    assert not vox[:, :, st.dead].any()
    stuck = st.stuck != 0
    assert stuck.mean() == pytest.approx(0.05 * 0.9, abs=0.015)
    tot = vox[:, :, stuck].sum(axis=(0, 1))
    np.testing.assert_array_equal(np.sign(tot[tot != 0]), st.stuck[stuck][tot != 0])
    assert np.abs(tot).mean() == pytest.approx(10.0, rel=0.15)  # 1 s at 10 Hz


def test_fps_aware_noise_keeps_noise_per_second():
    """per_frame: the net noise count after 1 s grows with sqrt(fps); per_second: it does not."""
    p = SensorParams(0.05, 0.05, 0.1)
    stds = {}
    for mode in ("per_frame", "per_second"):
        for fps in (30, 120):
            frames = np.full((fps + 1, 40, 40), 100, np.uint8)
            vox, _, _ = run({"noise_mode": mode, "noise_reference_fps": 30.0}, frames, p, fps=float(fps),
                            bins=1) if mode == "per_second" else (
                simulate_voxels(frames, p, 1, initial_potential=np.zeros((40, 40)), rng=np.random.default_rng(0))
                + (None,))
            stds[mode, fps] = vox.sum(axis=(0, 1)).std()
    assert stds["per_frame", 120] / stds["per_frame", 30] == pytest.approx(2.0, rel=0.1)
    assert stds["per_second", 120] / stds["per_second", 30] == pytest.approx(1.0, rel=0.1)
    hp = SensorParams(0.1, 0.1, 0.2, np.ones((2, 2)))
    s, h = effective_noise(hp, NonIdealities(noise_mode="per_second", noise_reference_fps=30.0), 120.0)
    assert s == pytest.approx(0.1) and h.max() == pytest.approx(0.25)

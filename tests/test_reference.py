"""Event-level reference simulator, voxel grids from events, and the paper's V2V claim."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from tests.conftest import read_luma_clip
from v2v_server.simulation.reference import (
    Events,
    events_to_voxels,
    interpolate_pair,
    log_frames,
    simulate_events,
    voxel_discrete,
    voxel_interpolated,
)
from v2v_server.simulation.simulate import SensorParams, simulate_voxels

SHAPE = (64, 80)


@pytest.fixture(scope="module")
def clip():
    return read_luma_clip("bikes.mp4", 21, SHAPE)


def _ev(x, y, t, p):
    return Events(np.array(x, np.int32), np.array(y, np.int32), np.array(t, float), np.array(p, np.int8))


def test_voxel_grids_follow_the_paper_definitions():
    # B = 4 over [0, 1] s; events at normalised t = 0, 0.3, 0.5, 0.74, 1.0
    ev = _ev([0, 0, 1, 1, 2], [0, 0, 0, 0, 0], [0.0, 0.3, 0.5, 0.74, 1.0], [1, 1, -1, 1, -1])
    d = voxel_discrete(ev, 4, (1, 3), 0.0, 1.0)
    assert d.dtype == np.int32 and d.shape == (4, 1, 3)
    np.testing.assert_array_equal(d[:, 0, 0], [1, 1, 0, 0])  # 0 -> bin 0, 0.3 -> bin 1
    np.testing.assert_array_equal(d[:, 0, 1], [0, 0, -1 + 1, 0])  # 0.5 and 0.74 -> bin 2
    np.testing.assert_array_equal(d[:, 0, 2], [0, 0, 0, -1])  # t = 1 counts in the last bin
    v = voxel_interpolated(ev, 4, (1, 3), 0.0, 1.0)
    # (B-1) t = 0 -> bin 0; 0.9 -> 0.1 / 0.9 split between bins 0 / 1
    np.testing.assert_allclose(v[:, 0, 0], [1 + 0.1, 0.9, 0, 0], atol=1e-6)
    # 1.5 -> -0.5 / -0.5 on bins 1, 2; 2.22 -> 0.78 / 0.22 on bins 2, 3
    np.testing.assert_allclose(v[:, 0, 1], [0, -0.5, -0.5 + 0.78, 0.22], atol=1e-6)
    np.testing.assert_allclose(v[:, 0, 2], [0, 0, 0, -1], atol=1e-6)
    # events outside the span are ignored; both grids conserve the summed polarity
    late = _ev([0], [0], [1.5], [1])
    assert voxel_discrete(late, 4, (1, 3), 0.0, 1.0).sum() == 0
    assert v.sum() == pytest.approx(d.sum())
    with pytest.raises(ValueError, match="t_end"):
        voxel_discrete(ev, 4, (1, 3), 1.0, 1.0)


def test_event_times_interpolate_the_threshold_crossing():
    # one pixel rising linearly in log intensity over one frame interval (fps = 10)
    frames = np.array([[[40]], [[200]]], np.uint8)
    l0, l1 = log_frames(frames)[:, 0, 0]
    c = (l1 - l0) / 3.5
    ev, pot = simulate_events(frames, SensorParams(c, 2 * c), fps=10.0, initial_potential=np.zeros((1, 1)))
    np.testing.assert_allclose(np.sort(ev.t), np.array([1, 2, 3]) / 3.5 / 10.0, rtol=1e-9)
    assert (ev.p == 1).all() and pot[0, 0] == pytest.approx(0.5 * c)
    # with a starting potential of 0.5 c the first crossing comes at half a threshold
    ev2, _ = simulate_events(frames, SensorParams(c, 2 * c), fps=10.0, initial_potential=np.full((1, 1), 0.5 * c))
    np.testing.assert_allclose(np.sort(ev2.t), np.array([0.5, 1.5, 2.5, 3.5]) / 3.5 / 10.0, rtol=1e-9)


@pytest.mark.parametrize("cp,cn", [(0.15, 0.37), (0.2, 0.2), (0.5, 0.06)])
@pytest.mark.parametrize("k", [1, 4])
def test_v2v_equals_reference_discrete_voxel_for_linear_paths(clip, cp, cn, k):
    """The paper's claim: where the log intensity moves monotonically inside each frame
    pair (any linear interpolation), V2V's discrete voxel is the reference's, for any
    c+, c-, with noise and hot pixels (spread linearly over the pair, same rng draws)."""
    hot = np.zeros(SHAPE, np.float32)
    hot[5, 7], hot[30, 40] = 0.8, -0.45
    params = SensorParams(cp, cn, 0.04, hot)
    vox, pot = simulate_voxels(clip, params, 5, rng=np.random.default_rng(11))
    ev, rpot = simulate_events(clip, params, subframes=k, interpolation="linear", rng=np.random.default_rng(11))
    ref = events_to_voxels(ev, 4, 5, SHAPE, 30.0)
    assert np.abs(ref).sum() > 5000
    np.testing.assert_array_equal(vox, ref)
    np.testing.assert_allclose(pot, rpot, atol=1e-6)
    # V2V's bins never mix polarities, so |voxel| is the reference's event count
    assert np.abs(vox).sum() == len(ev)


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    cp=st.floats(0.01, 2.0),
    ratio=st.floats(0.2, 5.0),
    k=st.integers(1, 6),
)
def test_v2v_equals_reference_on_random_frames(seed, cp, ratio, k):
    rng = np.random.default_rng(seed)
    frames = rng.integers(0, 256, (6, 5, 4), dtype=np.uint8)
    params = SensorParams(cp, cp * ratio)
    pot0 = rng.uniform(-cp * ratio, cp, (5, 4))
    vox, _ = simulate_voxels(frames, params, 5, initial_potential=pot0)
    ev, _ = simulate_events(frames, params, subframes=k, initial_potential=pot0)
    np.testing.assert_array_equal(vox, events_to_voxels(ev, 1, 5, (5, 4), 30.0))


def test_non_monotonic_paths_differ_boundedly_when_thresholds_are_equal(clip):
    """Motion-compensated sub-frames make the path inside a pair non-monotonic. With
    c+ = c- = c the net count obeys c * (sum N+ - sum N-) = L_end - L_0 + dL_hat_0 -
    dL_hat_end for both simulators, and both residuals lie in (-c, c): the cumulative net
    counts differ by at most 1 at every frame time, a bin by at most 2. With c+ != c- each
    up-down excursion adds (c- - c+) bias, so the difference grows without such a bound."""
    pot0 = np.random.default_rng(3).uniform(-0.2, 0.2, SHAPE)
    out = {}
    for cp, cn in [(0.2, 0.2), (0.12, 0.36)]:
        params = SensorParams(cp, cn)
        vox, _ = simulate_voxels(clip, params, 5, initial_potential=pot0)
        ev, _ = simulate_events(clip, params, subframes=8, interpolation="motion", flow_preset="ultrafast",
                                initial_potential=pot0)
        ref = events_to_voxels(ev, 4, 5, SHAPE, 30.0)
        cum = np.cumsum((ref - vox).reshape(20, *SHAPE).astype(np.int64), axis=0)
        out[cp == cn] = (np.abs(cum).max(), np.abs(ref - vox).max(), (ref != vox).mean())
    eq_cum, eq_bin, eq_frac = out[True]
    assert eq_frac > 0.005  # the motion path does change counts ...
    assert eq_cum <= 1 and eq_bin <= 2  # ... but only at the boundary
    ne_cum, _, ne_frac = out[False]
    assert ne_cum > 2 and ne_frac > eq_frac


def test_motion_interpolation_moves_content_half_way():
    rng = np.random.default_rng(0)
    base = rng.uniform(-4, 0, (48, 64 + 8))
    import cv2

    base = cv2.GaussianBlur(base, (0, 0), 2.0)
    l0, l1, mid = base[:, 4:68], base[:, 0:64], base[:, 2:66]  # content moves +4 px in x
    f01 = np.zeros((48, 64, 2), np.float32)
    f01[..., 0] = 4.0
    f10 = -f01
    m = interpolate_pair(l0, l1, [0.0, 0.5, 1.0], "motion", flow01=f01, flow10=f10)
    np.testing.assert_array_equal(m[0], l0)
    np.testing.assert_array_equal(m[2], l1)
    inner = (slice(None), slice(6, -6))
    err_mc = np.abs(m[1][inner] - mid[inner]).mean()
    err_lin = np.abs(0.5 * (l0 + l1)[inner] - mid[inner]).mean()
    assert err_mc < 0.1 * err_lin


def test_uint16_reference_matches_uint8_scaled_frames(clip):
    f8 = clip[:6]
    f16 = f8.astype(np.uint16) * 257  # same intensities at full scale 65535
    np.testing.assert_allclose(log_frames(f16), log_frames(f8), atol=1e-6)


def test_reference_validation():
    frames = np.zeros((3, 4, 4), np.uint8)
    p = SensorParams(0.1, 0.1)
    with pytest.raises(ValueError, match="subframes"):
        simulate_events(frames, p, subframes=0)
    with pytest.raises(ValueError, match="interpolation"):
        simulate_events(frames, p, interpolation="cubic")
    with pytest.raises(ValueError, match="uint8 or uint16"):
        simulate_events(frames.astype(np.float32), p)
    with pytest.raises(ValueError, match="initial_potential"):
        simulate_events(frames, p, initial_potential=np.zeros((3, 3)))

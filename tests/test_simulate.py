"""The V2V core against a float64 transcription of the paper's equations, on real frames."""
from __future__ import annotations

import math

import numpy as np
import pytest

from v2v_server.simulation.simulate import SensorParams, ParamRanges, sample_params, simulate_voxels


def reference_v2v(frames, cp, cn, num_bins, potential0, noise=None, hot=None):
    """Straight float64 transcription of the V2V equations, one frame pair at a time.

    Returns (voxels int64 (L, B, H, W), final potential float64, min distance of dL/c to an
    integer per pixel, used to spot exact-threshold ties)."""
    f = frames.astype(np.float64) / 255.0
    logi = np.log(1e-3 + f**2.2)
    pot = potential0.astype(np.float64).copy()
    out = []
    tie = np.full(frames.shape[1:], np.inf)
    for i in range(1, len(frames)):
        dl = pot + (logi[i] - logi[i - 1])
        if noise is not None:
            dl = dl + noise[i - 1]
        if hot is not None:
            dl = dl + hot
        npos = np.where(dl >= cp, np.floor(dl / cp), 0.0)
        nneg = np.where(dl <= -cn, np.floor(-dl / cn), 0.0)
        for q in (dl / cp, -dl / cn):
            tie = np.minimum(tie, np.abs(q - np.round(q)))
        pot = dl - cp * npos + cn * nneg
        out.append(npos - nneg)
    v = np.stack(out).astype(np.int64)
    return v.reshape(-1, num_bins, *frames.shape[1:]), pot, tie


@pytest.mark.parametrize("cp,cn", [(0.2, 0.3), (0.05, 0.07), (1.1, 0.8)])
def test_matches_float64_reference_on_real_frames(real_clip, cp, cn):
    frames = real_clip[:51]  # L = 10 voxels x 5 bins
    rng = np.random.default_rng(1)
    pot0 = rng.uniform(-cn, cp, frames.shape[1:])
    vox, pot = simulate_voxels(frames, SensorParams(cp, cn), 5, initial_potential=pot0)
    ref, ref_pot, tie = reference_v2v(frames, cp, cn, 5, pot0)
    assert vox.shape == (10, 5) + frames.shape[1:]
    assert np.issubdtype(vox.dtype, np.signedinteger)
    assert pot.dtype == np.float32 and pot.shape == frames.shape[1:]
    # float32 arithmetic may round differently only where dL / c lies within float32
    # precision of an integer (an exact-threshold tie); everywhere else: identical.
    clean = tie > 1e-4
    assert clean.mean() > 0.9
    assert (np.abs(ref).sum() > 1000), "the clip must produce events for the test to mean anything"
    np.testing.assert_array_equal(vox[:, :, clean], ref[:, :, clean])
    np.testing.assert_allclose(pot[clean], ref_pot[clean], atol=1e-4)


def test_float64_compute_matches_reference_exactly(real_clip):
    frames = real_clip[:26]
    cp, cn = 0.15, 0.21
    pot0 = np.random.default_rng(2).uniform(-cn, cp, frames.shape[1:])
    vox, _ = simulate_voxels(frames, SensorParams(cp, cn), 5, initial_potential=pot0, compute_dtype=np.float64)
    ref, _, tie = reference_v2v(frames, cp, cn, 5, pot0)
    clean = tie > 1e-9
    np.testing.assert_array_equal(vox[:, :, clean], ref[:, :, clean])


def test_hot_pixels_fire_every_pair():
    frames = np.full((11, 8, 8), 100, np.uint8)
    hot = np.zeros((8, 8), np.float32)
    hot[2, 3] = 0.55  # c+ = 0.1 -> 5 or 6 positive events per frame pair
    hot[5, 5] = -0.35  # c- = 0.1 -> about 3.5 negative events per pair
    vox, pot = simulate_voxels(frames, SensorParams(0.1, 0.1, 0.0, hot), 5, initial_potential=np.zeros((8, 8)))
    assert vox[:, :, 2, 3].sum() == pytest.approx(55, abs=1)
    assert vox[:, :, 5, 5].sum() == pytest.approx(-35, abs=1)
    others = np.ones((8, 8), bool)
    others[2, 3] = others[5, 5] = False
    assert not vox[:, :, others].any()
    assert np.all(pot >= -0.1 - 1e-6) and np.all(pot <= 0.1 + 1e-6)


def test_noise_statistics_match_expected_event_rate():
    # Static scene, noise only: the net event count of a pixel over T pairs times c equals
    # the summed noise plus a residual change bounded by c (conservation), so its standard
    # deviation across pixels is sqrt(T) * sigma / c up to that bounded term.
    h = w = 64
    frames = np.full((201, h, w), 128, np.uint8)
    sigma, c = 0.5, 0.05
    vox, pot = simulate_voxels(frames, SensorParams(c, c, sigma), 5, rng=np.random.default_rng(3))
    net = vox.sum(axis=(0, 1)).astype(np.float64)
    expected_std = math.sqrt(200) * sigma / c  # 141
    assert net.std() == pytest.approx(expected_std, rel=0.04)
    assert abs(net.mean()) < 4 * expected_std / math.sqrt(h * w)  # unbiased
    # events per pair: about E|N_i| / c = sigma * sqrt(2 / pi) / c, less the floor's loss
    rate = np.abs(vox).mean()
    assert 0.85 * sigma * math.sqrt(2 / math.pi) / c < rate <= sigma * math.sqrt(2 / math.pi) / c
    assert np.all(pot >= -c - 1e-5) and np.all(pot <= c + 1e-5)


def test_noise_off_is_deterministic_and_noise_on_depends_on_rng(real_clip):
    frames = real_clip[:11]
    pot0 = np.zeros(frames.shape[1:])
    a, _ = simulate_voxels(frames, SensorParams(0.2, 0.2), 5, initial_potential=pot0, rng=np.random.default_rng(1))
    b, _ = simulate_voxels(frames, SensorParams(0.2, 0.2), 5, initial_potential=pot0, rng=np.random.default_rng(2))
    np.testing.assert_array_equal(a, b)
    noisy = SensorParams(0.2, 0.2, 0.1)
    c, _ = simulate_voxels(frames, noisy, 5, initial_potential=pot0, rng=np.random.default_rng(1))
    d, _ = simulate_voxels(frames, noisy, 5, initial_potential=pot0, rng=np.random.default_rng(1))
    e, _ = simulate_voxels(frames, noisy, 5, initial_potential=pot0, rng=np.random.default_rng(2))
    np.testing.assert_array_equal(c, d)
    assert (c != e).any()


def test_continuation_with_returned_potential_equals_one_call(real_clip):
    frames = real_clip[:21]
    params = SensorParams(0.1, 0.13)
    pot0 = np.random.default_rng(4).uniform(-0.13, 0.1, frames.shape[1:]).astype(np.float32)
    whole, pend = simulate_voxels(frames, params, 5, initial_potential=pot0)
    first, pmid = simulate_voxels(frames[:11], params, 5, initial_potential=pot0)
    second, pend2 = simulate_voxels(frames[10:], params, 5, initial_potential=pmid)
    np.testing.assert_array_equal(whole, np.concatenate([first, second]))
    np.testing.assert_array_equal(pend, pend2)


def test_initial_potential_drawn_in_range():
    frames = np.full((6, 32, 32), 50, np.uint8)
    _, pot = simulate_voxels(frames, SensorParams(0.3, 0.2), 5, rng=np.random.default_rng(0))
    assert pot.min() >= -0.2 and pot.max() <= 0.3
    assert pot.min() < -0.15 and pot.max() > 0.25  # spread over U[-c-, c+]


@pytest.mark.parametrize(
    "kwargs,field",
    [
        (dict(pos_threshold=0, neg_threshold=0.1), "pos_threshold"),
        (dict(pos_threshold=-1, neg_threshold=0.1), "pos_threshold"),
        (dict(pos_threshold=0.1, neg_threshold=float("nan")), "neg_threshold"),
        (dict(pos_threshold=0.1, neg_threshold=float("inf")), "neg_threshold"),
        (dict(pos_threshold="a", neg_threshold=0.1), "pos_threshold"),
        (dict(pos_threshold=0.1, neg_threshold=0.1, noise_std=-0.1), "noise_std"),
        (dict(pos_threshold=0.1, neg_threshold=0.1, noise_std=float("nan")), "noise_std"),
        (dict(pos_threshold=0.1, neg_threshold=0.1, hot_pixels=np.zeros(5)), "hot_pixels"),
        (dict(pos_threshold=0.1, neg_threshold=0.1, hot_pixels=[[0.0]]), "hot_pixels"),
        (dict(pos_threshold=0.1, neg_threshold=0.1, hot_pixels=np.full((2, 2), np.nan)), "hot_pixels"),
    ],
)
def test_sensor_params_validation_names_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        SensorParams(**kwargs)


def test_sensor_params_frozen_and_hot_pixels_copied():
    hp = np.zeros((4, 4))
    p = SensorParams(0.1, 0.2, 0.0, hp)
    hp[0, 0] = 5
    assert p.hot_pixels[0, 0] == 0 and p.hot_pixels.dtype == np.float32
    with pytest.raises(Exception):
        p.pos_threshold = 3
    with pytest.raises(ValueError):
        p.hot_pixels[0, 0] = 1


@pytest.mark.parametrize(
    "frames,num_bins,match",
    [
        (np.zeros((10, 4, 4), np.uint8), 5, "L \\* num_bins \\+ 1"),
        (np.zeros((1, 4, 4), np.uint8), 5, "L \\* num_bins \\+ 1"),
        (np.zeros((11, 4, 4), np.float32), 5, "uint8 or uint16"),
        (np.zeros((11, 4), np.uint8), 5, "\\(N, H, W\\)"),
        (np.zeros((11, 4, 4), np.uint8), 0, "num_bins"),
    ],
)
def test_simulate_rejects_bad_frames(frames, num_bins, match):
    with pytest.raises(ValueError, match=match):
        simulate_voxels(frames, SensorParams(0.1, 0.1), num_bins)


def test_simulate_rejects_mismatched_shapes():
    frames = np.zeros((6, 4, 4), np.uint8)
    with pytest.raises(ValueError, match="hot_pixels"):
        simulate_voxels(frames, SensorParams(0.1, 0.1, 0, np.zeros((3, 3))), 5)
    with pytest.raises(ValueError, match="initial_potential"):
        simulate_voxels(frames, SensorParams(0.1, 0.1), 5, initial_potential=np.zeros((4, 5)))


def test_sample_params_follows_ranges():
    rng = np.random.default_rng(0)
    draws = [sample_params(rng, shape=(64, 64)) for _ in range(400)]
    lo = np.array([min(p.pos_threshold, p.neg_threshold) for p in draws])
    hi = np.array([max(p.pos_threshold, p.neg_threshold) for p in draws])
    assert lo.min() >= 0.05 and lo.max() <= 2.0
    ratio = hi / lo
    assert ratio.min() >= 1.0 and ratio.max() <= 1.5 + 1e-9
    pos_larger = np.mean([p.pos_threshold > p.neg_threshold for p in draws])
    assert 0.4 < pos_larger < 0.6  # fair coin
    sig = np.array([p.noise_std for p in draws])
    assert sig.min() >= 0 and sig.max() <= 0.1 and sig.mean() == pytest.approx(0.05, abs=0.01)
    frac = np.array([0 if p.hot_pixels is None else np.count_nonzero(p.hot_pixels) / 4096 for p in draws])
    assert frac.max() <= 0.004 and frac.mean() == pytest.approx(0.0005, rel=0.3)


def test_sample_params_custom_ranges_and_validation():
    rng = np.random.default_rng(1)
    p = sample_params(rng, {"threshold": [0.5, 0.5], "ratio": [2, 2], "noise_std": [0, 0], "hot_pixel_fraction": [0, 0]})
    assert sorted([p.pos_threshold, p.neg_threshold]) == pytest.approx([0.5, 1.0])
    assert p.noise_std == 0 and p.hot_pixels is None
    with pytest.raises(ValueError, match="ranges.threshold"):
        ParamRanges(threshold=(0.0, 1.0))
    with pytest.raises(ValueError, match="ranges.ratio"):
        ParamRanges(ratio=(0.5, 1.0))
    with pytest.raises(ValueError, match="unknown"):
        ParamRanges.from_dict({"thresholds": [1, 2]})

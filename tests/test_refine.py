"""Refinement: parse_refine, uniform / adaptive sub-frames, and agreement with the reference."""
from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import read_luma_clip
from v2v_server.flow.estimate import dis_flow
from v2v_server.simulation.reference import events_to_voxels, simulate_events
from v2v_server.simulation.refine import RefineSpec, parse_refine, refine_frames, simulate_voxels_refined
from v2v_server.simulation.simulate import SensorParams, simulate_voxels

SHAPE = (64, 80)


@pytest.fixture(scope="module")
def clip():
    return read_luma_clip("bikes.mp4", 11, SHAPE)


@pytest.mark.parametrize(
    "text,spec",
    [
        ("off", RefineSpec("off")),
        ("uniform:4", RefineSpec("uniform", k=4)),
        (" Adaptive:2.5 ", RefineSpec("adaptive", lam=2.5)),
        ("adaptive-dl:0.3", RefineSpec("adaptive-dl", lam=0.3)),
    ],
)
def test_parse_refine_round_trips(text, spec):
    got = parse_refine(text)
    assert got == spec
    assert parse_refine(str(got)) == got


@pytest.mark.parametrize("bad", ["", "on", "uniform", "uniform:0", "uniform:2.5", "adaptive:-1",
                                 "adaptive:nan", "adaptive:x", "linear:3", 4])
def test_parse_refine_rejects_naming_refine(bad):
    with pytest.raises(ValueError, match="refine"):
        parse_refine(bad)


def test_off_is_bit_identical_to_simulate_voxels(clip):
    p = SensorParams(0.2, 0.25, 0.05)
    a, pa = simulate_voxels(clip, p, 5, rng=np.random.default_rng(4))
    b, pb, info = simulate_voxels_refined(clip, p, 5, "off", rng=np.random.default_rng(4))
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(pa, pb)
    assert info["refine"] == "off" and info["events"] == np.abs(a).sum()


def test_uniform_refinement_equals_reference_with_same_subframes(clip):
    """V2V run on K motion-compensated sub-frames is the event reference's discrete voxel."""
    p = SensorParams(0.12, 0.3, 0.02)
    vox, pot, info = simulate_voxels_refined(clip, p, 5, "uniform:4", rng=np.random.default_rng(9))
    ev, rpot = simulate_events(clip, p, subframes=4, interpolation="motion", flow_preset="ultrafast",
                               rng=np.random.default_rng(9))
    np.testing.assert_array_equal(vox, events_to_voxels(ev, 2, 5, SHAPE, 30.0))
    np.testing.assert_allclose(pot, rpot, atol=1e-6)
    assert info["events"] == len(ev) and info["subframes_mean"] == 4.0
    plain, _ = simulate_voxels(clip, p, 5, rng=np.random.default_rng(9))
    assert (plain != vox).any()  # the motion path matters


def test_adaptive_refines_only_moving_pairs():
    # a textured patch: static for 5 pairs, then moving 6 px per frame
    rng = np.random.default_rng(0)
    import cv2

    tex = (cv2.GaussianBlur(rng.uniform(0, 255, (64, 160)), (0, 0), 2.0)).astype(np.uint8)
    frames = np.stack([tex[:, 40:120]] * 6 + [tex[:, 40 - 6 * j: 120 - 6 * j] for j in range(1, 6)])
    logs, info = refine_frames(frames, "adaptive:2")
    ks = info["subframes"]
    assert ks.shape == (10,)
    assert (ks[:5] == 1).all()  # static pairs: the plain V2V step
    assert (ks[5:] >= 3).all() and (ks[5:] <= 6).all()  # ~6 px / 2 px (max flow overshoots at borders)
    assert logs.shape == (1 + ks.sum(), 64, 80)
    assert (info["pair_of_step"] == np.repeat(np.arange(10), ks)).all()
    # a huge lambda (or a static clip) falls back to plain V2V exactly
    p = SensorParams(0.1, 0.2)
    pot0 = np.zeros((64, 80))
    a, _ = simulate_voxels(frames, p, 5, initial_potential=pot0)
    b, _, inf2 = simulate_voxels_refined(frames, p, 5, "adaptive:1000", initial_potential=pot0)
    np.testing.assert_array_equal(a, b)
    assert inf2["subframes_max"] == 1
    c, _, inf3 = simulate_voxels_refined(frames, p, 5, "adaptive:2", initial_potential=pot0)
    np.testing.assert_array_equal(a[0], c[0])  # first voxel is the static part
    assert (a[1] != c[1]).any() and inf3["refine"] == "adaptive:2"


def test_adaptive_dl_counts_log_change(clip):
    _, info = refine_frames(clip, "adaptive-dl:0.5")
    from v2v_server.simulation.reference import log_frames

    dl = np.abs(np.diff(log_frames(clip), axis=0)).max(axis=(1, 2))
    np.testing.assert_array_equal(info["subframes"], np.clip(np.ceil(dl / 0.5), 1, 16))


def test_flow_fn_override_and_determinism(clip):
    calls = []

    def zero_flow(a, b):
        calls.append(1)
        return np.zeros(a.shape + (2,), np.float32)

    p = SensorParams(0.2, 0.3)
    pot0 = np.random.default_rng(2).uniform(-0.3, 0.2, SHAPE)
    # zero flow: motion interpolation degenerates to the linear blend V2V already assumes;
    # three float64 sub-steps equal one step except where dL / c lands within rounding of
    # a threshold level (a tie), which shifts one event by one bin at most
    a, _ = simulate_voxels(clip, p, 5, initial_potential=pot0)
    b, _, _ = simulate_voxels_refined(clip, p, 5, "uniform:3", initial_potential=pot0, flow_fn=zero_flow)
    assert (a != b).mean() < 1e-4
    cum = np.cumsum((a - b).reshape(10, *SHAPE), axis=0)
    assert np.abs(cum).max() <= 1
    assert len(calls) == 2 * 10
    f1 = dis_flow(clip[0], clip[1], "fast")
    f2 = dis_flow(clip[0], clip[1], "fast")
    np.testing.assert_array_equal(f1, f2)

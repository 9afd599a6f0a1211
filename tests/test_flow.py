"""Optical flow (v2v_server/flow/estimate.py, options.py): accuracy on large motion through the
sample path, the option table, the DIS reuse policy, and RAFT refused cleanly without local weights."""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from v2v_server.flow import estimate as flow_mod
from v2v_server.samples.recipe import SampleRecipe
from v2v_server.flow.estimate import FlowEstimator, dis_flow
from v2v_server.luma import to_uint8
from v2v_server.flow.options import (DEFAULT_FLOW, FLOW_OPTIONS, DISParams, FlowOption, FlowUnavailable, TrackParams,
                                     check_option, unavailable_reason)
from v2v_server.samples.make import make_sample, plan_window, video_samples
from v2v_server.sources.local import LocalSource

STEP = 5


def texture(h=256, w=640, seed=0):
    """A photograph when scikit-image is there, else smoothed noise (both textured)."""
    try:
        import skimage.data as skd

        img = cv2.cvtColor(skd.astronaut(), cv2.COLOR_RGB2GRAY)
        return np.ascontiguousarray(cv2.resize(img, (w, w))[w // 2 - h // 2: w // 2 + h // 2])
    except ImportError:  # pragma: no cover
        rng = np.random.default_rng(seed)
        return cv2.GaussianBlur((rng.random((h, w)) * 255).astype(np.uint8), (0, 0), 2)


def panning_frames(n, px_per_frame, size=128, h=160):
    """uint8 (n, h, size + margin): a camera panning right over a texture, ``px_per_frame``
    whole pixels per frame, so the content's flow is (-px_per_frame, 0) per frame."""
    img = texture(h, size + 64 + px_per_frame * n)
    return np.stack([img[:, 32 + px_per_frame * t: 32 + px_per_frame * t + size + 32] for t in range(n)])


def median_epe(flow_2hw, dx, dy, margin):
    """Median end-point error (px) against a constant flow, inside ``margin`` px of the border
    that the motion leaves (points that leave the crop cannot be matched)."""
    e = np.hypot(flow_2hw[0] - dx, flow_2hw[1] - dy)
    return float(np.median(e[:, margin:] if dx < 0 else e[:, : e.shape[1] - margin]))


def test_translation_30px_per_voxel_through_the_sample_path(tmp_path):
    """A texture translating 6 px per frame (30 px per voxel of 5 frame pairs), encoded as
    H.264, served by video_samples: median EPE < 2 px with the default."""
    from harness.motion_clips import write_video

    cfg = SampleRecipe(sequence_length=4, num_bins=STEP, crop_size=128, keep_top_fraction=1.0, hflip_prob=0.0,
                      pause_enabled=False, max_samples_per_video=1)
    assert cfg.flow_preset == DEFAULT_FLOW
    frames = panning_frames(cfg.frames_per_sample, 6)
    write_video(str(tmp_path / "pan.mp4"), frames)
    (sid, arrays, meta), = list(video_samples(cfg, LocalSource(tmp_path), "pan.mp4", 0, ("frames", "flow")))
    fl = arrays["flow"]  # in the wire's dtype
    assert fl.shape == (4, 2, 128, 128) and fl.dtype == np.dtype(cfg.flow_dtype) == np.float16
    errs = [median_epe(fl[l].astype(np.float32), -30.0, 0.0, 30) for l in range(4)]
    assert max(errs) < 2.0, errs


def test_default_holds_at_40px_per_voxel_where_dis_at_the_voxel_spacing_fails():
    frames = panning_frames(4 * STEP + 1, 8)[:, :128, :128]
    new = FlowEstimator(DEFAULT_FLOW).voxel_flows(frames, STEP)
    dis = FlowEstimator("ultrafast").voxel_flows(frames, STEP)  # DIS between the boundary frames
    assert max(median_epe(new[l], -40.0, 0.0, 40) for l in range(4)) < 2.0
    assert min(median_epe(dis[l], -40.0, 0.0, 40) for l in range(4)) > 10.0


def _similarity_clip(kind, d):
    """Frames (11, 128, 128) of the test texture under a rotation / zoom of ``d`` px per voxel
    at the median radius, and the exact ground-truth flows."""
    from harness.flow_scenes import motion_matrices, render

    img = texture(512, 512)
    return render(img, motion_matrices(img.shape, kind, d, STEP, 2, 0.0), STEP)


@pytest.mark.parametrize("kind,d", [("rotation", 40.0), ("zoom-in", 20.0), ("zoom-out", 30.0),
                                    ("zoom-in", 40.0), ("zoom-out", 40.0)])
def test_default_holds_rotation_and_zoom_at_large_motion(kind, d):
    """Rotation by 46 degrees per voxel (40 px at the median radius), zoom in by 1.39x / 1.78x
    and out by 0.41x / 0.22x per voxel: the default's median EPE stays under 2 px, where DIS
    between the boundary frames is off by far more."""
    from harness.flow_scenes import epe

    frames, gts = _similarity_clip(kind, d)

    def median(name):
        fl = FlowEstimator(name).voxel_flows(frames, STEP)
        return float(np.median(np.concatenate([epe(fl[l], gts[l]) for l in range(len(gts))])))

    assert median(DEFAULT_FLOW) < 2.0
    assert median("ultrafast") > 5.0


def _zoom_off():
    est = FlowEstimator(DEFAULT_FLOW)
    est.option = dataclasses.replace(est.option, track=dataclasses.replace(est.option.track, zoom=None))
    return est


def test_zoom_compensation_is_what_holds_a_fast_zoom_out():
    """Zooming out to 0.22x per voxel (1.35x smaller every frame): plain LK drifts as the
    window's content shrinks (median EPE far over 2 px without ``zoom``); tracking in each next
    frame resized by the scale predicted from the previous pair keeps it under 0.5 px."""
    from harness.flow_scenes import epe

    frames, gts = _similarity_clip("zoom-out", 40.0)
    on = FlowEstimator(DEFAULT_FLOW).voxel_flows(frames, STEP)
    off = _zoom_off().voxel_flows(frames, STEP)
    med = lambda fl: float(np.median(np.concatenate([epe(fl[l], gts[l]) for l in range(len(gts))])))  # noqa: E731
    assert med(on) < 0.5
    assert med(off) > 4.0


def test_zoom_compensation_leaves_other_motion_alone():
    """Translation, rotation and an object moving over a background that moves otherwise (the
    points spread, but no similarity explains them): not one pair is compensated, the flow is
    bit for bit that of plain tracking."""
    from harness.flow_scenes import render_object

    clips = [panning_frames(2 * STEP + 1, 8)[:, :128, :128], _similarity_clip("rotation", 40.0)[0]]
    obj = cv2.resize(texture(256, 256)[::-1], (48, 48), interpolation=cv2.INTER_AREA)
    clips.append(render_object(texture(400, 400), obj, (4.0, 0.0), (-3.0, 8.0))[0])  # 20 / 40 px per voxel
    on, off = FlowEstimator(DEFAULT_FLOW), _zoom_off()
    for frames in clips:
        np.testing.assert_array_equal(on.voxel_flows(frames, STEP), off.voxel_flows(frames, STEP))


def test_similarity_fit_recovers_scale_rotation_and_shift_despite_outliers():
    from v2v_server.flow.tracking import _similarity_fit

    rng = np.random.default_rng(0)
    p = rng.uniform(0, 127, (64, 2))
    a = 0.8 * np.array([[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]])
    q = p @ a.T + [5.0, -3.0]
    q[:6] += rng.uniform(20, 40, (6, 2))  # points on the wrong match
    m = _similarity_fit(p, q)
    np.testing.assert_allclose(m, np.column_stack([a, [5.0, -3.0]]), atol=1e-9)
    assert 0.5 * np.log(abs(np.linalg.det(m[:, :2]))) == pytest.approx(np.log(0.8))
    assert _similarity_fit(np.ones((5, 2)), np.ones((5, 2))) is None  # no spread


def test_tracked_fills_dropped_points_with_a_local_affine_fit():
    """Grid points LK drops take the affine fit of the valid ones (close to exact for an affine
    field), one valid point gives its flow to all, a few valid points far away do not
    extrapolate a slope across the grid (a blurred fast pan once gave 560 px in a 96 px crop),
    a grid without valid points is zero."""
    from v2v_server.flow.tracking import _fill_lost

    n = 8
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32)
    field = np.stack([0.3 * xx - 0.2 * yy + 1.0, 0.1 * xx + 0.5 * yy - 2.0], -1)
    ok = np.ones((4, n, n), bool)
    ok[0, :, :2] = False  # two columns left the crop
    ok[1] = False
    ok[1, 3, 4] = True  # one valid point
    ok[2] = False
    ok[3] = False
    ok[3, :3, 6:] = True  # a few valid points in a corner, with a steep slope between them
    grids = np.stack([field] * 4)
    grids[3, ..., 0] = 9.0 * xx
    grids[~ok] = 99.0
    out = _fill_lost(grids, ok)
    np.testing.assert_allclose(out[0], field, atol=0.05)
    np.testing.assert_allclose(out[1], np.broadcast_to(field[3, 4], field.shape), atol=1e-4)
    assert not out[2].any()
    valid = grids[3, ..., 0][ok[3]]  # 54 .. 63: the fill stays within [45, 72]
    assert 2 * valid.min() - valid.max() <= out[3, ..., 0].min() and out[3, ..., 0].max() <= 2 * valid.max() - valid.min()
    np.testing.assert_array_equal(_fill_lost(grids[:1] * 0 + field, ok[:1] | True), field[None])


def test_make_sample_flow_uses_every_frame_and_pauses():
    """make_sample hands the whole sequence (pauses repeated) to the estimator: with a pause
    inside a voxel the tracking sees a pair that moves nothing and the voxel's flow is 4 moves,
    not 5."""
    cfg = SampleRecipe(sequence_length=2, num_bins=STEP, crop_size=128, keep_top_fraction=1.0, hflip_prob=0.0,
                      pause_enabled=False)
    src = panning_frames(cfg.frames_per_sample, 4)[:, :128, :128]
    plan = plan_window(cfg, 0, "x#0", 0, src.shape[1:])
    plan = dataclasses.replace(plan, offsets=np.array([0, 1, 2, 2, 3, 4, 5, 6, 7, 8, 9], np.int64))  # frame 2 repeated
    fl = make_sample(cfg, plan, src, ("flow",)).arrays["flow"]
    assert (median_epe(fl[0], -16.0, 0.0, 20)) < 1.0  # frames 0 -> 4: 4 moves of 4 px
    assert (median_epe(fl[1], -20.0, 0.0, 24)) < 1.0  # frames 4 -> 9: 5 moves


def test_every_option_handles_small_and_odd_sized_crops():
    """Crops down to the config's minimum (8 px), odd and non-square sizes."""
    for name, o in FLOW_OPTIONS.items():
        if o.method == "raft":
            continue
        est = FlowEstimator(name)
        for h, w in ((8, 8), (12, 20), (32, 32), (64, 48)):
            fl = est.voxel_flows(panning_frames(STEP + 1, 1)[:, :h, :w], STEP)
            assert fl.shape == (1, 2, h, w) and np.isfinite(fl).all(), (name, h, w)


def test_option_table_and_config_validation():
    assert DEFAULT_FLOW in FLOW_OPTIONS and FlowEstimator().preset == DEFAULT_FLOW
    assert set(FLOW_OPTIONS) == {"tracked", "tracked-g12", "ultrafast", "raft-small", "raft-large"}
    for name, o in FLOW_OPTIONS.items():
        assert o.name == name and o.summary
    assert FLOW_OPTIONS["ultrafast"].method == "direct" and FLOW_OPTIONS["ultrafast"].dis == DISParams("ultrafast")
    assert check_option("Tracked-G12").name == "tracked-g12"
    with pytest.raises(ValueError, match="flow_preset"):
        check_option("slow")
    with pytest.raises(ValueError, match="flow_preset"):
        SampleRecipe(flow_preset="slow")
    for name in FLOW_OPTIONS:
        if unavailable_reason(name) is None:
            assert SampleRecipe(flow_preset=name.upper()).flow_preset == name
    with pytest.raises(ValueError, match="method"):
        FlowOption("x", "chained")
    with pytest.raises(ValueError, match="preset"):
        DISParams("slow")
    with pytest.raises(ValueError, match="patch_size"):
        DISParams("fast", patch_size=0)
    for bad in (dict(grid=1), dict(window=8), dict(levels=-1), dict(iterations=0), dict(eps=0.0), dict(grid=True),
                dict(zoom=0.0), dict(zoom=True), dict(zoom="0.05"), dict(compensated_levels=-1)):
        with pytest.raises(ValueError, match="tracking"):
            TrackParams(**bad)
    with pytest.raises(ValueError, match="TrackParams"):
        FlowOption("x", "tracked", track=dict(grid=8))
    with pytest.raises(ValueError, match="frames must be"):
        FlowEstimator("ultrafast").voxel_flows(np.zeros((7, 16, 16), np.uint8), 5)


def test_flow_options_import_neither_opencv_nor_numba():
    """The configuration checks a preset name through flow.options without loading OpenCV or numba."""
    import subprocess
    import sys

    code = ("import sys, v2v_server.flow.options as f; f.check_option('tracked'); "
            "print(sorted(m for m in ('cv2', 'numba', 'torch') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_raft_refused_cleanly_without_local_weights(monkeypatch, tmp_path):
    monkeypatch.setenv("V2V_RAFT_WEIGHTS", str(tmp_path / "missing.pth"))
    for name in ("raft-small", "raft-large"):
        why = unavailable_reason(name)
        assert why and ("torchvision" in why or "never downloaded" in why)
        with pytest.raises(FlowUnavailable):
            FlowEstimator(name)
        with pytest.raises(ValueError, match="flow_preset 'raft"):
            SampleRecipe(flow_preset=name)


def test_reused_dis_objects_give_the_flow_of_fresh_ones():
    """A sample's flow must not depend on what its worker computed before (reuse policy)."""
    rng = np.random.default_rng(1)
    clips = [panning_frames(11, s)[:, :h, :h] for s, h in ((2, 128), (5, 96), (3, 128))]
    for name in [n for n, o in FLOW_OPTIONS.items() if o.method != "raft"]:
        warm = FlowEstimator(name)
        for c in clips:
            warm.voxel_flows(c, STEP)
        for c in clips[::-1]:
            np.testing.assert_array_equal(warm.voxel_flows(c, STEP), FlowEstimator(name).voxel_flows(c, STEP))
    a, b = (rng.random((2, 64, 64)) * 255).astype(np.uint8)
    fresh = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(
        np.ascontiguousarray(panning_frames(2, 3)[0, :128, :128]),
        np.ascontiguousarray(panning_frames(2, 3)[1, :128, :128]), None)
    # dis_flow and the "ultrafast" option are OpenCV's DIS, bit for bit
    pf = np.ascontiguousarray(panning_frames(2, 3)[:, :128, :128])
    np.testing.assert_array_equal(dis_flow(pf[0], pf[1], "medium"), fresh)
    ultra = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST).calc(pf[0], pf[1], None)
    np.testing.assert_array_equal(FlowEstimator("ultrafast").voxel_flows(pf, 1)[0], ultra.transpose(2, 0, 1))
    assert dis_flow(a, b, "fast").shape == (64, 64, 2)
    with pytest.raises(ValueError, match="preset"):
        dis_flow(a, b, "slow")


def test_dis_params_clamp_finest_scale_to_the_pyramid():
    """A finest level above OpenCV's coarsest for the frame size is clamped (it would make DIS
    10-50x slower without gaining accuracy)."""
    assert flow_mod._create_dis(DISParams("ultrafast"), (32, 32)).getFinestScale() == 0
    assert flow_mod._create_dis(DISParams("ultrafast"), (128, 128)).getFinestScale() == 2
    assert flow_mod._create_dis(DISParams("medium", finest_scale=0), (128, 128)).getFinestScale() == 0


def test_pause_pairs_are_skipped_without_changing_the_flow():
    """Tracked options find equal frames (pause repeats) by content whether ``repeats`` marks
    them or not: ``voxel_flows`` with the repeats marked equals it without them."""
    rng = np.random.default_rng(3)
    base = panning_frames(21, 3)[:, :128, :128]
    offsets = np.minimum(np.cumsum(np.r_[0, rng.random(20) < 0.5]), 20)  # pauses repeat frames
    seq = np.ascontiguousarray(base[offsets])
    repeats = np.r_[False, np.diff(offsets) == 0]
    assert repeats.sum() >= 5
    for name, o in FLOW_OPTIONS.items():
        if o.method == "tracked":
            est = FlowEstimator(name)
            np.testing.assert_array_equal(est.voxel_flows(seq, STEP, repeats), FlowEstimator(name).voxel_flows(seq, STEP))
    with pytest.raises(ValueError, match="repeats"):
        FlowEstimator(DEFAULT_FLOW).voxel_flows(seq, STEP, repeats[:-1])


def test_points_to_search_again_are_the_dropped_ones_still_inside():
    """``_dropped_inside`` (numba) marks the points with status 0, never dropped before, last
    position inside the crop (its edges included); NaN is outside."""
    from v2v_server.flow.tracking import _dropped_inside

    rng = np.random.default_rng(2)
    m, w, h = 400, 128, 96
    st = rng.integers(0, 2, (m, 1)).astype(np.uint8)
    ok = rng.random(m) < 0.8
    nxt = rng.uniform(-20, 150, (m, 1, 2)).astype(np.float32)
    nxt[:4, 0] = [[0, 0], [w - 1, h - 1], [w - 1 + 1e-3, 5], [np.nan, 3]]
    st[:4], ok[:4] = 0, True
    out = np.empty(m, bool)
    n = _dropped_inside(st, ok, nxt, w, h, out)
    x, y = nxt[:, 0, 0], nxt[:, 0, 1]
    expect = (st[:, 0] == 0) & ok & (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    np.testing.assert_array_equal(out, expect)
    assert n == expect.sum() and expect[:2].all() and not expect[2:4].any()


_FILL_NUMPY: dict = {}


def _fill_lost_numpy(grid_flow: np.ndarray, ok: np.ndarray, sigma: float = 2.0, ridge: float = 1e-2,
               support: float = 0.1) -> np.ndarray:
    """A vectorised numpy transcription of ``_fill_lost`` (batched weighted moments, LAPACK
    solve): the oracle of the numba one."""
    lost = ~ok.reshape(ok.shape[0], -1)
    if not lost.any():
        return grid_flow
    n = ok.shape[-1]
    key = (n, sigma, ridge, support)
    if key not in _FILL_NUMPY:
        yy, xx = np.divmod(np.arange(n * n, dtype=np.float64), n)
        wts = np.exp(-((xx[:, None] - xx[None, :]) ** 2 + (yy[:, None] - yy[None, :]) ** 2) / (2 * sigma * sigma))
        basis = np.column_stack([np.ones_like(xx), xx, yy])  # (n * n, 3)
        second = np.column_stack([basis, xx * xx, xx * yy, yy * yy])  # moments 1, x, y, xx, xy, yy
        _FILL_NUMPY[key] = (wts, basis, second, np.diag([0.0, ridge, ridge]), np.diag([0.0, support, support]))
    wts, basis, second, damp, floor = _FILL_NUMPY[key]
    vox = np.flatnonzero(lost.any(1))  # grids with something to fill
    f = grid_flow.reshape(grid_flow.shape[0], -1, 2)[vox].astype(np.float64)  # (V', n * n, 2)
    m = (~lost[vox]).astype(np.float64)[..., None]  # (V', n * n, 1)
    cols = np.concatenate([np.broadcast_to(second, f.shape[:2] + (6,)),
                           (basis[None, :, :, None] * f[:, :, None, :]).reshape(f.shape[:2] + (6,))], 2) * m
    mom = wts @ cols  # (V', n * n, 12): weighted moments of the valid points around every point
    where = lost[vox]
    mom = mom[where]  # (k, 12): around the lost points only
    lhs = mom[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(-1, 3, 3) + mom[:, :1, None] * damp + floor
    empty = mom[:, 0] <= 0  # a grid without valid points: zero
    lhs[empty] = np.eye(3)
    coef = np.linalg.solve(lhs, mom[:, 6:].reshape(-1, 3, 2))  # (k, 3, 2)
    pos = np.broadcast_to(basis, where.shape + (3,))[where]  # (k, 3): 1, x, y of each lost point
    # the valid range of each grid (V', 2), widened by itself on each side (zero: no valid point)
    vmax = np.where(where[..., None], -np.inf, f).max(1)
    vmin = np.where(where[..., None], np.inf, f).min(1)
    none = ~np.isfinite(vmax)
    vmax[none] = vmin[none] = 0.0
    lo, hi = 2 * vmin - vmax, 2 * vmax - vmin
    grid_of = np.broadcast_to(np.arange(len(vox))[:, None], where.shape)[where]
    fill = np.clip((pos[:, :, None] * coef).sum(1), lo[grid_of], hi[grid_of])
    out = grid_flow.reshape(grid_flow.shape[0], -1, 2).copy()
    sub = out[vox]
    sub[where] = fill.astype(np.float32)
    out[vox] = sub
    return out.reshape(grid_flow.shape)


def test_fill_lost_equals_a_numpy_transcription():
    """The numba ``_fill_lost`` (loops, 3 x 3 elimination with partial pivoting) gives what the
    batched numpy version with LAPACK's solve gave, to float32 rounding: random grids with a
    third of the points lost, grids with none, one and every point valid."""
    from v2v_server.flow.tracking import _fill_lost

    rng = np.random.default_rng(1)
    for n in (6, 8, 12):
        grids = (rng.standard_normal((30, n, n, 2)) * 8).astype(np.float32)
        ok = rng.random((30, n, n)) > 0.35
        ok[3], ok[4], ok[5] = False, True, False
        ok[5, 2, 2] = True
        want, got = _fill_lost_numpy(grids, ok), _fill_lost(grids, ok)
        assert got.dtype == np.float32 and got.shape == grids.shape
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-5)
        np.testing.assert_array_equal(got[ok], grids[ok])  # valid points are never touched


@pytest.mark.parametrize("name", ["tracked", "ultrafast"])
def test_voxel_flows_float16_is_the_float32_flow_cast(name):
    """dtype="float16" is the float32 flow rounded to nearest even bit for bit (tracked options
    and the others alike), and the tracked expansion from the grid equals the dense
    ``wy @ g @ wx_t`` product to float32 rounding."""
    frames = panning_frames(2 * STEP + 1, 3)[:, :96, :112]
    est = FlowEstimator(name)
    f32 = est.voxel_flows(frames, STEP)
    f16 = est.voxel_flows(frames, STEP, dtype="float16")
    assert f32.dtype == np.float32 and f16.dtype == np.float16 and f16.shape == f32.shape
    np.testing.assert_array_equal(f16.view(np.uint16), f32.astype(np.float16).view(np.uint16))
    with pytest.raises(ValueError, match="dtype"):
        est.voxel_flows(frames, STEP, dtype="int8")
    if name == "tracked":
        from v2v_wire.flowgrid import _expand_grids, _expand_tables
        from v2v_server.flow.tracking import _track_grid

        g = np.random.default_rng(3).standard_normal((3, 8, 8, 2)).astype(np.float32) * 10
        _, wy, wx_t = _track_grid(8, 96, 112)
        want = np.matmul(np.matmul(wy, np.ascontiguousarray(g.transpose(0, 3, 1, 2))), wx_t)
        got = np.empty((3, 2, 96, 112), np.float32)
        _expand_grids(g, *_expand_tables(8, 96, 112), got)
        np.testing.assert_allclose(got, want, rtol=0, atol=2e-5)


@pytest.mark.parametrize("name", ["tracked", "ultrafast"])
def test_deeper_frames_give_the_flow_of_their_8_bit_frames(name):
    """uint16 frames are read through the one conversion the ground-truth frames use
    (``v2v_server.luma.to_uint8``, rounded), not their top 8 bits."""
    f8 = panning_frames(11, 2)
    f16 = (f8.astype(np.uint16) << 8) | 0xC0  # low bits where rounding and the top byte disagree
    assert (to_uint8(f16) != (f16 >> 8)).mean() > 0.05
    est = FlowEstimator(name)
    np.testing.assert_array_equal(est.voxel_flows(f16, 5), est.voxel_flows(to_uint8(f16), 5))
    a, b = f16[0], f16[5]
    np.testing.assert_array_equal(dis_flow(a, b, "ultrafast"), dis_flow(to_uint8(a), to_uint8(b), "ultrafast"))

"""The paper's data-quality ablations: dynamic-range degradation and fixed sensor thresholds
change what they should and nothing else (same seed, same sample ids)."""
from __future__ import annotations

import numpy as np
import pytest

from v2v_server.samples.augment import augment_plan, degrade_dynamic_range, parse_degrade, video_thresholds
from v2v_server.samples.recipe import SampleRecipe
from v2v_server.samples.make import plan_window, video_samples
from v2v_server.sources.local import LocalSource
from v2v_server.simulation.simulate import ParamRanges

OUTS = ("voxels", "frames", "flow")
# what fixed_sensor_params changes: the thresholds, and the statistics of the events they make
DIFFERENT_KEYS = {"pos_threshold", "neg_threshold", "fixed_sensor_params", "stats"}


def cfg(**kw):
    base = dict(sequence_length=2, num_bins=2, crop_size=32, max_samples_per_video=2, seed=11)
    return SampleRecipe(**{**base, **kw})


def samples(c, videos, name="bikes.mp4", epoch=0):
    return {key.sample_id(c.crops_per_window): (arrays, meta)
            for key, arrays, meta in video_samples(c, LocalSource(videos), name, epoch, OUTS)}


def test_degrade_formula_is_the_papers():
    rng = np.random.default_rng(0)
    f = rng.integers(0, 256, (3, 8, 8), dtype=np.uint8)
    for s in (1.0, 1.7, 3.0):
        want = np.clip((f.astype(np.float64) - 127.5) * s + 127.5, 0, 255).astype(np.uint8)  # reference degrade_video
        assert np.array_equal(degrade_dynamic_range(f, s), want)
    assert np.array_equal(degrade_dynamic_range(f, 1.0), f)
    g = rng.integers(0, 65536, (2, 4, 4), dtype=np.uint16)
    got = degrade_dynamic_range(g, 2.0)
    assert got.dtype == np.uint16 and np.array_equal(got, np.clip((g - 32767.5) * 2 + 32767.5, 0, 65535).astype(np.uint16))
    with pytest.raises(ValueError, match="uint8 or uint16"):
        degrade_dynamic_range(f.astype(np.float32), 2.0)


def test_degrade_config():
    assert parse_degrade(None) == {} and parse_degrade({}) == {} and SampleRecipe().degrade_dynamic_range == {}
    assert parse_degrade(True) == {"probability": 0.8, "scale": [1.0, 3.0]}
    assert parse_degrade({"scale": [1, 2]}) == {"probability": 0.8, "scale": [1.0, 2.0]}
    for bad, field in (({"probability": 1.5}, "probability"), ({"scale": [3, 1]}, "scale"),
                       ({"scale": 2}, "scale"), ({"prob": 0.5}, "unknown")):
        with pytest.raises(ValueError, match=field):
            SampleRecipe(degrade_dynamic_range=bad)
    with pytest.raises(ValueError, match="fixed_sensor_params"):
        SampleRecipe(fixed_sensor_params="yes")


def test_degrade_probability_and_scale_per_sample():
    c = cfg(degrade_dynamic_range={"probability": 0.8, "scale": [1, 3]})
    scales = []
    for k in range(400):
        plan = plan_window(c, 0, f"v.mp4#{k}", k, (64, 64))
        scales.append(plan.info["dynamic_range_scale"])
    scales = np.array(scales)
    applied = scales != 1.0
    assert 0.72 < applied.mean() < 0.88
    assert scales[applied].min() >= 1.0 and scales[applied].max() <= 3.0 and scales[applied].std() > 0.4
    # a pure function of (seed, epoch, sample id)
    assert plan_window(c, 0, "v.mp4#3", 3, (64, 64)).info == plan_window(c, 0, "v.mp4#3", 3, (64, 64)).info
    assert plan_window(c, 1, "v.mp4#3", 3, (64, 64)).info != plan_window(c, 0, "v.mp4#3", 3, (64, 64)).info


def test_degradation_changes_frames_and_voxels_only(videos):
    plain = samples(cfg(), videos)
    always = samples(cfg(degrade_dynamic_range={"probability": 1.0, "scale": [2, 3]}), videos)
    never = samples(cfg(degrade_dynamic_range={"probability": 0.0}), videos)
    assert list(plain) == list(always) == list(never) == ["bikes.mp4#0", "bikes.mp4#1"]
    for sid, (arrays, meta) in plain.items():
        a, ma = always[sid]
        s = ma["dynamic_range_scale"]
        assert 2.0 <= s <= 3.0
        # crop, flip, pauses, params (the event statistics follow the degraded frames' events)
        assert {k: v for k, v in ma.items() if k not in ("dynamic_range_scale", "stats")} == \
            {k: v for k, v in meta.items() if k != "stats"}
        # the ground truth is the degraded clip: exactly the formula on the plain frames
        assert np.array_equal(a["frames"], degrade_dynamic_range(arrays["frames"], s))
        assert not np.array_equal(a["voxels"], arrays["voxels"])  # V2V saw the degraded frames
        n, mn = never[sid]
        assert mn["dynamic_range_scale"] == 1.0 and {k: v for k, v in mn.items() if k != "dynamic_range_scale"} == meta
        for k in OUTS:
            assert np.array_equal(n[k], arrays[k])


def test_fixed_sensor_params_keep_thresholds_per_video_and_nothing_else(videos):
    free = {e: samples(cfg(), videos, epoch=e) for e in (0, 1)}
    fixed = {e: samples(cfg(fixed_sensor_params=True), videos, epoch=e) for e in (0, 1)}
    want = video_thresholds(11, "bikes.mp4", ParamRanges())
    got = {(m["pos_threshold"], m["neg_threshold"]) for e in (0, 1) for _, m in fixed[e].values()}
    assert got == {want}  # every window, every epoch
    assert len({(m["pos_threshold"], m["neg_threshold"]) for e in (0, 1) for _, m in free[e].values()}) == 4
    assert video_thresholds(11, "bigbuckbunny.mp4", ParamRanges()) != want  # per video
    assert video_thresholds(12, "bikes.mp4", ParamRanges()) != want  # per seed
    for e in (0, 1):
        for sid, (arrays, meta) in free[e].items():
            fa, fm = fixed[e][sid]
            assert fm["fixed_sensor_params"] is True
            # crops, flips, pauses, noise and hot pixels are the sample's own, as without the option
            assert {k: v for k, v in fm.items() if k not in DIFFERENT_KEYS} == \
                   {k: v for k, v in meta.items() if k not in DIFFERENT_KEYS}
            assert np.array_equal(fa["frames"], arrays["frames"]) and np.array_equal(fa["flow"], arrays["flow"])
    # noise still varies per sample under fixed thresholds (as the reference's use_fixed_thresholds)
    assert len({m["noise_std"] for e in (0, 1) for _, m in fixed[e].values()}) == 4


def test_augment_plan_is_a_no_op_when_off():
    c = cfg()
    plan = plan_window(c, 0, "v.mp4#0", 0, (64, 64))
    assert augment_plan(c, 0, plan) is plan and plan.info == {}

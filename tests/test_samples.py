"""Samples: determinism, outputs computed only on request, pauses, crops, config and wire helpers."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from v2v_server.samples import make as samples_mod
from v2v_server.ops.config import load_config
from v2v_server.samples.recipe import SampleRecipe
from v2v_wire.protocol import (ProtocolError, decode_arrays, encode_arrays, narrow_int_dtype, pack, unpack)
from v2v_server.samples.make import pause_offsets, sample_rng, video_samples
from v2v_server.sources.local import LocalSource
from v2v_wire.ids import SampleKey


def small_cfg(**kw):
    """A short recipe with the authors' window layout (windows at k x stride: these tests cut the
    montage bikes.mp4 and synthetic step clips; windows inside shots are tests/test_shots.py's)."""
    base = dict(sequence_length=4, num_bins=5, crop_size=64, max_samples_per_video=3, seed=3, shot_cuts="off")
    base.update(kw)
    return SampleRecipe(**base)


def collect(cfg, videos, name, epoch=0, outputs=("voxels", "frames", "flow"), skip=()):
    return {key.sample_id(cfg.crops_per_window): arr
            for key, arr, _ in video_samples(cfg, LocalSource(videos), name, epoch, outputs, skip)}


def test_content_depends_only_on_seed_epoch_and_sample_id(videos):
    cfg = small_cfg()
    a = collect(cfg, videos, "bikes.mp4")
    assert list(a) == ["bikes.mp4#0", "bikes.mp4#1", "bikes.mp4#2"]
    # the same sample made alone (its neighbours skipped, as a replacement worker does)
    b = collect(cfg, videos, "bikes.mp4", skip={SampleKey("bikes.mp4", 0), SampleKey("bikes.mp4", 2)})
    assert list(b) == ["bikes.mp4#1"]
    for k in a["bikes.mp4#1"]:
        np.testing.assert_array_equal(a["bikes.mp4#1"][k], b["bikes.mp4#1"][k])
    c = collect(cfg, videos, "bikes.mp4", epoch=1)
    assert not np.array_equal(a["bikes.mp4#0"]["voxels"], c["bikes.mp4#0"]["voxels"])
    d = collect(small_cfg(seed=4), videos, "bikes.mp4")
    assert not np.array_equal(a["bikes.mp4#0"]["voxels"], d["bikes.mp4#0"]["voxels"])


def test_only_requested_outputs_are_computed(videos, monkeypatch):
    calls = {"flow": 0, "sim": 0}

    class NoFlow:
        def __init__(self, *a, **k):
            calls["flow"] += 1

        def voxel_flows(self, frames, step, repeats=None, dtype="float32"):
            calls["flow"] += 1
            return np.zeros(((len(frames) - 1) // step, 2) + frames.shape[1:], dtype)

    real_sim = samples_mod.simulate_voxels

    def counting_sim(*a, **k):
        calls["sim"] += 1
        return real_sim(*a, **k)

    monkeypatch.setattr(samples_mod, "FlowEstimator", NoFlow)
    monkeypatch.setattr(samples_mod, "simulate_voxels", counting_sim)
    out = collect(small_cfg(), videos, "bikes.mp4", outputs=("voxels",))
    assert all(set(v) == {"voxels"} for v in out.values())
    assert calls == {"flow": 0, "sim": 3}
    out = collect(small_cfg(), videos, "bikes.mp4", outputs=("frames",))
    assert all(set(v) == {"frames"} for v in out.values())
    assert calls == {"flow": 0, "sim": 3}


def test_frames_are_voxel_boundaries_and_flow_aligns(videos):
    cfg = small_cfg(pause_enabled=False, hflip_prob=0.0)
    (sid, arr), = list(collect(cfg, videos, "webvid_like_596x336.mp4").items())[:1]
    assert arr["frames"].shape == (5, 64, 64) and arr["frames"].dtype == np.uint8
    assert arr["voxels"].shape == (4, 5, 64, 64)
    assert arr["flow"].shape == (4, 2, 64, 64) and arr["flow"].dtype == np.dtype(cfg.flow_dtype)  # the wire's
    # warping frame l+1 back with the flow must explain frame l better than no motion does
    import cv2

    f0, f1 = arr["frames"][1].astype(np.float32), arr["frames"][2].astype(np.float32)
    fl = arr["flow"][1].astype(np.float32)
    yy, xx = np.mgrid[0:64, 0:64].astype(np.float32)
    warped = cv2.remap(f1, xx + fl[0], yy + fl[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    inner = (slice(8, -8), slice(8, -8))
    assert np.abs(warped - f0)[inner].mean() < np.abs(f1 - f0)[inner].mean()


def test_pause_chain_statistics():
    rng = np.random.default_rng(0)
    offs = [pause_offsets(rng, 201, 0.0102, 0.9791) for _ in range(300)]
    for o in offs:
        assert o[0] == 0 and np.all(np.diff(o) >= 0) and np.all(np.diff(o) <= 1)
    paused_steps = np.mean([200 - o[-1] for o in offs])
    # stationary share of paused steps: p_run / (p_run + 1 - p_paused) ~ 0.33 of steps
    assert 30 < paused_steps < 100
    none = pause_offsets(rng, 201, 0.0, 0.0)
    np.testing.assert_array_equal(none, np.arange(201))


def test_sample_rng_is_stable_across_processes():
    # blake2b of the id, not Python's salted hash(): the same numbers in every process
    import os
    import subprocess
    import sys

    code = "from v2v_server.samples.make import sample_rng; print(sample_rng(5, 2, 'x/a.mp4#3').integers(0, 2**62))"
    outs = {subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60,
                           env=dict(os.environ, PYTHONHASHSEED=str(h))).stdout.strip() for h in (1, 2)}
    assert outs == {str(sample_rng(5, 2, "x/a.mp4#3").integers(0, 2**62))}
    assert sample_rng(5, 2, "x/a.mp4#4").integers(0, 2**62) != int(outs.pop())


def test_small_video_is_scaled_up_not_rejected(tmp_path):
    import av

    path = tmp_path / "tiny.mp4"
    with av.open(str(path), "w") as c:
        s = c.add_stream("mpeg4", rate=25)
        s.width, s.height, s.pix_fmt = 80, 48, "yuv420p"
        for i in range(25):
            img = np.zeros((48, 80, 3), np.uint8)
            img[:, (i * 2) % 80:(i * 2) % 80 + 10] = 255
            for p in s.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    cfg = small_cfg(sequence_length=2, crop_size=64)  # span 11 frames; kept region is 80 x 25
    out = list(video_samples(cfg, LocalSource(tmp_path), "tiny.mp4", 0, ("voxels", "frames")))
    assert len(out) == 2
    sid, arr, meta = out[0]
    assert arr["frames"].shape == (3, 64, 64) and meta["scale"] >= 64 / 25


def test_config_yaml_and_flags(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("num_bins: 3\nsequence_length: 7\nranges:\n  threshold: [0.1, 0.2]\noutputs: [voxels, flow]\n")
    cfg = load_config(str(p), {"sequence_length": 9, "batch_size": None})
    assert (cfg.num_bins, cfg.sequence_length, cfg.batch_size) == (3, 9, 12)
    assert cfg.ranges.threshold == (0.1, 0.2) and cfg.outputs == ("voxels", "flow")
    assert cfg.recipe.frames_per_sample == 9 * 3 + 1
    for text, field in [("num_bins: 0\n", "num_bins"), ("crop_size: -5\n", "crop_size"),
                        ("ranges:\n  threshold: [-1, 2]\n", "threshold"), ("outputs: [events]\n", "outputs"),
                        ("hflip_prob: 2\n", "hflip_prob"), ("flow_preset: slow\n", "flow_preset"),
                        ("bogus_key: 1\n", "bogus_key"), ("ranges:\n  thresh: [1, 2]\n", "thresh")]:
        p.write_text(text)
        with pytest.raises(ValueError, match=field) as e:
            load_config(str(p))
        assert str(p) in str(e.value)
    p.write_text("keep_top_fraction: 0\n")
    with pytest.raises(ValueError, match="keep_top_fraction"):
        load_config(str(p))
    from v2v_server.cli import build_parser, config_from_args
    args = build_parser().parse_args(["--keep-top-fraction", "1.0", "--crop-size", "64"])
    assert config_from_args(args).keep_top_fraction == 1.0
    p.write_text("a: [unclosed\n")
    with pytest.raises(ValueError, match="not valid YAML"):
        load_config(str(p))


def test_wire_dtypes_and_roundtrip():
    assert narrow_int_dtype(np.array([-128, 127])) == np.int8
    assert narrow_int_dtype(np.array([-129, 5])) == np.int16
    assert narrow_int_dtype(np.array([40000])) == np.int32
    with pytest.raises(OverflowError):
        narrow_int_dtype(np.array([2**40]))
    arrays = {"voxels": np.arange(-6, 6, dtype=np.int8).reshape(3, 4), "flow": np.ones((2, 2), np.float16)}
    specs, frames = encode_arrays(arrays)
    back = decode_arrays(specs, [f.tobytes() for f in frames])
    for k in arrays:
        np.testing.assert_array_equal(back[k], arrays[k])
    with pytest.raises(ProtocolError):
        decode_arrays(specs, [frames[0].tobytes(), b"\x00"])  # size mismatch
    with pytest.raises(ProtocolError):
        decode_arrays([{"name": "x", "dtype": "object", "shape": [1]}], [b"\x00" * 8])
    with pytest.raises(ProtocolError):
        encode_arrays({"x": np.zeros(2, np.float64)})
    assert unpack(pack({"type": "hello"}))["type"] == "hello"
    for bad in (b"\xc1", pack({"type": "hello", "v": 99}), b"\x93\x01\x02\x03", b"x" * (2 << 20)):
        with pytest.raises(ProtocolError):
            unpack(bad)


def test_refine_and_nonidealities_are_server_options_recorded_in_params(videos):
    plain = {key.sample_id(): (a, m) for key, a, m in video_samples(small_cfg(max_samples_per_video=1), LocalSource(videos), "bikes.mp4", 0,
                                                          ("voxels",))}
    refined = {key.sample_id(): (a, m) for key, a, m in video_samples(small_cfg(max_samples_per_video=1, refine="uniform:4"),
                                                            LocalSource(videos), "bikes.mp4", 0, ("voxels",))}
    (a0, m0), (a1, m1) = plain["bikes.mp4#0"], refined["bikes.mp4#0"]
    assert m0["refine"] == "off" and m1["refine"] == "uniform:4" and m1["subframes_mean"] == 4.0
    assert not np.array_equal(a0["voxels"], a1["voxels"])  # sub-frames change where events fall
    ni = small_cfg(max_samples_per_video=1, nonidealities={"threshold_sigma": 0.05})
    (_, _, meta), = list(video_samples(ni, LocalSource(videos), "bikes.mp4", 0, ("voxels",)))
    assert meta["nonidealities"]["threshold_sigma"] == 0.05
    with pytest.raises(ValueError, match="refine"):
        small_cfg(refine="sometimes")
    with pytest.raises(ValueError, match="nonidealities"):
        small_cfg(nonidealities={"hot_pixels_everywhere": 1})
    # refinement and non-idealities compose (one kernel call), both recorded
    both = small_cfg(max_samples_per_video=1, refine="uniform:2", nonidealities={"threshold_sigma": 0.05})
    (_, a2, m2), = list(video_samples(both, LocalSource(videos), "bikes.mp4", 0, ("voxels",)))
    assert m2["refine"] == "uniform:2" and m2["nonidealities"]["threshold_sigma"] == 0.05
    assert a2["voxels"].shape == a0["voxels"].shape


def test_crops_per_window_ids_content_and_resume(videos):
    """K crops of one decoded window: ids path#window.crop, each crop its own plan (own crop
    corner, flip, pauses, sensor parameters) drawn from its id, made alike alone or together."""
    from v2v_wire.ids import SampleKey, parse_sample_id, window_keys

    cfg = small_cfg(crops_per_window=3, max_samples_per_video=2)
    got = [(key.sample_id(3), a, m) for key, a, m in video_samples(cfg, LocalSource(videos), "bikes.mp4", 0, ("voxels", "frames"))]
    ids = [sid for sid, _, _ in got]
    assert ids == [f"bikes.mp4#{w}.{c}" for w in range(2) for c in range(3)]
    metas = {sid: m for sid, _, m in got}
    arrays = {sid: a for sid, a, _ in got}
    corners = {(metas[s]["crop_y"], metas[s]["crop_x"], metas[s]["pos_threshold"]) for s in ids}
    assert len(corners) == 6  # every crop drew its own choices
    assert all(metas[s]["src_start_frame"] == (0 if s.split("#")[1].startswith("0") else cfg.windows.window_stride)
               for s in ids)
    assert not np.array_equal(arrays["bikes.mp4#0.0"]["frames"], arrays["bikes.mp4#0.1"]["frames"])
    # one crop made alone (a replacement worker skips the samples already received)
    keep = parse_sample_id("bikes.mp4#1.2", 3)
    assert keep == SampleKey("bikes.mp4", 1, 2) and keep.ordinal(3) == 5
    every = set(window_keys("bikes.mp4", 0, 3) + window_keys("bikes.mp4", 1, 3))
    alone = list(video_samples(cfg, LocalSource(videos), "bikes.mp4", 0, ("voxels", "frames"), every - {keep}))
    assert [key for key, _, _ in alone] == [keep]
    for k, v in alone[0][1].items():
        np.testing.assert_array_equal(v, arrays["bikes.mp4#1.2"][k])
    # K = 1 keeps the ids (and content) of a run without crops
    one = collect(small_cfg(crops_per_window=1), videos, "bikes.mp4", outputs=("frames",))
    base = collect(small_cfg(), videos, "bikes.mp4", outputs=("frames",))
    assert list(one) == list(base) == ["bikes.mp4#0", "bikes.mp4#1", "bikes.mp4#2"]
    np.testing.assert_array_equal(one["bikes.mp4#2"]["frames"], base["bikes.mp4#2"]["frames"])


@pytest.mark.parametrize("sid,k,expect", [("a/b.mp4#3", 1, ("a/b.mp4", 3)), ("a#b.mp4#3.2", 4, ("a#b.mp4", 14)),
                                          ("x.mp4#0.0", 2, ("x.mp4", 0))])
def test_sample_id_round_trip(sid, k, expect):
    from v2v_wire.ids import SampleKey, parse_sample_id

    key = parse_sample_id(sid, k)
    video, idx = expect
    assert key == SampleKey.at(video, idx, k) and key.ordinal(k) == idx
    assert key.sample_id(k) == sid
    assert SampleKey.from_wire(key.wire(), k) == key


@pytest.mark.parametrize("value", [["a.mp4", 1], ["a.mp4", -1, 0], ["a.mp4", 1, 2], ["", 1, 0], [1, 1, 0],
                                   ["a.mp4", True, 0], ["a.mp4", 1.0, 0], "a.mp4#1", None])
def test_sample_key_from_a_message_rejects(value):
    from v2v_wire.ids import SampleKey

    with pytest.raises(ValueError, match="sample key"):
        SampleKey.from_wire(value, 2)


@pytest.mark.parametrize("sid,k", [("a.mp4#3.1", 1), ("a.mp4#3", 2), ("a.mp4#3.2", 2), ("a.mp4", 1), ("#3", 1),
                                   ("a.mp4#-1", 1), ("a.mp4#x", 1), (7, 1), ("a.mp4#٣", 1)])
def test_sample_id_parse_rejects(sid, k):
    from v2v_wire.ids import parse_sample_id

    with pytest.raises(ValueError, match="sample id"):
        parse_sample_id(sid, k)


def test_crops_per_window_config_validation():
    with pytest.raises(ValueError, match="crops_per_window"):
        small_cfg(crops_per_window=0)


@pytest.mark.parametrize("flip", [False, True])
@pytest.mark.parametrize("x", [0, 5, 468])
def test_crop_cut_slices_as_crop_frame(flip, x):
    from v2v_server.samples.make import _CropFrames, crop_frame, plan_window

    cfg = SampleRecipe(seed=2)
    codes = np.random.default_rng(x).integers(0, 256, (181, 596)).astype(np.uint8)
    plan = dataclasses.replace(plan_window(cfg, 0, "v.mp4#0", 0, codes.shape), crop_x=x, flip=flip)
    rng = np.random.default_rng(x + flip)
    frames = [rng.integers(0, 256, (181, 596)).astype(np.uint8) for _ in range(plan.consumed)]
    lut = rng.permutation(256).astype(np.uint8)  # a code -> full-range map (any table)
    expand = lambda a: lut[a]  # noqa: E731
    want = np.stack([expand(crop_frame(cfg, plan, f)) for f in frames])
    # every row kept as codes (flipped and mapped once at the end), or one row under another map
    for other in (None, 3):
        cut = _CropFrames(cfg, SampleKey("v.mp4", 0), plan)
        for k, f in enumerate(frames):
            cut.add(k, f, k != other, expand, None)
        np.testing.assert_array_equal(cut.frames(expand), want)


def test_windows_step_200_frames_and_share_their_boundary_frame(tmp_path):
    """Window k spans source frames [k * 200, (k + 1) * 200] (the authors' loader steps
    ``frames_per_seq``): consecutive samples share their boundary frame, a 401-frame video
    holds two windows, and every frame pair is in exactly one window."""
    import av

    cfg = small_cfg(sequence_length=2, num_bins=2, pause_enabled=False, hflip_prob=0.0, max_samples_per_video=10)
    stride = cfg.windows.window_stride
    assert (cfg.frames_per_sample, stride) == (5, 4)
    assert [cfg.windows.windows_in(n) for n in (4, 5, 8, 9, 13)] == [0, 1, 1, 2, 3]
    assert SampleRecipe().windows.windows_in(401) == 2 and SampleRecipe().windows.windows_in(400) == 1
    path = tmp_path / "steps.mp4"
    with av.open(str(path), "w") as c:  # frame i is uniformly grey level 10 + 15 i
        s = c.add_stream("mpeg4", rate=25)
        s.width, s.height, s.pix_fmt, s.options = 96, 96, "yuv420p", {"qscale": "1"}
        for i in range(13):
            img = np.full((96, 96, 3), 10 + 15 * i, np.uint8)
            for p in s.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    got = list(video_samples(cfg, LocalSource(tmp_path), "steps.mp4", 0, ("frames",)))
    assert [key.sample_id() for key, _, _ in got] == ["steps.mp4#0", "steps.mp4#1", "steps.mp4#2"]
    assert [m["src_start_frame"] for _, _, m in got] == [0, 4, 8]
    levels = [np.round((a["frames"].reshape(a["frames"].shape[0], -1).mean(1) - 10) / 15).astype(int).tolist()
              for _, a, _ in got]
    assert levels == [[0, 2, 4], [4, 6, 8], [8, 10, 12]]

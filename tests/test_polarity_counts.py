"""The opt-in ``polarity_counts`` output: N+ and N- per bin (Lou et al. 2025, Sec. 3), uint8
saturating at 255, (L, 2, num_bins, H, W) per sample, made only when asked, over the stream and
in the Ray engine."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from harness.serve import ServeProcess
from tests.conftest import read_luma_clip
from v2v_client import V2VStreamDataset
from v2v_wire.ids import parse_sample_id
from v2v_server.ops.config import ServeConfig
from v2v_server.samples.recipe import SampleRecipe
from v2v_server.samples.make import video_samples
from v2v_server.sources.local import LocalSource
from v2v_server.simulation.kernel import noise_field
from v2v_server.simulation.simulate import (SensorParams, log_intensity_lut, polarity_counts, simulate_voxels)
from v2v_wire.outputs import ARRAYS, DEFAULT_OUTPUTS, OUTPUTS

L, B, CROP, MAXW, SEED = 4, 5, 64, 1, 5


def paper_counts(frames, cp, cn, sigma, hot, noise_seed, potential):
    """N+ and N- per frame pair by the paper's equations, in numpy: per pair i,
    dL = dL_hat + (L_i - L_{i-1}) + N_i + H, N+ = max(0, floor(dL / c+)),
    N- = max(0, floor(-dL / c-)), dL_hat = dL - c+ N+ + c- N- (stored in float32 between pairs);
    L = log(1e-3 + (F / 255) ** 2.2) (float32 table) and N_i the kernel's draws (noise_field)."""
    lut = log_intensity_lut(255, np.float32).astype(np.float64)
    logs = lut[frames]
    n = len(frames) - 1
    noise = noise_field(noise_seed, n, frames.shape[1:])
    pot = potential.astype(np.float32)
    pos, neg = np.zeros((n,) + frames.shape[1:]), np.zeros((n,) + frames.shape[1:])
    for i in range(n):
        dl = pot.astype(np.float64) + ((logs[i + 1] - logs[i]) + (hot + noise[i] * sigma))
        pos[i] = np.maximum(0.0, np.floor(dl / cp))
        neg[i] = np.maximum(0.0, np.floor(-dl / cn))
        pot = (dl - cp * pos[i] + cn * neg[i]).astype(np.float32)
    return pos, neg


def test_counts_follow_the_paper_equations_and_their_difference_is_the_voxel():
    frames = read_luma_clip("bikes.mp4", 2 * B + 1, (48, 64))
    rng = np.random.default_rng(3)
    hot = np.where(rng.random((48, 64)) < 0.01, rng.normal(0, 0.5, (48, 64)), 0.0).astype(np.float32)
    params = SensorParams(0.12, 0.15, 0.03, hot)
    start = rng.uniform(-0.15, 0.12, (48, 64)).astype(np.float32)
    vox, _, (n_pos, n_neg) = simulate_voxels(frames, params, B, initial_potential=start, noise_seed=99, split=True)
    counts = polarity_counts(n_pos, n_neg, 2, B)
    pos, neg = paper_counts(frames, 0.12, 0.15, 0.03, hot.astype(np.float64), 99, start)
    want = np.stack([pos.reshape(2, B, 48, 64), neg.reshape(2, B, 48, 64)], axis=1)
    assert counts.dtype == np.uint8 and counts.shape == (2, 2, B, 48, 64)
    assert want.max() < 255 and want.sum() > 1000  # real events, none saturated here
    np.testing.assert_array_equal(counts, want)
    np.testing.assert_array_equal(vox, counts[:, 0].astype(np.int32) - counts[:, 1])
    # the voxels of the split kernel are those of the default (fast) one, bit for bit
    plain, _ = simulate_voxels(frames, params, B, initial_potential=start, noise_seed=99, narrow=True)
    narrow, _, _ = simulate_voxels(frames, params, B, initial_potential=start, noise_seed=99, narrow=True, split=True)
    assert plain.dtype == narrow.dtype and np.array_equal(plain, narrow)


def test_counts_saturate_at_255_and_bins_sum_their_frame_pairs():
    # black <-> white every frame with c = 0.01: ~690 events per pair, beyond uint8
    frames = np.zeros((2 * 2 + 1, 4, 4), np.uint8)
    frames[1::2] = 255
    vox, _, (n_pos, n_neg) = simulate_voxels(frames, SensorParams(0.01, 0.01), 4, initial_potential=np.zeros((4, 4)),
                                             split=True)
    assert n_pos.max() > 255 and n_neg.max() > 255
    c = polarity_counts(n_pos, n_neg, 1, 2)  # two frame pairs per bin
    assert c.shape == (1, 2, 2, 4, 4) and c.dtype == np.uint8
    assert (c == 255).all()  # each bin has one rising and one falling pair, each > 255 events
    small = polarity_counts(np.ones((4, 1, 1)), np.zeros((4, 1, 1)), 1, 2)
    assert small[0, 0, :, 0, 0].tolist() == [2, 2] and small[0, 1].sum() == 0
    with pytest.raises(ValueError, match="multiple of sequence_length"):
        polarity_counts(np.ones((3, 1, 1)), np.ones((3, 1, 1)), 1, 2)


def recipe(**kw) -> SampleRecipe:
    return SampleRecipe(sequence_length=L, num_bins=B, crop_size=CROP, max_samples_per_video=MAXW, seed=SEED,
                       **kw)


def test_opt_in_samples_keep_the_default_outputs_bit_identical(videos):
    cfg = recipe()
    assert "polarity_counts" in OUTPUTS and "polarity_counts" not in DEFAULT_OUTPUTS
    base = {sid: a for sid, a, _ in video_samples(cfg, LocalSource(videos), "bikes.mp4", 0, DEFAULT_OUTPUTS)}
    both = {sid: a for sid, a, _ in video_samples(cfg, LocalSource(videos), "bikes.mp4", 0, DEFAULT_OUTPUTS + ("polarity_counts",))}
    assert base and set(base) == set(both)
    for sid, arrays in base.items():
        assert "polarity_counts" not in arrays
        for k, a in arrays.items():
            assert a.dtype == both[sid][k].dtype and np.array_equal(a, both[sid][k]), k
        c = both[sid]["polarity_counts"]
        assert c.shape == ARRAYS["polarity_counts"].shape(L, B, CROP) == (L, 2, B, CROP, CROP)
        ok = (c < 255).all(axis=1)  # voxel = N+ - N- where neither count saturated
        diff = c[:, 0].astype(np.int32) - c[:, 1]
        assert ok.mean() > 0.99 and np.array_equal(arrays["voxels"][ok], diff[ok])
    with pytest.raises(ValueError, match="plain V2V only"):
        next(video_samples(recipe(refine="uniform:2"), LocalSource(videos), "bikes.mp4", 0, ("polarity_counts",)))


def serve_args(videos, *extra):
    return ["--videos", str(videos), "--workers", "1", "--sequence-length", str(L), "--num-bins", str(B),
            "--crop-size", str(CROP), "--max-samples-per-video", str(MAXW), "--seed", str(SEED), *extra]


@pytest.mark.timeout(240)
def test_served_over_the_stream_only_to_a_client_that_asks(videos):
    cfg = recipe()
    with ServeProcess(serve_args(videos, "--batch-size", "2")) as srv:
        for raw in (False, True):
            b = next(iter(V2VStreamDataset(srv.endpoint, 2, outputs=("voxels", "polarity_counts"), timeout_s=120,
                                           raw=raw)))
            assert not b["padding"].any()
            c, v = b["polarity_counts"], b["voxels"]
            assert c.shape == (2, L, 2, B, CROP, CROP)
            assert c.dtype == (torch.uint8 if raw else torch.float32)
            assert v.shape == (2, L, B, CROP, CROP) and c.sum() > 0
            ok = (c < 255).all(dim=2)
            assert torch.equal(v.to(torch.int32)[ok], (c[:, :, 0].to(torch.int32) - c[:, :, 1].to(torch.int32))[ok])
            for i, sid in enumerate(b["sample_ids"]):  # the recipe's counts, bit for bit
                video = parse_sample_id(sid).video
                want = {k.sample_id(): a for k, a, _ in video_samples(cfg, LocalSource(videos), video, 0,
                                                                       ("polarity_counts",))}
                np.testing.assert_array_equal(c[i].numpy().astype(np.uint8), want[sid]["polarity_counts"])
        b = next(iter(V2VStreamDataset(srv.endpoint, 2, outputs=("voxels",), timeout_s=120)))
        assert "polarity_counts" not in b and b["voxels"].abs().sum() > 0


@pytest.mark.timeout(300)
def test_ray_rows_carry_the_same_counts(videos):
    ray = pytest.importorskip("ray", reason="the 'ray' extra is not installed (pip install -e '.[ray]')")
    pytest.importorskip("ray.data", reason="the 'ray' extra is not installed (pip install -e '.[ray]')")
    from v2v_server.ray_data import scan_corpus_windows, v2v_dataset

    cfg = recipe()
    scfg = ServeConfig.from_dict(cfg.recipe_dict())  # the Ray engine takes the whole configuration
    ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False, configure_logging=False)
    try:
        ray.data.DataContext.get_current().enable_progress_bars = False
        corpus = scan_corpus_windows(videos, scfg)
        rows = v2v_dataset(corpus, scfg, epoch=0, outputs=("polarity_counts",), concurrency=1).take_all()
    finally:
        ray.shutdown()
    assert rows and all(set(r) >= {"polarity_counts"} and "voxels" not in r for r in rows)
    for r in rows:
        if r["padding"]:
            continue
        video = parse_sample_id(r["sample_id"]).video
        want = {key.sample_id(): a for key, a, _ in video_samples(cfg, LocalSource(corpus.root), video, 0, ("polarity_counts",))}
        c = r["polarity_counts"]
        assert c.dtype == np.uint8 and c.shape == (L, 2, B, CROP, CROP)
        np.testing.assert_array_equal(c, want[r["sample_id"]]["polarity_counts"])


def test_polarity_counts_not_offered_under_refinement_or_nonidealities():
    """N+ and N- come from plain V2V only: with refinement or non-idealities the server does not
    offer them (default outputs), an explicit request is a configuration error naming the field,
    and the Ray engine refuses the column before any video is read."""
    from v2v_server.ops.config import ServeConfig

    cfg = ServeConfig.from_dict({"refine": "uniform:2"}, source="test")
    assert "polarity_counts" not in cfg.outputs and "voxels" in cfg.outputs
    cfg = ServeConfig.from_dict({"nonidealities": {"dead_fraction": 0.01}}, source="test")
    assert "polarity_counts" not in cfg.outputs
    with pytest.raises(ValueError, match="outputs: polarity_counts"):
        ServeConfig.from_dict({"refine": "uniform:2", "outputs": ["voxels", "polarity_counts"]},
                              source="test")
    assert "polarity_counts" in SampleRecipe().outputs

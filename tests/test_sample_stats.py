"""Per-sample statistics (v2v_server/samples/stats.py): what the worker puts in a sample's params,
checked against the kernel's own N+ and N- on a bundled clip, and their Prometheus histograms."""
from __future__ import annotations

import numpy as np
import pytest

from v2v_server.ops.metrics import ServerMetrics
from v2v_server.samples.make import video_samples
from v2v_server.samples.recipe import SampleRecipe
from v2v_server.samples.stats import event_stats
from v2v_server.sources.local import LocalSource
from harness.data import SAMPLE_VIDEOS


def test_rates_active_pixels_and_flow_by_hand():
    vox = np.zeros((2, 1, 2, 2), np.int8)
    vox[0, 0, 0, 0], vox[0, 0, 1, 1], vox[1, 0, 1, 0] = 1, -2, 3
    flow = np.zeros((2, 2, 2, 2), np.float32)
    flow[:, 0] = 3.0
    flow[:, 1] = 4.0  # 5 px per voxel step of 1 bin x 2 frame pairs: 2.5 px / frame
    s = event_stats(vox, None, flow, video_fps=10.0, num_bins=1, frames_per_bin=2, exact=False)
    # 2 grids x 2 frame intervals at 10 Hz = 0.4 s over 4 pixels
    assert s["rate_pos"] == pytest.approx(4 / 4 / 0.4) and s["rate_neg"] == pytest.approx(2 / 4 / 0.4)
    assert s["grid_rates"] == pytest.approx([3 / 4 / 0.2, 3 / 4 / 0.2])
    assert s["active_fraction"] == 0.75 and s["flow_mag"] == 2.5 and s["exact"] is False
    # int8's -128 is counted as 128 events, whatever the integer width
    vox[1, 0, 0, 1] = -128
    wide = [event_stats(vox.astype(d), None, None, 10.0, 1, 2, True) for d in (np.int8, np.int16, np.int32)]
    assert wide[0] == wide[1] == wide[2] and wide[0]["rate_neg"] == pytest.approx(130 / 4 / 0.4)
    deep = vox.astype(np.int16)
    deep[0, 0, 0, 1] = -32768  # int16's own absolute-value overflow
    assert event_stats(deep, None, None, 10.0, 1, 2, True) == event_stats(deep.astype(np.int64), None, None, 10.0, 1, 2, True)


def test_bad_arrays_and_rates_are_named():
    with pytest.raises(ValueError, match="video_fps"):
        event_stats(np.zeros((1, 1, 2, 2), np.int8), None, None, 0.0, 1, 1, True)
    with pytest.raises(ValueError, match="voxels"):
        event_stats(np.zeros((2, 2, 2), np.int8), None, None, 25.0, 1, 1, True)
    with pytest.raises(ValueError, match="flow"):
        event_stats(None, None, np.zeros((1, 3, 2, 2), np.float32), 25.0, 1, 1, True)


def test_worker_params_carry_the_kernels_event_counts():
    """A served sample's stats (from its voxels) equal the kernel's N+ and N- of the same call."""
    cfg = SampleRecipe(sequence_length=8, max_samples_per_video=3)
    got = list(video_samples(cfg, LocalSource(SAMPLE_VIDEOS), "bbb_camera_596x336.mp4", 0,
                             ("voxels", "flow", "polarity_counts")))
    assert len(got) == 3
    for key, arrays, meta in got:
        st, counts = meta["stats"], arrays["polarity_counts"].astype(np.int64)  # (L, 2, B, S, S)
        assert counts.max() < 255  # no saturation: the counts are the events
        seconds = cfg.sequence_length * cfg.num_bins / meta["video_fps"]
        npix = cfg.crop_size ** 2
        assert st["exact"] and st["rate_pos"] == pytest.approx(counts[:, 0].sum() / npix / seconds, rel=1e-4)
        assert st["rate_neg"] == pytest.approx(counts[:, 1].sum() / npix / seconds, rel=1e-4)
        assert st["active_fraction"] == pytest.approx((counts.sum(axis=(0, 1, 2)) > 0).mean(), rel=1e-4)
        assert len(st["grid_rates"]) == cfg.sequence_length
        assert sum(st["grid_rates"]) / cfg.sequence_length == pytest.approx(st["rate_pos"] + st["rate_neg"], rel=1e-3)
        f = arrays["flow"].astype(np.float64)
        assert st["flow_mag"] == pytest.approx(np.hypot(f[:, 0], f[:, 1]).mean() / cfg.num_bins, rel=1e-3)
        assert st["rate_pos"] > 0 and st["flow_mag"] > 0
        # the window's shot (one shot: no cut in this clip), thresholds and span beside them
        assert meta["shot"] == 0 and meta["shot_start_frame"] == 0
        assert {"pos_threshold", "neg_threshold", "noise_std", "src_start_frame", "src_frames"} <= set(meta)
        assert st["motion"] > 0.005  # the window moves


def test_histograms_on_metrics_page():
    m = ServerMetrics(progress=False)
    params = {"pos_threshold": 0.4, "neg_threshold": 0.5, "noise_std": 0.03,
              "stats": {"rate_pos": 2.0, "rate_neg": 1.5, "active_fraction": 0.6, "flow_mag": 1.2, "motion": 0.003}}
    m.on_sample_made(params)
    m.on_sample_made({"stats": "not a map", "pos_threshold": "x"})  # a malformed map adds nothing
    text = m.exposition().decode()
    get = m.registry.get_sample_value
    assert get("v2v_samples_made_total") == 2
    assert get("v2v_sample_events_per_pixel_second_count", {"polarity": "pos"}) == 1
    assert get("v2v_sample_events_per_pixel_second_sum", {"polarity": "neg"}) == 1.5
    assert get("v2v_sample_active_pixel_fraction_bucket", {"le": "0.75"}) == 1
    assert get("v2v_sample_flow_px_per_frame_sum") == 1.2
    assert get("v2v_sample_contrast_threshold_count", {"polarity": "pos"}) == 1
    assert get("v2v_sample_noise_std_sum") == 0.03
    assert get("v2v_sample_window_motion_bucket", {"le": "0.005"}) == 1  # a static window
    assert "# TYPE v2v_sample_events_per_pixel_second histogram" in text

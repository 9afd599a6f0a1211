"""v2v-eval: the H5 reader on files written by a test fixture (a synthetic moving edge),
the discrete voxel grids, the paper's metrics and the command line."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from trainer.config import default_config, merge
from trainer.evaluate import (H5Sequence, events_to_voxels, evaluate_e2vid, flow_metrics, main,
                              reconstruction_metrics, video_sequence)
from trainer.core import Trainer
from tests.trainer_fixtures import write_edge_events
from trainer.event_grids import voxel_grids
from trainer.recordings import EVENT_DTYPE

torch.set_num_threads(2)

H, W, DT, V, X0, NEV = 24, 32, 0.01, 200.0, 8.0, 3  # edge speed V px/s -> 2 px per frame interval


def write_moving_edge_h5(path, n_frames=6, with_flow=True):
    """TEST FIXTURE: an H5 file in the event_cnn_minimal layout for a vertical edge (dark
    right of it, bright left) moving right at V px/s. Each pixel column the edge crosses
    fires NEV positive events per row at the crossing time t_x = (x + 0.5 - X0) / V."""
    import h5py

    ts_img = np.arange(n_frames) * DT
    with h5py.File(path, "w") as f:
        f.attrs["sensor_resolution"] = (H, W)
        write_edge_events(f, W, H, NEV, lambda x: (x + 0.5 - X0) / V, keep=lambda t: 0 <= t < ts_img[-1])
        cols = np.arange(W)[None, :] + 0.5
        for i, t in enumerate(ts_img):
            img = np.where(cols < X0 + V * t, 200, 50).astype(np.uint8).repeat(H, 0)
            d = f.create_dataset(f"images/image{i:09d}", data=img)
            d.attrs["timestamp"] = t
            if with_flow and i < n_frames - 1:
                fl = np.zeros((2, H, W), np.float32)
                fl[0] = V * DT
                d = f.create_dataset(f"flow/flow{i:09d}", data=fl)
                d.attrs["timestamp"] = t
    return ts_img


def test_h5_reader_and_discrete_voxels(tmp_path):
    p = tmp_path / "edge.h5"
    ts_img = write_moving_edge_h5(p)
    seq = H5Sequence(str(p))
    assert (seq.height, seq.width) == (H, W) and seq.images.shape == (6, H, W)
    assert np.allclose(seq.image_ts, ts_img) and seq.flows.shape == (5, 2, H, W)
    vox, counts = seq.voxels(num_bins=2)
    assert vox.shape == (5, 2, H, W) and vox.dtype == np.int32
    for i in range(5):
        # interval i: the edge crosses columns 8 + 2i (first half: bin 0) and 9 + 2i (bin 1)
        expect = np.zeros((2, H, W), np.int32)
        expect[0, :, 8 + 2 * i] = NEV
        expect[1, :, 9 + 2 * i] = NEV
        assert np.array_equal(vox[i], expect), i
        assert np.array_equal(counts[i] > 0, expect.sum(0) > 0)
    assert int(vox.sum()) == len(seq.xs)


def test_events_to_voxels_signs_bins_and_errors():
    xs = np.array([0, 1, 1, 2, 2])
    ys = np.array([0, 0, 0, 1, 1])
    ts = np.array([0.0, 0.4, 0.6, 0.99, 1.5])
    ps = np.array([1, 0, 1, 1, -1])  # 0 and -1 are negative
    vox, counts = events_to_voxels(xs, ys, ts, ps, np.array([0.0, 1.0, 2.0]), 2, 2, 3)
    assert vox[0, 0, 0, 0] == 1 and vox[0, 0, 0, 1] == -1 and vox[0, 1, 0, 1] == 1 and vox[0, 1, 1, 2] == 1
    assert vox[1, 1, 1, 2] == -1 and counts[0, 0, 1] == 2 and counts[1].sum() == 1
    assert vox[0].sum() == 2 and np.abs(vox).sum() == 5
    with pytest.raises(ValueError):
        events_to_voxels(xs, ys, ts[::-1], ps, np.array([0.0, 1.0]), 2, 2, 3)
    with pytest.raises(ValueError):
        events_to_voxels(xs + 5, ys, ts, ps, np.array([0.0, 1.0]), 2, 2, 3)


def test_events_to_voxels_is_voxel_grids_over_whole_arrays():
    """Float seconds through events_to_voxels and integer microseconds through voxel_grids give
    the same grids (times exact in both units), with hand-checked values at the edges: an event
    on an edge opens the later interval, one just before it goes to the last bin."""
    ts = np.array([0.0, 0.25, 0.5, 0.75, 1.0, 1.125, 1.875, 2.5])  # 2.5: after the last edge, ignored
    xs, ys = np.array([0, 1, 2, 0, 1, 2, 0, 1]), np.array([0, 0, 1, 1, 0, 0, 1, 1])
    ps = np.array([1, 0, 1, 1, -1, 1, 0, 1])
    vox, counts = events_to_voxels(xs, ys, ts, ps, np.array([0.0, 1.0, 2.0]), 4, 2, 3)
    want = np.zeros((2, 4, 2, 3), np.int32)
    want[0, 0, 0, 0], want[0, 1, 0, 1], want[0, 2, 1, 2], want[0, 3, 1, 0] = 1, -1, 1, 1
    want[1, 0, 0, 1], want[1, 0, 0, 2], want[1, 3, 1, 0] = -1, 1, -1
    assert vox.dtype == np.int32 and counts.dtype == np.int32
    np.testing.assert_array_equal(vox, want)
    np.testing.assert_array_equal(counts, [[[1, 1, 0], [1, 0, 1]], [[0, 1, 1], [1, 0, 0]]])
    ev = np.zeros(len(ts), EVENT_DTYPE)
    ev["t"], ev["x"], ev["y"], ev["p"] = (ts * 1_000_000).astype(np.int64), xs, ys, np.where(ps > 0, 1, -1)
    grids = list(voxel_grids([ev[:3], ev[3:]], np.array([0, 1_000_000, 2_000_000]), 4, 2, 3))
    assert [k for k, _, _ in grids] == [0, 1]
    np.testing.assert_array_equal(np.stack([v for _, v, _ in grids]), vox)
    np.testing.assert_array_equal(np.stack([c for _, _, c in grids]), counts)
    empty, none = events_to_voxels(xs[:0], ys[:0], ts[:0], ps[:0], np.array([0.0, 1.0]), 2, 2, 3)
    assert empty.shape == (1, 2, 2, 3) and not empty.any() and not none.any()


def test_reconstruction_metrics_and_data_range_switch():
    rng = np.random.default_rng(0)
    gt = rng.random((32, 32))
    perfect = reconstruction_metrics(gt, gt)
    assert perfect["mse"] == 0.0 and perfect["ssim"] == pytest.approx(1.0)
    noisy = np.clip(gt + 0.1 * rng.standard_normal(gt.shape), 0, 1)
    m1, m2 = reconstruction_metrics(noisy, gt, 1.0), reconstruction_metrics(noisy, gt, 2.0)
    assert m1["mse"] == pytest.approx(np.mean((noisy - gt) ** 2))
    assert m2["ssim"] > m1["ssim"]  # the paper's data_range=2 convention reads higher
    over = reconstruction_metrics(gt + 5.0, gt)  # predictions are clipped to [0, 1]
    assert over["mse"] == pytest.approx(np.mean((1.0 - gt) ** 2))


def test_flow_metrics_dense_and_sparse():
    gt = np.zeros((2, 4, 4))
    gt[1] = 1.0  # (zero in both components would mark a pixel invalid)
    pred = gt.copy()
    pred[0, :2] = 4.0  # half the pixels off by 4 px
    mask = np.zeros((4, 4), bool)
    mask[0] = True
    m = flow_metrics(pred, gt, mask)
    assert m["aee"] == pytest.approx(2.0) and m["outlier_pct"] == pytest.approx(50.0)
    assert m["aee_sparse"] == pytest.approx(4.0) and m["outlier_pct_sparse"] == pytest.approx(100.0)
    assert np.isnan(flow_metrics(pred, gt, np.zeros((4, 4), bool))["aee_sparse"])


def test_video_sequence_uses_v2v_core(videos):
    vox, frames = video_sequence(str(videos / "bikes.mp4"), 5, max_frames=23, size=(48, 64))
    assert vox.shape == (4, 5, 48, 64) and frames.shape == (5, 48, 64) and frames.dtype == np.uint8
    assert np.abs(vox).sum() > 0


def _tiny_checkpoint(tmp_path, task):
    cfg = merge(default_config(task), {"model": {"num_bins": 2, "base_num_channels": 4}})
    t = Trainer(cfg, str(tmp_path / task), torch.device("cpu"))
    return str(t.save_checkpoint())


def test_eval_cli_on_fixture_h5(tmp_path, capsys):
    p = tmp_path / "edge.h5"
    write_moving_edge_h5(p)
    ck = _tiny_checkpoint(tmp_path, "e2vid")
    assert main(["--checkpoint", ck, "--h5", str(p), "--device", "cpu", "--out", str(tmp_path / "ev"),
                 "--save-images", "2"]) == 0
    res = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert res["task"] == "e2vid" and res["frames"] == 5
    for k in ("mse", "ssim", "base_mse", "base_ssim"):
        assert np.isfinite(res["mean"][k])
    # the baseline is the sequence-mean grey: its MSE is the frames' variance around it
    imgs = H5Sequence(str(p)).images[1:] / 255.0
    assert res["mean"]["base_mse"] == pytest.approx(np.mean((imgs - imgs.mean()) ** 2), rel=1e-6)
    assert (tmp_path / "ev" / "edge_00000.png").exists()
    ckf = _tiny_checkpoint(tmp_path, "evflow")
    assert main(["--checkpoint", ckf, "--h5", str(p), "--device", "cpu", "--out", str(tmp_path / "fl")]) == 0
    res = json.loads((tmp_path / "fl" / "metrics.json").read_text())
    assert set(res["mean"]) == {"aee", "outlier_pct", "aee_sparse", "outlier_pct_sparse", "valid_pct"}
    # an untrained net predicts ~0 flow: the error is ~ the true 2 px everywhere
    # 5 flows with timestamps: binned between them, 4 intervals are scored (flows 1..4)
    assert res["mean"]["aee"] == pytest.approx(2.0, abs=0.5) and res["frames"] == 4


def test_evaluate_e2vid_with_perfect_model():
    class Oracle(torch.nn.Module):  # returns the frame it is given through the voxel
        def forward(self, v, states=None):
            return v[:, :1], states

    frames = (np.random.default_rng(0).random((4, 16, 16)) * 255).astype(np.uint8)
    vox = np.stack([np.stack([frames[l + 1] / 255.0] * 2) for l in range(3)])
    r = evaluate_e2vid(Oracle(), vox, frames, torch.device("cpu"))
    assert np.allclose(r["mse"], 0.0) and np.allclose(r["ssim"], 1.0)
    assert all(b > 0 for b in r["base_mse"])


class _EdgeFlowFromEvents(torch.nn.Module):
    """A flow 'model' exact for the moving-edge fixture: the edge crosses one column per
    ``nev`` events in a row, so the columns crossed in a voxel are its x displacement."""

    def __init__(self, nev):
        super().__init__()
        self.nev = nev

    def forward(self, v):
        per_row = v.abs().sum(dim=(1, 3), keepdim=True) / self.nev  # (N, 1, H, 1) columns crossed
        u = per_row.amax(dim=2, keepdim=True).expand(v.shape[0], 1, v.shape[2], v.shape[3])
        return torch.cat([u, torch.zeros_like(u)], dim=1)


def test_flow_evaluation_masks_invalid_ground_truth_and_bins_between_flow_timestamps(tmp_path):
    from tests.trainer_fixtures import write_mvsec_like_h5
    from trainer.evaluate import evaluate_evflow

    p = tmp_path / "mvsec_like.h5"
    image_ts, flow_ts = write_mvsec_like_h5(p, nev=2)
    seq = H5Sequence(str(p))
    assert np.allclose(seq.flow_ts, flow_ts) and np.isnan(seq.flows).any()
    vox, counts, gt = seq.flow_voxels(num_bins=2)
    assert vox.shape[0] == len(flow_ts) - 1 and np.array_equal(gt, seq.flows[1:], equal_nan=True)
    for k in range(len(flow_ts) - 1):  # each voxel holds exactly the events of [flow_ts[k], flow_ts[k+1])
        inside = (seq.ts >= flow_ts[k]) & (seq.ts < flow_ts[k + 1])
        assert int(counts[k].sum()) == int(inside.sum()) > 0
    res = evaluate_evflow(_EdgeFlowFromEvents(nev=2), vox, gt, counts, torch.device("cpu"))
    # 200 px/s over 0.02 s: 4 columns crossed, the ground truth's 4 px, on every valid pixel
    assert res["aee"] == pytest.approx([0.0] * 3, abs=1e-9)
    assert all(np.isfinite(res["aee_sparse"])) and res["valid_pct"] == pytest.approx([100 * 12 / 16 * 42 / 48] * 3)
    # binned between image timestamps (0.01 s apart) the same model is 2 px off
    ivox, icounts = seq.voxels(num_bins=2)
    off = evaluate_evflow(_EdgeFlowFromEvents(nev=2), ivox[:3], gt, icounts[:3], torch.device("cpu"))
    assert off["aee"] == pytest.approx([2.0] * 3)


def test_flow_metrics_ignore_nan_and_zero_ground_truth():
    gt = np.full((2, 4, 4), 3.0)
    gt[:, 0] = np.nan          # no depth
    gt[0, 1, :2] = np.nan      # one component NaN
    gt[:, 2, :] = 0.0          # zero in both: invalid
    gt[0, 3, 0], gt[1, 3, 0] = 0.0, 5.0  # zero in one only: valid
    pred = np.full((2, 4, 4), 3.0)
    m = flow_metrics(pred, gt, event_mask=np.ones((4, 4), bool))
    valid = 2 + 4  # row 1 right half, row 3
    assert m["valid_pct"] == pytest.approx(100 * valid / 16)
    assert m["aee"] == pytest.approx(np.hypot(3, 2) / valid)  # only the (0, 5) pixel is off
    assert m["aee_sparse"] == pytest.approx(m["aee"])
    empty = flow_metrics(pred, np.full((2, 4, 4), np.nan))
    assert np.isnan(empty["aee"]) and empty["valid_pct"] == 0.0

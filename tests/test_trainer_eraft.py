"""E-RAFT in trainer/: the network against the V2V authors' (tests/data/eraft_reference.json,
derived from their classes by harness/eraft_reference.py), its warm start, the eraft task's
pairing of voxel grids, its config, v2v-eval's scoring, and v2v-train against a real
v2v-serve on 127.0.0.1."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from harness.serve import ServeProcess
from tests.trainer_fixtures import FakeV2VStream
import trainer.train as tr
from trainer.config import default_config, load_config, merge
from trainer.core import Trainer, build_optimizer
from trainer.data import batch_to_device
from trainer.models.eraft import forward_interpolate, min_side
from trainer.evaluate import evaluate_eraft
from trainer.tasks import stream_outputs
from trainer.zoo import build_model
from tests.test_trainer_raft import StandInRaft, stand_in_torchvision  # noqa: F401 (a fixture)

torch.set_num_threads(2)

REF = json.loads((Path(__file__).parent / "data" / "eraft_reference.json").read_text())
#: CPU-sized E-RAFT: 3 bins (FakeV2VStream's), 3 correlation levels (64-pixel inputs), 2 iterations
TINY = {"num_bins": 3, "iters": 2, "corr_levels": 3}


def tiny_cfg(**extra):
    return merge(default_config("eraft"), merge({"model": TINY, "optim": {"lr": 1e-3}}, extra))


def test_default_model_matches_the_authors_state_dict_and_parameter_count():
    m = build_model("eraft", default_config("eraft")["model"])
    ours = {k: list(v.shape) for k, v in m.state_dict().items()}
    assert list(ours.items()) == list(REF["eraft"]["state_dict"].items())  # names, shapes and order
    assert sum(p.numel() for p in m.parameters()) == REF["eraft"]["parameters"] == 5270080
    per = {}
    for name, p in m.named_parameters():
        per[name.split(".")[0]] = per.get(name.split(".")[0], 0) + p.numel()
    assert per == REF["eraft"]["parameters_per_module"]
    # their checkpoint's layout loads strictly into ours
    assert not build_model("eraft", {}).load_state_dict(m.state_dict(), strict=True).missing_keys


def test_forward_backward_shapes_padding_and_gradients():
    torch.manual_seed(0)
    m = build_model("eraft", TINY).train()
    a, b = torch.randn(2, 3, 60, 70), torch.randn(2, 3, 60, 70)  # padded top/left to 64 x 96
    flow = m(a, b)
    assert flow.shape == (2, 2, 60, 70) and flow.dtype == torch.float32 and torch.isfinite(flow).all()
    flow.abs().mean().backward()
    for name, p in m.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    assert sum(float(p.grad.abs().sum()) > 0 for p in m.parameters()) == len(list(m.parameters()))
    with pytest.raises(ValueError, match="must be"):
        m(torch.randn(1, 5, 64, 64), torch.randn(1, 5, 64, 64))
    with pytest.raises(ValueError, match="padded sides >= 128"):
        build_model("eraft", {"num_bins": 3})(torch.randn(1, 3, 64, 64), torch.randn(1, 3, 64, 64))
    assert min_side(4) == 128 and min_side(3) == 64


def test_warm_start_carries_the_splatted_flow_to_the_next_pair():
    torch.manual_seed(0)
    m = build_model("eraft", TINY).eval()
    g = torch.Generator().manual_seed(1)
    v = torch.randn(3, 1, 3, 64, 64, generator=g)
    with torch.no_grad():
        m.reset_states()
        m(v[0], v[1])
        init = m.flow_init.clone()
        m.reset_states()
        low, _ = m.forward_all(v[0], v[1])  # the same pair from zero flow; forward_all keeps no state
        assert torch.equal(init, forward_interpolate(low)) and m.flow_init is None
        m.flow_init = init
        warm = m(v[1], v[2])
        m.reset_states()
        cold = m(v[1], v[2])
    assert init.shape == (1, 2, 8, 8) and float(init.abs().max()) > 0
    assert not torch.allclose(warm, cold)  # the previous pair's flow initialised the second
    std = build_model("eraft", {**TINY, "subtype": "standard"}).eval()
    with torch.no_grad():
        std(v[0], v[1])
    assert std.flow_init is None


def test_forward_interpolate_moves_flow_to_where_it_points():
    f = torch.zeros(1, 2, 4, 5)
    f[0, 0, 1, 1] = 2.0  # pixel (x=1, y=1) moves 2 px right, onto (3, 1), whose own flow is 0
    f[0, 1, 2, 3] = 0.5  # pixel (x=3, y=2) moves half a pixel down: weight 1/2 on rows 2 and 3
    out = forward_interpolate(f)
    assert float(out[0, 0, 1, 1]) == 0.0  # nothing lands there
    assert float(out[0, 0, 1, 3]) == pytest.approx(1.0)  # mean of 2 and (3, 1)'s own 0, equal weights
    assert float(out[0, 1, 2, 3]) == pytest.approx(0.5)  # only the moved pixel lands on row 2
    # row 3: (3, 3)'s own 0 (integer target: four corners of weight 1) and the half of 0.5 (two of 1/2)
    assert float(out[0, 1, 3, 3]) == pytest.approx(0.5 * 1.0 / 5.0)
    mixed = forward_interpolate(torch.full((1, 2, 4, 5), 1.0))
    assert float(mixed[0, 0, 0, 0]) == 0.0 and float(mixed[0, 0, 3, 4]) == pytest.approx(1.0)


def test_config_file_has_the_authors_settings():
    cfg = load_config("trainer/configs/eraft.yaml")
    assert cfg["task"] == "eraft"
    assert cfg["model"] == {"num_bins": 5, "subtype": "warm_start", "iters": 12, "corr_levels": 4, "corr_radius": 4}
    opt = build_optimizer(build_model("eraft", cfg["model"]), cfg["optim"])
    assert isinstance(opt, torch.optim.Adam) and opt.defaults["lr"] == 1e-4 and opt.defaults["amsgrad"]
    assert opt.defaults["weight_decay"] == 0
    assert stream_outputs(cfg) == ("voxels", "flow")
    assert stream_outputs(merge(cfg, {"loss": {"flow_source": "raft_large"}})) == ("voxels", "frames")


def test_task_pairs_voxel_l_minus_1_and_l_against_the_flow_of_voxel_l(tmp_path):
    cfg = tiny_cfg()
    t = Trainer(cfg, str(tmp_path), torch.device("cpu"))
    batch = next(iter(FakeV2VStream(outputs=("voxels", "flow"), batch_size=2, sequence_length=4, crop=64)))
    b = batch_to_device(batch, torch.device("cpu"), t.spec.outputs, flow_from=t.spec.flow_from(4))
    assert b["flow"].shape[1] == 3  # voxels 1..3 have a predecessor
    t.model.train()
    loss, stats, preds = t.forward(dict(b))
    assert preds.shape == (2, 3, 2, 64, 64)
    # the same through the network directly: reset, then (v0, v1), (v1, v2), (v2, v3)
    t.model.reset_states()
    ref = [t.model(b["voxels"][:, l - 1], b["voxels"][:, l]) for l in range(1, 4)]
    l1 = sum((r - batch["flow"][:, l].float()).abs().mean() for r, l in zip(ref, range(1, 4))) / 3
    l1 = float(l1.detach())
    assert float(loss.detach()) == pytest.approx(l1, rel=1e-5)
    assert stats["flow_l1"] == pytest.approx(l1, rel=1e-5) and stats["aee"] > 0
    torch.testing.assert_close(preds, torch.stack([r.detach() for r in ref], 1), atol=1e-4, rtol=1e-4)
    with pytest.raises(ValueError, match="at least 2"):
        t.forward({"voxels": b["voxels"][:, :1], "flow": b["flow"][:, :0]})


def test_training_steps_lower_the_loss_on_a_fixed_batch(tmp_path):
    t = Trainer(tiny_cfg(optim={"lr": 1e-4}), str(tmp_path), torch.device("cpu"))  # the authors' lr
    batch = next(iter(FakeV2VStream(outputs=("voxels", "flow"), batch_size=2, sequence_length=3, crop=64, fixed=True)))
    losses = [t.train_step(batch)["loss"] for _ in range(6)]
    assert np.all(np.isfinite(losses)) and losses[-1] < losses[0]
    t.save_samples()
    assert (tmp_path / "samples" / "step_0000006.png").exists()


def test_v2v_eval_pairs_and_chunks_as_the_authors_test():
    torch.manual_seed(0)
    m = build_model("eraft", TINY).eval()
    rng = np.random.default_rng(0)
    vox = rng.integers(-2, 3, (5, 3, 64, 64)).astype(np.float32)
    gt = rng.normal(0, 1, (5, 2, 64, 64)).astype(np.float32)
    r = evaluate_eraft(m, vox, gt, None, torch.device("cpu"), sequence_length=3)
    assert len(r["aee"]) == 5 and np.isnan(r["aee_sparse"][0])  # no grid before voxel 0: empty mask
    # by hand: a zero grid before voxel 0, warm start reset at voxels 0 and 3
    with torch.no_grad():
        t = lambda k: torch.from_numpy(vox[k])[None]
        m.reset_states()
        p = [m(torch.zeros(1, 3, 64, 64), t(0)), m(t(0), t(1)), m(t(1), t(2))]
        m.reset_states()
        p += [m(t(2), t(3)), m(t(3), t(4))]
    aee = [float(np.sqrt(((q[0].numpy() - g) ** 2).sum(0)).mean()) for q, g in zip(p, gt)]
    np.testing.assert_allclose(r["aee"], aee, rtol=1e-5)


def test_v2v_train_eraft_from_a_live_server(tmp_path, bikes_corpus):
    vids = bikes_corpus
    out = tmp_path / "run"
    serve = ["--videos", str(vids), "--workers", "1", "--sequence-length", "3", "--num-bins", "3",
             "--crop-size", "64", "--batch-size", "2", "--seed", "3", "--max-samples-per-video", "4"]
    with ServeProcess(serve) as srv:
        args = ["--config", "trainer/configs/eraft.yaml", "--connect", srv.endpoint, "--out", str(out),
                "--device", "cpu", "--no-progress", "--set", "model.num_bins=3", "--set", "model.iters=2",
                "--set", "model.corr_levels=3", "--set", "optim.lr=0.001", "--set", "stream.timeout_s=60",
                "--max-steps", "2"]
        assert tr.main(args) == 0
    rows = list(csv.DictReader(open(out / "train_log.csv")))
    assert [int(r["step"]) for r in rows] == [1, 2]
    assert all(np.isfinite(float(r["loss"])) and float(r["aee"]) >= 0 for r in rows)
    ck = torch.load(out / "checkpoint_last.pt", weights_only=False)
    assert ck["task"] == "eraft" and ck["step"] == 2
    assert set(ck["model"]) == set(build_model("eraft", ck["config"]["model"]).state_dict())
    # the CPU demo's held-out check scores what v2v-train wrote
    from harness.eraft_demo import heldout_clips, score

    res = score(str(out / "checkpoint_last.pt"), heldout_clips(num_bins=3, voxels=3, displacements=[2.0]))
    assert len(res["clips"]) == 3 and np.isfinite(res["epe"]) and res["zero_flow_epe"] > 0


def test_v2v_eval_cli_scores_an_eraft_checkpoint(tmp_path):
    from tests.test_trainer_eval import write_moving_edge_h5
    from trainer.evaluate import main

    p = tmp_path / "edge.h5"
    write_moving_edge_h5(p)  # 24 x 32: padded to 32 x 32, so 2 correlation levels
    cfg = merge(default_config("eraft"), {"model": {"num_bins": 2, "iters": 1, "corr_levels": 2}})
    ck = str(Trainer(cfg, str(tmp_path / "run"), torch.device("cpu")).save_checkpoint())
    assert main(["--checkpoint", ck, "--h5", str(p), "--device", "cpu", "--out", str(tmp_path / "fl")]) == 0
    res = json.loads((tmp_path / "fl" / "metrics.json").read_text())
    assert res["task"] == "eraft" and res["frames"] == 4  # 5 timestamped flows: 4 intervals scored
    assert set(res["mean"]) == {"aee", "outlier_pct", "aee_sparse", "outlier_pct_sparse", "valid_pct"}
    assert np.isfinite(res["mean"]["aee"])


def test_eraft_targets_come_from_raft_large_on_frames_1_to_L(stand_in_torchvision, tmp_path):
    """loss.flow_source raft_large (the authors'): RAFT sees the frame pairs of voxels 1..L-1."""
    torch.save(StandInRaft().state_dict(), stand_in_torchvision / "raft_large-2dfb8e49.pth")
    cfg = tiny_cfg(loss={"flow_source": "raft_large", "raft_num_flow_updates": 12})
    t = Trainer(cfg, str(tmp_path / "run"), torch.device("cpu"))
    batch = next(iter(FakeV2VStream(outputs=stream_outputs(cfg), sequence_length=4, crop=64)))
    stats = t.train_step(batch)
    (img1, img2, k), = t.spec.raft.net.calls
    assert img1.shape[0] == 2 * 3 and k == 12  # 2 samples x pairs (1, 2), (2, 3), (3, 4) of frames
    frames = batch["frames"].float() / 255
    assert torch.allclose(img1[:, 0, :64, :64], frames[:, 1:4].flatten(0, 1)[:, 0] * 2 - 1, atol=1e-6)
    assert stats["aee"] > 0 and np.isfinite(stats["loss"])

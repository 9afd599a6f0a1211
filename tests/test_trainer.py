"""The trainer: models, losses, LPIPS loading/fallback, the training loop, checkpoints and
resume, against the FakeV2VStream test fixture (tests/trainer_fixtures.py)."""
from __future__ import annotations

import csv
import logging
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.trainer_fixtures import FakeV2VStream
from trainer.models import lpips as lpips_net
from trainer.config import apply_overrides, default_config, load_config, merge
from trainer.data import batch_to_device
from trainer.losses import ReconstructionLoss, flow_l1_loss, ssim, temporal_consistency_loss, warp
from trainer.zoo import build_model
from trainer.core import Trainer
from trainer.tasks import get_task, tc_start_index

torch.set_num_threads(2)

TINY = {"e2vid": {"num_bins": 3, "base_num_channels": 4},
        "evflow": {"num_bins": 3, "base_num_channels": 4}}


def tiny_cfg(task, **extra):
    return merge(default_config(task), merge({"model": TINY[task], "optim": {"lr": 1e-3}}, extra))


def outputs(task):
    return get_task(task).outputs


# ----------------------------------------------------------------------------- models
def test_e2vid_matches_reference_architecture():
    m = build_model("e2vid", {}).unetrecurrent  # paper config: 5 bins, base 32, 3 encoders, sum skips, 2 resblocks
    assert [e.conv.conv2d.out_channels for e in m.encoders] == [64, 128, 256]
    assert all(e.recurrent_block.hidden_size == c for e, c in zip(m.encoders, [64, 128, 256]))
    assert [e.conv.conv2d.kernel_size for e in m.encoders] == [(5, 5)] * 3
    assert len(m.resblocks) == 2
    # sum skips: decoder inputs are not doubled
    assert [d.conv2d.in_channels for d in m.decoders] == [256, 128, 64]
    assert m.pred.conv2d.in_channels == 32 and m.pred.conv2d.out_channels == 1 and not m.pred.relu
    x = torch.randn(2, 5, 40, 56)  # not a multiple of 8: padded and cropped back
    y, st = m(x)
    assert y.shape == (2, 1, 40, 56) and len(st) == 3
    y2, _ = m(x, st)  # the recurrent state changes the output
    assert not torch.allclose(y, y2)


def test_e2vid_state_dicts_with_this_trainers_own_earlier_key_names_still_load():
    torch.manual_seed(0)
    m = build_model("e2vid", {"num_bins": 3, "base_num_channels": 4})
    own = {k.removeprefix("unetrecurrent.").replace(".recurrent_block.Gates.", ".lstm.gates."): v
           for k, v in m.state_dict().items()}
    assert "encoders.0.lstm.gates.weight" in own and not any(k.startswith("unetrecurrent.") for k in own)
    fresh = build_model("e2vid", {"num_bins": 3, "base_num_channels": 4})
    fresh.load_state_dict(own)  # strict: every key renamed onto a parameter
    x = torch.randn(1, 3, 16, 16)
    assert torch.equal(fresh(x)[0], m(x)[0])
    assert [n for n, _ in fresh.named_parameters()] == [n for n, _ in m.named_parameters()]


#: The V2V reference's EVFlowNet parameters (model/model.py EVFlowNet -> model/unet.py UNet,
#: event_cnn_minimal; 5 bins, base 32, 4 encoders, concat skips, kernel 3, 2 residual
#: blocks, no head layer), written out from the architecture: name -> weight shape (every
#: conv also has a bias of shape (out,)).
REFERENCE_EVFLOWNET = {
    "unet.encoders.0.conv2d": (64, 5, 3, 3),
    "unet.encoders.1.conv2d": (128, 64, 3, 3),
    "unet.encoders.2.conv2d": (256, 128, 3, 3),
    "unet.encoders.3.conv2d": (512, 256, 3, 3),
    "unet.resblocks.0.conv1": (512, 512, 3, 3),
    "unet.resblocks.0.conv2": (512, 512, 3, 3),
    "unet.resblocks.1.conv1": (512, 512, 3, 3),
    "unet.resblocks.1.conv2": (512, 512, 3, 3),
    "unet.decoders.0.conv2d": (256, 1024, 3, 3),
    "unet.decoders.1.conv2d": (128, 512, 3, 3),
    "unet.decoders.2.conv2d": (64, 256, 3, 3),
    "unet.decoders.3.conv2d": (32, 128, 3, 3),
    "unet.pred.conv2d": (2, 32, 1, 1),
}


def reference_evflownet_forward(sd, x):
    """The reference UNet.forward written out with torch.nn.functional on a state dict."""
    import torch.nn.functional as F

    def conv(name, t, stride=1, relu=True):
        w = sd[name + ".weight"]
        t = F.conv2d(t, w, sd[name + ".bias"], stride=stride, padding=w.shape[-1] // 2)
        return F.relu(t) if relu else t

    blocks = []
    for i in range(4):
        x = conv(f"unet.encoders.{i}.conv2d", x, stride=2)
        blocks.append(x)
    for j in range(2):
        r = conv(f"unet.resblocks.{j}.conv2", conv(f"unet.resblocks.{j}.conv1", x), relu=False)
        x = F.relu(r + x)
    for i in range(4):
        x = torch.cat([x, blocks[3 - i]], dim=1)
        x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)
        x = conv(f"unet.decoders.{i}.conv2d", x)
    return conv("unet.pred.conv2d", x, relu=False)


def test_evflownet_is_the_reference_unet_and_loads_its_state_dict():
    m = build_model("evflow", {})
    want = {}
    for name, shape in REFERENCE_EVFLOWNET.items():
        want[name + ".weight"] = shape
        want[name + ".bias"] = shape[:1]
    assert {k: tuple(v.shape) for k, v in m.state_dict().items()} == want
    g = torch.Generator().manual_seed(0)
    ref_sd = {k: 0.05 * torch.randn(shape, generator=g) for k, shape in want.items()}
    m.load_state_dict(ref_sd, strict=True)  # a reference checkpoint's state_dict loads as it is
    x = torch.randn(1, 5, 32, 48, generator=g)
    with torch.no_grad():
        assert torch.allclose(m(x), reference_evflownet_forward(ref_sd, x), atol=1e-5)
        assert m(torch.randn(1, 5, 24, 40)).shape == (1, 2, 24, 40)  # padded and cropped back
    with pytest.raises(ValueError):
        m(torch.randn(1, 4, 16, 16))
    with pytest.raises(ValueError):
        build_model("e2vid", {"bogus": 1})


# ----------------------------------------------------------------------------- losses
def test_ssim_equals_skimage():
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(0)
    a = rng.random((2, 1, 20, 24)).astype(np.float32)
    b = np.clip(a + 0.2 * rng.standard_normal(a.shape), 0, 1).astype(np.float32)
    got = ssim(torch.from_numpy(a), torch.from_numpy(b)).numpy()
    for i in range(2):
        ref = structural_similarity(a[i, 0], b[i, 0], win_size=7, data_range=1.0)
        assert got[i] == pytest.approx(ref, abs=1e-5)
    assert ssim(torch.from_numpy(a), torch.from_numpy(a)).numpy() == pytest.approx(1.0, abs=1e-6)


def test_warp_translates_by_flow():
    img = torch.arange(8 * 10, dtype=torch.float32).view(1, 1, 8, 10)
    flow = torch.zeros(1, 2, 8, 10)
    flow[:, 0] = 2.0  # out(x) = img(x + 2)
    out, valid = warp(img, flow)
    assert torch.allclose(out[..., :8], img[..., 2:])
    assert valid[..., :8].all() and not valid[..., 8:].any()


def _translated_pair(shift=3):
    rng = np.random.default_rng(1)
    base = torch.from_numpy(rng.random((1, 1, 24, 40)).astype(np.float32))
    f0 = base[..., :, : 40 - shift]
    f1 = base[..., :, shift:]  # content moves by -shift px: flow 0->1 is (-shift, 0)
    flow = torch.zeros(1, 2, 24, 40 - shift)
    flow[:, 0] = -float(shift)
    return f0, f1, flow


def test_temporal_consistency_small_for_consistent_predictions_and_off_where_occluded():
    f0, f1, flow = _translated_pair()
    consistent = temporal_consistency_loss(f0, f1, f0, f1, flow)  # only the border the motion reveals differs
    inconsistent = temporal_consistency_loss(f0, f1, f0, torch.rand_like(f1), flow)
    assert float(consistent) < float(inconsistent) / 3
    # where the ground truth disagrees after warping by 1.0 (|dI| = 1), the weight is exp(-50)
    pred1 = torch.rand_like(f1)
    occluded = temporal_consistency_loss(f0, f1 + 1.0, f0, pred1, flow)
    assert float(inconsistent) > 0.05 and float(occluded) < 1e-20


def reference_tc(image0, image1, processed0, processed1, flow, alpha=50.0):
    """Direct transcription of the V2V reference: model/loss.py temporal_consistency_loss
    calls utils/loss.py temporal_consistency_loss(image0, image1, processed0, processed1,
    -flow), flow being the forward flow image0 -> image1."""
    import torch.nn.functional as F

    flow01 = -flow
    t_width, t_height = image0.shape[3], image0.shape[2]
    xx, yy = torch.meshgrid(torch.arange(t_width), torch.arange(t_height), indexing="xy")
    xx, yy = xx.float(), yy.float()
    warping_grid_x = (2 * (xx + flow01[:, 0]) / (t_width - 1)) - 1
    warping_grid_y = (2 * (yy + flow01[:, 1]) / (t_height - 1)) - 1
    warping_grid = torch.stack([warping_grid_x, warping_grid_y], dim=3)
    image0_warped_to1 = F.grid_sample(image0, warping_grid, align_corners=True)
    visibility_mask = torch.exp(-alpha * (image1 - image0_warped_to1) ** 2)
    processed0 = torch.clamp(processed0, 0, 255)
    processed0_warped_to1 = F.grid_sample(processed0, warping_grid, align_corners=True)
    div = torch.abs(processed1) + torch.abs(processed0_warped_to1) + 1e-5
    return (visibility_mask * torch.abs(processed1 - processed0_warped_to1) / div).mean()


def test_temporal_consistency_reference_form_equals_the_reference_code():
    g = torch.Generator().manual_seed(3)
    for _ in range(3):
        f0, f1 = torch.rand(2, 1, 20, 28, generator=g), torch.rand(2, 1, 20, 28, generator=g)
        p0 = torch.randn(2, 1, 20, 28, generator=g)  # negative values: clamped as the reference does
        p1 = torch.randn(2, 1, 20, 28, generator=g)
        flow = 4 * torch.randn(2, 2, 20, 28, generator=g)
        got = temporal_consistency_loss(f0, f1, p0, p1, flow)
        assert float(got) == pytest.approx(float(reference_tc(f0, f1, p0, p1, flow)), rel=1e-5)
        # the relative error is scale-free
        ref = temporal_consistency_loss(f0, f1, p0.abs(), 2 * p1.abs(), flow)
        ref2 = temporal_consistency_loss(f0, f1, 2 * p0.abs(), 4 * p1.abs(), flow)
        assert float(ref2) == pytest.approx(float(ref), rel=1e-4)


def test_training_step_averages_tc_over_all_steps_like_the_reference(tmp_path):
    """E2VID step: tc = (1 / L) * sum over l >= L0 of the reference loss between consecutive
    reconstructions (the reference's calc_loss: zeros before L0, mean over T)."""
    cfg = tiny_cfg("e2vid", loss={"perceptual_weight": 0.0})
    tr = Trainer(cfg, tmp_path, torch.device("cpu"))
    batch = next(iter(FakeV2VStream(sequence_length=4, num_bins=3, crop=32)))
    L = batch["voxels"].shape[1]
    l0 = tc_start_index(L, 0.5)
    b = batch_to_device(batch, torch.device("cpu"), outputs("e2vid"), flow_from=l0)
    tr.model.eval()
    with torch.no_grad():
        _, stats, preds = tr.forward(b)
    fr, fl = b["frames"], b["flow"]
    want = sum(float(reference_tc(fr[:, l], fr[:, l + 1], preds[l - 1], preds[l], fl[:, l - l0]))
               for l in range(l0, L)) / L
    assert stats["tc"] == pytest.approx(want, rel=1e-5) and want > 0


def test_fp32_by_default_bf16_an_option(tmp_path):
    assert default_config("e2vid")["amp"] == "fp32" and default_config("evflow")["amp"] == "fp32"
    for task in ("e2vid", "evflow"):
        assert load_config(str(Path(__file__).parents[1] / "trainer" / "configs" / f"{task}.yaml"), task)["amp"] == "fp32"
    with pytest.raises(ValueError, match="amp"):
        Trainer(tiny_cfg("evflow", amp="fp16"), tmp_path, torch.device("cpu"))
    assert Trainer(tiny_cfg("evflow", amp="bf16"), tmp_path, torch.device("cpu")).amp  # autocast on the CPU too
    assert not Trainer(tiny_cfg("evflow"), tmp_path, torch.device("cpu")).amp


def test_flow_l1():
    a = torch.zeros(2, 2, 4, 4)
    b = torch.ones(2, 2, 4, 4) * 3
    assert float(flow_l1_loss(a, b)) == pytest.approx(3.0)


# ----------------------------------------------------------------------------- LPIPS
def _random_lpips_package_state(net):
    """State dict named like lpips.LPIPS(net=net).state_dict() (test weights, random)."""
    m = lpips_net.LPIPSNet(net)
    torch.manual_seed(0)
    slices = {"vgg": [(0, 4), (4, 9), (9, 16), (16, 23), (23, 30)], "alex": [(0, 2), (2, 5), (5, 8), (8, 10), (10, 12)]}[net]
    sd = {}
    for k, (a, b) in enumerate(slices, start=1):
        for i in range(a, b):
            layer = m.features[i]
            if isinstance(layer, torch.nn.Conv2d):
                sd[f"net.slice{k}.{i}.weight"] = torch.randn_like(layer.weight) * 0.05
                sd[f"net.slice{k}.{i}.bias"] = torch.randn_like(layer.bias) * 0.05
    for k, lin in enumerate(m.lins):
        sd[f"lin{k}.model.1.weight"] = torch.rand_like(lin.weight)
    sd["scaling_layer.shift"] = torch.zeros(1, 3, 1, 1)
    return sd


def test_lpips_fallback_to_ssim_logged_once(caplog, monkeypatch):
    monkeypatch.setattr(ReconstructionLoss, "_warned", False)
    with caplog.at_level(logging.WARNING):
        a = ReconstructionLoss(use_lpips_package=False)
        b = ReconstructionLoss(use_lpips_package=False)
    assert a.perceptual == "ssim" and b.perceptual == "ssim"
    assert sum("SSIM" in r.message for r in caplog.records) == 1
    x = torch.rand(2, 1, 16, 16)
    r = a(x, x)
    assert float(r["ssim"]) == pytest.approx(0.0, abs=1e-5) and float(r["total"]) == pytest.approx(0.0, abs=1e-5)
    r = a(x, torch.rand(2, 1, 16, 16))
    assert float(r["ssim"]) > 0.5


@pytest.mark.parametrize("net", ["vgg", "alex"])
def test_lpips_loads_package_layout_weights(tmp_path, net):
    sd = _random_lpips_package_state(net)
    p = tmp_path / f"lpips_{net}.pth"
    torch.save(sd, p)
    m = lpips_net.load_lpips(net, str(p), use_package=False)
    assert isinstance(m, lpips_net.LPIPSNet)
    # weights landed on the torchvision-indexed layers
    idx, sl = {"vgg": (2, 1), "alex": (3, 2)}[net]  # a conv inside the first / second slice
    assert torch.equal(m.features[idx].weight, sd[f"net.slice{sl}.{idx}.weight"])
    assert torch.equal(m.lins[4].weight, sd["lin4.model.1.weight"])
    x = torch.rand(2, 1, 64, 64)
    y = torch.rand(2, 1, 64, 64)
    d_same, d_diff = m(x, x), m(x, y)
    assert d_same.shape == (2,) and torch.allclose(d_same, torch.zeros(2))
    assert (d_diff > 0).all()
    # the perceptual term in the E2VID loss is LPIPS when weights are given
    loss = ReconstructionLoss(lpips_net=net, lpips_weights=[str(p)], use_lpips_package=False)
    assert loss.perceptual == "lpips"
    assert float(loss(x, y)["lpips"]) == pytest.approx(float(d_diff.mean()), rel=1e-5)


def test_lpips_torchvision_backbone_plus_linear_heads(tmp_path):
    sd = _random_lpips_package_state("vgg")
    backbone = {k.replace(f"net.slice{k.split('.')[1][-1]}.", "features."): v for k, v in sd.items() if k.startswith("net.")}
    backbone["classifier.0.weight"] = torch.zeros(3)  # ignored
    lins = {k: v for k, v in sd.items() if k.startswith("lin")}
    torch.save(backbone, tmp_path / "vgg16.pth")
    torch.save(lins, tmp_path / "vgg.pth")
    m = lpips_net.load_lpips("vgg", [str(tmp_path / "vgg16.pth"), str(tmp_path / "vgg.pth")], use_package=False)
    assert torch.equal(m.features[28].weight, sd["net.slice5.28.weight"])
    with pytest.raises(ValueError, match="incomplete"):
        lpips_net.load_lpips("vgg", str(tmp_path / "vgg.pth"), use_package=False)
    with pytest.raises(FileNotFoundError):
        lpips_net.load_lpips("vgg", str(tmp_path / "missing.pth"))


# ----------------------------------------------------------------------------- data
def test_batch_to_device_converts_raw_and_slices_flow():
    ds = FakeV2VStream(batch_size=2, sequence_length=4, num_batches=1)
    b = next(iter(ds))
    assert b["voxels"].dtype == torch.int8 and b["frames"].dtype == torch.uint8 and b["flow"].dtype == torch.float16
    l0 = tc_start_index(4, 0.5)
    d = batch_to_device(b, torch.device("cpu"), outputs("e2vid"), flow_from=l0)
    assert d["voxels"].dtype == torch.float32 and torch.equal(d["voxels"], b["voxels"].float())
    assert d["frames"].max() <= 1.0 and torch.allclose(d["frames"] * 255, b["frames"].float())
    assert d["flow"].shape[1] == 4 - l0 and torch.equal(d["flow"], b["flow"][:, l0:].float())
    assert tc_start_index(40, 0.5) == 20
    with pytest.raises(KeyError):
        batch_to_device({"voxels": b["voxels"]}, torch.device("cpu"), outputs("evflow"))


def test_config_files_and_overrides():
    e = load_config("trainer/configs/e2vid.yaml")
    assert e["optim"] == {"optimizer": "adam", "lr": 1e-4, "amsgrad": True, "weight_decay": 0.0, "lr_gamma": 1.0,
                          "lr_gamma_every": 1000, "clip_grad_norm": None}
    assert e["model"]["skip_type"] == "sum" and e["model"]["num_encoders"] == 3 and e["loss"]["tc_alpha"] == 50
    f = load_config("trainer/configs/e2vid.yaml", task="evflow")  # --task switch uses evflow's model
    assert f["model"]["skip_type"] == "concat" and "tc_weight" not in f["loss"]
    g = apply_overrides(e, ["model.base_num_channels=8", "optim.lr=0.001"])
    assert g["model"]["base_num_channels"] == 8 and g["optim"]["lr"] == 0.001
    with pytest.raises(ValueError):
        apply_overrides(e, ["optim.nope=1"])


def test_config_values_are_typed_and_bad_ones_named(tmp_path):
    e = load_config("trainer/configs/e2vid.yaml")
    # YAML 1.1 reads "3e-4" as a string; the trainer stores the number it means
    g = apply_overrides(e, ["optim.lr=3e-4", "optim.clip_grad_norm=1", "stream.timeout_s=5"])
    assert g["optim"]["lr"] == 3e-4 and isinstance(g["optim"]["lr"], float)
    assert g["optim"]["clip_grad_norm"] == 1.0 and g["stream"]["timeout_s"] == 5.0
    for item, field in [("optim.lr=fast", "optim.lr"), ("log.checkpoint_every=2.5", "log.checkpoint_every"),
                        ("optim.amsgrad=1", "optim.amsgrad"), ("max_steps=many", "max_steps"),
                        ("loss.tc_alpha=[1]", "loss.tc_alpha")]:
        with pytest.raises(ValueError, match=field.replace(".", r"\.")):
            apply_overrides(e, [item])
    p = tmp_path / "bad.yaml"
    p.write_text("task: e2vid\noptim:\n  lr: 1e-3\n  weight_decay: none\n")
    with pytest.raises(ValueError, match="optim.weight_decay") as err:
        load_config(str(p))
    assert str(p) in str(err.value)
    p.write_text("task: e2vid\noptim:\n  lr: 1e-3\n")
    assert load_config(str(p))["optim"]["lr"] == 1e-3


# ----------------------------------------------------------------------------- training
@pytest.mark.parametrize("task,extra,ratio", [
    # the reference's relative TC term is ~1 wherever the clamped previous reconstruction is
    # ~0 (at initialisation) and its steep gradient there slows Adam's first steps: 25 steps
    # lower the total loss by ~2 % (measured)
    ("e2vid", {}, 0.99),
    ("evflow", {}, 0.85),
])
def test_loss_finite_and_decreasing(tmp_path, task, extra, ratio):
    t = Trainer(tiny_cfg(task, **extra), str(tmp_path), torch.device("cpu"))
    ds = FakeV2VStream(outputs=outputs(task), num_batches=25, fixed=True)  # the same batch: must be fitted
    s = t.fit(ds, 25, image_every=0, checkpoint_every=0, progress=False)
    assert s["steps"] == 25 and np.isfinite(s["last_loss"])
    assert s["mean_loss_last10"] < ratio * s["mean_loss_first10"]
    rows = list(csv.DictReader(open(tmp_path / "train_log.csv")))
    assert len(rows) == 25 and all(np.isfinite(float(r["loss"])) for r in rows)
    assert (tmp_path / "samples" / "step_0000025.png").exists() and (tmp_path / "checkpoint_last.pt").exists()


def test_e2vid_uses_temporal_consistency_on_second_half(tmp_path):
    t = Trainer(tiny_cfg("e2vid"), str(tmp_path), torch.device("cpu"))
    b = next(iter(FakeV2VStream(sequence_length=4, num_batches=1)))
    s = t.train_step(b)
    assert s["tc"] > 0 and s["loss"] == pytest.approx(s["l1"] + s["perceptual"] + s["tc"], rel=1e-4)
    t2 = Trainer(tiny_cfg("e2vid", loss={"tc_weight": 0.0}), str(tmp_path / "b"), torch.device("cpu"))
    s2 = t2.train_step(b)
    assert s2["tc"] == 0.0


def test_checkpoint_round_trip_and_resume_continues_stream(tmp_path):
    cfg = tiny_cfg("e2vid")
    t = Trainer(cfg, str(tmp_path), torch.device("cpu"))
    ds = FakeV2VStream(num_batches=10)
    t.fit(ds, 4, image_every=0, checkpoint_every=2, progress=False)
    assert (tmp_path / "checkpoint_0000004.pt").exists() and ds.state_dict() == {"pos": 4}

    t2 = Trainer(cfg, str(tmp_path), torch.device("cpu"))
    ds2 = FakeV2VStream(num_batches=10)
    t2.load_checkpoint(str(tmp_path / "checkpoint_last.pt"), ds2)
    assert t2.step == 4 and ds2.state_dict() == {"pos": 4}
    for a, b in zip(t.model.state_dict().values(), t2.model.state_dict().values()):
        assert torch.equal(a, b)
    assert t2.optimizer.state_dict()["state"][0]["step"] == t.optimizer.state_dict()["state"][0]["step"]
    s = t2.fit(ds2, 7, image_every=0, checkpoint_every=0, progress=False)
    assert s["steps"] == 3 and ds2.yielded_ids == [4, 5, 6]  # the epoch continues, no repeats
    rows = list(csv.DictReader(open(tmp_path / "train_log.csv")))
    assert [int(r["step"]) for r in rows] == list(range(1, 8))
    # each row says where its batch lay in its epoch: its position (2 samples a step)
    assert [(int(r["epoch"]), int(r["sample_in_epoch"])) for r in rows] == [(0, 2 * (i + 1)) for i in range(7)]
    # a crash after the last checkpoint leaves extra rows: resuming from step 7 drops them
    t3 = Trainer(cfg, str(tmp_path), torch.device("cpu"))
    t3.load_checkpoint(str(tmp_path / "checkpoint_0000004.pt"))
    t3.fit(FakeV2VStream(num_batches=10), 5, image_every=0, checkpoint_every=0, progress=False)
    rows = list(csv.DictReader(open(tmp_path / "train_log.csv")))
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4, 5]
    with pytest.raises(ValueError):
        Trainer(tiny_cfg("evflow"), str(tmp_path / "x"), torch.device("cpu")).load_checkpoint(str(tmp_path / "checkpoint_last.pt"))


def test_cli_end_to_end_with_resume(tmp_path, monkeypatch):
    import trainer.train as tr

    made = []

    def fake_make_stream(endpoint, task, timeout_s, raw, **kw):
        ds = FakeV2VStream(outputs=outputs(task), num_batches=10, raw=raw)
        made.append((endpoint, task, ds))
        return ds

    monkeypatch.setattr(tr, "make_stream", fake_make_stream)
    common = ["--config", "trainer/configs/evflow.yaml", "--connect", "tcp://127.0.0.1:1", "--out", str(tmp_path),
              "--device", "cpu", "--no-progress", "--set", "model.base_num_channels=4", "--set", "model.num_bins=3",
              "--set", "log.image_every=2"]
    assert tr.main(common + ["--max-steps", "3"]) == 0
    assert made[0][:2] == ("tcp://127.0.0.1:1", "evflow") and "frames" not in made[0][2].outputs
    assert (tmp_path / "samples" / "step_0000002.png").exists()
    assert tr.main(common + ["--max-steps", "5", "--resume", "auto"]) == 0
    assert made[1][2].yielded_ids == [3, 4]
    rows = list(csv.DictReader(open(tmp_path / "train_log.csv")))
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4, 5] and "loss" in rows[0]

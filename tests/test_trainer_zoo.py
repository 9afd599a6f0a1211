"""The V2V paper's model zoo in trainer/: E2VID, HyperE2VID and ETNet against the authors'
architectures (tests/data/zoo_reference.json, derived by harness/zoo_reference.py), their
optimisers and schedules, and a training step on a small stream batch on CPU."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.trainer_fixtures import FakeV2VStream
from trainer.config import default_config, load_config, merge
from trainer.core import Trainer, build_optimizer, set_lr
from trainer.models.etnet import sinusoid_table
from trainer.models.hypere2vid import fourier_bessel_bases
from trainer.zoo import build_model
from trainer.tasks import curriculum_beta, get_task

REF = json.loads((Path(__file__).parent / "data" / "zoo_reference.json").read_text())

#: reduced sizes for CPU steps (3 bins, as FakeV2VStream makes)
TINY = {"hypere2vid": {"num_bins": 3, "base_num_channels": 4},
        "etnet": {"num_bins": 3, "d_model": 16, "nhead": 2, "encoder_layers": 1, "decoder_layers": 1,
                  "dim_feedforward": 32}}


def tiny_cfg(task, **extra):
    return merge(default_config(task), merge({"model": TINY[task], "max_steps": 20}, extra))


@pytest.mark.parametrize("task", ["e2vid", "hypere2vid", "etnet"])
def test_default_model_matches_the_authors_state_dict(task):
    m = build_model(task, default_config(task)["model"])
    ours = {k: list(v.shape) for k, v in m.state_dict().items()}
    assert ours == REF[task]["state_dict"]
    assert sum(p.numel() for p in m.parameters()) == REF[task]["parameters"]
    per = {}
    for name, p in m.named_parameters():
        top = name.split(".")[1] if name.startswith("unetrecurrent.") else name.split(".")[0]
        per[top] = per.get(top, 0) + p.numel()
    assert per == REF[task]["parameters_per_module"]


def test_fourier_bessel_bases_equal_the_authors_buffer():
    ours = fourier_bessel_bases(5, 6)
    ref = torch.tensor(REF["hypere2vid"]["bases"])
    assert ours.shape == (12, 25)
    torch.testing.assert_close(ours, ref, atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="odd"):
        fourier_bessel_bases(4)


def test_position_table_is_sinusoidal():
    t = sinusoid_table(50, 8)[0]
    assert t.shape == (50, 8)
    assert float(t[7, 0]) == pytest.approx(np.sin(7.0)) and float(t[7, 1]) == pytest.approx(np.cos(7.0))
    assert float(t[7, 2]) == pytest.approx(np.sin(7.0 / 10000 ** (2 / 8)))


@pytest.mark.parametrize("task", ["hypere2vid", "etnet"])
def test_forward_is_recurrent_and_crops_odd_sizes(task):
    torch.manual_seed(0)
    m = build_model(task, TINY[task]).eval()
    x = torch.randn(2, 3, 20, 28)  # not a multiple of 8
    with torch.no_grad():
        y0, s = m(x)
        y1, _ = m(x, s)
        y0b, _ = m(x)
    assert y0.shape == (2, 1, 20, 28)
    torch.testing.assert_close(y0, y0b)          # deterministic from a fresh state
    assert not torch.allclose(y0, y1)             # the state carries over
    if task == "etnet":
        assert float(y0.min()) > 0 and float(y0.max()) < 1  # sigmoid output
    with pytest.raises(ValueError, match="voxel must be"):
        m(torch.randn(2, 4, 16, 16))


def test_hypere2vid_curriculum_mixes_the_ground_truth_into_the_context():
    torch.manual_seed(0)
    m = build_model("hypere2vid", TINY["hypere2vid"]).eval()
    x, gt = torch.randn(1, 3, 16, 16), torch.rand(1, 1, 16, 16)
    with torch.no_grad():
        _, s = m(x)
        a, _ = m(x, s)
        b, _ = m(x, s, gt_image=gt, beta=1.0)
        c, _ = m(x, (s[0], gt))  # beta 1 == the ground truth as the previous reconstruction
    assert not torch.allclose(a, b)
    torch.testing.assert_close(b, c)
    with pytest.raises(ValueError, match="num_encoders == 3"):
        build_model("hypere2vid", {"num_encoders": 4})


def test_curriculum_beta_falls_in_stages_like_hyper_epochs():
    # 80 "epochs" of 10 steps, 16 under the curriculum: beta = 1 - epoch / 16
    betas = [curriculum_beta(s, 800, 0.2, 16) for s in range(0, 800, 10)]
    assert betas[:16] == [1 - e / 16 for e in range(16)] and betas[16:] == [0.0] * 64
    assert curriculum_beta(5, 100, 0.0, 16) == 0.0


def test_optimisers_and_schedules_are_the_appendix():
    m = torch.nn.Linear(2, 2)
    o = default_config("hypere2vid")["optim"]
    opt = build_optimizer(m, o)
    assert type(opt) is torch.optim.Adam and opt.defaults["lr"] == 1e-3 and opt.defaults["amsgrad"]
    assert set_lr(opt, o, 10**6) == 1e-3  # constant
    o = default_config("etnet")["optim"]
    opt = build_optimizer(m, o)
    assert type(opt) is torch.optim.AdamW and opt.defaults["lr"] == 2e-4
    assert opt.defaults["weight_decay"] == 0.01 and opt.defaults["amsgrad"]
    every = o["lr_gamma_every"]
    assert set_lr(opt, o, every - 1) == 2e-4
    assert set_lr(opt, o, 3 * every) == pytest.approx(2e-4 * 0.94**3)
    assert opt.param_groups[0]["lr"] == pytest.approx(2e-4 * 0.94**3)
    e2 = default_config("e2vid")["optim"]
    assert (e2["optimizer"], e2["lr"], e2["lr_gamma"]) == ("adam", 1e-4, 1.0)
    with pytest.raises(ValueError, match="optim.optimizer"):
        build_optimizer(m, {**o, "optimizer": "sgd"})


@pytest.mark.parametrize("task", ["hypere2vid", "etnet"])
def test_config_file_is_the_default(task):
    path = Path(__file__).parents[1] / "trainer" / "configs" / f"{task}.yaml"
    cfg = load_config(str(path))
    assert cfg["model"] == default_config(task)["model"] and cfg["optim"] == default_config(task)["optim"]
    assert cfg["task"] == task


@pytest.mark.parametrize("task", ["hypere2vid", "etnet"])
def test_training_steps_on_a_stream_batch(tmp_path, task):
    t = Trainer(tiny_cfg(task), str(tmp_path), torch.device("cpu"))
    before = {k: v.clone() for k, v in t.model.state_dict().items()}
    ds = FakeV2VStream(outputs=get_task(task).outputs, sequence_length=4, num_batches=3)
    s = t.fit(ds, 3, image_every=0, checkpoint_every=0, progress=False)
    assert s["steps"] == 3 and np.isfinite(s["last_loss"])
    after = t.model.state_dict()
    changed = [k for k in before if before[k].dtype.is_floating_point and not torch.equal(before[k], after[k])]
    trainable = {k for k, _ in t.model.named_parameters()}
    assert trainable <= set(changed)  # every parameter got a gradient step
    assert (tmp_path / "checkpoint_last.pt").exists()


def test_task_switch_drops_the_files_own_sections():
    cfg = load_config("trainer/configs/etnet.yaml", task="hypere2vid")
    assert cfg["optim"] == default_config("hypere2vid")["optim"]  # not etnet's AdamW
    assert cfg["model"] == default_config("hypere2vid")["model"] and "curriculum" in cfg
    cfg = load_config("trainer/configs/e2vid.yaml", task="hypere2vid")
    assert cfg["optim"]["lr"] == 1e-3  # e2vid.yaml's Adam 1e-4 is e2vid's, not HyperE2VID's

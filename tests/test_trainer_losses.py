"""The paper's loss presets (``loss.preset``) against a direct transcription of the authors'
training loss (HYLZ-2019/V2V ``model/train_utils.py`` ``calc_loss``, ``model/loss.py`` and
``utils/loss.py``) on random tensors."""
from __future__ import annotations

import contextlib

import pytest
import torch
import torch.nn.functional as F

from trainer.config import LOSS_PRESETS, apply_overrides, default_config, load_config
from trainer.models.lpips import LPIPSNet
from trainer.tasks import E2VIDTask

#: The authors' loss settings of each preset (their config keys): lpips_weight, lpips_type,
#: l1_weight, temporal_consistency_weight, temporal_consistency_L0 for T = 8 (L0 = 4 is their
#: 20 of 40; "full" TC is their default L0 = 1).
AUTHORS = {"v+l1+h": (1.0, "vgg", 1.0, 1.0, 4), "alex+tc": (1.0, "alex", 0.0, 1.0, 1),
           "alex": (1.0, "alex", 0.0, 0.0, 1), "alex+th": (1.0, "alex", 0.0, 1.0, 4)}


def authors_tc(image0, image1, processed0, processed1, flow01, alpha=50.0):
    """utils/loss.py temporal_consistency_loss (reduce_batch=False), transcribed."""
    h, w = image0.shape[2:]
    xx, yy = torch.meshgrid(torch.arange(w), torch.arange(h), indexing="xy")
    gx = 2 * (xx.float() + flow01[:, 0]) / (w - 1) - 1
    gy = 2 * (yy.float() + flow01[:, 1]) / (h - 1) - 1
    grid = torch.stack([gx, gy], dim=3)
    vis = torch.exp(-alpha * (image1 - F.grid_sample(image0, grid, align_corners=True)) ** 2)
    p0w = F.grid_sample(torch.clamp(processed0, 0, 255), grid, align_corners=True)
    return (vis * torch.abs(processed1 - p0w) / (processed1.abs() + p0w.abs() + 1e-5)).mean(dim=(1, 2, 3))


def authors_loss(pred, frame, flow, lpips, preset):
    """calc_loss: per-step terms (B,), TC from step L0 with the flow frame t-1 -> t negated,
    averaged over T then over the batch. pred, frame (B, T, 1, H, W); flow (B, T, 2, H, W)."""
    lw, _, l1w, tcw, L0 = AUTHORS[preset]
    B, T = pred.shape[:2]
    total = torch.zeros(B, T)
    for t in range(T):
        total[:, t] += lw * lpips(pred[:, t], frame[:, t])
        total[:, t] += l1w * (pred[:, t] - frame[:, t]).abs().reshape(B, -1).mean(1)
        if tcw and t >= L0:
            total[:, t] += tcw * authors_tc(frame[:, t - 1], frame[:, t], pred[:, t - 1], pred[:, t], -flow[:, t])
    return total.mean(1).sum() / B


class Replay(torch.nn.Module):
    """A 'network' that returns given predictions step by step (the state is the step)."""

    def __init__(self, preds):
        super().__init__()
        self.preds = preds

    def forward(self, voxel, state=None):
        t = state or 0
        return self.preds[:, t], t + 1


@pytest.mark.parametrize("preset", list(LOSS_PRESETS))
def test_preset_equals_the_authors_loss(tmp_path, preset):
    g = torch.Generator().manual_seed(7)
    B, T, H, W = 2, 8, 64, 64
    net = AUTHORS[preset][1]
    torch.manual_seed(0)
    lp = LPIPSNet(net)  # random weights, the same module on both sides: the test is about composition
    for lin in lp.lins:
        lin.weight.data.abs_()
    wfile = tmp_path / f"lpips_{net}.pt"
    torch.save(lp.state_dict(), wfile)
    cfg = apply_overrides(default_config("e2vid"), [f"loss.preset={preset}", f"loss.lpips_weights={wfile}"])
    assert cfg["loss"]["lpips_net"] == net
    task = E2VIDTask(cfg, torch.device("cpu"))
    assert task.rec_loss.perceptual == "lpips"
    frames = torch.rand(B, T + 1, 1, H, W, generator=g)
    preds = torch.rand(B, T, 1, H, W, generator=g) * 1.2 - 0.1
    flow = 3 * torch.randn(B, T, 2, H, W, generator=g)
    l0 = task.flow_from(T)
    b = {"voxels": torch.zeros(B, T, 3, H, W), "frames": frames, "flow": flow[:, l0:]}
    loss, _, _ = task.forward(Replay(preds), b, contextlib.nullcontext)
    # the authors' layout: frame[t] is the frame at voxel t's end (our frames[:, t + 1]) and
    # flow[t] moves frame[t-1] to frame[t] (our flow[:, t])
    ref = authors_loss(preds, frames[:, 1:], flow, lp, preset)
    assert float(loss) == pytest.approx(float(ref), rel=1e-5)


def test_presets_in_files_and_overrides(tmp_path):
    assert default_config("e2vid")["loss"]["preset"] == "v+l1+h"
    assert {k: default_config("etnet")["loss"][k] for k in LOSS_PRESETS["v+l1+h"]} == LOSS_PRESETS["v+l1+h"]
    p = tmp_path / "c.yaml"
    p.write_text("task: hypere2vid\nloss:\n  preset: alex+tc\n  tc_weight: 0.5\n")
    loss = load_config(str(p))["loss"]
    assert (loss["lpips_net"], loss["l1_weight"], loss["tc_start_fraction"], loss["tc_weight"]) == ("alex", 0.0, 0.0, 0.5)
    c = apply_overrides(default_config("e2vid"), ["loss.preset=alex", "loss.tc_weight=0.25"])
    assert c["loss"]["lpips_net"] == "alex" and c["loss"]["tc_weight"] == 0.25
    p.write_text("loss:\n  preset: vgg+everything\n")
    with pytest.raises(ValueError, match="loss.preset"):
        load_config(str(p))

"""The training loop's GPU-facing options, checked on the CPU: bf16 autocast against float32,
torch.compile, the perceptual stand-in recorded and refused on request, the losses read only at
the logging interval, and a batch's host -> device conversion."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch

from tests.trainer_fixtures import FakeV2VStream
from trainer.config import default_config, merge
from trainer.core import Trainer
from trainer.data import batch_to_device
from trainer.models.lpips import STAND_IN, LPIPSUnavailable
from trainer.train import main as train_main

TINY = {"e2vid": {"num_bins": 3, "base_num_channels": 4}, "evflow": {"num_bins": 3, "base_num_channels": 4}}

#: |bf16 loss - float32 loss| / float32 loss allowed over a short run: bf16 keeps 8 bits of
#: mantissa (relative rounding 2**-9 = 0.2 % per operation); the losses of an 8-step run on the
#: same batches stay within a few per cent of float32's.
BF16_REL_TOL = 0.05


def tiny_cfg(task, **extra):
    return merge(default_config(task), merge({"model": TINY[task], "optim": {"lr": 1e-3}, "max_steps": 8}, extra))


def _losses(cfg, tmp_path, name):
    t = Trainer(cfg, str(tmp_path / name), torch.device("cpu"))
    s = t.fit(FakeV2VStream(num_batches=8, fixed=True), 8, image_every=0, checkpoint_every=0, progress=False,
              log_every=4)
    rows = list(csv.DictReader(open(tmp_path / name / "train_log.csv")))
    return np.array([float(r["loss"]) for r in rows]), s


@pytest.mark.parametrize("task", ["e2vid", "evflow"])
def test_bf16_run_stays_within_tolerance_of_float32(tmp_path, task):
    f32, _ = _losses(tiny_cfg(task), tmp_path, "f32")
    b16, _ = _losses(tiny_cfg(task, amp="bf16"), tmp_path, "b16")
    assert len(f32) == len(b16) == 8 and np.all(np.isfinite(b16))
    rel = np.abs(b16 - f32) / f32
    assert rel.max() < BF16_REL_TOL, rel
    assert not np.array_equal(b16, f32)  # autocast did run in bf16


def test_losses_are_read_every_log_interval_and_all_rows_are_written(tmp_path):
    losses, s = _losses(tiny_cfg("evflow"), tmp_path, "run")
    assert len(losses) == 8 and s["steps"] == 8 and s["last_loss"] == pytest.approx(losses[-1])
    t = Trainer(tiny_cfg("evflow"), str(tmp_path / "sync"), torch.device("cpu"))
    out = t.train_step(next(iter(FakeV2VStream(num_batches=1))), sync=False)
    assert isinstance(out["loss"], torch.Tensor) and out["loss"].ndim == 0 and isinstance(out["samples"], int)


def test_a_non_finite_loss_stops_the_run_at_the_logging_step(tmp_path):
    t = Trainer(tiny_cfg("evflow", optim={"lr": 1e30}), str(tmp_path), torch.device("cpu"))
    with pytest.raises(FloatingPointError, match="non-finite loss"):
        t.fit(FakeV2VStream(num_batches=40), 40, image_every=0, checkpoint_every=0, progress=False, log_every=5)


def test_compile_trains_the_same_network(tmp_path, inductor_cache):
    cfg = tiny_cfg("evflow", compile=True)
    t = Trainer(cfg, str(tmp_path), torch.device("cpu"))
    assert t.net is not t.model
    s = t.train_step(next(iter(FakeV2VStream(num_batches=1))))
    assert np.isfinite(s["loss"])
    assert set(t.checkpoint()["model"]) == set(Trainer(tiny_cfg("evflow"), str(tmp_path / "b"),
                                                       torch.device("cpu")).model.state_dict())


def test_stand_in_recorded_in_summary_and_checkpoint(tmp_path):
    t = Trainer(tiny_cfg("e2vid"), str(tmp_path), torch.device("cpu"))
    assert t.perceptual_term == STAND_IN  # no LPIPS weights on this host
    t.fit(FakeV2VStream(num_batches=2), 2, image_every=0, checkpoint_every=0, progress=False)
    assert json.loads((tmp_path / "summary.json").read_text())["perceptual_term"] == STAND_IN
    assert torch.load(tmp_path / "checkpoint_last.pt", weights_only=False)["perceptual_term"] == STAND_IN
    no_term = Trainer(tiny_cfg("e2vid", loss={"perceptual_weight": 0.0}), str(tmp_path / "b"), torch.device("cpu"))
    assert no_term.perceptual_term is None
    assert Trainer(tiny_cfg("evflow"), str(tmp_path / "c"), torch.device("cpu")).perceptual_term is None


def test_require_lpips_refuses_the_stand_in(tmp_path, caplog):
    with pytest.raises(LPIPSUnavailable, match="require_lpips"):
        Trainer(tiny_cfg("e2vid", require_lpips=True), str(tmp_path), torch.device("cpu"))
    Trainer(tiny_cfg("evflow", require_lpips=True), str(tmp_path / "flow"), torch.device("cpu"))  # no LPIPS term
    rc = train_main(["--task", "e2vid", "--require-lpips", "--out", str(tmp_path / "cli"), "--device", "cpu",
                     "--connect", "tcp://127.0.0.1:9"])
    assert rc == 2 and "not training with the 1 - SSIM stand-in" in caplog.text


def test_a_batch_reaches_the_device_as_float32_from_its_wire_dtypes_with_the_flow_tail():
    g = torch.Generator().manual_seed(0)
    voxels = torch.randint(-5, 6, (2, 4, 3, 20, 28), dtype=torch.int8, generator=g)
    frames = torch.randint(0, 256, (2, 5, 1, 20, 28), dtype=torch.uint8, generator=g)
    flow = (torch.randn(2, 4, 2, 20, 28, generator=g) * 3).half()
    batch = {"voxels": voxels, "frames": frames, "flow": flow, "sample_ids": ["a#0", "a#1"]}
    b = batch_to_device(batch, torch.device("cpu"), ("frames", "flow"), flow_from=2)
    assert set(b) == {"voxels", "frames", "flow"} and all(t.dtype == torch.float32 for t in b.values())
    assert torch.equal(b["voxels"], voxels.float())
    assert torch.equal(b["frames"], frames.float() / 255)
    assert torch.equal(b["flow"], flow[:, 2:].float())
    with pytest.raises(KeyError, match="stream batch lacks 'flow'"):
        batch_to_device({"voxels": voxels}, torch.device("cpu"), ("voxels", "flow"))

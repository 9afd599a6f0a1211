"""Toy-sized training steps of the five networks, for comparing the trainer's speeds
(``trainer/speed.py``) on the CPU: ``tests/test_trainer_fast.py`` (numerics) and
``bench/step_ops.py`` (aten ops dispatched per step) share them.

Sizes: 3 bins, base 4 channels (E2VID, EV-FlowNet, HyperE2VID), ETNet with d_model 16, one
encoder and decoder layer, E-RAFT with 3 correlation levels and 2 iterations on 64-pixel crops
(its smallest side, ``trainer.models.eraft.min_side(3)``), the others on 32-pixel crops;
sequences of 3 voxel grids, batch 2. The perceptual term is the 1 - SSIM stand-in (no LPIPS
weights are bundled).
"""
from __future__ import annotations

import tempfile
from collections import Counter
from typing import Dict, Tuple

import torch

from trainer.config import default_config, merge
from trainer.core import Trainer

__all__ = ["TASKS", "TOY_MODELS", "toy_config", "toy_batch", "toy_trainer", "step_ops", "HOST_READS"]

TASKS = ("e2vid", "evflow", "hypere2vid", "etnet", "eraft")
#: model sections of the toy networks
TOY_MODELS: Dict[str, dict] = {
    "e2vid": {"num_bins": 3, "base_num_channels": 4},
    "evflow": {"num_bins": 3, "base_num_channels": 4},
    "hypere2vid": {"num_bins": 3, "base_num_channels": 4},
    "etnet": {"num_bins": 3, "d_model": 16, "nhead": 2, "encoder_layers": 1, "decoder_layers": 1,
              "dim_feedforward": 32},
    "eraft": {"num_bins": 3, "iters": 2, "corr_levels": 3},
}
CROP = {"eraft": 64}
BATCH, LENGTH = 2, 3


def toy_config(task: str, speed: str = "eager", amp: str = "fp32", **extra) -> dict:
    """The task's default config with the toy model, ``speed``, ``amp`` and ``extra`` keys."""
    return merge(default_config(task), merge({"model": TOY_MODELS[task], "speed": speed, "amp": amp,
                                              "max_steps": 100, "optim": {"lr": 1e-3}}, extra))


def toy_batch(task: str, seed: int = 0) -> dict:
    """A stream batch in the client's raw format (int8 ``voxels`` (B, L, 3, S, S), uint8
    ``frames`` (B, L+1, 1, S, S), float16 ``flow`` (B, L, 2, S, S)), random but fixed by ``seed``,
    step ``seed`` of epoch 0."""
    g = torch.Generator().manual_seed(seed)
    s = CROP.get(task, 32)
    return {"voxels": torch.randint(-3, 4, (BATCH, LENGTH, 3, s, s), generator=g, dtype=torch.int8),
            "frames": torch.randint(0, 256, (BATCH, LENGTH + 1, 1, s, s), generator=g, dtype=torch.uint8),
            "flow": (torch.randn((BATCH, LENGTH, 2, s, s), generator=g) * 2).half(),
            "sample_ids": [f"toy-{seed}-{i}" for i in range(BATCH)], "epoch": 0, "step": seed}


def toy_trainer(task: str, speed: str = "eager", amp: str = "fp32", **extra) -> Tuple[Trainer, str]:
    """A CPU :class:`trainer.core.Trainer` of the toy network (seed 0, so both speeds start
    from the same weights) writing into a fresh temporary folder; returns ``(trainer, folder)``."""
    out = tempfile.mkdtemp(prefix=f"toy-{task}-")
    return Trainer(toy_config(task, speed, amp, **extra), out, torch.device("cpu")), out


#: aten ops that copy a device value to the host (``.item()``, ``float(tensor)``, ``bool(tensor)``):
#: on CUDA each one waits for the device
HOST_READS = ("aten::_local_scalar_dense", "aten::item")


def step_ops(trainer: Trainer, batch: dict) -> Counter:
    """The aten ops one ``trainer.train_step(batch, sync=False)`` dispatches on the CPU
    (``torch.profiler``; nested ops count, so ``aten::conv2d`` and the ``aten::convolution`` it
    calls are two): ``Counter`` of op name -> calls. Profile a step after a first one, so the
    optimiser's state exists and a compiled network is compiled."""
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        trainer.train_step(batch, sync=False)
    return Counter(e.name for e in prof.events() if e.name.startswith("aten::"))

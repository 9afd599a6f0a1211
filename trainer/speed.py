"""How fast a training step runs: the config key ``speed``.

* ``eager`` (default): the V2V authors' step as their ``train.py`` runs it with
  ``use_compile: false``: fp32 (or bf16 autocast with ``amp: bf16``), NCHW tensors, PyTorch's
  default optimiser implementation (the per-parameter loop on the CPU, ``foreach`` multi-tensor
  kernels on CUDA), PyTorch's default matmul precision, ``torch.compile(model)`` only with
  ``compile: true``.
* ``fast``: the same losses and updates, dispatched with less work per step. What each part
  does on CUDA and on the CPU:

  - channels-last parameters and activations for the convolution-dominated networks
    (:data:`CHANNELS_LAST`: E2VID, EV-FlowNet, HyperE2VID), on every device. ETNet's step is
    dominated by its transformer's token matmuls; E-RAFT's gradients under channels-last
    differed from eager by up to 2 % (relative norm, its BatchNorm context encoder at toy size
    on the CPU), more than the tolerance below, so both keep NCHW parameters. On CUDA the
    compiled network's convolutions may run channels-last anyway (inductor picks convolution
    layouts itself), E-RAFT's included: that difference is not measured;
  - the optimiser's ``fused`` kernel on CUDA and the CPU, ``foreach`` on other devices. On the
    CPU it replaces the per-parameter loop: a quarter of its aten ops (``foreach`` dispatches no
    fewer there, its CPU kernels loop over the tensors; ``bench/step_ops.py``). On CUDA eager
    already uses ``foreach``; ``fused`` saves its remaining launches per step;
  - with ``amp: bf16`` on an eager network (the CPU), each weight is cast to bf16 once per step,
    not once per recurrent call: the task's per-call autocast regions sit inside one outer
    autocast-disabled region, so autocast's weight-cast cache lives for the whole forward (losses
    stay fp32 as in eager). A compiled network (CUDA) has the casts inside its graphs: there
    the saving does not apply;
  - on CUDA, the network runs through ``torch.compile(mode="reduce-overhead", dynamic=False)``:
    CUDA graphs of the recurrent step at the run's fixed shapes, whatever ``compile`` says.
    Elsewhere ``compile: true`` gives plain ``torch.compile`` (inductor), and eager otherwise:
    on the CPU compilation costs far more than it saves over a short run. One graph per network
    for the whole run: the recurrent networks start each sequence from zero tensors (their
    ``initial_states``, bit-identical to None) and HyperE2VID's curriculum weight is a device
    tensor (``trainer.tasks.HyperE2VIDTask``); a batch whose shape differs from the first
    one's (an epoch's smaller last batch, one with padding dropped, Ray's partial batch) runs
    the model eagerly instead of compiling another graph (``Trainer.network_for``);
    the predictions kept for previews and the final checkpoint are copies (a replay overwrites
    a CUDA graph's outputs). E-RAFT's warm start starts each sequence as zeros, not None
    (``ERAFT.reset_states(voxel)``, bit-identical): one graph, not two;
  - the reconstruction tasks' losses (E2VID, HyperE2VID, ETNet) on the whole sequence at once,
    on every device: one L1, one LPIPS/SSIM and one temporal-consistency call on the stacked
    predictions instead of one per voxel grid (``E2VIDTask._forward_whole_sequence``; equal to
    eager's within float32 summation order);
  - on CUDA, ``torch.set_float32_matmul_precision("high")`` (:func:`matmul_precision`): fp32
    matmuls (ETNet's transformer, the linear layers) on TF32 tensor cores, inputs rounded to
    10 mantissa bits (relative error about 1e-3 per product; PyTorch already runs fp32
    convolutions in TF32 by default). The CPU keeps the default;
  - under ``--engine ray`` with several ranks, the reduced gradients keep each parameter's
    layout and an empty step is skipped inside the fused kernel, with no read from the device
    (``trainer.ray_train.SampleWeightedAllReduce``).

  Neither speed's forward or backward reads a value from the device: the loop reads the
  losses at its logging interval and at checkpoints (``trainer/loop.py``). The only host reads
  of a step are Adam's step counters, which the per-parameter and ``foreach`` optimisers keep on
  the host (no device wait); the fused optimiser keeps them on the parameters' device.

``fast`` is off by default on every device: its numerics are shown equal to ``eager`` on the
CPU only (``tests/test_trainer_fast.py``, one step of each of the five networks: fp32 loss
within rtol 1e-5, outputs within 1e-5, gradients within rtol 1e-4 + 1e-5 x the largest
gradient; bf16 loss within rtol 1e-4, outputs within 8e-3, gradients within rtol 2e-2 + 2e-2 x
the largest; compiled, the fp32 tolerances: by inductor for four networks, E-RAFT through dynamo and
AOT autograd only, as inductor's cold compile of its step takes minutes); CUDA graphs, TF32 matmuls and CUDA's fused kernels could not be run here. A compiled
network draws its dropout masks (ETNet's) from inductor's generator, not eager's: other masks,
the same distribution.
"""
from __future__ import annotations

import contextlib
from typing import Dict

import torch
import torch.nn as nn

__all__ = ["SPEEDS", "CHANNELS_LAST", "check_speed", "prepare_model", "compiled", "optimizer_options",
           "forward_context", "matmul_precision"]

#: The values of the config key ``speed``.
SPEEDS = ("eager", "fast")
#: Tasks whose networks are convolution-dominated: channels-last under ``speed: fast``.
CHANNELS_LAST = ("e2vid", "evflow", "hypere2vid")


def check_speed(speed) -> str:
    """``speed`` as one of :data:`SPEEDS`.

    Raises:
        ValueError: for another value, naming the choices.
    """
    if speed not in SPEEDS:
        raise ValueError(f"speed must be one of {list(SPEEDS)}, got {speed!r}")
    return speed


def prepare_model(model: nn.Module, task: str, speed: str) -> nn.Module:
    """``model`` (already on its device), its 4-d parameters and buffers made channels-last in
    place under ``speed: fast`` for a task of :data:`CHANNELS_LAST`; returned. State-dict keys
    and values are unchanged (only the strides), so checkpoints load into either speed."""
    if speed == "fast" and task in CHANNELS_LAST:
        model.to(memory_format=torch.channels_last)
    return model


def compiled(model: nn.Module, cfg: dict, device: torch.device) -> nn.Module:
    """What the trainer's forward calls: under ``speed: fast`` on CUDA,
    ``torch.compile(model, mode="reduce-overhead", dynamic=False)`` (CUDA graphs on the fixed
    crop); else ``torch.compile(model)`` when ``cfg['compile']`` (the authors' ``use_compile``);
    else ``model``. A compiled module shares ``model``'s parameters and state dict."""
    if cfg.get("speed", "eager") == "fast" and device.type == "cuda":
        return torch.compile(model, mode="reduce-overhead", dynamic=False)
    if cfg.get("compile"):
        return torch.compile(model)
    return model


def optimizer_options(speed: str, device: torch.device) -> Dict[str, bool]:
    """Keyword arguments for ``torch.optim.Adam``/``AdamW``: ``{}`` (eager: the per-parameter
    loop), ``{"fused": True}`` under ``speed: fast`` on CUDA or the CPU, ``{"foreach": True}``
    under ``speed: fast`` on another device."""
    if speed != "fast":
        return {}
    return {"fused": True} if device.type in ("cuda", "cpu") else {"foreach": True}


def forward_context(speed: str, amp: bool, device: torch.device):
    """The context a step's forward runs in: under ``speed: fast`` with bf16 autocast, an outer
    ``torch.autocast(enabled=False)`` region (autocast clears its weight-cast cache only when
    the outermost region exits, so the task's per-call bf16 regions reuse one cast of each
    weight per step; the code between them stays fp32); else nothing."""
    if speed == "fast" and amp:
        return torch.autocast(device.type, dtype=torch.bfloat16, enabled=False)
    return contextlib.nullcontext()


def matmul_precision(speed: str, device: torch.device):
    """What ``torch.set_float32_matmul_precision`` is given for a run: ``"high"`` under
    ``speed: fast`` on CUDA (float32 matmuls on TF32 tensor cores, inputs rounded to 10
    mantissa bits: a relative error of about 1e-3 per product, the precision PyTorch's default
    already gives float32 convolutions through cuDNN); None (PyTorch's default, ``"highest"``,
    left as it is) under ``eager`` and on other devices, where ``"high"`` changes nothing the
    CPU runs."""
    return "high" if speed == "fast" and device.type == "cuda" else None

"""One training run's state: model, optimiser, the task's losses, one step, previews and
checkpoints (the loop that drives it is ``trainer/loop.py``; both engines use it).

Paper: Lou et al., "V2V", NeurIPS 2025 (training recipe of event_cnn_minimal): Adam (lr 1e-4,
amsgrad, no weight decay, constant lr), batch 12, sequences of 40 voxel grids.
"""
from __future__ import annotations

import contextlib
import logging
import math
import os
import shutil
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from .data import batch_to_device, drop_padding
from . import speed
from .models.lpips import STAND_IN, LPIPSUnavailable
from .zoo import build_model
from .tasks import get_task
from .viz import grid_image, write_png

__all__ = ["Trainer", "resolve_device", "build_optimizer", "set_lr"]

log = logging.getLogger("trainer")


def resolve_device(name: str) -> torch.device:
    """'auto' -> cuda if available else cpu; 'cuda' without a GPU raises ``RuntimeError``."""
    if name in (None, "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("--device cuda requested but torch.cuda.is_available() is False")
    return dev


def build_optimizer(model: torch.nn.Module, o: dict, **impl) -> torch.optim.Optimizer:
    """The ``optim`` section's optimiser over ``model``'s parameters: ``torch.optim.Adam``
    (weight decay as L2) or ``torch.optim.AdamW`` (decoupled weight decay), with ``lr``,
    ``amsgrad`` and ``weight_decay``. Paper appendix: E2VID/EvFlow Adam 1e-4, HyperE2VID Adam
    1e-3, ETNet AdamW 2e-4 wd 0.01, all amsgrad. ``impl``: the implementation's keywords
    (``foreach``/``fused``, ``trainer.speed.optimizer_options``). Raises ``ValueError`` for
    another name."""
    cls = {"adam": torch.optim.Adam, "adamw": torch.optim.AdamW}.get(str(o.get("optimizer", "adam")))
    if cls is None:
        raise ValueError(f"optim.optimizer must be 'adam' or 'adamw', got {o.get('optimizer')!r}")
    return cls(model.parameters(), lr=float(o["lr"]), amsgrad=bool(o["amsgrad"]), weight_decay=float(o["weight_decay"]),
               **impl)


def set_lr(optimizer: torch.optim.Optimizer, o: dict, step: int) -> float:
    """Set and return the learning rate of optimiser step ``step`` (0-based):
    ``lr * lr_gamma ** (step // lr_gamma_every)``, the stream's form of the reference's
    ``ExponentialLR`` stepped once per epoch (ETNet: gamma 0.94). Stateless in ``step``, so a
    resumed run continues the schedule."""
    gamma, every = float(o.get("lr_gamma", 1.0)), max(1, int(o.get("lr_gamma_every", 1000)))
    lr = float(o["lr"]) * gamma ** (step // every)
    for g in optimizer.param_groups:
        g["lr"] = lr
    return lr


class Trainer:
    """One training run: model, optimiser, the task (``trainer.tasks``), previews and checkpoints.

    Args:
        cfg: full config (see ``trainer/config.py``); ``cfg['task']`` names a task of
            ``trainer.tasks.TASKS``.
        out_dir: folder for logs, samples and checkpoints (created).
        device: torch device.

    Raises:
        ValueError: an unknown task, ``amp``, ``speed`` or a bad loss setting (naming it).
        LPIPSUnavailable: ``require_lpips`` set and the perceptual term would be the stand-in.

    Use ``trainer.loop.train_loop`` (or :meth:`fit`) with an iterable of stream batches (the
    contract of ``v2v_client.V2VStreamDataset``), or :meth:`train_step` on one batch.
    """

    def __init__(self, cfg: dict, out_dir: str, device: torch.device):
        self.cfg = cfg
        self.task = cfg["task"]
        self.device = device
        self.out = Path(out_dir)
        (self.out / "samples").mkdir(parents=True, exist_ok=True)
        torch.manual_seed(int(cfg.get("seed", 0)))
        if device.type == "cuda":
            torch.backends.cudnn.benchmark = True  # fixed crop size: let cuDNN pick its kernels
        amp = str(cfg.get("amp", "fp32")).lower()
        if amp not in ("fp32", "bf16"):
            raise ValueError(f"amp must be 'fp32' or 'bf16', got {cfg.get('amp')!r}")
        self.spec = get_task(self.task)(cfg, device)
        rec = getattr(self.spec, "rec_loss", None)
        #: the perceptual term the losses use (``ReconstructionLoss.term``), recorded in the
        #: summary and checkpoints; None for a task without one
        self.perceptual_term = rec.term if rec is not None else None
        if cfg.get("require_lpips") and self.perceptual_term == STAND_IN:
            raise LPIPSUnavailable(f"require_lpips: no LPIPS ({cfg['loss'].get('lpips_net')}) weights found (give "
                                   "loss.lpips_weights or install the lpips package); not training with the "
                                   "1 - SSIM stand-in")
        #: ``eager`` or ``fast`` (``trainer.speed``)
        self.speed = speed.check_speed(cfg.get("speed", "eager"))
        precision = speed.matmul_precision(self.speed, device)
        if precision is not None:  # process-wide, as cudnn.benchmark above
            torch.set_float32_matmul_precision(precision)
        self.model = speed.prepare_model(build_model(self.task, dict(cfg["model"])).to(device), self.task, self.speed)
        #: what forward calls: the model, or its ``torch.compile`` (``trainer.speed.compiled``;
        #: parameters and state dict stay the model's, so checkpoints keep their keys)
        self.net = speed.compiled(self.model, cfg, device)
        #: voxel shape (B, L, num_bins, H, W) the compiled network runs at: the first batch's
        #: (after padding is dropped); None until then
        self.compiled_shape: Optional[tuple] = None
        self.optimizer = build_optimizer(self.model, cfg["optim"], **speed.optimizer_options(self.speed, device))
        self.clip = cfg["optim"].get("clip_grad_norm")
        self.amp = amp == "bf16"
        self.step = 0
        self.stream_state = None

    def _autocast(self):
        """bf16 autocast on the training device when ``amp: bf16`` (the tasks compute losses
        and metrics on float32 copies of the predictions), else nothing."""
        if self.amp:
            return torch.autocast(self.device.type, dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def _check_batch(self, b: dict):
        nb = self.cfg["model"]["num_bins"]
        v = b["voxels"]
        if v.ndim != 5 or v.shape[2] != nb:
            raise ValueError(f"stream voxels have shape {tuple(v.shape)}, model expects (B, L, {nb}, H, W); "
                             f"start v2v-serve with --num-bins {nb} or set model.num_bins")

    def network_for(self, b: dict) -> torch.nn.Module:
        """The module a batch ``b`` (its ``voxels`` (B, L, num_bins, H, W)) runs through: the
        compiled network (:attr:`net`) when its voxels have the shape of the first batch the
        compiled network ran, else :attr:`model` eagerly. A compiled network is built for fixed
        shapes (``dynamic=False``; CUDA graphs): a batch of another shape (an epoch's smaller
        last batch, a batch after ``drop_padding``, Ray's partial batch) would be a new compile,
        a new CUDA-graph recording and a step towards dynamo's recompile limit for a handful of
        steps; eagerly it costs that step's launch overhead only. Without compilation it is
        always :attr:`model`."""
        if self.net is self.model:
            return self.model
        shape = tuple(b["voxels"].shape)
        if self.compiled_shape is None:
            self.compiled_shape = shape
        return self.net if shape == self.compiled_shape else self.model

    def forward(self, b: dict):
        """The task's loss, logged terms and predictions for a batch on the device (through
        :meth:`network_for`)."""
        with speed.forward_context(self.speed, self.amp, self.device):
            return self.spec.forward(self.network_for(b), b, self._autocast)

    def train_step(self, batch: dict, sync: bool = True) -> dict:
        """One optimiser step on one stream batch (host tensors). Samples flagged ``padding``
        are left out of the loss; a batch of padding only makes no step and returns
        ``{"loss": nan, "samples": 0}``.

        With ``sync`` (default) returns floats, ``loss``, the task's terms and ``grad_norm``
        (the gradient's total L2 norm before clipping), and checks the loss. With ``sync=False``
        nothing in the step waits for the device: those are detached 0-dim tensors on the device
        (``trainer.loop`` reads them at its logging interval and checks them there);
        ``samples`` (int) and ``lr`` (the step's learning rate, float) are the host's either way.

        Raises:
            ValueError: voxels of another bin count than the model's.
            FloatingPointError: a non-finite loss (``sync`` only).
        """
        batch, n_real = drop_padding(batch)
        if n_real == 0:
            return {"loss": float("nan"), "samples": 0}
        self._check_batch(batch)
        self.model.train()
        L = batch["voxels"].shape[1]
        b = batch_to_device(batch, self.device, self.spec.outputs, flow_from=self.spec.flow_from(L))
        self.optimizer.zero_grad(set_to_none=True)
        lr = set_lr(self.optimizer, self.cfg["optim"], self.step)
        self.spec.step = self.step
        loss, stats, preds = self.forward(b)
        loss.backward()
        if self.clip:  # the norm before clipping
            grad_norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), float(self.clip))
        else:
            grads = [p.grad for p in self.model.parameters() if p.grad is not None]
            grad_norm = torch.nn.utils.get_total_norm(grads) if grads else torch.zeros((), device=self.device)
        self.optimizer.step()
        self.step += 1
        if self.net is not self.model:
            # a compiled network's outputs may live in CUDA-graph memory that the next replay
            # overwrites (a Ctrl-C mid-step included): previews and the final checkpoint read
            # these later, so they keep a copy (a list's in one stack, returned as its views)
            preds = list(torch.stack(preds).unbind(0)) if isinstance(preds, list) else preds.detach().clone()
        self._last = (b, preds)
        stats["loss"] = loss.detach()
        stats["grad_norm"] = grad_norm.detach()
        if sync:
            stats = {k: float(v) for k, v in stats.items()}
            if not math.isfinite(stats["loss"]):
                raise FloatingPointError(f"non-finite loss {stats['loss']} at step {self.step - 1}")
        stats["samples"] = n_real
        stats["lr"] = lr
        return stats

    def preview(self, max_rows: int = 4) -> np.ndarray:
        """The last step's preview, (H, W, 3) uint8 BGR: per sample (up to ``max_rows``) a row
        voxel | prediction | ground truth at the sequence's last voxel (``spec.preview_row``)."""
        b, preds = self._last
        vox = b["voxels"][:, -1].cpu().numpy()
        return grid_image([self.spec.preview_row(b, preds, i, vox[i]) for i in range(min(max_rows, vox.shape[0]))])

    def save_samples(self, path: Optional[str] = None, max_rows: int = 4, grid: Optional[np.ndarray] = None) -> str:
        """Write the last step's :meth:`preview` (or ``grid``, one made already) as a PNG, by
        default ``samples/step_NNNNNNN.png``. Returns the path."""
        path = path or str(self.out / "samples" / f"step_{self.step:07d}.png")
        write_png(path, self.preview(max_rows) if grid is None else grid)
        return path

    def checkpoint(self, stream=None) -> dict:
        """Everything needed to resume: model, optimiser, step, config, stream state."""
        sd = None
        if stream is not None and hasattr(stream, "state_dict"):
            sd = stream.state_dict()
        return {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(), "step": self.step,
                "task": self.task, "config": self.cfg, "stream_state": sd, "torch_rng": torch.get_rng_state(),
                "perceptual_term": self.perceptual_term}

    def save_checkpoint(self, stream=None) -> Path:
        """Write ``checkpoint_NNNNNNN.pt`` and refresh ``checkpoint_last.pt``; returns the former."""
        ck = self.checkpoint(stream)
        path = self.out / f"checkpoint_{self.step:07d}.pt"
        tmp, last = path.with_suffix(".tmp"), self.out / "checkpoint_last.tmp"
        try:  # whole files or none: an interrupt while writing leaves no temporary file behind
            torch.save(ck, tmp)
            os.replace(tmp, path)
            shutil.copyfile(path, last)
            os.replace(last, self.out / "checkpoint_last.pt")
        except BaseException:
            for t in (tmp, last):
                t.unlink(missing_ok=True)
            raise
        return path

    def load_checkpoint(self, path: str, stream=None) -> None:
        """Restore model, optimiser and step from ``path``; hand the stored stream state to
        ``stream.load_state_dict`` when both exist (else the stream starts afresh, logged).
        Raises ``ValueError`` when the checkpoint is for another task."""
        ck = torch.load(path, map_location=self.device, weights_only=False)
        if ck.get("task") != self.task:
            raise ValueError(f"checkpoint {path} is for task {ck.get('task')!r}, not {self.task!r}")
        self.model.load_state_dict(ck["model"])
        self.optimizer.load_state_dict(ck["optimizer"])
        self.step = int(ck["step"])
        self.stream_state = ck.get("stream_state")
        if stream is not None:
            if self.stream_state is not None and hasattr(stream, "load_state_dict"):
                stream.load_state_dict(self.stream_state)
                log.info("resumed stream position from checkpoint")
            else:
                log.warning("checkpoint has no stream state or the client cannot load one: "
                            "the stream restarts its epoch")
        log.info("resumed from %s at step %d", path, self.step)

    def fit(self, stream, max_steps: int, image_every: int = 500, checkpoint_every: int = 1000,
            progress: bool = True, log_every: int = 10, tensorboard: bool = True,
            startup: Optional[dict] = None) -> dict:
        """Train from a stream until ``max_steps`` total steps, the stream ends or Ctrl-C.

        ``stream``: a plan's epochs (``v2v_client.PlanEpochs``, read through a
        ``trainer.data.ReadAhead``), a read path already made (``trainer.data.read_path``:
        ``v2v-train`` starts reading before it builds the model), or any other iterable of stream batches
        (a list, say: ``trainer.data.make_loader``). Checkpoints carry the read path's
        ``state_dict()`` (a ``ReadAhead``'s: the position of the last batch trained on); with
        ``tensorboard``, event files too, their ``recipe`` the stream's ``recipe()`` when it has
        one (a plan's: ``v2v_client.PlanEpochs.recipe``). ``startup``: the caller's start-up
        phases (seconds), added to the summary's ``startup_s``. Returns the summary of
        ``trainer.loop.train_loop``, its ``feed`` line with the server's figures where it reports
        them (``server_feed``). Ctrl-C or SIGTERM leaves a ``ReadAhead`` without waiting for its
        thread (:func:`close_read_path`)."""
        from torch.utils.data import DataLoader

        from .data import ReadAhead, close_read_path, read_path
        from .loop import RunHooks, Schedule, train_loop

        if isinstance(stream, (ReadAhead, DataLoader)):  # a read path already made (v2v-train's)
            feed, source = stream, stream.stream if isinstance(stream, ReadAhead) else stream.dataset
        else:
            feed, source = read_path(stream, self.device), stream
        saved = feed if isinstance(feed, ReadAhead) else source

        def extra() -> dict:
            first = getattr(feed, "first_batch_s", None)
            phases = dict(startup or {}, **({"first_batch": round(first, 4)} if first is not None else {}))
            return {"startup_s": phases} if phases else {}

        recipe, server_feed = getattr(source, "recipe", None), getattr(source, "server_feed", None)
        hooks = RunHooks(recipe=recipe if callable(recipe) else (lambda: None), summary_extra=extra,
                         server_feed=server_feed if callable(server_feed) else (lambda timeout_s=None: None))
        interrupted = False
        try:
            return train_loop(self, feed, max_steps, Schedule(image_every, checkpoint_every, progress, log_every,
                                                              tensorboard),
                              lambda: self.save_checkpoint(saved), hooks)
        except KeyboardInterrupt:
            interrupted = True
            raise
        finally:
            close_read_path(feed, wait=not interrupted)

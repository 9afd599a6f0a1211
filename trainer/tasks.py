"""What each training task is: the outputs it asks the stream for, its loss, its logged terms
and its preview. ``TASKS`` is the registry the trainer, the Ray engine and the stream helpers
look a task up in; adding a task is adding an entry.

* ``e2vid``: video reconstruction (Rebecq et al., TPAMI 2019) with the V2V paper's recipe: a
  recurrent network run through the sequence, L1 + LPIPS against the frame at each voxel's end,
  and temporal consistency (warped previous reconstruction) on the last part of the sequence.
* ``hypere2vid`` (Ercan et al., TIP 2024) and ``etnet`` (Weng et al., ICCV 2021): the same
  reconstruction recipe with their networks; HyperE2VID adds its ground-truth curriculum
  (``curriculum`` config section).
* ``evflow``: optical flow (EV-FlowNet, Zhu et al., RSS 2018) regressed per voxel with an L1
  loss; average end-point error logged.
* ``eraft``: optical flow (E-RAFT, Gehrig et al., 3DV 2021) from pairs of consecutive voxel
  grids with warm start through the sequence, L1 loss on the last iteration's flow (the V2V
  authors' ``forward_type: eraft``).
"""
from __future__ import annotations

import contextlib
import logging
import math
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np
import torch

from .losses import ReconstructionLoss, flow_l1_loss, temporal_consistency_loss
from .viz import flow_to_bgr, gray_to_u8, voxel_to_u8

__all__ = ["TrainTask", "E2VIDTask", "HyperE2VIDTask", "ETNetTask", "EvFlowTask", "ERAFTTask", "TASKS", "get_task",
           "stream_outputs", "tc_start_index", "curriculum_beta"]

log = logging.getLogger("trainer")

Autocast = Callable[[], contextlib.AbstractContextManager]


def tc_start_index(sequence_length: int, fraction: float) -> int:
    """First voxel index l whose reconstruction enters the temporal consistency loss:
    ``max(1, ceil(fraction * L))`` (20 for L = 40, fraction 0.5: frames 20..39)."""
    return max(1, int(math.ceil(fraction * sequence_length)))


def curriculum_beta(step: int, max_steps: int, fraction: float, stages: int) -> float:
    """HyperE2VID's curriculum weight of the ground-truth frame at optimiser step ``step``:
    ``1 - floor(stages * step / (fraction * max_steps)) / stages`` while step < fraction *
    max_steps, else 0 (the authors' ``hyper_beta = 1 - epoch / hyper_epochs`` with
    ``stages`` = hyper_epochs and an "epoch" of ``fraction * max_steps / stages`` steps)."""
    span = fraction * max_steps
    if span <= 0 or step >= span or stages < 1:
        return 0.0
    return 1.0 - math.floor(stages * step / span) / stages


def _detached(v, like: torch.Tensor) -> torch.Tensor:
    """``v`` (a tensor, or the float 0.0 of a term never added to) as a detached 0-dim tensor
    on ``like``'s device."""
    return v.detach() if isinstance(v, torch.Tensor) else torch.zeros((), device=like.device)


class TrainTask:
    """One task's part of a training step. Subclasses set ``name``, ``outputs`` (what the
    stream must carry, in wire order) and ``terms`` (the loss terms logged besides ``loss``).

    Args:
        cfg: the trainer config (``trainer/config.py``); a task reads its ``loss`` section.
        device: where the losses' own modules live.
    """

    name: str = ""
    outputs: Tuple[str, ...] = ()
    terms: Tuple[str, ...] = ()

    def __init__(self, cfg: dict, device: torch.device):
        self.cfg = cfg
        self.fast = cfg.get("speed", "eager") == "fast"  # trainer/speed.py
        self.step = 0  # the optimiser step about to be taken; the trainer sets it before forward
        self.outputs = stream_outputs(cfg)
        self.raft = None  # RaftFlow when loss.flow_source names RAFT (tasks that use flow)
        lc = cfg.get("loss", {})
        if lc.get("flow_source", "stream") != "stream":
            from .raft_flow import RaftFlow

            self.raft = RaftFlow(lc["flow_source"], device, int(lc.get("raft_num_flow_updates", 12)),
                                 lc.get("raft_weights"))
            log.info("%s: flow from %s on %s, %d iterations", self.name, lc["flow_source"], device,
                     self.raft.num_flow_updates)

    @classmethod
    def csv_columns(cls) -> List[str]:
        """Columns of ``train_log.csv`` for this task (``trainer.tensorboard_log`` names their tags)."""
        return ["step", "epoch", "sample_in_epoch", "loss", *cls.terms, "lr", "grad_norm", "data_wait_s", "step_s",
                "samples_per_s"]

    def flow_from(self, sequence_length: int) -> Optional[int]:
        """First voxel whose flow the step uses (only that part is copied to the device), or
        None for all of it."""
        return None

    def forward(self, model: torch.nn.Module, b: dict, autocast: Autocast):
        """Loss (scalar float32 tensor), logged terms (detached 0-dim tensors on the device:
        reading them waits for the device, which the trainer does only at its logging
        interval) and the predictions (detached, float32) of one batch ``b`` already on the
        device (``trainer.data.batch_to_device``). ``autocast()`` wraps the network's forward
        only; losses and metrics are computed in float32."""
        raise NotImplementedError

    def preview_row(self, b: dict, preds, i: int, voxel: np.ndarray) -> list:
        """Images of sample ``i`` at the sequence's last voxel: voxel | prediction | ground truth."""
        raise NotImplementedError


class E2VIDTask(TrainTask):
    name = "e2vid"
    outputs = ("voxels", "frames", "flow")
    terms = ("l1", "perceptual", "tc")

    def __init__(self, cfg: dict, device: torch.device):
        super().__init__(cfg, device)
        lc = cfg["loss"]
        self.rec_loss = ReconstructionLoss(lc["l1_weight"], lc["perceptual_weight"], lc["lpips_net"],
                                           lc["lpips_weights"], lc["use_lpips_package"]).to(device)
        log.info("E2VID perceptual term: %s", self.rec_loss.perceptual)

    def flow_from(self, sequence_length: int) -> Optional[int]:
        return tc_start_index(sequence_length, float(self.cfg["loss"].get("tc_start_fraction", 0.5)))

    def forward(self, model, b, autocast):
        """The recurrent state is carried through the sequence (and dropped after it: every
        stream batch holds new clips). Reconstruction loss averaged over the L steps;
        temporal consistency averaged over all L steps, those before the start contributing
        zero (the V2V reference's ``calc_loss``)."""
        vox, frames, flow = b["voxels"], b["frames"], b.get("flow")
        L = vox.shape[1]
        lc = self.cfg["loss"]
        l0 = self.flow_from(L)
        if self.raft is not None and float(lc["tc_weight"]) > 0 and l0 < L:
            flow = self.raft(frames, l0)  # the layout of the stream's flow[:, l0:]
        use_tc = float(lc["tc_weight"]) > 0 and flow is not None and l0 < L
        if self.fast:
            return self._forward_whole_sequence(model, vox, frames, flow, l0, use_tc, autocast)
        states, prev = None, None
        sums = {"l1": 0.0, "perceptual": 0.0, "rec": 0.0, "tc": 0.0}
        n_tc = 0
        preds = []
        for l in range(L):
            with autocast():
                pred, states = self.step_model(model, vox[:, l], states, frames[:, l + 1])
            pred = pred.float()  # losses in float32, outside autocast
            r = self.rec_loss(pred, frames[:, l + 1])
            sums["rec"] = sums["rec"] + r["total"]
            sums["l1"] = sums["l1"] + r["l1"].detach()
            if self.rec_loss.perceptual in r:
                sums["perceptual"] = sums["perceptual"] + r[self.rec_loss.perceptual].detach()
            if use_tc and l >= l0:
                # flow was sliced from l0 on: flow[:, l - l0] is frame l -> l + 1
                sums["tc"] = sums["tc"] + temporal_consistency_loss(
                    frames[:, l], frames[:, l + 1], prev, pred, flow[:, l - l0],
                    alpha=float(lc["tc_alpha"]))
                n_tc += 1
            prev = pred
            preds.append(pred.detach())
        loss = sums["rec"] / L
        tc = sums["tc"] / L if n_tc else torch.zeros((), device=vox.device)
        loss = loss + float(lc["tc_weight"]) * tc
        stats = {"l1": _detached(sums["l1"] / L, loss), "perceptual": _detached(sums["perceptual"] / L, loss),
                 "tc": tc.detach()}
        return loss, stats, preds

    def _forward_whole_sequence(self, model, vox, frames, flow, l0: int, use_tc: bool, autocast):
        """``forward`` under ``speed: fast``: the network runs through the sequence as in eager,
        from the first state as zero tensors (the network's ``initial_states``: bit-identical
        to ``None``, and one compiled graph for every step of the sequence), then each loss term is one call on the L predictions stacked along the batch (one L1
        and one LPIPS/SSIM call on (B * L, 1, H, W), one temporal-consistency call on the
        B * (L - l0) pairs) instead of L calls: the terms are means over equal-sized steps, so
        the mean over the stack is the mean of the per-step means (equal up to float32
        summation order; ``tests/test_trainer_fast.py``)."""
        lc = self.cfg["loss"]
        L = vox.shape[1]
        with autocast():  # the zero states take autocast's dtype, as the states the network returns
            states = model.initial_states(vox[:, 0], requires_grad=torch.is_grad_enabled())
        preds = []
        for l in range(L):
            with autocast():
                pred, states = self.step_model(model, vox[:, l], states, frames[:, l + 1])
            preds.append(pred.float())  # losses in float32, outside autocast
        seq = torch.stack(preds, 1)  # (B, L, 1, H, W)
        r = self.rec_loss(seq.flatten(0, 1), frames[:, 1:].flatten(0, 1))
        zero = torch.zeros((), device=vox.device)
        tc = zero
        if use_tc:  # pairs (l - 1, l) for l = l0..L-1; flow was sliced from l0 on
            tc = temporal_consistency_loss(frames[:, l0:L].flatten(0, 1), frames[:, l0 + 1:].flatten(0, 1),
                                           seq[:, l0 - 1:L - 1].flatten(0, 1), seq[:, l0:].flatten(0, 1),
                                           flow[:, :L - l0].flatten(0, 1), alpha=float(lc["tc_alpha"]))
            tc = tc * ((L - l0) / L)  # averaged over all L steps, those before l0 zero (as eager)
        loss = r["total"] + float(lc["tc_weight"]) * tc
        perceptual = r.get(self.rec_loss.perceptual, zero)
        stats = {"l1": r["l1"].detach(), "perceptual": perceptual.detach(), "tc": tc.detach()}
        return loss, stats, [p.detach() for p in preds]

    def step_model(self, model, voxel, states, target):
        """One recurrent step: ``(prediction (N, 1, H, W), states)``; ``target`` is the frame at
        the voxel's end (used by HyperE2VID's curriculum)."""
        return model(voxel, states)

    def preview_row(self, b, preds, i, voxel):
        return [voxel_to_u8(voxel), gray_to_u8(preds[-1][i].cpu().numpy()), gray_to_u8(b["frames"][i, -1].cpu().numpy())]


class HyperE2VIDTask(E2VIDTask):
    """HyperE2VID: the E2VID recipe; during the curriculum the dynamic decoder's context sees
    ``(1 - beta) * previous reconstruction + beta * frame`` where frame is the target of the
    step (the authors' ``forward_sequence`` passes ``frame[:, t]``, the frame at voxel t's end)."""

    name = "hypere2vid"

    def __init__(self, cfg: dict, device: torch.device):
        super().__init__(cfg, device)
        self._betas: Dict[Tuple[float, torch.device], torch.Tensor] = {}

    def _beta_tensor(self, beta: float, device: torch.device) -> torch.Tensor:
        """``beta`` as a 0-dim float32 tensor on ``device``, made once per curriculum stage (a
        copy to the device per stage, none per step)."""
        t = self._betas.get((beta, device))
        if t is None:
            t = self._betas[(beta, device)] = torch.tensor(beta, dtype=torch.float32, device=device)
        return t

    def step_model(self, model, voxel, states, target):
        """Under ``speed: fast`` the network gets the frame and beta (a device tensor) on every
        training step, 0 after the curriculum too, and (``_forward_whole_sequence``) the
        sequence's first state as zero tensors (``HyperE2VID.initial_states``): the same inputs
        for the whole run, so a compiled network keeps one graph through all the stages
        (bit-identical at beta 0 and 1, ``trainer.models.hypere2vid.HyperE2VID``). ``eager``:
        the authors' float and branch."""
        c = self.cfg["curriculum"]
        beta = curriculum_beta(self.step, int(self.cfg["max_steps"]), float(c["fraction"]), int(c["stages"]))
        if self.fast and model.training:
            return model(voxel, states, gt_image=target, beta=self._beta_tensor(beta, voxel.device))
        if beta > 0 and model.training:
            return model(voxel, states, gt_image=target, beta=beta)
        return model(voxel, states)


class ETNetTask(E2VIDTask):
    """ETNet: the E2VID recipe with the transformer network (sigmoid output in (0, 1))."""

    name = "etnet"


class EvFlowTask(TrainTask):
    name = "evflow"
    outputs = ("voxels", "flow")
    terms = ("flow_l1", "aee")

    def forward(self, model, b, autocast):
        if self.raft is not None:
            b["flow"] = self.raft(b["frames"])  # targets: frame l -> l + 1 for each voxel l
        vox, flow = b["voxels"], b["flow"]
        n, L = vox.shape[:2]
        with autocast():
            pred = model(vox.flatten(0, 1))
        pred = pred.float()
        gt = flow.flatten(0, 1)
        l1 = flow_l1_loss(pred, gt)
        loss = float(self.cfg["loss"]["flow_l1_weight"]) * l1
        with torch.no_grad():
            aee = torch.linalg.vector_norm(pred - gt, dim=1).mean()
        return loss, {"flow_l1": l1.detach(), "aee": aee}, pred.detach().view(n, L, *pred.shape[1:])

    def preview_row(self, b, preds, i, voxel):
        gt = b["flow"][i, -1].cpu().numpy()
        pred = preds[i, -1].cpu().numpy()
        m = max(float(np.percentile(np.hypot(gt[0], gt[1]), 99)), 1e-3)
        return [voxel_to_u8(voxel), flow_to_bgr(pred, m), flow_to_bgr(gt, m)]


class ERAFTTask(EvFlowTask):
    """E-RAFT as the V2V authors train it (``model/train_flow_utils.py``,
    ``forward_sequence_eraft``): the sequence's warm-start flow is reset, then for l = 1..L-1
    the network sees voxel grids l-1 and l and predicts the flow over voxel l's interval, frame
    l -> l+1 (their sample carries L+1 grids for L flows; a stream sample of L grids gives L-1
    pairs, the first grid serving only as the first pair's predecessor). Loss: L1 between the
    last iteration's flow and the target, averaged over pixels, components, samples and the
    L-1 pairs (their ``l1_loss`` per step, averaged over steps); ``aee`` logged the same way."""

    name = "eraft"
    outputs = ("voxels", "flow")
    terms = ("flow_l1", "aee")

    def flow_from(self, sequence_length: int) -> Optional[int]:
        return 1

    def forward(self, model, b, autocast):
        vox = b["voxels"]
        n, L = vox.shape[:2]
        if L < 2:
            raise ValueError(f"eraft needs sequences of at least 2 voxel grids (pairs l-1, l), got L = {L}")
        if self.raft is not None:
            b["flow"] = self.raft(b["frames"], 1)
        flow = b["flow"]  # (n, L-1, 2, H, W): the targets of voxels 1..L-1 (the stream's arrive sliced, flow_from)
        if self.fast:
            # the warm start as zeros, not None: one compiled graph for every pair
            model.reset_states(vox[:, 0])
            # one L1 and one end-point-error call on the stacked flows instead of L - 1 of each:
            # means over equal-sized pairs, so equal to the per-pair mean up to summation order
            preds = []
            for l in range(1, L):
                with autocast():
                    preds.append(model(vox[:, l - 1], vox[:, l]).float())
            seq = torch.stack(preds, dim=1)  # (n, L-1, 2, H, W)
            l1 = flow_l1_loss(seq, flow)
            with torch.no_grad():
                aee = torch.linalg.vector_norm(seq - flow, dim=2).mean()
            loss = float(self.cfg["loss"]["flow_l1_weight"]) * l1
            return loss, {"flow_l1": l1.detach(), "aee": aee}, seq.detach()
        model.reset_states()
        l1 = aee = 0.0
        preds = []
        for l in range(1, L):
            with autocast():
                pred = model(vox[:, l - 1], vox[:, l])
            pred = pred.float()
            gt = flow[:, l - 1]
            l1 = l1 + flow_l1_loss(pred, gt)
            with torch.no_grad():
                aee = aee + torch.linalg.vector_norm(pred - gt, dim=1).mean()
            preds.append(pred.detach())
        l1, aee = l1 / (L - 1), aee / (L - 1)
        loss = float(self.cfg["loss"]["flow_l1_weight"]) * l1
        # stats stay on the device (read at the logging interval: no host sync per step)
        return loss, {"flow_l1": l1.detach(), "aee": aee}, torch.stack(preds, dim=1)


#: The tasks by name (``cfg["task"]``, ``v2v-train --task``).
TASKS: Dict[str, type] = {t.name: t for t in (E2VIDTask, EvFlowTask, HyperE2VIDTask, ETNetTask, ERAFTTask)}


def stream_outputs(cfg: dict) -> Tuple[str, ...]:
    """What the stream must carry for the run ``cfg``: the task's ``outputs``, with the flow
    replaced by the frames it is computed from when ``loss.flow_source`` names RAFT.

    Raises:
        ValueError: for an unknown task.
    """
    outs = get_task(cfg["task"]).outputs
    if cfg.get("loss", {}).get("flow_source", "stream") == "stream" or "flow" not in outs:
        return outs
    return tuple(o for o in outs if o != "flow") + (() if "frames" in outs else ("frames",))


def get_task(name: str) -> type:
    """The task class called ``name``.

    Raises:
        ValueError: naming the known tasks, for another name.
    """
    if name not in TASKS:
        raise ValueError(f"task must be one of {list(TASKS)}, got {name!r}")
    return TASKS[name]

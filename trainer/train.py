"""``v2v-train``: train E2VID or EvFlow from a live ``v2v-serve`` stream.

Paper: Lou et al., "V2V", NeurIPS 2025 (training recipe of event_cnn_minimal):
Adam (lr 1e-4, amsgrad, no weight decay, constant lr), batch 12, sequences of 40 voxel
grids; E2VID's recurrent state is carried through a sequence and reset (hence detached)
at the next one, since every stream batch holds new random clips.

Outputs in ``--out``: ``train_log.csv`` (one row per step, column ``loss``), ``train.log``,
``samples/step_NNNNNNN.png`` (voxel / prediction / ground truth), ``checkpoint_last.pt``
and ``checkpoint_NNNNNNN.pt`` (model, optimiser, step, config, the stream's
``state_dict()`` when the client has one).
"""
from __future__ import annotations

import argparse
import contextlib
import csv
import json
import logging
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Iterable, Optional

import numpy as np
import torch

from .config import apply_overrides, load_config
from .data import batch_to_device, drop_padding, make_loader, make_stream, tc_start_index, task_outputs
from .losses import TC_FORMS, ReconstructionLoss, flow_l1_loss, temporal_consistency_loss
from .models import build_model
from .viz import flow_to_bgr, gray_to_u8, save_grid, voxel_to_u8

__all__ = ["Trainer", "resolve_device", "main"]

log = logging.getLogger("trainer")

CSV_COLUMNS = {
    "e2vid": ["step", "epoch", "batch_id", "loss", "l1", "perceptual", "tc", "data_wait_s", "step_s"],
    "evflow": ["step", "epoch", "batch_id", "loss", "flow_l1", "aee", "data_wait_s", "step_s"],
}


def resolve_device(name: str) -> torch.device:
    """'auto' -> cuda if available else cpu; 'cuda' without a GPU raises ``RuntimeError``."""
    if name in (None, "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("--device cuda requested but torch.cuda.is_available() is False")
    return dev


class Trainer:
    """One training run: model, optimiser, losses, logs and checkpoints.

    Args:
        cfg: full config (see ``trainer/config.py``); ``cfg['task']`` is 'e2vid' or 'evflow'.
        out_dir: folder for logs, samples and checkpoints (created).
        device: torch device.

    Use :meth:`fit` with an iterable of stream batches (the contract of
    ``v2v_client.V2VStreamDataset``), or :meth:`train_step` on one batch.
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
        self.model = build_model(self.task, dict(cfg["model"])).to(device)
        o = cfg["optim"]
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=float(o["lr"]), amsgrad=bool(o["amsgrad"]),
                                          weight_decay=float(o["weight_decay"]))
        self.clip = o.get("clip_grad_norm")
        amp = str(cfg.get("amp", "fp32")).lower()
        if amp not in ("fp32", "bf16"):
            raise ValueError(f"amp must be 'fp32' or 'bf16', got {cfg.get('amp')!r}")
        self.amp = device.type == "cuda" and amp == "bf16"
        self.step = 0
        lc = cfg["loss"]
        self.tc_form = str(lc.get("tc_form", "reference"))
        if self.task == "e2vid" and self.tc_form not in TC_FORMS:
            raise ValueError(f"loss.tc_form must be one of {list(TC_FORMS)}, got {self.tc_form!r}")
        if self.task == "e2vid":
            self.rec_loss = ReconstructionLoss(lc["l1_weight"], lc["perceptual_weight"], lc["lpips_net"],
                                               lc["lpips_weights"], lc["use_lpips_package"]).to(device)
            log.info("E2VID perceptual term: %s", self.rec_loss.perceptual)
        self.stream_state = None
        self._csv = None

    # ------------------------------------------------------------------ steps
    def _autocast(self):
        if self.amp:
            return torch.autocast("cuda", dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def _forward_e2vid(self, b: dict):
        vox, frames, flow = b["voxels"], b["frames"], b.get("flow")
        n, L = vox.shape[:2]
        lc = self.cfg["loss"]
        l0 = tc_start_index(L, float(lc["tc_start_fraction"]))
        use_tc = float(lc["tc_weight"]) > 0 and flow is not None and l0 < L
        states, prev = None, None
        sums = {"l1": 0.0, "perceptual": 0.0, "rec": 0.0, "tc": 0.0}
        n_tc = 0
        preds = []
        for l in range(L):
            with self._autocast():
                pred, states = self.model(vox[:, l], states)
                r = self.rec_loss(pred.float(), frames[:, l + 1])
            pred = pred.float()
            sums["rec"] = sums["rec"] + r["total"]
            sums["l1"] = sums["l1"] + r["l1"].detach()
            if self.rec_loss.perceptual in r:
                sums["perceptual"] = sums["perceptual"] + r[self.rec_loss.perceptual].detach()
            if use_tc and l >= l0:
                # flow was sliced from l0 on: flow[:, l - l0] is frame l -> l + 1
                sums["tc"] = sums["tc"] + temporal_consistency_loss(
                    frames[:, l], frames[:, l + 1], prev, pred, flow[:, l - l0],
                    alpha=float(lc["tc_alpha"]), mode=lc["tc_warp"], form=self.tc_form)
                n_tc += 1
            prev = pred
            preds.append(pred.detach())
        loss = sums["rec"] / L
        # reference form: averaged over all L steps, those before l0 contributing zero (the V2V
        # reference's calc_loss); absolute form: averaged over the steps that have the term
        tc_div = L if self.tc_form == "reference" else n_tc
        tc = sums["tc"] / tc_div if n_tc else torch.zeros((), device=vox.device)
        loss = loss + float(lc["tc_weight"]) * tc
        stats = {"l1": float(sums["l1"] / L), "perceptual": float(sums["perceptual"] / L), "tc": float(tc.detach())}
        return loss, stats, preds

    def _forward_evflow(self, b: dict):
        vox, flow = b["voxels"], b["flow"]
        n, L = vox.shape[:2]
        with self._autocast():
            pred = self.model(vox.flatten(0, 1))
        pred = pred.float()
        gt = flow.flatten(0, 1)
        l1 = flow_l1_loss(pred, gt)
        loss = float(self.cfg["loss"]["flow_l1_weight"]) * l1
        with torch.no_grad():
            aee = torch.linalg.vector_norm(pred - gt, dim=1).mean()
        return loss, {"flow_l1": float(l1.detach()), "aee": float(aee)}, pred.detach().view(n, L, *pred.shape[1:])

    def _check_batch(self, b: dict):
        nb = self.cfg["model"]["num_bins"]
        v = b["voxels"]
        if v.ndim != 5 or v.shape[2] != nb:
            raise ValueError(f"stream voxels have shape {tuple(v.shape)}, model expects (B, L, {nb}, H, W); "
                             f"start v2v-serve with --num-bins {nb} or set model.num_bins")

    def train_step(self, batch: dict) -> dict:
        """One optimiser step on one stream batch (host tensors). Returns floats:
        ``loss`` and the task's terms. Samples flagged ``padding`` are left out of the loss;
        a batch of padding only makes no step and returns ``{"loss": nan, "samples": 0}``."""
        batch, n_real = drop_padding(batch)
        if n_real == 0:
            return {"loss": float("nan"), "samples": 0}
        self._check_batch(batch)
        self.model.train()
        L = batch["voxels"].shape[1]
        l0 = tc_start_index(L, float(self.cfg["loss"].get("tc_start_fraction", 0.5))) if self.task == "e2vid" else None
        b = batch_to_device(batch, self.device, self.task, tc_start=l0)
        self.optimizer.zero_grad(set_to_none=True)
        if self.task == "e2vid":
            loss, stats, preds = self._forward_e2vid(b)
        else:
            loss, stats, preds = self._forward_evflow(b)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"non-finite loss {float(loss)} at step {self.step}")
        loss.backward()
        if self.clip:
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), float(self.clip))
        self.optimizer.step()
        self.step += 1
        self._last = (b, preds)
        stats["loss"] = float(loss.detach())
        return stats

    # -------------------------------------------------------------- outputs
    def save_samples(self, path: Optional[str] = None, max_rows: int = 4) -> str:
        """PNG grid of the last step: per sample, voxel | prediction | ground truth at the
        sequence's last voxel. Returns the path."""
        b, preds = self._last
        path = path or str(self.out / "samples" / f"step_{self.step:07d}.png")
        vox = b["voxels"][:, -1].cpu().numpy()
        rows = []
        for i in range(min(max_rows, vox.shape[0])):
            if self.task == "e2vid":
                pred = preds[-1][i].cpu().numpy()
                gt = b["frames"][i, -1].cpu().numpy()
                rows.append([voxel_to_u8(vox[i]), gray_to_u8(pred), gray_to_u8(gt)])
            else:
                gt = b["flow"][i, -1].cpu().numpy()
                pred = preds[i, -1].cpu().numpy()
                m = max(float(np.percentile(np.hypot(gt[0], gt[1]), 99)), 1e-3)
                rows.append([voxel_to_u8(vox[i]), flow_to_bgr(pred, m), flow_to_bgr(gt, m)])
        save_grid(path, rows)
        return path

    def checkpoint(self, stream=None) -> dict:
        """Everything needed to resume: model, optimiser, step, config, stream state."""
        sd = None
        if stream is not None and hasattr(stream, "state_dict"):
            sd = stream.state_dict()
        return {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(), "step": self.step,
                "task": self.task, "config": self.cfg, "stream_state": sd, "torch_rng": torch.get_rng_state()}

    def save_checkpoint(self, stream=None) -> Path:
        """Write ``checkpoint_NNNNNNN.pt`` and refresh ``checkpoint_last.pt``; returns the former."""
        ck = self.checkpoint(stream)
        path = self.out / f"checkpoint_{self.step:07d}.pt"
        tmp = path.with_suffix(".tmp")
        torch.save(ck, tmp)
        os.replace(tmp, path)
        shutil.copyfile(path, self.out / "checkpoint_last.tmp")
        os.replace(self.out / "checkpoint_last.tmp", self.out / "checkpoint_last.pt")
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

    # ------------------------------------------------------------------ loop
    def fit(self, stream: Iterable, max_steps: int, image_every: int = 500, checkpoint_every: int = 1000,
            progress: bool = True) -> dict:
        """Train until ``max_steps`` total steps, the stream ends or Ctrl-C (which still saves
        a checkpoint).

        Writes one CSV row per step and the sample/checkpoint files on their schedule and
        at the end. Returns a summary dict: steps, first/last loss, steps_per_s,
        data_wait_fraction (time blocked on the stream / wall time of the loop).
        """
        loader = make_loader(stream, self.device)
        csv_path = self.out / "train_log.csv"
        new = not csv_path.exists() or self.step == 0
        if not new:  # resumed: drop rows logged after the checkpoint we resumed from
            with open(csv_path, newline="") as f:
                kept = [r for r in csv.DictReader(f) if r.get("step", "").isdigit() and int(r["step"]) <= self.step]
            with open(csv_path, "w", newline="") as f:
                w = csv.DictWriter(f, fieldnames=CSV_COLUMNS[self.task], extrasaction="ignore")
                w.writeheader()
                w.writerows(kept)
        fh = open(csv_path, "w" if new else "a", newline="", buffering=1)  # line-buffered: tail -f works
        writer = csv.DictWriter(fh, fieldnames=CSV_COLUMNS[self.task], extrasaction="ignore")
        if new:
            writer.writeheader()
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=max_steps, initial=self.step, unit="step", dynamic_ncols=True, file=sys.stderr)
        losses, wait_total, t_start = [], 0.0, time.perf_counter()
        start_step = self.step
        it = iter(loader)
        try:
            while self.step < max_steps:
                t0 = time.perf_counter()
                try:
                    batch = next(it)
                except StopIteration:
                    log.info("stream ended at step %d", self.step)
                    break
                t1 = time.perf_counter()
                stats = self.train_step(batch)
                if self.device.type == "cuda":
                    torch.cuda.synchronize(self.device)
                t2 = time.perf_counter()
                wait_total += t1 - t0
                stats.update(step=self.step, epoch=batch.get("epoch", ""), batch_id=batch.get("batch_id", ""),
                             data_wait_s=round(t1 - t0, 5), step_s=round(t2 - t0, 5))
                writer.writerow(stats)
                losses.append(stats["loss"])
                if bar is not None:
                    el = t2 - t_start
                    bar.set_postfix(loss=f"{stats['loss']:.4f}", wait=f"{wait_total / max(el, 1e-9):.0%}", refresh=False)
                    bar.update(1)
                if image_every and self.step % image_every == 0:
                    self.save_samples()
                if checkpoint_every and self.step % checkpoint_every == 0:
                    fh.flush()
                    self.save_checkpoint(stream)
        except KeyboardInterrupt:
            log.warning("interrupted at step %d: saving a checkpoint", self.step)
        finally:
            fh.close()
            if bar is not None:
                bar.close()
        elapsed = time.perf_counter() - t_start
        n = self.step - start_step
        if n:
            self.save_samples()
            if not checkpoint_every or self.step % checkpoint_every:
                self.save_checkpoint(stream)
        summary = {"task": self.task, "steps": n, "final_step": self.step,
                   "first_loss": losses[0] if losses else None, "last_loss": losses[-1] if losses else None,
                   "mean_loss_first10": float(np.mean(losses[:10])) if losses else None,
                   "mean_loss_last10": float(np.mean(losses[-10:])) if losses else None,
                   "steps_per_s": n / elapsed if elapsed > 0 else None,
                   "data_wait_fraction": wait_total / elapsed if elapsed > 0 else None}
        with open(self.out / "summary.json", "w") as f:
            json.dump(summary, f, indent=2)
        log.info("done: %s", json.dumps(summary))
        return summary


def _setup_logging(out: Path):
    out.mkdir(parents=True, exist_ok=True)
    root = logging.getLogger()
    root.setLevel(logging.INFO)
    fmt = logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s")
    for h in (logging.StreamHandler(sys.stderr), logging.FileHandler(out / "train.log")):
        h.setFormatter(fmt)
        root.addHandler(h)


def build_arg_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="v2v-train", description="Train E2VID / EvFlow from a v2v-serve stream.")
    p.add_argument("--config", help="YAML config (trainer/configs/e2vid.yaml, evflow.yaml)")
    p.add_argument("--task", choices=["e2vid", "evflow"])
    p.add_argument("--connect", help="server endpoint, e.g. tcp://127.0.0.1:5555")
    p.add_argument("--max-steps", type=int)
    p.add_argument("--out", help="output folder (default runs/<task>)")
    p.add_argument("--device", help="auto | cpu | cuda | cuda:N")
    p.add_argument("--resume", help="checkpoint path, or 'auto' for <out>/checkpoint_last.pt if present")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="config override, e.g. --set model.base_num_channels=8 (repeatable)")
    p.add_argument("--no-progress", action="store_true", help="no tqdm bar")
    p.add_argument("--engine", choices=["stream", "ray"], default="stream",
                   help="stream: read a v2v-serve endpoint (--connect); ray: make the samples in a Ray Data "
                        "pipeline from --videos and train in a Ray Train TorchTrainer (needs the 'ray' extra)")
    from .ray_train import add_ray_arguments

    add_ray_arguments(p)
    return p


def main(argv=None) -> int:
    args = build_arg_parser().parse_args(argv)
    cfg = load_config(args.config, args.task)
    cfg = apply_overrides(cfg, args.set)
    for key in ("connect", "max_steps", "out", "device", "resume"):
        v = getattr(args, key)
        if v is not None:
            cfg[key] = v
    out = Path(str(cfg["out"]).format(task=cfg["task"]))
    _setup_logging(out)
    if args.engine == "ray":
        from .ray_train import run_ray

        return run_ray(cfg, args, out)
    device = resolve_device(cfg["device"])
    log.info("task %s on %s, stream %s asking for %s", cfg["task"], device, cfg["connect"], task_outputs(cfg["task"]))
    with open(out / "config.json", "w") as f:
        json.dump(cfg, f, indent=2)
    trainer = Trainer(cfg, str(out), device)
    log.info("model: %d parameters", sum(p.numel() for p in trainer.model.parameters()))
    s = cfg["stream"]
    extra = {k: s[k] for k in ("reconnect", "curve_keys") if s.get(k)}  # only when set: keeps make_stream's old calls
    stream = make_stream(cfg["connect"], cfg["task"], s["credits"], s["timeout_s"], s["raw"], **extra)
    resume = cfg.get("resume")
    if resume == "auto":
        resume = str(out / "checkpoint_last.pt") if (out / "checkpoint_last.pt").exists() else None
    if resume:
        trainer.load_checkpoint(resume, stream)
    lg = cfg["log"]
    trainer.fit(stream, int(cfg["max_steps"]), int(lg["image_every"]), int(lg["checkpoint_every"]),
                progress=bool(lg["progress"]) and not args.no_progress)
    close = getattr(stream, "close", None)
    if callable(close):
        close()
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

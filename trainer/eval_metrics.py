"""``v2v-eval``'s metrics: a frame's reconstruction and flow errors (the V2V paper's), and a
network run over one sequence, a real recording's grids included, scored frame by frame.

Conventions (``trainer/evaluate.py``'s docstring gives the inputs and the flow convention):

* reconstruction: MSE on [0, 1] images (prediction clipped to [0, 1]); SSIM with
  ``skimage.metrics.structural_similarity(win_size=7, data_range=R)``; LPIPS (AlexNet, v0.1)
  when a model is given; the constant-mean-image baseline alongside;
* flow: AEE (mean end-point error, pixels) and the % of pixels with error > 3 px, dense and
  sparse (pixels with at least one event).
"""
from __future__ import annotations

from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
import torch

__all__ = ["reconstruction_metrics", "flow_metrics", "evaluate_e2vid", "evaluate_evflow", "evaluate_eraft",
           "evaluate_recording", "summarise"]


def reconstruction_metrics(pred: np.ndarray, gt: np.ndarray, ssim_data_range: float = 1.0) -> Dict[str, float]:
    """MSE and SSIM of one frame. ``pred``, ``gt``: float (H, W) in [0, 1] (pred is
    clipped). SSIM: ``skimage.metrics.structural_similarity(win_size=7, data_range=R)``."""
    from skimage.metrics import structural_similarity

    pred = np.clip(np.asarray(pred, np.float64), 0.0, 1.0)
    gt = np.asarray(gt, np.float64)
    return {"mse": float(np.mean((pred - gt) ** 2)),
            "ssim": float(structural_similarity(pred, gt, win_size=7, data_range=ssim_data_range))}


def flow_metrics(pred: np.ndarray, gt: np.ndarray, event_mask: Optional[np.ndarray] = None,
                 threshold_px: float = 3.0) -> Dict[str, float]:
    """Flow errors of one frame pair.

    Ground-truth pixels that are NaN in either component or zero in both (MVSEC: no depth)
    are not scored, as in the V2V reference (``model/train_flow_utils.py``, mean over valid
    pixels).

    Args:
        pred, gt: float (2, H, W) flow in pixels.
        event_mask: bool (H, W), pixels with at least one event (sparse metrics), or None.
        threshold_px: outlier threshold on the end-point error, pixels.

    Returns:
        ``aee`` (mean end-point error, px) and ``outlier_pct`` (% of pixels with EPE >
        threshold) over the valid pixels (NaN when there is none), ``aee_sparse`` /
        ``outlier_pct_sparse`` over the valid event pixels (NaN when none or no mask), and
        ``valid_pct``, the % of pixels with valid ground truth.
    """
    gt = np.asarray(gt, np.float64)
    valid = ~(np.isnan(gt).any(axis=0) | ((gt[0] == 0) & (gt[1] == 0)))
    epe = np.sqrt(((np.asarray(pred, np.float64) - gt) ** 2).sum(0))
    nan = float("nan")
    out = {"aee": nan, "outlier_pct": nan, "aee_sparse": nan, "outlier_pct_sparse": nan,
           "valid_pct": float(100.0 * valid.mean())}
    if valid.any():
        e = epe[valid]
        out["aee"] = float(e.mean())
        out["outlier_pct"] = float(100.0 * (e > threshold_px).mean())
    if event_mask is not None:
        sparse = valid & np.asarray(event_mask, bool)
        if sparse.any():
            e = epe[sparse]
            out["aee_sparse"] = float(e.mean())
            out["outlier_pct_sparse"] = float(100.0 * (e > threshold_px).mean())
    return out


def _score(res: Dict[str, List[float]], p: np.ndarray, gt: np.ndarray, mean_img: np.ndarray,
           ssim_data_range: float, lpips_model, device) -> None:
    """Append one reconstruction's scores to ``res``: MSE and SSIM of ``p`` and of the
    constant-mean-image baseline ``mean_img`` against ``gt`` (float32 (H, W) in [0, 1]), and
    their LPIPS when ``lpips_model`` is given."""
    m = reconstruction_metrics(p, gt, ssim_data_range)
    b = reconstruction_metrics(mean_img, gt, ssim_data_range)
    res["mse"].append(m["mse"]); res["ssim"].append(m["ssim"])
    res["base_mse"].append(b["mse"]); res["base_ssim"].append(b["ssim"])
    if lpips_model is not None:
        g = torch.from_numpy(gt)[None, None].to(device)
        res["lpips"].append(float(lpips_model(torch.from_numpy(np.clip(p, 0, 1))[None, None].to(device), g)[0]))
        res["base_lpips"].append(float(lpips_model(torch.from_numpy(mean_img)[None, None].to(device), g)[0]))


@torch.no_grad()
def evaluate_e2vid(model, voxels: np.ndarray, frames: np.ndarray, device: torch.device, ssim_data_range: float = 1.0,
                   lpips_model=None, skip_first: int = 0) -> Dict[str, List[float]]:
    """Run the recurrent model over one sequence (state reset at its start) and score
    voxel l's reconstruction against frame l+1.

    Args:
        voxels: (L, B, H, W) signed counts; frames: uint8 (L+1, H, W).
        skip_first: frames at the start left out of the scores (recurrent warm-up).

    Returns:
        Per-frame lists: ``mse``, ``ssim``, ``lpips`` (if a model is given) and the
        constant-mean-image baseline's ``base_mse``, ``base_ssim``, ``base_lpips``.
    """
    gt_all = frames.astype(np.float32) / 255.0
    mean_img = np.full(gt_all.shape[1:], gt_all[1:].mean(), np.float32)
    res: Dict[str, List[float]] = {k: [] for k in ("mse", "ssim", "base_mse", "base_ssim")}
    if lpips_model is not None:
        res["lpips"], res["base_lpips"] = [], []
    states = None
    preds = []
    for l in range(voxels.shape[0]):
        v = torch.from_numpy(np.ascontiguousarray(voxels[l], dtype=np.float32))[None].to(device)
        pred, states = model(v, states)
        p = pred[0, 0].float().cpu().numpy()
        preds.append(p)
        if l < skip_first:
            continue
        _score(res, p, gt_all[l + 1], mean_img, ssim_data_range, lpips_model, device)
    res["_preds"] = preds  # not a metric; for saving images
    return res


@torch.no_grad()
def evaluate_evflow(model, voxels: np.ndarray, flows: np.ndarray, counts: Optional[np.ndarray],
                    device: torch.device) -> Dict[str, List[float]]:
    """Score flow predictions of each voxel against ``flows`` (L, 2, H, W) pixels;
    ``counts`` (L, H, W) event counts for the sparse metrics (None: the voxel's non-zero
    pixels are used). Returns per-frame lists of :func:`flow_metrics`' keys."""
    res: Dict[str, List[float]] = {}
    for l in range(min(voxels.shape[0], flows.shape[0])):
        v = torch.from_numpy(np.ascontiguousarray(voxels[l], dtype=np.float32))[None].to(device)
        p = model(v)[0].float().cpu().numpy()
        mask = counts[l] > 0 if counts is not None else np.any(voxels[l] != 0, axis=0)
        for k, val in flow_metrics(p, flows[l], mask).items():
            res.setdefault(k, []).append(val)
    return res


@torch.no_grad()
def evaluate_eraft(model, voxels: np.ndarray, flows: np.ndarray, counts: Optional[np.ndarray],
                   device: torch.device, sequence_length: int = 80) -> Dict[str, List[float]]:
    """Score E-RAFT's flow of each voxel against ``flows`` (K, 2, H, W) pixels, as the V2V
    authors' MVSEC test does (``data/testh5.py`` ``TestH5FlowDataset`` with
    ``output_additional_evs``, ``model/train_flow_utils.py`` ``forward_sequence_eraft``):

    * the voxels are cut into chunks of ``sequence_length`` (80); the warm-start flow is reset
      at each chunk's start;
    * voxel k is paired with voxel k-1 (the voxel before the chunk for its first pair; a zero
      grid before voxel 0, their empty event slice) and its flow scored against ``flows[k]``;
    * the sparse metrics' event mask is that of the pair's first voxel: their
      ``compute_metrics`` takes ``events[t]``, which for E-RAFT's L+1 grids is the grid before
      the scored interval (dense metrics do not use it).

    Args:
        voxels: (K, B, H, W) signed counts; counts: (K, H, W) event counts or None (then the
            voxels' non-zero pixels).
        sequence_length: pairs per chunk (their test configs: 80).

    Returns:
        Per-frame lists of :func:`flow_metrics`' keys.
    """
    res: Dict[str, List[float]] = {}
    k_all = min(voxels.shape[0], flows.shape[0])

    def grid(k):
        if k < 0:
            return torch.zeros((1, *voxels.shape[1:]), dtype=torch.float32, device=device)
        return torch.from_numpy(np.ascontiguousarray(voxels[k], dtype=np.float32))[None].to(device)

    for k in range(k_all):
        if k % int(sequence_length) == 0:
            model.reset_states()
        p = model(grid(k - 1), grid(k))[0].float().cpu().numpy()
        if k == 0:
            mask = np.zeros(voxels.shape[2:], bool)
        else:
            mask = counts[k - 1] > 0 if counts is not None else np.any(voxels[k - 1] != 0, axis=0)
        for key, val in flow_metrics(p, flows[k], mask).items():
            res.setdefault(key, []).append(val)
    return res


def summarise(per_input: Dict[str, Dict[str, List[float]]]) -> dict:
    """Means over every frame of every input (``mean``), the frame count (``frames``) and
    each input's means (``per_input``); keys starting with ``_`` are not metrics."""
    keys = sorted({k for r in per_input.values() for k in r if not k.startswith("_")})
    allv = {k: [v for r in per_input.values() for v in r.get(k, [])] for k in keys}
    return {
        "mean": {k: float(np.nanmean(v)) if len(v) else None for k, v in allv.items()},
        "frames": max((len(v) for v in allv.values()), default=0),
        "per_input": {name: {k: float(np.nanmean(v)) for k, v in r.items() if not k.startswith("_") and len(v)}
                      for name, r in per_input.items()},
    }


@torch.no_grad()
def evaluate_recording(model, task: str, grids, device: torch.device, frames: Optional[np.ndarray] = None,
                       ssim_data_range: float = 1.0, lpips_model=None, skip_first: int = 0,
                       video_dir: Optional[Path] = None, fps: float = 20.0, name: str = "recording",
                       save_every: int = 0, save_dir: Optional[Path] = None) -> Dict[str, List[float]]:
    """Run a network over voxel grids streamed from a real recording, one grid at a time.

    Args:
        model: a reconstruction network (``model(voxel, states) -> (image, states)``), a flow
            network (``model(voxel) -> flow``) or E-RAFT (``task == "eraft"``: pairs of
            consecutive grids, the first paired with a zero grid).
        task: the trainer task name of ``model``.
        grids: iterable of ``(k, voxel int32 (B, H, W), counts)`` (``trainer.event_grids.voxel_grids``).
        frames: uint8 (K+1, H, W) ground truth, frame k+1 ending grid k (reconstruction only),
            or None: nothing scored.
        ssim_data_range, lpips_model, skip_first: as :func:`evaluate_e2vid`.
        video_dir: where to write ``<name>_NNNNN.png`` reconstructions and ``<name>.mp4`` (or
            ``<name>_flow.mp4``, the flow colour-coded by ``trainer.viz.flow_to_bgr``), or None.
        fps: frame rate of the MP4.
        save_every, save_dir: with frames, every ``save_every``-th grid as ``<name>_cmp_NNNNN.png``
            in ``save_dir``: the voxel grid, the reconstruction and the frame side by side.

    Returns:
        Per-frame lists as :func:`evaluate_e2vid` (empty without frames or for flow), plus
        ``_grids``, the number of grids run.
    """
    from .viz import Mp4Writer, flow_to_bgr

    recon = task not in ("evflow", "eraft")
    res: Dict[str, List[float]] = {k: [] for k in ("mse", "ssim", "base_mse", "base_ssim")}
    if lpips_model is not None and frames is not None:
        res["lpips"], res["base_lpips"] = [], []
    if frames is not None:
        gt_all = frames.astype(np.float32) / 255.0
        mean_img = np.full(gt_all.shape[1:], gt_all[1:].mean(), np.float32)
    writer = None
    if video_dir is not None:
        video_dir.mkdir(parents=True, exist_ok=True)
        writer = Mp4Writer(video_dir / (f"{name}.mp4" if recon else f"{name}_flow.mp4"), fps)
    if task == "eraft":
        model.reset_states()
    states, prev, n = None, None, 0
    try:
        for k, vox, _ in grids:
            v = torch.from_numpy(vox.astype(np.float32))[None].to(device)
            n += 1
            if not recon:
                flow = (model(prev if prev is not None else torch.zeros_like(v), v) if task == "eraft" else model(v))
                prev = v
                if writer is not None:
                    writer.write(flow_to_bgr(flow[0].float().cpu().numpy()))
                continue
            pred, states = model(v, states)
            p = pred[0, 0].float().cpu().numpy()
            if writer is not None:
                img = (np.clip(p, 0, 1) * 255 + 0.5).astype(np.uint8)
                import cv2

                cv2.imwrite(str(video_dir / f"{name}_{k:05d}.png"), img)
                writer.write(img)
            if frames is None or k < skip_first or k + 1 >= len(frames):
                continue
            gt = gt_all[k + 1]
            if save_every and save_dir is not None and k % save_every == 0:
                from .viz import gray_to_u8, save_grid, voxel_to_u8

                save_grid(str(save_dir / f"{name}_cmp_{k:05d}.png"), [[voxel_to_u8(vox), gray_to_u8(p), gray_to_u8(gt)]])
            _score(res, p, gt, mean_img, ssim_data_range, lpips_model if "lpips" in res else None, device)
    except BaseException:
        if writer is not None:
            writer.abort()
        raise
    if writer is not None:
        writer.close()
    res["_grids"] = n
    return res

"""Training losses of the V2V paper (Lou et al., NeurIPS 2025; losses of event_cnn_minimal).

* E2VID ("V+L1+H"): L1 + LPIPS (VGG) on every reconstruction, plus the temporal
  consistency loss of Lai et al. (ECCV 2018) in the V2V reference's form (relative error
  ``|P_t - W(P_{t-1})| / (|P_t| + |W(P_{t-1})| + 1e-5)`` weighted by the visibility
  ``exp(-alpha * |I_t - W(I_{t-1})|^2)``, alpha = 50), counted from the middle of each
  sequence and averaged over all of its steps (the first half contributes zero). Without
  LPIPS weights, ``1 - SSIM`` replaces the LPIPS term (logged once).
* EvFlow: dense L1 between predicted and the stream's optical flow (pixels).
"""
from __future__ import annotations

import logging
from typing import Tuple

import torch
import torch.nn as nn
import torch.nn.functional as F

from .models.lpips import STAND_IN, load_lpips

__all__ = ["ssim", "warp", "temporal_consistency_loss", "flow_l1_loss", "ReconstructionLoss"]

log = logging.getLogger(__name__)


def ssim(x: torch.Tensor, y: torch.Tensor, data_range: float = 1.0, win_size: int = 7) -> torch.Tensor:
    """Mean SSIM per image, identical in definition to scikit-image's
    ``structural_similarity(x, y, win_size=7, data_range=...)`` (uniform window, sample
    covariance, K1 = 0.01, K2 = 0.03, mean over the valid interior).

    Args:
        x, y: float (N, C, H, W), H and W >= win_size; channels are averaged.
        data_range: dynamic range R of the images (1.0 for [0, 1] images).
        win_size: odd side of the uniform window, pixels.

    Returns:
        float (N,). Raises ``ValueError`` for mismatched or too small inputs.
    """
    if x.shape != y.shape or x.ndim != 4:
        raise ValueError(f"expected equal (N, C, H, W) tensors, got {tuple(x.shape)}, {tuple(y.shape)}")
    if min(x.shape[-2:]) < win_size or win_size % 2 == 0:
        raise ValueError(f"win_size must be odd and <= H, W; got {win_size} for {tuple(x.shape)}")
    x, y = x.float(), y.float()
    np_ = win_size * win_size
    cov_norm = np_ / (np_ - 1.0)
    pool = lambda t: F.avg_pool2d(t, win_size, stride=1)  # noqa: E731
    ux, uy = pool(x), pool(y)
    uxx, uyy, uxy = pool(x * x), pool(y * y), pool(x * y)
    vx = cov_norm * (uxx - ux * ux)
    vy = cov_norm * (uyy - uy * uy)
    vxy = cov_norm * (uxy - ux * uy)
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    s = ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux * ux + uy * uy + c1) * (vx + vy + c2))
    return s.mean(dim=(1, 2, 3))


def warp(img: torch.Tensor, flow: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Backward-warp ``img`` by ``flow``: ``out(x) = img(x + flow(x))`` (bilinear).

    Args:
        img: float (N, C, H, W).
        flow: float (N, 2, H, W), pixels; channel 0 = x (columns), 1 = y (rows).

    Returns:
        ``(warped (N, C, H, W), valid (N, 1, H, W) float)``, where ``valid`` is 1 where
        the sample point lies inside the image (0 outside, where ``warped`` is 0).
    """
    n, _, h, w = img.shape
    if flow.shape != (n, 2, h, w):
        raise ValueError(f"flow must be {(n, 2, h, w)}, got {tuple(flow.shape)}")
    ys, xs = torch.meshgrid(
        torch.arange(h, device=img.device, dtype=flow.dtype),
        torch.arange(w, device=img.device, dtype=flow.dtype), indexing="ij")
    px = xs + flow[:, 0]
    py = ys + flow[:, 1]
    gx = 2.0 * px / max(w - 1, 1) - 1.0
    gy = 2.0 * py / max(h - 1, 1) - 1.0
    grid = torch.stack([gx, gy], dim=-1)
    out = F.grid_sample(img, grid.to(img.dtype), mode="bilinear", padding_mode="zeros", align_corners=True)
    valid = ((px >= 0) & (px <= w - 1) & (py >= 0) & (py <= h - 1)).unsqueeze(1).to(img.dtype)
    return out, valid


def temporal_consistency_loss(frame0: torch.Tensor, frame1: torch.Tensor, pred0: torch.Tensor,
                              pred1: torch.Tensor, flow01: torch.Tensor, alpha: float = 50.0) -> torch.Tensor:
    """Short-term temporal consistency loss of one step (Lai et al. ECCV 2018, Eq. 2; E2VID
    training), averaged over pixels, in the V2V reference code's form (``utils/loss.py``
    ``temporal_consistency_loss``, called by ``model/loss.py`` with the negated forward flow):
    the previous frame and the previous reconstruction (clamped to [0, 255]) are warped onto
    frame t's grid with ``-flow01``, ``W(X)(x) = X(x - F(x))`` (bilinear, zeros outside), and

        ``M = exp(-alpha * (I_1 - W(I_0))^2)``,
        ``loss = mean(M * |P_1 - W(P_0)| / (|P_1| + |W(P_0)| + 1e-5))``

    over all pixels (no in-image mask).

    Args:
        frame0, frame1: float (N, 1, H, W) ground-truth frames at t-1 and t, in [0, 1].
        pred0, pred1: float (N, 1, H, W) reconstructions at t-1 and t.
        flow01: float (N, 2, H, W), the stream's *forward* flow from frame t-1 to t in
            pixels (defined on frame t-1's pixel grid; channel 0 = x, 1 = y).
        alpha: visibility sharpness (50 in the paper and the reference).

    Returns:
        Scalar float tensor.
    """
    w_frame, _ = warp(frame0, -flow01)
    w_pred, _ = warp(torch.clamp(pred0, 0, 255), -flow01)
    vis = torch.exp(-alpha * (frame1 - w_frame) ** 2)
    return (vis * (pred1 - w_pred).abs() / (pred1.abs() + w_pred.abs() + 1e-5)).mean()


def flow_l1_loss(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Dense L1 between flows (N, 2, H, W), pixels; mean over all pixels and both
    components (the EvFlow training loss)."""
    if pred.shape != gt.shape:
        raise ValueError(f"flow shapes differ: {tuple(pred.shape)} vs {tuple(gt.shape)}")
    return (pred.float() - gt.float()).abs().mean()


class ReconstructionLoss(nn.Module):
    """Per-timestep E2VID loss: ``l1_weight * L1 + perceptual_weight * P`` where P is
    LPIPS (VGG) when weights are available, else ``1 - SSIM`` (win 7, data_range 1).

    Args:
        l1_weight, perceptual_weight: term weights.
        lpips_net: backbone, ``'vgg'`` in the paper.
        lpips_weights: local weight file(s), see :func:`trainer.models.lpips.load_lpips`.
        use_lpips_package: allow ``import lpips`` when no path is given.

    Attributes:
        perceptual: ``'lpips'`` or ``'ssim'``, the term actually used.
        term: what results record as the perceptual term: ``'lpips-vgg'`` / ``'lpips-alex'``,
            ``trainer.models.lpips.STAND_IN`` (1 - SSIM, no LPIPS weights), or None (weight 0).

    ``forward(pred, target)``: float (N, 1, H, W) each, target in [0, 1] -> dict of scalar
    tensors ``{'l1', 'lpips'|'ssim', 'total'}``.
    """

    _warned = False

    def __init__(self, l1_weight: float = 1.0, perceptual_weight: float = 1.0, lpips_net: str = "vgg",
                 lpips_weights=None, use_lpips_package: bool = True):
        super().__init__()
        self.l1_weight = float(l1_weight)
        self.perceptual_weight = float(perceptual_weight)
        self.lpips = load_lpips(lpips_net, lpips_weights, use_package=use_lpips_package) if perceptual_weight else None
        self.perceptual = "lpips" if self.lpips is not None else "ssim"
        self.term = None if not perceptual_weight else (f"lpips-{lpips_net}" if self.lpips is not None else STAND_IN)
        if self.lpips is None and perceptual_weight and not ReconstructionLoss._warned:
            log.warning("LPIPS weights not found (no lpips_weights path in the config and no usable "
                        "`lpips` package): using 1 - SSIM (win 7) in place of the LPIPS term.")
            ReconstructionLoss._warned = True

    def forward(self, pred: torch.Tensor, target: torch.Tensor) -> dict:
        pred = pred.float()
        target = target.float()
        out = {"l1": (pred - target).abs().mean()}
        total = self.l1_weight * out["l1"]
        if self.perceptual_weight:
            if self.lpips is not None:
                out["lpips"] = self.lpips(pred, target).mean()
            else:
                out["ssim"] = 1.0 - ssim(pred, target).mean()
            total = total + self.perceptual_weight * out[self.perceptual]
        out["total"] = total
        return out

"""Preview PNG of one sample: voxel bins, frames and optical flow side by side (OpenCV only)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import cv2
import numpy as np


def voxel_to_bgr(bin_counts: np.ndarray, scale: float) -> np.ndarray:
    """(H, W) signed event counts -> uint8 BGR (H, W, 3): white = 0, red = positive polarity,
    blue = negative polarity, saturating at ``scale`` events."""
    v = np.clip(bin_counts / max(scale, 1e-6), -1.0, 1.0)
    img = np.full(v.shape + (3,), 255.0, np.float32)
    pos, neg = np.maximum(v, 0), np.maximum(-v, 0)
    img[..., 0] -= 255 * pos  # less blue
    img[..., 1] -= 255 * (pos + neg)
    img[..., 2] -= 255 * neg  # less red
    return np.clip(img, 0, 255).astype(np.uint8)


def flow_to_bgr(flow: np.ndarray, max_mag: Optional[float] = None) -> np.ndarray:
    """(2, H, W) flow in pixels -> uint8 BGR: hue = direction, brightness = magnitude."""
    u, v = flow[0].astype(np.float32), flow[1].astype(np.float32)
    mag, ang = cv2.cartToPolar(u, v, angleInDegrees=True)
    m = max_mag or max(float(np.percentile(mag, 99)), 1e-3)
    hsv = np.zeros(u.shape + (3,), np.uint8)
    hsv[..., 0] = (ang / 2).astype(np.uint8)
    hsv[..., 1] = 255
    hsv[..., 2] = np.clip(mag / m * 255, 0, 255).astype(np.uint8)
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)


def render_sample(voxels=None, frames=None, flow=None, title: str = "", rows: int = 4) -> np.ndarray:
    """Compose a BGR uint8 image of one sample.

    Args:
        voxels: (L, B, H, W) event counts; frames: (L + 1, H, W) in [0, 1] or uint8;
        flow: (L, 2, H, W) pixels. Any may be None. ``rows`` voxel indices spread over L.
    """
    ref = next(a for a in (voxels, frames, flow) if a is not None)
    L = ref.shape[0] - (1 if ref is frames else 0)
    h, w = ref.shape[-2:]
    idx = np.unique(np.linspace(0, L - 1, num=min(rows, L)).round().astype(int))
    scale = float(np.percentile(np.abs(voxels), 99.5)) if voxels is not None else 1.0
    mag = None
    if flow is not None:
        m = np.hypot(flow[:, 0].astype(np.float32), flow[:, 1].astype(np.float32))
        mag = max(float(np.percentile(m, 99)), 1e-3)

    def gray(f):
        f = np.asarray(f, np.float32)
        f = f * 255 if f.max() <= 1.0 else f
        return cv2.cvtColor(np.clip(f, 0, 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)

    out_rows = []
    for l in idx:
        tiles, labels = [], []
        if frames is not None:
            tiles.append(gray(frames[l])); labels.append(f"frame {l}")
        if voxels is not None:
            for b in range(voxels.shape[1]):
                tiles.append(voxel_to_bgr(np.asarray(voxels[l, b], np.float32), scale)); labels.append(f"v{l} bin {b}")
        if frames is not None:
            tiles.append(gray(frames[l + 1])); labels.append(f"frame {l + 1}")
        if flow is not None:
            tiles.append(flow_to_bgr(np.asarray(flow[l]), mag)); labels.append(f"flow {l}->{l + 1}")
        for t, lab in zip(tiles, labels):
            cv2.putText(t, lab, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 160, 0), 1, cv2.LINE_AA)
        out_rows.append(np.concatenate(tiles, axis=1))
    grid = np.concatenate(out_rows, axis=0)
    head = np.full((40, grid.shape[1], 3), 255, np.uint8)
    cv2.putText(head, title[:160], (4, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(head, f"red = positive, blue = negative polarity (saturates at {scale:.0f} events); flow hue = "
                f"direction, brightness = magnitude (max {mag or 0:.1f} px)", (4, 32), cv2.FONT_HERSHEY_SIMPLEX,
                0.35, (60, 60, 60), 1, cv2.LINE_AA)
    return np.concatenate([head, grid], axis=0)


def write_preview(batch: dict, path: str, index: int = 0) -> Path:
    """Write a PNG of sample ``index`` of a dataset's batch; returns the path.

    Raises:
        OSError: when the PNG cannot be written.
    """
    def get(name):
        t = batch.get(name)
        return None if t is None else t[index].numpy()

    frames = get("frames")
    if frames is not None:
        frames = frames[:, 0]
    p = batch["params"][index]
    title = (f"{batch['sample_ids'][index]}  c+={p['pos_threshold']:.3f} c-={p['neg_threshold']:.3f} "
             f"sigma={p['noise_std']:.3f} hot={p['hot_pixel_count']} pauses={p['pauses']} flip={p['flip']}")
    img = render_sample(get("voxels"), frames, get("flow"), title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), img):
        raise OSError(f"could not write {path}")
    return path

"""Clips with known optical flow, rendered from still textures: the scenes that tests and
``bench.flow`` / ``bench.flow_objects`` measure flow on.

* ``motion_matrices`` + ``render``: one global similarity motion (translation, rotation or zoom
  of ``d`` px per voxel at the crop's median radius) and its exact ground-truth flow;
* ``render_object``: an object translating over a background that translates otherwise
  (independent motion), with the object's coverage;
* ``epe``: end-point error against ground truth, on the pixels that stay observable.
"""
from __future__ import annotations

import os
from typing import List, Tuple

import cv2
import numpy as np

KINDS = ("translation", "rotation", "zoom")
#: further motions for a closer look (``--kinds``): zoom with its sign fixed (``zoom`` draws
#: in or out per texture)
EXTRA_KINDS = ("zoom-in", "zoom-out")
SIZE = 128


def textures(quick: bool = False) -> List[Tuple[str, np.ndarray]]:
    """Grey uint8 textures: the motion-clip photographs and the middle frame of each bundled clip."""
    from harness.motion_clips import source_images

    out = list(source_images())
    if quick:
        out = out[:4]
    here = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "v2v_server", "sample_videos")
    from v2v_server.frames.decode import decode_luma, open_video

    for name in sorted(os.listdir(here)):
        if not name.endswith(".mp4"):
            continue
        c, s, info = open_video(os.path.join(here, name), 1)
        try:
            for i, luma in enumerate(decode_luma(c, s, info.height)):
                if i == 100:
                    out.append((name, np.ascontiguousarray(luma)))
                    break
        finally:
            c.close()
    return out


def _median_radius() -> float:
    ys, xs = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    c = (SIZE - 1) / 2
    return float(np.median(np.hypot(xs - c, ys - c)))


def motion_matrices(image_shape, kind: str, d: float, step: int, voxels: int, direction: float) -> List[np.ndarray]:
    """Affine 2x3 matrices (image -> view) of each frame for a motion of ``d`` px per voxel."""
    ih, iw = image_shape
    m = _median_radius()
    per = 1.0 / step
    v = np.zeros(2)
    th = 0.0
    lz = 0.0
    if kind == "translation":
        v = d * per * np.array([np.cos(direction), np.sin(direction)])
    elif kind == "rotation":
        th = 2 * np.arcsin(min(d / (2 * m), 1.0)) * per * np.sign(np.cos(direction) or 1)
    elif kind in ("zoom", "zoom-in", "zoom-out"):
        sign = {"zoom-in": 1, "zoom-out": -1}.get(kind, 1 if np.cos(direction) >= 0 else -1)
        lz = np.log1p(d / m) * per * sign
        if lz < 0:  # zoom out by the same displacement at the median radius
            lz = np.log1p(-min(d / m, 0.9)) * per
    else:
        raise ValueError(kind)
    # the crop shows about half of the texture's shorter side, so zoom and pan stay on content
    s0 = SIZE / (0.5 * min(ih, iw))
    p0 = np.array([iw / 2, ih / 2])
    cv = np.array([(SIZE - 1) / 2, (SIZE - 1) / 2])
    out = []
    for t in range(step * voxels + 1):
        a, s = th * t, s0 * np.exp(lz * t)
        r = s * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        mat = np.zeros((2, 3))
        mat[:, :2] = r
        mat[:, 2] = cv + v * t - r @ p0
        out.append(mat)
    return out


def render(image: np.ndarray, mats: List[np.ndarray], step: int):
    """Frames uint8 (N, S, S) and ground-truth flows float32 (L, S, S, 2) between boundaries."""
    frames = np.stack([cv2.warpAffine(image, m, (SIZE, SIZE), flags=cv2.INTER_LINEAR,
                                      borderMode=cv2.BORDER_REFLECT101) for m in mats])
    ys, xs = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    pts = np.stack([xs, ys, np.ones_like(xs)], -1)
    gts = []
    for l in range((len(mats) - 1) // step):
        a = np.vstack([mats[l * step], [0, 0, 1]])
        b = np.vstack([mats[(l + 1) * step], [0, 0, 1]])
        xb = pts @ (b @ np.linalg.inv(a))[:2].T
        gts.append((xb - pts[..., :2]).astype(np.float32))
    return frames, np.stack(gts)


def epe(flow_l2hw: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """EPE in pixels of one flow (2, S, S) against ground truth (S, S, 2), observable pixels only."""
    ys, xs = np.mgrid[0:SIZE, 0:SIZE].astype(np.float32)
    dx, dy = xs + gt[..., 0], ys + gt[..., 1]
    ok = (dx >= 0) & (dx <= SIZE - 1) & (dy >= 0) & (dy <= SIZE - 1)
    return np.hypot(flow_l2hw[0] - gt[..., 0], flow_l2hw[1] - gt[..., 1])[ok]


def square(img: np.ndarray, size: int) -> np.ndarray:
    h, w = img.shape
    s = min(h, w)
    y, x = (h - s) // 2, (w - s) // 2
    return cv2.resize(img[y:y + s, x:x + s], (size, size), interpolation=cv2.INTER_AREA)


def render_object(bg: np.ndarray, obj: np.ndarray, v_bg, v_obj, frames: int = 11):
    """Frames uint8 (T, SIZE, SIZE) and the object's coverage (T, SIZE, SIZE) bool: the
    background translates by ``v_bg`` px per frame, the object by ``v_obj``; the object passes
    the crop centre at the middle frame."""
    big = square(bg, 400)
    n = obj.shape[0]
    start = np.array([SIZE / 2 - n / 2, SIZE / 2 - n / 2]) - (frames - 1) / 2 * np.asarray(v_obj)
    out, cover = [], []
    ones = np.ones_like(obj, np.float32)
    for t in range(frames):
        m_bg = np.float32([[1, 0, -136 + t * v_bg[0]], [0, 1, -136 + t * v_bg[1]]])
        f = cv2.warpAffine(big, m_bg, (SIZE, SIZE), flags=cv2.INTER_LINEAR).astype(np.float32)
        p = start + t * np.asarray(v_obj)
        m_obj = np.float32([[1, 0, p[0]], [0, 1, p[1]]])
        o = cv2.warpAffine(obj, m_obj, (SIZE, SIZE), flags=cv2.INTER_LINEAR, borderValue=0).astype(np.float32)
        a = cv2.warpAffine(ones, m_obj, (SIZE, SIZE), flags=cv2.INTER_LINEAR, borderValue=0)
        out.append(np.clip(np.rint(f * (1 - a) + o * a), 0, 255).astype(np.uint8))
        cover.append(a > 0.99)
    return np.stack(out), np.stack(cover)

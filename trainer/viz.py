"""Images for logs: voxel grids, reconstructions and optical flow as uint8 pictures, and an
MP4 writer for a sequence of them."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

__all__ = ["voxel_to_u8", "gray_to_u8", "flow_to_bgr", "grid_image", "write_png", "save_grid", "Mp4Writer"]


def voxel_to_u8(voxel: np.ndarray) -> np.ndarray:
    """(num_bins, H, W) signed counts -> (H, W, 3) uint8: the sum over bins, grey 128 = 0,
    scaled by the 99th percentile of |sum| (white = positive, black = negative)."""
    s = np.asarray(voxel, dtype=np.float32).sum(0)
    m = max(float(np.percentile(np.abs(s), 99)), 1e-6)
    g = np.clip(128 + 127 * s / m, 0, 255).astype(np.uint8)
    return cv2.cvtColor(g, cv2.COLOR_GRAY2BGR)


def gray_to_u8(img: np.ndarray) -> np.ndarray:
    """(H, W) or (1, H, W) intensities in [0, 1] (clipped) -> (H, W, 3) uint8."""
    g = np.asarray(img, dtype=np.float32).reshape(np.shape(img)[-2:])
    g = (np.clip(g, 0, 1) * 255 + 0.5).astype(np.uint8)
    return cv2.cvtColor(g, cv2.COLOR_GRAY2BGR)


def flow_to_bgr(flow: np.ndarray, max_mag: float = None) -> np.ndarray:
    """(2, H, W) flow in pixels -> (H, W, 3) uint8 BGR (hue = direction, value = magnitude
    relative to ``max_mag``, default the 99th percentile of the magnitude)."""
    u, v = np.asarray(flow[0], np.float32), np.asarray(flow[1], np.float32)
    mag, ang = cv2.cartToPolar(u, v)
    if max_mag is None:
        max_mag = max(float(np.percentile(mag, 99)), 1e-6)
    hsv = np.zeros(u.shape + (3,), np.uint8)
    hsv[..., 0] = (ang * 90 / np.pi).astype(np.uint8)
    hsv[..., 1] = 255
    hsv[..., 2] = np.clip(255 * mag / max_mag, 0, 255).astype(np.uint8)
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)


def grid_image(rows: Sequence[Sequence[np.ndarray]], pad: int = 2) -> np.ndarray:
    """Rows of equal-size (H, W, 3) uint8 tiles as one (H', W', 3) uint8 image, ``pad`` white
    pixels apart."""
    h, w = rows[0][0].shape[:2]
    ncol = max(len(r) for r in rows)
    canvas = np.full((len(rows) * (h + pad) + pad, ncol * (w + pad) + pad, 3), 255, np.uint8)
    for i, r in enumerate(rows):
        for j, tile in enumerate(r):
            y, x = pad + i * (h + pad), pad + j * (w + pad)
            canvas[y:y + h, x:x + w] = tile
    return canvas


def write_png(path: str, img: np.ndarray) -> None:
    """Write an (H, W, 3) uint8 BGR image as a PNG. Raises ``OSError`` when it cannot be written."""
    if not cv2.imwrite(str(path), img):
        raise OSError(f"could not write {path}")


def save_grid(path: str, rows: Sequence[Sequence[np.ndarray]], pad: int = 2) -> None:
    """Write rows of equal-size (H, W, 3) uint8 tiles as one PNG, ``pad`` white pixels apart."""
    write_png(path, grid_image(rows, pad))


class Mp4Writer:
    """Encode (H, W) uint8 grey or (H, W, 3) uint8 BGR frames as an H.264 MP4 with PyAV, one at a
    time (odd sizes are padded by one pixel: yuv420p needs even ones). The file is written
    beside ``path`` under a temporary name and renamed to it by :meth:`close`: an interrupted
    run (:meth:`abort`) leaves no partial MP4."""

    def __init__(self, path: Path, fps: float):
        import av

        self.path, self.fps = Path(path), fps
        self._tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.part")
        self._av, self._c, self._s = av, None, None

    def write(self, img: np.ndarray) -> None:
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        h, w = img.shape[:2]
        img = np.pad(img, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
        if self._c is None:
            from fractions import Fraction

            self._c = self._av.open(str(self._tmp), "w", format="mp4")
            self._s = self._c.add_stream("libx264", rate=Fraction(self.fps).limit_denominator(1000))
            self._s.width, self._s.height, self._s.pix_fmt = img.shape[1], img.shape[0], "yuv420p"
            self._s.options = {"crf": "18", "preset": "fast"}
        vf = self._av.VideoFrame.from_ndarray(np.ascontiguousarray(img), format="bgr24").reformat(format="yuv420p")
        for pkt in self._s.encode(vf):
            self._c.mux(pkt)

    def close(self) -> None:
        """Finish the MP4 and give it its name."""
        if self._c is not None:
            for pkt in self._s.encode():
                self._c.mux(pkt)
            self._c.close()
            self._c = None
            os.replace(self._tmp, self.path)

    def abort(self) -> None:
        """Drop what was written (an interrupted or failed run)."""
        if self._c is not None:
            try:
                self._c.close()
            except Exception:  # noqa: BLE001 - the partial file goes anyway
                pass
            self._c = None
        self._tmp.unlink(missing_ok=True)

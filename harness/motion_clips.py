"""Camera-motion clips over still photographs, for training-data variety in demos.

The bundled corpus holds one real street source (``bikes.mp4`` and its forward-backward
copy ``webvid_like_596x336.mp4``) besides the held-out ``bigbuckbunny.mp4``: too little for a
reconstruction network to learn what scenes look like where no events fire. E2VID's own
training data was of this kind (Rebecq et al., TPAMI 2019: MS-COCO images moved by random
camera motions in ESIM); this tool renders such clips as ordinary videos so that they go
through ``v2v-serve`` like any other file.

Each clip moves a virtual camera over one photograph with a smooth random similarity
transform (translation, rotation, zoom; every component a sum of two sinusoids with random
period and phase), renders grey frames with ``cv2.warpAffine`` (bilinear, reflected border)
and encodes them as H.264 with PyAV.

Sources: the natural photographs that scikit-image ships in its wheel (``skimage.data``,
public-domain or CC0 images, see ``skimage/data/README.txt``) and matplotlib's
``grace_hopper.jpg`` sample. Nothing is downloaded.

    python -m harness.motion_clips --out DIR [--frames 250] [--size 272 480] [--seed 0]
"""
from __future__ import annotations

import argparse
import os
from typing import List, Tuple

import cv2
import numpy as np

#: skimage.data images that are photographs (the rest are binary, synthetic or tiny)
SKIMAGE_PHOTOS = ("astronaut", "camera", "chelsea", "coffee", "coins", "rocket", "grass", "gravel", "brick", "moon", "immunohistochemistry", "hubble_deep_field", "page")


def source_images() -> List[Tuple[str, np.ndarray]]:
    """The still photographs clips are made from: ``[(name, uint8 (H, W) grey image)]``.

    Raises ``RuntimeError`` if none can be loaded (scikit-image missing)."""
    out = []
    try:
        import skimage.data as skd
    except ImportError as e:  # pragma: no cover - the trainer extra installs it
        raise RuntimeError("harness.motion_clips needs scikit-image (pip install -e '.[trainer]')") from e
    for name in SKIMAGE_PHOTOS:
        try:
            img = np.asarray(getattr(skd, name)())
        except Exception:  # an image the installed version does not ship
            continue
        out.append((name, _to_grey(img)))
    try:
        import matplotlib.cbook as cbook

        with cbook.get_sample_data("grace_hopper.jpg") as f:
            buf = np.frombuffer(f.read(), np.uint8)
        out.append(("grace_hopper", cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)))
    except Exception:
        pass
    if not out:
        raise RuntimeError("no source photographs could be loaded from skimage.data or matplotlib")
    return out


def _to_grey(img: np.ndarray) -> np.ndarray:
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3].astype(np.uint8), cv2.COLOR_RGB2GRAY)
    if img.dtype != np.uint8:
        img = img.astype(np.float64)
        img = (255 * (img - img.min()) / max(img.max() - img.min(), 1e-12)).astype(np.uint8)
    return img


def camera_path(frames: int, rng: np.random.Generator, max_speed_px: float = 3.0,
                max_rot_deg: float = 8.0, max_zoom: float = 0.15) -> np.ndarray:
    """A smooth random camera path: ``float64 (frames, 4)`` of (dx px, dy px, rotation deg,
    log zoom) per frame. Each component is a sum of two sinusoids of random period (40-400
    frames) and phase; each translation component moves at most pi/3 * ``max_speed_px``
    (about 1.05 x) per frame."""
    t = np.arange(frames, dtype=np.float64)
    out = np.zeros((frames, 4))
    amp = [max_speed_px * frames / 6, max_speed_px * frames / 6, max_rot_deg, max_zoom]
    for k in range(4):
        for _ in range(2):
            period = rng.uniform(40, 400)
            a = rng.uniform(-1, 1) * amp[k] * min(1.0, period / frames) / 2
            out[:, k] += a * np.sin(2 * np.pi * t / period + rng.uniform(0, 2 * np.pi))
        out[:, k] -= out[0, k]
    return out


def render_clip(image: np.ndarray, size: Tuple[int, int], frames: int, rng: np.random.Generator) -> np.ndarray:
    """Frames of a camera moving over ``image``: ``uint8 (frames, H, W)``, ``size = (H, W)``.

    The photograph is scaled so the view covers at most 80 % of its shorter side, so the
    camera mostly looks at real content (the border is reflected where it does not)."""
    h, w = size
    ih, iw = image.shape
    base = max(h / (0.8 * ih), w / (0.8 * iw))
    path = camera_path(frames, rng)
    out = np.empty((frames, h, w), np.uint8)
    cx, cy = iw / 2, ih / 2
    for i, (dx, dy, rot, lz) in enumerate(path):
        s = base * float(np.exp(lz))
        m = cv2.getRotationMatrix2D((cx + dx / s, cy + dy / s), float(rot), s)
        # move the (shifted) image centre to the view centre
        m[0, 2] += w / 2 - (cx + dx / s)
        m[1, 2] += h / 2 - (cy + dy / s)
        out[i] = cv2.warpAffine(image, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT101)
    return out


def write_video(path: str, frames: np.ndarray, fps: int = 25, crf: int = 18) -> None:
    """Encode ``uint8 (T, H, W)`` grey frames as an H.264 (yuv420p) MP4 at ``fps`` with PyAV.
    H and W must be even (yuv420p)."""
    import av

    t, h, w = frames.shape
    if h % 2 or w % 2:
        raise ValueError(f"{path}: frame size {h}x{w} must be even for yuv420p")
    with av.open(path, "w") as c:
        s = c.add_stream("libx264", rate=fps)
        s.width, s.height, s.pix_fmt = w, h, "yuv420p"
        s.options = {"crf": str(crf), "preset": "fast"}
        for f in frames:
            vf = av.VideoFrame.from_ndarray(np.ascontiguousarray(f), format="gray").reformat(format="yuv420p")
            for pkt in s.encode(vf):
                c.mux(pkt)
        for pkt in s.encode():
            c.mux(pkt)


def make_clips(out_dir: str, frames: int = 250, size: Tuple[int, int] = (272, 480), seed: int = 0) -> List[str]:
    """Write one clip per source photograph to ``out_dir`` (``motion_<name>.mp4``); return
    their paths. The same ``seed`` gives the same camera paths."""
    os.makedirs(out_dir, exist_ok=True)
    paths = []
    for i, (name, img) in enumerate(source_images()):
        rng = np.random.default_rng([seed, i])
        p = os.path.join(out_dir, f"motion_{name}.mp4")
        write_video(p, render_clip(img, size, frames, rng))
        paths.append(p)
    return paths


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="folder to write motion_<name>.mp4 clips to")
    ap.add_argument("--frames", type=int, default=250, help="frames per clip (25 fps; default 250)")
    ap.add_argument("--size", type=int, nargs=2, default=(272, 480), metavar=("H", "W"),
                    help="frame size, even numbers (default 272 480)")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    for p in make_clips(a.out, a.frames, tuple(a.size), a.seed):
        print(p)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

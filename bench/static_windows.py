"""Which windows are static: a window's motion (``frames.motion``: the mean change of log intensity
per frame pair, measured on its frames before any simulation) against the signal events it makes
at the paper's most sensitive contrast threshold, and where ``STATIC_MOTION`` falls between
still and moving footage.

``python -m bench.static_windows [--json docs/static_windows.json]`` writes, in a temporary
folder, 640 x 360 H.264 clips (crf 18) from real photographs (``harness.motion_clips.source_images``):

* ``still``: each photograph held still (what is left is the codec's noise);
* ``still + sensor noise``: the same with Gaussian noise of 2 grey levels drawn afresh per frame
  (a still camera's temporal noise);
* ``pan P px/frame``: each photograph moved at a constant P pixels a frame, for P in ``SPEEDS``;

and reads the bundled clips (``v2v_server/sample_videos``) as they are. Every 41-frame window
(``sequence_length`` 8) of each is simulated once at c+ = c- = 0.05 with no noise and no hot
pixels (``ranges``), pauses off, 128 x 128 crops from the whole frame: its motion (the sample's
``stats.motion``) and its signal events per pixel per frame pair (``stats`` rates / fps).
Prints, per material, the windows, their motion and event range, and how many fall below
``STATIC_MOTION``; and what the motion meter costs a frame at 596 x 181 and 1920 x 583 kept rows.
"""
from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path
from typing import Dict, List, Optional

import cv2
import numpy as np

from harness.data import SAMPLE_VIDEOS
from harness.motion_clips import source_images, write_video

#: Constant pan speeds, pixels a frame.
SPEEDS = (0.1, 0.25, 0.5, 1.0, 2.0)
#: Frames of each generated clip: 4 windows of 41 frames.
FRAMES = 161
SIZE = (360, 640)
#: The recipe: 41-frame windows, the most sensitive threshold, no noise, no pauses, whole frames.
OVERRIDES = {"sequence_length": 8, "max_samples_per_video": 4, "keep_top_fraction": 1.0, "pause_enabled": False,
             "ranges": {"threshold": [0.05, 0.05], "ratio": [1.0, 1.0], "noise_std": [0.0, 0.0],
                        "hot_pixel_fraction": [0.0, 0.0]}}


def _frames(img: np.ndarray, speed: float, noise: float, rng: np.random.Generator) -> np.ndarray:
    """``FRAMES`` frames of ``SIZE`` cut from ``img`` (resized to cover it with room to pan),
    moved ``speed`` px a frame, with Gaussian ``noise`` grey levels."""
    h, w = SIZE
    room = int(np.ceil(speed * FRAMES)) + 2
    scale = max((w + room) / img.shape[1], h / img.shape[0])
    big = cv2.resize(img, (int(np.ceil(img.shape[1] * scale)), int(np.ceil(img.shape[0] * scale))),
                     interpolation=cv2.INTER_CUBIC).astype(np.float32)
    out = np.empty((FRAMES, h, w), np.uint8)
    for t in range(FRAMES):
        m = np.float32([[1, 0, -speed * t], [0, 1, 0]])
        f = cv2.warpAffine(big, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        if noise:
            f = f + rng.normal(0, noise, f.shape).astype(np.float32)
        out[t] = np.clip(np.rint(f), 0, 255).astype(np.uint8)
    return out


def write_material(root: Path, photos: int = 4) -> Dict[str, Path]:
    """The generated clips under ``root/<material>/`` and the bundled clips' folder: material -> folder."""
    rng = np.random.default_rng(0)
    kinds = {"still": (0.0, 0.0), "still + sensor noise": (0.0, 2.0)}
    kinds.update({f"pan {s:g} px/frame": (s, 0.0) for s in SPEEDS})
    folders = {}
    for k, (name, (speed, noise)) in enumerate(kinds.items()):
        d = root / f"m{k}"
        d.mkdir(parents=True)
        for pname, img in source_images()[:photos]:
            write_video(str(d / f"{pname}.mp4"), _frames(img, speed, noise, rng))
        folders[name] = d
    folders["bundled clips"] = SAMPLE_VIDEOS
    return folders


def measure(folders: Dict[str, Path]) -> dict:
    """Per material: each window's motion and signal events per pixel per frame pair."""
    from v2v_server.ops.config import load_config
    from v2v_server.samples.make import video_samples
    from v2v_server.sources.local import LocalSource
    from v2v_server.frames.motion import STATIC_MOTION

    cfg = load_config(None, OVERRIDES)
    out = {"static_motion": STATIC_MOTION, "materials": {}}
    for name, folder in folders.items():
        rows = []
        src = LocalSource(folder)
        for rel in sorted(p.name for p in folder.glob("*.mp4")):
            for _key, _arrays, meta in video_samples(cfg.recipe, src, rel, 0, ("voxels",)):
                st = meta["stats"]
                rows.append((st["motion"], (st["rate_pos"] + st["rate_neg"]) / meta["video_fps"]))
        m = np.array([r[0] for r in rows])
        e = np.array([r[1] for r in rows])
        out["materials"][name] = {
            "windows": len(rows), "motion_min_max": [float(m.min()), float(m.max())],
            "events_per_pixel_pair_min_max": [float(e.min()), float(e.max())],
            "static": int((m < STATIC_MOTION).sum()), "rows": rows}
    return out


def meter_cost(sizes=((181, 596), (583, 1920)), frames: int = 400) -> Dict[str, float]:
    """Microseconds ``MotionMeter.score`` takes a frame of each (rows, columns) kept region, best
    of 3 runs over ``frames`` frames alternating between a random frame and it shifted by 1 px."""
    import time

    from v2v_server.frames.decode import full_range
    from v2v_server.frames.motion import MotionMeter

    out = {}
    rng = np.random.default_rng(1)
    for h, w in sizes:
        a = rng.integers(0, 256, (h, w), dtype=np.uint8)
        b = np.roll(a, 1, axis=1)
        m = MotionMeter()
        m.score(a, full_range)
        best = float("inf")
        for _ in range(3):
            t = time.perf_counter()
            for i in range(frames):
                m.score(b if i % 2 else a, full_range)
            best = min(best, (time.perf_counter() - t) / frames)
        out[f"{w}x{h}"] = round(best * 1e6, 1)
    return out


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--photos", type=int, default=4, help="photographs per generated material")
    ap.add_argument("--json", type=Path, default=None, help="write the result here too")
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="v2v-static-"))
    try:
        r = measure(write_material(tmp, args.photos))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    r["meter_us_per_frame"] = meter_cost()
    r["command"] = "python -m bench.static_windows" + "".join(f" {a}" for a in (argv if argv is not None else []))
    print(f"STATIC_MOTION {r['static_motion']} (log intensity per frame pair); the meter, us a frame: "
          f"{r['meter_us_per_frame']}")
    print("| material | windows | motion, min-max | signal events / pixel / frame pair at c = 0.05, min-max | static |")
    print("|---|---:|---|---|---:|")
    for name, m in r["materials"].items():
        print(f"| {name} | {m['windows']} | {m['motion_min_max'][0]:.4f}-{m['motion_min_max'][1]:.4f} | "
              f"{m['events_per_pixel_pair_min_max'][0]:.4f}-{m['events_per_pixel_pair_min_max'][1]:.4f} | "
              f"{m['static']} |")
    if args.json:
        args.json.write_text(json.dumps(r, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

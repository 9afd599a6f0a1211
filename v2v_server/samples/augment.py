"""The paper's data-quality ablations as sample options, both off by default.

* ``degrade_dynamic_range: {probability: 0.8, scale: [1, 3]}`` (paper appendix "Dataset
  quality"; reference ``data/v2v_datasets.py`` ``degrade_video``, ``video_degrade: hdr``,
  ``degrade_ratio: 0.8``): with the given probability per sample, every frame of the window
  becomes ``F' = clip((F - 127.5) * s + 127.5, 0, 255)`` truncated to uint8, s ~ U[scale],
  before V2V, so the voxels, the ground-truth frames and the flow all see the degraded clip.
  uint16 (deeper) sources use the same rule about their mid-level 32767.5, clipped to 65535.
* ``fixed_sensor_params: true`` (the paper's "-F" datasets; reference ``use_fixed_thresholds``
  with ``scripts/generate_random_thresholds.py``): each video keeps one contrast-threshold
  pair (c+, c-) for every window and every epoch, drawn by the usual rule from a generator
  seeded by (seed, video path) only. As in the reference, noise and hot pixels are still drawn
  per sample.

Both draw from their own generators (``aux_rng``), never from the sample's generator, so
switching one on changes what it should and nothing else: the same seed and sample ids give
the same crops, flips, pauses, noise and hot pixels. What was applied goes into the sample's
params: ``dynamic_range_scale`` (1.0 when the coin said no) and ``fixed_sensor_params``.
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import replace
from typing import Optional

import numpy as np

from v2v_server.checks import check_keys
from v2v_server.simulation.simulate import ParamRanges, sample_params

__all__ = ["DEGRADE_DEFAULTS", "parse_degrade", "aux_rng", "degrade_dynamic_range", "video_thresholds",
           "augment_plan", "degrade_window"]

#: The paper's setting, used for keys left out of a ``degrade_dynamic_range`` section.
DEGRADE_DEFAULTS = {"probability": 0.8, "scale": [1.0, 3.0]}
_TAG_DEGRADE, _TAG_FIXED = 0xD16, 0xF1


def parse_degrade(d) -> dict:
    """Validate a ``degrade_dynamic_range`` config value: ``None``/``{}``/``false`` is off
    (returns ``{}``), ``true`` the paper's defaults, a mapping overrides them.

    Returns ``{"probability": float, "scale": [lo, hi]}`` or ``{}``.

    Raises:
        ValueError: naming the key, for unknown keys, a probability outside [0, 1], or a
            scale that is not two finite numbers 0 < lo <= hi.
    """
    if d is None or d is False or d == {}:
        return {}
    if d is True:
        d = {}
    if not isinstance(d, dict):
        raise ValueError(f"degrade_dynamic_range must be a mapping {{probability, scale}} or true/false, got {d!r}")
    check_keys(d, DEGRADE_DEFAULTS, "degrade_dynamic_range")
    out = {**DEGRADE_DEFAULTS, **d}
    p = out["probability"]
    if isinstance(p, bool) or not isinstance(p, (int, float)) or not 0.0 <= p <= 1.0:
        raise ValueError(f"degrade_dynamic_range.probability must be in [0, 1], got {p!r}")
    sc = out["scale"]
    if (not isinstance(sc, (list, tuple)) or len(sc) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in sc)
            or not 0 < sc[0] <= sc[1]):
        raise ValueError(f"degrade_dynamic_range.scale must be [lo, hi] with 0 < lo <= hi, got {sc!r}")
    return {"probability": float(p), "scale": [float(sc[0]), float(sc[1])]}


def aux_rng(seed: int, tag: int, *keys) -> np.random.Generator:
    """A generator for one augmentation, a pure function of (seed, tag, keys); ``keys`` are
    ints or strings (hashed with BLAKE2b). Independent of ``samples.sample_rng``'s stream."""
    words = [int(seed), int(tag)]
    for k in keys:
        if isinstance(k, str):
            k = int.from_bytes(hashlib.blake2b(k.encode("utf-8"), digest_size=8).digest(), "little")
        words.append(int(k))
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(words)))


def degrade_dynamic_range(frames: np.ndarray, scale: float) -> np.ndarray:
    """``clip((F - mid) * scale + mid, 0, full)`` truncated to the input dtype (the
    reference's ``astype(np.uint8)``), mid = 127.5 and full = 255 for uint8, 32767.5 and
    65535 for uint16.

    Args:
        frames: uint8 or uint16 array of any shape (full-range luma).
        scale: contrast factor s (> 1 stretches and saturates: the paper's degradation).

    Returns:
        A new array of the same shape and dtype. Raises ``ValueError`` for other dtypes.
    """
    if frames.dtype == np.uint8:
        mid, top = 127.5, 255.0
    elif frames.dtype == np.uint16:
        mid, top = 32767.5, 65535.0
    else:
        raise ValueError(f"frames must be uint8 or uint16, got {frames.dtype}")
    out = (frames.astype(np.float64) - mid) * float(scale) + mid
    return np.clip(out, 0.0, top).astype(frames.dtype)


def video_thresholds(seed: int, video: str, ranges: ParamRanges) -> tuple:
    """The contrast thresholds (c+, c-) a video keeps under ``fixed_sensor_params``: drawn
    by ``simulate.sample_params``' rule from a generator of (seed, video path) only."""
    p = sample_params(aux_rng(seed, _TAG_FIXED, video), ranges, (1, 1))
    return p.pos_threshold, p.neg_threshold


def augment_plan(recipe, epoch: int, plan):
    """A freshly drawn ``make.WindowPlan`` with the ablations ``recipe`` (a
    ``recipe.SampleRecipe``) asks for: a new plan (``dataclasses.replace``) whose ``params``
    hold the video's fixed c+ / c- (``fixed_sensor_params`` True), and whose
    ``dynamic_range_scale`` is the degradation scale drawn (1.0 when the coin said no). The
    plan itself when both are off."""
    if recipe.fixed_sensor_params:
        video = plan.sample_id.rsplit("#", 1)[0]
        cp, cn = video_thresholds(recipe.seed, video, recipe.ranges)
        plan = replace(plan, params=replace(plan.params, pos_threshold=cp, neg_threshold=cn),
                       fixed_sensor_params=True)
    deg = recipe.degrade_dynamic_range
    if deg:
        rng = aux_rng(recipe.seed, _TAG_DEGRADE, epoch, plan.sample_id)
        apply = rng.random() < deg["probability"]
        s = float(rng.uniform(*deg["scale"]))
        plan = replace(plan, dynamic_range_scale=s if apply else 1.0)
    return plan


def degrade_window(plan, window_frames: np.ndarray) -> np.ndarray:
    """``window_frames`` degraded by the scale ``augment_plan`` drew (the array itself when
    there is none or it is 1.0)."""
    s: Optional[float] = plan.dynamic_range_scale
    if s is None or s == 1.0:
        return window_frames
    return degrade_dynamic_range(window_frames, s)

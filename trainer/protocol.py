"""The V2V paper's evaluation protocol (Lou et al., NeurIPS 2025, appendix): which sequences,
which part of each, the metric conventions, the table layout, and the checkpoint-selection rule.

Sequence cuts, in seconds from the sequence's first image (the authors' conversion scripts,
HYLZ-2019/V2V ``scripts/ijrr_to_h5.py``, ``scripts/mvsec_to_h5.py``, ``scripts/evaid_to_h5.py``;
their test lists ``config/{hqf,ijrr,mvsec,evaid}_test.txt``): IJRR and MVSEC keep the images
with ``start <= t < end``; EVAID 5-second segments keep ``start <= t <= end`` (their script
keeps one image past the first at or after ``end``: ``[begin:end + 1]``); HQF sequences are
used whole. Files are looked up as ``DATA_ROOT/<dataset>/<sequence>.h5`` (full recordings in
the event_cnn_minimal H5 layout: the cut is applied here).

Metrics per reconstructed frame: MSE on [0, 1], SSIM with scikit-image ``win_size=7`` and
``data_range=2`` (the convention of the earlier papers the tables compare with), LPIPS AlexNet
v0.1. A sequence's score is the mean over its frames, a dataset's the mean over its sequences,
and the table's mean row the mean over the datasets evaluated.

Checkpoint selection: the checkpoint with the lowest mean LPIPS over HQF and EVAID (the
authors' ``scripts/select_best_checkpoint.py`` sums the two datasets' validation losses).
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np

__all__ = ["PAPER_CUTS", "HQF_SEQUENCES", "PAPER_DATASETS", "SELECTION_DATASETS", "paper_files", "cut_sequence",
           "evaluate_paper", "paper_markdown", "select_checkpoint"]

log = logging.getLogger("trainer")

#: (start s, end s) per sequence, from the first image of the full recording.
PAPER_CUTS: Dict[str, Dict[str, Tuple[float, float]]] = {
    "ijrr": {"boxes_6dof": (5, 20), "calibration": (5, 20), "dynamic_6dof": (5, 20), "office_zigzag": (5, 12),
             "poster_6dof": (5, 20), "shapes_6dof": (5, 20), "slider_depth": (1, 2.5)},
    "mvsec": {"indoor_flying1": (10, 70), "indoor_flying2": (10, 70), "indoor_flying3": (10, 70),
              "indoor_flying4": (10, 19.8), "outdoor_day1": (0, 60), "outdoor_day2": (100, 160)},
    "evaid": {"ball": (0, 5), "bear": (0, 5), "box": (0, 5), "building": (0, 5), "outdoor": (0, 5),
              "playball": (25, 30), "room1": (0, 5), "sculpture": (0, 5), "toy": (0, 5), "traffic": (0, 5),
              "wall": (0, 5)},
}
#: HQF sequences, evaluated whole.
HQF_SEQUENCES = ("bike_bay_hdr", "boxes", "desk", "desk_fast", "desk_hand_only", "desk_slow", "engineering_posters",
                 "high_texture_plants", "poster_pillar_1", "poster_pillar_2", "reflective_materials",
                 "slow_and_fast_desk", "slow_hand", "still_life")
#: Datasets in the order of the paper's tables.
PAPER_DATASETS = ("ijrr", "mvsec", "hqf", "evaid")
#: The datasets of the checkpoint-selection rule.
SELECTION_DATASETS = ("hqf", "evaid")
_INCLUSIVE_END = {"evaid"}


def paper_files(data_root: str, datasets=PAPER_DATASETS) -> Tuple[List[Tuple[str, str, Path, Optional[tuple]]], List[str]]:
    """The protocol's inputs under ``data_root``: ``(present, missing)`` where present is a list
    of ``(dataset, sequence, path, cut or None)`` and missing the paths not found (named so a
    partial evaluation says what it left out)."""
    present, missing = [], []
    for ds in datasets:
        seqs = {s: None for s in HQF_SEQUENCES} if ds == "hqf" else PAPER_CUTS[ds]
        for name, cut in seqs.items():
            p = Path(data_root) / ds / f"{name}.h5"
            (present.append((ds, name, p, cut)) if p.is_file() else missing.append(str(p)))
    return present, missing


def cut_sequence(seq, start_s: float, end_s: float, inclusive_end: bool = False):
    """Restrict an ``H5Sequence`` in place to the images with ``start_s <= t - t0 < end_s``
    (``<= end_s`` with ``inclusive_end``; t0 = its first image's timestamp, seconds) and the
    events between the first and last kept image. Returns ``seq``. Raises ``ValueError``
    when fewer than two images remain."""
    rel = seq.image_ts - seq.image_ts[0]
    keep = (rel >= start_s) & ((rel <= end_s) if inclusive_end else (rel < end_s))
    idx = np.flatnonzero(keep)
    if idx.size < 2:
        raise ValueError(f"{seq.path}: fewer than two images in the cut [{start_s}, {end_s}] s")
    seq.images, seq.image_ts = seq.images[idx], seq.image_ts[idx]
    ev = (seq.ts >= seq.image_ts[0]) & (seq.ts <= seq.image_ts[-1])
    seq.xs, seq.ys, seq.ts, seq.ps = seq.xs[ev], seq.ys[ev], seq.ts[ev], seq.ps[ev]
    return seq


def evaluate_paper(score_sequence: Callable, data_root: str, datasets=PAPER_DATASETS) -> dict:
    """Evaluate with the protocol. ``score_sequence(path, cut, inclusive_end)`` scores one file
    (``cut`` None for a whole sequence, else (start s, end s) for :func:`cut_sequence`) and
    returns per-frame lists ``mse``, ``ssim`` and, with LPIPS weights, ``lpips``
    (``trainer.evaluate`` builds it around a model). Returns a JSON-safe dict: ``datasets``
    {name: {mse, ssim[, lpips], sequences}}, ``mean`` (over the datasets evaluated),
    ``per_sequence`` {"dataset/sequence": {..., frames}} and ``missing`` (paths not found,
    skipped and logged)."""
    present, missing = paper_files(data_root, datasets)
    for m in missing:
        log.warning("v2v-paper protocol: %s not found, skipped", m)
    per_seq: Dict[str, dict] = {}
    per_ds: Dict[str, List[dict]] = {}
    for ds, name, path, cut in present:
        r = score_sequence(path, cut, ds in _INCLUSIVE_END)
        row = {k: float(np.mean(r[k])) for k in ("mse", "ssim", "lpips") if k in r and len(r[k])}
        row["frames"] = len(r["mse"])
        per_seq[f"{ds}/{name}"] = row
        per_ds.setdefault(ds, []).append(row)
    metrics = [k for k in ("mse", "ssim", "lpips") if per_seq and all(k in r for r in per_seq.values())]
    table = {ds: {**{k: float(np.mean([r[k] for r in rows])) for k in metrics}, "sequences": len(rows)}
             for ds, rows in per_ds.items()}
    mean = {k: float(np.mean([t[k] for t in table.values()])) for k in metrics} if table else {}
    return {"datasets": table, "mean": mean, "per_sequence": per_seq, "missing": missing}


def paper_markdown(result: dict, title: str = "") -> str:
    """The paper's table layout: one row per dataset (in ``PAPER_DATASETS`` order) and a mean
    row, columns MSE, SSIM, LPIPS."""
    cols = [k for k in ("mse", "ssim", "lpips") if k in result["mean"]] or ["mse", "ssim"]
    lines = ([f"**{title}**", ""] if title else []) + [
        "| dataset | sequences | " + " | ".join(c.upper() for c in cols) + " |",
        "|---|---|" + "---|" * len(cols)]
    for ds in PAPER_DATASETS:
        if ds in result["datasets"]:
            t = result["datasets"][ds]
            lines.append(f"| {ds.upper()} | {t['sequences']} | " + " | ".join(f"{t[c]:.3f}" for c in cols) + " |")
    if result["mean"]:
        lines.append("| mean | | " + " | ".join(f"{result['mean'][c]:.3f}" for c in cols) + " |")
    if result["missing"]:
        lines += ["", f"Missing (skipped): {', '.join(result['missing'])}"]
    return "\n".join(lines)


def select_checkpoint(run_dir: str, evaluate_checkpoint: Callable) -> dict:
    """The paper's rule over a run's ``checkpoint_*.pt`` files (``checkpoint_last.pt`` is a copy
    and is left out): ``evaluate_checkpoint(path, SELECTION_DATASETS)`` (an
    :func:`evaluate_paper` result) for each, and the one with the lowest mean of the HQF and
    EVAID LPIPS is chosen. Returns ``{"selected", "scores" {path: mean LPIPS}, "missing"}``.

    Raises:
        ValueError: no checkpoints in ``run_dir``, no HQF/EVAID file found, or no LPIPS scores.
    """
    cks = sorted(p for p in Path(run_dir).glob("checkpoint_*.pt") if p.name != "checkpoint_last.pt")
    if not cks:
        raise ValueError(f"{run_dir}: no checkpoint_*.pt files")
    scores, missing = {}, []
    for ck in cks:
        r = evaluate_checkpoint(ck, SELECTION_DATASETS)
        missing = r["missing"]
        if not r["datasets"]:
            raise ValueError(f"none of the HQF/EVAID files found (e.g. {missing[:2]})")
        if "lpips" not in r["mean"]:
            raise ValueError("checkpoint selection needs LPIPS (AlexNet) weights: give --lpips-weights")
        scores[str(ck)] = r["mean"]["lpips"]
        log.info("%s: mean LPIPS over %s = %.4f", ck.name, list(r["datasets"]), scores[str(ck)])
    return {"selected": min(scores, key=scores.get), "scores": scores, "missing": missing}

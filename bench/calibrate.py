"""``v2v-calibrate`` against the shared real recordings: every statistic before (the default
recipe's ranges) and after (the fitted recipe), and what a fit costs.

``python -m bench.calibrate [--evaluations N] [--epochs E] [--out DIR]`` (from the repository
root) prints markdown tables and writes ``DIR/calibrate.md`` and ``DIR/calibrate.json``.

* **From frames** (the DAVIS346 AEDAT4 file, APS frames at 25 Hz): ``fit_frames`` with seed 0;
  then the recording's frames simulated again with the fitted values and other draws (seed 1),
  against its events between the same frames: events, active fraction of the (frame interval,
  pixel) cells, per-pixel correlation of the signed counts. "default" is the default recipe's
  threshold range centre (1.025) and noise centre (0.05).
* **By statistics** (the DAVIS346 and the Prophesee EVK4 EVT3 file): ``fit_corpus`` over the
  bundled clips' windows as epochs 0 and 1 cut them (48), with the default recipe except ``sequence_length: 8`` (windows of 41
  frames: the clips give 24 windows an epoch where the 201-frame default gives 3; the ranges, bins and
  grid are the default's). Then the stream as a server makes it, ``from_corpus`` (the worker's
  sample path) for ``--epochs`` epochs with the default and with the fitted recipe: each grid
  statistic's median over the voxel grids, against the recording's cells of the same 0.2 s.
* **Cost**: wall seconds of each fit and its simulations, on the machine it ran on.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import List, Optional

import numpy as np
import yaml

from harness.data import DAVIS346, EVT3, SAMPLE_VIDEOS
from trainer.calibrate_fit import (CORPUS_STATS, FRAME_STATS, corpus_windows, fit_corpus, fit_frames, frame_stats,
                                   frame_target, recording_target, simulate_frames)
from trainer.grid_stats import summarise
from trainer.stream_stats import from_corpus
from v2v_server.ops.config import load_config

#: the recipe of the fits by statistics: the default with 41-frame windows (module docstring)
BASE = {"sequence_length": 8}


def frames_row(max_evals: int) -> dict:
    """The fit from frames on the DAVIS346 and its check with other draws."""
    target = frame_target(str(DAVIS346))
    t0 = time.perf_counter()
    res = fit_frames(target, load_config(None).recipe, seed=0, max_evals=max_evals)
    seconds = time.perf_counter() - t0
    other_draws = frame_stats(simulate_frames(target, res.params, seed=1), target)
    return {"recording": DAVIS346.name, "intervals": int(target.real.shape[0]), "target": res.target,
            "default": res.before, "fitted": res.after, "fitted_other_draws": other_draws,
            "params": res.params, "simulations": res.evaluations, "seconds": seconds}


def corpus_row(path: Path, max_evals: int, epochs: int, cfg_path: Path) -> dict:
    """The fit by statistics for the recording at ``path`` and the streams made with the
    default and the fitted recipe."""
    base = load_config(str(cfg_path))
    t0 = time.perf_counter()
    win = corpus_windows(base, str(SAMPLE_VIDEOS), 96, 0)
    r = base.recipe
    cell_s = r.num_bins * r.frames_per_bin / float(np.median(win.fps))
    target = recording_target(str(path), cell_s, r.num_bins)
    res = fit_corpus(win, target, r, max_evals)
    seconds = time.perf_counter() - t0
    fitted_path = cfg_path.with_name(f"fitted_{path.stem}.yaml")
    fitted_path.write_text(yaml.safe_dump({**BASE, "ranges": res.ranges, "nonidealities": res.nonidealities}))

    def served(cfg):
        col = from_corpus(cfg, str(SAMPLE_VIDEOS), 10_000, lambda n: None, epochs)
        s = summarise([c for row in col.rows for c in row["cells"]])
        return {k: s[k].get("median") for k in CORPUS_STATS}, len(col.rows)

    (default, n), (fitted, _) = served(base), served(load_config(str(fitted_path)))
    return {"recording": path.name, "cells": target.cells, "windows": len(win.seqs), "samples": n,
            "target": res.target, "default": default, "fitted": fitted, "fit_default": res.before,
            "fit_fitted": res.after, "params": res.params, "ranges": res.ranges,
            "nonidealities": res.nonidealities, "simulations": res.evaluations, "seconds": seconds}


def _f(v, fmt=".4g") -> str:
    return "n/a" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, fmt)


def tables(res: dict) -> str:
    """Markdown tables of :func:`run`'s result."""
    fr = res["frames"]
    out = [f"### From frames: {fr['recording']} ({fr['intervals']} frame intervals)", "",
           "| statistic | recording | default | fitted | fitted, other draws | fitted / recording |",
           "|---|---:|---:|---:|---:|---:|"]
    for k in FRAME_STATS:
        t, o = fr["target"][k], fr["fitted_other_draws"][k]
        out.append(f"| {k} | {_f(t)} | {_f(fr['default'][k])} | {_f(fr['fitted'][k])} | {_f(o)} | "
                   f"{'' if k == 'corr' else _f(o / t, '.3f')} |")
    out += ["", "fitted: " + ", ".join(f"{k} {v:.4g}" for k, v in fr["params"].items())
            + f"; {fr['simulations']} simulations in {fr['seconds']:.1f} s", ""]
    for row in res["corpus"]:
        out += [f"### By statistics: {row['recording']} ({row['cells']} cells of 0.2 s) against the bundled clips "
                f"({row['windows']} windows; stream: {row['samples']} samples)", "",
                "| statistic (median over cells) | recording | default stream | fitted stream | default / rec | "
                "fitted / rec |", "|---|---:|---:|---:|---:|---:|"]
        for k in CORPUS_STATS:
            t, d, f = row["target"][k], row["default"][k], row["fitted"][k]
            out.append(f"| {k} | {_f(t)} | {_f(d)} | {_f(f)} | {_f(d / t, '.3f')} | {_f(f / t, '.3f')} |")
        out += ["", "fitted: " + ", ".join(f"{k} {v:.4g}" for k, v in row["params"].items())
                + f"; {row['simulations']} simulations in {row['seconds']:.1f} s (windows cut included)", ""]
    return "\n".join(out)


def run(max_evals: int, epochs: int, work: Path) -> dict:
    """Every fit of the module docstring; ``work`` holds the recipes written."""
    work.mkdir(parents=True, exist_ok=True)
    cfg_path = work / "base.yaml"
    cfg_path.write_text(yaml.safe_dump(BASE))
    return {"frames": frames_row(max_evals), "corpus": [corpus_row(p, max_evals, epochs, cfg_path)
                                                         for p in (DAVIS346, EVT3)]}


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.calibrate", description=__doc__.split("\n")[0])
    ap.add_argument("--evaluations", type=int, default=120, help="most simulations per fit")
    ap.add_argument("--epochs", type=int, default=3, help="epochs of the served streams compared")
    ap.add_argument("--out", default="bench/results", help="folder for calibrate.md / .json and the recipes")
    a = ap.parse_args(argv)
    out = Path(a.out)
    res = run(a.evaluations, a.epochs, out / "calibrate_recipes")
    res["command"] = f"python -m bench.calibrate --evaluations {a.evaluations} --epochs {a.epochs}"
    md = tables(res)
    print(md)
    (out / "calibrate.md").write_text(md + "\n")
    (out / "calibrate.json").write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())

"""Where the simulated event rate of the bundled corpus falls against real sensors, and which
contrast threshold would match each: ``python -m bench.event_rate``.

1. The default recipe (the paper's ranges, unchanged) on the bundled clips
   (``v2v_server/sample_videos``), ``--epochs`` epochs (each draws new sensor parameters for the
   same windows): each sample's events per pixel per second (``samples/stats.py``, both
   polarities), per sample and per voxel grid (5 frame intervals: 0.2 s at 25 fps).
2. The same windows at one fixed threshold each (``ranges.threshold: [c, c]``, ``ratio: [1, 1]``,
   every other range the default's) for c in ``THRESHOLDS``: the median rate per grid at each c.
3. The real recordings (``tests/data/events``: DAVIS346, Prophesee Gen3 and EVK4) in windows of
   one voxel grid's duration (``trainer.stream_stats.recording_windows``; one shorter than that,
   over its whole length as one window): median and 10-90 %
   rate; the threshold whose simulated median rate equals the recording's median (log-log
   interpolation of step 2), and the range whose rates span the recording's 10-90 %.

4. A still scene: the first frame of the bundled camera clip, 128 x 128, repeated for one sample
   (201 frames), simulated with ``STILL_DRAWS`` default-recipe draws of the sensor parameters:
   the rate the noise and hot pixels alone make, the floor under which no window's event count
   can tell stillness from motion.

Writes ``docs/event_rate.json`` and ``docs/img/event_rate.png``; docs/fidelity.md reads them. The
scenes differ (a film and street clips against a road, grass and a dark room): a matching
threshold makes the rates alike on this corpus, not the scenes.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import List, Optional

import numpy as np

from harness.data import DAVIS346, EVT2, EVT3, SAMPLE_VIDEOS

ROOT = Path(__file__).resolve().parents[1]
#: The fixed thresholds of step 2 (log intensity): the default range [0.05, 2.0] and beyond it.
THRESHOLDS = (0.05, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0)
#: Default-recipe parameter draws simulated on the still scene (step 4).
STILL_DRAWS = 60
RECORDINGS = {"DAVIS346 (road)": DAVIS346, "Prophesee Gen3 (grass)": EVT2, "Prophesee EVK4 (dark room)": EVT3}


def _samples(overrides: dict, n: int, epochs: int) -> List[dict]:
    from trainer.stream_stats import from_corpus
    from v2v_server.ops.config import load_config

    return from_corpus(load_config(None, overrides), str(SAMPLE_VIDEOS), n, lambda k: None, epochs).rows


def _match(curve_c, curve_rate, rate: float) -> Optional[float]:
    """The threshold at which the (decreasing) simulated rate curve equals ``rate`` (log-log
    interpolation), or None outside the curve."""
    lc, lr = np.log(curve_c), np.log(np.maximum(curve_rate, 1e-9))
    if not (lr.min() <= np.log(rate) <= lr.max()):
        return None
    order = np.argsort(lr)
    return float(np.exp(np.interp(np.log(rate), lr[order], lc[order])))


def still_rates(draws: int = STILL_DRAWS) -> List[float]:
    """Events per pixel per second of a still scene (step 4), one per default-recipe draw."""
    import cv2

    from v2v_server.samples.recipe import SampleRecipe
    from v2v_server.samples.stats import event_stats
    from v2v_server.simulation.simulate import sample_params, simulate_voxels

    cfg = SampleRecipe()
    cap = cv2.VideoCapture(str(SAMPLE_VIDEOS / "bbb_camera_596x336.mp4"))
    ok, bgr = cap.read()
    cap.release()
    s = cfg.crop_size
    frames = np.repeat(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)[None, :s, :s], cfg.frames_per_sample, axis=0)
    out = []
    for i in range(draws):
        rng = np.random.default_rng(i)
        vox, _ = simulate_voxels(frames, sample_params(rng, cfg.ranges, (s, s)), cfg.frames_per_sample - 1, rng=rng)
        st = event_stats(vox.reshape(cfg.sequence_length, cfg.num_bins, s, s), None, None, 25.0, cfg.num_bins, 1, True)
        out.append(st["rate_pos"] + st["rate_neg"])
    return out


def measure(epochs: int = 4, per_threshold: int = 3) -> dict:
    """Steps 1-3 (see the module doc); returns the JSON written."""
    from trainer.stream_stats import recording_windows

    default = _samples({}, 10_000, epochs)
    fps = float(np.median([r["video_fps"] for r in default]))
    grid_s = 5 / fps
    sweep = {}
    for c in THRESHOLDS:
        rows = _samples({"ranges": {"threshold": [c, c], "ratio": [1.0, 1.0]}}, per_threshold, 1)
        sweep[c] = float(np.median([g for r in rows for g in r["grid_rates"]]))
    cs, rates = np.array(list(sweep)), np.array(list(sweep.values()))
    out = {"clips": str(SAMPLE_VIDEOS.relative_to(ROOT)), "epochs": epochs, "grid_s": grid_s,
           "default": {"sample_rates": [r["rate_pos"] + r["rate_neg"] for r in default],
                       "grid_rates": [g for r in default for g in r["grid_rates"]],
                       "thresholds": [[r["pos_threshold"], r["neg_threshold"]] for r in default]},
           "sweep": {str(c): v for c, v in sweep.items()}, "recordings": {}}
    still = still_rates()
    out["still"] = {"rates": still, "p50_p90_p99_max": [float(v) for v in np.percentile(still, [50, 90, 99, 100])],
                    "default_grids_below_p90": float((np.array(out["default"]["grid_rates"])
                                                      < np.percentile(still, 90)).mean())}
    g = np.array(out["default"]["grid_rates"])
    out["default"]["grid_p10_p50_p90"] = [float(v) for v in np.percentile(g, [10, 50, 90])]
    for name, path in RECORDINGS.items():
        rw = recording_windows(str(path), grid_s)
        window_s = grid_s
        if not rw["windows"]:  # shorter than one grid: its whole length (in 10 ms steps) as one window
            window_s = np.floor(rw["duration_s"] * 100) / 100
            rw = recording_windows(str(path), window_s)
        r = np.array([x["rate_pos"] + x["rate_neg"] for x in rw["windows"]])
        p10, p50, p90 = (float(v) for v in np.percentile(r, [10, 50, 90]))
        out["recordings"][name] = {
            "path": path.name, "windows": int(r.size), "window_s": float(window_s), "p10_p50_p90": [p10, p50, p90],
            "default_grids_below_p50": float((g < p50).mean()),
            "matching_threshold": _match(cs, rates, p50),
            "threshold_range": [_match(cs, rates, p90), _match(cs, rates, p10)]}
    return out


def figure(r: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(13, 4.5))
    g = np.array(r["default"]["grid_rates"])
    bins = np.logspace(-3, 3, 49)
    a.hist(g[g > 0], bins=bins, alpha=0.6, density=True, label="simulated voxel grids, default recipe")
    for (name, rec), col in zip(r["recordings"].items(), ("tab:red", "tab:green", "tab:purple")):
        lo, mid, hi = rec["p10_p50_p90"]
        a.axvspan(lo, hi, color=col, alpha=0.15)
        a.axvline(mid, color=col, label=f"{name}: median, 10-90 % shaded")
    a.set_xscale("log")
    a.set_xlabel(f"events / pixel / s, windows of {r['grid_s']:.2f} s")
    a.legend(fontsize=7)
    a.set_title("event rate: default recipe vs real sensors")
    cs = [float(c) for c in r["sweep"]]
    b.loglog(cs, list(r["sweep"].values()), "o-", label="simulated median (c+ = c- = c)")
    for (name, rec), col in zip(r["recordings"].items(), ("tab:red", "tab:green", "tab:purple")):
        b.axhline(rec["p10_p50_p90"][1], color=col, ls="--", label=name)
    b.axvspan(0.05, 2.0, color="grey", alpha=0.1, label="default threshold range")
    b.set_xlabel("contrast threshold c (log intensity)")
    b.set_ylabel("events / pixel / s")
    b.legend(fontsize=7)
    b.set_title("simulated rate against the threshold")
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epochs", type=int, default=4)
    ap.add_argument("--per-threshold", type=int, default=3, help="samples simulated at each fixed threshold")
    ap.add_argument("--json", default=str(ROOT / "docs" / "event_rate.json"))
    ap.add_argument("--png", default=str(ROOT / "docs" / "img" / "event_rate.png"))
    a = ap.parse_args(argv)
    r = measure(a.epochs, a.per_threshold)
    Path(a.json).write_text(json.dumps(r, indent=1) + "\n")
    figure(r, Path(a.png))
    lo, mid, hi = r["default"]["grid_p10_p50_p90"]
    print(f"default recipe, {len(r['default']['grid_rates'])} voxel grids of {r['grid_s']:.2f} s: "
          f"events/pixel/s p10 {lo:.3g}, median {mid:.3g}, p90 {hi:.3g}")
    print("sweep (threshold: median rate): " + ", ".join(f"{c}: {v:.3g}" for c, v in r["sweep"].items()))
    st = r["still"]
    print(f"still scene, {len(st['rates'])} default draws: events/pixel/s median/p90/p99/max "
          + "/".join(f"{v:.3g}" for v in st["p50_p90_p99_max"])
          + f"; {st['default_grids_below_p90']:.0%} of default grids below its p90")
    for name, rec in r["recordings"].items():
        fmt = lambda v: "outside the sweep" if v is None else f"{v:.3g}"  # noqa: E731
        print(f"{name}: {rec['windows']} windows of {rec['window_s']:.2f} s, p10/median/p90 " + "/".join(f"{v:.3g}" for v in rec["p10_p50_p90"])
              + f"; {rec['default_grids_below_p50']:.0%} of default grids below its median; matching threshold "
              f"{fmt(rec['matching_threshold'])}, range {fmt(rec['threshold_range'][0])} - {fmt(rec['threshold_range'][1])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

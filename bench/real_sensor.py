"""V2V held against a real sensor: voxels simulated from a DAVIS346's APS frames against the
events the same camera recorded between the same frame timestamps.

``python -m bench.real_sensor [--recording PATH] [--out DIR]`` (from the repository root)
prints a markdown table and writes ``DIR/real_sensor.md`` and ``DIR/real_sensor.json``.

Setup: the DAVIS346 recording of ``tests/data/events`` (AEDAT4: events, 25 Hz APS frames,
trainer/recordings.py reads both). The frames from the first one after the first event, a
whole number of 5-frame-interval groups, are the simulator's input (uint8 luma, one frame pair
per bin); the real events between the same frame timestamps are binned into the discrete voxel
grid (``trainer.event_grids.voxel_grids``): one grid of one bin per frame interval, 5 of them
summed giving the paper's 5-bin grid (5 frame intervals) summed over its bins
(``tests/test_real_sensor.py`` checks both hold the same events).

The contrast thresholds c+ and c- are fitted on plain V2V so that its N+ and N- over the clip
equal the real sensor's (N is roughly proportional to 1 / c: a few multiplicative steps); every
setting then runs with them and one initial potential U[-c-, c+] (seed 0), no noise or hot pixels.

Settings: plain V2V (``simulate_voxels``), V2V refined (``simulate_voxels_refined``:
``adaptive-dl:1``, ``uniform:4``), the event-level reference (``reference.simulate_events``,
16 motion-compensated sub-frames per pair, DIS MEDIUM); baselines: zero, and plain V2V shifted
by one frame interval (grid k compared with real grid k + 1).

Metrics (cells = frame interval x pixel, signed counts N+ - N-):

* ``corr``: Pearson correlation of the signed counts over all cells; ``corr moving``: over the
  cells where the APS log intensity changes by more than the mean fitted threshold between the
  interval's two frames; ``corr 5-bin sum``: of the 5-bin grids summed over their bins (a
  pixel's net count over 5 frame intervals, 200 ms);
* ``sign agree``: of the cells where both the real and the simulated count are non-zero, the
  fraction with the same sign; ``nL1``: ``sum |V - R| / sum |R|`` (the zero baseline's is 1);
* ``N ratio``: simulated events (N+ + N-) over real ones;
* ``ms / interval``: simulation time per frame interval (2 shared CPU cores, +-30 %).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import List, Optional

import numpy as np

from harness.data import DAVIS346
from trainer.event_grids import voxel_grids
from trainer.recordings import open_recording
from v2v_server.simulation.reference import events_to_voxels, simulate_events
from v2v_server.simulation.refine import RefineSpec, simulate_voxels_refined
from v2v_server.simulation.simulate import SensorParams, log_intensity_lut, simulate_voxels

DEFAULT = DAVIS346
GROUP = 5  # the paper's bins per voxel grid


def real_and_frames(path: Path):
    """``(frames uint8 (N, H, W), real int64 (N-1, H, W) signed counts per frame interval,
    n_pos, n_neg, frame timestamps int64 (N,) us, the recording)``; N - 1 a multiple of
    :data:`GROUP`. One pass over the events: with polarities +-1, N+ + N- is the events
    counted and N+ - N- the sum of the signed counts."""
    rec = open_recording(path)
    fr = rec.frames()
    t_first = rec.first_t_us()
    first = int(np.searchsorted(fr.t_us, t_first, "left"))
    n = (len(fr.t_us) - first - 1) // GROUP * GROUP + 1
    ts, frames = fr.t_us[first:first + n], fr.images[first:first + n]
    real = np.zeros((n - 1, rec.height, rec.width), np.int64)
    events = 0
    for k, vox, cnt in voxel_grids(rec.chunks(int(ts[0]), int(ts[-1])), ts, 1, rec.height, rec.width):
        real[k] = vox[0]
        events += int(cnt.sum())
    net = int(real.sum())
    return frames, real, (events + net) // 2, (events - net) // 2, ts, rec


def fit_thresholds(frames: np.ndarray, n_pos: int, n_neg: int, pot_seed: int = 0, steps: int = 8):
    """c+ and c- such that plain V2V's N+ and N- over ``frames`` match ``n_pos`` and ``n_neg``."""
    cp = cn = 0.2
    for _ in range(steps):
        pot = np.random.default_rng(pot_seed).uniform(-cn, cp, frames.shape[1:])
        _, _, (sp, sn) = simulate_voxels(frames, SensorParams(cp, cn), 1, initial_potential=pot, split=True)
        cp *= float(sp.sum()) / n_pos
        cn *= float(sn.sum()) / n_neg
    return cp, cn


def metrics(sim: np.ndarray, real: np.ndarray, moving: np.ndarray, n_real: int, n_sim: Optional[int]) -> dict:
    """The module docstring's metrics of ``sim`` against ``real`` (both int64 (K, H, W))."""
    def corr(a, b):
        a, b = a.astype(np.float64).ravel(), b.astype(np.float64).ravel()
        if a.std() == 0 or b.std() == 0:
            return float("nan")
        return float(np.corrcoef(a, b)[0, 1])

    k = sim.shape[0] // GROUP * GROUP
    both = (sim != 0) & (real != 0)
    return {
        "corr": corr(sim, real),
        "corr_moving": corr(sim[moving], real[moving]),
        "corr_5bin_sum": corr(sim[:k].reshape(-1, GROUP, *sim.shape[1:]).sum(1),
                              real[:k].reshape(-1, GROUP, *real.shape[1:]).sum(1)),
        "sign_agree": float((np.sign(sim[both]) == np.sign(real[both])).mean()) if both.any() else float("nan"),
        "nl1": float(np.abs(sim - real).sum() / max(np.abs(real).sum(), 1)),
        "n_ratio": None if n_sim is None else n_sim / n_real,
    }


def run(path: Path) -> dict:
    """All settings on one recording: ``{"setup": {...}, "rows": [...]}``."""
    frames, real, n_pos, n_neg, ts, rec = real_and_frames(path)
    shape = frames.shape[1:]
    n_int = frames.shape[0] - 1
    t0 = time.perf_counter()
    cp, cn = fit_thresholds(frames, n_pos, n_neg)
    fit_s = time.perf_counter() - t0
    params = SensorParams(cp, cn)
    pot = np.random.default_rng(0).uniform(-cn, cp, shape)
    lut = log_intensity_lut(255, np.float64)
    dlog = np.abs(np.diff(lut[frames], axis=0))
    moving = dlog > 0.5 * (cp + cn)
    fps = 1e6 / float(np.median(np.diff(ts)))

    def plain():
        v, _, (sp, sn) = simulate_voxels(frames, params, 1, initial_potential=pot, split=True)
        return v[:, 0].astype(np.int64), int(sp.sum() + sn.sum())

    def refined(spec):
        def f():
            v, _, info = simulate_voxels_refined(frames, params, 1, spec, initial_potential=pot)
            return v[:, 0].astype(np.int64), int(info["events"])
        return f

    def reference():
        ev, _ = simulate_events(frames, params, subframes=16, interpolation="motion", flow_preset="medium",
                                initial_potential=pot, fps=fps)
        return events_to_voxels(ev, n_int, 1, shape, fps)[:, 0].astype(np.int64), len(ev)

    settings = [("V2V (plain)", plain), ("V2V --refine adaptive-dl:1", refined("adaptive-dl:1")),
                ("V2V --refine uniform:4", refined("uniform:4")),
                ("V2V --refine uniform:4 (DIS medium)", refined(RefineSpec("uniform", k=4, flow_preset="medium"))),
                ("reference (16 motion sub-frames)", reference)]
    rows = []
    n_real = n_pos + n_neg
    plain_vox = plain_n = None
    for name, fn in settings:
        t = time.perf_counter()
        vox, n_sim = fn()
        dt = time.perf_counter() - t
        if plain_vox is None:
            plain_vox, plain_n = vox, n_sim
        rows.append({"setting": name, "ms_per_interval": 1e3 * dt / n_int, **metrics(vox, real, moving, n_real, n_sim)})
    rows.append({"setting": "baseline: zero", "ms_per_interval": 0.0,
                 **metrics(np.zeros_like(real), real, moving, n_real, 0)})
    shifted = np.concatenate([np.zeros_like(plain_vox[:1]), plain_vox[:-1]])  # grid k-1 against real k
    rows.append({"setting": "baseline: V2V shifted by one frame interval",
                 "ms_per_interval": rows[0]["ms_per_interval"],
                 **metrics(shifted, real, moving, n_real, plain_n)})  # plain V2V's events, one interval late
    setup = {"recording": path.name, "sensor": f"{rec.width}x{rec.height}", "frames": int(frames.shape[0]),
             "intervals": n_int, "fps": fps, "real_events": n_real, "real_n_pos": n_pos, "real_n_neg": n_neg,
             "c_pos": cp, "c_neg": cn, "fit_s": fit_s, "moving_cells_pct": float(100 * moving.mean())}
    return {"setup": setup, "rows": rows}


def table(res: dict) -> str:
    """Markdown table of :func:`run`'s rows."""
    def f(v, fmt):
        return "n/a" if v is None or (isinstance(v, float) and np.isnan(v)) else format(v, fmt)

    out = ["| setting | ms / interval | corr | corr moving | corr 5-bin sum | sign agree | nL1 | N ratio |",
           "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in res["rows"]:
        out.append(f"| {r['setting']} | {f(r['ms_per_interval'], '.1f')} | {f(r['corr'], '.3f')} | "
                   f"{f(r['corr_moving'], '.3f')} | {f(r['corr_5bin_sum'], '.3f')} | {f(r['sign_agree'], '.3f')} | "
                   f"{f(r['nl1'], '.3f')} | "
                   f"{f(r['n_ratio'], '.2f')} |")
    s = res["setup"]
    out.append("")
    out.append(f"{s['recording']}: {s['sensor']}, {s['frames']} APS frames at {s['fps']:.0f} Hz "
               f"({s['intervals']} intervals), {s['real_events']} real events (N+ {s['real_n_pos']}, "
               f"N- {s['real_n_neg']}); fitted c+ = {s['c_pos']:.3f}, c- = {s['c_neg']:.3f}; "
               f"moving cells {s['moving_cells_pct']:.1f} %.")
    return "\n".join(out)


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.real_sensor", description=__doc__.split("\n")[0])
    ap.add_argument("--recording", default=str(DEFAULT), help="an AEDAT4 recording with APS frames")
    ap.add_argument("--out", default="bench/results", help="folder for real_sensor.md / .json")
    args = ap.parse_args(argv)
    res = run(Path(args.recording))
    md = table(res)
    print(md)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "real_sensor.md").write_text(md + "\n")
    (out / "real_sensor.json").write_text(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())

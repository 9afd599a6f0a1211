"""Speed / accuracy trade of V2V against an event-level reference, on real clips.

``python -m bench.tradeoff --out DIR`` (from the repository root) prints a markdown
table and writes ``DIR/tradeoff.md``, ``DIR/tradeoff.json`` and ``DIR/pareto.png``.

Setup (same for every candidate): each clip is decoded to luma, centre-cropped to
``--crop`` pixels at native resolution, ``--voxels`` voxel grids of ``--bins`` bins, each
bin spanning ``--pairs-per-bin`` frame intervals of the source; one initial potential
U[-c-, c+] (seed ``--seed``), no noise or hot pixels (so the error is the motion shortcut
alone), thresholds ``--cpos`` / ``--cneg``.

Reference: ``reference.simulate_events`` on the full-rate clip with 16 motion-compensated
sub-frames per pair (DIS MEDIUM), binned into the discrete voxel grid (SBT).

Candidates: V2V on the clip subsampled by 1, 2, 4 in time; float64 compute; V2V plus
uniform K = 2, 4, 8 motion-compensated sub-frames; DIS presets ULTRAFAST / FAST / MEDIUM
at K = 4; adaptive refinement at several lambda (pixels) and adaptive-dl (log units);
the int8 (narrowed) and float16 wire.

Metrics per candidate V against reference R (L, B, H, W): time per voxel grid (ms, decode
excluded, best of ``--repeat``), speed relative to plain V2V, normalised L1
``sum |V - R| / sum |R|``, fraction of voxel cells whose count differs, event-rate error
``(events_V - events_R) / events_R`` (events = N+ + N- summed over all steps), and wire
bytes per voxel grid.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import List, Optional

import numpy as np

from harness.data import SAMPLE_VIDEOS
from v2v_wire.protocol import narrow_int_dtype

from v2v_server.simulation.reference import events_to_voxels, simulate_events
from v2v_server.simulation.refine import simulate_voxels_refined
from v2v_server.simulation.simulate import SensorParams, simulate_voxels

DEFAULT_CLIPS = ["bikes.mp4", "bigbuckbunny.mp4", "webvid_like_596x336.mp4"]




def read_crop(path: Path, n: int, crop: int) -> np.ndarray:
    """First ``n`` full-range luma frames of a clip (``v2v_server.frames.decode.iter_luma``), centre crop
    ``crop x crop`` at native resolution: uint8 (n, crop, crop). Raises ValueError if the clip is shorter."""
    from v2v_server.frames.decode import iter_luma

    out = []
    frames = iter_luma(path)
    for g in frames:
        h, w = g.shape
        y0, x0 = (h - crop) // 2, (w - crop) // 2
        out.append(np.ascontiguousarray(g[y0 : y0 + crop, x0 : x0 + crop]))
        if len(out) == n:
            break
    frames.close()
    if len(out) < n:
        raise ValueError(f"{path} has {len(out)} frames, need {n}")
    return np.stack(out)


def _narrow(v: np.ndarray) -> np.ndarray:
    return v.astype(narrow_int_dtype(v))


def _timed(fn, repeat: int):
    best, out = np.inf, None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def run_clip(frames: np.ndarray, args) -> dict:
    """All candidates on one clip: {"reference": {...}, "rows": [...], "claim": {...}}."""
    L, B, P = args.voxels, args.bins, args.pairs_per_bin
    n_pairs = L * B * P
    frames = frames[: n_pairs + 1]
    shape = frames.shape[1:]
    params = SensorParams(args.cpos, args.cneg)
    pot0 = np.random.default_rng(args.seed).uniform(-args.cneg, args.cpos, shape)

    t_ref, (ev, _) = _timed(lambda: simulate_events(frames, params, subframes=16, interpolation="motion",
                                                    flow_preset="medium", initial_potential=pot0, fps=args.fps), 1)
    ref = events_to_voxels(ev, L, B, shape, args.fps, frames_per_bin=P).astype(np.int64)
    ref_events = len(ev)

    def v2v(step, dtype=np.float32):
        sub = frames[::step]
        pb = P // step
        v, _ = simulate_voxels(sub, params, B * pb, initial_potential=pot0, compute_dtype=dtype)
        per_pair = v.reshape(L, B, pb, *shape).astype(np.int64)
        return per_pair.sum(2), int(np.abs(per_pair).sum())

    def refined(spec):
        v, _, info = simulate_voxels_refined(frames, params, B * P, spec, initial_potential=pot0)
        return v.reshape(L, B, P, *shape).astype(np.int64).sum(2), info["events"], info["subframes_mean"]

    cands = [("V2V (every frame)", lambda: v2v(1) + (1.0,))]
    cands += [(f"V2V, 1/{s} frames", (lambda s=s: v2v(s) + (1.0 / s,))) for s in (2, 4)]
    cands += [("V2V float64", lambda: v2v(1, np.float64) + (1.0,))]
    for k in (2, 4, 8):
        cands.append((f"uniform:{k} (ultrafast)", lambda k=k: refined(f"uniform:{k}")))
    for preset in ("fast", "medium"):
        from v2v_server.simulation.refine import RefineSpec

        cands.append((f"uniform:4 ({preset})", lambda p=preset: refined(RefineSpec("uniform", k=4, flow_preset=p))))
    for lam in args.lambdas:
        cands.append((f"adaptive:{lam:g}", lambda lam=lam: refined(f"adaptive:{lam:g}")))
    for lam in args.dl_lambdas:
        cands.append((f"adaptive-dl:{lam:g}", lambda lam=lam: refined(f"adaptive-dl:{lam:g}")))

    rows = []
    base_t = None
    for name, fn in cands:
        t, (vox, events, subf) = _timed(fn, args.repeat)
        if base_t is None:
            base_t = t
        rows.append(_metrics(name, t, vox, events, subf, ref, ref_events, L, base_t, _narrow(vox).nbytes))
        if name == "V2V (every frame)":
            f16 = vox.astype(np.float16).astype(np.int64)
            rows.append(_metrics("  wire float16", t, f16, events, subf, ref, ref_events, L, base_t, vox.size * 2))
            rows[-2]["name"] = "V2V (every frame), int8 wire"

    # the paper's claim at frame-pair resolution: plain V2V vs the reference, c+ = c- and c+ != c-
    claim = {}
    for label, (cp, cn) in {"c+ = c-": (args.cpos, args.cpos), "c+ != c-": (args.cpos, args.cneg)}.items():
        p2 = SensorParams(cp, cn)
        ev2, _ = simulate_events(frames, p2, subframes=16, interpolation="motion", flow_preset="medium",
                                 initial_potential=pot0, fps=args.fps)
        r2 = events_to_voxels(ev2, L, B * P, shape, args.fps).reshape(n_pairs, *shape).astype(np.int64)
        v2, _ = simulate_voxels(frames, p2, B * P, initial_potential=pot0)
        d = v2.reshape(n_pairs, *shape).astype(np.int64) - r2
        cum = np.abs(np.cumsum(d, axis=0))
        lin, _ = simulate_events(frames, p2, subframes=1, initial_potential=pot0, fps=args.fps)
        r_lin = events_to_voxels(lin, L, B * P, shape, args.fps).reshape(n_pairs, *shape)
        claim[label] = {
            "frac_bins_differ": float((d != 0).mean()),
            "max_abs_bin_diff": int(np.abs(d).max()),
            "max_abs_cumulative_diff": int(cum.max()),
            "mean_abs_cumulative_diff_end": float(cum[-1].mean()),
            "nl1": float(np.abs(d).sum() / max(np.abs(r2).sum(), 1)),
            # float32 state ties only (V2V stores dL_hat in float32, the reference in float64)
            "linear_reference_cells_differ": int((r_lin != v2.reshape(n_pairs, *shape)).sum()),
            "cells": int(d.size),
        }
    return {"reference": {"time_ms": 1e3 * t_ref / L, "events": ref_events}, "rows": rows, "claim": claim}


def _metrics(name, t, vox, events, subf, ref, ref_events, L, base_t, nbytes):
    return {
        "name": name,
        "time_ms": 1e3 * t / L,
        "speed_vs_v2v": base_t / t,
        "nl1": float(np.abs(vox - ref).sum() / max(np.abs(ref).sum(), 1)),
        "frac_differ": float((vox != ref).mean()),
        "rate_err": float((events - ref_events) / max(ref_events, 1)),
        "subframes": float(subf),
        "wire_bytes": int(nbytes // L),
    }


def _table(rows, ref=None) -> str:
    head = ("| setting | ms / voxel | speed vs V2V | sub-frames / pair | norm. L1 | cells differing "
            "| event-rate err | wire B / voxel |\n|---|---:|---:|---:|---:|---:|---:|---:|\n")
    lines = []
    if ref is not None:
        lines.append(f"| reference (16 motion sub-frames, DIS medium) | {ref['time_ms']:.1f} | "
                     f"{rows[0]['time_ms'] / ref['time_ms']:.3f} | 16 | 0 | 0 | 0 | - |")
    for r in rows:
        lines.append(f"| {r['name']} | {r['time_ms']:.2f} | {r['speed_vs_v2v']:.2f} | {r['subframes']:.2f} | "
                     f"{r['nl1']:.3f} | {r['frac_differ']:.3f} | {r['rate_err']:+.3f} | {r['wire_bytes']} |")
    return head + "\n".join(lines) + "\n"


def _mean_rows(results: dict) -> List[dict]:
    names = [r["name"] for r in next(iter(results.values()))["rows"]]
    out = []
    for i, name in enumerate(names):
        rs = [res["rows"][i] for res in results.values()]
        out.append({k: (name if k == "name" else float(np.mean([r[k] for r in rs]))) for k in rs[0]})
    return out


def _plot(rows: List[dict], ref_ms: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.8), dpi=90)
    pts = [(r["time_ms"], r["nl1"], r["name"].strip()) for r in rows if not r["name"].startswith("  wire")]
    front, best = [], np.inf
    for t, e, n in sorted(pts):
        if e < best:
            front.append((t, e))
            best = e
    for t, e, n in pts:
        on = (t, e) in front
        ax.scatter(t, e, c="C3" if on else "C0", s=28, zorder=3)
        ax.annotate(n, (t, e), fontsize=7, xytext=(4, 3), textcoords="offset points")
    ax.plot(*zip(*front), "C3--", lw=1, label="Pareto front")
    ax.axvline(ref_ms, color="gray", lw=0.8, ls=":", label=f"reference ({ref_ms:.0f} ms, error 0)")
    ax.set_xscale("log")
    ax.set_xlabel("time per voxel grid (ms, log scale, 2 shared CPU cores)")
    ax.set_ylabel("normalised L1 vs event-level reference")
    ax.set_title("V2V speed / accuracy trade (mean over 3 real clips)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv: Optional[List[str]] = None) -> int:
    """CLI entry point; returns the exit status."""
    ap = argparse.ArgumentParser(prog="python -m bench.tradeoff", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="output folder (table, json, Pareto PNG)")
    ap.add_argument("--videos", type=Path, default=None, help="folder of clips (default: the bundled ones)")
    ap.add_argument("--clips", nargs="+", default=DEFAULT_CLIPS)
    ap.add_argument("--crop", type=int, default=128)
    ap.add_argument("--voxels", type=int, default=2)
    ap.add_argument("--bins", type=int, default=5)
    ap.add_argument("--pairs-per-bin", type=int, default=4, help="source frame intervals per bin (multiple of 4)")
    ap.add_argument("--cpos", type=float, default=0.2)
    ap.add_argument("--cneg", type=float, default=0.3)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--lambdas", type=float, nargs="+", default=[8.0, 4.0, 2.0, 1.0])
    ap.add_argument("--dl-lambdas", type=float, nargs="+", default=[1.0, 0.5])
    args = ap.parse_args(argv)
    if args.pairs_per_bin % 4:
        ap.error("--pairs-per-bin must be a multiple of 4 (the 1/4 subsampled candidate)")
    vdir = args.videos or SAMPLE_VIDEOS
    args.out.mkdir(parents=True, exist_ok=True)
    n = args.voxels * args.bins * args.pairs_per_bin + 1
    results = {}
    for clip in args.clips:
        frames = read_crop(vdir / clip, n, args.crop)
        results[clip] = run_clip(frames, args)
        print(f"## {clip}\n\n" + _table(results[clip]["rows"], results[clip]["reference"]), flush=True)
    mean = _mean_rows(results)
    ref_ms = float(np.mean([r["reference"]["time_ms"] for r in results.values()]))
    cfg = (f"crop {args.crop}x{args.crop}, {args.voxels} voxels x {args.bins} bins x {args.pairs_per_bin} "
           f"frame intervals per bin, c+ = {args.cpos}, c- = {args.cneg}, seed {args.seed}, no noise")
    md = [f"# V2V speed / accuracy trade\n\n{cfg}.\n\n## Mean over {len(results)} clips\n",
          _table(mean, {"time_ms": ref_ms})]
    for clip, res in results.items():
        md.append(f"\n## {clip}\n\n" + _table(res["rows"], res["reference"]))
    md.append("\n## V2V vs reference at frame-pair resolution (the paper's claim)\n\n"
              "| clip | thresholds | bins differing | max bin diff | max cumulative diff | nL1 | "
              "linear-interp. reference: cells differing |\n|---|---|---:|---:|---:|---:|---:|\n")
    for clip, res in results.items():
        for label, c in res["claim"].items():
            md.append(f"| {clip} | {label} | {c['frac_bins_differ']:.4f} | {c['max_abs_bin_diff']} | "
                      f"{c['max_abs_cumulative_diff']} | {c['nl1']:.3f} | {c['linear_reference_cells_differ']} of {c['cells']} |\n")
    text = "".join(md)
    (args.out / "tradeoff.md").write_text(text)
    (args.out / "tradeoff.json").write_text(json.dumps({"config": vars(args) | {"out": str(args.out),
                                                        "videos": str(vdir)}, "results": results, "mean": mean},
                                                       indent=1, default=str))
    try:
        _plot(mean, ref_ms, args.out / "pareto.png")
    except ImportError:
        print("matplotlib not installed (pip install 'v2v[bench]'): no Pareto plot")
    print(f"## mean over clips\n\n{_table(mean, {'time_ms': ref_ms})}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

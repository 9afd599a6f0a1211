"""Optical flow options against ground truth: end-point error vs displacement, and cost.

Clips with known motion are rendered over real textures: the still photographs
``harness/motion_clips.py`` uses (skimage / matplotlib) and one frame from the middle of each
bundled clip. Each clip is ``--voxels`` voxel grids of ``--step`` frames (5) moving at constant
velocity with one similarity motion about the crop centre: translation, rotation or zoom, at
0..40 px per voxel, where a displacement ``d`` means the *median* ground-truth displacement over
the 128 x 128 crop is ``d`` pixels per voxel (translation: every pixel moves d; rotation and zoom:
pixels at the median radius move d). Frames are rendered with ``cv2.warpAffine`` (bilinear,
reflected border) from exact affine matrices, so the ground-truth flow is exact:
``x_b = A_b A_a^-1 x``.

End-point error (EPE) = ``|| flow - ground truth ||`` in pixels, over the pixels whose
ground-truth destination lies inside the crop (the rest cannot be observed), pooled over the
textures and all voxels of a clip (the first voxel included, which has no previous voxel to
start from). Cost: ms per sample = one call of ``FlowEstimator.voxel_flows`` on a 201-frame
128 x 128 sample (40 flows), OpenCV on one thread, process CPU time, the minimum of
``--repeats`` rounds that time every option, decoding and the voxels once each in turn (the
machine is shared: the minimum is the least disturbed run, and load from other jobs hits all
alike), next to the CPU time of decoding one sample (201 frames) of the bundled 596 x 336 clip.

    python -m bench.flow --out docs [--quick]
    python -m bench.flow --out docs --name flow_bench_zoom --kinds zoom-in zoom-out --options ...
    python -m bench.flow --out docs --name flow_bench_real --real --options ...

Writes ``OUT/NAME.md`` (table), ``OUT/NAME.json`` and, for the default name ``flow_bench``, the
plot ``OUT/img/flow_epe.png``. For iterating: ``--quick`` (4
photographs and the 3 clips), ``--kinds``, ``--displacements``, ``--options``, ``--repeats``.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from typing import Dict, List

import cv2
import numpy as np

from harness.flow_scenes import EXTRA_KINDS, KINDS, SIZE, epe, motion_matrices, render, textures
from v2v_server.flow.estimate import FlowEstimator
from v2v_server.flow.options import DEFAULT_FLOW, FLOW_OPTIONS, FlowUnavailable

def time_option(est: FlowEstimator, sample: np.ndarray, step: int, repeats: int) -> float:
    """CPU ms for one sample's flows (min over ``repeats``; process CPU time, one thread)."""
    est.voxel_flows(sample[: step + 1], step)  # warm up (object creation)
    best = float("inf")
    for _ in range(repeats):
        t = time.process_time()
        est.voxel_flows(sample, step)
        best = min(best, time.process_time() - t)
    return best * 1000


def time_decode(repeats: int, frames: int = 201) -> float:
    """CPU ms to decode one sample's frames (201, luma) of the bundled 596 x 336 clip, one thread:
    the cost the flow is compared with (min over ``repeats``)."""
    from v2v_server.frames.decode import decode_luma, open_video

    here = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "v2v_server", "sample_videos")
    best = float("inf")
    for _ in range(repeats):
        t = time.process_time()
        c, s, info = open_video(os.path.join(here, "webvid_like_596x336.mp4"), 1)
        try:
            for i, _luma in enumerate(decode_luma(c, s, info.height)):
                if i + 1 == frames:
                    break
        finally:
            c.close()
        best = min(best, time.process_time() - t)
    return best * 1000


def time_voxels(sample: np.ndarray, repeats: int) -> float:
    """CPU ms of the voxels output (plain V2V, ``simulate_voxels``, 200 bins) of one sample."""
    from v2v_server.simulation.simulate import sample_params, simulate_voxels

    params = sample_params(np.random.default_rng(0), shape=sample.shape[1:])
    best = float("inf")
    for _ in range(repeats):
        t = time.process_time()
        simulate_voxels(sample, params, sample.shape[0] - 1, rng=np.random.default_rng(0))
        best = min(best, time.process_time() - t)
    return best * 1000


def run(options: List[str], displacements: List[float], step: int, voxels: int, repeats: int, quick: bool,
        kinds=KINDS) -> Dict:
    cv2.setNumThreads(1)
    kinds = tuple(kinds)
    for k in kinds:
        if k not in KINDS + EXTRA_KINDS:
            raise ValueError(f"--kinds: unknown motion {k!r}, known: {KINDS + EXTRA_KINDS}")
    tex = textures(quick)
    rng = np.random.default_rng(0)
    directions = {name: float(rng.uniform(0, 2 * np.pi)) for name, _ in tex}
    clips = {}
    for kind in kinds:
        for d in displacements:
            clips[(kind, d)] = [render(img, motion_matrices(img.shape, kind, d, step, voxels, directions[n]), step)
                                for n, img in tex]
    # timing input: a 40-voxel sample of the first texture translating 20 px per voxel
    img0 = tex[0][1]
    sample, _ = render(img0, motion_matrices(img0.shape, "translation", 20.0, step, 40, 0.5), step)
    results = {"textures": [n for n, _ in tex], "displacements": displacements, "step": step,
               "voxels_per_clip": voxels, "default": DEFAULT_FLOW, "kinds": list(kinds), "options": {}, "skipped": {}}
    ests = {}
    for name in options:
        try:
            est = FlowEstimator(name)
        except FlowUnavailable as e:
            logging.warning("flow option %s skipped: %s", name, e)
            results["skipped"][name] = str(e)
            continue
        row = {"summary": FLOW_OPTIONS[name].summary, "median": {}, "mean": {}, "p90": {}}
        all_errs = []
        for kind in kinds:
            med, mean, p90 = [], [], []
            for d in displacements:
                errs = []
                for frames, gts in clips[(kind, d)]:
                    fl = est.voxel_flows(frames, step)
                    errs += [epe(fl[l], gts[l]) for l in range(len(gts))]
                e = np.concatenate(errs)
                all_errs.append(e)
                med.append(float(np.median(e)))
                mean.append(float(e.mean()))
                p90.append(float(np.percentile(e, 90)))
            row["median"][kind], row["mean"][kind], row["p90"][kind] = med, mean, p90
        row["median_all"] = [float(np.median(np.concatenate([all_errs[k * len(displacements) + i]
                                                              for k in range(len(kinds))])))
                             for i in range(len(displacements))]
        results["options"][name] = row
        ests[name] = est
        print(f"{name:28s} worst median EPE {max(max(v) for v in row['median'].values()):6.2f} px", flush=True)
    # costs last, round-robin: every option (and decoding, and the voxels) once per round, the
    # minimum over rounds, so that load from other jobs on a shared machine hits all alike
    best = {k: float("inf") for k in ["decode", "voxels"] + list(ests)}
    for _ in range(repeats):
        best["decode"] = min(best["decode"], time_decode(1))
        best["voxels"] = min(best["voxels"], time_voxels(sample, 1))
        for name, est in ests.items():
            best[name] = min(best[name], time_option(est, sample, step, 1))
    results["decode_ms_per_sample"], results["voxels_ms_per_sample"] = best["decode"], best["voxels"]
    print(f"decoding one sample (201 frames of the bundled 596 x 336 clip): {best['decode']:.1f} ms", flush=True)
    print(f"voxels of one sample (plain V2V, 201 frames of 128 x 128): {best['voxels']:.1f} ms", flush=True)
    for name in ests:
        results["options"][name]["ms_per_sample"] = best[name]
        print(f"{name:28s} {best[name]:7.1f} ms/sample", flush=True)
    return results


def real_clip_residuals(options: List[str], crops: int = 12, seed: int = 0) -> Dict:
    """No ground truth on real footage, so a proxy: the photometric residual of each option's
    flow on the bundled clips, mean ``|a(x) - b(x + flow(x))|`` (grey levels, 0..255) over the
    pixels whose destination lies inside the crop, for ``crops`` random 128 x 128 crops of 21
    frames (4 voxels) per clip, next to the residual of zero flow. Lower means the flow explains
    more of the change between the boundary frames; it is not the flow error (motion blur,
    occlusion and lighting leave a floor, and a wrong flow can match by chance)."""
    from v2v_server.frames.decode import decode_luma, open_video

    cv2.setNumThreads(1)
    here = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "v2v_server", "sample_videos")
    rng = np.random.default_rng(seed)
    gx, gy = np.meshgrid(np.arange(SIZE, dtype=np.float32), np.arange(SIZE, dtype=np.float32))
    out = {"crops_per_clip": crops, "clips": {}}
    for vid in sorted(n for n in os.listdir(here) if n.endswith(".mp4")):
        c, s, info = open_video(os.path.join(here, vid), 1)
        try:
            frames = []
            for luma in decode_luma(c, s, info.height):
                frames.append(np.ascontiguousarray(luma))
                if len(frames) == 400:
                    break
        finally:
            c.close()
        frames = np.stack(frames)
        t, h, w = frames.shape
        row = {name: [] for name in ["zero flow"] + options}
        for _ in range(crops):
            t0, y, x = int(rng.integers(0, t - 21)), int(rng.integers(0, h - SIZE)), int(rng.integers(0, w - SIZE))
            clip = np.ascontiguousarray(frames[t0:t0 + 21, y:y + SIZE, x:x + SIZE])
            flows = {"zero flow": np.zeros((4, 2, SIZE, SIZE), np.float32)}
            flows.update({name: FlowEstimator(name).voxel_flows(clip, 5) for name in options})
            for name, fl in flows.items():
                for l in range(4):
                    a, b = clip[5 * l].astype(np.float32), clip[5 * l + 5].astype(np.float32)
                    mx, my = gx + fl[l, 0], gy + fl[l, 1]
                    inside = (mx >= 0) & (mx <= SIZE - 1) & (my >= 0) & (my <= SIZE - 1)
                    if inside.mean() > 0.3:  # else the flow leaves the crop: no residual to speak of
                        row[name].append(float(np.abs(a - cv2.remap(b, mx, my, cv2.INTER_LINEAR))[inside].mean()))
        out["clips"][vid] = {name: float(np.mean(v)) if v else float("nan") for name, v in row.items()}
        print(vid, " ".join(f"{k} {v:.2f}" for k, v in out["clips"][vid].items()), flush=True)
    return out


def real_table(res: Dict) -> str:
    names = list(next(iter(res["clips"].values())))
    lines = [
        f"Photometric residual on the bundled clips (no ground truth there): mean |a(x) - b(x + flow(x))| in grey "
        f"levels over pixels whose destination stays in the crop, {res['crops_per_clip']} random 128 x 128 crops of "
        f"4 voxels per clip. Lower: the flow explains more of the change; not the flow error.",
        "",
        "| clip | " + " | ".join(names) + " |",
        "|---|" + "---:|" * len(names),
    ]
    for vid, row in res["clips"].items():
        lines.append(f"| {vid} | " + " | ".join(f"{row[n]:.2f}" for n in names) + " |")
    return "\n".join(lines) + "\n"


def table(res: Dict) -> str:
    ds = res["displacements"]
    kinds = res.get("kinds", KINDS)
    pick = ([i for i, d in enumerate(ds) if d in (10, 20, 30, 40)] if len(ds) > 5 else []) or list(range(len(ds)))
    short = {"translation": "transl.", "rotation": "rot.", "zoom": "zoom", "zoom-in": "zoom in", "zoom-out": "zoom out"}
    lines = [
        f"Median end-point error (px) over {len(res['textures'])} textures x {res['voxels_per_clip']} voxels, "
        f"by displacement per voxel ({res['step']} frames); CPU ms per sample (40 flows of 128 x 128, one core) "
        f"and as a fraction of decoding one sample ({res['decode_ms_per_sample']:.0f} ms, same run; the voxels "
        f"output costs {res['voxels_ms_per_sample']:.0f} ms).",
        "",
        "| option | ms / sample | x decode | " + " | ".join(f"{short.get(k, k)} {ds[i]:g}" for k in kinds for i in pick) + " | worst median |",
        "|---|---:|---:|" + "---:|" * (len(kinds) * len(pick)) + "---:|",
    ]
    for name, r in res["options"].items():
        worst = max(max(v) for v in r["median"].values())
        cells = [f"{r['median'][k][i]:.2f}" for k in kinds for i in pick]
        tag = f"**{name}** (default)" if name == res["default"] else name
        ratio = r["ms_per_sample"] / res["decode_ms_per_sample"]
        lines.append(f"| {tag} | {r['ms_per_sample']:.1f} | {ratio:.2f} | " + " | ".join(cells) + f" | {worst:.2f} |")
    for name, why in res["skipped"].items():
        lines.append(f"| {name} | skipped | | " + " | ".join("" for _ in range(len(kinds) * len(pick))) + f" | {why} |")
    return "\n".join(lines) + "\n"


def plot(res: Dict, path: str) -> None:
    """Three panels of median EPE vs displacement (one per motion) and EPE vs cost."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ds = res["displacements"]
    kinds = res.get("kinds", KINDS)[:3]
    fig, axes = plt.subplots(2, 2, figsize=(13, 9.5))
    cmap = plt.get_cmap("tab20")
    floor = 0.03
    for i, (name, r) in enumerate(res["options"].items()):
        method = FLOW_OPTIONS[name].method if name in FLOW_OPTIONS else "direct"
        style = dict(color="k" if name == res["default"] else cmap(i % 20), lw=3.0 if name == res["default"] else 1.3,
                     ls={"tracked": "-."}.get(method, "--"), marker="o", ms=3)
        for ax, kind in zip(axes.flat, kinds):
            ax.plot(ds, np.maximum(r["median"][kind], floor), label=name, **style)
        worst = max(max(v) for v in r["median"].values())
        axes[1, 1].scatter(r["ms_per_sample"], worst, color=style["color"], s=90 if name == res["default"] else 30)
        axes[1, 1].annotate(name, (r["ms_per_sample"], worst), fontsize=7, xytext=(3, 3), textcoords="offset points")
    for ax, kind in zip(axes.flat, kinds):
        ax.axhline(2.0, color="k", ls=":", lw=1)
        ax.set(xlabel="displacement per voxel (px, median over the crop)", ylabel="median EPE (px)",
               yscale="log", ylim=(floor, 60),
               title=f"{kind}: median EPE vs displacement")
    axes[0, 0].legend(fontsize=7, ncol=2)
    ax = axes[1, 1]
    ax.axhline(2.0, color="k", ls=":", lw=1)
    ax.axvline(30.0, color="k", ls=":", lw=1)
    ax.set(xlabel=f"CPU ms per sample (40 flows of 128 x 128, one core; decoding: {res['decode_ms_per_sample']:.0f} ms)",
           xscale="log", yscale="log", ylabel="worst median EPE over motions, 0..40 px (px)", title="EPE vs cost")
    fig.suptitle(f"dashed: DIS at the voxel spacing, dash-dot: tracked; thick black: the default "
                 f"({res['default']}); dotted: the target (2 px, 30 ms)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def _write(out: str, name: str, res: Dict, md: str, tool: str) -> None:
    """``OUT/NAME.json`` (raw results) and ``OUT/NAME.md`` (the table, marked as written by
    ``tool``); prints the table."""
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, f"{name}.json"), "w") as f:
        json.dump(res, f, indent=1)
    with open(os.path.join(out, f"{name}.md"), "w") as f:
        f.write(f"<!-- written by {tool}; do not edit -->\n" + md)
    print(md)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="folder for flow_bench.md, flow_bench.json, img/flow_epe.png")
    ap.add_argument("--options", nargs="*", default=list(FLOW_OPTIONS), help="options to measure (default all)")
    ap.add_argument("--displacements", type=float, nargs="*", default=[0, 5, 10, 15, 20, 25, 30, 35, 40])
    ap.add_argument("--step", type=int, default=5, help="frames per voxel (B * frames_per_bin)")
    ap.add_argument("--voxels", type=int, default=3, help="voxel grids per rendered clip")
    ap.add_argument("--repeats", type=int, default=7, help="timing rounds (minimum over rounds)")
    ap.add_argument("--quick", action="store_true", help="4 photographs (and the 3 clips) only: a quicker run")
    ap.add_argument("--kinds", nargs="*", default=list(KINDS),
                    help=f"motions to render (default {' '.join(KINDS)}; also {' '.join(EXTRA_KINDS)})")
    ap.add_argument("--name", default="flow_bench", help="stem of the files written (default flow_bench)")
    ap.add_argument("--real", action="store_true",
                    help="instead: the photometric residual of --options on crops of the bundled clips")
    ap.add_argument("--from-json", help="redraw table and plot from an earlier flow_bench.json (no measuring)")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    if a.real:
        res = real_clip_residuals([o for o in a.options if FLOW_OPTIONS[o].method != "raft"])
        _write(a.out, a.name, res, real_table(res), "python -m bench.flow --real")
        return 0
    if a.from_json:
        with open(a.from_json) as f:
            res = json.load(f)
        res["default"] = DEFAULT_FLOW  # mark today's default
    else:
        res = run(a.options, a.displacements, a.step, a.voxels, a.repeats, a.quick, a.kinds)
    os.makedirs(os.path.join(a.out, "img"), exist_ok=True)
    _write(a.out, a.name, res, table(res), "python -m bench.flow")
    if a.name != "flow_bench":
        return 0
    try:
        plot(res, os.path.join(a.out, "img", "flow_epe.png"))
    except ImportError:
        print("matplotlib not installed (pip install 'v2v[bench]'): no plot", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Optical flow on independent motion: a textured object moving over a background that moves otherwise.

``bench.flow`` renders one global similarity motion per clip, where a smooth flow field is
right everywhere. Real footage also has objects that move on their own, where the flow jumps at
the object's border; a coarse or smooth estimator (a grid of tracked points with bilinear fill,
a 32 x 32 chain) blurs that jump. Here a square object (32 or 56 px, a photograph) translates at
``d_obj`` px per voxel over a background photograph translating at ``d_bg`` px per voxel in
another direction, on 128 x 128 frames; each pairing of 4 backgrounds x 4 objects x 2 sizes is
rendered for 2 voxels of 5 frames (``cv2.warpAffine``, bilinear), so the ground truth is exact:
the object's velocity on its pixels, the background's elsewhere.

End-point error is measured separately on the object (its pixels eroded by 2 px: the border
itself is ambiguous) and on the background (pixels at least 3 px from the object in the first
frame, not covered by it at their destination, destination inside the crop); the table gives
the median over clips and voxels of each clip's median EPE.

    python -m bench.flow_objects --out docs [--options tracked tracked-g12 ...]

Writes ``OUT/flow_bench_objects.md`` and ``.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Dict, List

import cv2
import numpy as np

from harness.flow_scenes import SIZE, render_object, square, textures
from v2v_server.flow.estimate import FlowEstimator
from v2v_server.flow.options import DEFAULT_FLOW


STEP = 5
#: (object px per voxel, background px per voxel)
MOTIONS = ((10, 5), (20, 10), (30, 0), (40, 20))


def errors(flow: np.ndarray, cover: np.ndarray, v_bg, v_obj) -> Dict[str, List[float]]:
    """Median EPE on the object and on the background for each voxel of one clip."""
    gx, gy = np.meshgrid(np.arange(SIZE), np.arange(SIZE))
    out = {"object": [], "background": []}
    for l in range(flow.shape[0]):
        a, b = l * STEP, (l + 1) * STEP
        on = cover[a]
        gt = np.where(on[None], STEP * np.asarray(v_obj, float)[:, None, None], STEP * np.asarray(v_bg, float)[:, None, None])
        tx, ty = gx + gt[0], gy + gt[1]
        inside = (tx >= 0) & (tx <= SIZE - 1) & (ty >= 0) & (ty <= SIZE - 1)
        dest_on = cover[b][np.clip(np.rint(ty).astype(int), 0, SIZE - 1), np.clip(np.rint(tx).astype(int), 0, SIZE - 1)]
        obj = cv2.erode(on.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool) & inside
        bgm = ~cv2.dilate(on.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool) & ~dest_on & inside
        e = np.hypot(flow[l, 0] - gt[0], flow[l, 1] - gt[1])
        out["object"].append(float(np.median(e[obj])))
        out["background"].append(float(np.median(e[bgm])))
    return out


def run(options: List[str]) -> dict:
    cv2.setNumThreads(1)
    photos = [img for _, img in textures()][:8]
    backgrounds, objects = photos[:4], photos[4:8]
    res = {"options": options, "motions": [list(m) for m in MOTIONS], "rows": {}}
    for d_obj, d_bg in MOTIONS:
        acc = {o: {"object": [], "background": []} for o in options}
        for i, (bg, ob) in enumerate(zip(backgrounds, objects)):
            ang = 0.7 + i
            v_bg = (d_bg / STEP * np.cos(ang), d_bg / STEP * np.sin(ang))
            v_obj = (d_obj / STEP * np.cos(ang + 2), d_obj / STEP * np.sin(ang + 2))
            for size in (32, 56):
                frames, cover = render_object(bg, square(ob, size), v_bg, v_obj)
                for o in options:
                    e = errors(FlowEstimator(o).voxel_flows(frames, STEP), cover, v_bg, v_obj)
                    for k in e:
                        acc[o][k] += e[k]
        res["rows"][f"{d_obj}/{d_bg}"] = {o: {k: float(np.median(v)) for k, v in acc[o].items()} for o in options}
        print(d_obj, d_bg, {o: {k: round(float(np.median(v)), 2) for k, v in acc[o].items()} for o in options},
              flush=True)
    return res


def table(res: dict) -> str:
    opts = res["options"]
    head = "| object / background px per voxel | " + " | ".join(
        f"{o}{' (default)' if o == DEFAULT_FLOW else ''}: object | background" for o in opts) + " |"
    lines = ["Median EPE (px) on an object moving over a background that moves otherwise "
             "(`python -m bench.flow_objects`; 4 backgrounds x 4 objects x 2 sizes, 2 voxels each).", "",
             head, "|---|" + "---:|---:|" * len(opts)]
    for key, row in res["rows"].items():
        lines.append(f"| {key} | " + " | ".join(f"{row[o]['object']:.2f} | {row[o]['background']:.2f}" for o in opts) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="folder for flow_bench_objects.md and .json")
    ap.add_argument("--options", nargs="*", default=[DEFAULT_FLOW, "tracked-g12", "ultrafast"])
    a = ap.parse_args(argv)
    res = run(a.options)
    os.makedirs(a.out, exist_ok=True)
    with open(os.path.join(a.out, "flow_bench_objects.json"), "w") as f:
        json.dump(res, f, indent=1)
    md = table(res)
    with open(os.path.join(a.out, "flow_bench_objects.md"), "w") as f:
        f.write("<!-- written by python -m bench.flow_objects; do not edit -->\n" + md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())

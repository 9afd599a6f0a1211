"""Held-out check of the E-RAFT CPU demo (``bench/trainer_demo.sh ... eraft``): end-point error
of a checkpoint on clips with known motion, next to zero flow.

The clips are rendered by ``harness.flow_scenes`` (128 x 128 crops of a still texture moving by
a known similarity transform, exact ground-truth flow between voxel boundaries) over the middle
frame of ``bigbuckbunny.mp4``, which the demo never serves; their voxel grids come from the V2V
core (``v2v_server.simulation.simulate.simulate_voxels``, one frame pair per bin) with sensor
settings drawn from the server's default ranges (seeded). Each checkpoint is scored with
``trainer.evaluate.evaluate_eraft`` (the V2V authors' pairing and warm start) on every voxel;
only pixels whose ground-truth target stays in the crop count (``flow_scenes.epe``).

    python -m harness.eraft_demo runs/demo/eraft/checkpoint_0000100.pt [...] [--d 2 4]

prints one JSON object per checkpoint: mean EPE (px) of the model and of zero flow per motion.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Dict, List, Tuple

import numpy as np
import torch

from harness.flow_scenes import KINDS, SIZE, epe, motion_matrices, render, textures


def heldout_clips(num_bins: int, voxels: int, displacements: List[float], seed: int = 0
                  ) -> Dict[str, Tuple[np.ndarray, np.ndarray]]:
    """{``kind@d``: (voxels float32 (L, num_bins, S, S), flows float32 (L, S, S, 2))} over the
    bigbuckbunny texture, for each of ``flow_scenes.KINDS`` and displacement ``d`` px/voxel."""
    from v2v_server.simulation.simulate import sample_params, simulate_voxels

    tex = dict(textures())
    img = next(v for k, v in tex.items() if "bigbuckbunny" in k)
    rng = np.random.default_rng(seed)
    out = {}
    for kind in KINDS:
        for d in displacements:
            frames, gts = render(img, motion_matrices(img.shape, kind, d, num_bins, voxels, float(rng.uniform(0, 2 * np.pi))),
                                 num_bins)
            params = sample_params(rng, shape=(SIZE, SIZE))
            vox, _ = simulate_voxels(frames, params, num_bins, rng=rng)
            out[f"{kind}@{d:g}"] = (np.asarray(vox, np.float32), gts)
    return out


def score(checkpoint: str, clips) -> dict:
    """Mean EPE (px) of the checkpoint's flow and of zero flow on each clip, voxels 1..L-1 (the
    first voxel has no predecessor in the clip)."""
    from trainer.evaluate import evaluate_eraft, load_model

    device = torch.device("cpu")
    task, model, _, _ = load_model(checkpoint, device)
    if task != "eraft":
        raise ValueError(f"{checkpoint} is a {task!r} checkpoint, not eraft")
    res = {"checkpoint": os.path.basename(checkpoint), "clips": {}}
    model_all, zero_all = [], []
    for name, (vox, gts) in clips.items():
        preds = []
        model.reset_states()
        with torch.no_grad():
            for l in range(1, len(vox)):
                a, b = (torch.from_numpy(vox[i])[None] for i in (l - 1, l))
                preds.append(model(a, b)[0].numpy())
        e_m = np.concatenate([epe(p, gts[l]) for l, p in zip(range(1, len(vox)), preds)])
        e_z = np.concatenate([epe(np.zeros_like(p), gts[l]) for l, p in zip(range(1, len(vox)), preds)])
        res["clips"][name] = {"epe": float(e_m.mean()), "zero_flow_epe": float(e_z.mean())}
        model_all.append(e_m), zero_all.append(e_z)
    res["epe"] = float(np.concatenate(model_all).mean())
    res["zero_flow_epe"] = float(np.concatenate(zero_all).mean())
    # the same model through v2v-eval's scoring function (pairing, warm start, valid pixels)
    name, (vox, gts) = next(iter(clips.items()))
    r = evaluate_eraft(model, vox, np.moveaxis(gts, -1, 1), None, device)
    res["v2v_eval_aee_first_clip"] = float(np.nanmean(r["aee"]))
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoints", nargs="+")
    ap.add_argument("--num-bins", type=int, default=5)
    ap.add_argument("--voxels", type=int, default=6, help="voxel grids per clip")
    ap.add_argument("--d", type=float, nargs="+", default=[2.0, 4.0], help="displacements, px per voxel")
    a = ap.parse_args(argv)
    clips = heldout_clips(a.num_bins, a.voxels, a.d)
    for ck in a.checkpoints:
        print(json.dumps(score(ck, clips)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

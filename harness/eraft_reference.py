"""Derive tests/data/eraft_reference.json from the V2V authors' E-RAFT (HYLZ-2019/V2V
``model/eraft/``), built as their ``config/train_v2v_eraft_10k.yaml`` builds it
(``subtype: warm_start``, ``n_first_channels: 5``).

The listing is what ``tests/test_trainer_eraft.py`` checks ``trainer.models.eraft.ERAFT`` against:
every state-dict key with its shape (in the authors' order), the trainable parameter count, and the count
per top-level module.

Run with a checkout (or ``git archive HEAD model/eraft``) of the authors' repository, which
needs scipy and matplotlib importable (their ``image_utils`` imports them)::

    python -m harness.eraft_reference /path/to/V2V --out tests/data/eraft_reference.json

With ``--compare`` it instead loads the authors' randomly initialised weights into the
trainer's ERAFT and prints the largest differences over a warm-started sequence of voxel
grids, in train and eval mode: flows, the warm-start flow carried to the next call, the
batch-norm running statistics and the gradients of an L1 loss on the sequence.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import sys

import torch

#: The authors' model parameters in config/train_v2v_eraft_10k.yaml.
AUTHORS_PARAMS = {"config": {"subtype": "warm_start"}, "n_first_channels": 5}


def authors_model(repo: str) -> torch.nn.Module:
    sys.path.insert(0, repo)
    from model.eraft.eraft import ERAFT

    torch.manual_seed(0)
    return ERAFT(**AUTHORS_PARAMS)


def listing(model: torch.nn.Module) -> dict:
    per_module: dict = {}
    for name, p in model.named_parameters():
        top = name.split(".")[0]
        per_module[top] = per_module.get(top, 0) + p.numel()
    return {"state_dict": {k: list(v.shape) for k, v in model.state_dict().items()},
            "parameters": sum(p.numel() for p in model.parameters()),
            "parameters_per_module": per_module}


def compare(ref: torch.nn.Module, steps: int = 4, size=(130, 150)) -> dict:
    """Largest |authors - ours| over ``steps`` pairs of a random (2, 5, *size) voxel sequence."""
    sys.path.insert(0, ".")
    from trainer.zoo import build_model

    ours = build_model("eraft", {"num_bins": 5, "subtype": "warm_start"})
    ours.load_state_dict(ref.state_dict())
    g = torch.Generator().manual_seed(1)
    vox = torch.randn(steps + 1, 2, 5, *size, generator=g)
    out = {}
    for mode in ("train", "eval"):
        for m in (ref, ours):
            getattr(m, mode)()
            m.reset_states()
            m.zero_grad(set_to_none=True)
        flow_d = init_d = 0.0
        loss_r = loss_o = 0.0
        for t in range(1, steps + 1):
            r, o = ref(vox[t - 1], vox[t]), ours(vox[t - 1], vox[t])
            flow_d = max(flow_d, float((r - o).abs().max()))
            init_d = max(init_d, float((ref.flow_init - ours.flow_init).abs().max()))
            loss_r, loss_o = loss_r + r.abs().mean(), loss_o + o.abs().mean()
        loss_r.backward()
        loss_o.backward()
        grads = dict(ours.named_parameters())
        grad_d = max(float((p.grad - grads[n].grad).abs().max()) for n, p in ref.named_parameters())
        bufs = dict(ours.named_buffers())
        buf_d = max(float((b.float() - bufs[n].float()).abs().max()) for n, b in ref.named_buffers())
        out[mode] = {"flow": flow_d, "warm_start_flow": init_d, "grad": grad_d, "buffers": buf_d}
        print(f"{mode}: max |authors - ours| over {steps} warm-started pairs: flow {flow_d:.3g}, "
              f"warm-start flow {init_d:.3g}, gradients {grad_d:.3g}, batch-norm buffers {buf_d:.3g}")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("repo", help="the authors' repository root (holds model/eraft/)")
    ap.add_argument("--compare", action="store_true")
    ap.add_argument("--out", help="write the listing here")
    a = ap.parse_args()
    ref = authors_model(a.repo)
    if a.compare:
        compare(ref)
        return
    out = {"source": "HYLZ-2019/V2V 62ce9c8 model/eraft, built by harness/eraft_reference.py",
           "params": AUTHORS_PARAMS, "eraft": listing(ref)}
    with open(a.out, "w") if a.out else contextlib.nullcontext(sys.stdout) as f:
        json.dump(out, f, indent=1)
        f.write("\n")


if __name__ == "__main__":
    main()

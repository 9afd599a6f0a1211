"""Derive tests/data/zoo_reference.json from the V2V authors' model code (HYLZ-2019/V2V).

The listing is what ``tests/test_trainer_zoo.py`` checks the trainer's E2VID, HyperE2VID and
ETNet (and the original E2VID++ checkpoints' ``FlowNet``, which ``trainer.checkpoints`` maps
onto the trainer's E2VID) against: every state-dict key with its shape, the trainable parameter count per top-level
module, and the values of HyperE2VID's Fourier-Bessel basis buffer (a constant computed from a
table of Bessel-function zeros). Models are built with the authors' training configs
``config/train_v2v_e2vid_10k.yaml``, ``config/train_v2v_hyper_10k.yaml`` and
``config/train_v2v_etnet_10k.yaml``; ``FlowNet`` with ``config/test_e2vid++_original.yaml``.

Run with a checkout (or ``git archive``) of the authors' repository, which needs scipy and
einops importable::

    python harness/zoo_reference.py /path/to/V2V --out tests/data/zoo_reference.json

With ``--compare`` it also loads the authors' randomly initialised weights into the trainer's
models and prints the largest output difference on a random voxel sequence (the check that
the key names and the forward pass agree), instead of writing the listing.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import sys

import torch

HYPER_KWARGS = dict(num_bins=5, skip_type="sum", recurrent_block_type="convlstm", kernel_size=5,
                    channel_multiplier=2, num_encoders=3, base_num_channels=32, num_residual_blocks=2,
                    use_upsample_conv=True, norm="none", num_output_channels=1, use_dynamic_decoder=True)
ETNET_KWARGS = dict(num_bins=5, norm="none")
E2VID_KWARGS = dict(num_bins=5, skip_type="sum", recurrent_block_type="convlstm", num_encoders=3, base_num_channels=32,
                    num_residual_blocks=2, use_upsample_conv=True, final_activation="", norm="none")
E2VIDPP_KWARGS = dict(num_bins=5, skip_type="sum", recurrent_block_type="convlstm", num_encoders=3,
                      base_num_channels=32, num_residual_blocks=2, use_upsample_conv=True, norm="none",
                      num_output_channels=3)


def authors_models(repo: str):
    sys.path.insert(0, repo)
    from model.eitr.eitr import EITR
    from model.hyper_model import HyperE2VID
    from model.model import E2VIDRecurrent, FlowNet

    torch.manual_seed(0)
    with contextlib.redirect_stdout(sys.stderr):  # their constructors print their settings
        return {"e2vid": E2VIDRecurrent(dict(E2VID_KWARGS)), "hypere2vid": HyperE2VID(dict(HYPER_KWARGS)),
                "etnet": EITR(dict(ETNET_KWARGS)), "e2vid++": FlowNet(dict(E2VIDPP_KWARGS))}


def listing(model: torch.nn.Module) -> dict:
    per_module: dict = {}
    for name, p in model.named_parameters():
        top = name.split(".")[1] if name.startswith(("unetrecurrent.", "unetflow.")) else name.split(".")[0]
        per_module[top] = per_module.get(top, 0) + p.numel()
    return {"state_dict": {k: list(v.shape) for k, v in model.state_dict().items()},
            "parameters": sum(p.numel() for p in model.parameters()),
            "parameters_per_module": per_module}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("repo", help="the authors' repository root (holds model/)")
    ap.add_argument("--compare", action="store_true")
    ap.add_argument("--out", help="write the listing here (their code prints to stdout, also at exit)")
    a = ap.parse_args()
    models = authors_models(a.repo)
    if a.compare:
        compare(models)
        return
    out = {"source": "HYLZ-2019/V2V 62ce9c8, built by harness/zoo_reference.py",
           "configs": {"e2vid": E2VID_KWARGS, "hypere2vid": HYPER_KWARGS, "etnet": ETNET_KWARGS,
                       "e2vid++": E2VIDPP_KWARGS}}
    for name, m in models.items():
        out[name] = listing(m)
    bases = models["hypere2vid"].unetrecurrent.decoders[0].dynamic_atom_generation.bases
    out["hypere2vid"]["bases"] = [[round(float(v), 7) for v in row] for row in bases]
    with open(a.out, "w") if a.out else contextlib.nullcontext(sys.stdout) as f:
        json.dump(out, f, indent=1)
        f.write("\n")


def compare(models) -> None:
    sys.path.insert(0, ".")
    from trainer.checkpoints import authors_state_dict, build_authors_model

    torch.manual_seed(1)
    vox = torch.randn(3, 2, 5, 48, 64)
    for name, ref in models.items():
        ours = build_authors_model(name)
        ours.load_state_dict(authors_state_dict(ref.state_dict(), name))
        ref.eval(), ours.eval()
        ref.reset_states()
        states, diff = None, 0.0
        with torch.no_grad():
            for t in range(vox.shape[0]):
                r = ref(vox[t])["image"][:, :1]
                o, states = ours(vox[t], states)
                diff = max(diff, float((r - o).abs().max()))
        print(f"{name}: max |authors - ours| over {vox.shape[0]} steps = {diff:.3g}")


if __name__ == "__main__":
    main()

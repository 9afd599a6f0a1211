"""The V2V authors' released checkpoint formats (HYLZ-2019/V2V ``ckpt_paths/*.txt``), loaded into
the trainer's networks.

Their checkpoints are ``torch.save({"state_dict": <the network's state dict>, ...})`` (their
``train.py``; the originals converted by ``scripts/convert_checkpoint_from_original.py``), keys
possibly prefixed by ``_orig_mod.`` (``torch.compile``) and ``module.`` (DDP), which their
``convert_to_compiled`` strips. The formats, by the name ``v2v-eval --model`` takes:

========== ======================================== ===========================================
name       their class (config)                     loads into
========== ======================================== ===========================================
e2vid      ``model.model.E2VIDRecurrent``           ``trainer.models.E2VIDRecurrent``, keys as
           (``train_v2v_e2vid_10k.yaml``)           they are
e2vid++    ``model.model.FlowNet``                  ``trainer.models.E2VIDPlusPlus``, keys
           (``test_e2vid++_original.yaml``)         ``unetflow.*`` -> ``unetrecurrent.*``
hypere2vid ``model.hyper_model.HyperE2VID``         ``trainer.models.HyperE2VID``, as they are
           (``train_v2v_hyper_10k.yaml``,
           ``test_hypere2vid_original.yaml``)
etnet      ``model.eitr.eitr.EITR``                 ``trainer.models.ETNet``, as they are
           (``train_v2v_etnet_10k.yaml``,
           ``test_etnet_original.yaml``)
evflow     ``model.model.EVFlowNet``                ``trainer.models.EVFlowNet``, as they are
           (``train_v2v_evflow_10k.yaml``)
========== ======================================== ===========================================

The HyperE2VID and ETNet baselines (``*_original``) are built by the authors with the same
classes and configs as their V2V retrainings, so they load the same way. Loading is strict:
a state dict that does not fit raises ``ValueError`` naming the file, the format and the
missing and unexpected keys (the authors' own test loads with ``strict=False``, which would
score a half-initialised network silently).
"""
from __future__ import annotations

from typing import Callable, Dict, Optional, Tuple

from dataclasses import asdict

import torch
import torch.nn as nn

from .models import E2VIDPlusPlus, E2VIDRecurrent, ETNet, EVFlowNet, HyperE2VID

__all__ = ["AUTHORS_FORMATS", "build_authors_model", "authors_state_dict", "detect_format", "is_authors_checkpoint",
           "load_authors_checkpoint"]

#: name -> (their class, the network built with the paper's configuration, key renames (prefix
#: of theirs -> prefix of ours), the trainer task whose metrics score it).
AUTHORS_FORMATS: Dict[str, Tuple[str, Callable[[], nn.Module], Tuple[Tuple[str, str], ...], str]] = {
    "e2vid": ("model.model.E2VIDRecurrent", E2VIDRecurrent, (), "e2vid"),
    "e2vid++": ("model.model.FlowNet", E2VIDPlusPlus, (("unetflow.", "unetrecurrent."),), "e2vid"),
    "hypere2vid": ("model.hyper_model.HyperE2VID", HyperE2VID, (), "hypere2vid"),
    "etnet": ("model.eitr.eitr.EITR", ETNet, (), "etnet"),
    "evflow": ("model.model.EVFlowNet", EVFlowNet, (), "evflow"),
}

#: A key that only each format has (checked in this order), for :func:`detect_format`.
_MARKERS = (("e2vid++", "unetflow.head.conv2d.weight"),
            ("hypere2vid", "unetrecurrent.decoders.0.dynamic_conv.bias"),
            ("etnet", "trans_encoder0.encoder.layers.0.self_attn.in_proj_weight"),
            ("evflow", "unet.encoders.0.conv2d.weight"),
            ("e2vid", "unetrecurrent.head.conv2d.weight"))


def _check_name(name: str) -> None:
    if name not in AUTHORS_FORMATS:
        raise ValueError(f"unknown checkpoint format {name!r}; known: {list(AUTHORS_FORMATS)}")


def build_authors_model(name: str) -> nn.Module:
    """The trainer's network for format ``name`` (a key of :data:`AUTHORS_FORMATS`) with the
    paper's configuration (its task's model section, ``trainer.config.TASK_SECTIONS``).
    Raises ``ValueError`` for another name."""
    from .config import TASK_SECTIONS

    _check_name(name)
    _, cls, _, task = AUTHORS_FORMATS[name]
    return cls(**asdict(TASK_SECTIONS[task]["model"]()))


def is_authors_checkpoint(ck) -> bool:
    """True for a loaded checkpoint in the authors' layout (a dict with ``state_dict`` and
    without this trainer's ``task`` and ``config``)."""
    return isinstance(ck, dict) and "state_dict" in ck and not ("task" in ck and "config" in ck)


def _strip(key: str) -> str:
    parts = key.split(".")
    if parts[0] == "_orig_mod":
        parts.pop(0)
    if parts[0] == "module":
        parts.pop(0)
    return ".".join(parts)


def detect_format(state_dict: Dict[str, torch.Tensor]) -> Optional[str]:
    """The format whose marker key the (prefix-stripped) ``state_dict`` holds, or None."""
    keys = {_strip(k) for k in state_dict}
    return next((name for name, marker in _MARKERS if marker in keys), None)


def authors_state_dict(state_dict: Dict[str, torch.Tensor], name: str) -> Dict[str, torch.Tensor]:
    """The authors' ``state_dict`` of format ``name`` renamed to the trainer's network's keys:
    ``_orig_mod.`` and ``module.`` prefixes stripped (their ``convert_to_compiled``), then the
    format's renames. Raises ``ValueError`` for an unknown format."""
    _check_name(name)
    renames = AUTHORS_FORMATS[name][2]
    out = {}
    for k, v in state_dict.items():
        k = _strip(k)
        for theirs, ours in renames:
            if k.startswith(theirs):
                k = ours + k[len(theirs):]
        out[k] = v
    return out


def load_authors_checkpoint(path: str, name: Optional[str], device: torch.device) -> Tuple[str, nn.Module]:
    """Load an authors' checkpoint file into the trainer's network.

    Args:
        path: the ``.pth`` file (``{"state_dict": ...}``).
        name: its format (a key of :data:`AUTHORS_FORMATS`), or None to detect it from the keys.
        device: where the network goes.

    Returns:
        ``(name, model in eval mode)``.

    Raises:
        ValueError: the file is not in the authors' layout, the format is unknown or cannot
            be detected, or the state dict does not fit the format's network (naming the file,
            the format, and the missing and unexpected keys or the shapes that differ).
    """
    ck = torch.load(path, map_location=device, weights_only=False)
    if not is_authors_checkpoint(ck):
        raise ValueError(f"{path}: not an authors' checkpoint (a dict with 'state_dict'); "
                         f"top-level keys: {sorted(ck)[:10] if isinstance(ck, dict) else type(ck).__name__}")
    sd = ck["state_dict"]
    if name is None:
        name = detect_format(sd)
        if name is None:
            raise ValueError(f"{path}: cannot tell the checkpoint's network from its keys (first: "
                             f"{list(sd)[:3]}); give its format, one of {list(AUTHORS_FORMATS)}")
    model = build_authors_model(name)
    mapped = authors_state_dict(sd, name)
    own = model.state_dict()
    missing = sorted(set(own) - set(mapped))
    unexpected = sorted(set(mapped) - set(own))
    shapes = [f"{k}: {tuple(mapped[k].shape)} vs {tuple(own[k].shape)}" for k in own
              if k in mapped and tuple(mapped[k].shape) != tuple(own[k].shape)]
    if missing or unexpected or shapes:
        raise ValueError(f"{path}: does not fit the {name!r} format ({AUTHORS_FORMATS[name][0]}): "
                         f"{len(missing)} missing key(s) {missing[:3]}, {len(unexpected)} unexpected "
                         f"{unexpected[:3]}, {len(shapes)} of another shape {shapes[:3]}")
    model.load_state_dict(mapped)
    return name, model.to(device).eval()

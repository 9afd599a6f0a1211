"""Trainer configuration: defaults per task, YAML files, and dotted command-line overrides.

Defaults follow the V2V paper's reference training configs (Lou et al., NeurIPS 2025):
Adam lr 1e-4 (amsgrad, no weight decay, constant), batch 12, sequences of 40 voxels of
5 bins, crop 128 (the server's defaults; the trainer checks what arrives).
"""
from __future__ import annotations

import copy
from typing import Any, Iterable, Optional

import yaml

from v2v_server.settings import YamlLoader, check_float, load_yaml

__all__ = ["DEFAULTS", "default_config", "load_config", "apply_overrides", "merge", "check_types"]

_COMMON = {
    "connect": "tcp://127.0.0.1:5555",
    "device": "auto",              # auto | cpu | cuda | cuda:N
    "out": "runs/{task}",
    "max_steps": 200000,
    "seed": 0,
    # connect may list several servers (shards): "tcp://a:5555,tcp://b:5555" (fan-in)
    # curve_keys: [client .key_secret file, server .key file] for a server that requires CurveZMQ
    "stream": {"credits": 4, "timeout_s": 60.0, "raw": True, "reconnect": False, "curve_keys": None},
    "optim": {"lr": 1.0e-4, "amsgrad": True, "weight_decay": 0.0, "clip_grad_norm": None},
    "amp": "fp32",                 # fp32 as the reference trains; bf16: autocast on CUDA (ignored on CPU)
    "log": {"image_every": 500, "checkpoint_every": 1000, "progress": True},
    "resume": None,                # path to a checkpoint, or "auto" = <out>/checkpoint_last.pt if present
}

DEFAULTS = {
    "e2vid": {
        **_COMMON,
        "task": "e2vid",
        "model": {"num_bins": 5, "base_num_channels": 32, "num_encoders": 3, "num_residual_blocks": 2,
                  "num_output_channels": 1, "skip_type": "sum", "kernel_size": 5},
        "loss": {
            "l1_weight": 1.0,
            "perceptual_weight": 1.0,       # LPIPS (VGG); 1 - SSIM when no LPIPS weights
            "lpips_net": "vgg",
            "lpips_weights": None,          # local file(s); see trainer/lpips_net.py
            "use_lpips_package": True,
            "tc_weight": 1.0,               # temporal consistency ("V+L1+H")
            "tc_alpha": 50.0,
            "tc_start_fraction": 0.5,       # frames 20..39 of 40
        },
    },
    "evflow": {
        **_COMMON,
        "task": "evflow",
        "model": {"num_bins": 5, "base_num_channels": 32, "num_encoders": 4, "num_residual_blocks": 2,
                  "num_output_channels": 2, "skip_type": "concat", "kernel_size": 3},
        "loss": {"flow_l1_weight": 1.0},
    },
}


def merge(base: dict, upd: dict) -> dict:
    """Recursive dict merge; ``upd`` wins. Returns a new dict."""
    out = copy.deepcopy(base)
    for k, v in (upd or {}).items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def default_config(task: str) -> dict:
    """A deep copy of the defaults of ``task`` ('e2vid' | 'evflow'); ``ValueError`` otherwise."""
    if task not in DEFAULTS:
        raise ValueError(f"task must be one of {sorted(DEFAULTS)}, got {task!r}")
    return copy.deepcopy(DEFAULTS[task])


def _check_keys(cfg: dict, ref: dict, prefix: str = ""):
    for k, v in cfg.items():
        if k not in ref:
            raise ValueError(f"unknown config key {prefix}{k!r}; known: {sorted(ref)}")
        if isinstance(v, dict) and isinstance(ref[k], dict) and k != "model":
            _check_keys(v, ref[k], prefix + k + ".")


#: keys whose default is None but which take a number when set
_OPTIONAL_FLOATS = {"optim.clip_grad_norm"}


def _as_float(v: Any, field: str) -> float:
    return check_float(f"config field {field!r}", v, positive=False)


def check_types(cfg: dict, ref: Optional[dict] = None, prefix: str = "") -> dict:
    """Check ``cfg`` against the types of the task defaults, in place, and return it.

    Floats accept ints (files and ``--set`` values are read with ``v2v_server.settings``'s
    YAML loader, so ``3e-4`` is a number) and are stored as ``float``; ints must be integers; booleans
    must be booleans. Keys whose default is None are not checked, except
    ``optim.clip_grad_norm`` (None or a number). The ``model`` section is checked when the
    model is built. Raises ``ValueError`` naming the dotted field.
    """
    if ref is None:
        ref = DEFAULTS.get(cfg.get("task"), DEFAULTS["e2vid"])
    for k, v in list(cfg.items()):
        field = prefix + k
        d = ref.get(k)
        if k == "model" and not prefix:
            continue
        if isinstance(d, dict):
            if not isinstance(v, dict):
                raise ValueError(f"config field {field!r} must be a mapping, got {v!r}")
            check_types(v, d, field + ".")
        elif field in _OPTIONAL_FLOATS:
            if v is not None:
                cfg[k] = _as_float(v, field)
        elif isinstance(d, bool):
            if not isinstance(v, bool):
                raise ValueError(f"config field {field!r} must be true or false, got {v!r}")
        elif isinstance(d, float):
            cfg[k] = _as_float(v, field)
        elif isinstance(d, int):
            if isinstance(v, bool) or not isinstance(v, int):
                raise ValueError(f"config field {field!r} must be an integer, got {v!r}")
    return cfg


def load_config(path: Optional[str] = None, task: Optional[str] = None) -> dict:
    """Load a YAML config over the task's defaults.

    The task comes from ``task`` if given, else the file's ``task:`` key, else 'e2vid'.
    Raises ``ValueError`` for unknown keys (model keys are checked when the model is built)
    and ``FileNotFoundError`` for a missing file.
    """
    user = dict(load_yaml(path)) if path else {}
    file_task = user.get("task")
    task = task or file_task or "e2vid"
    base = default_config(task)
    if file_task and file_task != task:
        # --task overrides a file written for the other task: its model and loss
        # sections do not apply, the new task's defaults are used instead.
        user.pop("model", None)
        user.pop("loss", None)
    user["task"] = task
    _check_keys(user, base)
    try:
        return check_types(merge(base, user))
    except ValueError as e:
        raise ValueError(f"{path}: {e}") if path else e


def _parse_value(s: str) -> Any:
    return yaml.load(s, Loader=YamlLoader)


def apply_overrides(cfg: dict, overrides: Iterable[str]) -> dict:
    """Apply ``key.sub=value`` strings (values parsed as YAML) to a copy of ``cfg``.
    Raises ``ValueError`` for a malformed item, an unknown key path or a value of the wrong
    type (see :func:`check_types`)."""
    cfg = copy.deepcopy(cfg)
    for item in overrides or ():
        if "=" not in item:
            raise ValueError(f"override must be key.path=value, got {item!r}")
        key, val = item.split("=", 1)
        parts = key.strip().split(".")
        node = cfg
        for p in parts[:-1]:
            if not isinstance(node.get(p), dict):
                raise ValueError(f"unknown config section {p!r} in override {item!r}")
            node = node[p]
        if parts[-1] not in node and parts[0] != "model":
            raise ValueError(f"unknown config key {key!r} in override {item!r}")
        node[parts[-1]] = _parse_value(val)
    return check_types(cfg)

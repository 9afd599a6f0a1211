"""The networks the trainer can build, by task name: E2VID and EV-FlowNet (``trainer.models``),
HyperE2VID (``trainer.hypere2vid``), ETNet (``trainer.etnet``) and E-RAFT (``trainer.eraft``),
the V2V paper's zoo."""
from __future__ import annotations

import inspect

import torch.nn as nn

from .eraft import ERAFT
from .etnet import ETNet
from .hypere2vid import HyperE2VID
from .models import E2VIDRecurrent, EVFlowNet

__all__ = ["MODELS", "build_model"]

#: Network class of each task.
MODELS = {"e2vid": E2VIDRecurrent, "evflow": EVFlowNet, "hypere2vid": HyperE2VID, "etnet": ETNet, "eraft": ERAFT}


def build_model(task: str, model_cfg: dict) -> nn.Module:
    """Build the network of ``task`` (a key of ``MODELS``) from the ``model:`` config section
    (keyword arguments of the class). Raises ``ValueError`` for an unknown task or unknown keys."""
    cls = MODELS.get(task)
    if cls is None:
        raise ValueError(f"task must be one of {list(MODELS)}, got {task!r}")
    known = set(inspect.signature(cls.__init__).parameters) - {"self"}
    unknown = sorted(set(model_cfg) - known)
    if unknown:
        raise ValueError(f"unknown model key(s) for {task}: {unknown}; known: {sorted(known)}")
    return cls(**model_cfg)

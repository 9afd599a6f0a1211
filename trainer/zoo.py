"""The networks the trainer can build, by task name: E2VID, EV-FlowNet, HyperE2VID, ETNet and
E-RAFT (one module each under ``trainer/models/``), the V2V paper's zoo."""
from __future__ import annotations

from dataclasses import asdict

import torch.nn as nn

from v2v_server.checks import check_keys

from .config import TASK_SECTIONS, ConfigError
from .models import ERAFT, E2VIDRecurrent, ETNet, EVFlowNet, HyperE2VID

__all__ = ["MODELS", "build_model"]

#: Network class of each task.
MODELS = {"e2vid": E2VIDRecurrent, "evflow": EVFlowNet, "hypere2vid": HyperE2VID, "etnet": ETNet, "eraft": ERAFT}


def build_model(task: str, model_cfg: dict) -> nn.Module:
    """Build the network of ``task`` (a key of ``MODELS``) from the ``model:`` config section:
    the task's model section (``trainer.config.TASK_SECTIONS[task]["model"]``, the one
    declaration of the network's parameters and their defaults) updated with ``model_cfg``,
    passed to the class as keyword arguments.

    Raises:
        ConfigError: (a ``ValueError``) for an unknown task, naming the unknown keys and the
            allowed ones, or for sizes the network refuses.
    """
    cls = MODELS.get(task)
    if cls is None:
        raise ConfigError(f"task must be one of {list(MODELS)}, got {task!r}")
    section = TASK_SECTIONS[task]["model"]
    try:
        check_keys(model_cfg, asdict(section()), f"model of {task}")
        return cls(**{**asdict(section()), **model_cfg})
    except ValueError as e:
        raise ConfigError(str(e)) from None

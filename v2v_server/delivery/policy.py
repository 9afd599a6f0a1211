"""Delivery settings: rows per batch, the plan's shuffle buffer, how long a worker may stay silent
on a task (the keys push delivery had are refused in one line: ``v2v_wire.push_names``).

``DeliveryPolicy`` is the one owner of these settings' defaults, help and checks
(``docs/config.md``'s delivery keys are generated from the fields made with ``setting``);
``ops.config.ServeConfig`` composes it.
"""
from __future__ import annotations

from dataclasses import dataclass

from v2v_server.checks import check_float, check_int
from v2v_server.settings import setting
from v2v_wire.plan import SHUFFLE_BUFFER

__all__ = ["DeliveryPolicy", "MAX_SHUFFLE_BUFFER"]

#: Most samples ``shuffle_buffer`` may name (a typo like ``100000`` is an error, not an OOM).
MAX_SHUFFLE_BUFFER = 4096


@dataclass(frozen=True)
class DeliveryPolicy:
    """How the plan is served (docs/delivery.md).

    Attributes:
        batch_size: rows per batch a reader asks for by default (its ``batch_size`` wins).
        task_timeout_s: seconds a worker may send nothing on a task before the task goes to
            another worker and the worker is replaced.
        shuffle_buffer: samples of the plan's shuffle buffer (``v2v_wire.plan.EpochPlan``, step
            2): part of the plan's identity, and the samples the server makes ahead of the fetches.

    Raises:
        ValueError: naming the field, for a value out of its range.
    """

    batch_size: int = setting(12, help="rows per batch a reader asks for when it names no batch size")
    task_timeout_s: float = setting(300.0, help="seconds a worker may send nothing on a task before the task goes "
                                                "to another worker and the worker is replaced",
                                    flag="--task-timeout")
    shuffle_buffer: int = setting(SHUFFLE_BUFFER, help="samples of the plan's shuffle buffer: each epoch's order "
                                                       "draws from the videos in an order of (seed, epoch), through "
                                                       "a buffer of this many samples (docs/shuffle.md); the server "
                                                       "makes this many samples ahead of the fetches")

    def __post_init__(self):
        check_int("batch_size", self.batch_size, 1)
        object.__setattr__(self, "task_timeout_s", check_float("task_timeout_s", self.task_timeout_s))
        check_int("shuffle_buffer", self.shuffle_buffer, 1, MAX_SHUFFLE_BUFFER, "samples")

"""Delivery settings: rows per batch, the plan's shuffle buffer, how long a worker may stay silent
on a task; and the keys push delivery had, which are refused in one line.

``DeliveryPolicy`` is the one owner of these settings' defaults, help and checks
(``docs/config.md``'s delivery keys are generated from the fields made with ``setting``);
``ops.config.ServeConfig`` composes it.
"""
from __future__ import annotations

from dataclasses import dataclass

from v2v_server.checks import check_float, check_int
from v2v_server.settings import setting
from v2v_wire.plan import SHUFFLE_BUFFER

__all__ = ["DeliveryPolicy", "REMOVED", "MAX_SHUFFLE_BUFFER", "removed_problem"]

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


#: Keys (and their flags) of push delivery, which v2v no longer has -> what to do instead. Given
#: in a config file or on the command line, each is refused in one line (:func:`removed_problem`).
REMOVED = {
    "delivery_mode": (("--delivery",), "delivery is by plan only: read the server with v2v_client.V2VStreamDataset"),
    "epochs": (("--epochs",), "the trainer owns its epochs: ds.set_epoch(e) for each, and stop when done"),
    "state_dir": (("--state-dir",), "a checkpoint is the trainer's position (batch['position'], ds.state_dict()); "
                                    "the server keeps no record of its readers"),
    "revoke_s": (("--revoke-timeout", "--revoke-s"), "a plan server hands out no batch to take back"),
    "lease_s": (("--lease",), "a plan server hands out no batch to take back"),
    "client_timeout_s": (("--client-timeout",), "a plan server keeps no session: a reader silent for an hour costs "
                                                "nothing"),
    "max_credits": (("--max-credits",), "a reader bounds what it asks with prefetch="),
    "end_grace_s": (("--end-grace-s",), "a plan server serves every epoch until it is stopped"),
    "heartbeat_s": (("--heartbeat-s",), "a plan server sends no heartbeats: a reader asks again what goes "
                                        "unanswered (retry_s=)"),
    "prefetch_batches": (("--prefetch-batches",), "the server makes shuffle_buffer samples ahead of the fetches"),
    "shuffle": (("--shuffle",), "every plan draws its order from (seed, epoch) through shuffle_buffer samples"),
}


def removed_problem(key: str) -> str:
    """One line for a key or flag of push delivery (a config key, or a flag such as ``--epochs``),
    or ``""`` for any other."""
    for name, (flags, instead) in REMOVED.items():
        if key == name or key in flags:
            return f"{flags[0]} ({name}) was push delivery's, which v2v no longer has: {instead} (docs/delivery.md)"
    return ""

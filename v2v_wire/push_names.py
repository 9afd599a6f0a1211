"""Push delivery's names, which v2v does not have (delivery is by plan, docs/delivery.md): the
one table of what each is refused with, and the line that refuses it.

Read by ``v2v-serve``'s configuration and command line (:data:`SERVER_KEYS`), the client
package's names (:data:`CLIENT_NAMES`), ``V2VStreamDataset``'s settings and resume states
(:data:`READER_SETTINGS`, :func:`resume_state_problem`), ``v2v-loadtest``'s flags
(:data:`LOADTEST_FLAGS`) and the wire's version check (:data:`OLDER_PROTOCOL`). Each refusal is
one line saying what to use instead. Standard library only: ``import v2v_client`` reads it
without torch.
"""
from __future__ import annotations

from typing import Iterable

__all__ = ["SERVER_KEYS", "TAKEN", "CLIENT_NAMES", "READER_SETTINGS", "LOADTEST_FLAGS", "OLDER_PROTOCOL",
           "server_key_problem", "client_name_problem", "reader_settings_problem", "resume_state_problem",
           "loadtest_flag_problem"]

#: ``v2v-serve``'s keys of push delivery (and their flags) -> what to do instead. Given in a config
#: file or on the command line, each is refused (:func:`server_key_problem`).
SERVER_KEYS = {
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

#: Keys of :data:`SERVER_KEYS` with the one value that is what every server does: taken, not refused.
TAKEN = {"delivery_mode": "plan"}

#: ``v2v_client``'s names of push delivery -> what to use instead (:func:`client_name_problem`).
CLIENT_NAMES = {
    "V2VPushDataset": "V2VStreamDataset",
    "StreamLoader": "torch's DataLoader(V2VStreamDataset(...), batch_size=None)",
    "ResumeState": "a batch's 'position' (V2VStreamDataset.state_dict / load_state_dict)",
    "PushServerError": "PlanServerError",
    "StreamError": "PlanServerError",
    "StreamTimeout": "TimeoutError",
    "dist_position": "V2VStreamDataset (its rank and world_size come from torch.distributed)",
}

#: ``V2VStreamDataset``'s keyword arguments of push delivery, which a plan reader has no use for
#: (:func:`reader_settings_problem`).
READER_SETTINGS = ("credits", "heartbeat_s", "reconnect", "reconnect_timeout_s", "group", "shm", "compact_flow")

#: ``v2v-loadtest``'s flags of push delivery -> what to do instead (:func:`loadtest_flag_problem`).
LOADTEST_FLAGS = {"--credits": "drop it"}

#: What the wire's version check adds for a peer of an older protocol (``protocol.version_problem``).
OLDER_PROTOCOL = "delivery is by plan only now: a push server or V2VPushDataset is gone, docs/delivery.md"


def _line(what: str, instead: str) -> str:
    return f"{what} was push delivery's, which v2v no longer has: {instead} (docs/delivery.md)"


def server_key_problem(key: str, value=None) -> str:
    """One line for ``v2v-serve``'s key or flag ``key`` (a config key such as ``epochs``, or a flag
    such as ``--epochs``) of push delivery given ``value``, or ``""`` for any other key and for
    the value :data:`TAKEN` takes."""
    for name, (flags, instead) in SERVER_KEYS.items():
        if key == name or key in flags:
            return "" if name in TAKEN and value == TAKEN[name] else _line(f"{flags[0]} ({name})", instead)
    return ""


def client_name_problem(name: str) -> str:
    """One line for ``v2v_client``'s name ``name`` of push delivery, or ``""`` for any other."""
    if name not in CLIENT_NAMES:
        return ""
    return f"v2v_client.{name} was removed with push delivery: use {CLIENT_NAMES[name]} (docs/delivery.md)"


def reader_settings_problem(settings: Iterable[str]) -> str:
    """One line for ``V2VStreamDataset`` settings of push delivery among ``settings`` (all of
    them named), or ``""`` when there are none."""
    given = sorted(s for s in settings if s in READER_SETTINGS)
    if not given:
        return ""
    return f"{', '.join(given)}: setting(s) of push delivery, which v2v no longer has (docs/delivery.md): drop them"


def resume_state_problem(state) -> str:
    """One line for a resume state of push delivery (a dict listing the samples it ``delivered``,
    without a plan), saying what to resume from; ``""`` for anything else."""
    if not (isinstance(state, dict) and "delivered" in state and "plan" not in state):
        return ""
    return (f"a resume state of push delivery, which v2v no longer has (consumer {state.get('consumer')!r}, "
            f"completed epoch {state.get('completed_epoch')!r}) is not a plan's position: resume from a batch's "
            "'position', or read an epoch from its start with set_epoch()")


def loadtest_flag_problem(flag: str) -> str:
    """One line for ``v2v-loadtest``'s flag ``flag`` of push delivery, or ``""`` for any other."""
    return _line(flag, LOADTEST_FLAGS[flag]) if flag in LOADTEST_FLAGS else ""

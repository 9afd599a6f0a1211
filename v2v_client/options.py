"""What one consumer's stream asks a server for and how it talks to it: :class:`StreamOptions`,
the one object the dataset, the per-server stream and its connection read their settings from.
"""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from typing import Optional, Tuple

from v2v_wire.codecs import COMPRESSIONS, available
from v2v_wire.protocol import is_loopback

__all__ = ["StreamOptions", "AUTO_REMOTE", "job_group", "LAUNCHER_VARIABLES"]

#: What launchers set that tells one job from another on a host: torchrun's (and accelerate
#: launch's) run id and rendezvous endpoint, Lightning's and Ray Train's ``MASTER_ADDR`` /
#: ``MASTER_PORT``, Slurm's job and step.
LAUNCHER_VARIABLES = ("TORCHELASTIC_RUN_ID", "MASTER_ADDR", "MASTER_PORT", "SLURM_JOB_ID", "SLURM_STEP_ID")


def job_group(environ=os.environ) -> str:
    """The DDP group a job's ranks read as when ``group=`` is not given: named from what its
    launcher set (``LAUNCHER_VARIABLES``), the same for every rank of one job and for its elastic
    restarts, different for two jobs on one host (they need different rendezvous ports);
    ``"default"`` when no launcher set any (ranks started by hand: a second job then finds the
    group's ranks read, and is refused with a line saying to set ``group=``)."""
    seen = [f"{k}={environ[k]}" for k in LAUNCHER_VARIABLES if environ.get(k)]
    if not seen:
        return "default"
    return "job-" + hashlib.blake2b("\n".join(seen).encode(), digest_size=8).hexdigest()

#: Compression ``compression="auto"`` asks servers on other hosts for (docs/wire.md measures it:
#: 6.3x fewer bytes per default sample, decompressed at about 1.2 GB/s per core).
AUTO_REMOTE = "zstd"


def auto_compression(endpoint: str, server_codecs=COMPRESSIONS) -> str:
    """What ``compression="auto"`` asks of ``endpoint``: none for ``ipc://``, ``inproc://`` and
    loopback ``tcp://`` (bytes cost less than compressing them), ``AUTO_REMOTE`` across hosts when
    its library is installed here and the server has it (``server_codecs``), else none."""
    remote = not is_loopback(endpoint) and available(AUTO_REMOTE) and AUTO_REMOTE in server_codecs
    return AUTO_REMOTE if remote else "none"


@dataclass(frozen=True, kw_only=True)
class StreamOptions:
    """What a stream asks a server for and how it talks to it (validated by
    ``V2VPushDataset``; the seconds made floats, ``curve_keys`` a tuple or None, here; see
    its arguments for each field's meaning and unit: ``outputs``,
    ``credits`` (batches), ``timeout_s`` / ``heartbeat_s`` / ``reconnect_timeout_s``
    (seconds), ``raw``, ``reconnect``, ``curve_keys`` (key file paths), DDP ``rank`` /
    ``world_size`` / ``group``, ``shm`` (True, False or ``"auto"``), ``compact_flow``,
    ``compression``)."""

    outputs: Tuple[str, ...]
    credits: int
    timeout_s: float
    heartbeat_s: float
    raw: bool
    reconnect: bool
    reconnect_timeout_s: float
    curve_keys: Optional[Tuple[str, str]]
    rank: int
    world_size: int
    group: Optional[str]
    shm: object
    compact_flow: bool = False
    compression: str = "auto"

    def __post_init__(self):
        _set = object.__setattr__  # frozen: normalised once, here
        for name in ("timeout_s", "heartbeat_s", "reconnect_timeout_s"):
            _set(self, name, float(getattr(self, name)))
        _set(self, "reconnect", bool(self.reconnect))
        _set(self, "curve_keys", tuple(self.curve_keys) if self.curve_keys else None)

    def wants_shm(self, endpoint: str) -> bool:
        """Whether a connection to ``endpoint`` asks for batches through the server's shared
        memory: ``shm=True`` always (the server agrees only when bound to ``ipc://``),
        ``"auto"`` for ``ipc://`` endpoints (the server is on this host)."""
        return self.shm is True or (self.shm == "auto" and endpoint.startswith("ipc://"))

    def compression_for(self, endpoint: str) -> Tuple[str, bool]:
        """The compression a connection to ``endpoint`` asks for, and whether it was chosen by
        default (``"auto"``: none for ``ipc://``, ``inproc://`` and loopback ``tcp://``, where
        bytes cost less than compressing them; ``AUTO_REMOTE`` across hosts when its library
        is installed)."""
        if self.compression != "auto":
            return self.compression, False
        return auto_compression(endpoint), True

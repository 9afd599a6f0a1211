"""What a server serving by plan keeps of the manifests it served (docs/delivery.md, "A corpus that
changed"), so that a position taken under an earlier manifest of the same listing is refused
naming the files that changed, not only the fingerprints.

A record is one file per manifest, ``cache_dir/plans/PATHS/FINGERPRINT.tags``: ``PATHS`` the
listing's ``Manifest.paths_fingerprint`` (its videos and crops per window), ``FINGERPRINT`` the
manifest's (its videos' tags too), holding each video's tag digest (:func:`tag_digests`) in the
manifest's order. 4 bytes a video (4 MB for a million), read and compared with numpy at start.
The digest only names what changed; whether a position is refused is the manifest's fingerprint's
word (SHA-256 over every tag).
The last :data:`RECORDS_KEPT` manifests of a listing are kept.
"""
from __future__ import annotations

import logging
import os
import zlib
from pathlib import Path
from typing import Dict

import numpy as np

from v2v_wire.plan import Manifest

log = logging.getLogger("v2v.server")

#: Manifests of one listing whose records a host keeps (the most recently served).
RECORDS_KEPT = 8

#: Files named in the line that says what changed (the rest are counted).
NAMED = 3


def tag_digests(manifest: Manifest) -> np.ndarray:
    """uint32 (videos,): the CRC-32 of each video's tag (``"-"`` for None), in the manifest's
    order, little-endian.

    Raises:
        ValueError: the manifest has no tags."""
    if not manifest.tags:
        raise ValueError("manifest: no tags to record")
    return np.fromiter((zlib.crc32(("-" if t is None else t).encode()) for t in manifest.tags), dtype="<u4",
                       count=len(manifest.tags))


def plan_changes(cache_dir: str, manifest: Manifest) -> Dict[str, str]:
    """Record ``manifest`` under ``cache_dir`` and say, for each earlier manifest of the same
    listing recorded there, what changed since: ``{fingerprint: "1 file changed its size or
    modification time since: bikes.mp4"}`` (``PlanIdentity.changes``). Empty for a manifest
    without tags. A record that cannot be read or kept is named in one warning and left out:
    a position of that manifest is still refused, naming the fingerprints only."""
    if not manifest.tags:
        return {}
    folder = Path(cache_dir) / "plans" / manifest.paths_fingerprint()
    mine, digests, changes = manifest.fingerprint(), tag_digests(manifest), {}
    try:
        folder.mkdir(parents=True, exist_ok=True)
        records = sorted(folder.glob("*.tags"), key=lambda p: p.stat().st_mtime_ns, reverse=True)
        for path in records:
            if path.stem == mine:
                continue
            old = np.fromfile(path, dtype="<u4")
            if old.shape != digests.shape:
                log.warning("%s: %d tag(s), the listing has %d: not read", path, old.size, digests.size)
                continue
            changed = np.flatnonzero(old != digests)
            names = ", ".join(manifest.slots[i][0] for i in changed[:NAMED])
            more = f" and {len(changed) - NAMED} more" if len(changed) > NAMED else ""
            changes[path.stem] = f"{len(changed)} file(s) changed their size or modification time since: {names}{more}"
        own = folder / f"{mine}.tags"
        if not own.exists():
            tmp = folder / f".{mine}.{os.getpid()}.tmp"
            digests.tofile(tmp)
            os.replace(tmp, own)
        os.utime(own)  # the most recently served: kept longest
        for path in [p for p in records if p.stem != mine][RECORDS_KEPT - 1:]:
            path.unlink(missing_ok=True)
    except OSError as e:
        log.warning("%s: cannot keep this plan's record (%s): a position taken under an earlier manifest of "
                    "this listing is refused without naming the files that changed", folder, e.strerror or e)
    return changes

"""Which videos of a listing a server serves: the bundled demo corpus served when none is given,
static sharding over hosts (``--shard I/N``), and the fingerprint of a listing that servers
sharding one corpus compare."""
from __future__ import annotations

import hashlib
from pathlib import Path
from typing import List


#: The bundled demo corpus (see sample_videos/SOURCES.md): served when no corpus is given.
SAMPLE_VIDEOS = Path(__file__).resolve().parents[1] / "sample_videos"


def shard_of(rel_path: str, count: int) -> int:
    """The shard (0 .. count - 1) that serves the video at ``rel_path`` (POSIX, relative to the
    corpus root).

    A stable hash: the first 8 bytes of BLAKE2b(``rel_path`` as UTF-8), big-endian, modulo
    ``count``. It depends on nothing but the path (not on Python's per-process ``hash``
    salt, the host or the order of the scan), so N servers started with ``--shard 0/N`` ..
    ``--shard N-1/N`` on copies of one corpus split it into disjoint parts that together
    hold every file once. Content is untouched: a sample stays a function of (seed, epoch,
    sample id), whichever shard serves it.
    """
    if count < 1:
        raise ValueError(f"shard count must be >= 1, got {count}")
    digest = hashlib.blake2b(rel_path.encode("utf-8"), digest_size=8).digest()
    return int.from_bytes(digest, "big") % count


def select_shard(videos: List[str], index: int, count: int) -> List[str]:
    """The videos of ``videos`` (relative POSIX paths) that shard ``index`` of ``count`` serves,
    in their original order (see ``shard_of``)."""
    if not 0 <= index < count:
        raise ValueError(f"shard index must be in [0, {count}), got {index}")
    if count == 1:
        return list(videos)
    return [v for v in videos if shard_of(v, count) == index]


def corpus_fingerprint(videos: List[str]) -> str:
    """A short hash of a corpus listing (relative POSIX paths, any order): servers sharding one
    corpus must have listed the same files, or a file only one of them sees may fall in the
    other's shard and never be served."""
    h = hashlib.sha256()
    for v in sorted(videos):
        h.update(v.encode("utf-8") + b"\n")
    return h.hexdigest()[:16]

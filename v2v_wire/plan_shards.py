"""One plan over several servers, each serving one shard of the corpus (``v2v-serve --shard I/N``):
the shards' plans interleaved. Global position ``t`` is shard ``t mod N``'s position ``t // N``.

Each shard's plan is a pure function of its own manifest (a server knows only its videos), so the
interleave is a pure function of the shards' plans: every sample has one global position, the
sequence is the same at any world size and under any timing, and a position resumes it. A shard
whose epoch is shorter than another's leaves padding rows (``N`` times the longest shard's
samples, less the total: shards of a hashed corpus differ by a few percent). Pure, numpy-free.
"""
from __future__ import annotations

import hashlib
from typing import Dict, List, Optional, Sequence, Tuple

from .plan import PlanIdentity, PlanMismatch

__all__ = ["shard_ranges", "shard_parts", "interleaved", "shards_samples", "epoch_floor", "step_in_epoch", "probes",
           "furthest_slot", "shards_identity"]


def shard_ranges(start: int, stop: int, shards: int) -> List[Tuple[int, int]]:
    """Global positions ``start .. stop - 1`` as each shard's own positions: for shard ``i``,
    ``[lo, hi)`` (empty when ``lo == hi``: fewer rows than shards)."""
    return [(-(-(start - i) // shards), -(-(stop - i) // shards)) for i in range(shards)]


def shard_parts(start: int, stop: int, shards: int) -> Dict[int, Tuple[int, int]]:
    """The shards a fetch of global positions ``start .. stop - 1`` is asked of: shard -> its own
    ``[lo, hi)`` (:func:`shard_ranges`), for each shard holding at least one of them, in shard order."""
    return {k: (lo, hi) for k, (lo, hi) in enumerate(shard_ranges(start, stop, shards)) if hi > lo}


def interleaved(start: int, stop: int, shards: int) -> List[Tuple[int, int]]:
    """``(shard, row of that shard's part)`` of each global position ``start .. stop - 1``, in
    order; a shard's part holds its rows of :func:`shard_ranges`."""
    ranges = shard_ranges(start, stop, shards)
    return [(t % shards, t // shards - ranges[t % shards][0]) for t in range(start, stop)]


def shards_samples(samples: Sequence[Optional[int]]) -> Optional[int]:
    """The interleaved epoch's length, padding included (one past the last position that holds a
    sample), from each shard's samples; None while any shard's is not known."""
    if any(s is None for s in samples):
        return None
    n = len(samples)
    return max(((s - 1) * n + i + 1 for i, s in enumerate(samples) if s > 0), default=0)


def epoch_floor(samples: Sequence[Optional[int]]) -> int:
    """A lower bound of the interleaved epoch's length from the shards whose samples are known
    (None: not known yet): one past the last position of theirs that holds a sample; the length
    itself once every shard's is known (:func:`shards_samples`)."""
    n = len(samples)
    return max(((s - 1) * n + i + 1 for i, s in enumerate(samples) if s), default=0)


def step_in_epoch(first: int, samples: Sequence[Optional[int]], seen: int) -> Optional[bool]:
    """Whether a step whose positions (every rank's) start at global position ``first`` lies in the
    interleaved epoch: True once some position at or after ``first`` is known to hold a sample
    slot (``seen``: one past the furthest position a reader got a row with a sample id at, or
    0), False once every shard's ``samples`` is known and none does, None while that depends on
    shards not known yet (ask each of them for the row :func:`probes` names).

    Every rank decides each step so, from what it read: a rank reading some shards only ends
    the epoch at the step the others end it at."""
    if max(seen, epoch_floor(samples)) > first:
        return True
    return False if all(s is not None for s in samples) else None


def probes(first: int, samples: Sequence[Optional[int]]) -> List[Tuple[int, int]]:
    """``(shard, its position)`` to ask of each shard whose samples are not known, to settle
    :func:`step_in_epoch` for ``first``: the shard's first position at or after global ``first``.
    A row with a sample id there puts the step in the epoch; a row past the shard's end comes
    with its samples (the server answers past the end once it knows where that is)."""
    n = len(samples)
    return [(k, max(0, -(-(first - k) // n))) for k, s in enumerate(samples) if s is None]


def furthest_slot(seen: int, shard: int, shards: int, start: int, sample_ids: Sequence[Optional[object]]) -> int:
    """``seen`` (one past the furthest global position a reader got a row with a sample id at, or
    0) after rows of ``shard`` (of ``shards``) from its own position ``start`` on, whose ids are
    ``sample_ids`` (None: a row past that shard's end): what :func:`step_in_epoch` takes."""
    slots = [(start + j) * shards + shard + 1 for j, sid in enumerate(sample_ids) if sid is not None]
    return max([seen] + slots)


def shards_identity(identities: Sequence[PlanIdentity]) -> PlanIdentity:
    """The interleaved plan's identity: the shards' recipe, seed, shuffle buffer and version, and a
    manifest fingerprint of theirs in shard order (one shard: its own identity).

    Raises:
        PlanMismatch: shards with different recipes, seeds, shuffle buffers or plan versions
            (one line naming the field and each shard's value)."""
    if len(identities) == 1:
        return identities[0]
    for field in ("version", "recipe", "seed", "shuffle_buffer"):
        values = [getattr(p, field) for p in identities]
        if len(set(values)) > 1:
            raise PlanMismatch(f"the shards' plans differ in {field}: " + ", ".join(
                f"shard {i}: {v}" for i, v in enumerate(values)))
    h = hashlib.blake2b(digest_size=8)
    for p in identities:
        h.update(p.manifest.encode() + b"/")
    first = identities[0]
    return PlanIdentity(f"{len(identities)}x{h.hexdigest()}", first.recipe, first.seed, first.shuffle_buffer,
                        first.version)

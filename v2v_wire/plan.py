"""Delivery by plan, pure: an epoch's sequence of samples as a function of (manifest, mixing, seed,
epoch), each rank's batch at each step as a fixed slice of it, and a checkpoint as a position.

The contract (docs/plan.md):

* **The manifest** (:class:`Manifest`) is what a plan knows of a corpus: each video's *slots*
  (its windows per epoch, or an upper bound of them) and ``crops_per_window``. Its fingerprint,
  with the recipe's and :data:`PLAN_VERSION`, is the plan's identity (:class:`PlanIdentity`).
* **The epoch's sequence** (:class:`EpochPlan`) is built in two pure steps:

  1. the *production order*: the videos in :func:`video_order` (a BLAKE2b key of
     ``(seed, epoch, path)`` each), each video's samples in the order a decode makes them
     (window, then crop);
  2. a shuffle buffer of ``shuffle_buffer`` samples over it, as ``tf.data``'s: the buffer fills
     from the production order, and each position takes the buffer's element at an index drawn
     from ``(seed, epoch, position)`` (SplitMix64 on uint64, the same on every platform and numpy
     version), the production order's next sample taking its place.

  Position ``t`` is thus one of the production order's first ``t + shuffle_buffer`` samples
  (:meth:`EpochPlan.made_by`): what a server must have made to serve it, so it holds at most a
  buffer's samples beyond those it serves.
* **Ranks and steps**: at world size ``n`` and per-rank batch size ``b``, rank ``r``'s batch at
  step ``s`` of an epoch started at position ``p0`` is the positions
  ``p0 + (s * n + r) * b`` .. ``+ b``. Every rank has :meth:`EpochPlan.steps` steps; positions
  past the epoch's last sample are *padding* rows (no sample: ``None`` keys).
* **A checkpoint is a position** (:class:`Position`): the plan's identity, the epoch and the
  number of the epoch's samples every rank together consumed. It is the same on every rank and
  resumes at any world size and batch size: the next step starts at that position.

Nothing here owns a socket, a clock or a process; needs numpy only.
``tests/test_plan.py`` checks the contract's properties on random manifests.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Iterable, List, Mapping, Optional, Tuple

import numpy as np

from v2v_wire.ids import SampleKey

__all__ = ["PLAN_VERSION", "SHUFFLE_BUFFER", "video_order", "Manifest", "PlanIdentity", "EpochPlan", "Position",
           "PlanMismatch", "distinct_videos"]

#: The version of the rules above: a plan of another version gives another sequence, so a
#: position taken under it is refused (:meth:`PlanIdentity.problem`).
PLAN_VERSION = 1

#: Default samples the shuffle buffer holds (step 2): ``DeliveryPolicy.shuffle_buffer``'s default.
SHUFFLE_BUFFER = 64

_MASK = np.uint64(0xFFFFFFFFFFFFFFFF)


class PlanMismatch(ValueError):
    """A position, a plan or a request names another plan than the one at hand: the message is
    one line naming what differs (manifest, recipe, seed, shuffle buffer, version)."""


def video_order(videos: Iterable[str], seed: int, epoch: int) -> List[str]:
    """``videos`` permuted for ``epoch``: sorted by a BLAKE2b hash of ``(seed, epoch, path)``.

    The key of a video depends only on its own path, so the order of any subset (a shard) is
    the global order restricted to it, and every host draws the same order.

    Args:
        videos: corpus-relative paths (str); duplicates keep their relative order.
        seed, epoch: non-negative ints.
    Returns:
        A new list holding the same paths.
    """
    base = hashlib.blake2b(f"{seed}/{epoch}/".encode(), digest_size=8)

    def key(v: str) -> bytes:  # the hash of f"{seed}/{epoch}/{v}", its prefix hashed once
        h = base.copy()
        h.update(v.encode())
        return h.digest()

    return sorted(videos, key=key)


def _splitmix64(x: np.ndarray) -> np.ndarray:
    """SplitMix64's finaliser over a uint64 array (a bijection of uint64; wraps modulo 2**64)."""
    with np.errstate(over="ignore"):
        z = (x + np.uint64(0x9E3779B97F4A7C15)) & _MASK
        z = ((z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)) & _MASK
        z = ((z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)) & _MASK
        return z ^ (z >> np.uint64(31))


def _seed_key(seed: int, epoch: int) -> np.uint64:
    return np.uint64(int.from_bytes(hashlib.blake2b(f"plan/{seed}/{epoch}".encode(), digest_size=8).digest(), "little"))


@dataclass(frozen=True)
class Manifest:
    """What a plan knows of a corpus: each video's slots and the crops per window.

    Attributes:
        slots: ``((video, slots), ...)`` sorted by video: corpus-relative POSIX paths, each
            with the windows it gives per epoch (or an upper bound; a slot its decode does not
            fill is a padding row). Videos with 0 slots are kept (they name the listing) but
            give no sample.
        crops_per_window: samples per window (K >= 1).

    Build with :meth:`of`, which sorts and checks.
    """

    slots: Tuple[Tuple[str, int], ...]
    crops_per_window: int = 1

    @classmethod
    def of(cls, slots: Mapping[str, int], crops_per_window: int = 1) -> "Manifest":
        """The manifest of ``{video: slots}``.

        Raises:
            ValueError: a video that is not a non-empty str, slots that are not an int >= 0,
                or ``crops_per_window`` < 1, naming it.
        """
        if not isinstance(crops_per_window, int) or isinstance(crops_per_window, bool) or crops_per_window < 1:
            raise ValueError(f"manifest: crops_per_window must be an int >= 1, got {crops_per_window!r}")
        for v, n in slots.items():
            if not isinstance(v, str) or not v:
                raise ValueError(f"manifest: a video must be a non-empty path, got {v!r:.80}")
            if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 0:
                raise ValueError(f"manifest: slots of {v!r} must be an int >= 0, got {n!r}")
        return cls(tuple(sorted((v, int(n)) for v, n in slots.items())), crops_per_window)

    @property
    def samples(self) -> int:
        """Samples an epoch lists: the slots times ``crops_per_window``."""
        return sum(n for _, n in self.slots) * self.crops_per_window

    def fingerprint(self) -> str:
        """A short hash (16 hex digits) of the videos, their slots and the crops per window."""
        h = hashlib.sha256(f"crops={self.crops_per_window}\n".encode())
        for v, n in self.slots:
            h.update(f"{n} {v}\n".encode())
        return h.hexdigest()[:16]


@dataclass(frozen=True)
class PlanIdentity:
    """What decides an epoch's sequence besides ``(seed, epoch)``: the manifest's fingerprint,
    the recipe's (``SampleRecipe.fingerprint``: what decides a sample's content), the seed, the
    shuffle buffer and :data:`PLAN_VERSION`. Two plans with equal identities and seeds give the same
    sequences."""

    manifest: str
    recipe: str
    seed: int
    shuffle_buffer: int = SHUFFLE_BUFFER
    version: int = PLAN_VERSION

    def to_dict(self) -> dict:
        """A plain, msgpack/JSON-safe dict (:meth:`from_dict` reads it)."""
        return {"manifest": self.manifest, "recipe": self.recipe, "seed": self.seed,
                "shuffle_buffer": self.shuffle_buffer, "version": self.version}

    @classmethod
    def from_dict(cls, d) -> "PlanIdentity":
        """The identity of :meth:`to_dict` output.

        Raises:
            PlanMismatch: not a dict of those keys with the right types, naming the field.
        """
        if not isinstance(d, Mapping):
            raise PlanMismatch(f"plan identity must be a mapping, got {type(d).__name__}")
        kinds = {"manifest": str, "recipe": str, "seed": int, "shuffle_buffer": int, "version": int}
        for k, t in kinds.items():
            if not isinstance(d.get(k), t) or isinstance(d.get(k), bool):
                raise PlanMismatch(f"plan identity field {k!r} must be {t.__name__}, got {d.get(k)!r:.80}")
        return cls(**{k: d[k] for k in kinds})

    def problem(self, other: "PlanIdentity") -> Optional[str]:
        """``None`` when ``other`` names this plan, else one line naming every field that
        differs, ``other``'s value first (``"recipe abc... (this plan: def...)"``)."""
        diffs = [f"{k} {getattr(other, k)} (this plan: {getattr(self, k)})"
                 for k in ("version", "manifest", "recipe", "seed", "shuffle_buffer")
                 if getattr(other, k) != getattr(self, k)]
        return None if not diffs else "another plan: " + ", ".join(diffs)


class EpochPlan:
    """One epoch's sequence of samples (module docstring: steps 1 and 2), held as two arrays.

    Args:
        manifest: the corpus's slots.
        seed, epoch: ints >= 0.
        shuffle_buffer: samples the shuffle buffer holds (>= 1; 1 keeps the production order).

    Attributes:
        videos: the manifest's videos with slots, in this epoch's :func:`video_order`.
        video_index: int64 (N,): each position's index into :attr:`videos`.
        ordinal: int64 (N,): each position's sample number in its video (``SampleKey.ordinal``).
        production: int64 (N,): each position's index in the production order.

    Raises:
        ValueError: a negative seed or epoch, or a shuffle buffer < 1, naming it.
    """

    def __init__(self, manifest: Manifest, seed: int, epoch: int, shuffle_buffer: int = SHUFFLE_BUFFER):
        for name, v, low in (("seed", seed, 0), ("epoch", epoch, 0), ("shuffle_buffer", shuffle_buffer, 1)):
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < low:
                raise ValueError(f"plan: {name} must be an int >= {low}, got {v!r}")
        self.manifest, self.seed, self.epoch = manifest, int(seed), int(epoch)
        self.shuffle_buffer = int(shuffle_buffer)
        slots = dict(manifest.slots)
        self.videos = video_order((v for v, n in manifest.slots if n), seed, epoch)
        k = manifest.crops_per_window
        counts = np.array([slots[v] * k for v in self.videos], dtype=np.int64)
        vid = np.repeat(np.arange(len(counts), dtype=np.int64), counts)
        self.production = self._shuffle(len(vid))
        self.video_index = vid[self.production]
        self.ordinal = (self.production - np.repeat(np.cumsum(counts) - counts, counts)[self.production])

    def _shuffle(self, n: int) -> np.ndarray:
        """The production index each position takes (step 2)."""
        m = self.shuffle_buffer
        if m == 1 or n == 0:
            return np.arange(n, dtype=np.int64)
        draws = _splitmix64(np.arange(n, dtype=np.uint64) ^ _seed_key(self.seed, self.epoch)).tolist()
        out = [0] * n
        buf = list(range(min(m, n)))
        nxt = len(buf)
        for t in range(n):
            j = draws[t] % len(buf)
            out[t] = buf[j]
            if nxt < n:
                buf[j] = nxt
                nxt += 1
            else:
                buf[j] = buf[-1]
                buf.pop()
        return np.array(out, dtype=np.int64)

    def __len__(self) -> int:
        """Samples in the epoch (no padding)."""
        return len(self.video_index)

    def key(self, position: int) -> Optional[SampleKey]:
        """The sample at ``position`` (0-based), or ``None`` for a padding row (``position`` at or
        past :func:`len`)."""
        if position < 0:
            raise IndexError(f"plan position must be >= 0, got {position}")
        if position >= len(self):
            return None
        return SampleKey.at(self.videos[self.video_index[position]], int(self.ordinal[position]),
                            self.manifest.crops_per_window)

    def keys(self, start: int, stop: int) -> List[Optional[SampleKey]]:
        """:meth:`key` of each position in ``start`` .. ``stop - 1``."""
        return [self.key(p) for p in range(start, stop)]

    def made_by(self, position: int) -> int:
        """How many samples of the production order a server must have made (in that order) to
        serve every position up to ``position``: ``min(N, position + shuffle_buffer)``."""
        return min(len(self), position + self.shuffle_buffer)

    def steps(self, world_size: int, batch_size: int, start: int = 0) -> int:
        """Steps every rank takes from position ``start`` to the epoch's end:
        ``ceil((len - start) / (world_size * batch_size))`` (0 when nothing is left).

        Raises:
            ValueError: ``world_size`` or ``batch_size`` < 1, or ``start`` < 0.
        """
        _check_layout(world_size, batch_size, start)
        return max(0, -(-(len(self) - start) // (world_size * batch_size)))

    def batch_positions(self, step: int, rank: int, world_size: int, batch_size: int, start: int = 0) -> range:
        """The positions of rank ``rank``'s batch at step ``step`` from ``start``:
        ``start + (step * world_size + rank) * batch_size`` and the ``batch_size - 1`` after it.
        Positions at or past :func:`len` are padding rows.

        Raises:
            ValueError: a layout :meth:`steps` refuses, or ``rank`` outside 0 .. ``world_size - 1``,
                or ``step`` < 0.
        """
        _check_layout(world_size, batch_size, start)
        if not 0 <= rank < world_size or step < 0:
            raise ValueError(f"plan: rank {rank} of world size {world_size}, step {step}: out of range")
        first = start + (step * world_size + rank) * batch_size
        return range(first, first + batch_size)


def _check_layout(world_size: int, batch_size: int, start: int) -> None:
    if world_size < 1 or batch_size < 1 or start < 0:
        raise ValueError(f"plan: world_size and batch_size must be >= 1 and start >= 0, "
                         f"got {world_size}, {batch_size}, {start}")


@dataclass(frozen=True)
class Position:
    """A checkpoint: the plan it was taken under, the epoch, and how many of the epoch's
    positions (padding rows included) every rank together consumed. The same on every rank;
    it resumes at any world size and batch size (the next step starts at ``sample_in_epoch``).

    Attributes:
        plan: the plan's identity.
        epoch: int >= 0.
        sample_in_epoch: int >= 0: the next position of ``epoch`` to read.
    """

    plan: PlanIdentity
    epoch: int = 0
    sample_in_epoch: int = 0

    def after(self, steps: int, world_size: int, batch_size: int) -> "Position":
        """The position after ``steps`` more steps of every rank at that layout."""
        _check_layout(world_size, batch_size, 0)
        return Position(self.plan, self.epoch, self.sample_in_epoch + steps * world_size * batch_size)

    def to_dict(self) -> dict:
        """A plain dict (``state_dict`` form): ``{"plan": {...}, "epoch": e, "sample_in_epoch": p}``."""
        return {"plan": self.plan.to_dict(), "epoch": self.epoch, "sample_in_epoch": self.sample_in_epoch}

    @classmethod
    def from_dict(cls, d, expected: Optional[PlanIdentity] = None) -> "Position":
        """The position of :meth:`to_dict` output, checked against the plan at hand.

        Raises:
            PlanMismatch: a malformed position (naming the field), or one taken under another
                plan than ``expected`` (one line naming what differs).
        """
        if not isinstance(d, Mapping):
            raise PlanMismatch(f"position must be a mapping, got {type(d).__name__}")
        plan = PlanIdentity.from_dict(d.get("plan"))
        for k in ("epoch", "sample_in_epoch"):
            v = d.get(k)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise PlanMismatch(f"position field {k!r} must be an int >= 0, got {v!r:.80}")
        if expected is not None:
            problem = expected.problem(plan)
            if problem:
                raise PlanMismatch(f"position taken under {problem}")
        return cls(plan, d["epoch"], d["sample_in_epoch"])


def distinct_videos(plan: EpochPlan, batch_size: int, world_size: int = 1) -> float:
    """Mean distinct videos per batch over the epoch's full batches at that layout (a measure of
    mixing: ``bench/plan_mixing`` and ``tests/test_plan.py`` read it)."""
    full = len(plan) // batch_size
    if not full:
        return 0.0
    vid = plan.video_index[:full * batch_size].reshape(full, batch_size)
    s = np.sort(vid, axis=1)
    return float(np.mean(1 + np.count_nonzero(np.diff(s, axis=1), axis=1)))


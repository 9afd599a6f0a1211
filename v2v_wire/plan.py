"""Delivery by plan, pure: an epoch's sequence of samples as a function of (manifest, mixing, seed,
epoch), each rank's batch at each step as a fixed slice of it, and a checkpoint as a position.

The contract (docs/delivery.md):

* **The manifest** (:class:`Manifest`) is what a plan knows of a corpus: its videos, each one's
  *slots* (its windows per epoch) where they are known, each one's *tag* (what stands for its
  content without reading it: a file's size and modification time, an object's ETag) and
  ``crops_per_window``. A video's slots are a function of its file and the recipe, so they are
  not part of the identity: the manifest's fingerprint names the videos, their tags and the
  crops per window, and with the recipe's and :data:`PLAN_VERSION` it is the plan's identity
  (:class:`PlanIdentity`). A file replaced under its name (another cut: other slots) is thus
  another plan, whose positions mean other samples: a position taken before is refused. A plan
  *unfolds* as slots become known (a server learns a video's from its first decode): what it
  says of a position never changes once said.
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
  buffer's samples beyond those it serves; and it is decided once the slots of the first videos
  in that order that hold those samples are known (:attr:`EpochPlan.known`), whatever the
  others' are.
* **Ranks and steps**: at world size ``n`` and per-rank batch size ``b``, rank ``r``'s batch at
  step ``s`` of an epoch started at position ``p0`` is the positions
  ``p0 + (s * n + r) * b`` .. ``+ b`` (:func:`batch_positions`). Every rank has
  :func:`epoch_steps` steps; positions past the epoch's last sample are *padding* rows (no
  sample: ``None`` keys).
* **A checkpoint is a position** (:class:`Position`): the plan's identity, the epoch and the
  number of the epoch's samples every rank together consumed. It is the same on every rank and
  resumes at any world size and batch size: the next step starts at that position.

Nothing here owns a socket, a clock or a process; needs numpy only.
``tests/test_plan.py`` checks the contract's properties on random manifests.
"""
from __future__ import annotations

import hashlib
from array import array
from dataclasses import dataclass, field
from typing import Iterable, List, Mapping, Optional, Set, Tuple

import numpy as np

from v2v_wire.ids import SampleKey

__all__ = ["PLAN_VERSION", "SHUFFLE_BUFFER", "video_order", "Manifest", "PlanIdentity", "EpochPlan", "Position",
           "PlanMismatch", "NotKnownYet", "distinct_videos", "epoch_steps", "batch_positions"]

#: The version of the rules above: a plan of another version gives another sequence, or names
#: its corpus otherwise (version 3: the manifest's fingerprint covers each video's tag), so a
#: position taken under it is refused (:meth:`PlanIdentity.problem`).
PLAN_VERSION = 3

#: Default samples the shuffle buffer holds (step 2): ``DeliveryPolicy.shuffle_buffer``'s default.
SHUFFLE_BUFFER = 64

_MASK = np.uint64(0xFFFFFFFFFFFFFFFF)


class PlanMismatch(ValueError):
    """A position, a plan or a request names another plan than the one at hand: the message is
    one line naming what differs (manifest, recipe, seed, shuffle buffer, version)."""


class NotKnownYet(LookupError):
    """A position of an epoch whose plan has not unfolded that far: the slots of a video the
    production order reaches first are not known yet (:attr:`EpochPlan.known`)."""


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
    """What a plan knows of a corpus: its videos, each one's slots where known, each one's tag,
    and the crops per window.

    Attributes:
        slots: ``((video, slots), ...)`` sorted by video: corpus-relative POSIX paths, each
            with the windows it gives per epoch (a slot its decode does not fill is a padding
            row), or None where not known yet. Videos with 0 slots are kept (they name the
            listing) but give no sample.
        crops_per_window: samples per window (K >= 1).
        tags: each video's tag in the order of ``slots`` (a str standing for its content, e.g.
            ``VideoSource.listed_tag``; None: it could not be read at start), or ``()`` for a
            manifest that names paths only (the pure tests' and the seeded world's).

    Build with :meth:`of`, which sorts and checks.
    """

    slots: Tuple[Tuple[str, int], ...]
    crops_per_window: int = 1
    tags: Tuple[Optional[str], ...] = ()

    @classmethod
    def of(cls, slots: Mapping[str, Optional[int]], crops_per_window: int = 1,
           tags: Optional[Mapping[str, Optional[str]]] = None) -> "Manifest":
        """The manifest of ``{video: slots or None}``, with ``{video: tag or None}`` for each
        video when given.

        Raises:
            ValueError: a video that is not a non-empty str, slots that are neither None nor an
                int >= 0, ``crops_per_window`` < 1, or ``tags`` that lack a video or hold a tag
                that is neither None nor a str, naming it.
        """
        if not isinstance(crops_per_window, int) or isinstance(crops_per_window, bool) or crops_per_window < 1:
            raise ValueError(f"manifest: crops_per_window must be an int >= 1, got {crops_per_window!r}")
        for v, n in slots.items():
            if not isinstance(v, str) or not v:
                raise ValueError(f"manifest: a video must be a non-empty path, got {v!r:.80}")
            if n is not None and (not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 0):
                raise ValueError(f"manifest: slots of {v!r} must be None or an int >= 0, got {n!r}")
        ordered = tuple(sorted((v, None if n is None else int(n)) for v, n in slots.items()))
        if tags is None:
            return cls(ordered, crops_per_window)
        held = tuple(tags.get(v, False) for v, _ in ordered)
        for (v, _), tag in zip(ordered, held):
            if tag is not None and type(tag) is not str:
                raise ValueError(f"manifest: no tag for {v!r:.80}" if tag is False else
                                 f"manifest: the tag of {v!r:.80} must be None or a str, got {tag!r:.80}")
        return cls(ordered, crops_per_window, held)

    @property
    def samples(self) -> Optional[int]:
        """Samples an epoch lists (the slots times ``crops_per_window``), or None while some
        video's slots are not known."""
        if any(n is None for _, n in self.slots):
            return None
        return sum(n for _, n in self.slots) * self.crops_per_window

    def fingerprint(self) -> str:
        """A short hash (16 hex digits) of the videos, their tags and the crops per window (not
        their slots: those follow from the files and the recipe, and become known as the plan
        unfolds); of the videos and crops only (:meth:`paths_fingerprint`) when it has no tags."""
        if not self.tags:
            return self.paths_fingerprint()
        h = hashlib.sha256(f"crops={self.crops_per_window}\n".encode())
        for (v, _), tag in zip(self.slots, self.tags):
            h.update(f"{v}\t{'-' if tag is None else tag}\n".encode())
        return h.hexdigest()[:16]

    def paths_fingerprint(self) -> str:
        """A short hash (16 hex digits) of the videos and the crops per window only: the same
        for two manifests of one listing whose files changed (a server keeps what it served
        under it to name the files that changed, ``ops.plan_record``)."""
        h = hashlib.sha256(f"crops={self.crops_per_window}\n".encode())
        for v, _ in self.slots:
            h.update(f"{v}\n".encode())
        return h.hexdigest()[:16]


@dataclass(frozen=True)
class PlanIdentity:
    """What decides an epoch's sequence besides ``(seed, epoch)``: the manifest's fingerprint,
    the recipe's (``SampleRecipe.fingerprint``: what decides a sample's content), the seed, the
    shuffle buffer and :data:`PLAN_VERSION`. Two plans with equal identities and seeds give the same
    sequences.

    ``changes`` is no part of the identity (not compared, not in :meth:`to_dict`): the server's
    word on manifests of the same listing it served before, ``{fingerprint: "bikes.mp4 changed
    since ..."}`` (``ops.plan_record``), which :meth:`problem` adds to the line that refuses a
    position taken under one of them; a server sends it with the identity (``PlanInfo``)."""

    manifest: str
    recipe: str
    seed: int
    shuffle_buffer: int = SHUFFLE_BUFFER
    version: int = PLAN_VERSION
    changes: Mapping[str, str] = field(default_factory=dict, compare=False, hash=False, repr=False)

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
        differs, ``other``'s value first (``"recipe abc... (this plan: def...)"``; a manifest
        in :attr:`changes` with what changed since: ``"manifest abc... (this plan: def...;
        1 file changed since: bikes.mp4 ...)"``)."""
        diffs = [f"{k} {getattr(other, k)} (this plan: {getattr(self, k)}"
                 + (f"; {self.changes[other.manifest]})" if k == "manifest" and other.manifest in self.changes else ")")
                 for k in ("version", "manifest", "recipe", "seed", "shuffle_buffer")
                 if getattr(other, k) != getattr(self, k)]
        return None if not diffs else "another plan: " + ", ".join(diffs)


class EpochPlan:
    """One epoch's sequence of samples (module docstring: steps 1 and 2), unfolding as the
    videos' slots become known.

    Args:
        manifest: the corpus's videos and the slots known so far.
        seed, epoch: ints >= 0.
        shuffle_buffer: samples the shuffle buffer holds (>= 1; 1 keeps the production order).

    Attributes:
        videos: the manifest's videos not known to have 0 slots, in this epoch's
            :func:`video_order`.
        known: positions decided so far (0 .. ``known - 1``); every position once
            :attr:`complete`.
        complete: every video's slots are known, so the epoch's length is (:func:`len`).

    :meth:`learn` unfolds it further; what it says of a position never changes.

    Raises:
        ValueError: a negative seed or epoch, or a shuffle buffer < 1, naming it.
    """

    def __init__(self, manifest: Manifest, seed: int, epoch: int, shuffle_buffer: int = SHUFFLE_BUFFER):
        for name, v, low in (("seed", seed, 0), ("epoch", epoch, 0), ("shuffle_buffer", shuffle_buffer, 1)):
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < low:
                raise ValueError(f"plan: {name} must be an int >= {low}, got {v!r}")
        self.seed, self.epoch = int(seed), int(epoch)
        self.crops_per_window = manifest.crops_per_window
        self.shuffle_buffer = int(shuffle_buffer)
        self.videos = video_order((v for v, n in manifest.slots if n != 0), seed, epoch)
        self._starts = array("q", [0])  # production index of each counted video's first sample
        self._production = array("q")  # each decided position's production index
        self._buffer: Optional[List[int]] = None
        self._next = 0  # the production order's next sample to enter the buffer
        self._key = _seed_key(self.seed, self.epoch)
        self.complete = False
        self.learn(dict(manifest.slots))

    @property
    def known(self) -> int:
        return len(self._production)

    @property
    def counted(self) -> Tuple[int, int]:
        """(videos, samples) of the production order counted so far: its first videos in
        :attr:`videos`, whose slots are known."""
        return len(self._starts) - 1, self._starts[-1]

    def production_start(self, video: str) -> Optional[int]:
        """``video``'s first sample's index in the production order (samples, from 0), or None
        for a video not counted yet (its slots, or an earlier video's, not known) or not in
        this epoch."""
        i = self._video_number(video)
        return self._starts[i] if i is not None and i < len(self._starts) - 1 else None

    def undecided(self, keys: Iterable[SampleKey]) -> Set[SampleKey]:
        """Those of ``keys`` (samples of this epoch's videos) that no decided position holds yet:
        of a video not counted, or counted and still in the buffer or past it."""
        if self.complete and not self._buffer:
            return set()
        counted, buf = len(self._starts) - 1, set(self._buffer or ())
        out = set()
        for key in keys:
            i = self._video_number(key.video)
            if i is None:
                continue
            prod = self._starts[i] + key.ordinal(self.crops_per_window) if i < counted else None
            if prod is None or prod >= self._next or prod in buf:
                out.add(key)
        return out

    def _video_number(self, video: str) -> Optional[int]:
        """``video``'s index into :attr:`videos` (None for a video not in this epoch)."""
        if getattr(self, "_index", None) is None or len(self._index) != len(self.videos):
            self._index = {v: i for i, v in enumerate(self.videos)}
        return self._index.get(video)

    def learn(self, slots: Mapping[str, Optional[int]]) -> int:
        """Unfold with ``slots`` (video -> slots or None; videos not in it stay unknown): the
        production order takes in each next video whose slots are known, and the positions its
        samples decide. Returns :attr:`known`."""
        k = self.crops_per_window
        counted = len(self._starts) - 1
        while counted < len(self.videos):
            n = slots.get(self.videos[counted])
            if n is None:
                break
            self._starts.append(self._starts[-1] + n * k)
            counted += 1
        self.complete = counted == len(self.videos)
        self._shuffle(self._starts[-1])
        return self.known

    def _shuffle(self, made: int) -> None:
        """Decide the positions the production order's first ``made`` samples decide (step 2):
        position ``t`` once its buffer's refill is decided too (``t + shuffle_buffer < made``,
        or every sample counted)."""
        m, out = self.shuffle_buffer, self._production
        if self._buffer is None:
            if made < m and not self.complete:
                return
            self._buffer, self._next = list(range(min(m, made))), min(m, made)
        buf, nxt, t = self._buffer, self._next, len(out)
        while buf and (nxt < made or self.complete):
            stop = t + (made - nxt if nxt < made else len(buf))
            draws = _splitmix64(np.arange(t, stop, dtype=np.uint64) ^ self._key).tolist()
            for d in draws:
                j = d % len(buf)
                out.append(buf[j])
                if nxt < made:
                    buf[j] = nxt
                    nxt += 1
                else:
                    buf[j] = buf[-1]
                    buf.pop()
            t = stop
        self._next = nxt

    def _video_of(self, production: np.ndarray) -> np.ndarray:
        return np.searchsorted(np.frombuffer(self._starts, dtype=np.int64), production, side="right") - 1

    @property
    def production(self) -> np.ndarray:
        """int64 (known,): each decided position's index in the production order."""
        return np.frombuffer(self._production, dtype=np.int64).copy()

    @property
    def video_index(self) -> np.ndarray:
        """int64 (known,): each decided position's index into :attr:`videos`."""
        return self._video_of(self.production)

    @property
    def ordinal(self) -> np.ndarray:
        """int64 (known,): each decided position's sample number in its video (``SampleKey.ordinal``)."""
        prod = self.production
        return prod - np.frombuffer(self._starts, dtype=np.int64)[self._video_of(prod)]

    def __len__(self) -> int:
        """Samples in the epoch (no padding).

        Raises:
            NotKnownYet: the plan is not :attr:`complete`."""
        if not self.complete:
            raise NotKnownYet(f"epoch {self.epoch}: its length is not known until every video's slots are "
                              f"({len(self._starts) - 1} of {len(self.videos)} videos counted)")
        return len(self._production)

    def key(self, position: int) -> Optional[SampleKey]:
        """The sample at ``position`` (0-based), or ``None`` for a padding row (``position`` at or
        past :func:`len`).

        Raises:
            IndexError: ``position`` < 0.
            NotKnownYet: ``position`` is not decided yet (at or past :attr:`known` of a plan not
                :attr:`complete`)."""
        if position < 0:
            raise IndexError(f"plan position must be >= 0, got {position}")
        if position >= len(self._production):
            if self.complete:
                return None
            raise NotKnownYet(f"epoch {self.epoch} position {position}: not decided yet ({self.known} are)")
        prod = self._production[position]
        v = int(self._video_of(np.int64(prod)))
        return SampleKey.at(self.videos[v], prod - self._starts[v], self.crops_per_window)

    def position(self, key: SampleKey) -> Optional[int]:
        """The decided position holding ``key`` (a sample of this epoch's videos), or None while no
        decided position holds it (its video not counted yet, or its sample still in the buffer
        or past it) or for a video not in this epoch. The inverse of :meth:`key` (int64, one entry
        a counted sample), extended as the plan unfolds."""
        i = self._video_number(key.video)
        if i is None or i >= len(self._starts) - 1:
            return None
        prod = self._starts[i] + key.ordinal(self.crops_per_window)
        if prod >= self._starts[i + 1]:
            return None
        done, table = getattr(self, "_inverse", (0, np.empty(0, dtype=np.int64)))
        if done != self.known:  # extended with the positions decided since: a plan unfolding pays once a position
            if len(table) < self._starts[-1]:
                table = np.concatenate([table, np.full(max(self._starts[-1], 2 * len(table)) - len(table), -1,
                                                       dtype=np.int64)])
            table[np.frombuffer(self._production, dtype=np.int64)[done:]] = np.arange(done, self.known, dtype=np.int64)
            self._inverse = (self.known, table)
        p = int(table[prod]) if prod < len(table) else -1
        return None if p < 0 else p

    def keys(self, start: int, stop: int) -> List[Optional[SampleKey]]:
        """:meth:`key` of each position in ``start`` .. ``stop - 1``."""
        return [self.key(p) for p in range(start, stop)]

    def next_videos(self, count: int) -> List[str]:
        """The first ``count`` videos the production order reaches after the counted ones: those
        whose slots unfold the plan next (empty once :attr:`complete`)."""
        counted = len(self._starts) - 1
        return self.videos[counted:counted + count]

    def made_by(self, position: int) -> int:
        """How many samples of the production order a server must have made (in that order) to
        serve every position up to ``position``: ``position + shuffle_buffer``, at most every
        sample of a :attr:`complete` plan."""
        return min(len(self), position + self.shuffle_buffer) if self.complete else position + self.shuffle_buffer


def epoch_steps(samples: Optional[int], world_size: int, batch_size: int, start: int = 0) -> Optional[int]:
    """Steps every rank takes from position ``start`` to the end of an epoch of ``samples``
    samples (``len`` of its :class:`EpochPlan`): ``ceil((samples - start) / (world_size *
    batch_size))``, 0 when nothing is left; None while ``samples`` is None (not known yet).

    Raises:
        ValueError: ``world_size`` or ``batch_size`` < 1, or ``start`` < 0.
    """
    _check_layout(world_size, batch_size, start)
    return None if samples is None else max(0, -(-(samples - start) // (world_size * batch_size)))


def batch_positions(step: int, rank: int, world_size: int, batch_size: int, start: int = 0) -> range:
    """The positions of rank ``rank``'s batch at step ``step`` from ``start``:
    ``start + (step * world_size + rank) * batch_size`` and the ``batch_size - 1`` after it.
    Positions at or past the epoch's length are padding rows.

    Raises:
        ValueError: a layout :func:`epoch_steps` refuses, or ``rank`` outside 0 .. ``world_size - 1``,
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
    """Mean distinct videos per batch over the decided positions' full batches at that layout (a measure of
    mixing: ``bench/plan_mixing`` and ``tests/test_plan.py`` read it)."""
    full = plan.known // batch_size
    if not full:
        return 0.0
    vid = plan.video_index[:full * batch_size].reshape(full, batch_size)
    s = np.sort(vid, axis=1)
    return float(np.mean(1 + np.count_nonzero(np.diff(s, axis=1), axis=1)))


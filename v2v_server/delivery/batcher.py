"""Shuffled epochs, pure: the order videos are handed out in, and how made samples become batches.

* :func:`video_order` (``v2v_wire.plan``'s, re-exported) draws each epoch's order of the videos
  from ``(seed, epoch)``: every video gets a sort key hashed from ``(seed, epoch, path)``, so the
  order is the same on every restart and host, and a shard (any subset of the listing) gets the
  global order restricted to its videos, whatever the shard count.
* :class:`Batcher` turns made samples into batches. With ``lanes`` open batches per
  (epoch, outputs) group, each arriving sample joins a uniformly random one of them (a shuffle
  buffer of at most ``lanes x batch_size`` samples); an open batch that is full becomes a batch
  and an empty one opens in its place. A sample's open batch is chosen *before*
  its arrays are copied (:meth:`Batcher.lane`), so the server copies it straight into that
  batch's buffer row (``assembly.BatchAssembler.place``): a full batch is consecutive rows of
  one buffer and goes out zero-copy, as without shuffling. ``lanes = 1`` keeps arrival order.
  When the caller knows how many samples a group can still bring, the choice is among no more
  open batches than those samples fill, so an epoch smaller than the buffer still makes whole
  batches as samples arrive.

Nothing here owns a socket, a clock or a process; ``tests/test_shuffle.py`` drives it directly.
"""
from __future__ import annotations

import itertools
import random
from typing import Any, Callable, Dict, Iterable, List, Optional, Tuple

from v2v_server.delivery.ledger import DeliveryLedger
from v2v_server.delivery.table import BatchRecord
from v2v_wire.ids import SampleKey
from v2v_wire.plan import video_order  # the one rule of an epoch's video order, the plan's step 1

#: ``shuffle`` settings: ``epoch`` draws a new order each epoch and mixes batches; ``none`` keeps
#: the listing's order and the samples' arrival order.
SHUFFLES = ("epoch", "none")


class Batcher:
    """Kept samples waiting for a batch, grouped by (epoch, outputs computed) and spread over
    ``lanes`` open batches per group; the batches made of them go to the ledger. Pure.

    Args:
        batch_size: samples per batch (>= 1).
        make_batch: ``samples -> payload`` (samples in batch order).
        ledger: where each batch made goes (``DeliveryLedger.add_batch``).
        lanes: open batches per group (1: arrival order). The buffer holds up to
            ``lanes x batch_size`` samples per group, i.e. that many batches' memory.
        seed: seeds each group's choice of lane (with the epoch), so one worker's stream gives
            the same batches on every run.
        first_id: the first batch's id, then counted up (docs/delivery.md, "Transport": a
            restarted server's ids never repeat its predecessor's).

    Raises:
        ValueError: ``batch_size`` or ``lanes`` < 1.
    """

    def __init__(self, batch_size: int, make_batch: Callable, ledger: DeliveryLedger, lanes: int = 1,
                 seed: int = 0, first_id: int = 0):
        if batch_size < 1 or lanes < 1:
            raise ValueError(f"batch_size and lanes must be >= 1, got {batch_size} and {lanes}")
        self.batch_size, self.make_batch, self.ledger = batch_size, make_batch, ledger
        self.lanes, self.seed = lanes, seed
        self._batch_ids = itertools.count(first_id)
        self._lane_ids = itertools.count()  # an open batch's id: unique for the Batcher's life
        # (epoch, outputs) -> lane id -> [(key, sample)] in arrival order (dicts keep lane order)
        self.pending: Dict[Tuple[int, tuple], Dict[int, List[Tuple[SampleKey, Any]]]] = {}
        self._rngs: Dict[Tuple[int, tuple], random.Random] = {}

    def _group(self, gkey: Tuple[int, tuple]) -> Dict[int, list]:
        group = self.pending.get(gkey)
        if group is None:
            group = self.pending[gkey] = {next(self._lane_ids): [] for _ in range(self.lanes)}
            self._rngs[gkey] = random.Random(f"{self.seed}/{gkey[0]}/{','.join(gkey[1])}")
        return group

    def lane(self, epoch: int, outputs: tuple, more: Optional[int] = None) -> int:
        """The open batch the next sample of ``(epoch, outputs)`` joins: a uniformly random one
        of the group's ``lanes`` open batches (each has a free row: a full one is replaced at
        once). Pass it to :meth:`add` (and to the data path, which places the sample's arrays
        in that batch's buffer).

        ``more``: at most how many samples the group can still bring after this one (None:
        unknown). When this sample, the ones waiting and ``more`` fill fewer than ``lanes``
        batches, the choice is among that many open batches only (every one holding a sample,
        then empty ones in the group's order), so an epoch smaller than the buffer fills whole
        batches as its samples come (zero-copy, sent before the epoch ends) instead of leaving
        every open batch part-full for :meth:`flush` to copy. When ``more`` is exact and the
        group's samples are a multiple of ``batch_size``, nothing is left for :meth:`flush`."""
        gkey = (epoch, tuple(outputs))
        group = self._group(gkey)
        if self.lanes == 1:
            return next(iter(group))
        rng = self._rngs[gkey]
        if more is not None:
            held = sum(len(items) for items in group.values())
            k = -(-(held + 1 + max(more, 0)) // self.batch_size)  # batches left to make in this group
            if k < self.lanes:
                started = [lane for lane, items in group.items() if items]
                empty = [lane for lane, items in group.items() if not items]
                pick = started + empty[:max(0, k - len(started))]
                return pick[rng.randrange(len(pick))]  # k >= 1: never empty
        return list(group)[rng.randrange(self.lanes)]

    def add(self, epoch: int, outputs: tuple, key: SampleKey, sample, lane: Optional[int] = None) -> None:
        """Queue one sample in open batch ``lane`` (from :meth:`lane`; None, or one no longer
        open: a fresh choice); a full open batch becomes a batch."""
        gkey = (epoch, tuple(outputs))
        group = self._group(gkey)
        if lane not in group:
            lane = self.lane(epoch, outputs)
        items = group[lane]
        items.append((key, sample))
        if len(items) >= self.batch_size:
            del group[lane]
            group[next(self._lane_ids)] = []
            self._make(gkey, items)

    def _make(self, gkey: Tuple[int, tuple], items: list) -> None:
        payload = self.make_batch([s for _, s in items])
        self.ledger.add_batch(BatchRecord(next(self._batch_ids), gkey[0], [k for k, _ in items], payload,
                                          outputs=frozenset(gkey[1])))

    def flush(self, ended: Callable[[int], bool]) -> None:
        """Batch the leftovers of every epoch for which ``ended(epoch)`` (none of its jobs runs
        or waits): the open batches' samples, lane after lane, in batches of ``batch_size``
        (only the last one smaller)."""
        for gkey, group in list(self.pending.items()):
            if not ended(gkey[0]):
                continue
            rest = [item for items in group.values() for item in items]
            for i in range(0, len(rest), self.batch_size):
                self._make(gkey, rest[i:i + self.batch_size])
            del self.pending[gkey]
            del self._rngs[gkey]

    def drop(self, should_drop: Callable[[int, SampleKey], bool]) -> List[Tuple[int, List[SampleKey]]]:
        """Remove the waiting samples for which ``should_drop(epoch, key)``; returns
        ``(epoch, keys removed)`` per group that lost some."""
        out = []
        for (epoch, _), group in self.pending.items():
            gone = []
            for items in group.values():
                kept, lost = [], []
                for key, sample in items:
                    if should_drop(epoch, key):
                        lost.append(key)
                    else:
                        kept.append((key, sample))
                if lost:
                    items[:] = kept
                    gone.extend(lost)
            if gone:
                out.append((epoch, gone))
        return out

    def waiting(self) -> bool:
        """Some sample waits for a batch."""
        return any(items for group in self.pending.values() for items in group.values())

    def waiting_epochs(self) -> set:
        """The epochs of the samples waiting for a batch."""
        return {epoch for (epoch, _), group in self.pending.items() if any(group.values())}

    def fill(self) -> Tuple[int, int]:
        """``(samples waiting, capacity)`` of the shuffle buffer: the open batches' samples,
        and ``lanes x batch_size`` for each group that has any open batch (at least one group)."""
        held = sum(len(items) for group in self.pending.values() for items in group.values())
        return held, self.lanes * self.batch_size * max(1, len(self.pending))

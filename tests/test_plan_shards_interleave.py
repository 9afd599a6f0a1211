"""The interleave of several shards' plans (``v2v_wire.plan_shards``), pure: every global position
once in some shard's part at any batch size (fewer rows than shards included), and a seeded world
of ranks that each see only the rows they fetched from shards never scanned (each shard's length
learned from a row past its end, or from one row asked of a shard it does not read): every rank
ends the epoch at the same step, the step the whole interleaved epoch ends at."""
from __future__ import annotations

import random

import pytest

from v2v_wire.plan_shards import (epoch_floor, furthest_slot, interleaved, probes, shard_ranges, shards_samples,
                                  step_in_epoch)


@pytest.mark.parametrize("shards", [1, 2, 3, 5])
def test_a_fetch_of_any_size_splits_into_the_shards_parts_and_merges_back_in_order(shards):
    for start in range(0, 13):
        for rows in range(1, 2 * shards + 3):
            parts = shard_ranges(start, start + rows, shards)
            order = interleaved(start, start + rows, shards)
            assert [(k, parts[k][0] + j) for k, j in order] == [(t % shards, t // shards)
                                                                for t in range(start, start + rows)]
            assert sum(hi - lo for lo, hi in parts) == rows and all(hi >= lo for lo, hi in parts)


def read_rank(sizes, world, batch, rank):
    """What one rank of ``world`` yields of an epoch over shards of ``sizes`` samples, none known
    at start: ``(steps, ids)``, ids ``(shard, position)``. Each step's own rows are read; a row
    past a shard's end says that shard's length (as a server's answer does); while the step's
    place is not settled, each shard not known yet is asked one row (``probes``)."""
    n = len(sizes)
    known = [None] * n
    seen, ids, step = 0, [], 0
    per_step = world * batch
    while True:
        assert step <= max(sizes, default=0) * n, "reads past every shard's end"
        total = shards_samples(known)
        if total is not None and step >= -(-total // per_step):
            return step, ids
        first = step * per_step
        got = []
        for t in range(first + rank * batch, first + (rank + 1) * batch):
            k, q = t % n, t // n
            if q < sizes[k]:
                got.append((k, q))
                seen = max(seen, t + 1)
            else:
                known[k] = sizes[k]
        verdict = step_in_epoch(first, known, seen)
        while verdict is None:
            asks = probes(first, known)
            assert asks and all(known[k] is None and q * n + k >= first for k, q in asks)
            for k, q in asks:
                if q < sizes[k]:
                    seen = max(seen, q * n + k + 1)
                else:
                    known[k] = sizes[k]
            verdict = step_in_epoch(first, known, seen)
        if not verdict:
            return step, ids
        ids += got
        step += 1


def test_every_rank_ends_the_epoch_at_the_interleaved_epochs_last_step_reading_each_sample_once():
    rng = random.Random(86)
    for _ in range(3000):
        n = rng.randint(1, 5)
        sizes = [rng.choice([0, rng.randint(1, 4), rng.randint(1, 30)]) for _ in range(n)]
        world, batch = rng.randint(1, 4), rng.randint(1, 2 * n + 1)
        total = shards_samples(sizes)
        assert total == epoch_floor(sizes)
        want = -(-total // (world * batch))
        ranks = [read_rank(sizes, world, batch, r) for r in range(world)]
        assert [s for s, _ in ranks] == [want] * world, (sizes, world, batch)
        ids = [i for _, got in ranks for i in got]
        assert sorted(ids) == [(k, q) for k in range(n) for q in range(sizes[k])], (sizes, world, batch)


def test_a_step_is_settled_by_a_known_shards_end_or_a_slot_seen_and_open_while_a_shard_may_reach_it():
    # shards of 3 and unknown: global positions 0, 2, 4 of shard 0 hold samples (length >= 5)
    assert step_in_epoch(4, [3, None], 0) is True
    assert step_in_epoch(5, [3, None], 0) is None and probes(5, [3, None]) == [(1, 2)]
    assert step_in_epoch(5, [3, None], 6) is True  # shard 1's position 2 (global 5) holds a slot
    assert step_in_epoch(5, [3, 2], 0) is False  # both known: the epoch is 5 long
    assert probes(0, [None, None, None]) == [(0, 0), (1, 0), (2, 0)]


def test_the_furthest_slot_seen_is_one_past_the_last_row_holding_a_sample_id_in_global_positions():
    # shard 1 of 3, its own positions 4, 5, 6: global 13, 16, 19; the last row past its end
    assert furthest_slot(0, 1, 3, 4, ["a", "b", None]) == 17
    assert furthest_slot(20, 1, 3, 4, ["a", "b", None]) == 20  # a further one seen before stays
    assert furthest_slot(5, 0, 2, 0, [None]) == 5

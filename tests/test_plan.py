"""Delivery by plan, the pure part (``v2v_wire.plan``): the epoch's sequence, the ranks' slices,
positions as checkpoints. Properties on random manifests (hypothesis), then the pinned rules."""
from __future__ import annotations

import hashlib
from collections import Counter

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from v2v_wire.ids import SampleKey
from v2v_wire.plan import (PLAN_VERSION, EpochPlan, Manifest, NotKnownYet, PlanIdentity, PlanMismatch, Position,
                           batch_positions, distinct_videos, epoch_steps, video_order)

manifests = st.builds(
    Manifest.of,
    st.dictionaries(st.from_regex(r"[a-z]{1,3}/[a-z0-9]{1,6}\.mp4", fullmatch=True), st.integers(0, 9),
                    max_size=25),
    st.integers(1, 3))
layouts = st.tuples(st.integers(1, 5), st.integers(1, 7))  # world size, batch size per rank


def all_keys(m: Manifest):
    return sorted(SampleKey.at(v, i, m.crops_per_window) for v, n in m.slots for i in range(n * m.crops_per_window))


@settings(max_examples=150, deadline=None)
@given(manifests, st.integers(0, 2 ** 31), st.integers(0, 50), st.integers(1, 80))
def test_an_epoch_lists_every_sample_of_the_manifest_once(m, seed, epoch, buffer):
    plan = EpochPlan(m, seed, epoch, buffer)
    keys = plan.keys(0, len(plan))
    assert len(plan) == m.samples
    assert sorted(keys) == all_keys(m)
    again = EpochPlan(m, seed, epoch, buffer)  # another host, another run
    assert again.keys(0, len(again)) == keys


@settings(max_examples=150, deadline=None)
@given(manifests, st.integers(0, 1000), layouts)
def test_ranks_take_fixed_slices_the_same_number_of_steps_padding_only_at_the_tail(m, seed, layout):
    world, batch = layout
    plan = EpochPlan(m, seed, 3)
    steps = epoch_steps(len(plan), world, batch)
    seen = Counter()
    for r in range(world):
        rows = [p for s in range(steps) for p in batch_positions(s, r, world, batch)]
        assert len(rows) == steps * batch  # every rank, every step: a whole batch
        seen.update(rows)
    assert all(c == 1 for c in seen.values())
    real = [p for p in seen if plan.key(p) is not None]
    assert sorted(real) == list(range(len(plan)))  # each sample once, in the plan
    padding = len(seen) - len(real)
    assert 0 <= padding < world * batch and all(plan.key(p) is None for p in seen if p >= len(plan))


@settings(max_examples=150, deadline=None)
@given(manifests, st.integers(0, 1000), layouts, layouts, st.integers(0, 30))
def test_a_position_resumes_at_any_world_size_and_batch_size_without_a_repeat_or_a_loss(m, seed, before, after,
                                                                                          taken):
    ident = PlanIdentity(m.fingerprint(), "recipe0", seed)
    plan = EpochPlan(m, seed, 1)
    world, batch = before
    taken = min(taken, epoch_steps(len(plan), world, batch))
    got = [plan.key(p) for s in range(taken) for r in range(world) for p in batch_positions(s, r, world, batch)]
    pos = Position(ident, 1).after(taken, world, batch)
    pos = Position.from_dict(pos.to_dict(), expected=ident)  # saved and loaded on every rank alike
    world, batch = after
    start = pos.sample_in_epoch
    got += [plan.key(p) for s in range(epoch_steps(len(plan), world, batch, start)) for r in range(world)
            for p in batch_positions(s, r, world, batch, start)]
    assert sorted(k for k in got if k is not None) == all_keys(m)


@settings(max_examples=80, deadline=None)
@given(manifests, st.integers(0, 1000), st.integers(1, 70))
def test_a_server_holds_at_most_a_buffer_of_samples_beyond_those_it_serves(m, seed, buffer):
    """Serving positions in order, a server that makes samples in the production order has
    made what each position needs by :meth:`made_by`, and holds at most ``buffer`` samples
    made but not yet served."""
    plan = EpochPlan(m, seed, 2, buffer)
    production = EpochPlan(m, seed, 2, 1).keys(0, len(plan))
    served = set()
    for t in range(len(plan)):
        made = plan.made_by(t)
        assert plan.key(t) in set(production[:made]) and plan.production[t] < made
        served.add(plan.production[t])
        assert made - len(served) <= buffer - 1


def test_the_production_order_is_video_after_video_as_a_decode_makes_them():
    m = Manifest.of({"a.mp4": 3, "b.mp4": 2, "c.mp4": 1}, crops_per_window=2)
    plan = EpochPlan(m, 0, 0, shuffle_buffer=1)
    keys = plan.keys(0, len(plan))
    assert [k.video for k in keys] == [v for v in plan.videos for _ in range(dict(m.slots)[v] * 2)]
    assert [(k.window, k.crop) for k in keys[:2]] == [(0, 0), (0, 1)]
    assert list(plan.production) == list(range(len(plan)))


def test_epochs_and_seeds_give_other_orders_and_batches_mix_many_videos():
    m = Manifest.of({f"clips/{i:04d}.mp4": 1 + i % 3 for i in range(600)})
    a, b, c = EpochPlan(m, 0, 0), EpochPlan(m, 0, 1), EpochPlan(m, 1, 0)
    assert a.keys(0, 50) != b.keys(0, 50) and a.keys(0, 50) != c.keys(0, 50)
    # short clips, the WebVid case: a buffer of 64 samples spans ~32 videos
    assert distinct_videos(a, 12) > 9
    # longer clips (docs/shuffle.md's shape: 200 videos of 10 windows)
    ten = Manifest.of({f"v/{i:03d}.mp4": 10 for i in range(200)})
    assert distinct_videos(EpochPlan(ten, 0, 0), 12) > 8
    assert distinct_videos(EpochPlan(ten, 0, 0, shuffle_buffer=1), 12) < 3


def test_the_plans_video_order_is_a_hash_of_seed_epoch_and_path():
    """Every host draws the same order, and a shard's order is the corpus order restricted to it:
    each video's place is its BLAKE2b-64 of ``"{seed}/{epoch}/{path}"`` alone."""
    videos = [f"v{i:02d}.mp4" for i in range(30)]
    by_hash = sorted(videos, key=lambda v: hashlib.blake2b(f"4/2/{v}".encode(), digest_size=8).digest())
    assert video_order(videos, 4, 2) == by_hash != videos
    assert video_order(videos[::3], 4, 2) == [v for v in by_hash if v in videos[::3]]
    assert video_order(videos, 4, 3) != by_hash and video_order(videos, 5, 2) != by_hash
    plan = EpochPlan(Manifest.of({v: 1 for v in videos}), 4, 2, shuffle_buffer=1)
    assert plan.videos == video_order(videos, 4, 2)


def test_a_position_of_another_plan_is_refused_in_one_line_naming_what_differs():
    ident = PlanIdentity("m" * 16, "r" * 16, 7)
    pos = Position(PlanIdentity("m" * 16, "x" * 16, 7, shuffle_buffer=32), 2, 100).to_dict()
    with pytest.raises(PlanMismatch) as err:
        Position.from_dict(pos, expected=ident)
    line = str(err.value)
    assert "\n" not in line and "recipe xxxxxxxxxxxxxxxx (this plan: rrrrrrrrrrrrrrrr)" in line
    assert "shuffle_buffer 32 (this plan: 64)" in line and "manifest" not in line
    for bad, field in (({**pos, "epoch": -1}, "epoch"), ({**pos, "sample_in_epoch": "3"}, "sample_in_epoch"),
                       ({**pos, "plan": {**pos["plan"], "version": None}}, "version"), ([1, 2], "mapping")):
        with pytest.raises(PlanMismatch, match=field):
            Position.from_dict(bad, expected=ident)
    assert Position.from_dict(Position(ident, 2, 100).to_dict(), expected=ident) == Position(ident, 2, 100)


def test_a_manifests_fingerprint_names_its_videos_and_crops_not_the_slots_known_so_far():
    base = Manifest.of({"a.mp4": 2, "b.mp4": 3})
    assert Manifest.of({"b.mp4": 3, "a.mp4": 2}).fingerprint() == base.fingerprint()
    assert Manifest.of({"a.mp4": None, "b.mp4": 4}).fingerprint() == base.fingerprint()
    others = [Manifest.of({"a.mp4": 2, "c.mp4": 3}), Manifest.of({"a.mp4": 2, "b.mp4": 3}, crops_per_window=2),
              Manifest.of({"a.mp4": 2})]
    assert len({m.fingerprint() for m in others} | {base.fingerprint()}) == 4


def test_a_manifests_fingerprint_covers_each_videos_tag_and_a_changed_one_is_named():
    tags = {"a.mp4": "file 10 100", "b.mp4": "file 20 200"}
    base = Manifest.of({"a.mp4": 2, "b.mp4": None}, tags=tags)
    assert Manifest.of({"b.mp4": 3, "a.mp4": None}, tags=tags).fingerprint() == base.fingerprint()
    replaced = Manifest.of({"a.mp4": 2, "b.mp4": 1}, tags={**tags, "b.mp4": "file 12 201"})
    assert replaced.fingerprint() != base.fingerprint()
    paths_only = Manifest.of({"a.mp4": 2, "b.mp4": 3}).fingerprint()
    assert replaced.paths_fingerprint() == base.paths_fingerprint() == paths_only
    for bad, field in (({"a.mp4": "x"}, "no tag for 'b.mp4'"), ({**tags, "a.mp4": 3}, "tag of 'a.mp4'")):
        with pytest.raises(ValueError, match=field):
            Manifest.of({"a.mp4": 2, "b.mp4": 3}, tags=bad)
    ident = PlanIdentity(replaced.fingerprint(), "r", 0, changes={base.fingerprint(): "1 file(s) changed: b.mp4"})
    old = PlanIdentity(base.fingerprint(), "r", 0)
    assert ident == PlanIdentity(replaced.fingerprint(), "r", 0)  # what changed is no part of the identity
    with pytest.raises(PlanMismatch, match=rf"^position taken under another plan: manifest {base.fingerprint()} "
                                           rf"\(this plan: {replaced.fingerprint()}; 1 file\(s\) changed: b.mp4\)$"):
        Position.from_dict(Position(old, 0, 4).to_dict(), expected=ident)


@settings(max_examples=150, deadline=None)
@given(manifests, st.integers(0, 2 ** 31), st.integers(0, 9), st.integers(1, 40), st.randoms(use_true_random=False))
def test_a_plan_unfolding_as_slots_become_known_says_what_the_whole_plan_says(m, seed, epoch, buffer, rnd):
    """Slots learned in any order and any number of steps: each position, once decided, is the
    complete plan's, and a position is decided once the videos the production order reaches
    first hold its buffer's samples."""
    whole = EpochPlan(m, seed, epoch, buffer)
    slots = dict(m.slots)
    unknown = list(slots)
    rnd.shuffle(unknown)
    part = EpochPlan(Manifest.of({v: (None if v in unknown else n) for v, n in slots.items()},
                                 m.crops_per_window), seed, epoch, buffer)
    learned, said = {}, []
    while True:
        assert part.keys(0, part.known) == whole.keys(0, part.known)
        assert part.known >= len(said) and part.keys(0, len(said)) == said
        said = part.keys(0, part.known)
        if part.known < len(whole) or not part.complete:
            with pytest.raises(NotKnownYet):
                part.key(part.known)
            with pytest.raises(NotKnownYet):
                len(part)
        assert part.next_videos(3)[:1] == ([] if part.complete else [next(v for v in part.videos if v in unknown
                                                                         and v not in learned)])
        if not unknown:
            break
        for v in unknown[:rnd.randint(1, 3)]:
            learned[v] = slots[v]
        unknown = [v for v in unknown if v not in learned]
        part.learn(learned)
    assert part.complete and len(part) == len(whole) and part.key(len(whole)) is None
    assert part.keys(0, len(whole)) == whole.keys(0, len(whole))


@settings(max_examples=150, deadline=None)
@given(manifests, st.integers(0, 2 ** 31), st.integers(0, 50), st.integers(1, 80), st.randoms())
def test_a_samples_position_is_the_one_holding_it_once_decided(m, seed, epoch, buffer, rnd):
    """``EpochPlan.position`` inverts ``key`` over the decided positions, and is None for a sample
    no decided position holds yet (its video not counted, or its sample still in the buffer),
    past its video's slots, or of a video not in the manifest."""
    slots = dict(m.slots)
    known = {v: (n if rnd.random() < 0.6 else None) for v, n in slots.items()}
    plan = EpochPlan(Manifest.of(known, m.crops_per_window), seed, epoch, buffer)
    for step in range(2):  # as first known, then once every video's slots are
        held = {plan.key(p): p for p in range(plan.known)}
        for key in all_keys(m):
            assert plan.position(key) == held.get(key), (step, key)
        plan.learn(slots)
    for v, n in slots.items():
        assert plan.position(SampleKey.at(v, n * m.crops_per_window, m.crops_per_window)) is None
    assert plan.position(SampleKey.at("not/listed.mp4", 0, m.crops_per_window)) is None


def test_a_plan_decides_a_position_once_its_buffer_is_counted():
    m = Manifest.of({f"v{i}.mp4": None for i in range(10)})
    plan = EpochPlan(m, 1, 0, 4)
    assert plan.known == 0 and not plan.complete and plan.next_videos(2) == plan.videos[:2]
    plan.learn({plan.videos[0]: 3})
    assert plan.known == 0  # 3 samples made: the buffer of 4 is not yet full
    plan.learn({plan.videos[0]: 3, plan.videos[1]: 3})
    assert plan.known == 2  # 6 made: positions 0 and 1 (each refill decided: t + 4 < 6)
    assert plan.next_videos(1) == [plan.videos[2]]


@pytest.mark.parametrize("slots, crops, field", [({"": 1}, 1, "video"), ({"a.mp4": -1}, 1, "a.mp4"),
                                                 ({"a.mp4": 1.5}, 1, "a.mp4"), ({"a.mp4": 1}, 0, "crops_per_window")])
def test_a_bad_manifest_is_refused_naming_the_field(slots, crops, field):
    with pytest.raises(ValueError, match=field):
        Manifest.of(slots, crops)


def test_bad_layouts_are_refused():
    plan = EpochPlan(Manifest.of({"a.mp4": 4}), 0, 0)
    for args in ((0, 2), (2, 0)):
        with pytest.raises(ValueError, match="world_size"):
            epoch_steps(len(plan), *args)
    with pytest.raises(ValueError, match="rank 2 of world size 2"):
        batch_positions(0, 2, 2, 1)
    assert epoch_steps(None, 2, 2) is None  # an epoch whose length is not known yet
    with pytest.raises(ValueError, match="seed"):
        EpochPlan(Manifest.of({"a.mp4": 4}), -1, 0)


def test_the_sequence_is_pinned_for_this_plan_version():
    """Hosts and engines must draw the same sequence: this digest changes only with
    :data:`PLAN_VERSION` (a change of the rules without a new version would mix two plans)."""
    m = Manifest.of({f"d{i % 7}/{i:03d}.mp4": i % 5 for i in range(120)}, crops_per_window=2)
    plan = EpochPlan(m, 123, 4)
    digest = hashlib.sha256(np.stack([plan.video_index, plan.ordinal]).astype("<i8").tobytes()
                            + "\n".join(plan.videos).encode()).hexdigest()[:16]
    assert (PLAN_VERSION, digest) == (3, PINNED)  # version 3: the identity covers the tags; same sequence


PINNED = "b12c8400f0f5825c"


@settings(max_examples=150, deadline=None)
@given(st.lists(manifests, min_size=1, max_size=4), st.integers(0, 1000), layouts, st.integers(0, 40))
def test_shards_interleaved_give_each_sample_once_in_fixed_slices_and_a_position_resumes_them(shards, seed, layout,
                                                                                           resume_at):
    """Several servers, one shard each: global position t is shard t mod N's position t // N.
    Read through fixed slices of any layout, fetched shard by shard, every sample of every shard
    comes once, padding only where a shard's epoch is shorter, and a read resumed at any position
    gives the rest."""
    from v2v_wire.plan_shards import interleaved, shard_ranges, shards_samples

    n = len(shards)
    plans = [EpochPlan(m, seed, 2) for m in shards]
    total = shards_samples([len(p) for p in plans])
    world, batch = layout

    def rows(start: int, stop: int):  # what a reader merges from one fetch per shard
        parts = [p.keys(lo, hi) if hi > lo else [] for p, (lo, hi) in zip(plans, shard_ranges(start, stop, n))]
        return [(i, parts[i][j]) for i, j in interleaved(start, stop, n)]

    read = rows(0, total)
    ids = [(i, k) for i, k in read if k is not None]
    assert sorted(ids) == sorted((i, k) for i, p in enumerate(plans) for k in p.keys(0, len(p)))
    assert total == 0 or read[-1][1] is not None  # the epoch ends at its last sample
    steps = -(-total // (world * batch))
    sliced = [row for s in range(steps) for r in range(world)
              for row in rows(s * world * batch + r * batch, min(total, (s * world + r + 1) * batch))]
    assert sliced == read
    at = min(resume_at, total)
    assert rows(0, at) + rows(at, total) == read


def test_the_shards_identity_names_their_manifests_and_refuses_other_recipes():
    from v2v_wire.plan_shards import shards_identity

    a, b = PlanIdentity("aa", "r", 0), PlanIdentity("bb", "r", 0)
    assert shards_identity([a]) == a
    both = shards_identity([a, b])
    assert both.manifest.startswith("2x") and both.manifest != shards_identity([b, a]).manifest
    assert (both.recipe, both.seed) == ("r", 0)
    with pytest.raises(PlanMismatch, match=r"^the shards' plans differ in seed: shard 0: 0, shard 1: 5$"):
        shards_identity([a, PlanIdentity("bb", "r", 5)])


def test_the_plan_message_carries_what_changed_since_earlier_manifests():
    from v2v_wire.plan_messages import PlanInfo, WireError

    ident = PlanIdentity("m2", "r", 0, changes={"m1": "1 file(s) changed: b.mp4"})
    back = PlanInfo.from_wire(PlanInfo(ident, None, {}).to_wire())
    assert back.plan == ident and back.plan.changes == {"m1": "1 file(s) changed: b.mp4"}
    assert "changes" not in Position(ident).to_dict()["plan"]  # a position and a fetch name the identity only
    with pytest.raises(WireError, match="field 'changes'"):
        PlanInfo.from_wire({**PlanInfo(ident, None, {}).to_wire(), "changes": {"m1": 3}})


def test_the_plan_message_carries_the_servers_instance_checked_at_the_edge():
    from v2v_wire.plan_messages import MAX_INSTANCE, PlanInfo, WireError

    ident = PlanIdentity("m", "r", 0)
    assert PlanInfo.from_wire(PlanInfo(ident, 4, {}, "a" * 32).to_wire()).instance == "a" * 32
    assert PlanInfo.from_wire(PlanInfo(ident, 4, {}).to_wire()).instance is None  # not said: never read as another's
    for bad in ("", "x" * (MAX_INSTANCE + 1), 7, ["a"]):
        with pytest.raises(WireError, match="plan: field 'instance'"):
            PlanInfo.from_wire({**PlanInfo(ident, 4, {}).to_wire(), "instance": bad})


def test_a_videos_production_start_is_the_samples_of_the_videos_produced_before_it():
    slots = {"a.mp4": 3, "b.mp4": None, "c.mp4": 2, "d.mp4": 0}
    plan = EpochPlan(Manifest.of(slots, 2), 7, 1, 4)
    order = plan.videos
    first_unknown = order.index("b.mp4")
    starts, n = {}, 0
    for v in order[:first_unknown]:
        starts[v] = n
        n += slots[v] * 2
    assert {v: plan.production_start(v) for v in order} == {v: starts.get(v) for v in order}
    plan.learn({**slots, "b.mp4": 1})
    n = 0
    for v in order:
        assert plan.production_start(v) == n
        n += {**slots, "b.mp4": 1}[v] * 2
    assert plan.production_start("nope.mp4") is None

"""Serving by plan, the pure part (``delivery.plan_feed.PlanFeed``), driven by a seeded world:
workers that decode at their own pace, stall, die and are replaced; files that give fewer windows
than their slots or break; jobs of several ranks that fetch ahead, checkpoint and resume at another
world size. Every seed checks that each job reads each epoch's plan exactly: every row at its
position, every sample once, padding only past the end or for a window the run made fail."""
from __future__ import annotations

import random
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

import pytest

from v2v_server.delivery.plan_feed import PlanFeed, SlotsExceeded
from v2v_wire.ids import SampleKey
from v2v_wire.plan import EpochPlan, Manifest


@dataclass
class Worker:
    ident: str
    task: Optional[object] = None
    todo: List[SampleKey] = field(default_factory=list)
    stalled_until: float = 0.0


@dataclass
class Job:
    name: str
    world: int
    batch: int
    epoch: int = 0
    start: int = 0  # the position this layout started at
    step: int = 0  # next step to ask for, per rank alike
    asked: Dict[Tuple[int, int], int] = field(default_factory=dict)  # (step, rank) -> request id
    rows: Dict[int, List] = field(default_factory=dict)  # epoch -> rows received
    taken: int = 0  # steps whose every rank's rows arrived


def world(seed: int, ticks: int = 4000):
    rng = random.Random(seed)
    kpw = rng.choice([1, 1, 2])
    slots = {f"v{i:02d}.mp4": rng.randint(0, 6) for i in range(rng.randint(1, 14))}
    given = {v: (n if rng.random() < 0.8 else rng.randint(0, n)) for v, n in slots.items()}  # short decodes
    broken = {v for v in slots if rng.random() < 0.1}  # the pass breaks after its windows
    m = Manifest.of(slots, kpw)
    feed = PlanFeed(m, seed, rng.choice([1, 4, 16]), ("voxels",), lookahead=rng.choice([0, 8]),
                    keep_samples=rng.choice([0, 4, 32]), hedge_s=5.0, task_timeout_s=40.0)
    workers = [Worker(f"w{i}") for i in range(rng.randint(1, 3))]
    next_worker = len(workers)
    jobs = [Job(f"j{i}", rng.randint(1, 3), rng.randint(1, 5)) for i in range(rng.randint(1, 2))]
    epochs = 2
    request = 0
    biggest = 0
    for now in range(ticks):
        # clients: ask up to two steps ahead; take a step when every rank's rows came
        for job in jobs:
            if job.epoch >= epochs:
                continue
            plan = feed.plan(job.epoch)
            steps = plan.steps(job.world, job.batch, job.start)
            while job.step < min(steps, job.taken + 2):
                for r in range(job.world):
                    pos = plan.batch_positions(job.step, r, job.world, job.batch, job.start)
                    request += 1
                    job.asked[(job.step, r)] = request
                    feed.fetch((job.name, r), request, job.epoch, pos.start, pos.stop, now)
                job.step += 1
            if job.taken >= steps:
                job.epoch, job.start, job.step, job.taken, job.asked = job.epoch + 1, 0, 0, 0, {}
            elif rng.random() < 0.01 and job.taken and job.taken == job.step:  # checkpoint, resume at another layout
                job.start += job.taken * job.world * job.batch
                job.world, job.batch = rng.randint(1, 3), rng.randint(1, 5)
                job.step = job.taken = 0
                job.asked = {}
        for f, rows in feed.answer(now):
            job = next(j for j in jobs if j.name == f.client[0])
            if (f.epoch, f.request) not in {(job.epoch, r) for r in job.asked.values()}:
                continue
            plan = feed.plan(f.epoch)
            for row in rows:
                assert row.key == plan.key(row.position)  # the fixed slice
                if row.sample is not None:
                    assert row.sample == (f.epoch, row.key)
            job.rows.setdefault(f.epoch, []).extend(rows)
            step = next(s for (s, r), q in job.asked.items() if q == f.request)
            job.asked[(step, f.client[1])] = -1
            while all(job.asked.get((job.taken, r)) == -1 for r in range(job.world)) and job.taken < job.step:
                job.taken += 1
        # workers: one sample per tick unless stalled; some die, some stall
        for w in list(workers):
            if rng.random() < 0.002:  # killed: the pool replaces it
                feed.worker_lost(w.ident)
                workers.remove(w)
                workers.append(Worker(f"w{next_worker}"))
                next_worker += 1
                continue
            if rng.random() < 0.004:
                w.stalled_until = now + rng.choice([3, 20, 60])
            if now < w.stalled_until:
                continue
            if w.task is None:
                w.task = feed.task_for(w.ident, now)
                if w.task is not None:
                    t = w.task
                    w.todo = [SampleKey.at(t.video, i, kpw) for i in range(given[t.video] * kpw)
                              if (i // kpw, i % kpw) not in set(t.skip)]
                continue
            t = w.task
            if w.todo:
                key = w.todo.pop(0)
                feed.sample(w.ident, t.task, key, now, lambda lane, e=t.epoch, k=key: (e, k))
            else:
                error = "decoder error: broken packet" if t.video in broken and given[t.video] < slots[t.video] else None
                feed.done(w.ident, t.task, given[t.video], {}, error)
                w.task = None
        for ident, _ in feed.timed_out(now):
            for w in workers:
                if w.ident == ident:
                    w.task, w.todo, w.stalled_until = None, [], 0.0
        biggest = max(biggest, len(feed.store))
        if all(j.epoch >= epochs for j in jobs):
            break
    return feed, jobs, slots, given, epochs, m, biggest


@pytest.mark.parametrize("seed", range(300))
def test_each_job_reads_each_epochs_plan_exactly_whatever_the_workers_do(seed):
    feed, jobs, slots, given, epochs, m, biggest = world(seed)
    for job in jobs:
        assert job.epoch == epochs, f"seed {seed}: {job.name} stuck in epoch {job.epoch} at step {job.taken}"
        for e in range(epochs):
            plan = EpochPlan(m, feed.seed, e, feed.shuffle_buffer)
            rows = job.rows.get(e, [])
            real = [r for r in rows if r.key is not None]
            assert sorted(r.position for r in real) == list(range(len(plan)))  # each position once
            made = [r.key for r in real if r.sample is not None]
            assert len(made) == len(set(made))
            for r in real:
                if r.sample is None:  # padding in place of a sample: only for windows the file did not give
                    assert r.key.window >= given[r.key.video], (seed, r)
                else:
                    assert r.key.window < given[r.key.video]
            assert all(r.sample is None for r in rows if r.key is None)
    # memory: what pending fetches name, plus the kept ones, plus a video's samples decoded ahead
    bound = feed.keep_samples + 2 * (max(j.batch * j.world for j in jobs) * 5 + feed.lookahead) + \
        max(slots.values(), default=0) * m.crops_per_window * 3
    assert biggest <= bound


def test_a_stalled_worker_is_hedged_and_the_first_copy_wins():
    m = Manifest.of({"a.mp4": 2, "b.mp4": 1})
    feed = PlanFeed(m, 0, 1, ("voxels",), lookahead=0, hedge_s=5.0, task_timeout_s=100.0)
    plan = feed.plan(0)
    feed.fetch("c", 1, 0, 0, 3, 0.0)
    first = feed.task_for("w1", 0.0)
    second = feed.task_for("w2", 0.0)  # the other video
    assert {first.video, second.video} == {"a.mp4", "b.mp4"}
    assert feed.task_for("w3", 1.0) is None  # nothing late yet
    hedge = feed.task_for("w3", 6.0)  # both silent for 6 s: the first in production order is hedged
    assert hedge.video == plan.videos[0] and hedge.task not in (first.task, second.task)
    slow, slow_worker = (first, "w1") if first.video == hedge.video else (second, "w2")
    keys = [SampleKey.at(hedge.video, i) for i in range(dict(m.slots)[hedge.video])]
    assert all(feed.sample("w3", hedge.task, k, 7.0, lambda lane, k=k: ("hedge", k)) for k in keys)
    assert not feed.sample(slow_worker, slow.task, keys[0], 8.0, lambda lane: ("late", keys[0]))  # the first copy won
    assert feed.store[(0, keys[0])] == ("hedge", keys[0])


def test_a_decode_past_the_manifests_slots_is_an_error_naming_the_video():
    feed = PlanFeed(Manifest.of({"a.mp4": 1}), 0, 1, ("voxels",))
    feed.fetch("c", 1, 0, 0, 1, 0.0)
    t = feed.task_for("w", 0.0)
    with pytest.raises(SlotsExceeded, match=r"a.mp4: the decode gave a.mp4#1, past the manifest's 1 window"):
        feed.sample("w", t.task, SampleKey("a.mp4", 1), 1.0, lambda lane: None)


def test_a_short_decode_gives_padding_rows_and_no_worker_is_asked_again():
    feed = PlanFeed(Manifest.of({"a.mp4": 3}), 0, 1, ("voxels",), lookahead=0)
    feed.fetch("c", 1, 0, 0, 4, 0.0)
    t = feed.task_for("w", 0.0)
    feed.sample("w", t.task, SampleKey("a.mp4", 0), 1.0, lambda lane: "s0")
    feed.done("w", t.task, 1, {}, None)
    (f, rows), = feed.answer(3.0)
    assert [r.sample for r in rows] == ["s0", None, None, None]
    assert [r.key for r in rows] == [SampleKey("a.mp4", 0), SampleKey("a.mp4", 1), SampleKey("a.mp4", 2), None]
    assert "the decode gave 1 window(s), the manifest 3" in rows[1].reason
    assert feed.task_for("w", 2.0) is None



def test_decode_ahead_goes_on_into_the_next_epoch_within_the_lookahead():
    # a trainer reading the end of epoch 0 finds epoch 1's first samples made, so one worker never
    # waits at the boundary; what is made ahead stays within the lookahead
    m = Manifest.of({f"v{i}.mp4": 2 for i in range(4)})
    feed = PlanFeed(m, 0, 1, ("voxels",), lookahead=4, keep_samples=0)
    feed.fetch("c", 1, 0, 6, 8, 0.0)  # the epoch's last batch
    made = []
    while (t := feed.task_for("w", 0.0)) is not None:
        made.append((t.epoch, t.video))
        for i in range(2):
            feed.sample("w", t.task, SampleKey.at(t.video, i), 0.0, lambda lane: "s")
        feed.done("w", t.task, 2, {}, None)
    waited = {(0, EpochPlan(m, 0, 0, 1).key(p).video) for p in (6, 7)}
    assert set(made[:len(waited)]) == waited
    ahead = made[len(waited):]
    assert ahead and {e for e, _ in ahead} == {1}
    assert ahead[0][1] == EpochPlan(m, 0, 1, 1).key(0).video  # the next epoch's first position first
    assert sum(1 for sk in feed.store if sk[0] == 1) <= feed.lookahead + 1


def test_workers_make_the_outputs_fetches_ask_for_and_a_new_one_remakes_what_lacks_it():
    m = Manifest.of({"a.mp4": 2})
    feed = PlanFeed(m, 0, 1, ("voxels", "frames", "flow"), lookahead=0)
    feed.fetch("c", 1, 0, 0, 1, 0.0, ("voxels",))
    narrow = feed.task_for("w1", 0.0)
    assert narrow.outputs == ("voxels",)
    assert feed.sample("w1", narrow.task, SampleKey("a.mp4", 0), 1.0, lambda lane: "voxels only")
    (f, rows), = feed.answer(1.0)
    assert rows[0].sample == "voxels only"
    feed.fetch("d", 2, 0, 0, 2, 2.0, ("flow", "voxels"))  # flow: what was made lacks it
    assert feed.making == ("voxels", "flow") and not feed.store
    assert not feed.sample("w1", narrow.task, SampleKey("a.mp4", 1), 3.0, lambda lane: "voxels only")
    assert feed.task_for("w2", 3.0) is None  # the video is being decoded: it ends first
    feed.done("w1", narrow.task, 2, {}, None)
    assert not feed.answer(4.0) and not feed.failed
    wide = feed.task_for("w2", 4.0)
    assert wide.outputs == ("voxels", "flow")
    for i in range(2):
        assert feed.sample("w2", wide.task, SampleKey("a.mp4", i), 5.0, lambda lane, i=i: f"wide {i}")
    (f, rows), = feed.answer(5.0)
    assert [r.sample for r in rows] == ["wide 0", "wide 1"]
    with pytest.raises(ValueError, match="polarity_counts"):
        feed.fetch("e", 3, 0, 0, 1, 6.0, ("polarity_counts",))

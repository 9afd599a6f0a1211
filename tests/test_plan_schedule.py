"""Serving by plan, the pure part (``delivery.plan_schedule.PlanScheduler``): driven by the seeded world of
``harness.plan_world`` (each job reads each epoch's plan exactly: every row at its position, every
sample once, padding only past the end or for a window the run made fail), and unit checks of its
decisions."""
from __future__ import annotations

import pytest

from harness.plan_world import TOTALS, check
from v2v_server.delivery.plan_orders import TOLD_S
from v2v_server.delivery.plan_schedule import PASS_ATTEMPTS, PlanScheduler, SlotsExceeded
from v2v_wire.ids import SampleKey
from v2v_wire.plan import EpochPlan, Manifest


def test_each_job_reads_each_epochs_plan_exactly_in_1000_seeded_worlds():
    """``harness.plan_world``: workers killed, stalled, hedged and timed out; short, empty and broken
    files; slots known at start or learned from decodes (the plan unfolding); 1-4 shard servers
    read as one interleaved plan, each killed and started again on its own, a file replaced under
    its name by another cut while it was down (the positions of the plan before refused, the epoch
    read again); videos of 0-40 samples; jobs of 1-32 readers (1-8 ranks at 1-32 rows, read by
    the main process or by DataLoader workers, persistent or not) that take ``set_epoch`` and
    ``load_state_dict`` at their next pass, resuming at other layouts and rolling back to older
    checkpoints, cut off mid-epoch and started again; outputs widened mid-run. A third of the
    seeds run a fleet of 1-16 hosts serving one plan (``harness.plan_world_fleet``) that join,
    leave (their names staying, as in a static list, or not), stall and restart under the same or
    a new name, read through the client's ``fleet_pass.Pass`` and ``Router`` over a transport
    that delays and loses messages: each position once, its bytes, padding only where one server
    puts it, each pass ended at the epoch's end, positions resumed on another number of hosts,
    no video asked of dead hosts only for long while a host is up. Where one job reads at a time (a
    job cut off and started again included), no server restarts and no output widens, each sample
    read is made once (1.05 made a sample read at most), in jobs of 16 readers and more, at 16
    rows a rank and more, over videos of 20 samples and more (``World.judge_decodes``). Replay a seed with ``python -m harness.plan_world --seeds N:N+1``."""
    failed = {}
    totals = dict.fromkeys(TOTALS, 0)
    for seed in range(1000):
        o = check(seed)
        for k in totals:
            totals[k] += getattr(o, k)
        if o.problems:
            failed[seed] = o.problems[0]
    assert not failed, f"{len(failed)} seed(s) failed, first: {next(iter(failed.items()))}"
    # the faults and the cases happened
    assert all(n > 50 for k, n in totals.items() if k != "resized" and not k.startswith("counted_")), totals
    assert totals["resized"] > 30, totals  # a fleet's position resumed on another number of hosts
    assert totals["sharded"] > 400 and totals["loader_passes"] > 1000 and totals["probes"] > 200, totals
    assert totals["fleets"] > 250 and totals["hedged"] > 500 and totals["copies"] > 2000, totals
    assert totals["withdrawn"] > 1000, totals  # a copy whose samples came first from another host, withdrawn
    # seeds whose decodes were counted (each sample read made once), and among them: a job of 16
    # readers or more, 16 rows a rank or more, a video of 20 samples or more, a job cut off
    assert totals["counted"] > 80, totals
    assert totals["counted_readers"] >= 8 and totals["counted_batch"] >= 15, totals
    assert totals["counted_long"] >= 8 and totals["counted_cut"] >= 10, totals


def test_a_stalled_worker_is_hedged_and_the_first_copy_wins():
    m = Manifest.of({"a.mp4": 2, "b.mp4": 1})
    scheduler = PlanScheduler(m, 0, 1, ("voxels",), lookahead=0, hedge_s=5.0, task_timeout_s=100.0)
    plan = scheduler.plan(0)
    scheduler.fetch("c", 1, 0, 0, 3, 0.0)
    first = scheduler.task_for("w1", 0.0)
    second = scheduler.task_for("w2", 0.0)  # the other video
    assert {first.video, second.video} == {"a.mp4", "b.mp4"}
    assert scheduler.task_for("w3", 1.0) is None  # nothing late yet
    hedge = scheduler.task_for("w3", 6.0)  # both silent for 6 s: the first in production order is hedged
    assert hedge.video == plan.videos[0] and hedge.task not in (first.task, second.task)
    slow, slow_worker = (first, "w1") if first.video == hedge.video else (second, "w2")
    keys = [SampleKey.at(hedge.video, i) for i in range(dict(m.slots)[hedge.video])]
    assert all(scheduler.sample("w3", hedge.task, k, 7.0, lambda k=k: ("hedge", k)) for k in keys)
    assert not scheduler.sample(slow_worker, slow.task, keys[0], 8.0, lambda: ("late", keys[0]))  # the first copy won
    assert scheduler.store[(0, keys[0])] == ("hedge", keys[0])


def test_a_decode_past_the_manifests_slots_is_an_error_naming_the_video():
    scheduler = PlanScheduler(Manifest.of({"a.mp4": 1}), 0, 1, ("voxels",))
    scheduler.fetch("c", 1, 0, 0, 1, 0.0)
    t = scheduler.task_for("w", 0.0)
    with pytest.raises(SlotsExceeded, match=r"a.mp4: the decode gave a.mp4#1, past the manifest's 1 window"):
        scheduler.sample("w", t.task, SampleKey("a.mp4", 1), 1.0, lambda: None)


def test_a_short_decode_gives_padding_rows_and_no_worker_is_asked_again():
    scheduler = PlanScheduler(Manifest.of({"a.mp4": 3}), 0, 1, ("voxels",), lookahead=0)
    scheduler.fetch("c", 1, 0, 0, 4, 0.0)
    t = scheduler.task_for("w", 0.0)
    scheduler.sample("w", t.task, SampleKey("a.mp4", 0), 1.0, lambda: "s0")
    scheduler.done("w", t.task, 1, {}, None)
    (f, rows), = scheduler.answer(3.0)
    assert [r.sample for r in rows] == ["s0", None, None, None]
    assert [r.key for r in rows] == [SampleKey("a.mp4", 0), SampleKey("a.mp4", 1), SampleKey("a.mp4", 2), None]
    assert "the decode gave 1 window(s), the manifest 3" in rows[1].reason
    assert scheduler.task_for("w", 2.0) is None


def test_a_fetch_far_past_the_epochs_end_is_padding_and_the_server_serves_on():
    """A careless or hostile reader asks positions far past the epoch's end (the wire takes any
    start): they are padding rows, and the answer times the server keeps reach only the plan's
    positions (kept to the fetch's stop, they asked for 8 TB and the server died), so it serves on."""
    scheduler = PlanScheduler(Manifest.of({"a.mp4": 3}), 0, 1, ("voxels",), lookahead=0)
    far = 2 ** 40
    scheduler.fetch("c", 1, 0, far, far + 4, 0.0)
    (f, rows), = scheduler.answer(1.0)
    assert f.start == far and [r.sample for r in rows] == [None] * 4 and {r.key for r in rows} == {None}
    scheduler.fetch("c", 2, 0, 0, 1, 2.0)
    t = scheduler.task_for("w", 2.0)
    scheduler.sample("w", t.task, SampleKey("a.mp4", 0), 3.0, lambda: "s0")
    assert [[r.sample for r in rows] for _, rows in scheduler.answer(3.0)] == [["s0"]]


def test_a_window_the_worker_reports_failed_is_a_padding_row_with_its_reason():
    # the wire's Done keys a failed window by its digits
    scheduler = PlanScheduler(Manifest.of({"a.mp4": 3}), 0, 1, ("voxels",), lookahead=0)
    scheduler.fetch("c", 1, 0, 0, 3, 0.0)
    t = scheduler.task_for("w", 0.0)
    for w in (0, 2):
        scheduler.sample("w", t.task, SampleKey("a.mp4", w), 1.0, lambda w=w: f"s{w}")
    scheduler.done("w", t.task, 3, {"1": "window 1: a frame of another size"}, None, "failed")
    (f, rows), = scheduler.answer(2.0)
    assert [r.sample for r in rows] == ["s0", None, "s2"] and rows[1].reason == "window 1: a frame of another size"
    assert scheduler.task_for("w", 3.0) is None


def _pass(scheduler, worker, now, windows, error=None):
    """One worker's pass: a task, its samples up to ``windows`` (those not skipped), its end."""
    t = scheduler.task_for(worker, now)
    for w in range(windows):
        if (w, 0) not in t.skip:
            scheduler.sample(worker, t.task, SampleKey(t.video, w), now, lambda w=w: f"s{w}")
    scheduler.done(worker, t.task, windows, {}, error, "error" if error else "")
    return t


@pytest.mark.parametrize("known", [True, False])
def test_a_pass_stopped_by_a_store_error_is_asked_again_and_fixes_no_slots(known):
    """A store failing for a while cuts a pass short: the video is decoded again (skipping what
    was made), and its slots, where not known, come from the whole pass, so the plan is the one a
    server that never saw the error lists."""
    scheduler = PlanScheduler(Manifest.of({"a.mp4": 4 if known else None}), 0, 1, ("voxels",), lookahead=0)
    scheduler.fetch("c", 1, 0, 0, 4, 0.0)
    _pass(scheduler, "w", 0.0, 1, "reading a.mp4: the store timed out")
    assert scheduler.answer(1.0) == [] and scheduler.slots.samples["a.mp4"] == (4 if known else None)
    again = _pass(scheduler, "w", 2.0, 4)
    assert again.video == "a.mp4" and (0, 0) in again.skip
    (f, rows), = scheduler.answer(3.0)
    assert [r.sample for r in rows] == ["s0", "s1", "s2", "s3"] and scheduler.slots.samples["a.mp4"] == 4


def test_a_file_that_breaks_at_one_place_costs_a_few_passes_once_then_pads():
    """A file broken at one place stops each pass there: after PASS_ATTEMPTS passes its slots
    are what they gave, and a later epoch's pass that stops is final at once."""
    scheduler = PlanScheduler(Manifest.of({"a.mp4": None}), 0, 1, ("voxels",), lookahead=0)
    scheduler.fetch("c", 1, 0, 0, 3, 0.0)
    for attempt in range(PASS_ATTEMPTS):
        assert scheduler.answer(float(attempt)) == [] and scheduler.slots.samples["a.mp4"] is None
        _pass(scheduler, "w", float(attempt), 2, "decoding a.mp4: invalid data at packet 97")
    (f, rows), = scheduler.answer(9.0)  # learned from the broken passes: 2 windows, the third row past the end
    assert [r.sample for r in rows] == ["s0", "s1", None] and rows[2].key is None
    scheduler.fetch("c", 2, 1, 0, 2, 10.0)  # the next epoch: one pass, its error final at once
    _pass(scheduler, "w", 10.0, 1, "decoding a.mp4: invalid data at packet 97")
    (f, rows), = scheduler.answer(11.0)
    assert rows[0].sample == "s0" and rows[1].reason == "decoding a.mp4: invalid data at packet 97"
    assert scheduler.task_for("w", 12.0) is None



def test_a_plan_unfolding_decodes_the_production_order_in_turn_and_answers_once_decided():
    """No slot known: the first fetch waits on the videos whose first decodes decide its
    positions, taken in the production order; each decode's windows unfold the plan, and the
    rows are the whole plan's."""
    slots = {f"v{i}.mp4": 1 + i % 3 for i in range(6)}
    scheduler = PlanScheduler(Manifest.of({v: None for v in slots}), 7, 2, ("voxels",), lookahead=0)
    whole = EpochPlan(Manifest.of(slots), 7, 0, 2)
    scheduler.fetch("c", 1, 0, 0, 2, 0.0)
    assert scheduler.answer(0.0) == [] and scheduler.slots.epoch_samples is None
    decoded = []
    while not (answered := scheduler.answer(1.0)):
        t = scheduler.task_for("w", 1.0)
        decoded.append(t.video)
        for i in range(slots[t.video]):
            scheduler.sample("w", t.task, SampleKey.at(t.video, i), 1.0, lambda k=(t.video, i): k)
        scheduler.done("w", t.task, slots[t.video], {}, None)
    assert decoded == whole.videos[:len(decoded)] and len(decoded) < len(slots)  # in turn, not every video
    (f, rows), = answered
    assert [r.key for r in rows] == whole.keys(0, 2) and all(r.sample is not None for r in rows)
    assert scheduler.plan(0).known >= 2 and not scheduler.plan(0).complete


def test_decode_ahead_goes_on_into_the_next_epoch_within_the_lookahead():
    # a trainer reading the end of epoch 0 finds epoch 1's first samples made, so one worker never
    # waits at the boundary; what is made ahead stays within the lookahead
    m = Manifest.of({f"v{i}.mp4": 2 for i in range(4)})
    scheduler = PlanScheduler(m, 0, 1, ("voxels",), lookahead=4, keep_samples=0)
    scheduler.fetch("c", 1, 0, 6, 8, 0.0)  # the epoch's last batch
    made = []
    while (t := scheduler.task_for("w", 0.0)) is not None:
        made.append((t.epoch, t.video))
        for i in range(2):
            scheduler.sample("w", t.task, SampleKey.at(t.video, i), 0.0, lambda: "s")
        scheduler.done("w", t.task, 2, {}, None)
    waited = {(0, EpochPlan(m, 0, 0, 1).key(p).video) for p in (6, 7)}
    assert set(made[:len(waited)]) == waited
    ahead = made[len(waited):]
    assert ahead and {e for e, _ in ahead} == {1}
    assert ahead[0][1] == EpochPlan(m, 0, 1, 1).key(0).video  # the next epoch's first position first
    assert sum(1 for sk in scheduler.store if sk[0] == 1) <= scheduler.lookahead + 1


def _work(scheduler, now):
    """Idle workers' tasks until none: each video's 2 samples; the (epoch, video) made, in order."""
    made = []
    while (t := scheduler.task_for("w", now)) is not None:
        made.append((t.epoch, t.video))
        for i in range(2):
            scheduler.sample("w", t.task, SampleKey.at(t.video, i), now, lambda: "s")
        scheduler.done("w", t.task, 2, {}, None)
    return made


def test_a_reader_slower_than_the_workers_finds_its_next_batches_made_across_epochs():
    """Decode-ahead follows the furthest fetch of each epoch, answered or not: a reader that
    has every fetch answered (its loop busy with a step) still finds the next positions made,
    past the epoch's end too, and after more epochs than the server keeps plans for; what a
    reader has fetched of an epoch it moved into is not made again."""
    m = Manifest.of({f"v{i}.mp4": 2 for i in range(4)})
    scheduler = PlanScheduler(m, 0, 1, ("voxels",), lookahead=4, keep_samples=0)
    for epoch in range(6):  # more than PLANS_KEPT epochs, read in turn
        for start in range(0, 8, 2):
            scheduler.fetch("c", 1, epoch, start, start + 2, float(epoch))
            _work(scheduler, float(epoch))
            assert len(scheduler.answer(float(epoch))) == 1
            assert not scheduler.pending
        _work(scheduler, float(epoch))  # nothing pending: made ahead of the last fetch, into the next epoch
        nxt = EpochPlan(m, 0, epoch + 1, 1)
        assert all((epoch + 1, nxt.key(p)) in scheduler.store for p in (0, 1)), epoch  # the next batch is made
    scheduler.fetch("c", 1, 6, 0, 2, 6.0)  # the reader moved into epoch 6: its positions after 2 lead
    scheduler.answer(6.0)
    later = {EpochPlan(m, 0, 6, 1).key(p).video for p in range(2, 8)}
    assert all(e == 6 and v in later for e, v in _work(scheduler, 6.0))


def test_workers_make_the_outputs_fetches_ask_for_and_a_new_one_remakes_what_lacks_it():
    m = Manifest.of({"a.mp4": 2})
    scheduler = PlanScheduler(m, 0, 1, ("voxels", "frames", "flow"), lookahead=0)
    scheduler.fetch("c", 1, 0, 0, 1, 0.0, ("voxels",))
    narrow = scheduler.task_for("w1", 0.0)
    assert narrow.outputs == ("voxels",)
    assert scheduler.sample("w1", narrow.task, SampleKey("a.mp4", 0), 1.0, lambda: "voxels only")
    (f, rows), = scheduler.answer(1.0)
    assert rows[0].sample == "voxels only"
    scheduler.fetch("d", 2, 0, 0, 2, 2.0, ("flow", "voxels"))  # flow: what was made lacks it
    assert scheduler.making.now == ("voxels", "flow") and not scheduler.store
    assert not scheduler.sample("w1", narrow.task, SampleKey("a.mp4", 1), 3.0, lambda: "voxels only")
    assert scheduler.task_for("w2", 3.0) is None  # the video is being decoded: it ends first
    scheduler.done("w1", narrow.task, 2, {}, None)
    assert not scheduler.answer(4.0) and not scheduler.failed
    wide = scheduler.task_for("w2", 4.0)
    assert wide.outputs == ("voxels", "flow")
    for i in range(2):
        assert scheduler.sample("w2", wide.task, SampleKey("a.mp4", i), 5.0, lambda i=i: f"wide {i}")
    (f, rows), = scheduler.answer(5.0)
    assert [r.sample for r in rows] == ["wide 0", "wide 1"]
    with pytest.raises(ValueError, match="polarity_counts"):
        scheduler.fetch("e", 3, 0, 0, 1, 6.0, ("polarity_counts",))


def test_readers_of_as_many_epochs_as_the_kept_plans_rebuild_none_to_decode_ahead():
    """Four jobs each at the last batch of its own epoch, every fetch answered, the kept plans
    theirs: decode-ahead into a next epoch would build a plan that drops one of theirs, to be
    built again at once; it builds none."""
    m = Manifest.of({f"v{i}.mp4": 2 for i in range(4)})
    scheduler = PlanScheduler(m, 0, 1, ("voxels",), lookahead=0, keep_samples=0)
    for epoch in range(0, 8, 2):
        scheduler.fetch(("job", epoch), 1, epoch, 6, 8, 0.0)
        _work(scheduler, 0.0)
        scheduler.answer(0.0)
    assert list(scheduler.plans) == [0, 2, 4, 6]
    scheduler.lookahead, built = 64, scheduler.plans_built
    for turn in range(3):
        _work(scheduler, 1.0 + turn)
        assert scheduler.plans_built == built, turn


def test_a_make_asked_again_while_it_waits_is_no_new_demand():
    """A reader asks a make again when it has waited ``retry_s`` for it (a lost or late reply);
    a host whose queue holds it longer sees it twice. The retry replaces the make it repeats
    (the reader awaits the new one only: rows sent once, the queue a host says counted once),
    and what ``v2v_samples_asked_total`` counts (the demand an HPA sizes the fleet on) is the
    samples no make of that reader waiting here names already: the retry adds none, another
    reader's make of the same samples adds them."""
    m = Manifest.of({"a.mp4": 4, "b.mp4": 2})
    scheduler = PlanScheduler(m, 0, 1, ("voxels",), lookahead=0)
    assert scheduler.make("r", 1, 0, "a.mp4", (0, 1), 0.0) == 2
    assert scheduler.make("r", 2, 0, "a.mp4", (0, 1), 10.0) == 0  # its retry
    assert [o.request for o in scheduler.orders.waiting] == [2] and scheduler.queued() == 2
    assert scheduler.make("r", 3, 0, "a.mp4", (1, 2), 11.0) == 1  # one sample new
    assert [o.request for o in scheduler.orders.waiting] == [2, 3]  # make 2 asks sample 0 too: awaited still
    assert scheduler.make("s", 1, 0, "a.mp4", (0, 1), 11.0) == 2  # another reader's
    assert scheduler.make("r", 4, 0, "b.mp4", (0,), 11.0) == 1  # another video
    assert scheduler.make("r", 5, 0, "b.mp4", None, 11.0) == 0  # its windows only


def test_a_fleet_hosts_decode_is_kept_for_the_makes_that_follow_it_in_a_full_store():
    """A make of a video's windows decodes all its samples; the reader then asks each as its plan
    reaches it, the shuffle buffer spreading them over positions far apart. With the store full
    of other samples, those of the video a make waits on, and then of one a make was answered
    for, stay until asked: no video is decoded twice (a fleet host made a third of its samples
    twice when they were dropped as spare)."""
    m = Manifest.of({"a.mp4": None, **{f"o{i}.mp4": 2 for i in range(6)}})
    scheduler = PlanScheduler(m, 0, 1, ("voxels",), lookahead=0, keep_samples=0)
    for i in range(6):  # other videos' second samples, made and never asked: the store is over its bound
        scheduler.make("r", 10 + i, 0, f"o{i}.mp4", (0,), 0.0)
        t = scheduler.task_for("w", 0.0)
        for k in range(2):
            scheduler.sample("w", t.task, SampleKey(t.video, k), 0.0, lambda: "other")
        scheduler.done("w", t.task, 2, {}, None)
        scheduler.answer(0.0)
    t0 = TOLD_S + 1  # the other videos' makes were answered long ago
    scheduler.make("r", 1, 0, "a.mp4", None, t0)  # its windows
    t = scheduler.task_for("w", t0)
    assert t.video == "a.mp4"
    for i in range(3):
        scheduler.sample("w", t.task, SampleKey("a.mp4", i), t0, lambda i=i: f"a {i}")
        scheduler.answer(t0)  # a trim at each turn, the make of windows still waiting
    scheduler.done("w", t.task, 3, {}, None)
    (o, rows), = scheduler.answer(t0)
    assert o.ordinals is None and rows == [] and scheduler.slots.samples["a.mp4"] == 3
    assert not any(k.video.startswith("o") for _, k in scheduler.store)  # the spare ones went
    for i in (2, 0, 1):  # asked one by one, as a plan puts them
        scheduler.make("r", 2 + i, 0, "a.mp4", (i,), t0 + 1 + i)
        assert scheduler.task_for("w", t0 + 1 + i) is None, i  # no decode again
        (o, rows), = scheduler.answer(t0 + 1 + i)
        assert [r.sample for r in rows] == [f"a {i}"]


class _Host:
    """One server's scheduler at its defaults (lookahead: a shuffle buffer; kept once fetched: a
    batch of 12) and ``workers`` workers making a sample a tick each, read by jobs that fetch
    consecutive batches, up to ``ahead`` more in flight."""

    def __init__(self, videos=150, per=10, workers=1, known=True):
        self.m = Manifest.of({f"v{i:03d}.mp4": per if known else None for i in range(videos)})
        self.s = PlanScheduler(self.m, 0, 64, ("voxels",), lookahead=64, keep_samples=12)
        self.per, self.workers, self.total = per, workers, videos * per
        self.now, self.tasks, self.request, self.made = 0.0, {}, 0, {}
        self.decodes = {}  # epoch -> decodes started (a video's task, whatever it skips)

    def _made(self, epoch):
        self.made[epoch] = self.made.get(epoch, 0) + 1
        return "s"

    def tick(self):
        answered = self.s.answer(self.now)
        for w in range(self.workers):
            if w not in self.tasks and (t := self.s.task_for(w, self.now)) is not None:
                self.tasks[w] = [t, iter([i for i in range(self.per) if (i, 0) not in t.skip])]
                self.decodes[t.epoch] = self.decodes.get(t.epoch, 0) + 1
            if w in self.tasks:
                t, todo = self.tasks[w]
                i = next(todo, None)
                if i is None:
                    self.s.done(w, t.task, self.per, {}, None)
                    del self.tasks[w]
                else:
                    self.s.sample(w, t.task, SampleKey.at(t.video, i), self.now, lambda e=t.epoch: self._made(e))
        self.now += 1.0 / self.workers
        return answered

    def read(self, client, epoch, batch, start=0, stop=None, ahead=0):
        """Samples of ``epoch`` made per sample read while ``client`` reads ``start .. stop - 1`` of it."""
        stop, pos, waiting, made = self.total if stop is None else stop, start, set(), self.made.get(epoch, 0)
        while pos < stop or waiting:
            while len(waiting) <= ahead and pos < stop:
                self.request += 1
                self.s.fetch(client, self.request, epoch, pos, min(stop, pos + batch), self.now)
                waiting.add(self.request)
                pos += batch
            waiting -= {f.request for f, _ in self.tick() if f.client == client}
        return (self.made.get(epoch, 0) - made) / (stop - start)


@pytest.mark.parametrize("batch", [1, 4, 12, 16, 32])
def test_a_host_makes_each_sample_once_at_any_batch_size(batch):
    """Whole epochs read in batches of 1-32, one fetch or three in flight: the store's bound
    leaves out the batches pending fetches name, and what it must drop goes in the order the
    readers reach it last, so no sample the plan reaches is dropped and made again (at batch 12
    and over, the oldest unfetched samples went first: the shuffle buffer's, read next, and each
    drop decoded a video again: 1.5-3.7 made per sample read)."""
    for ahead in (0, 2):
        host = _Host(videos=60, workers=2)
        made = [host.read("job", epoch, batch, ahead=ahead) for epoch in range(3)]
        assert max(made) <= 1.02, (ahead, made)


def test_a_job_started_after_another_was_cut_off_mid_epoch_makes_each_sample_once():
    """A job cut off mid-epoch leaves its made-ahead samples and its head; a job started then
    reads the epoch from its start: the cut-off job's head is idle once it asked nothing for a few
    of its own intervals, so what it left far ahead of the new job's head is kept beside the
    bound until that head reaches it, and the new job's samples stay. With the slots learned as
    videos are decoded (a corpus without an index), what the cut-off job left deciding the plan's
    next positions counts as samples at the plan's edge: kept while far, dropped furthest first
    (kept unconditionally, it held the store and the new job's samples were dropped: 1.2 made a
    sample read). What the cut-off job was given is not taken as read by the new job's readers
    (taken so, decodes ahead for the new job skipped it, and each of those videos was decoded
    again when the new job got there: 175 decodes of 150 videos)."""
    for known in (True, False):
        for cut in (100, 700, 1400):
            host = _Host(known=known)
            host.read("cut off", 0, 12, 0, cut, ahead=3)
            before = host.decodes[0]
            made = [host.read("new", epoch, 12, ahead=1) for epoch in range(2)]
            assert max(made) <= 1.02, (known, cut, made)
            # each video decoded once for the new job: none again for what the cut-off job was given
            decodes = [host.decodes[0] - before, host.decodes[1]]
            assert max(decodes) <= 1.02 * len(host.m.slots), (known, cut, decodes)
            # kept, made ahead, a video, the batches asked, and the cut-off job's stock beside
            assert len(host.s.store) <= 12 + 2 * 64 + 10 + 2 * 12, (known, cut)


def test_a_bad_seed_range_is_one_usage_error_naming_the_option(capsys):
    from harness.plan_world import main
    for bad in ("x:y", "5:3", "7"):
        with pytest.raises(SystemExit) as e:
            main(["--seeds", bad])
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert "argument --seeds" in err and repr(bad) in err and "Traceback" not in err


def _read_as_job(host, readers, epoch, batch, start=0, stop=None, spread=3, client="reader"):
    """Samples of ``epoch`` made per sample read while ``readers`` processes of one job read
    ``start .. stop - 1`` of it, each its own client (``(client, r)``: its connection) and every
    ``readers``-th batch, two fetches in flight each, reader ``r`` taking its answers every
    ``1 + r % spread`` ticks (the heads spread)."""
    stop, made = host.total if stop is None else stop, host.made.get(epoch, 0)
    nxt = {r: start + r * batch for r in range(readers)}
    waiting, turn = {}, 0
    while any(p < stop for p in nxt.values()) or waiting:
        turn += 1
        for r in range(readers):
            while turn % (1 + r % spread) == 0 and sum(1 for c in waiting.values() if c == r) < 2 and nxt[r] < stop:
                host.request += 1
                host.s.fetch((client, r), host.request, epoch, nxt[r], min(stop, nxt[r] + batch), host.now)
                waiting[host.request] = r
                nxt[r] += readers * batch
        for f, _ in host.tick():
            waiting.pop(f.request, None)
    return (host.made.get(epoch, 0) - made) / (stop - start)


@pytest.mark.parametrize("readers", [3, 6])
def test_the_readers_of_one_job_find_what_the_others_read_not_made_again(readers):
    """Each reader of a job (a rank, a DataLoader worker) has its own connection and its own head,
    and reads every ``readers``-th batch: what lies ahead of the slowest head was read by the
    others. Decode-ahead for a head skips what a reader was answered, and a decode skips it too,
    so nothing is made again for the slow heads (1.1-1.2 made a sample read where it was)."""
    for batch in (1, 3):
        host = _Host(videos=20, per=3, workers=3)
        host.s = PlanScheduler(host.m, 0, 16, ("voxels",), lookahead=16, keep_samples=0)
        made = [_read_as_job(host, readers, epoch, batch) for epoch in range(2)]
        assert max(made) <= 1.02, (batch, made)


def _old_job(host, readers, stop):
    """A job of ``readers`` processes reading positions ``0 .. stop - 1`` of epoch 0 a step at a
    time, 4 s between steps (a slow trainer), then killed: its heads stay moving a few intervals."""
    for step in range(stop // readers):
        waiting = set()
        for r in range(readers):
            host.request += 1
            host.s.fetch(("old", r), host.request, 0, step * readers + r, step * readers + r + 1, host.now)
            waiting.add(host.request)
        while waiting:
            waiting -= {f.request for f, _ in host.tick()}
        for _ in range(12):
            host.tick()


def test_a_job_resumed_in_new_processes_makes_nothing_again_for_the_heads_it_left():
    """A job resumed from its checkpoint in new processes leaves its old readers' heads behind,
    slow ones, moving for a few of their intervals more. What the new readers were answered is
    read, however far behind them and whichever of them started first, and what the old job read
    before the checkpoint is read too: neither is made ahead for the old heads nor made again by a
    decode (counted by the latest few answers a head had, or only since the last new reader's
    first fetch, they were: 1.03-1.15 made a sample read; the seeded world's seeds 3670 and 5862)."""
    for readers in (1, 4, 6):
        for checkpoint in (12, 24, 36):
            host = _Host(videos=20, per=3, workers=3)
            host.s = PlanScheduler(host.m, 0, 16, ("voxels",), lookahead=16, keep_samples=0)
            _old_job(host, readers, checkpoint)
            _read_as_job(host, readers, 0, 1, start=checkpoint)
            _read_as_job(host, readers, 1, 1)
            made = (host.made[0] + host.made[1]) / (2 * host.total)
            assert made <= 1.02, (readers, checkpoint, made)


def test_a_job_paused_keeps_what_it_made_ahead_and_makes_nothing_again():
    """Every reader of a job pauses (an evaluation, a checkpoint saved) for longer than a head
    stays moving: the stock made ahead of it is kept by its furthest fetch and made ahead up to
    the lookahead, and nothing is made again while it waits or once it reads on (taken as
    reached by no reader, the stock went oldest first and was made ahead again, over and over:
    1.08-1.09 made a sample read)."""
    for readers in (2, 4, 6):
        host = _Host(videos=20, per=3, workers=3)
        host.s = PlanScheduler(host.m, 0, 16, ("voxels",), lookahead=16, keep_samples=0)
        _read_as_job(host, readers, 0, 1, 0, 12)
        made = host.made[0]
        for _ in range(900):  # 5 minutes
            host.tick()
        assert host.made[0] - made <= 16 + 3, readers  # the lookahead, and a video's samples
        _read_as_job(host, readers, 0, 1, start=12)
        _read_as_job(host, readers, 1, 1)
        made = (host.made[0] + host.made[1]) / (2 * host.total)
        assert made <= 1.02, (readers, made)


def test_a_plan_unfolding_keeps_what_its_next_positions_need():
    """No corpus index: the first fetch waits on the videos whose slots decide its positions, and
    several workers decode long ones at once. Their samples no position holds yet count where the
    plan will place them (their order in production: the shuffle buffer draws a sample about
    there), and those of the videos a pending fetch waits on are that fetch's: the ones read next
    stay, the ones produced last go first (dropped oldest first, as samples at the plan's edge:
    1.04-1.1 made a sample read)."""
    for workers, batch in ((2, 1), (3, 8)):
        host = _Host(videos=4, per=20, workers=workers, known=False)
        host.s = PlanScheduler(host.m, 0, 16, ("voxels",), lookahead=16, keep_samples=batch)
        made = [host.read("job", epoch, batch) for epoch in range(2)]
        assert max(made) <= 1.02, (workers, batch, made)


def test_long_videos_of_unknown_slots_decoded_at_once_while_the_plan_unfolds_are_kept_until_read():
    """No corpus index and a small store: the first fetch waits on the plan to unfold, each worker
    takes a video of 40 samples, more than the store's bound holds. They are that fetch's, read in
    production order: kept past the bound until fetched (dropped, they were made again: 1.23 made
    a sample read with 2 workers, 1.48 with 3)."""
    for workers, batch in ((2, 1), (3, 1), (3, 4)):
        host = _Host(videos=4, per=40, workers=workers, known=False)
        host.s = PlanScheduler(host.m, 0, 1, ("voxels",), lookahead=1, keep_samples=batch)
        made = [host.read("job", epoch, batch) for epoch in range(2)]
        assert max(made) <= 1.02, (workers, batch, made)
        assert len(host.s.store) <= batch + 1 + workers * 40 + batch, (workers, batch)


def test_a_job_rolled_back_to_the_epochs_start_finds_the_next_epochs_first_samples_kept():
    """A job read an epoch to its end (the next epoch's first samples made ahead), then rolled back
    to the epoch's start in new processes. While it reads the epoch again, the next epoch's
    samples lie past its heads' end of the epoch: kept in the order the heads reach them (dropped
    first, as of an epoch no reader reaches, they were made again)."""
    host = _Host(videos=60, workers=2)
    host.read("first", 0, 12, ahead=1)
    for _ in range(20):
        host.tick()  # the next epoch's first samples, made ahead
    host.read("again", 0, 12, ahead=1)
    host.read("again", 1, 12, ahead=1)
    assert host.made[1] / host.total <= 1.02, host.made[1] / host.total  # the samples made ahead count

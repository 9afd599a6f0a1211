"""Shuffled epochs without sockets: the epoch order of the videos (``batcher.video_order``, the
scheduler), the shuffle buffer of open batches (``batcher.Batcher``), its zero-copy buffers
(``assembly.BatchAssembler`` lanes), and the settings' errors."""
from __future__ import annotations

import collections

import numpy as np
import pytest

from v2v_server.delivery.batcher import Batcher, video_order
from v2v_server.delivery.core import DeliveryCore, DeliveryPolicy
from v2v_server.delivery.ledger import DeliveryLedger
from v2v_server.delivery.schedule import EpochScheduler
from v2v_server.ops.config import ServeConfig
from v2v_server.ray_data import RayCorpus, epoch_descriptors
from v2v_server.service.assembly import BatchAssembler, make_batch
from v2v_wire.ids import SampleKey
from v2v_wire.messages import Hello

VIDEOS = [f"v{i:02d}.mp4" for i in range(24)]


def handed_out(sched: EpochScheduler):
    """(epoch, video) of every task one worker gets, each finished with no windows."""
    order = []
    while (task := sched.next_task("w", 0.0)) is not None:
        order.append((task.epoch, task.video))
        sched.task_done(task.task_id, "w", windows=0)
    return order


def test_epoch_orders_differ_between_epochs_and_repeat_on_a_restart():
    first = handed_out(EpochScheduler(VIDEOS, epochs=3, shuffle_seed=5))
    again = handed_out(EpochScheduler(VIDEOS, epochs=3, shuffle_seed=5))  # a restarted server
    by_epoch = {e: [v for ee, v in first if ee == e] for e in range(3)}
    assert first == again
    assert all(sorted(vs) == VIDEOS for vs in by_epoch.values())  # each epoch: every video once
    assert len({tuple(vs) for vs in by_epoch.values()}) == 3 and tuple(by_epoch[0]) != tuple(VIDEOS)
    other_seed = handed_out(EpochScheduler(VIDEOS, epochs=1, shuffle_seed=6))
    assert [v for _, v in other_seed] != by_epoch[0]


def test_a_shard_gets_the_global_order_restricted_to_its_videos():
    """A video's place depends on (seed, epoch, its path) only: whatever the shard count, each
    shard hands its videos out in the order they have in the whole corpus's permutation."""
    whole = video_order(VIDEOS, 3, 7)
    for count in (2, 3, 5):
        for index in range(count):
            mine = VIDEOS[index::count]
            assert video_order(mine, 3, 7) == [v for v in whole if v in set(mine)]
    assert video_order(list(reversed(VIDEOS)), 3, 7) == whole  # the listing's order does not matter


def test_shuffle_none_keeps_the_listing_order_and_arrival_order():
    """``--shuffle none``: one worker gets the videos in the listing's order, epoch after epoch,
    and the batcher keeps the samples' arrival order."""
    policy = DeliveryPolicy(shuffle="none", shuffle_buffer=64)
    assert policy.lanes == 1
    sched = EpochScheduler(["c.mp4", "a.mp4", "b.mp4"], epochs=2)
    assert handed_out(sched) == [(e, v) for e in (0, 1) for v in ("c.mp4", "a.mp4", "b.mp4")]
    ledger = DeliveryLedger(lease_s=1.0, client_timeout_s=100.0, max_credits=64)
    batcher = Batcher(2, list, ledger, lanes=policy.lanes)
    keys = [SampleKey("c.mp4", w, 0) for w in range(3)] + [SampleKey("a.mp4", 0, 0)]
    for k in keys:
        batcher.add(0, ("voxels",), k, k, batcher.lane(0, ("voxels",)))
    assert [ledger.batches[i].keys for i in ledger.ready] == [keys[:2], keys[2:]]


def feed(batcher: Batcher, keys, epoch=0, outputs=("voxels",)):
    for k in keys:
        batcher.add(epoch, outputs, k, k, batcher.lane(epoch, outputs))


def sequential_keys(videos=VIDEOS, windows=5):
    """What one worker makes: each video's windows in order, video after video."""
    return [SampleKey(v, w, 0) for v in videos for w in range(windows)]


def test_the_shuffle_buffer_batches_every_sample_once_and_mixes_one_workers_videos():
    keys = sequential_keys()
    ledger = DeliveryLedger(lease_s=1.0, client_timeout_s=100.0, max_credits=64)
    batcher = Batcher(8, list, ledger, lanes=4, seed=1)
    feed(batcher, keys)
    held, capacity = batcher.fill()
    assert capacity == 32 and 0 < held <= capacity and batcher.waiting()
    batcher.flush(lambda e: True)
    assert batcher.fill() == (0, 32) and not batcher.waiting()
    batches = [ledger.batches[i].keys for i in ledger.ready]
    assert collections.Counter(k for b in batches for k in b) == collections.Counter(keys)
    assert [len(b) for b in batches] == [8] * 15  # 120 samples: only the last batch may be smaller
    mixed = np.mean([len({k.video for k in b}) for b in batches])
    plain = Batcher(8, list, DeliveryLedger(lease_s=1.0, client_timeout_s=100.0, max_credits=64), lanes=1)
    feed(plain, keys)
    plain.flush(lambda e: True)
    unmixed = np.mean([len({k.video for k in plain.ledger.batches[i].keys}) for i in plain.ledger.ready])
    assert unmixed == 2.4 and mixed >= 1.5 * unmixed, (mixed, unmixed)


def test_the_shuffle_buffer_repeats_its_batches_for_the_same_arrivals_and_seed():
    def batches(seed):
        ledger = DeliveryLedger(lease_s=1.0, client_timeout_s=100.0, max_credits=64)
        b = Batcher(8, list, ledger, lanes=4, seed=seed)
        feed(b, sequential_keys())
        b.flush(lambda e: True)
        return [ledger.batches[i].keys for i in ledger.ready]

    assert batches(1) == batches(1) and batches(1) != batches(2)


def test_leftovers_wait_for_the_end_of_their_epoch_and_drops_leave_the_buffer():
    ledger = DeliveryLedger(lease_s=1.0, client_timeout_s=100.0, max_credits=64)
    batcher = Batcher(4, list, ledger, lanes=3, seed=0)
    feed(batcher, sequential_keys(VIDEOS[:2], 2), epoch=0)
    feed(batcher, sequential_keys(VIDEOS[2:4], 2), epoch=1)
    gone = batcher.drop(lambda e, k: e == 1 and k.video == VIDEOS[2])
    assert [(e, sorted(ks)) for e, ks in gone] == [(1, [SampleKey(VIDEOS[2], 0, 0), SampleKey(VIDEOS[2], 1, 0)])]
    batcher.flush(lambda e: e == 0)
    made = [ledger.batches[i] for i in ledger.ready]
    assert {b.epoch for b in made} == {0}
    assert sorted(k for b in made for k in b.keys) == sorted(sequential_keys(VIDEOS[:2], 2))
    assert batcher.fill() == (2, 12)  # epoch 1's two samples left, in one group of 3 x 4 rows


def test_a_full_open_batch_is_its_buffers_rows_and_goes_zero_copy():
    """Each open batch fills rows of its own buffer (``BatchAssembler.place`` lane), so a batch
    the shuffle buffer makes is consecutive rows of one buffer: ``make_batch`` copies nothing."""
    ledger = DeliveryLedger(lease_s=1.0, client_timeout_s=100.0, max_credits=64)
    batcher = Batcher(4, make_batch, ledger, lanes=3, seed=0)
    asm = BatchAssembler(4)
    for i, key in enumerate(sequential_keys(VIDEOS[:6], 2)):
        lane = batcher.lane(0, ("voxels",))
        arrays = {"voxels": np.full((2, 3, 8, 8), i, np.int8)}
        batcher.add(0, ("voxels",), key, asm.place(key.sample_id(), {}, arrays, lane), lane)
    full = [ledger.batches[i] for i in ledger.ready]
    assert full and all(b.payload._rows is not None for b in full)  # views of one buffer's rows
    for b in full:
        assert [int(b.payload.arrays["voxels"][r, 0, 0, 0, 0]) for r in range(4)] == [
            2 * VIDEOS.index(k.video) + k.window for k in b.keys]
    assert len({k.video for b in full for k in b.keys[:4]}) > 2


def test_an_epoch_smaller_than_the_buffer_fills_whole_batches_as_it_comes_zero_copy():
    """12 samples, 16 open batches of 4: told how many samples are still to come, the batcher
    spreads them over 3 open batches only, so 3 full batches (each one buffer's rows) leave as
    the samples arrive and nothing is left for the epoch-end flush to copy."""
    keys = sequential_keys(VIDEOS[:6], 2)
    ledger = DeliveryLedger(lease_s=1.0, client_timeout_s=100.0, max_credits=64)
    batcher = Batcher(4, make_batch, ledger, lanes=16, seed=0)
    asm = BatchAssembler(4)
    for i, key in enumerate(keys):
        lane = batcher.lane(0, ("voxels",), more=len(keys) - 1 - i)
        arrays = {"voxels": np.full((2, 3, 8, 8), i, np.int8)}
        batcher.add(0, ("voxels",), key, asm.place(key.sample_id(), {}, arrays, lane), lane)
    made = [ledger.batches[i] for i in ledger.ready]
    assert [len(b.keys) for b in made] == [4, 4, 4] and not batcher.waiting()
    assert all(b.payload._rows is not None for b in made)  # zero-copy: views of one buffer's rows
    assert sorted(k for b in made for k in b.keys) == sorted(keys)
    assert max(len({k.video for k in b.keys}) for b in made) > 2  # mixed: not 2 videos' runs in a row
    batcher.flush(lambda e: True)
    assert len(ledger.ready) == 3  # nothing left over


def test_a_count_not_a_multiple_of_the_batch_keeps_every_sample_once():
    """13 samples in batches of 4 with the count known: spread over the 4 open batches the count
    needs, every sample is batched once, and the batches made before the flush are full ones (2
    for this seed: at most 3 can fill, as many as the random spread fills)."""
    keys = sequential_keys(VIDEOS[:13], 1)
    ledger = DeliveryLedger(lease_s=1.0, client_timeout_s=100.0, max_credits=64)
    batcher = Batcher(4, list, ledger, lanes=16, seed=3)
    for i, key in enumerate(keys):
        batcher.add(0, ("voxels",), key, key, batcher.lane(0, ("voxels",), more=len(keys) - 1 - i))
    assert len(ledger.ready) >= 2 and all(len(ledger.batches[i].keys) == 4 for i in ledger.ready)
    batcher.flush(lambda e: True)
    assert collections.Counter(k for i in ledger.ready for k in ledger.batches[i].keys) == collections.Counter(keys)


def test_a_large_epoch_mixes_as_without_a_count():
    """While more samples are to come than the buffer holds, a known count changes no choice:
    the same batches form as when the count is unknown."""
    def batches(counted):
        ledger = DeliveryLedger(lease_s=1.0, client_timeout_s=100.0, max_credits=64)
        b = Batcher(8, list, ledger, lanes=4, seed=1)
        keys = sequential_keys()
        for i, k in enumerate(keys[:80]):
            b.add(0, ("voxels",), k, k, b.lane(0, ("voxels",), more=len(keys) - 1 - i if counted else None))
        return [ledger.batches[i].keys for i in ledger.ready]

    assert batches(True) == batches(False) and len(batches(True)) >= 5


def one_worker_stream(policy: DeliveryPolicy, videos, windows: int):
    """One worker makes every window of every video, epoch after epoch, with a trainer joined
    but not reading. Returns ``(on the fly, all)``: epoch -> sizes of the batches made while
    the epoch's samples arrived (no tick yet), and epoch -> every key batched once a tick
    flushed the leftovers."""
    core = DeliveryCore(videos, policy, list)
    core.hello(b"t", Hello(("voxels",), 64), 0.0)
    while (task := core.task_for(b"w", 0.0)) is not None:
        for w in range(windows):
            key = SampleKey(task.video, w, 0)
            assert core.sample(b"w", task.task, key, 0.0, lambda lane, key=key: key)
        core.done(b"w", task.task, windows, {}, None)
    on_the_fly = collections.defaultdict(list)
    for b in core.ledger.batches.values():
        on_the_fly[b.epoch].append(len(b.keys))
    core.tick(0.0)
    every = collections.defaultdict(list)
    for b in core.ledger.batches.values():
        every[b.epoch].extend(b.keys)
    return dict(on_the_fly), dict(every)


@pytest.mark.parametrize("bound,exact_from", [(None, 1), (2, 0)])
def test_the_core_counts_a_small_epoch_and_sends_whole_batches_before_it_ends(bound, exact_from):
    """6 videos of 2 windows, batches of 4, the default buffer (16 open batches): once the
    scheduler knows each file's count (from an earlier epoch's pass, or ``max_samples_per_video``
    bounding it from the start), an epoch's 12 samples make 3 full batches before the epoch's
    jobs end, and the flush adds none; every epoch batches each sample exactly once."""
    videos = VIDEOS[:6]
    bounded = {} if bound is None else {"max_samples_per_video": bound}
    policy = DeliveryPolicy(batch_size=4, epochs=2, shuffle="epoch", shuffle_buffer=64, seed=1,
                            lease_s=100.0, client_timeout_s=100.0, **bounded)
    on_the_fly, every = one_worker_stream(policy, videos, 2)
    for epoch in (0, 1):
        assert collections.Counter(every[epoch]) == collections.Counter(sequential_keys(videos, 2))
    for epoch in range(exact_from, 2):
        assert on_the_fly[epoch] == [4, 4, 4]
    if exact_from == 1:
        assert sum(on_the_fly.get(0, [])) < 12  # epoch 0's counts are unknown until its passes end


def test_shuffle_buffer_rounds_up_to_whole_open_batches():
    assert DeliveryPolicy(batch_size=12, shuffle="epoch", shuffle_buffer=64).lanes == 6
    assert DeliveryPolicy(batch_size=4, shuffle="epoch", shuffle_buffer=64).lanes == 16
    assert DeliveryPolicy(batch_size=12, shuffle="epoch", shuffle_buffer=1).lanes == 1


@pytest.mark.parametrize("kw,field", [({"shuffle": "random"}, "shuffle"), ({"shuffle_buffer": 0}, "shuffle_buffer"),
                                      ({"shuffle_buffer": 10 ** 6}, "shuffle_buffer")])
def test_bad_shuffle_settings_name_the_field(kw, field):
    with pytest.raises(ValueError, match=field):
        ServeConfig(**kw)
    if field == "shuffle" or kw[field] < 1:
        with pytest.raises(ValueError, match=field):
            DeliveryPolicy(**kw)


def test_the_ray_engine_lists_each_epoch_in_the_servers_order():
    corpus = RayCorpus("corpus", {v: 2 for v in VIDEOS}, {})
    served = handed_out(EpochScheduler(VIDEOS, epochs=2, shuffle_seed=5))
    for epoch in (0, 1):
        descs = epoch_descriptors(corpus, epoch, shuffle_seed=5)
        assert [d["video"] for d in descs] == [v for e, v in served if e == epoch]
    assert [d["video"] for d in epoch_descriptors(corpus, 1)] == VIDEOS  # shuffle none: the listing's order


# ---------------------------------------------------------------------------------- live server
def stream_order(corpus, *extra, content: dict = None) -> dict:
    """epoch -> sample ids in the order one trainer received them, from a one-worker server;
    ``content`` gets (epoch, sample id) -> the bytes of its voxels."""
    from harness.serve import ServeProcess
    from v2v_client import V2VPushDataset

    args = ["--videos", str(corpus), "--workers", "1", "--sequence-length", "4", "--crop-size", "32",
            "--max-samples-per-video", "3", "--batch-size", "4", "--shuffle-buffer", "8", "--seed", "2",
            "--flow-preset", "ultrafast", *extra]
    order: dict = {}
    with ServeProcess(args, ready_timeout_s=120) as srv:
        for b in V2VPushDataset(srv.endpoint, outputs=("voxels",), timeout_s=60):
            order.setdefault(int(b["epoch"]), []).extend(b["sample_ids"])
            for sid, v in zip(b["sample_ids"], b["voxels"]):
                (content if content is not None else {})[(int(b["epoch"]), sid)] = v.numpy().tobytes()
        assert srv.wait(30) == 0
    return order


@pytest.mark.timeout(240)
def test_a_served_epoch_has_its_own_order_and_a_restarted_server_repeats_it(tmp_path):
    from harness.corpus import write_video

    corpus = tmp_path / "clips"
    corpus.mkdir()
    for i in range(8):
        write_video(corpus / f"clip{i}.mp4", 61, 64, 48)
    shuffled, plain = {}, {}
    first = stream_order(corpus, "--epochs", "2", content=shuffled)
    assert sorted(first[0]) == sorted(first[1]) and len(set(first[0])) == len(first[0]) == 24  # each once
    assert first[0] != first[1]
    assert stream_order(corpus, "--epochs", "1")[0] == first[0]  # a new server process, the same epoch 0
    listing = stream_order(corpus, "--epochs", "2", "--shuffle", "none", content=plain)
    assert listing[0] == listing[1] != first[0]
    assert plain == shuffled  # each sample's content depends on (seed, epoch, id), not on the order


def test_the_epoch_order_sorts_by_the_hash_of_seed_epoch_and_path():
    import hashlib

    key = lambda v: hashlib.blake2b(f"3/7/{v}".encode(), digest_size=8).digest()  # noqa: E731
    assert video_order(VIDEOS + ["ü/ä.mp4"], 3, 7) == sorted(VIDEOS + ["ü/ä.mp4"], key=key)

"""Shuffled epochs: the epoch order of the videos (``v2v_wire.plan.video_order``, which the plan
and the Ray engine produce in), the settings' errors, and a served epoch's order and content."""
from __future__ import annotations

import hashlib
import subprocess
import sys

import pytest

from v2v_server.delivery.policy import DeliveryPolicy
from v2v_server.ops.config import ServeConfig
from v2v_server.ray_data import RayCorpus, epoch_descriptors
from v2v_wire.plan import EpochPlan, Manifest, video_order

VIDEOS = [f"v{i:02d}.mp4" for i in range(24)]


def test_epoch_orders_differ_between_epochs_and_seeds_and_repeat_on_a_restart():
    by_epoch = {e: video_order(VIDEOS, 5, e) for e in range(3)}
    assert all(sorted(vs) == VIDEOS for vs in by_epoch.values())  # each epoch: every video once
    assert len({tuple(vs) for vs in by_epoch.values()}) == 3 and by_epoch[0] != VIDEOS
    assert video_order(VIDEOS, 6, 0) != by_epoch[0]
    code = "from v2v_wire.plan import video_order; print(video_order([f'v{i:02d}.mp4' for i in range(24)], 5, 1))"
    again = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60)
    assert again.stdout.strip() == repr(by_epoch[1])  # another process (a restarted server) draws the same


def test_a_shard_gets_the_global_order_restricted_to_its_videos():
    """A video's place depends on (seed, epoch, its path) only: whatever the shard count, each
    shard hands its videos out in the order they have in the whole corpus's permutation."""
    whole = video_order(VIDEOS, 3, 7)
    for count in (2, 3, 5):
        for index in range(count):
            mine = VIDEOS[index::count]
            assert video_order(mine, 3, 7) == [v for v in whole if v in set(mine)]
    assert video_order(list(reversed(VIDEOS)), 3, 7) == whole  # the listing's order does not matter


@pytest.mark.parametrize("value", [0, 10 ** 6])
def test_a_bad_shuffle_buffer_names_the_field(value):
    with pytest.raises(ValueError, match="shuffle_buffer"):
        ServeConfig(shuffle_buffer=value)
    with pytest.raises(ValueError, match="shuffle_buffer"):
        DeliveryPolicy(shuffle_buffer=value)


def test_the_ray_engine_lists_each_epoch_in_the_plans_order():
    corpus = RayCorpus("corpus", {v: 2 for v in VIDEOS}, {})
    manifest = Manifest.of({v: 2 for v in VIDEOS})
    for epoch in (0, 1):
        descs = epoch_descriptors(corpus, epoch, shuffle_seed=5)
        assert [d["video"] for d in descs] == EpochPlan(manifest, 5, epoch).videos != VIDEOS
    assert [d["video"] for d in epoch_descriptors(corpus, 1)] == VIDEOS  # no seed: the listing's order


# ---------------------------------------------------------------------------------- live server
def stream_order(corpus, *extra, epochs=2, content: dict = None) -> dict:
    """epoch -> sample ids in the order one trainer reads them (``set_epoch`` for each), from a
    one-worker server; ``content`` gets (epoch, sample id) -> the bytes of its voxels."""
    from harness.serve import ServeProcess
    from v2v_client import V2VStreamDataset

    args = ["--videos", str(corpus), "--workers", "1", "--sequence-length", "4", "--crop-size", "32",
            "--max-samples-per-video", "3", "--batch-size", "4", "--shuffle-buffer", "8", "--seed", "2",
            "--flow-preset", "ultrafast", *extra]
    order: dict = {}
    with ServeProcess(args, ready_timeout_s=120) as srv:
        ds = V2VStreamDataset(srv.endpoint, outputs=("voxels",), raw=True, timeout_s=60)
        for epoch in range(epochs):
            ds.set_epoch(epoch)
            for b in ds:
                assert int(b["epoch"]) == epoch
                for sid, pad, v in zip(b["sample_ids"], b["padding"].tolist(), b["voxels"]):
                    if not pad:
                        order.setdefault(epoch, []).append(sid)
                        (content if content is not None else {})[(epoch, sid)] = v.numpy().tobytes()
    return order


@pytest.mark.timeout(240)
def test_a_served_epoch_has_its_own_order_and_a_restarted_server_repeats_it(tmp_path):
    from harness.corpus import write_video

    corpus = tmp_path / "clips"
    corpus.mkdir()
    for i in range(8):
        write_video(corpus / f"clip{i}.mp4", 61, 64, 48)
    shuffled, unbuffered = {}, {}
    first = stream_order(corpus, content=shuffled)
    assert sorted(first[0]) == sorted(first[1]) and len(set(first[0])) == len(first[0]) == 24  # each once
    assert first[0] != first[1]
    assert stream_order(corpus, epochs=1)[0] == first[0]  # a new server process, the same epoch 0
    videos_in_turn = stream_order(corpus, "--shuffle-buffer", "1", content=unbuffered)  # each video's windows together
    assert videos_in_turn[0] != first[0] and videos_in_turn[0] != videos_in_turn[1]
    assert all(len({s.split("#")[0] for s in videos_in_turn[0][i:i + 3]}) == 1 for i in range(0, 24, 3))
    assert unbuffered == shuffled  # each sample's content depends on (seed, epoch, id), not on the order


def test_the_epoch_order_sorts_by_the_hash_of_seed_epoch_and_path():
    key = lambda v: hashlib.blake2b(f"3/7/{v}".encode(), digest_size=8).digest()  # noqa: E731
    assert video_order(VIDEOS + ["ü/ä.mp4"], 3, 7) == sorted(VIDEOS + ["ü/ä.mp4"], key=key)

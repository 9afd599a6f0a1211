"""The trainer's read path (``v2v_client.ReadAhead`` over a plan's epochs, docs/trainer_feed.md)
against a real server over the bundled clips: the batches the loop gets are the plan's, in its
order, byte for byte; a checkpoint is the position of what the loop took, not of what the
thread read ahead; a failure reaches the loop as the stream raised it; closing leaves nothing
running."""
from __future__ import annotations

import hashlib
import threading
import time

import pytest
import torch

from v2v_client import PlanEpochs, ReadAhead, V2VStreamDataset
from v2v_server.ops.config import load_config
from v2v_server.service.local import local_server

#: 8 voxel grids a window: the bundled clips give 24 samples an epoch, 6 batches of 4
RECIPE = {"sequence_length": 8, "shuffle_buffer": 8}


@pytest.fixture(scope="module")
def server():
    with local_server(None, workers=2, batch_size=4, config=load_config(None, RECIPE)) as endpoint:
        yield endpoint


def rows(batch):
    """(epoch, sample id or None, voxels digest) of each row of a batch."""
    return [(batch["epoch"], sid, hashlib.sha1(batch["voxels"][j].numpy().tobytes()).hexdigest()[:12])
            for j, sid in enumerate(batch["sample_ids"])]


def take(it, n):
    return [r for _ in range(n) for r in rows(next(it))]


def epochs(server):
    return PlanEpochs(V2VStreamDataset(server, 4, outputs=("voxels",), raw=True, timeout_s=60.0))


def test_read_ahead_yields_the_plans_batches_in_order_across_epochs(server):
    plain = take(iter(epochs(server)), 9)  # 6 steps an epoch: into epoch 1
    ahead = ReadAhead(epochs(server))
    try:
        got = take(iter(ahead), 9)
    finally:
        ahead.close()
    assert got == plain and {e for e, _, _ in got} == {0, 1}


def test_a_checkpoint_is_the_position_the_loop_took_not_what_was_read_ahead(server):
    ahead = ReadAhead(epochs(server), depth=3)
    it = iter(ahead)
    taken = [next(it) for _ in range(2)]
    deadline = time.monotonic() + 60
    while ahead.stream.state_dict()["sample_in_epoch"] < 20 and time.monotonic() < deadline:
        time.sleep(0.05)  # until the thread has read 3 batches past the 2 taken
    assert ahead.stream.state_dict()["sample_in_epoch"] >= 20
    state = ahead.state_dict()
    assert state == taken[-1]["position"] and state["sample_in_epoch"] == 8
    expected = take(it, 4)
    ahead.close()
    resumed = epochs(server)
    resumed.load_state_dict(state)
    again = ReadAhead(resumed)
    try:
        assert take(iter(again), 4) == expected  # nothing lost, nothing repeated
    finally:
        again.close()


def test_before_any_batch_the_checkpoint_is_the_streams_loaded_state(server):
    stream = epochs(server)
    stream.load_state_dict({**stream.state_dict(), "epoch": 2, "sample_in_epoch": 12})
    ahead = ReadAhead(stream).start()
    try:
        s = ahead.state_dict()
        assert (s["epoch"], s["sample_in_epoch"]) == (2, 12)
        b = next(iter(ahead))
        assert (b["epoch"], b["step"]) == (2, 0) and ahead.state_dict()["sample_in_epoch"] == 16
    finally:
        ahead.close()


def test_a_server_gone_mid_read_reaches_the_loop_as_the_streams_own_error():
    with local_server(None, workers=1, batch_size=4, config=load_config(None, RECIPE)) as endpoint:
        # the worker's start and first decode, under whatever load, before the 3 s that the gone server is given
        next(iter(V2VStreamDataset(endpoint, 4, outputs=("voxels",), timeout_s=120.0)))
        ahead = ReadAhead(PlanEpochs(V2VStreamDataset(endpoint, 4, outputs=("voxels",), timeout_s=3.0, retry_s=1.0)))
        it = iter(ahead)
        next(it)
    with pytest.raises(TimeoutError, match="no rows for 3.0 s"):
        for _ in range(12):  # an epoch and a half: past what was read before the server went
            next(it)
    ahead.close()
    assert not ahead._thread.is_alive()


def test_close_stops_the_reader_with_batches_unread(server):
    ahead = ReadAhead(epochs(server), depth=1)
    it = iter(ahead)
    next(it)
    before = threading.active_count()
    ahead.close()
    assert not ahead._thread.is_alive() and threading.active_count() == before - 1


def test_a_bad_depth_is_refused_naming_it(server):
    with pytest.raises(ValueError, match="depth must be an int >= 1, got 0"):
        ReadAhead(epochs(server), depth=0)

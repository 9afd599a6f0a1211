"""The client's protocol handling without a socket, a thread or torch: ``v2v_client.session.ServerSession``
fed the server's messages as ``v2v_wire`` encodes them (header in; items and typed outgoing
messages out). A real server and the I/O thread around it are covered by test_stream.py and
test_wire.py."""
from __future__ import annotations

import threading

import numpy as np
import pytest

from v2v_client.options import StreamOptions
from v2v_client.receipts import Abandon, Receipt
from v2v_client.resume import ResumeState, owed_padding, take_epoch_end
from v2v_client.session import LoopAbandoned, ServerPadding, ServerSession, StreamError
from v2v_wire import messages as cm
from v2v_wire.protocol import PROTOCOL_VERSION, encode_arrays, pack, unpack
from v2v_wire.stream_messages import Drained, EpochDone


def _options(outputs=("voxels", "frames"), **kw) -> StreamOptions:
    return StreamOptions(**{"outputs": tuple(outputs), "credits": 2, "timeout_s": 10.0, "heartbeat_s": 1.0,
                            "raw": False, "reconnect": False, "reconnect_timeout_s": 10.0, "curve_keys": None,
                            "rank": 0, "world_size": 1, "group": "default", "shm": False, **kw})


def _session(outputs=("voxels", "frames"), record=None, **kw) -> ServerSession:
    return ServerSession("tcp://127.0.0.1:1", _options(outputs), record or ResumeState("c"), "c", **kw)


def _batch(batch_id: int, n: int = 2, epoch: int = 0, **extra) -> list:
    arrays = {"voxels": np.full((n, 4, 5, 8, 8), batch_id, np.int8), "frames": np.zeros((n, 5, 8, 8), np.uint8)}
    specs, frames = encode_arrays(arrays)
    h = {"type": "batch", "batch_id": batch_id, "epoch": epoch, "arrays": specs,
         "sample_ids": [f"v.mp4#{batch_id}.{i}" for i in range(n)], "params": [{}] * n, **extra}
    return [pack(h)] + [memoryview(f).cast("B") for f in frames]


def _items(s: ServerSession) -> list:
    out = []
    while not s.items.empty():
        out.append(s.items.get())
    return out


def _welcomed(s: ServerSession) -> None:
    s.hello(new_socket=True)
    (hello,) = s.outgoing()
    assert isinstance(hello, cm.Hello) and hello.hello_id == 1 and not hello.shm and hello.consumer == "c"
    assert s.on_message([pack({"type": "welcome", "hello_id": 1, "info": {"crop_size": 8}})]) is None


def test_batches_come_out_as_numpy_items_taken_only_once_granted():
    s = _session()
    _welcomed(s)
    for bid in (7, 8, 9):
        assert s.on_message(_batch(bid)) is None
    a, b, c = _items(s)
    assert a["batch_id"] == 7 and a["voxels"].dtype == np.int8 and a["voxels"].shape == (2, 4, 5, 8, 8)
    assert int(a["voxels"][0, 0, 0, 0, 0]) == 7 and a["sample_ids"] == ["v.mp4#7.0", "v.mp4#7.1"]
    # the first GRANT_AHEAD batches are asked for as they come; the third waits for the consumer
    assert len(s.held) == 3 and s.outgoing() == [cm.Hold((7,)), cm.Hold((8,))]
    assert s.held.claim(a, lambda: "recorded", lambda: False) == (False, None)  # not granted: never taken
    assert s.on_message([pack({"type": "revoke", "batch_ids": [7, 8, 9]})]) is None
    # asked ones stay (the server reads the hold before anything later); the leased one goes back
    assert s.outgoing() == [cm.Released((9,))]
    assert "voxels" not in c and c["sample_ids"]  # given back: arrays freed, ids kept
    assert s.on_message([pack({"type": "granted", "batch_ids": [7], "refused": [8]})]) is None
    assert s.held.claim(a, lambda: "recorded", lambda: False) == (True, "recorded")
    assert "voxels" not in b and s.held.claim(b, lambda: "recorded", lambda: False) == (False, None)
    assert not s.held.claim(c, lambda: None, lambda: False)[0] and len(s.held) == 0


def test_a_new_hello_discards_granted_batches_and_names_only_what_was_claimed():
    """The claim (with the consumer's record) and a hello's resume state are one step each:
    a batch claimed before the hello is in its resume state; one granted but not claimed is
    discarded by it and never taken."""
    record = ResumeState("c")
    s = _session(record=record)
    _welcomed(s)
    s.on_message(_batch(1))
    s.on_message(_batch(2))
    a, b = _items(s)
    s.on_message([pack({"type": "granted", "batch_ids": [1, 2]})])
    s.outgoing()
    assert s.take(a, lambda: record.claim(0, 1, a["sample_ids"], False))[0]
    assert s.outgoing() == [cm.Ack((1,))]
    s.hello()
    (hello,) = s.outgoing()
    assert hello.resume.delivered == {0: ("v.mp4#1.0", "v.mp4#1.1")} and hello.resume.batches == {0: 1}
    assert s.take(b, lambda: record.claim(0, 2, b["sample_ids"], False)) == (False, None)
    s.on_message([pack({"type": "granted", "batch_ids": [2]})])  # a late answer about the older session
    assert len(s.held) == 0 and record.delivered == {0: {"v.mp4#1.0", "v.mp4#1.1"}}


def test_control_messages_become_items_and_the_end_or_an_error_ends_the_session():
    s = _session(("voxels",))
    _welcomed(s)
    assert s.on_message([pack({"type": "epoch_done", "epoch": 0, "batches": 3})]) is None
    assert s.on_message([pack({"type": "drained"})]) is None
    assert s.on_message(_batch(1, padding=True)) is None
    done, drained, pad = _items(s)
    assert isinstance(done, EpochDone) and (done.epoch, done.batches) == (0, 3) and isinstance(drained, Drained)
    assert isinstance(pad, ServerPadding) and pad.item["batch_id"] == 1 and len(s.held) == 0  # never leased
    assert s.on_message([pack({"type": "shutdown"})]) == "lost"
    assert s.on_message([pack({"type": "end", "reason": "all epochs served"})]) == "over"
    assert isinstance(_items(s)[0], StopIteration)
    assert s.on_message([pack({"type": "error", "message": "boom"})]) == "over"
    (err,) = _items(s)
    assert isinstance(err, StreamError) and "boom" in str(err)


def test_a_batch_lacking_an_output_or_a_dropped_session_is_handled():
    s = _session(("voxels", "flow"))
    _welcomed(s)
    assert s.on_message(_batch(3)) == "over"
    (err,) = _items(s)
    assert isinstance(err, StreamError) and "lacks requested outputs ['flow']" in str(err)

    s = _session(("voxels",))
    _welcomed(s)
    s.on_message(_batch(4))
    (item,) = _items(s)
    assert s.outgoing() == [cm.Hold((4,))]
    assert s.on_message([pack({"type": "error", "code": "dropped", "message": "silent"})]) is None
    (again,) = s.outgoing()
    assert isinstance(again, cm.Hello) and again.hello_id == 2  # introduced again with the resume state
    assert s.held.discarded == 1 and "voxels" not in item  # what it held goes elsewhere
    # until the welcome to that hello, batches, revokes and grants of the old session are ignored
    assert s.on_message(_batch(5)) is None and _items(s) == []
    assert s.on_message([pack({"type": "granted", "batch_ids": [4]})]) is None and s.outgoing() == []
    s.on_message([pack({"type": "welcome", "hello_id": 2, "info": {}})])
    s.on_message(_batch(6))
    assert [i["batch_id"] for i in _items(s)] == [6]


def test_an_unknown_client_answering_a_heartbeat_after_the_latest_hello_brings_it_again():
    """While a session awaits its latest hello's welcome, ``unknown_client`` answers what it said
    before that hello, and is ignored; but every heartbeat names the latest hello, and an answer
    naming it back says the server read the heartbeat with no hello of ours: the hello was lost
    (a server crash), so it is said again (docs/delivery.md, rule 5; simulator finding F27)."""
    s = _session(("voxels",))
    _welcomed(s)
    s.on_message([pack({"type": "error", "code": "dropped", "message": "silent"})])
    assert [m.hello_id for m in s.outgoing() if isinstance(m, cm.Hello)] == [2]
    s.tick(0.0)
    s.tick(1.0)
    assert s.outgoing() == [cm.Heartbeat(2)]
    for stale in ({}, {"hello_id": 1}):  # a hold's answer, or a heartbeat's said before the hello
        assert s.on_message([pack({"type": "error", "code": "unknown_client", "message": "who?", **stale})]) is None
        assert s.outgoing() == [] and _items(s) == []
    assert s.on_message([pack({"type": "error", "code": "unknown_client", "message": "who?", "hello_id": 2})]) is None
    (again,) = s.outgoing()
    assert isinstance(again, cm.Hello) and again.hello_id == 3 and _items(s) == []


def test_a_refused_welcome_ends_the_session_naming_why():
    s = _session(("voxels",), welcomed=lambda info: "another recipe")
    s.hello(new_socket=True)
    assert s.on_message([pack({"type": "welcome", "hello_id": 1, "info": {}})]) == "over"
    (err,) = _items(s)
    assert isinstance(err, StreamError) and str(err) == "v2v server at tcp://127.0.0.1:1: another recipe"


def test_server_messages_round_trip_typed_and_a_bad_field_is_named():
    from v2v_wire import stream_messages as sm

    msgs = [sm.Welcome({"crop_size": 8}, 3), sm.Batch(4, 0, ("v#0",), ({"a": 1},), ({"name": "voxels"},)),
            sm.Batch(-1, 2, ("v#1",), ({},), (), {"file": "b0", "gen": 1, "offsets": [64]}, True),
            sm.Revoke((1, 2)), sm.EpochDone(0), sm.EpochDone(1, 5), sm.Drained(), sm.End(), sm.End("done"),
            sm.Heartbeat(), sm.Shutdown(), sm.ServerError("boom"), sm.ServerError("gone", "dropped"),
            sm.ServerError("who?", "unknown_client", 7)]
    for m in msgs:
        assert sm.stream_message(unpack(pack(m.to_wire()))) == m
    assert sm.stream_message({"type": "news"}) is None  # a newer server's message this client can do without
    bad = [({"type": "batch", "batch_id": 1, "epoch": "0", "sample_ids": [], "params": [], "arrays": []}, "epoch"),
           ({"type": "batch", "batch_id": 1, "epoch": 0, "sample_ids": [3], "params": [], "arrays": []}, "sample_ids"),
           ({"type": "batch", "batch_id": 1, "epoch": 0, "sample_ids": [], "params": [], "arrays": [],
             "padding": 1}, "padding"),
           ({"type": "revoke", "batch_ids": [True]}, "batch_ids"), ({"type": "epoch_done"}, "epoch"),
           ({"type": "welcome", "info": []}, "info"), ({"type": "error", "message": 7}, "message"),
           ({"type": 5}, "type")]
    for h, name in bad:
        with pytest.raises(sm.StreamMessageError, match=f"field '{name}'"):
            sm.stream_message(h)
    s = _session(("voxels",))
    assert s.on_message([pack({"type": "epoch_done", "epoch": -1})]) == "over"
    err = s.items.get_nowait()
    assert isinstance(err, StreamError) and "epoch_done message: field 'epoch'" in str(err)


def test_client_messages_go_out_as_the_server_parses_them():
    """What a client sends (ack, hold, released, credit, heartbeat, bye) is built from the
    types the server's edge parses, and comes back equal through msgpack and that check."""
    from v2v_wire import messages as cm

    msgs = [cm.Ack((1, 2)), cm.Hold((3,)), cm.Released((4, 5, 6)), cm.Credit(7), cm.Heartbeat(), cm.Heartbeat(3), cm.Bye()]
    for m in msgs:
        assert cm.decode_client(pack(m.to_wire()), 1 << 16, 64) == m
    s = _session()
    _welcomed(s)
    s.on_message(_batch(9))
    s.on_message([pack({"type": "granted", "batch_ids": [], "refused": [9]})])
    for bid in (10, 11, 12):
        s.on_message(_batch(bid))
    s.on_message([pack({"type": "revoke", "batch_ids": [11, 12]})])
    out = s.outgoing()
    assert out == [cm.Hold((9,)), cm.Hold((10,)), cm.Hold((11,)), cm.Released((12,))]
    assert [cm.decode_client(pack(m.to_wire()), 1 << 16, 64) for m in out] == out


def test_a_dataloader_workers_hello_says_it_ends_on_drained():
    """A StreamLoader worker's hello says ``ends_on_drained`` (the server then sends it nothing
    after ``drained``); a trainer's does not; the server's edge takes only true or false, and
    reads the hello a session builds back equal."""
    import msgpack

    for ends in (True, False):
        s = _session(ends_on_drained=ends)
        s.hello(new_socket=True)
        (hello,) = s.outgoing()
        parsed = cm.decode_client(pack(hello.to_wire()), 1 << 16, 64)
        assert parsed.ends_on_drained is ends and (parsed.consumer, parsed.credits, parsed.outputs) == (
            "c", 2, ("voxels", "frames"))
    bad = dict(hello.to_wire(), ends_on_drained=1, v=PROTOCOL_VERSION)
    with pytest.raises(cm.WireError, match="ends_on_drained"):
        cm.decode_client(msgpack.packb(bad), 1 << 16, 64)


def test_the_loaders_receipts_acknowledge_and_an_abandoned_iteration_gives_back_what_it_queued():
    """In a DataLoader worker a claimed batch waits in the record's pipeline (no ack) until the
    loop's receipt; a receipt acknowledges it; when the loader leaves the iteration the consumer
    is told, and closing gives back the batches still queued in the loader and says bye."""
    record = ResumeState("c")
    s = _session(record=record, ends_on_drained=True, iteration=3)
    _welcomed(s)
    for bid in (1, 2):
        s.on_message(_batch(bid))
    a, b = _items(s)
    s.on_message([pack({"type": "granted", "batch_ids": [1, 2]})])
    s.outgoing()
    for item in (a, b):
        ok, keep = s.take(item, lambda item=item: record.claim(0, item["batch_id"], item["sample_ids"], True),
                          ack=False)
        assert ok and keep == [0, 1]
    assert s.outgoing() == [] and record.pipeline_ids() == [1, 2] and not s.lingering_done()
    s.on_loader(Receipt((1, 99)))
    assert s.outgoing() == [cm.Ack((1,))] and record.delivered == {0: {"v.mp4#1.0", "v.mp4#1.1"}}
    s.on_loader(Abandon(2))  # another iteration's
    assert _items(s) == [] and not s.abandoned
    s.on_loader(Abandon(3))
    assert isinstance(_items(s)[0], LoopAbandoned) and s.lingering_done()
    assert s.closing() == [cm.Released((2,)), cm.Bye()]


def test_a_workers_hello_names_the_batches_waiting_in_the_loader_as_queued():
    """A StreamLoader worker's hello names the granted batches waiting in the loader's queues by
    batch id and epoch (``queued``), their ids among those handed on, and the server's edge reads
    them back; a received one is named no more, and a bad ``queued`` is named (docs/delivery.md,
    "DataLoader workers")."""
    import msgpack

    record = ResumeState("c")
    s = _session(record=record, ends_on_drained=True)
    _welcomed(s)
    for bid in (1, 2):
        s.on_message(_batch(bid, epoch=1))
    s.on_message([pack({"type": "granted", "batch_ids": [1, 2]})])
    for item in _items(s):
        s.take(item, lambda item=item: record.claim(1, item["batch_id"], item["sample_ids"], True), ack=False)
    s.on_loader(Receipt((1,)))
    s.outgoing()
    s.hello()
    (hello,) = s.outgoing()
    parsed = cm.decode_client(pack(hello.to_wire()), 1 << 16, 64)
    assert parsed.resume.queued == {2: 1}
    assert set(hello.resume.delivered[1]) == {f"v.mp4#{b}.{i}" for b in (1, 2) for i in (0, 1)}
    for bad in ({"2": -1}, {"x": 1}, [2, 1]):
        wire = dict(hello.to_wire(), v=PROTOCOL_VERSION)
        wire["resume"] = dict(wire["resume"], queued=bad)
        with pytest.raises(cm.WireError, match="resume.queued"):
            cm.decode_client(msgpack.packb(wire), 1 << 16, 64)


def test_a_workers_queued_batches_keep_ids_a_server_numbers_from_its_start_time():
    """A server numbers its batches from its start time in ns, so a restarted one never repeats a
    predecessor's ids (docs/delivery.md, "Transport"): a worker's hello names such batches waiting in
    the loader as ``queued`` and the server's edge reads them back as they were; one of 2**63 or more
    is named."""
    import time

    import msgpack

    record = ResumeState("c")
    s = _session(record=record, ends_on_drained=True)
    _welcomed(s)
    first = time.time_ns()
    for k, bid in enumerate((first, first + 1)):
        frames = _batch(k, epoch=1)
        s.on_message([pack(dict(msgpack.unpackb(frames[0]), batch_id=bid))] + frames[1:])
    s.on_message([pack({"type": "granted", "batch_ids": [first, first + 1]})])
    for item in _items(s):
        s.take(item, lambda item=item: record.claim(1, item["batch_id"], item["sample_ids"], True), ack=False)
    s.outgoing()
    s.hello()
    (hello,) = s.outgoing()
    assert cm.decode_client(pack(hello.to_wire()), 1 << 16, 64).resume.queued == {first: 1, first + 1: 1}
    wire = dict(hello.to_wire(), v=PROTOCOL_VERSION)
    wire["resume"] = dict(wire["resume"], queued={str(2 ** 63): 1})
    with pytest.raises(cm.WireError, match="resume.queued"):
        cm.decode_client(msgpack.packb(wire), 1 << 16, 64)


def test_a_workers_iteration_ends_only_on_a_drained_of_its_current_session():
    """A DataLoader worker dropped for silence says hello again: a ``drained`` queued before that
    hello, or sent before the server read it, is about the session that ended (its grants came
    back to the queue with the new hello) and must not end the new one; the server tells the new
    session itself. A worker holding a batch, or a trainer, never ends on one (docs/delivery.md,
    "The protocol", rule 6; the simulator's F10)."""
    s = _session(ends_on_drained=True)
    _welcomed(s)
    s.on_message([pack({"type": "drained"})])  # queued, not yet taken off by the consumer
    assert s.on_message([pack({"type": "error", "message": "dropped", "code": "dropped"})]) is None
    (hello,) = s.outgoing()
    assert isinstance(hello, cm.Hello) and hello.hello_id == 2
    s.on_message([pack({"type": "drained"})])  # sent before the server read the new hello: not queued
    (stale,) = _items(s)
    assert isinstance(stale, Drained) and not s.held.ends_on(stale)
    s.on_message([pack({"type": "welcome", "hello_id": 2, "info": {"crop_size": 8}})])
    s.on_message(_batch(4))
    s.on_message([pack({"type": "drained"})])
    batch, told = _items(s)
    assert not s.held.ends_on(told)  # batch 4 is still held
    s.give_back(batch)
    assert s.held.ends_on(told)
    trainer = _session()
    _welcomed(trainer)
    trainer.on_message([pack({"type": "drained"})])
    assert not trainer.held.ends_on(_items(trainer)[0])


def test_time_brings_heartbeats_and_asks_again_for_what_stays_unanswered():
    """``tick(now)`` sends a heartbeat every ``heartbeat_s`` (1 s here) and, with it, asks again for
    a grant unanswered a whole heartbeat (the clock is the caller's: a simulator passes its own)."""
    s = _session()
    _welcomed(s)
    s.on_message(_batch(7))
    assert s.outgoing() == [cm.Hold((7,))]
    s.tick(10.0)
    assert s.outgoing() == []
    s.tick(11.0)
    assert s.outgoing() == [cm.Heartbeat(1)]  # asked just now: not yet
    s.tick(11.5)
    s.tick(12.0)
    assert s.outgoing() == [cm.Heartbeat(1), cm.Hold((7,))]  # a heartbeat later, unanswered: again
    s.on_message([pack({"type": "granted", "batch_ids": [7]})])
    s.tick(13.0)
    assert s.outgoing() == [cm.Heartbeat(1)]


def test_a_hold_unanswered_for_a_whole_heartbeat_is_asked_again():
    """A grant lost when a connection broke behind ZeroMQ's reconnect would leave the consumer
    waiting: the I/O thread asks again, each heartbeat, for what stayed unanswered since the last."""
    s = _session()
    _welcomed(s)
    s.on_message(_batch(7))
    assert s.held.still_asked(set()) == (set(), {7})  # asked just now: not yet
    assert s.held.still_asked({7}) == ({7}, {7})  # a heartbeat later, unanswered: again
    s.on_message([pack({"type": "granted", "batch_ids": [7]})])
    assert s.held.still_asked({7}) == (set(), set())


def test_what_was_said_of_a_granted_batch_is_named_each_heartbeat_until_the_server_has_read_it():
    """An ``ack`` (or a ``released`` of a granted batch) lost with a broken connection would leave
    the batch granted at the server: the session names it in each heartbeat's ``hold``; a
    ``granted`` answer means the server still holds it for us (said again), ``refused`` that it
    read what was said (forgotten). A batch sent to us again is the book's, not said again."""
    s = _session()
    _welcomed(s)
    for bid in (7, 8):
        s.on_message(_batch(bid))
    a, b = _items(s)
    s.on_message([pack({"type": "granted", "batch_ids": [7, 8]})])
    s.outgoing()
    assert s.take(a, lambda: None)[0] and s.outgoing() == [cm.Ack((7,))]
    s.give_back(b)
    assert s.outgoing() == [cm.Released((8,))]
    s.tick(10.0)
    s.tick(11.0)
    assert s.outgoing() == [cm.Heartbeat(1), cm.Hold((7, 8))]
    s.on_message([pack({"type": "granted", "batch_ids": [7, 8]})])  # both were lost
    assert s.outgoing() == [cm.Ack((7,)), cm.Released((8,))]
    s.on_message([pack({"type": "granted", "batch_ids": [], "refused": [7]})])  # read
    s.on_message(_batch(8))  # given back, and sent to this connection again: the book's
    _items(s)
    assert s.outgoing() == [cm.Hold((8,))]
    s.tick(12.0)
    assert s.outgoing() == [cm.Heartbeat(1)]
    s.on_message([pack({"type": "granted", "batch_ids": [8]})])
    assert s.outgoing() == [] and s.held.granted == {8}


def _pad(batch: dict, epoch: int) -> dict:
    """``endpoint.padding_copy`` without tensors."""
    return {"epoch": epoch, "batch_id": -1, "sample_ids": list(batch["sample_ids"])}


def test_a_ddp_rank_that_read_an_epochs_end_with_nothing_to_repeat_pays_with_the_servers_copy():
    """A DDP rank told epoch 0 complete (every rank yields 1 batch) before any batch reached
    it owes one padding batch with nothing to repeat. Its hello, sent before it read that end,
    reopened epoch 0, so the server sends a padding copy of it: the copy pays that batch, once
    (it was dropped as "complete here", and the job hung in an all-reduce: simulator finding
    F19, ``ddp`` seeds 782, 930). A copy of a later, open epoch also pays what older epochs
    still owe, oldest first."""
    r = ResumeState("c")
    assert r.complete(0, 1) == 1  # nothing to repeat: owed in the record
    copy = {"epoch": 0, "batch_id": -1, "sample_ids": ["v.mp4#0"]}
    assert list(owed_padding(r, copy, _pad, own=True)) == [copy] and r.is_complete(0)
    assert list(owed_padding(r, copy, _pad, own=True)) == []  # a second copy of a complete epoch is nobody's
    r = ResumeState("c")
    assert r.complete(0, 2) == 2
    copy = {"epoch": 1, "batch_id": -1, "sample_ids": ["v.mp4#1"]}
    got = list(owed_padding(r, copy, _pad, own=True))
    assert [b["epoch"] for b in got] == [0, 0, 1] and got[-1] is copy  # epoch 1 is open: its copy counts in it
    assert r.complete(1, 1) == 0


@pytest.mark.parametrize("raw", [False, True])
@pytest.mark.parametrize("points,compact", [(0, False), (0, True), (8, False), (8, True)])
def test_a_rank_owing_padding_at_the_end_with_nothing_to_repeat_yields_zeros_shaped_as_the_stream(raw, points, compact):
    """A DDP rank told its group's count with nothing to repeat, when the server that had the
    group's last batch crashed, is sent no copy: at the stream's end it yields a batch of zeros
    (``endpoint.zero_padding``) with the arrays, per-sample shapes and dtypes of the stream's
    batches as the client converts them, every sample flagged (the ranks ended with different
    counts and the job hung in an all-reduce: simulator ``mixed`` seeds 3853, 4461). A tracked flow
    option (``points`` per side in the welcome) read with ``compact_flow`` has ``flow_grid`` in its
    batches, and so in its padding: a loop that expands the grid finds it in every batch."""
    from v2v_client.endpoint import zero_padding
    from v2v_client.tensors import batch_to_torch
    from v2v_wire.outputs import ARRAYS

    info = {"sequence_length": 4, "num_bins": 5, "crop_size": 16, "flow_dtype": "float16",
            "outputs": ["voxels", "frames", "flow"], "flow_grid_points": points}
    outputs = ("voxels", "frames", "flow", "polarity_counts")
    options = StreamOptions(outputs=outputs, credits=2, timeout_s=1.0, heartbeat_s=1.0, raw=raw, reconnect=False,
                            reconnect_timeout_s=1.0, curve_keys=None, rank=1, world_size=2, group="g", shm=False,
                            compact_flow=compact)
    rng = np.random.default_rng(0)
    wire = {n: rng.integers(0, 3, (3,) + ARRAYS[n].shape(4, 5, 16)).astype("float16" if n == "flow" else ARRAYS[n].dtypes[0])
            for n in outputs}
    if points:  # what a tracked option's worker sends (server.stream_info's flow_grid_points)
        wire["flow_grid"] = rng.normal(size=(3, 4, 2, points, points)).astype("float32")
        del wire["flow"]
    real = batch_to_torch(wire, raw, (16, 16), "float16", compact_flow=compact)
    assert ("flow_grid" in real) == (points > 0 and compact)
    pad = zero_padding(info, options, 2)
    assert {k: (tuple(v.shape[1:]), v.dtype) for k, v in real.items()} == \
        {k: (tuple(pad[k].shape[1:]), pad[k].dtype) for k in real}
    assert not {"flow", "flow_grid"} & (set(pad) - set(real))
    assert all(not pad[k].any() for k in real)
    assert pad["padding"].tolist() == [True] and pad["epoch"] == 2 and pad["batch_id"] == -1
    assert len(pad["sample_ids"]) == len(pad["params"]) == 1


def test_a_ddp_ranks_checkpoint_taken_while_its_padding_waits_for_the_loop_keeps_what_it_owes():
    """A DDP rank that yielded 2 batches of epoch 0 is told it complete, every rank yielding 4:
    it owes 2 padding batches, which reach the loop one step at a time. A checkpoint taken after
    the first names epoch 0 open with 3 batches, so a rank resumed from it (its hello reopens the
    epoch; the server tells its end again) owes the one left, and the job's ranks yield alike (its
    record completed the epoch when it read the end, the checkpoint said so, the resumed rank owed
    nothing, and the job hung in an all-reduce: simulator finding F23, ``ddp`` seed 878)."""
    r = ResumeState("c")
    r.place("job", 2, 3)
    for bid in (16, 20):
        assert r.claim(0, bid, [f"v.mp4#{bid}"], loader=False) == [0]
    assert r.complete(0, 4) == 2 and not r.is_complete(0)
    pads = owed_padding(r, {"epoch": 0, "batch_id": 20, "sample_ids": ["v.mp4#20"]}, _pad)
    assert next(pads)["epoch"] == 0
    saved = r.state()
    assert saved["completed_epoch"] == -1 and saved["batches"] == {"0": 3}
    assert saved["delivered"] == {"0": ["v.mp4#16", "v.mp4#20"]}  # its ids are still its own
    resumed = ResumeState()
    resumed.load(saved)
    assert resumed.hello_resume().completed_epoch == -1  # the hello reopens epoch 0
    assert resumed.complete(0, 4) == 1
    assert [b["epoch"] for b in owed_padding(resumed, {"epoch": 1, "sample_ids": ["v.mp4#30"]}, _pad)] == [0]
    assert resumed.is_complete(0) and resumed.state()["batches"] == {}
    assert [b["epoch"] for b in pads] == [0] and r.is_complete(0)  # the rank that read on
    assert r.complete(0, 4) is None  # an end told again once paid: nothing more


def test_a_ddp_rank_saying_hello_again_pays_no_padding_of_the_ends_told_to_the_session_it_ended():
    """A DDP rank paused past the client timeout holds a batch of epoch 0 and reads, on waking,
    epoch 0's end (every rank yields 3) and then ``dropped``: it says hello again with epoch 0 open
    (1 batch), and the server tells that epoch's end again, with the count its group has now (a
    grant given back may have lowered it, or come to this rank). The end queued before the hello,
    one sent before the server read it, the server's padding copy of that session and the padding
    the rank owed from it are the old session's: none is paid (it paid them, its record completed
    epoch 0 while the server sent it batches of it, and it gave them back for good or yielded more
    than the others: simulator finding F35, ``ddp`` seeds 1128, 1664, 2768). Their counts are kept:
    an end told again says no fewer (``ddp`` seed 1609)."""
    record = ResumeState("c")
    s = ServerSession("tcp://127.0.0.1:1", _options(rank=0, world_size=3, group="job"), record, "c")
    _welcomed(s)
    assert record.claim(0, 3, ["v.mp4#3.0"], loader=False) == [0]
    s.on_message(_batch(-1, padding=True))
    s.on_message([pack({"type": "epoch_done", "epoch": 0, "batches": 3})])
    assert record.complete(0, 3) == 2  # one end the loop took before the hello: it owes 2
    assert s.on_message([pack({"type": "error", "message": "dropped", "code": "dropped"})]) is None
    (hello,) = s.outgoing()
    assert hello.resume.completed_epoch == -1 and hello.resume.batches == {0: 1}
    assert list(owed_padding(record, {"epoch": 0, "sample_ids": ["v.mp4#3.0"]}, _pad)) == []  # nothing owed now
    s.on_message([pack({"type": "epoch_done", "epoch": 0, "batches": 3})])  # sent before the server read the hello
    copy, stale = _items(s)
    assert isinstance(copy, ServerPadding) and isinstance(stale, EpochDone)
    assert not s.held.of_session(copy) and not s.held.of_session(stale)
    s.on_message([pack({"type": "welcome", "hello_id": 2, "info": {"crop_size": 8}})])
    s.on_message([pack({"type": "epoch_done", "epoch": 0, "batches": 3})])  # told again, to this session
    (told,) = _items(s)
    assert s.held.of_session(told) and record.complete(told.epoch, told.batches) == 2 and not record.is_complete(0)
    other = ResumeState("c")  # an end of an ended session that the loop takes: only its count is kept, and an
    assert other.complete(0, 3, stale=True) is None and not other.is_complete(0)  # end told again says no fewer
    assert other.complete(0, 2) == 3  # (a restarted server that lost the count: F33)


def test_a_ddp_rank_told_an_epochs_end_after_one_it_never_got_says_hello_again():
    """A cut ZeroMQ mends (no hello follows) lost the server's padding copy of epoch 0 and epoch 0's
    end to a DDP rank granted nothing of it; epoch 1's end came. The server tells a rank's ends in
    order, an epoch with its count alone, so the rank says hello again (its state has epoch 0 open)
    instead of completing epoch 0 unpaid: it yielded a batch fewer than its group and the job hung in
    an all-reduce (simulator finding F38, ``mixed`` seed 6397). The stream's end sent before the server
    read that hello is the ended session's too; the new session is told the ends again, in order."""
    record = ResumeState("c")
    s = ServerSession("tcp://127.0.0.1:1", _options(rank=1, world_size=3, group="job"), record, "c")
    _welcomed(s)
    assert s.on_message([pack({"type": "epoch_done", "epoch": 1, "batches": 0})]) is None
    (hello,) = s.outgoing()
    assert isinstance(hello, cm.Hello) and hello.hello_id == 2 and hello.resume.completed_epoch == -1
    assert s.on_message([pack({"type": "end"})]) is None  # said before the server read the hello
    assert _items(s) == [] and not record.is_complete(0)
    s.on_message([pack({"type": "welcome", "hello_id": 2, "info": {"crop_size": 8}})])
    s.on_message(_batch(-1, padding=True))
    for e, n in ((0, 1), (1, 0), (1, 0), (3, None)):  # in order, a duplicate, a run of forgotten epochs told at once
        s.on_message([pack({"type": "epoch_done", "epoch": e, **({} if n is None else {"batches": n})})])
    assert s.on_message([pack({"type": "end"})]) == "over" and s.outgoing() == []
    copy, *ends, end = _items(s)
    assert isinstance(copy, ServerPadding)
    assert [(d.epoch, d.batches) for d in ends] == [(0, 1), (1, 0), (1, 0), (3, None)]
    assert isinstance(end, StopIteration) and all(s.held.of_session(i) for i in [copy] + ends)
    one = _session(("voxels",))  # without DDP an end names no count, and completes every epoch before it
    _welcomed(one)
    one.on_message([pack({"type": "epoch_done", "epoch": 2})])
    assert one.outgoing() == [] and isinstance(_items(one)[0], EpochDone)


def test_a_hello_comes_wholly_before_or_after_the_loop_records_an_epochs_end():
    """The loop takes a DDP rank's epoch end (owing one padding batch) and records it in the step
    that finds it told to the current session; a hello the I/O thread says meanwhile waits for
    that step. The hello then forgets the padding owed (the server tells the end and count again),
    so the rank pays nothing of the old end. Had the hello come between the check and the record,
    the rank would pay that padding and the server's again (simulator finding F35's race, found by
    reading ``EndpointStream``)."""
    record = ResumeState("c")
    s = ServerSession("tcp://127.0.0.1:1", _options(rank=0, world_size=2, group="job"), record, "c")
    _welcomed(s)
    s.on_message([pack({"type": "epoch_done", "epoch": 0, "batches": 1})])
    (end,) = _items(s)
    said = threading.Event()
    hello = threading.Thread(target=lambda: (s.hello(), said.set()))

    def record_end(current: bool) -> None:
        hello.start()
        assert not said.wait(0.3)  # the hello waits for this step
        take_epoch_end(record, end, True, current)
        assert record.owed == {0: 1}

    assert s.held.of_session(end, record_end)
    assert said.wait(5.0)
    hello.join()
    assert record.owed == {} and list(owed_padding(record, {"epoch": 0}, lambda b, e: b)) == []
    (h,) = s.outgoing()
    assert isinstance(h, cm.Hello) and h.resume.completed_epoch == -1


def test_a_ddp_rank_told_the_streams_end_before_its_last_epochs_end_says_hello_again():
    """A cut ZeroMQ mends lost a DDP rank's end of the stream's last epoch (its count) and delivered
    the ``end`` sent after it: the rank says hello again instead of ending a batch short of its group,
    which hung the job in an all-reduce (simulator finding F45, ``mixed`` seed 45325). Without DDP, or
    told every end, ``end`` ends the stream."""
    def welcome(s: ServerSession, hello_id: int) -> None:
        s.on_message([pack({"type": "welcome", "hello_id": hello_id, "info": {"crop_size": 8, "epochs": 2}})])

    rank = ServerSession("tcp://127.0.0.1:1", _options(rank=1, world_size=3, group="job"), ResumeState("c"), "c")
    rank.hello(new_socket=True)
    rank.outgoing()
    welcome(rank, 1)
    rank.on_message([pack({"type": "epoch_done", "epoch": 0, "batches": 1})])
    assert rank.on_message([pack({"type": "end"})]) is None
    (hello,) = rank.outgoing()
    assert isinstance(hello, cm.Hello) and hello.hello_id == 2 and hello.resume.completed_epoch == -1
    welcome(rank, 2)
    for e in (0, 1):
        rank.on_message([pack({"type": "epoch_done", "epoch": e, "batches": 1})])
    assert rank.on_message([pack({"type": "end"})]) == "over" and rank.outgoing() == []
    one = _session(("voxels",))
    one.hello(new_socket=True)
    welcome(one, 1)
    one.on_message([pack({"type": "epoch_done", "epoch": 0})])
    assert one.on_message([pack({"type": "end"})]) == "over"
    assert [type(m) for m in one.outgoing()] == [cm.Hello]

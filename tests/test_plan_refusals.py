"""A server's ``refused`` carries a code (``plan_messages.REFUSALS``) and the reader picks its
error by that code, never by the words of the line; a client message is bounded by what a fetch
holds (``protocol.MAX_CLIENT_MSG``); a plan reader of an older protocol is answered at a version
its own check names both versions at. The server sets each code end to end in
``tests/test_plan_stream.py`` (the hostile client) and ``tests/test_plan_rows.py`` (the batch
limit)."""
from __future__ import annotations

import threading

import msgpack
import pytest
import zmq

from v2v_client import PlanServerError, V2VStreamDataset
from v2v_wire.plan import PlanIdentity, PlanMismatch
from v2v_wire.plan_messages import (MAX_FETCH_ROWS, REFUSALS, Fetch, OldClient, PlanAsk, PlanInfo, Refused, WireError,
                                    decode_plan_client, old_client_answer, plan_server_message)
from v2v_wire.protocol import MAX_CLIENT_MSG, OUTPUTS, PROTOCOL_VERSION, ProtocolError, pack, unpack

PLAN = PlanIdentity("a" * 16, "b" * 16, 0)
STREAM = {"batch_size": 2, "sequence_length": 4, "num_bins": 5, "crop_size": 32, "outputs": ["voxels"]}


def _refusing_server(refusal: Refused):
    """A ROUTER on a free loopback port that answers ``plan_ask`` with a plan of 8 samples and
    every ``fetch`` with ``refusal`` (its request id put in), for 30 s; returns (endpoint, stop)."""
    ctx = zmq.Context.instance()
    router = ctx.socket(zmq.ROUTER)
    router.setsockopt(zmq.LINGER, 0)
    port = router.bind_to_random_port("tcp://127.0.0.1")
    done = threading.Event()

    def serve():
        while not done.is_set():
            if not router.poll(100):
                continue
            peer, header = router.recv_multipart()[:2]
            msg = decode_plan_client(header, MAX_CLIENT_MSG)
            if isinstance(msg, PlanAsk):
                answer = PlanInfo(PLAN, 8, STREAM).to_wire()
            else:
                answer = Refused(msg.request, refusal.message, refusal.code).to_wire()
            router.send_multipart([peer, pack(answer)])

    t = threading.Thread(target=serve, daemon=True)
    t.start()

    def stop():
        done.set()
        t.join(10)
        router.close()

    return f"tcp://127.0.0.1:{port}", stop


def _first_batch_error(refusal: Refused) -> BaseException:
    endpoint, stop = _refusing_server(refusal)
    try:
        with pytest.raises(Exception) as err:
            next(iter(V2VStreamDataset(endpoint, 2, timeout_s=30, compression="none")))
    finally:
        stop()
    return err.value


def test_a_refusal_of_another_plan_is_a_plan_mismatch_and_the_words_alone_are_not():
    mismatch = _first_batch_error(Refused(0, "fetch under another plan: seed 99 (this plan: 0)", "plan"))
    assert isinstance(mismatch, PlanMismatch) and "seed 99 (this plan: 0)" in str(mismatch)
    # a line that happens to hold the words, under another code: the server's error, not the reader's plan
    worded = _first_batch_error(Refused(0, "outputs ['another plan'] are not served here (--outputs)", "outputs"))
    assert type(worded) is PlanServerError and "are not served here" in str(worded)
    assert not isinstance(worded, PlanMismatch)


@pytest.mark.parametrize("code", [None, "", "another plan", 7])
def test_a_refused_without_a_known_code_is_a_wire_error_naming_the_field(code):
    h = {"type": "refused", "request": 3, "message": "fetch under another plan: seed 1 (this plan: 0)"}
    if code is not None:
        h["code"] = code
    with pytest.raises(WireError, match="refused: field 'code' must be one of"):
        plan_server_message(h)


def test_every_refusal_code_reads_back_as_sent():
    for code in REFUSALS:
        r = Refused(5, f"why: {code}", code)
        assert plan_server_message(unpack(pack(r.to_wire()))) == r


def test_the_largest_fetch_fits_a_client_message_and_a_padded_one_is_refused_naming_the_limit():
    big = 2 ** 62
    largest = Fetch(big, 2 ** 31 - 1, big - MAX_FETCH_ROWS, big, tuple(OUTPUTS), PlanIdentity("f" * 16, "e" * 16, big,
                                                                                                big, big), "zstd")
    frame = pack(largest.to_wire())
    assert len(frame) * 8 <= MAX_CLIENT_MSG  # room for more fields
    assert decode_plan_client(frame, MAX_CLIENT_MSG) == largest
    # a peer padding a field to 64 KiB: refused as oversized, never decoded (nor echoed in a refusal)
    padded = pack({**largest.to_wire(), "plan": {**largest.plan.to_dict(), "recipe": "e" * 65536}})
    with pytest.raises(WireError, match=str(MAX_CLIENT_MSG)):
        decode_plan_client(padded, MAX_CLIENT_MSG)


@pytest.mark.parametrize("kind", ["plan_ask", "fetch"])
def test_an_older_plan_reader_is_answered_at_this_version_and_names_both_versions(kind):
    """A plan reader of protocol ``PROTOCOL_VERSION - 1`` reads a message's version before its
    type: the answer at this server's version is refused by that reader's own check, naming both."""
    old = PROTOCOL_VERSION - 1
    header = {"v": old, "type": kind}
    if kind == "fetch":
        header.update(Fetch(1, 0, 0, 2, ("voxels",), PLAN).to_wire(), v=old)
    with pytest.raises(OldClient) as err:
        decode_plan_client(msgpack.packb(header, use_bin_type=True), MAX_CLIENT_MSG)
    answer = pack(old_client_answer(err.value))
    with pytest.raises(ProtocolError, match=f"^protocol version {PROTOCOL_VERSION}, expected {old}: "):
        unpack(answer, expect_version=old)  # what that reader's edge does first


def test_a_push_client_is_answered_at_its_own_version_which_it_reads():
    with pytest.raises(OldClient) as err:
        decode_plan_client(msgpack.packb({"v": 10, "type": "ack", "batch_id": 3}), MAX_CLIENT_MSG)
    answer = unpack(pack(old_client_answer(err.value)), expect_version=10)
    assert answer["type"] == "error" and f"protocol version 10, expected {PROTOCOL_VERSION}" in answer["message"]

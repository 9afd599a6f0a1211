"""Server <-> worker messages (v2v_wire.worker_messages): each type survives msgpack, a bad field is
refused naming the message and the field, and a worker's exception reaches the server with its
type, traceback and where it was raised (a real v2v-serve on a corpus with a file that is no video)."""
from __future__ import annotations

import shutil

import pytest

from v2v_wire.ids import SampleKey
from v2v_wire.protocol import ProtocolError, pack, unpack
from v2v_wire.worker_messages import (Done, Failure, Ready, Sample, Slot, Stop, Task, WorkerMessageError,
                                      server_message, worker_message)

from .conftest import video_dir

SPECS = ({"name": "voxels", "dtype": "int8", "shape": [2, 3, 8, 8]},)


def _through_msgpack(msg) -> dict:
    return unpack(pack(msg.to_wire()))


def _decode_error() -> Failure:
    def open_clip():
        raise OSError("moov atom not found")

    try:
        open_clip()
    except OSError as e:
        return Failure.of(e, "in worker w1.0, pid 7, while making bikes.mp4 in epoch 2, after sample bikes.mp4#3")


WORKER_SIDE = [Ready(True), Ready(False),
               Sample(4, SampleKey("clips/a.mp4", 3, 1), {"crop": [0, 8]}, SPECS, stages={"decode": 0.5}),
               Sample(4, SampleKey("a.mp4", 0), {}, SPECS, ({"codec": "zstd", "name": "voxels", "nbytes": 90},), 2),
               Done(4, 2, {"1": "frame size changed"}, "OSError: moov atom not found", _decode_error(), 80, 1, 1,
                    {"send": 0.25}, {"frame_cache": {"hits": 3}}, "error"),
               Done(6, 0, error="132 frames, shorter than one window of 151 frames", cause="short"),
               Done(5)]
SERVER_SIDE = [Task(4, 0, "a.mp4", ("voxels", "flow"), ((1, 0), (2, 1)), ("zstd",)), Task(5, 3, "b.mkv", ("frames",)),
               Slot(2), Stop()]


@pytest.mark.parametrize("msg", WORKER_SIDE, ids=lambda m: type(m).__name__)
def test_worker_messages_come_back_equal_through_msgpack(msg):
    assert worker_message(_through_msgpack(msg), crops_per_window=2) == msg


@pytest.mark.parametrize("msg", SERVER_SIDE, ids=lambda m: type(m).__name__)
def test_server_messages_come_back_equal_through_msgpack(msg):
    assert server_message(_through_msgpack(msg)) == msg


def test_the_keys_on_the_wire_are_the_ones_workers_and_servers_always_sent():
    assert set(SERVER_SIDE[0].to_wire()) == {"type", "task", "epoch", "video", "outputs", "skip", "codecs"}
    assert set(WORKER_SIDE[3].to_wire()) == {"type", "task", "key", "meta", "arrays", "packed", "slot", "stages"}
    assert WORKER_SIDE[3].to_wire()["key"] == ["a.mp4", 0, 0]
    assert set(WORKER_SIDE[4].to_wire()) == {"type", "task", "frames", "windows", "error", "failure", "stages", "cuts",
                                             "dropped", "store", "failed", "cause"}


BAD = [  # (header, the message and field the error must name)
    ({"type": "task", "task": "7", "epoch": 0, "video": "a.mp4", "outputs": ["voxels"]}, "task message: field 'task'"),
    ({"type": "task", "task": 7, "epoch": 0, "video": 3, "outputs": ["voxels"]}, "task message: field 'video'"),
    ({"type": "task", "task": 7, "epoch": 0, "video": "a.mp4", "outputs": ["voxels"], "skip": [[1]]},
     "task message: field 'skip'"),
    ({"type": "task", "task": 7, "epoch": -1, "video": "a.mp4", "outputs": ["voxels"]}, "task message: field 'epoch'"),
    ({"type": "slot", "slot": True}, "slot message: field 'slot'"),
    ({"type": "stop!"}, "unknown server message type"),
]
BAD_FROM_WORKERS = [
    ({"type": "ready", "ring": 1}, "ready message: field 'ring'"),
    ({"type": "sample", "task": 1, "key": ["a.mp4", 0, 5], "meta": {}, "arrays": []}, "sample message: field 'key'"),
    ({"type": "sample", "task": 1, "key": ["a.mp4", 0, 0], "meta": [], "arrays": []}, "sample message: field 'meta'"),
    ({"type": "sample", "task": 1, "key": ["a.mp4", 0, 0], "meta": {}, "arrays": "x"}, "sample message: field 'arrays'"),
    ({"type": "sample", "task": 1, "key": ["a.mp4", 0, 0], "meta": {}, "arrays": [], "slot": "0"},
     "sample message: field 'slot'"),
    ({"type": "sample", "task": 1, "key": ["a.mp4", 0, 0], "meta": {}, "arrays": [], "packed": [{"codec": "zstd"}]},
     "sample message: field 'packed'"),
    ({"type": "sample", "task": 1, "key": ["a.mp4", 0, 0], "meta": {}, "arrays": [], "stages": {"send": "1"}},
     "sample message: field 'stages'"),
    ({"type": "done", "task": 1, "windows": 2.5}, "done message: field 'windows'"),
    ({"type": "done", "task": 1, "failed": {"1": 2}}, "done message: field 'failed'"),
    ({"type": "done", "task": 1, "failed": {"w1": "x"}}, "done message: field 'failed'"),  # the plan's feed reads digits
    ({"type": "done", "task": 1, "error": ["x"]}, "done message: field 'error'"),
    ({"type": "done", "task": 1, "failure": {"exc_type": "OSError", "message": "", "traceback": ""}},
     "done message: field 'failure.where'"),
    ({"type": "done", "task": 1, "failure": "OSError"}, "done message: field 'failure'"),
    ({"type": "done", "task": 1, "cause": "shorter than one window"}, "done message: field 'cause'"),
    ({"type": "hello"}, "unknown worker message type"),
]


@pytest.mark.parametrize("h,named", BAD, ids=[n for _, n in BAD])
def test_a_bad_server_message_is_refused_naming_the_message_and_field(h, named):
    with pytest.raises(WorkerMessageError, match=named) as e:
        server_message(h)
    assert isinstance(e.value, ProtocolError)  # what the worker side of a socket catches


@pytest.mark.parametrize("h,named", BAD_FROM_WORKERS, ids=[n for _, n in BAD_FROM_WORKERS])
def test_a_bad_worker_message_is_refused_naming_the_message_and_field(h, named):
    with pytest.raises(WorkerMessageError, match=named):
        worker_message(h)


def test_a_failure_keeps_the_exceptions_type_traceback_and_where():
    f = _decode_error()
    got = worker_message(_through_msgpack(Done(9, error="OSError: moov atom not found", failure=f))).failure
    assert got == f
    assert (got.exc_type, got.message) == ("OSError", "moov atom not found")
    assert got.traceback.startswith("Traceback (most recent call last)") and "in open_clip" in got.traceback
    assert got.traceback.rstrip().endswith("OSError: moov atom not found")
    assert got.where == "in worker w1.0, pid 7, while making bikes.mp4 in epoch 2, after sample bikes.mp4#3"
    assert str(got) == f"OSError: moov atom not found ({got.where})"


def test_a_workers_exception_reaches_the_server_with_its_type_and_where(tmp_path):
    from harness.serve import ServeProcess
    from v2v_client import V2VStreamDataset

    corpus = tmp_path / "corpus"
    corpus.mkdir()
    shutil.copy(video_dir() / "bikes.mp4", corpus / "bikes.mp4")
    (corpus / "not_a_video.mp4").write_text("this is not a video\n" * 100)
    args = ["--videos", str(corpus), "--workers", "1", "--sequence-length", "4", "--num-bins", "2", "--crop-size", "32",
            "--max-samples-per-video", "1", "--batch-size", "1", "--log-level", "DEBUG"]
    with ServeProcess(args) as srv:
        ds = V2VStreamDataset(srv.endpoint, 1, outputs=("voxels",), timeout_s=120)
        rows = [(s, bool(p)) for b in ds for s, p in zip(b["sample_ids"], b["padding"])]
        lines = [ln for ln in srv.log.splitlines() if "not_a_video.mp4:" in ln and "skipped" in ln]
        raised = [ln for ln in srv.log.splitlines() if "Error raised in worker w0." in ln]
    assert [s for s, pad in rows if not pad] == ["bikes.mp4#0"], rows  # the rest of the epoch is padding
    assert len(lines) == 1, srv.log[-3000:]
    # the exception's type and where it was raised, from the worker's Failure, with its traceback below
    assert len(raised) == 1 and "while making not_a_video.mp4 in epoch 0, before its first sample" in raised[0], \
        srv.log[-3000:]
    assert "Traceback (most recent call last)" in srv.log.split(raised[0], 1)[1]

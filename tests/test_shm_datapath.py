"""The shared-memory data path: worker slot rings in /dev/shm, samples copied
once into reused batch buffers, the socket path as fallback. Unit tests of the ring and the
assembler, a pool whose worker dies before mapping its ring, and a real v2v-serve on ipc://
whose samples are bit-identical to the socket path's."""
from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
import zmq

from v2v_server.service.assembly import BatchAssembler, make_batch, sample_from_slot, sample_from_worker
from v2v_server.service.shm import BatchDir, SlotRing, create_ring, slot_bytes
from v2v_wire.protocol import ProtocolError, encode_arrays
from v2v_wire.worker_messages import Sample, Task

from .conftest import video_dir

L, NB, S = 3, 2, 8


def _arrays(i, vox=np.int8):
    rng = np.random.default_rng(i)
    return {"voxels": rng.integers(-100, 100, (L, NB, S, S)).astype(vox),
            "frames": rng.integers(0, 256, (L + 1, S, S)).astype(np.uint8),
            "flow": rng.normal(0, 9, (L, 2, S, S)).astype(np.float16)}


def _ring(tmp_path, slots=3):
    return SlotRing.create(slots, slot_bytes(L, NB, S), str(tmp_path))


def _sample(i, specs, slot=None, video="v.mp4"):
    """A worker's ``sample`` header as the server reads it (checked at the edge)."""
    h = {"type": "sample", "task": 1, "key": [video, i, 0], "meta": {"i": i}, "arrays": specs}
    if slot is not None:
        h["slot"] = slot
    return Sample.from_wire(h)


def _via_slot(ring, worker, asm, i, arrays):
    slot = worker.free.pop(0)
    specs = worker.put(slot, arrays)
    s = sample_from_slot(_sample(i, specs, slot), ring, asm)
    worker.free.append(slot)  # the relay copied it out: the worker may write it again
    return s


def _wire_bytes(batch):
    specs, frames = batch.wire(("voxels", "frames", "flow"))
    return specs, [np.ascontiguousarray(f).tobytes() for f in frames]


def test_slot_path_sends_the_same_bytes_as_the_socket_path_and_stacks_nothing(tmp_path):
    relay = _ring(tmp_path)
    worker = SlotRing.attach(relay.spec)  # the worker's mapping; attaching unlinks the file
    assert not Path(relay.path).exists() and os.listdir(tmp_path) == []
    asm = BatchAssembler(4)
    samples = [_via_slot(relay, worker, asm, i, _arrays(i)) for i in range(4)]  # 4 samples through 3 slots
    batch = make_batch(samples)
    buf = samples[0].buffer
    assert all(np.shares_memory(batch.arrays[k], buf.arrays[k]) for k in buf.arrays)  # the rows, not a stack
    socket_samples = []
    for i in range(4):
        specs, frames = encode_arrays(_arrays(i))
        socket_samples.append(sample_from_worker(_sample(i, specs), [f.tobytes() for f in frames]))
    assert _wire_bytes(batch) == _wire_bytes(make_batch(socket_samples))
    assert not samples[0].arrays["voxels"].flags.writeable
    worker.close()
    relay.close()


def test_a_held_batch_is_never_overwritten_and_idle_buffers_are_reused(tmp_path):
    relay = _ring(tmp_path)
    worker = SlotRing.attach(relay.spec)
    asm = BatchAssembler(2, spare=1)
    held = make_batch([_via_slot(relay, worker, asm, i, _arrays(i)) for i in range(2)])
    want = _wire_bytes(held)
    dropped = make_batch([_via_slot(relay, worker, asm, i, _arrays(i)) for i in range(2, 4)])
    dropped_buf = id(dropped.arrays["voxels"].base)  # (a reference would keep it busy)
    del dropped  # acknowledged: nothing views its buffer any more
    again = make_batch([_via_slot(relay, worker, asm, i, _arrays(i)) for i in range(4, 6)])
    assert asm.reused == 1 and id(again.arrays["voxels"].base) == dropped_buf
    assert _wire_bytes(held) == want  # the held batch kept its content
    ids = [f"v.mp4#{i}" for i in (4, 5)]
    assert again.sample_ids == ids and np.array_equal(again.arrays["frames"][1], _arrays(5)["frames"])


def test_a_buffer_is_not_refilled_while_a_zero_copy_send_of_it_is_in_flight():
    big = lambda i: {"voxels": np.full((4, 2, 96, 96), i, np.int8)}  # noqa: E731  (past ZeroMQ's copy threshold)
    asm = BatchAssembler(2, spare=1)
    ctx = zmq.Context()
    tx, rx = ctx.socket(zmq.PAIR), ctx.socket(zmq.PAIR)
    tx.bind("inproc://relay-lease")
    rx.connect("inproc://relay-lease")
    samples = [asm.place(f"v#{i}", {}, big(i)) for i in range(2)]
    buf = samples[0].buffer
    batch = make_batch(samples)
    specs, frames = batch.wire(("voxels",))
    batch.send(tx, [b"head"], frames)
    del samples, batch, frames  # acknowledged, but ZeroMQ still holds the frames: not yet received
    assert not buf.idle()
    other = make_batch([asm.place(f"v#{i}", {}, big(i)) for i in range(2, 4)])
    assert asm.reused == 0 and not np.shares_memory(other.arrays["voxels"], buf.arrays["voxels"])
    got = rx.recv_multipart()
    assert got[0] == b"head" and np.frombuffer(got[1], np.int8).reshape(2, 4, 2, 96, 96)[1].min() == 1
    deadline = time.monotonic() + 5
    while not buf.idle() and time.monotonic() < deadline:  # ZeroMQ releases the frames on its own thread
        time.sleep(0.01)
    assert buf.idle()
    del other
    make_batch([asm.place(f"v#{i}", {}, big(i)) for i in range(4, 6)])
    assert asm.reused == 1
    tx.close(0)
    rx.close(0)
    ctx.term()


def test_mixed_layouts_fall_back_to_one_stacking_copy(tmp_path):
    relay = _ring(tmp_path)
    worker = SlotRing.attach(relay.spec)
    asm = BatchAssembler(3)
    a = _via_slot(relay, worker, asm, 0, _arrays(0))
    b = _via_slot(relay, worker, asm, 1, _arrays(1, np.int16))  # counts that needed int16
    c = _via_slot(relay, worker, asm, 2, _arrays(2))
    batch = make_batch([a, b, c])
    assert batch.samples is not None  # not one buffer's rows: stacked when first sent
    assert batch.arrays["voxels"].dtype == np.int16
    for i, s in enumerate((a, b, c)):
        assert np.array_equal(batch.arrays["voxels"][i], _arrays(i)["voxels"])
    sub = make_batch([c, a])  # rows out of order: stacked as well, in the order given
    assert np.array_equal(sub.arrays["flow"][0].view(np.uint16), _arrays(2)["flow"].view(np.uint16))


def test_bad_slot_headers_are_protocol_errors(tmp_path):
    relay = _ring(tmp_path, slots=2)
    asm = BatchAssembler(2)
    specs = [{"name": "voxels", "dtype": "int8", "shape": [L, NB, S, S]}]
    for slot in (2, -1, "0", True):
        with pytest.raises(ProtocolError, match="slot"):
            sample_from_slot(_sample(0, specs, slot, "v"), relay, asm)
    huge = [{"name": "voxels", "dtype": "int32", "shape": [1 << 20, 64]}]
    with pytest.raises(ProtocolError, match="overrun"):
        sample_from_slot(_sample(0, huge, 0, "v"), relay, asm)
    overflow = [{"name": "voxels", "dtype": "int32", "shape": [1 << 62, 4]}]  # wraps in int64
    with pytest.raises(ProtocolError, match="overrun"):
        sample_from_slot(_sample(0, overflow, 0, "v"), relay, asm)
    with pytest.raises(ProtocolError):
        sample_from_slot(_sample(0, [{"name": "x", "dtype": "object", "shape": [1]}], 0, "v"), relay, asm)
    too_big = {"voxels": np.zeros((L * 10, NB, S, S), np.int32)}
    assert relay.put(0, too_big) is None  # the worker sends such a sample as frames
    relay.unlink()
    relay.close()


def test_no_ring_where_shared_memory_is_off(tmp_path, monkeypatch):
    monkeypatch.setenv("V2V_SHM_DIR", "")
    assert create_ring(L, NB, S) is None
    assert create_ring(L, NB, S, str(tmp_path / "missing")) is None
    monkeypatch.setenv("V2V_SHM_DIR", str(tmp_path))
    ring = create_ring(L, NB, S)
    assert ring is not None and Path(ring.path).parent == tmp_path
    with pytest.raises(ValueError, match="expected"):
        SlotRing.attach(dict(ring.spec, slots=ring.slots + 1))
    assert os.listdir(tmp_path) == []  # a failed attach still unlinks
    ring.close()


def test_a_shm_folder_that_is_not_one_is_named(tmp_path, monkeypatch, caplog):
    """V2V_SHM_DIR set to a missing folder falls back to the socket, with one warning naming it."""
    monkeypatch.setenv("V2V_SHM_DIR", str(tmp_path / "typo"))
    with caplog.at_level("WARNING", logger="v2v.datapath"):
        assert create_ring(L, NB, S) is None and create_ring(L, NB, S) is None
    assert [r.getMessage() for r in caplog.records] == \
        [f"V2V_SHM_DIR={tmp_path / 'typo'} is not a folder: no shared memory, arrays go over the socket"]


def _die_before_mapping(*args):
    os._exit(3)


def test_a_worker_that_dies_before_mapping_its_ring_leaks_nothing(tmp_path, monkeypatch):
    from v2v_server.ops.config import ServeConfig
    from v2v_server.service.pool import WorkerPool
    from v2v_server.service.worker import worker_config

    monkeypatch.setenv("V2V_SHM_DIR", str(tmp_path))
    cfg = ServeConfig(sequence_length=L, num_bins=NB, crop_size=S)
    pool = WorkerPool(worker_config(cfg), str(tmp_path), "ipc:///nonexistent", 1, target=_die_before_mapping)
    pool.start()
    first = next(iter(pool.workers.values()))
    first.proc.join(30)
    assert first.ring is not None and Path(first.ring.path).exists()  # never mapped, never unlinked by it
    dead = pool.reap()  # replaced by a fresh worker with a fresh ring
    assert [code for _, code in dead] == [3] and not Path(first.ring.path).exists()
    second = next(iter(pool.workers.values()))
    assert second.ring.path != first.ring.path
    pool.stop(lambda ident: None, grace_s=5.0)
    assert os.listdir(tmp_path) == []


def _read_epoch(endpoint):
    from v2v_client import V2VPushDataset

    got = {}
    for batch in V2VPushDataset(endpoint, outputs=("voxels", "frames", "flow"), raw=True, timeout_s=90):
        for i, sid in enumerate(batch["sample_ids"]):
            got[sid] = {k: batch[k][i].numpy().copy() for k in ("voxels", "frames", "flow")}
    return got


def test_served_samples_are_bit_identical_with_and_without_shared_memory_over_ipc():
    from harness.serve import ServeProcess

    args = ["--videos", str(video_dir()), "--workers", "1", "--sequence-length", "4", "--num-bins", "3",
            "--crop-size", "48", "--max-samples-per-video", "2", "--seed", "5", "--epochs", "1", "--batch-size", "3"]
    # this test's own shared-memory folder (on /dev/shm's tmpfs where there is one), so that
    # other servers on the host do not count as its leaks
    shm_root = "/dev/shm" if os.path.isdir("/dev/shm") else None
    with tempfile.TemporaryDirectory(prefix="v2v-ipc-") as d, \
            tempfile.TemporaryDirectory(prefix="v2v-test-shm-", dir=shm_root) as own:
        with ServeProcess(args + ["--bind", f"ipc://{d}/serve.sock"], env={"V2V_SHM_DIR": own}) as srv:  # same host
            shm = _read_epoch(srv.endpoint)
            assert "through shared-memory slot rings" in srv.log and "could not map" not in srv.log
        leaked = os.listdir(own)
        with ServeProcess(args, env={"V2V_SHM_DIR": ""}) as srv:
            sock = _read_epoch(srv.endpoint)
            assert "as socket frames" in srv.log
    assert len(shm) >= 4 and shm.keys() == sock.keys()
    for sid in shm:
        for k in ("voxels", "frames", "flow"):
            a, b = shm[sid][k], sock[sid][k]
            assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), (sid, k)
    assert not leaked


def test_a_worker_with_every_slot_taken_blocks_until_the_server_gives_one_back(tmp_path):
    import threading

    import zmq

    from v2v_wire.protocol import pack
    from v2v_server.service.worker import _Inbox

    ring = SlotRing.create(2, slot_bytes(L, NB, S), str(tmp_path))
    ctx = zmq.Context()
    server, worker = ctx.socket(zmq.ROUTER), ctx.socket(zmq.DEALER)
    worker.setsockopt(zmq.IDENTITY, b"w0")
    server.bind("inproc://slots")
    worker.connect("inproc://slots")
    inbox = _Inbox(worker, ring)
    assert [inbox.slot(os.getppid()), inbox.slot(os.getppid())] == [0, 1]
    got = []
    t = threading.Thread(target=lambda: got.append(inbox.slot(os.getppid())))
    t.start()
    worker.send(pack({"type": "ready"}))  # lets the ROUTER learn the worker's identity
    assert server.recv_multipart()[0] == b"w0"
    t.join(1.5)
    assert t.is_alive() and got == []  # blocked, nothing dropped or overwritten
    server.send_multipart([b"w0", pack(Task(1, 0, "a.mp4", ("voxels",)).to_wire())])  # kept for the main loop, in order
    server.send_multipart([b"w0", pack({"type": "slot", "slot": 1})])
    t.join(10)
    assert got == [1] and inbox.waiting == [Task(1, 0, "a.mp4", ("voxels",))]
    server.send_multipart([b"w0", pack({"type": "slot", "slot": 7})])  # out of range: ignored
    server.send_multipart([b"w0", pack({"type": "slot", "slot": 0})])
    assert inbox.slot(os.getppid()) == 0 and ring.free == []
    server.send_multipart([b"w0", pack({"type": "stop"})])
    with pytest.raises(SystemExit):
        inbox.slot(os.getppid())
    worker.close(0)
    server.close(0)
    ctx.term()
    ring.unlink()
    ring.close()


@pytest.mark.parametrize("size", ["1m", "64m"])
def test_a_small_dev_shm_never_kills_a_worker(tmp_path, size):
    from harness import faults_deploy
    from harness.faults import Layout

    r = faults_deploy.scenario_small_shm(tmp_path, Layout(L=4, crop=64, windows=2, batch=2), size)
    if "skipped" in r:
        pytest.skip(r["skipped"])
    assert (r["lost"], r["duplicated"], r["unexpected"]) == (0, 0, 0), r
    f = r["facts"]
    assert f["worker_deaths"] == 0 and f["server_exit"] == 0, r
    assert (f["rings_refused"] > 0) == (size == "1m"), r  # 2 rings of ~1.5 MB fit in 64 MiB, not in 1 MiB


def test_a_batch_directory_gone_while_serving_leaves_batches_in_anonymous_memory(tmp_path):
    """The server's batch directory replaced by a file (a vanished mount): a new batch buffer
    cannot be made there, so it is anonymous memory (batches go as socket frames), the same
    rows; the failure is reported with the path, once per buffer, never raised."""
    import shutil

    files = BatchDir.create(str(tmp_path))
    asm = BatchAssembler(2, spare=0, files=files)
    errors = []
    asm.on_error = lambda path, e: errors.append((path, type(e).__name__))
    first = make_batch([asm.place(f"v.mp4#{i}", {}, _arrays(i)) for i in range(2)])
    assert first.arrays["voxels"].base is not None and os.listdir(files.path)  # rows in a file of the directory
    shutil.rmtree(files.path)
    Path(files.path).write_text("not a folder")
    later = make_batch([asm.place(f"v.mp4#{i}", {}, _arrays(i)) for i in range(2, 4)])
    assert [p for p, _ in errors] == [files.path]
    for i in range(2):
        assert np.array_equal(later.arrays["voxels"][i], _arrays(i + 2)["voxels"])

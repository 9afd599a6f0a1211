"""The shared-memory data path: worker slot rings in /dev/shm, each sample copied once out
of its slot, the socket path as fallback. Unit tests of the ring and the copy out of it, a
pool whose worker dies before mapping its ring, and a real v2v-serve on ipc:// whose samples
are bit-identical to the socket path's."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import pytest

from v2v_server.service.assembly import sample_from_slot, sample_from_worker
from v2v_server.service.shm import SlotRing, create_ring, slot_bytes
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


def _via_slot(ring, worker, i, arrays):
    slot = worker.free.pop(0)
    specs = worker.put(slot, arrays)
    s = sample_from_slot(_sample(i, specs, slot), ring)
    worker.free.append(slot)  # the relay copied it out: the worker may write it again
    return s


def _same(a, b):
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def test_a_sample_copied_out_of_its_slot_equals_the_socket_paths_and_outlives_the_slot(tmp_path):
    relay = _ring(tmp_path)
    worker = SlotRing.attach(relay.spec)  # the worker's mapping; attaching unlinks the file
    assert not Path(relay.path).exists() and os.listdir(tmp_path) == []
    # 6 samples through 3 slots, voxels narrowed differently (counts that needed int16)
    made = [_arrays(i, np.int16 if i == 1 else np.int8) for i in range(6)]
    samples = [_via_slot(relay, worker, i, made[i]) for i in range(6)]  # each slot written twice
    for i, s in enumerate(samples):
        specs, frames = encode_arrays(made[i])
        sock = sample_from_worker(_sample(i, specs), [f.tobytes() for f in frames])
        assert s.sample_id == sock.sample_id == f"v.mp4#{i}" and s.meta == {"i": i}
        assert s.arrays.keys() == sock.arrays.keys() == made[i].keys()
        for k in made[i]:  # the slot written again after the copy left the sample as it was
            assert _same(s.arrays[k], made[i][k]) and _same(s.arrays[k], sock.arrays[k]), (i, k)
            views = [v for slot in range(relay.slots) for v in relay.arrays(slot, specs).values()]
            assert not any(np.shares_memory(s.arrays[k], v) for v in views)  # its own copy
    worker.close()
    relay.close()


def test_bad_slot_headers_are_protocol_errors(tmp_path):
    relay = _ring(tmp_path, slots=2)
    specs = [{"name": "voxels", "dtype": "int8", "shape": [L, NB, S, S]}]
    for slot in (2, -1, "0", True):
        with pytest.raises(ProtocolError, match="slot"):
            sample_from_slot(_sample(0, specs, slot, "v"), relay)
    huge = [{"name": "voxels", "dtype": "int32", "shape": [1 << 20, 64]}]
    with pytest.raises(ProtocolError, match="overrun"):
        sample_from_slot(_sample(0, huge, 0, "v"), relay)
    overflow = [{"name": "voxels", "dtype": "int32", "shape": [1 << 62, 4]}]  # wraps in int64
    with pytest.raises(ProtocolError, match="overrun"):
        sample_from_slot(_sample(0, overflow, 0, "v"), relay)
    with pytest.raises(ProtocolError):
        sample_from_slot(_sample(0, [{"name": "x", "dtype": "object", "shape": [1]}], 0, "v"), relay)
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
    from v2v_client import V2VStreamDataset

    got = {}
    for batch in V2VStreamDataset(endpoint, 3, outputs=("voxels", "frames", "flow"), raw=True, timeout_s=120):
        for i, sid in enumerate(batch["sample_ids"]):
            if not batch["padding"][i]:
                assert sid not in got, sid
                got[sid] = {k: batch[k][i].numpy().copy() for k in ("voxels", "frames", "flow")}
    return got


def test_served_samples_are_bit_identical_with_and_without_shared_memory_over_ipc():
    from harness.serve import ServeProcess

    args = ["--videos", str(video_dir()), "--workers", "1", "--sequence-length", "4", "--num-bins", "3",
            "--crop-size", "48", "--max-samples-per-video", "2", "--seed", "5", "--batch-size", "3"]
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
    """The server's shared memory (``V2V_SHM_DIR``) a tmpfs of ``size`` (Docker's default
    /dev/shm is 64 MiB): slot rings reserve their pages when made, so one that does not fit is
    refused at start with a log line (workers send arrays over the socket) instead of a worker
    dying of SIGBUS at a later write; the epoch is whole either way."""
    from harness.faults import Layout, expected_ids, good_corpus
    from harness.serve import ServeProcess

    from harness.faults_deploy import private_tmpfs

    wrap = private_tmpfs(size, tmp_path / "shm")
    if wrap is None:
        pytest.skip("unshare -m / mount -t tmpfs not permitted here")
    layout = Layout(L=4, crop=64, windows=2, batch=2)
    corpus = good_corpus(tmp_path, 2)
    with ServeProcess(["--videos", str(corpus), "--workers", "2", *layout.args()],
                      env={"V2V_SHM_DIR": str(tmp_path / "shm")}, wrap=wrap) as srv:
        got = _read_epoch(srv.endpoint)
    assert sorted(got) == expected_ids(corpus, layout)
    assert all(got[sid]["voxels"].any() for sid in got)
    assert "died (exit code" not in srv.log and " 0 worker restart(s)" in srv.log, srv.log
    refused = srv.log.count("no shared-memory slot ring")
    assert (refused > 0) == (size == "1m"), srv.log  # 2 rings of ~1.5 MB fit in 64 MiB, not in 1 MiB
    assert ("as socket frames" if size == "1m" else "through shared-memory slot rings") in srv.log

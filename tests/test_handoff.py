"""Same-host batch hand-off: batch buffers in files of a private /dev/shm
directory, batches sent to an ipc:// client as a reference, copied out by the client. Unit tests
of the buffer files, generations and the client's checks of a server's header; a real v2v-serve
on ipc:// read with the hand-off on and off (same arrays per sample id, no file left behind,
a SIGKILLed server's directory removed by the next start)."""
from __future__ import annotations

import os
import shutil
import tempfile

import numpy as np
import pytest

from v2v_client.handoff import ShmReader, check_shm_dir
from v2v_server.service.assembly import BatchAssembler, make_batch
from v2v_server.service.shm import BatchDir, remove_stale_shm
from v2v_wire.protocol import ProtocolError

from .conftest import video_dir

OUT = ("voxels", "frames", "flow")


@pytest.fixture
def shm_root():
    root = "/dev/shm" if os.path.isdir("/dev/shm") else None
    d = tempfile.mkdtemp(prefix="v2v-test-handoff-", dir=root)
    yield d
    shutil.rmtree(d, ignore_errors=True)


def _arrays(i):
    rng = np.random.default_rng(i)
    return {"voxels": rng.integers(-100, 100, (3, 2, 8, 8)).astype(np.int8),
            "frames": rng.integers(0, 256, (4, 8, 8)).astype(np.uint8),
            "flow": rng.normal(0, 9, (3, 2, 8, 8)).astype(np.float16)}


def _batch(asm, first, n=4):
    return make_batch([asm.place(f"v.mp4#{i}", {}, _arrays(i)) for i in range(first, first + n)])


def _header(batch):
    specs, ref = batch.shm_ref(OUT)
    return {"type": "batch", "batch_id": 0, "arrays": specs, "shm": ref}


def test_a_batch_read_through_the_file_equals_its_frames_and_is_a_private_copy(shm_root):
    files = BatchDir.create(shm_root)
    asm = BatchAssembler(4, files=files)
    batch = _batch(asm, 0)
    h = _header(batch)
    assert sorted(os.listdir(files.path)) == [".lock", h["shm"]["file"]]  # the lock file says a live server owns it
    reader = ShmReader()
    reader.set_dir(files.path)
    got = reader.read(h)
    specs, frames = batch.wire(OUT)
    for spec, f in zip(specs, frames):
        a = got[spec["name"]]
        assert a.dtype.name == spec["dtype"] and list(a.shape) == spec["shape"] and a.tobytes() == f.tobytes()
        assert a.flags.writeable and not np.shares_memory(a, batch.arrays[spec["name"]])
    views = reader.read(h, copy=False)  # raw=False converts straight from the mapping
    assert all(np.array_equal(views[k], got[k]) for k in OUT) and reader.valid(h)
    del views
    # a subset (resume) is a copy outside the buffer: no reference, frames instead
    assert batch.subset([0, 2]).shm_ref(OUT) is None
    reader.close()
    asm.close()
    assert not os.path.exists(files.path)


def test_a_buffer_is_refilled_only_after_its_batch_is_gone_and_a_late_reader_sees_the_new_generation(shm_root):
    files = BatchDir.create(shm_root)
    asm = BatchAssembler(4, spare=2, files=files)
    reader = ShmReader()
    reader.set_dir(files.path)
    held = _batch(asm, 0)  # the ledger keeps it until acked: a re-send still finds its bytes
    h = _header(held)
    expect = {k: v.copy() for k, v in held.arrays.items()}
    for j in range(3):  # more batches come and go (acked at once) while `held` is unacked
        other = _batch(asm, 10 + 4 * j)
        assert other.shm_ref(OUT)[1]["file"] != h["shm"]["file"]
        del other
    again = reader.read(h)
    assert all(np.array_equal(again[k], expect[k]) for k in OUT) and asm.reused >= 1
    del held  # acked: the buffer may be refilled
    files_before = set(os.listdir(files.path))
    refills = [_batch(asm, 100 + 4 * j) for j in range(3)]
    refilled = [b for b in refills if b.shm_ref(OUT)[1]["file"] == h["shm"]["file"]]
    assert refilled and refilled[0].shm_ref(OUT)[1]["gen"] > h["shm"]["gen"]
    assert reader.read(h) is None and not reader.valid(h)  # a stale header reads nothing
    assert set(os.listdir(files.path)) <= files_before | {f"b{i}" for i in range(10)}
    reader.close()
    asm.close()


def test_a_private_copy_is_never_refilled_while_a_tensor_or_view_of_it_lives(shm_root):
    """The client's copies go into reused memory: memory a tensor (torch.from_numpy) or a numpy
    view of a copy still references is not lent again, and memory nothing references is."""
    torch = pytest.importorskip("torch")
    files = BatchDir.create(shm_root)
    asm = BatchAssembler(4, files=files)
    batches = [_batch(asm, 4 * j) for j in range(3)]
    headers = [_header(b) for b in batches]
    reader = ShmReader(keep=2)
    reader.set_dir(files.path)
    first = reader.read(headers[0])
    expect = {k: v.copy() for k, v in first.items()}
    where = {k: v.__array_interface__["data"][0] for k, v in first.items()}
    tensor, view = torch.from_numpy(first["voxels"]), first["frames"][1:]
    del first  # the dict goes; a tensor and a view stay, as in a training step
    second = reader.read(headers[1])
    assert not any(np.shares_memory(second[k], view) or np.shares_memory(second[k], tensor.numpy())
                   for k in OUT)
    assert np.array_equal(tensor.numpy(), expect["voxels"]) and np.array_equal(view, expect["frames"][1:])
    del tensor, view
    third = reader.read(headers[2])  # the first copy's memory is idle again: lent once more
    assert all(np.array_equal(third[k], batches[2].arrays[k]) for k in OUT)
    assert {k: v.__array_interface__["data"][0] for k, v in third.items()} == where
    assert not any(np.shares_memory(third[k], second[k]) for k in OUT)
    reused = reader.read(headers[0])
    del second
    assert all(np.array_equal(reused[k], expect[k]) for k in OUT)
    reader.close()
    asm.close()


def test_the_client_refuses_a_header_pointing_outside_the_file_or_directory(shm_root):
    files = BatchDir.create(shm_root)
    asm = BatchAssembler(4, files=files)
    batch = _batch(asm, 0)
    h = _header(batch)
    size = os.path.getsize(os.path.join(files.path, h["shm"]["file"]))
    reader = ShmReader()
    with pytest.raises(ProtocolError, match="shm_dir"):
        reader.read(h)  # no directory from the welcome
    for bad in ("/etc", "/dev/shm/../etc", "relative/v2v-batches-1-x", "/tmp/v2v-batches-1-x/..", 7):
        with pytest.raises(ProtocolError, match="info.shm_dir"):
            check_shm_dir(bad)
    reader.set_dir(files.path)

    def tampered(**change):
        out = dict(h, shm=dict(h["shm"]))
        for k, v in change.items():
            if k == "arrays":
                out["arrays"] = v
            else:
                out["shm"][k] = v
        return out

    last = len(h["arrays"]) - 1
    cases = {
        "shm.offsets[0]": tampered(offsets=[size] + h["shm"]["offsets"][1:]),
        f"shm.offsets[{last}]": tampered(offsets=h["shm"]["offsets"][:-1] + [size - 8]),
        "shm.offsets[1]": tampered(offsets=[h["shm"]["offsets"][0], -4096] + h["shm"]["offsets"][2:]),
        "shm.offsets'": tampered(offsets=h["shm"]["offsets"][:1]),
        "shm.file": tampered(file="../../etc/passwd"),
        "shm.gen": tampered(gen=-1),
    }
    huge = [dict(s) for s in h["arrays"]]
    huge[0]["shape"] = [1 << 40, 1 << 20]
    cases["shm.offsets[0] "] = tampered(arrays=huge)
    for field, bad in cases.items():
        with pytest.raises(ProtocolError, match=field.strip().replace("[", r"\[").replace("]", r"\]")):
            reader.read(bad)
    assert reader.read(tampered(file="b999")) is None  # no such file: removed, the batch is gone
    assert reader.read(tampered(gen=h["shm"]["gen"] + 1)) is None
    assert reader.read(h) is not None
    reader.close()
    asm.close()


@pytest.mark.parametrize("namespace", ["same", "own PID namespace"])
def test_only_what_dead_servers_left_is_removed_whatever_their_pid(shm_root, namespace):
    """A live server holds an flock on its batch directory's lock file and on its slot rings:
    the next server's start removes what nobody holds (a server killed, whatever its pid or PID
    namespace) and never a live server's (also one that is PID 1 of another PID namespace), a
    symlink, or a directory still being made."""
    import subprocess
    import sys
    import time

    from v2v_server.service.shm import SlotRing

    from harness.faults_deploy import pid_namespace

    wrap = (pid_namespace() or []) if namespace != "same" else []
    if namespace != "same" and not wrap:
        pytest.skip("unshare -p is not permitted on this machine")
    live = subprocess.Popen([*wrap, sys.executable, "-c", (
        "import sys, time\n"
        "from v2v_server.service.shm import BatchDir, SlotRing\n"
        f"d = BatchDir.create({shm_root!r}); r = SlotRing.create(2, 4096, {shm_root!r})\n"
        "print(d.path, r.path, flush=True); time.sleep(60)\n")], stdout=subprocess.PIPE, text=True)
    live_dir, live_ring = live.stdout.readline().split()
    try:
        dead = BatchDir.create(shm_root)  # a server that dies without cleaning up: its locks go with it
        dead_ring = SlotRing.create(2, 4096, shm_root)
        dead_dir, dead_ring_path = dead.path, dead_ring.path
        os.close(dead._lock)
        dead_ring.close()
        young = os.path.join(shm_root, "v2v-batches-1-young")  # made, lock file not yet: a server starting
        os.mkdir(young)
        old = os.path.join(shm_root, "v2v-batches-1-old")  # no lock file for long
        os.mkdir(old)
        os.utime(old, (time.time() - 3600, time.time() - 3600))
        link = os.path.join(shm_root, "v2v-batches-1-link")
        os.symlink(dead_dir, link)
        gone = remove_stale_shm(shm_root)
        assert sorted(gone) == sorted([dead_dir, dead_ring_path, old])
        for p in (live_dir, live_ring, young):
            assert os.path.exists(p), p
        assert os.path.islink(link)
    finally:
        live.kill()
        live.wait()
    deadline = time.monotonic() + 10  # (in its own namespace the server is unshare's child: it goes next)
    while (gone := remove_stale_shm(shm_root)) == [] and time.monotonic() < deadline:
        time.sleep(0.1)
    assert sorted(gone) == sorted([live_dir, live_ring])  # now it is dead too


def _read_epoch(endpoint, shm, raw=True):
    from v2v_client import V2VPushDataset

    got = {}
    for batch in V2VPushDataset(endpoint, outputs=OUT, raw=raw, timeout_s=90, shm=shm):
        for i, sid in enumerate(batch["sample_ids"]):
            got[sid] = {k: batch[k][i].numpy().copy() for k in OUT}
    return got


def _batch_dirs(root):
    return [f for f in os.listdir(root) if f.startswith("v2v-batches-")]


def test_served_batches_are_identical_with_the_hand_off_on_and_off_and_no_file_outlives_the_server(
        shm_root, monkeypatch):
    from harness.serve import ServeProcess
    from v2v_client import handoff

    reads = []
    real_read = handoff.ShmReader.read
    monkeypatch.setattr(handoff.ShmReader, "read", lambda self, h, copy=True: reads.append(1) or real_read(self, h, copy))
    args = ["--videos", str(video_dir()), "--workers", "1", "--sequence-length", "4", "--num-bins", "3",
            "--crop-size", "48", "--max-samples-per-video", "2", "--seed", "5", "--epochs", "1", "--batch-size", "3",
            # arrival order: a shuffle buffer larger than this 6-sample epoch holds every sample to
            # the epoch's end, whose leftovers from several open batches are stacked (copied)
            "--shuffle", "none"]
    env = {"V2V_SHM_DIR": shm_root}
    with tempfile.TemporaryDirectory(prefix="v2v-ipc-") as d:
        ep = ["--bind", f"ipc://{d}/serve.sock"]
        with ServeProcess(args + ep, env=env) as srv:
            on = _read_epoch(srv.endpoint, shm="auto")
            assert len(_batch_dirs(shm_root)) == 1
            srv.wait(60)  # the stream ended: the server exits by itself
        n_on = len(reads)
        assert _batch_dirs(shm_root) == []
        with ServeProcess(args + ep, env=env) as srv:
            off = _read_epoch(srv.endpoint, shm=False)
        assert len(reads) == n_on
        with ServeProcess(args + ep, env=env) as srv:  # raw=False converts from the mapping
            conv = _read_epoch(srv.endpoint, shm=True, raw=False)
        assert len(reads) > n_on
        n_conv = len(reads)
        with ServeProcess(args, env=env) as srv:  # bound to tcp://: the server does not honour shm
            tcp = _read_epoch(srv.endpoint, shm=True)
            assert _batch_dirs(shm_root) == []
        assert len(reads) == n_conv
        # SIGKILL leaves the directory; the next server removes it at start
        srv = ServeProcess(args + ep, env=env).start()
        assert len(_batch_dirs(shm_root)) == 1
        srv.proc.kill()
        srv.stop()
        assert len(_batch_dirs(shm_root)) == 1
        with ServeProcess(args + ep, env=env) as srv:
            assert len(_batch_dirs(shm_root)) == 1 and str(srv.proc.pid) in _batch_dirs(shm_root)[0]
    assert _batch_dirs(shm_root) == []
    # one batch of this corpus is consecutive rows of one buffer (a reference), the other mixes
    # int8 and int16 voxels (stacked: frames); both arrive identical to the frames-only run
    assert n_on >= 1 and len(on) >= 4 and on.keys() == off.keys() == conv.keys() == tcp.keys()
    for sid in on:
        for k in OUT:
            a, b = on[sid][k], off[sid][k]
            assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), (sid, k)
            assert a.tobytes() == tcp[sid][k].tobytes()
            assert conv[sid][k].dtype == np.float32
        assert np.array_equal(conv[sid]["voxels"], on[sid]["voxels"].astype(np.float32))
        assert np.array_equal(conv[sid]["frames"], on[sid]["frames"] * np.float32(1 / 255.0))


def test_a_symlinked_batch_directory_is_refused_and_batches_come_over_the_socket(shm_root, tmp_path):
    """A welcome naming a batch directory that is a symbolic link (forged, or planted by another
    user): the client reads nothing through it and says hello again without the hand-off."""
    import threading

    import zmq

    from v2v_client import V2VPushDataset
    from v2v_client.handoff import shm_dir_problem
    from v2v_wire.protocol import pack, unpack

    target = tmp_path / "elsewhere"
    target.mkdir()
    link = os.path.join(shm_root, "v2v-batches-1-forged")
    os.symlink(target, link)
    assert shm_dir_problem(link) == "is a symbolic link"
    ctx = zmq.Context()
    router = ctx.socket(zmq.ROUTER)
    router.setsockopt(zmq.LINGER, 0)
    port = router.bind_to_random_port("tcp://127.0.0.1")
    ds = V2VPushDataset(f"tcp://127.0.0.1:{port}", outputs=("voxels",), timeout_s=5, shm=True)
    t = threading.Thread(target=lambda: next(iter(ds), None), daemon=True)
    t.start()
    hellos = []
    try:
        while len(hellos) < 2 and router.poll(10_000):
            ident, msg = router.recv_multipart()
            h = unpack(msg)
            if h["type"] == "hello":
                hellos.append(h)
                router.send_multipart([ident, pack({"type": "welcome", "hello_id": h["hello_id"],
                                                    "info": {"shm_dir": link}})])
    finally:
        ds.close()
        router.close()
        ctx.term()
    assert [h.get("shm", False) for h in hellos] == [True, False]

"""Short runs of the fault scenarios (harness/faults.py): within an epoch every sample id reaches the trainer
exactly once, whatever crashes in between; bad input is a verdict, not an outage."""
from __future__ import annotations

import subprocess
import sys
import time

import pytest
import torch

from harness import faults
from harness.faults import Layout
from v2v_client import StreamError, V2VPushDataset
from harness.serve import ServeProcess
from v2v_wire.protocol import pack

LAYOUT = Layout(L=4, crop=64, windows=2, batch=2)


def assert_exactly_once(r):
    assert r["expected"] > 0
    assert (r["lost"], r["duplicated"], r["unexpected"]) == (0, 0, 0), r
    assert r["delivered"] == r["expected"]


def test_worker_sigkill_mid_epoch(tmp_path):
    # enough videos that the workers are still busy when the first kill lands (a corpus the
    # shuffle buffer holds whole can be made before the first batch is read: no restart)
    r = faults.scenario_worker_kill(tmp_path, LAYOUT, kills=2, copies=4)
    assert_exactly_once(r)
    assert r["facts"]["restarts"] > 0


def test_client_sigkill_and_restart_from_state_dict(tmp_path):
    assert_exactly_once(faults.scenario_client_kill(tmp_path, LAYOUT, kill_after_steps=2))


def test_server_restart_mid_epoch_with_client_resume(tmp_path):
    """The restarted server's batch ids are all above the killed one's: a client's records name batches by id
    alone (docs/delivery.md, "Transport")."""
    r = faults.scenario_server_restart(tmp_path, LAYOUT, kill_after_batches=2)
    assert_exactly_once(r)
    assert r["recover_s"] is not None
    before, after = r["facts"]["batch_ids"]
    assert before and after and min(after) > max(before), (before, after)


def test_a_client_stopped_past_its_timeout_across_a_server_restart_reads_on(tmp_path):
    r = faults.scenario_stopped_past_timeout_across_restart(tmp_path, LAYOUT, timeout_s=3.0)
    assert_exactly_once(r)
    assert r["facts"]["client_exit"] == 0 and r["recover_s"] is not None, r


def test_stalled_client_longer_than_lease(tmp_path):
    r = faults.scenario_stalled_client(tmp_path, LAYOUT, lease_s=1.0, stall_s=3.0)
    assert_exactly_once(r)
    assert r["facts"]["held"] > 0  # the stalled client really held batches


def test_corpus_with_every_kind_of_bad_file(tmp_path):
    r = faults.scenario_bad_corpus(tmp_path, LAYOUT)
    assert_exactly_once(r)
    f = r["facts"]
    assert (f["bad_logged_once"], f["bad_files"], f["non_videos_logged"], f["non_videos"], f["server_exit"]) == (8, 8, 4, 4, 0)


def test_fuzzing_peer_does_not_disturb_a_trainer(tmp_path):
    r = faults.scenario_fuzzing_peer(tmp_path, LAYOUT, n=150)
    assert_exactly_once(r)
    assert r["facts"]["server_exit"] == 0


def test_fuzz_against_idle_server_then_serve(tmp_path):
    """Random and mutated frames first; a normal client is served afterwards."""
    corpus = faults.good_corpus(tmp_path)
    with ServeProcess(["--videos", str(corpus), "--workers", "1", *LAYOUT.args()]) as srv:
        assert faults.run_fuzzer(srv.endpoint, 200, 20.0, seed=3) > 0
        assert srv.proc.poll() is None
        it = iter(V2VPushDataset(srv.endpoint, timeout_s=30))
        b = next(it)
        it.close()
        assert b["voxels"].shape[1:] == (LAYOUT.L, 5, LAYOUT.crop, LAYOUT.crop)
    assert "dropping client" in srv.log


def test_check_lists_every_file_with_its_verdict(tmp_path):
    from harness.corpus import make_fault_corpus

    exp = make_fault_corpus(tmp_path / "c", faults.GOOD_VIDEOS, LAYOUT.L * 5 + 1)
    exp["deleted_during_epoch.mp4"] = "usable"  # still there: only the serving scenario deletes it
    out = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--check", "--videos", str(tmp_path / "c"),
                          *LAYOUT.args()], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    lines = {ln.split()[0]: ln for ln in out.stdout.splitlines()[1:-1]}
    for name, want in exp.items():
        verdict = {"usable": "window(s)", "skipped": "unusable", "ignored": "ignored"}[want]
        assert verdict in lines[name], (name, lines.get(name))
    assert "empty file" in lines["zero_length.mp4"] and "unsupported codec" in lines["unsupported_codec.mp4"]


def test_corpus_without_usable_video_is_a_clear_error(tmp_path):
    d = tmp_path / "bad"
    d.mkdir()
    (d / "a.mp4").write_bytes(b"")
    (d / "b.mp4").write_text("not a video")
    out = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--check", "--videos", str(d)],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "0 usable video(s) of 2" in out.stdout
    with ServeProcess(["--videos", str(d), "--workers", "1"]) as srv:
        with pytest.raises(StreamError, match="no usable video"):
            next(iter(V2VPushDataset(srv.endpoint, timeout_s=30)))
        assert srv.wait(30) == 2


def test_sigterm_stops_server_and_workers(tmp_path):
    corpus = faults.good_corpus(tmp_path)
    srv = ServeProcess(["--videos", str(corpus), "--workers", "2", *LAYOUT.args()]).start()
    try:
        it = iter(V2VPushDataset(srv.endpoint, timeout_s=30))
        next(it)
        kids = faults.worker_pids(srv.proc.pid)
        assert len(kids) == 2
        srv.proc.terminate()
        assert srv.wait(15) == 143, "SIGTERM: one line and 128 + 15, as every command answers it"
        with pytest.raises(StreamError, match="shut down"):
            for _ in range(50):
                next(it)
        time.sleep(0.5)
        for k in kids:
            assert not _alive(k), f"worker {k} left behind"
    finally:
        srv.stop()


def test_state_dict_round_trip_and_validation():
    ds = V2VPushDataset("tcp://127.0.0.1:1")
    ds.load_state_dict({"version": 1, "completed_epoch": 2, "delivered": {"3": ["a.mp4#0", "b.mp4#1"]}})
    sd = ds.state_dict()
    assert sd["completed_epoch"] == 2 and sd["delivered"] == {"3": ["a.mp4#0", "b.mp4#1"]}
    torch.save(sd, "/dev/null")
    with pytest.raises(ValueError):
        ds.load_state_dict({"epoch": 1})


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except OSError:
        return False


BAD_REPLIES = {
    "not msgpack": [b"\xc1garbage"],
    "no version": [b"\x81\xa4type\xa5batch"],
    "wrong version": [pack({"type": "batch", "v": 7})],
    "truncated array": [pack({"type": "batch", "batch_id": 0, "epoch": 0, "sample_ids": ["a#0"], "params": [{}],
                              "arrays": [{"name": "voxels", "dtype": "int8", "shape": [1, 2, 2]}]}), b"\x00"],
    "ids do not match arrays": [pack({"type": "batch", "batch_id": 0, "epoch": 0, "sample_ids": ["a#0", "a#1"],
                                      "params": [{}, {}],
                                      "arrays": [{"name": "voxels", "dtype": "int8", "shape": [1, 1]}]}), b"\x00"],
}


@pytest.mark.parametrize("name", sorted(BAD_REPLIES))
def test_client_survives_a_misbehaving_server(name):
    """A server that answers garbage gives the trainer a clear StreamError, never a crash or hang."""
    import threading

    import zmq

    from harness.serve import free_port

    ctx = zmq.Context()
    srv = ctx.socket(zmq.ROUTER)
    srv.setsockopt(zmq.LINGER, 0)
    port = free_port()
    srv.bind(f"tcp://127.0.0.1:{port}")
    it = iter(V2VPushDataset(f"tcp://127.0.0.1:{port}", outputs=("voxels",), timeout_s=10))
    result = {}

    def consume():
        try:
            next(it)
        except Exception as e:  # noqa: BLE001 - the test inspects it
            result["error"] = e

    th = threading.Thread(target=consume)
    th.start()
    assert srv.poll(5000)
    ident, _hello = srv.recv_multipart()
    srv.send_multipart([ident, *BAD_REPLIES[name]])
    th.join(20)
    assert not th.is_alive()
    assert isinstance(result.get("error"), StreamError) and "bad message" in str(result["error"])
    srv.close()
    ctx.term()

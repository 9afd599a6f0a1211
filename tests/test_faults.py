"""Short runs of the fault scenarios (harness/faults.py, harness/faults_misuse.py) against a real
v2v-serve serving by plan: within an epoch every sample id reaches the trainer exactly once,
whatever crashes in between; bad input is a verdict, not an outage."""
from __future__ import annotations

import subprocess
import sys
import threading
import time

import pytest

from harness import faults, faults_misuse
from harness.faults import Layout
from v2v_client import V2VStreamDataset
from v2v_client.plan_dataset import PlanServerError
from v2v_wire.plan import PLAN_VERSION, PlanMismatch
from v2v_wire.protocol import pack

LAYOUT = Layout(L=4, crop=64, windows=2, batch=2)


def assert_exactly_once(r):
    assert r["expected"] > 0
    assert (r["lost"], r["duplicated"], r["unexpected"]) == (0, 0, 0), r
    assert r["delivered"] == r["expected"]
    return r["facts"]


def test_worker_sigkill_mid_epoch(tmp_path):
    # enough videos that the workers are still busy when the first kill lands
    f = assert_exactly_once(faults.scenario_worker_kill(tmp_path, LAYOUT, kills=2, copies=4))
    assert f["restarts"] > 0 and f["clean"], f


def test_trainer_sigkill_and_restart_from_its_position(tmp_path):
    f = assert_exactly_once(faults.scenario_client_kill(tmp_path, LAYOUT, kill_after_steps=2))
    assert f["client_exit"] == 0, f


def test_a_trainer_suspended_while_another_job_reads_reads_its_epoch_on(tmp_path):
    f = assert_exactly_once(faults.scenario_stopped_trainer(tmp_path, LAYOUT, stop_s=3.0))
    assert f["a_exit"] == 0 and f["clean"], f


def test_a_restart_from_an_older_checkpoint_reads_the_lost_step_again_the_same_rows(tmp_path):
    f = assert_exactly_once(faults.scenario_old_checkpoint(tmp_path, LAYOUT, ckpt_step=2))
    assert f["resent"] == LAYOUT.batch and f["same_rows"], f


def test_a_worker_stopped_with_a_task_is_replaced_and_the_epoch_is_whole(tmp_path):
    r = faults.scenario_hung_worker(tmp_path, LAYOUT, task_timeout_s=2.0)
    f = assert_exactly_once(r)
    assert f["task_timeouts"] >= 1 and f["trainer_error"] is None and f["clean"], f


def test_fuzzing_peer_does_not_disturb_a_trainer(tmp_path):
    f = assert_exactly_once(faults.scenario_fuzzing_peer(tmp_path, LAYOUT, n=150))
    assert f["fuzz_messages"] == 150 and f["alive"] and f["clean"], f
    assert 0 < f["logged"] < 150, f  # refusals are logged, a bounded number of times


def test_ranks_resumed_at_another_world_size_read_each_sample_once(tmp_path):
    f = assert_exactly_once(faults_misuse.scenario_world_size_change(tmp_path, LAYOUT, 2, 1))
    assert f["same_positions"] and f["errors"] == [], f


def test_dataloader_workers_break_and_iterate_again_from_the_position(tmp_path):
    f = assert_exactly_once(faults_misuse.scenario_loader_workers(tmp_path, LAYOUT, persistent=True, take=3))
    assert f["iterations"] >= 3 and f["clean"], f


def test_positions_that_lie_are_refused_or_read_only_what_they_name(tmp_path):
    f = assert_exactly_once(faults_misuse.scenario_lying_positions(tmp_path, LAYOUT))
    a = f["answers"]
    for name in ("negative", "another seed", "a string", "no plan", "bool offset"):
        assert a[name].startswith("refused"), (name, a)
    assert a["past the end"] == "read 0 rows", a
    assert f["clean"], f


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


def test_sigterm_stops_server_and_workers(tmp_path):
    corpus = faults.good_corpus(tmp_path)
    srv = faults._serve(corpus, LAYOUT).start()
    try:
        it = iter(V2VStreamDataset(srv.endpoint, timeout_s=3, retry_s=1.0))
        next(it)
        kids = faults.worker_pids(srv.proc.pid)
        assert len(kids) == 2
        srv.proc.terminate()
        assert srv.wait(15) == 143, "SIGTERM: one line and 128 + 15, as every command answers it"
        with pytest.raises(TimeoutError, match="no rows for 3"):
            for _ in range(50):
                next(it)
        time.sleep(0.5)
        for k in kids:
            assert not _alive(k), f"worker {k} left behind"
    finally:
        srv.stop()


def test_a_malformed_position_is_refused_naming_the_field_before_any_server_is_asked():
    ds = V2VStreamDataset("tcp://127.0.0.1:1")  # nothing listens there
    with pytest.raises(PlanMismatch, match="'sample_in_epoch'"):
        ds.load_state_dict({"plan": {"manifest": "0" * 16, "recipe": "1" * 16, "seed": 3, "shuffle_buffer": 8,
                                     "version": PLAN_VERSION}, "epoch": 0, "sample_in_epoch": -1})
    with pytest.raises(PlanMismatch, match="plan"):
        ds.load_state_dict({"epoch": 1, "sample_in_epoch": 0})


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except OSError:
        return False


BAD_REPLIES = {
    "not msgpack": [b"\xc1garbage"],
    "no version": [b"\x81\xa4type\xa4plan"],
    "wrong version": [pack({"type": "plan", "v": 7})],
    "unknown type": [b"\x82\xa4type\xa5hello\xa1v\x01"],
}


@pytest.mark.parametrize("name", sorted(BAD_REPLIES))
def test_a_reader_survives_a_misbehaving_server(name):
    """A server that answers garbage gives the trainer a clear PlanServerError naming it, never a crash or hang."""
    import zmq

    from harness.serve import free_port

    ctx = zmq.Context()
    srv = ctx.socket(zmq.ROUTER)
    srv.setsockopt(zmq.LINGER, 0)
    port = free_port()
    srv.bind(f"tcp://127.0.0.1:{port}")
    ds = V2VStreamDataset(f"tcp://127.0.0.1:{port}", 2, outputs=("voxels",), timeout_s=10)
    result = {}

    def consume():
        try:
            next(iter(ds))
        except Exception as e:  # noqa: BLE001 - the test inspects it
            result["error"] = e

    th = threading.Thread(target=consume)
    th.start()
    assert srv.poll(5000)
    ident, _ask = srv.recv_multipart()
    srv.send_multipart([ident, *BAD_REPLIES[name]])
    th.join(20)
    assert not th.is_alive()
    assert isinstance(result.get("error"), PlanServerError) and f"127.0.0.1:{port}" in str(result["error"]), result
    srv.close()
    ctx.term()

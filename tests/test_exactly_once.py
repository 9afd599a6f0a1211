"""End to end on 127.0.0.1: each delivery failure mode as a short run of its scenario in
harness/faults.py (a real v2v-serve, real clips, tiny samples). Every sample id reaches a training loop
once per epoch; nothing is lost; nobody hangs or crashes."""
from __future__ import annotations

import subprocess
import sys
import time

import msgpack
import pytest

from harness import faults, faults_misuse
from harness.faults import Layout
from v2v_client import StreamError, V2VPushDataset
from v2v_server.ops.config import load_config
from harness.serve import ServeProcess
from v2v_wire.protocol import PROTOCOL_VERSION
from v2v_wire.messages import MAX_CONTAINERS, WireError, decode_client
from v2v_wire.ids import SampleKey

LAYOUT = Layout(L=4, crop=64, windows=2, batch=2)


def exactly_once(r):
    assert r["expected"] > 0
    assert (r["lost"], r["duplicated"], r["unexpected"]) == (0, 0, 0), r
    assert r["delivered"] == r["expected"], r


def test_breaking_out_of_the_loop_duplicates_nothing(tmp_path):
    exactly_once(faults.scenario_break_loop(tmp_path, LAYOUT, breaks=3))


def test_client_suspended_past_its_timeout_hands_on_nothing_it_held(tmp_path):
    r = faults.scenario_silent_client(tmp_path, LAYOUT, client_timeout_s=1.5)
    exactly_once(r)
    assert r["facts"]["drops"] > 0, r  # it really was dropped


@pytest.mark.parametrize("run", range(2))
def test_a_client_frozen_past_its_timeout_on_busy_cores_doubles_and_loses_nothing(tmp_path, run):
    """The delivery scenario of issue 61: A (credits 4, 0.3 s steps) stopped for 5 s past a 2 s
    client timeout, wherever it was between receiving a batch and yielding it, while B reads and
    two busy processes load the cores; run twice."""
    r = faults.scenario_frozen_client(tmp_path, LAYOUT, client_timeout_s=2.0, freeze_s=5.0, credits=4, step_s=0.3)
    exactly_once(r)
    assert r["facts"]["drops"] > 0 and r["facts"]["server_exit"] == 0, r  # it really was dropped


def test_a_client_stopped_at_its_yield_past_its_timeout_doubles_and_loses_nothing(tmp_path):
    """A stops itself (SIGSTOP) right as its second batch reaches its loop, before the ack may
    have left the process, for 5 s past the 2 s client timeout, on busy cores."""
    r = faults.scenario_frozen_client(tmp_path, LAYOUT, client_timeout_s=2.0, freeze_s=5.0, at_yield=True)
    exactly_once(r)
    assert r["facts"]["drops"] > 0 and r["facts"]["a_batches"] >= 2, r


def test_checkpoint_older_than_the_last_ack_loses_nothing(tmp_path):
    r = faults.scenario_old_checkpoint(tmp_path, LAYOUT, ckpt_step=2)
    exactly_once(r)
    assert r["facts"]["resent"] == 2, r


def test_a_window_that_fails_is_lost_only_for_itself_every_epoch(tmp_path):
    r = faults.scenario_partial_file(tmp_path, LAYOUT, epochs=2)
    exactly_once(r)
    assert r["facts"]["windows_per_epoch"] == [2, 2], r


def test_a_revoke_left_unanswered_expires(tmp_path):
    r = faults.scenario_revoke_ignored(tmp_path, LAYOUT, lease_s=1.0, revoke_s=1.5)
    exactly_once(r)
    assert "dropped" in r["facts"]["codes"] and r["facts"]["server_exit"] == 0, r


def test_a_trainer_slower_than_its_lease_never_holds_more_than_its_credits(tmp_path):
    # 4 credits: two batches granted ahead of the loop, the other two leased and revoked in turn
    r = faults.scenario_slow_trainer(tmp_path, LAYOUT, lease_s=0.4, step_s=0.6, credits=4, copies=2)
    exactly_once(r)
    assert r["facts"]["peak_held"] <= 4 and r["facts"]["requeues"] > 0, r


def test_a_hung_worker_is_replaced_and_the_trainer_waits(tmp_path):
    r = faults.scenario_hung_worker(tmp_path, LAYOUT, task_timeout_s=2.0, client_timeout_s=1.5)
    exactly_once(r)
    assert r["facts"]["trainer_error"] is None and r["facts"]["task_timeouts"] > 0, r


def test_a_trainer_stopped_past_the_task_timeout_costs_no_worker(tmp_path):
    """The server does not read its busy workers while enough batches wait for the stopped trainer:
    that silence is no hang (the task clock runs only while the server reads its workers)."""
    r = faults.scenario_reader_stopped_past_task_timeout(tmp_path, LAYOUT, task_timeout_s=2.0, stop_s=8.0)
    exactly_once(r)
    f = r["facts"]
    assert f["busy"] > 0, r  # workers were mid-task, unread, for 4 task timeouts
    assert (f["restarts"], f["task_timeouts"], f["server_exit"]) == (0, 0, 0), r


def test_bad_messages_neither_crash_nor_flood_the_server(tmp_path):
    r = faults.scenario_bad_peer(tmp_path, LAYOUT)
    exactly_once(r)
    f = r["facts"]
    assert f["log_lines"] < 100 and not f["traceback"] and f["server_exit"] == 0, r


def test_a_file_name_that_is_not_utf8_is_ignored_and_the_rest_served(tmp_path):
    r = faults.scenario_undecodable_name(tmp_path, LAYOUT)
    exactly_once(r)
    f = r["facts"]
    assert f["logged"] == 1 and f["server_exit"] == 0 and not f["traceback"], r


def test_independent_trainers_resume_apart_after_a_restart_with_a_journal(tmp_path):
    r = faults.scenario_independent_restart(tmp_path, LAYOUT, journal=True, late_s=3.0)
    exactly_once(r)
    assert r["facts"]["server_exit"] == 0, r


def test_ddp_ranks_get_equal_batch_counts(tmp_path):
    r = faults.scenario_ddp_ranks(tmp_path, LAYOUT, world=4)
    exactly_once(r)
    counts = r["facts"]["batches_per_rank"]
    assert len(set(counts)) == 1 and counts[0] > 0 and r["facts"]["errors"] == 0, r


def test_a_late_ddp_rank_after_a_server_restart(tmp_path):
    r = faults.scenario_ddp_late_rank(tmp_path, LAYOUT, delay_s=2.5)
    exactly_once(r)
    assert r["facts"]["errors"] == [], r


def test_twenty_trainers_share_a_stream(tmp_path):
    r = faults.scenario_fair_sharing(tmp_path, Layout(L=4, crop=64, windows=2, batch=1), clients=20)
    exactly_once(r)
    lo, hi = r["facts"]["min_batches"], r["facts"]["max_batches"]
    assert lo >= 1 and hi - lo <= 2, r


def test_outputs_follow_the_clients_and_limits_are_clear(tmp_path):
    corpus = faults.good_corpus(tmp_path)
    with ServeProcess(["--videos", str(corpus), "--workers", "1", *LAYOUT.args(), "--max-credits", "8"]) as srv:
        it = iter(V2VPushDataset(srv.endpoint, outputs=("voxels",), timeout_s=30))
        assert "flow" not in next(it)
        it2 = iter(V2VPushDataset(srv.endpoint, outputs=("voxels", "flow"), timeout_s=30))
        b = next(it2)  # a second client asking for more gets it: the workers compute the union now
        assert b["flow"].shape[1:] == (LAYOUT.L, 2, LAYOUT.crop, LAYOUT.crop)
        it.close()
        it2.close()
        with pytest.raises(StreamError, match="at most 8 batches in flight"):
            next(iter(V2VPushDataset(srv.endpoint, credits=9, timeout_s=30)))
    out = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--workers", "2000", "--check"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "workers must be <= 256" in out.stderr
    cfg = tmp_path / "c.yaml"
    cfg.write_text("lease_s: 1.0e9\nclient_timeout_s: 3e1\nprefetch_batches: 4\n")
    c = load_config(str(cfg))
    assert c.lease_s == 1.0e9 and c.client_timeout_s == 30.0
    cfg.write_text("prefetch_batches: 100000\n")
    with pytest.raises(ValueError, match="prefetch_batches must be <= 256"):
        load_config(str(cfg))


def test_check_names_the_window_where_the_frame_size_changes(tmp_path):
    from harness.corpus import write_size_change_video

    span = LAYOUT.L * 5 + 1
    write_size_change_video(tmp_path / "sc.mpg", span + span // 2, 2 * span)
    # windows at k x stride: the shot detector takes the change of size for a cut
    out = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--check", "--videos", str(tmp_path),
                          *LAYOUT.args(), "--max-samples-per-video", "3", "--shot-cuts", "off"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "2 window(s)" in out.stdout and "window 1: frame size changed from 320x240 to 256x192" in out.stdout


# ---------------------------------------------------------------------- bounded decoding (no server needed)
@pytest.mark.parametrize("frame,why", [
    (msgpack.packb({"type": "hello", "v": PROTOCOL_VERSION, "outputs": ["voxels"], "credits": 1,
                    "resume": {"delivered": {"0": [[]] * 4000}}}), "arrays/maps"),
    (b"\x91" * 200000 + b"\xc0", "msgpack"),
    (msgpack.packb({"type": "ack", "v": PROTOCOL_VERSION, "batch_ids": list(range(5000))}), "msgpack"),
    (msgpack.packb({"type": "ack", "v": PROTOCOL_VERSION, "batch_ids": ["1"]}), "batch_ids"),
    (msgpack.packb({"type": "ack", "v": PROTOCOL_VERSION, "batch_ids": [True]}), "batch_ids"),
    (msgpack.packb({"type": "hello", "v": PROTOCOL_VERSION, "outputs": ["voxels"], "credits": 1,
                    "resume": {"delivered": {"٣": "a#1"}}}), "epoch numbers"),
    (msgpack.packb({"type": "hello", "v": PROTOCOL_VERSION, "outputs": ["voxels"], "credits": 1, "rank": 3, "world_size": 2}),
     "rank"),
    (msgpack.packb({"type": "credit", "v": PROTOCOL_VERSION, "credit": 1.5}), "credit"),
])
def test_wire_rejects_bombs_and_wrong_types_quickly(frame, why):
    t = time.perf_counter()
    with pytest.raises(WireError, match=why):
        decode_client(frame, 16 << 20, 64)
    assert time.perf_counter() - t < 1.0
    assert MAX_CONTAINERS <= 1024


def test_wire_ignores_sample_ids_with_non_ascii_digits():
    h = decode_client(msgpack.packb({"type": "hello", "v": PROTOCOL_VERSION, "outputs": ["voxels"], "credits": 2,
                                     "resume": {"delivered": {"0": "a.mp4#1\na.mp4#٣\n../x#2"}}}), 1 << 20, 64)
    assert h.resume.delivered[0] == frozenset({SampleKey("a.mp4", 1), SampleKey("../x", 2)})  # the server only knows its own files


# ---------------------------------------------------------------------- careless and hostile clients (issue 69)
def test_a_second_trainer_on_one_consumer_id_is_refused_and_the_first_reads_everything(tmp_path):
    r = faults_misuse.scenario_two_readers_one_consumer(tmp_path, LAYOUT)
    exactly_once(r)
    f = r["facts"]
    assert f["second_batches"] == 0 and f["server_exit"] == 0, r
    assert f["refused"] and "consumer" in f["refused"][0] and "one reader per consumer" in f["refused"][0], r


def test_a_second_ddp_job_on_the_default_group_is_refused_with_a_line_saying_to_set_group(tmp_path):
    r = faults_misuse.scenario_two_ddp_jobs_one_group(tmp_path, LAYOUT)
    exactly_once(r)
    f = r["facts"]
    assert f["second_samples"] == 0 and not f["first_errors"] and f["server_exit"] == 0, r
    assert f["refused"] and all("group=" in line for line in f["refused"]), r


@pytest.mark.parametrize("old,new", [(2, 1), (1, 2)])
def test_a_job_resumed_at_another_world_size_trains_every_sample_once(tmp_path, old, new):
    """From one rank's state alone a 2 -> 1 resume is refused before the first batch with one
    line saying what to load; from every rank's state (and 1 -> 2 from the one state) it is exact."""
    r = faults_misuse.scenario_world_size_change(tmp_path, LAYOUT, old, new)
    exactly_once(r)
    f = r["facts"]
    assert not f["errors"], r
    if old > 1:
        assert f["refused"] and "v2v_ranks" in f["refused"][0] and f"rank 0 of {old}" in f["refused"][0], r


def test_a_trainer_woken_after_another_read_every_epoch_gets_back_what_it_held(tmp_path):
    r = faults_misuse.scenario_wake_after_others_ran_ahead(tmp_path, LAYOUT, epochs=2, freeze_s=6.0)
    exactly_once(r)
    assert r["facts"]["a_exit"] == 0 and r["facts"]["a_samples"] > 0, r


def test_a_peer_sitting_on_grants_delays_the_honest_trainers_end_by_the_lease_at_most(tmp_path):
    r = faults_misuse.scenario_sitting_on_grants(tmp_path, LAYOUT, lease_s=2.0)
    exactly_once(r)
    f = r["facts"]
    assert f["held"] > 0 and not f["errors"] and f["ended_after_s"] is not None, r
    assert f["ended_after_s"] < 2.0 + 3.0, r  # the lease, plus a loaded machine's turns


def test_a_loop_that_stops_reading_delays_nobody_and_gets_what_it_held(tmp_path):
    r = faults_misuse.scenario_loop_stops_reading(tmp_path, LAYOUT, pause_s=4.0)
    exactly_once(r)
    assert r["facts"]["b_samples"] > 0, r


def test_lying_resume_states_are_refused_and_cost_what_they_weigh(tmp_path):
    r = faults_misuse.scenario_lying_resume_states(tmp_path, LAYOUT, big=200_000)
    exactly_once(r)
    f = r["facts"]
    big = f["codes"].pop("200000 ids")
    assert set(f["codes"].values()) == {"resume"} and big == "error", r  # the ids counted before any is parsed
    assert "never granted" in f["messages"]["never sent"] and "--epochs 2" in f["messages"]["completed 5"], r
    assert "which gives 2" in f["messages"]["200000 ids"] and f["holds_s"] < 5 and f["longest_wait_s"] < 5, r
    assert not f["errors"] and f["server_exit"] == 0, r
    assert f["rss_after_mb"] <= 1.1 * f["rss_before_mb"], r


def test_a_first_hello_past_the_last_epoch_is_refused_and_moves_nothing(tmp_path):
    r = faults_misuse.scenario_first_hello_far_ahead(tmp_path, LAYOUT)
    exactly_once(r)
    assert r["facts"]["code"] == "resume" and "--epochs 2" in r["facts"]["message"], r


def test_an_old_client_is_refused_with_one_line():
    """A hello of the protocol before this one is answered with an error naming both versions."""
    with pytest.raises(WireError, match=f"protocol version {PROTOCOL_VERSION - 1}, expected {PROTOCOL_VERSION}"):
        decode_client(msgpack.packb({"type": "hello", "v": PROTOCOL_VERSION - 1, "outputs": ["voxels"],
                                     "credits": 1}), 1 << 20, 64)

"""Short runs of the deployment fault scenarios (harness/faults_deploy.py) against servers serving
by plan: v2v-train killed against two shards, a second server in its own PID namespace, IPv6, a
scrape storm, resumes across shards and under another recipe - every sample id exactly once."""
from __future__ import annotations

import pytest

from harness import faults_deploy
from harness.faults import Layout

LAYOUT = Layout(L=4, crop=64, windows=2, batch=2)


def exactly_once(r):
    if "skipped" in r:
        pytest.skip(r["skipped"])
    assert r["expected"] > 0
    assert (r["lost"], r["duplicated"], r["unexpected"], r["delivered"]) == (0, 0, 0, r["expected"]), r
    return r["facts"]


def test_v2v_train_killed_with_sigkill_against_two_shards_resumes_exactly_once(tmp_path):
    f = exactly_once(faults_deploy.scenario_train_killed_two_shards(tmp_path, Layout(L=4, crop=64, windows=3, batch=2),
                                                                    checkpoint_every=2, kill_after=5))
    assert f["kill_exit"] == -9 and f["resumed_exit"] == 0 and f["server_exits"] == [130, 130], f
    assert f["killed_after"] > f["checkpoint_step"] >= 2, f  # steps after the checkpoint were lost with the process


def test_two_shards_resumed_from_an_older_position_read_the_lost_steps_again(tmp_path):
    f = exactly_once(faults_deploy.scenario_fan_in_resume(tmp_path, LAYOUT, ckpt_step=2, crash_step=4))
    assert f["read_again"] == 2 * LAYOUT.batch and f["clean"], f


def test_a_second_server_in_its_own_pid_namespace_leaves_a_live_servers_workers_alone(tmp_path):
    f = exactly_once(faults_deploy.scenario_second_server_pid_namespace(tmp_path, LAYOUT))
    assert f["worker_deaths"] == 0 and f["left"] == [] and f["server_exits"] == [130, 130], f


def test_ipv6_loopback_epoch(tmp_path):
    f = exactly_once(faults_deploy.scenario_ipv6(tmp_path, LAYOUT))
    assert f["server_exit"] == 130 and f["clean"], f


def test_a_scrape_storm_leaves_the_epoch_whole_and_every_scrape_answered(tmp_path):
    f = exactly_once(faults_deploy.scenario_scrape_storm(tmp_path, LAYOUT, rate=200))
    assert f["scrapes"] >= 100 * f["seconds"] * 0.5 and f["scrape_errors"] == 0 and f["server_exit"] == 130, f


def test_a_resume_under_another_seed_sequence_length_or_crops_per_window_is_refused(tmp_path):
    r = faults_deploy.scenario_resume_other_recipe(tmp_path, LAYOUT)
    assert (r["facts"]["refused"], r["facts"]["handed"]) == (r["facts"]["cases"], 0), r

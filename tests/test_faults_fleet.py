"""Short runs of the fleet fault scenarios (harness/faults_fleet.py): real ``v2v-serve`` hosts on
127.0.0.1 read as one fleet - a first-listed host dead for good, one host under two names, a file
replaced under the fleet - every sample id exactly once."""
from __future__ import annotations

import pytest

from harness import faults_fleet
from harness.faults import Layout
from v2v_client.fleet_read import ASK_NEXT_S

LAYOUT = Layout(L=4, crop=64, windows=2, batch=2)


def exactly_once(r):
    assert r["expected"] > 0
    assert (r["lost"], r["duplicated"], r["unexpected"], r["delivered"]) == (0, 0, 0, r["expected"]), r
    return r["facts"]


@pytest.mark.timeout(300)
def test_a_first_listed_host_dead_for_good_costs_the_next_epoch_one_short_ask_not_its_timeout(tmp_path):
    f = exactly_once(faults_fleet.scenario_first_host_killed(tmp_path, LAYOUT, timeout_s=20.0))
    assert f["error"] is None and f["epoch1_samples"] > 0, f
    assert ASK_NEXT_S <= f["epoch1_first_s"] < 20.0 / 2, f  # the dead host skipped after ASK_NEXT_S, not waited on
    assert f["server_exit"] == 130 and f["clean"], f


@pytest.mark.timeout(300)
def test_one_host_under_two_names_is_read_once_and_said_in_one_line(tmp_path):
    f = exactly_once(faults_fleet.scenario_one_host_two_names(tmp_path, LAYOUT))
    assert f["hosts"] == [f["hosts"][0]] and f["hosts"][0].startswith("tcp://localhost:"), f  # the first name kept
    assert f["made"] == f["read"], f  # each sample made once, not once per name
    assert len(f["said"]) == 1, f
    assert f["server_exit"] == 130 and f["clean"], f


@pytest.mark.timeout(300)
def test_a_file_replaced_under_a_fleet_is_never_mixed_into_one_epoch_and_is_named_in_one_line(tmp_path):
    """A deploy replaces bikes.mp4 and restarts each host in turn: every pass's samples of it are
    of one version (old in epoch 0, new once epoch 1 is started over); a host left out is named
    with the file; the pass no host serves any more fails in one line naming it and saying to
    start the epoch over; the next pass reads the new plan, said in one line naming the file."""
    f = exactly_once(faults_fleet.scenario_file_replaced_under_fleet(tmp_path, LAYOUT))
    assert f["versions"]["epoch 0"] == ["old"] and f["versions"]["epoch 1, started over"] == ["new"], f
    assert f["mixed"] == [], f
    assert f["versions"].get("epoch 1, first pass", ["old"]) == ["old"], f  # read before it failed: the old file's
    for line in (f["said"][0], f["error"], f["switched"][0]):
        assert "\n" not in line and "bikes.mp4 (tag file 509868 1500000000" in line, f
    assert "start epoch 1 over" in f["error"], f
    assert len(f["switched"]) == 1, f
    assert f["server_exit"] == (130, 130) and f["clean"], f

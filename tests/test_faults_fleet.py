"""Short runs of the fleet fault scenarios (harness/faults_fleet.py): real ``v2v-serve`` hosts on
127.0.0.1 read as one fleet - a first-listed host dead for good, one host under two names - every
sample id exactly once."""
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

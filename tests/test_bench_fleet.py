"""``bench/fleet.py``'s ``cache`` row on the bundled clips once (4 videos), its ``ranks`` row on
them sixty times (240 videos: a reader's queue long enough for its load bound to matter) and its
``batches`` row at batch 32 on them eight times: real ``v2v-serve`` hosts pinned with
``taskset``; and a bad ``--rows`` or ``--ranks`` in one line."""
from __future__ import annotations

import os
import shutil

import pytest

from bench.fleet import batches_row, cache_row, main, make_corpus, ranks_row


def test_a_row_the_bench_lacks_is_one_line(capsys):
    assert main(["--rows", "cache,nope"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--rows nope" in err
    assert main(["--rows", "ranks", "--ranks", "0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--ranks" in err
    assert main(["--copies", "0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--copies" in err


def test_results_never_replace_a_file_that_is_not_json(tmp_path, capsys):
    """bench.fleet's and harness.fleet_sim's --json naming a source (or any file not .json) is one
    line, the file untouched."""
    from harness.fleet_sim import main as sim_main
    src = tmp_path / "fleet.py"
    src.write_text("source\n")
    for run, tool in ((main, "bench.fleet"), (sim_main, "harness.fleet_sim")):
        assert run(["--json", str(src)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith(f"{tool}: --json {src}: exists and is not a .json file"), err
        assert src.read_text() == "source\n"


def test_the_simulators_tables_refuse_a_json_they_would_not_write(tmp_path, capsys):
    """harness.fleet_sim's --waits, --padding and --autoscale print a table only: with --json each
    is one line naming both options, and nothing is written."""
    from harness.fleet_sim import main as sim_main
    out = tmp_path / "sim.json"
    for option in (["--waits", "1"], ["--padding", "10"], ["--autoscale"]):
        assert sim_main(["--json", str(out), *option]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith(f"harness.fleet_sim: --json {out}: not written with "
                                                        f"{option[0]}"), err
        assert not out.exists()


@pytest.mark.skipif(shutil.which("taskset") is None or (os.cpu_count() or 1) < 2, reason="needs taskset and 2 cores")
@pytest.mark.timeout(300)
def test_epoch_2_finds_a_lone_hosts_videos_and_a_fleets_that_stay_on_their_host_in_its_frame_cache(tmp_path):
    r = cache_row(make_corpus(tmp_path / "corpus", 1), tmp_path)
    one, pair = r["alone"], r["fleet"]
    assert one["hits"] > 0 and one["misses"] == 0 and one["videos_moved"] == 0
    assert pair["videos"] == 4 and pair["hits"] + pair["misses"] >= 4  # each video passed at least once
    # a video made by the same host in both epochs is found in that host's cache
    assert pair["hits"] >= round(4 * (1 - pair["videos_moved"]))
    assert r["fleet_over_alone"] == pair["hit_ratio"]


@pytest.mark.skipif(shutil.which("taskset") is None or (os.cpu_count() or 1) < 2, reason="needs taskset and 2 cores")
@pytest.mark.timeout(300)
def test_four_ranks_of_a_job_reading_a_fleet_have_each_video_made_about_once(tmp_path):
    """Each rank routes its own asks; a video both ranks need goes to one host (where its arbiter
    placed it for the first rank that asked), not to one host per rank."""
    r = ranks_row(make_corpus(tmp_path / "corpus", 60), 4)
    assert r["samples_read"] > 0 and 1.0 <= r["made_over_read"] <= 1.1, r  # each rank's own load bound: 1.66
    assert r["videos_of_two_hosts"] <= 0.05, r  # 0.41


@pytest.mark.skipif(shutil.which("taskset") is None or (os.cpu_count() or 1) < 2, reason="needs taskset and 2 cores")
@pytest.mark.timeout(300)
def test_one_host_read_at_batch_32_makes_each_sample_of_each_epoch_once(tmp_path):
    """A batch larger than the host's own (12): the samples a pending fetch names are asked now,
    not made ahead, so the store's bound does not push out the shuffle buffer's samples the plan
    reaches next, and a video is decoded once an epoch (2.4 made a sample read from epoch 1 on
    when it did)."""
    r = batches_row(make_corpus(tmp_path / "corpus", 8), batches=(32,), epochs=2)[32]
    assert [e["samples_read"] for e in r["epochs"]] == [8 * 29, 8 * 29], r  # 10, 10, 6 and 3 samples a clip
    assert r["worst_made_over_read"] <= 1.02, r

"""``bench/fleet.py``'s ``cache`` row on the bundled clips once (4 videos): real ``v2v-serve``
hosts with a frame cache each, pinned with ``taskset``; and a bad ``--rows`` in one line."""
from __future__ import annotations

import os
import shutil

import pytest

from bench.fleet import cache_row, main, make_corpus


def test_a_row_the_bench_lacks_is_one_line(capsys):
    assert main(["--rows", "cache,nope"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--rows nope" in err


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

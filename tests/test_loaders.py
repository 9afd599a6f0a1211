"""The stream under the loaders people train with (real libraries, real server on 127.0.0.1):
Lightning's DDP launcher, torch DataLoader workers, torchdata's StatefulDataLoader."""
from __future__ import annotations

import json
import subprocess
import sys

from harness import faults
from harness.faults import Layout
from harness.serve import ServeProcess

LAYOUT = Layout(L=4, crop=64, windows=2, batch=2)


def test_lightning_ddp_with_the_dataset_built_before_fit(tmp_path):
    corpus = faults.good_corpus(tmp_path, 2)
    expected = faults.expected_ids(corpus, LAYOUT)
    out = tmp_path / "out"
    out.mkdir()
    with ServeProcess(["--videos", str(corpus), "--workers", "2", "--epochs", "1", *LAYOUT.args()]) as srv:
        r = subprocess.run([sys.executable, "-m", "harness.lightning_ddp", srv.endpoint, str(out)],
                           capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr[-3000:]
        assert srv.wait(30) == 0
    ranks = [json.loads((out / f"rank{i}.json").read_text()) for i in range(2)]
    assert [r["dataset_world_size"] for r in ranks] == [2, 2]
    assert ranks[0]["batches"] == ranks[1]["batches"] > 0
    seen = ranks[0]["seen"] + ranks[1]["seen"]
    assert sorted(seen) == expected  # every sample once over both ranks, padding aside


def test_dist_position_reads_the_process_group_then_the_environment(monkeypatch):
    import pytest
    import torch.distributed as dist

    from harness.serve import free_port
    from v2v_client import dist_position

    monkeypatch.delenv("RANK", raising=False)
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    assert dist_position() == (0, 1)
    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("WORLD_SIZE", "3")
    assert dist_position() == (1, 3)
    monkeypatch.setenv("RANK", "one")
    with pytest.raises(ValueError, match="RANK"):
        dist_position()
    monkeypatch.setenv("RANK", "0")
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{free_port()}", rank=0, world_size=1)
    try:
        with pytest.raises(ValueError, match="world size 1 but WORLD_SIZE=3"):
            dist_position()
        monkeypatch.setenv("WORLD_SIZE", "1")
        assert dist_position() == (0, 1)
    finally:
        dist.destroy_process_group()


def test_stateful_dataloader_resumes_an_older_checkpoint_after_the_epoch_ended(tmp_path):
    r = faults.scenario_resume_after_end(tmp_path, LAYOUT, ckpt_step=2, grace_s=3.0)
    assert (r["lost"], r["duplicated"], r["unexpected"]) == (0, 0, 0), r
    f = r["facts"]
    assert f["ended_alive"] and f["resumed_equal"] and f["server_exit"] == 0, r
    assert 3.0 <= f["exit_after_s"] < 30, r


def test_stream_loader_workers_persistent_break_and_iterate_again(tmp_path):
    r = faults.scenario_loader_workers(tmp_path, LAYOUT, persistent=True, take=3)
    assert (r["lost"], r["duplicated"], r["unexpected"]) == (0, 0, 0), r
    assert r["facts"]["rounds"] > 1 and r["facts"]["server_exit"] == 0, r


def test_stream_loader_workers_not_persistent_break_and_iterate_again(tmp_path):
    r = faults.scenario_loader_workers(tmp_path, LAYOUT, persistent=False, take=3)
    assert (r["lost"], r["duplicated"], r["unexpected"]) == (0, 0, 0), r
    assert r["facts"]["rounds"] > 1 and r["facts"]["server_exit"] == 0, r

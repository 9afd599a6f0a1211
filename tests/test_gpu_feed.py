"""``bench/gpu_feed.py`` in its CPU smoke mode: a live v2v-serve on this host, the cached and
live runs of EV-FlowNet and E-RAFT (consecutive voxel pairs), the per-step
operator count, the producer-alone row, and the JSON and markdown it writes."""
from __future__ import annotations

import json
import math
import os

import pytest

from bench.gpu_feed import PAPER_BATCH, main
from trainer.config import default_config


def test_paper_batches():
    assert PAPER_BATCH == {"e2vid": 12, "hypere2vid": 12, "evflow": 12, "etnet": 6, "eraft": 10}


def test_gpu_feed_smoke_run(tmp_path, videos):
    assert main(["--smoke", "--models", "evflow,eraft", "--amp", "fp32", "--workers", "1", "--steps", "1",
                 "--warmup", "1", "--producer", "1", "--no-trades", "--producer-samples", "24", "--videos", str(videos),
                 "--device", "cpu", "--out", str(tmp_path)]) == 0
    out = json.loads((tmp_path / "gpu_feed.json").read_text())
    assert out["smoke"] and out["sizes"]["sequence_length"] == 2 and out["torch"]
    assert [(r["model"], r["amp"], r["batch"]) for r in out["rows"]] == [("evflow", "fp32", "2"),
                                                                          ("eraft", "fp32", "2")]
    # each row in a process of its own
    assert len({r["pid"] for r in out["rows"]} | {os.getpid()}) == 3
    for r in out["rows"]:
        # an eager network compiles nothing, and no CUDA graph is skipped
        assert r["graphs"] == r["recompiles"] == r["cudagraph_skips"] == 0
        for run in ("cached", "live"):
            m = r[run]
            assert m["steps_per_s"] > 0 and math.isclose(m["samples_per_s"], 2 * m["steps_per_s"])
            assert 0 <= m["data_wait_fraction"] < 1 and m["peak_mem_gib"] is None  # no GPU memory on a CPU
        assert r["cached"]["gpu_busy"] is None  # no GPU to sample
        assert r["launches"]["what"] == "aten ops dispatched (CPU)" and r["launches"]["count"] > 100
        assert r["workers_needed"] == "<= 1" or r["workers_needed"] >= 1
    # E-RAFT runs the network once per consecutive pair, on a bigger graph than EV-FlowNet's
    assert out["rows"][1]["launches"]["count"] > out["rows"][0]["launches"]["count"]
    (p,) = out["producer"]["rows"]
    assert p["recipe"] == "default" and out["producer"]["sizes"]["crop"] == 32  # toy sizes with --smoke
    assert p["workers"] == 1 and p["samples"] >= 24 and p["per_worker_cpu_s"] > 0 and p["threads"] >= 1
    assert 0 < p["share_of_bound"] and 0 <= p["other_threads"] <= 1
    text = (tmp_path / "gpu_feed.md").read_text()
    assert text.count("| evflow |") == 1 and text.count("| eraft |") == 1
    assert "No GPU here" in text and "torch " in text and "python -m bench.gpu_feed --smoke" in text
    assert "## Producer alone" in text


def test_speed_option_follows_the_trainer_config(tmp_path, videos):
    # no --videos: the bench's own corpus of copies of the WebVid-like clip
    args = ["--smoke", "--models", "evflow", "--amp", "fp32", "--workers", "1", "--steps", "1", "--warmup", "1",
            "--device", "cpu", "--out", str(tmp_path), "--speed", "eager,fast"]
    if "speed" not in default_config("evflow"):
        with pytest.raises(SystemExit, match="no 'speed' setting"):
            main(args)
        return
    assert main(args) == 0
    out = json.loads((tmp_path / "gpu_feed.json").read_text())
    assert [(r["speed"], r["batch"]) for r in out["rows"]] == [("eager", "2"), ("fast", "2")]
    assert out["videos"] == "2 copies of webvid_like_596x336.mp4"


def test_busy_sampler_polls_nvidia_smi_of_the_visible_gpu(monkeypatch):
    """Without pynvml the GPU-busy column polls ``nvidia-smi`` for the physical GPU behind the
    torch device (CUDA_VISIBLE_DEVICES renumbers them) and averages its percentages."""
    import sys
    import time
    import types

    import torch

    import bench.gpu_feed as gf

    calls = []

    def fake_run(cmd, **kw):
        calls.append(cmd)
        return types.SimpleNamespace(stdout="70\n" if len(calls) % 2 else "90\n")

    monkeypatch.setitem(sys.modules, "pynvml", None)  # import pynvml raises ImportError
    monkeypatch.setattr(gf.shutil, "which", lambda name: "/usr/bin/nvidia-smi")
    monkeypatch.setattr(gf.subprocess, "run", fake_run)
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "3,5")
    with gf.BusySampler(torch.device("cuda", 1), period_s=0.001) as busy:
        deadline = time.monotonic() + 30
        while len(busy.samples) < 4 and time.monotonic() < deadline:
            time.sleep(0.001)
    n = len(busy.samples)
    assert n >= 4 and "--id=5" in calls[0] and "--query-gpu=utilization.gpu" in calls[0]
    assert busy.mean == sum(70 if i % 2 == 0 else 90 for i in range(n)) / n / 100


def test_compiled_rows_count_graphs_through_a_moving_curriculum(tmp_path, videos, inductor_cache):
    """``--compile`` on a CPU: inductor compiles the network, so the graphs column counts real
    graphs. HyperE2VID under ``speed: fast`` with its 16-stage curriculum spread over the row's 4
    cached steps (beta 1, 0.75, 0.5, 0.25, then 0 for the live steps, whose last batch of an
    epoch may be smaller) runs on the one graph of its first step."""
    if "speed" not in default_config("hypere2vid"):
        pytest.skip("this trainer has no 'speed' setting")
    assert main(["--smoke", "--models", "hypere2vid", "--amp", "fp32", "--speed", "fast", "--compile",
                 "--workers", "1", "--steps", "3", "--warmup", "1", "--videos", str(videos), "--device", "cpu",
                 "--out", str(tmp_path)]) == 0
    out = json.loads((tmp_path / "gpu_feed.json").read_text())
    (r,) = out["rows"]
    assert out["compile"] and r["curriculum"] == "beta 1 -> 0 in 16 stages over 4 steps"
    assert r["graphs"] == 1 and r["recompiles"] == 0 and r["cudagraph_skips"] == 0
    assert "`--compile`" in (tmp_path / "gpu_feed.md").read_text()

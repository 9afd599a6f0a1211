"""v2v-train against a real v2v-serve on 127.0.0.1 (bikes.mp4, tiny crops and models)."""
from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from harness.serve import ServeProcess
import trainer.train as tr

torch.set_num_threads(2)


def record_trained(monkeypatch) -> list:
    """A list that receives ``(epoch, sample_ids)`` of every batch ``v2v-train`` trains on."""
    seen = []
    orig = tr.Trainer.train_step

    def recording_step(self, batch, sync=True):
        seen.append((batch["epoch"], list(batch["sample_ids"])))
        return orig(self, batch, sync)

    monkeypatch.setattr(tr.Trainer, "train_step", recording_step)
    return seen


def test_train_from_live_server_then_resume(tmp_path, bikes_corpus, monkeypatch):
    seen = record_trained(monkeypatch)  # (epoch, sample_ids) of every batch trained on
    vids = bikes_corpus
    out = tmp_path / "run"
    serve = ["--videos", str(vids), "--workers", "1", "--sequence-length", "4", "--num-bins", "3",
             "--crop-size", "32", "--batch-size", "2", "--seed", "3", "--max-samples-per-video", "6"]
    with ServeProcess(serve) as srv:
        common = ["--task", "e2vid", "--connect", srv.endpoint, "--out", str(out), "--device", "cpu",
                  "--no-progress", "--set", "model.num_bins=3", "--set", "model.base_num_channels=4",
                  "--set", "optim.lr=0.001", "--set", "log.image_every=3", "--set", "stream.timeout_s=30"]
        assert tr.main(common + ["--max-steps", "2"]) == 0  # 4 of the 6 samples of epoch 0
        ck = torch.load(out / "checkpoint_last.pt", weights_only=False)
        assert ck["stream_state"] is not None  # the client's position travels with the model
        assert tr.main(common + ["--max-steps", "8", "--resume", "auto"]) == 0
    rows = list(csv.DictReader(open(out / "train_log.csv")))
    assert [int(r["step"]) for r in rows] == list(range(1, 9))
    # the resumed run finished epoch 0 without repeating or skipping a sample
    epoch0 = [sid for e, ids in seen if e == 0 for sid in ids]
    assert len(epoch0) == 6 and len(set(epoch0)) == 6
    losses = np.array([float(r["loss"]) for r in rows])
    assert np.all(np.isfinite(losses)) and all(float(r["tc"]) > 0 for r in rows)
    ck = torch.load(out / "checkpoint_last.pt", weights_only=False)
    assert ck["step"] == 8 and ck["task"] == "e2vid"
    assert (out / "samples" / "step_0000003.png").exists()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 6 and 0 <= summary["data_wait_fraction"] <= 1


def test_train_against_two_shards_then_resume(tmp_path, videos, monkeypatch):
    """v2v-train reading two shards (the compose/Kubernetes topology) stops, then resumes from
    its checkpoint: epoch 0 is trained exactly once over both runs."""
    seen = record_trained(monkeypatch)
    vids = tmp_path / "vids"
    vids.mkdir()
    for i in range(4):
        shutil.copyfile(videos / "bikes.mp4", vids / f"bikes{i}.mp4")
    out = tmp_path / "run"
    serve = ["--videos", str(vids), "--workers", "1", "--sequence-length", "4", "--num-bins", "3",
             "--crop-size", "32", "--batch-size", "2", "--seed", "3", "--max-samples-per-video", "3"]
    with ServeProcess(serve + ["--shard", "0/2"]) as a, ServeProcess(serve + ["--shard", "1/2"]) as b:
        common = ["--task", "e2vid", "--connect", f"{a.endpoint},{b.endpoint}", "--out", str(out), "--device", "cpu",
                  "--no-progress", "--set", "model.num_bins=3", "--set", "model.base_num_channels=4",
                  "--set", "stream.timeout_s=30", "--set", "log.image_every=100"]
        assert tr.main(common + ["--max-steps", "3"]) == 0
        # past epoch 0's end (12 samples, padding at a shorter shard's tail)
        assert tr.main(common + ["--max-steps", "14", "--resume", "auto"]) == 0
    epoch0 = [sid for e, ids in seen if e == 0 for sid in ids if sid is not None]
    assert sorted(epoch0) == sorted(set(epoch0)), seen
    assert sorted(epoch0) == sorted(f"bikes{i}.mp4#{w}" for i in range(4) for w in range(3)), seen


def test_sigkill_after_a_checkpoint_loses_no_log_row(tmp_path, bikes_corpus):
    """The real ``v2v-train`` (a subprocess) checkpoints every 3 steps and logs every 10; it is
    SIGKILLed once checkpoint 6 is on the disk. The log then holds every row up to 6 (rows reach
    the disk with each checkpoint), and after ``--resume auto`` to step 9 it holds steps 1..9
    once each. The resumed run is ``--speed fast``: an eager checkpoint (model and optimiser
    state) resumes into the fast path's layout and fused optimiser."""
    out = tmp_path / "run"
    serve = ["--videos", str(bikes_corpus), "--workers", "1", "--sequence-length", "2", "--num-bins", "3",
             "--crop-size", "32", "--batch-size", "1", "--seed", "3", "--max-samples-per-video", "6"]
    with ServeProcess(serve) as srv:
        cmd = [sys.executable, "-m", "trainer.train", "--task", "e2vid", "--connect", srv.endpoint, "--out", str(out),
               "--device", "cpu", "--no-progress", "--set", "model.num_bins=3", "--set", "model.base_num_channels=4",
               "--set", "log.image_every=0", "--set", "log.checkpoint_every=3", "--set", "log.every=10",
               "--set", "stream.timeout_s=30"]
        proc = subprocess.Popen(cmd + ["--max-steps", "1000"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        deadline = time.monotonic() + 120
        while not (out / "checkpoint_0000006.pt").exists():
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read().decode()[-3000:]
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
        proc.stderr.close()
        on_disk = [int(r["step"]) for r in csv.DictReader(open(out / "train_log.csv"))]
        assert on_disk[:6] == [1, 2, 3, 4, 5, 6]
        resumed_at = torch.load(out / "checkpoint_last.pt", weights_only=False)["step"]
        end = resumed_at + 3
        r = subprocess.run(cmd + ["--max-steps", str(end), "--resume", "auto", "--speed", "fast"], capture_output=True,
                           text=True, timeout=180)
        assert r.returncode == 0, r.stderr[-3000:]
    rows = list(csv.DictReader(open(out / "train_log.csv")))
    assert [int(r["step"]) for r in rows] == list(range(1, end + 1))
    assert all(np.isfinite(float(r["loss"])) for r in rows)


def test_train_from_a_server_serving_by_plan_then_resume_at_its_position(tmp_path, bikes_corpus, monkeypatch):
    """``v2v-train --connect`` a server (it serves by plan): it reads the plan in the
    server's batch size, epoch after epoch; a checkpoint's stream state is the plan's position,
    so the resumed run finishes epoch 0 without a repeat or a loss and goes on into epoch 1."""
    seen = record_trained(monkeypatch)
    out = tmp_path / "run"
    serve = ["--videos", str(bikes_corpus), "--workers", "1", "--sequence-length", "4", "--num-bins", "3",
             "--crop-size", "32", "--batch-size", "2", "--seed", "3", "--max-samples-per-video", "6"]
    with ServeProcess(serve) as srv:
        common = ["--task", "e2vid", "--connect", srv.endpoint, "--out", str(out), "--device", "cpu",
                  "--no-progress", "--set", "model.num_bins=3", "--set", "model.base_num_channels=4",
                  "--set", "log.image_every=0", "--set", "stream.timeout_s=30"]
        assert tr.main(common + ["--max-steps", "2"]) == 0
        ck = torch.load(out / "checkpoint_last.pt", weights_only=False)
        assert ck["stream_state"]["epoch"] == 0 and ck["stream_state"]["sample_in_epoch"] == 4
        assert tr.main(common + ["--max-steps", "5", "--resume", "auto"]) == 0
    assert all(len(ids) == 2 for _, ids in seen)  # the server's batch size
    epoch0 = [sid for e, ids in seen if e == 0 for sid in ids if sid is not None]
    assert len(epoch0) == 6 and len(set(epoch0)) == 6
    assert [e for e, _ in seen] == [0, 0, 0, 1, 1]
    rows = list(csv.DictReader(open(out / "train_log.csv")))
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4, 5]
    # where each batch lay in its epoch (3 steps of 2 samples), the resumed run's going on from the checkpoint
    assert [(int(r["epoch"]), int(r["sample_in_epoch"])) for r in rows] == [(0, 2), (0, 4), (0, 6), (1, 2), (1, 4)]
    assert "batch_id" not in rows[0]


def test_train_at_an_address_with_no_server_ends_in_one_line(tmp_path):
    """``v2v-train --connect`` where nothing listens (the real command, a process of its own):
    after ``stream.timeout_s`` one line naming the address, exit status 1, no traceback."""
    from harness.serve import free_port

    endpoint = f"tcp://127.0.0.1:{free_port()}"
    r = subprocess.run([sys.executable, "-m", "trainer.train", "--task", "e2vid", "--connect", endpoint, "--out",
                        str(tmp_path / "run"), "--device", "cpu", "--no-progress", "--no-tensorboard",
                        "--set", "model.base_num_channels=4", "--set", "stream.timeout_s=2"],
                       capture_output=True, text=True, timeout=300)
    err = r.stderr.strip().splitlines()
    assert r.returncode == 1 and err[-1].startswith(f"v2v-train: {endpoint}: no answer"), r.stderr
    assert "Traceback" not in r.stderr, r.stderr


def test_a_run_against_a_plan_server_says_whether_it_was_fed(tmp_path, bikes_corpus, monkeypatch):
    """The summary, its one line and TensorBoard carry the feed figures: samples/s, the data-wait
    fraction and the model's own rate after the first step, the start-up by phase, and what
    would feed the run, from the server's own figures (its workers)."""
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    seen = record_trained(monkeypatch)
    out = tmp_path / "run"
    serve = ["--videos", str(bikes_corpus), "--workers", "1", "--sequence-length", "4", "--num-bins", "3",
             "--crop-size", "32", "--batch-size", "2", "--seed", "3"]
    with ServeProcess(serve) as srv:
        assert tr.main(["--task", "e2vid", "--connect", srv.endpoint, "--out", str(out), "--device", "cpu",
                        "--no-progress", "--set", "model.num_bins=3", "--set", "model.base_num_channels=4",
                        "--set", "log.every=2", "--set", "stream.timeout_s=30", "--max-steps", "6"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["samples"] == sum(len(ids) for _, ids in seen) == 12
    assert s["samples_per_s"] > 0 and s["model_samples_per_s"] >= s["samples_per_s"]
    assert 0 <= s["data_wait_fraction"] <= 1
    assert {"connect", "model_build", "first_batch", "to_loop", "first_batch_wait", "first_step",
            "to_first_step"} <= set(s["startup_s"])
    assert s["startup_s"]["to_first_step"] >= s["startup_s"]["first_step"] > 0
    if s["data_wait_fraction"] > 0.05:  # the server reported its one worker: the line says how many would feed
        assert s["feed"].startswith("starved: ") and "more decode worker(s) at this recipe" in s["feed"]
    else:
        assert s["feed"].startswith("fed: ")
    assert f"feed: {s['feed']}" in (out / "train.log").read_text()
    acc = EventAccumulator(str(out), size_guidance={"scalars": 0, "tensors": 0})
    acc.Reload()
    for key in ("samples_per_s", "model_samples_per_s", "data_wait_fraction"):
        (e,) = acc.Scalars(f"feed/{key}")
        assert e.step == 6 and e.value == pytest.approx(s[key], rel=1e-5)
    assert "feed/text_summary" in acc.Tags()["tensors"]  # the line, as TensorBoard keeps text
    # the recipe the batches were made under, as the server said it: its plan and the stream's shapes
    (text,) = acc.Tensors("recipe/text_summary")
    said = text.tensor_proto.string_val[0].decode()
    assert not said.startswith("not reported"), said
    recipe = json.loads(said)
    ck = torch.load(out / "checkpoint_last.pt", weights_only=False)
    assert recipe["plan"] == ck["stream_state"]["plan"] and recipe["plan"]["seed"] == 3
    assert {k: recipe[k] for k in ("sequence_length", "num_bins", "crop_size", "batch_size", "shard")} == \
        {"sequence_length": 4, "num_bins": 3, "crop_size": 32, "batch_size": 2, "shard": None}
    assert "feed" not in recipe  # the server's running figures are the feed line's, not the recipe's
    # the batches' place in their epoch, per step, as the CSV has it
    rows = list(csv.DictReader(open(out / "train_log.csv")))
    for column in ("epoch", "sample_in_epoch"):
        assert [(e.step, e.value) for e in acc.Scalars(f"stream/{column}")] == \
            [(int(r["step"]), float(r[column])) for r in rows], column


def _rows(out) -> int:
    """The rows of ``out``'s ``train_log.csv`` (0 before it exists)."""
    try:
        return len(list(csv.DictReader(open(out / "train_log.csv"))))
    except FileNotFoundError:
        return 0


def _rows_settled(out, proc, quiet_s: float, cap_s: float) -> int:
    """The rows of ``out``'s ``train_log.csv`` once no row has come for ``quiet_s`` (the batches
    read ahead are trained, the run waits for the server), at most after ``cap_s``."""
    last, since, deadline = -1, time.monotonic(), time.monotonic() + cap_s
    while time.monotonic() < deadline and proc.poll() is None:
        n = _rows(out)
        if n != last:
            last, since = n, time.monotonic()
        elif time.monotonic() - since >= quiet_s:
            break
        time.sleep(0.1)
    return last


def test_an_interrupt_while_the_server_is_stopped_ends_the_run_at_once(tmp_path, bikes_corpus):
    """The real ``v2v-train`` (its console script's entry, a process of its own) reading a real
    ``v2v-serve`` that is then SIGSTOPped (silent: it neither answers nor closes): Ctrl-C, then
    SIGTERM to the run resumed from that checkpoint, each end it with its one line and its status
    long before ``stream.timeout_s`` (60 s): the end-of-run question for the server's feed figures
    waits ``trainer.loop.INTERRUPTED_ASK_S``, and nobody waits for the read-ahead thread blocked on
    the server.
    The interrupted run's checkpoint is where the resumed run goes on, no step trained twice."""
    out = tmp_path / "run"
    serve = ["--videos", str(bikes_corpus), "--workers", "1", "--sequence-length", "2", "--num-bins", "3",
             "--crop-size", "32", "--batch-size", "1", "--seed", "3"]
    code = "import sys\nfrom v2v_wire.commands import train\nsys.exit(train())"
    cmd = [sys.executable, "-c", code, "--task", "e2vid", "--out", str(out), "--device", "cpu", "--no-progress",
           "--set", "model.num_bins=3", "--set", "model.base_num_channels=4", "--set", "log.image_every=0",
           "--set", "log.checkpoint_every=2", "--set", "log.every=1", "--set", "stream.timeout_s=60",
           "--max-steps", "100000"]
    with ServeProcess(serve) as srv:
        steps = []
        for sig, said, extra in ((signal.SIGINT, "interrupted (Ctrl-C)", []),
                                 (signal.SIGTERM, "stopped (SIGTERM)", ["--resume", "auto"])):
            before = steps[-1] if steps else 0
            proc = subprocess.Popen(cmd + ["--connect", srv.endpoint, *extra], stdout=subprocess.DEVNULL,
                                    stderr=subprocess.PIPE, text=True)
            try:
                deadline = time.monotonic() + 180
                while _rows(out) < before + 2:  # two steps trained
                    assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()[-3000:]
                    time.sleep(0.05)
                os.kill(srv.proc.pid, signal.SIGSTOP)
                try:
                    _rows_settled(out, proc, quiet_s=2.0, cap_s=20.0)
                    sent = time.monotonic()
                    proc.send_signal(sig)
                    try:
                        proc.wait(15)  # a quarter of stream.timeout_s: it did not wait for the server
                    except subprocess.TimeoutExpired:
                        pytest.fail(f"v2v-train still running 15 s after {signal.Signals(sig).name}, its server "
                                    f"stopped (stream.timeout_s 60)")
                    took = time.monotonic() - sent
                finally:
                    os.kill(srv.proc.pid, signal.SIGCONT)
            finally:
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()
            err = proc.stderr.read()
            proc.stderr.close()
            lines = [ln for ln in err.splitlines() if ln.strip()]
            assert proc.returncode == 128 + sig and "Traceback" not in err, (took, err[-3000:])
            step = torch.load(out / "checkpoint_last.pt", weights_only=False)["step"]
            assert lines[-1] == f"v2v-train: {said}; stopped at step {step}; checkpoint in {out}", lines[-3:]
            rows = list(csv.DictReader(open(out / "train_log.csv")))
            assert [int(r["step"]) for r in rows] == list(range(1, step + 1)) and step >= before + 2
            steps.append(step)

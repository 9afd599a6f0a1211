"""The stream under the loaders people train with (real libraries, real server on 127.0.0.1):
Lightning's DDP launcher, torch DataLoader workers, torchdata's StatefulDataLoader."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

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


def test_a_stream_and_its_loader_are_truthy_though_they_have_no_length():
    """len() refuses (loaders that index a dataset, DeepSpeed's training_data=, must not take a
    stream), but ``if ds:`` and ``if loader:`` are true for the dataset and StreamLoader, as for any
    dataset a loop holds. torch's own DataLoader asks the dataset's len() for its truth: the error
    says how to test it instead."""
    import pytest
    import torch

    from v2v_client import StreamLoader, V2VPushDataset

    ds = V2VPushDataset("tcp://127.0.0.1:9")  # never iterated: no connection is made
    loader = StreamLoader(ds, num_workers=1)
    with pytest.raises(TypeError, match="stream without a length"):
        len(ds)
    with pytest.raises(TypeError, match="stream without a length"):
        len(loader)
    assert bool(ds) and bool(loader)
    with pytest.raises(TypeError, match="test it with `is not None`"):
        bool(torch.utils.data.DataLoader(ds, batch_size=None))


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


def test_a_world_size_without_a_rank_is_refused(monkeypatch):
    """WORLD_SIZE=3 without RANK would make every process rank 0, each taking rank 0's share."""
    import pytest

    from v2v_client import dist_position

    monkeypatch.delenv("RANK", raising=False)
    monkeypatch.setenv("WORLD_SIZE", "3")
    with pytest.raises(ValueError, match="WORLD_SIZE=3 in the environment but no RANK"):
        dist_position()
    monkeypatch.setenv("WORLD_SIZE", "1")
    assert dist_position() == (0, 1)


def test_stateful_dataloader_resumes_an_older_checkpoint_after_the_epoch_ended(tmp_path):
    r = faults.scenario_resume_after_end(tmp_path, LAYOUT, ckpt_step=2, grace_s=3.0)
    assert (r["lost"], r["duplicated"], r["unexpected"]) == (0, 0, 0), r
    f = r["facts"]
    assert f["ended_alive"] and f["resumed_equal"] and f["server_exit"] == 0, r
    assert 3.0 <= f["exit_after_s"] < 30, r


def test_stream_loader_workers_persistent_break_and_iterate_again(tmp_path):
    r = faults.scenario_loader_workers(tmp_path, LAYOUT, persistent=True, take=3)
    assert (r["lost"], r["duplicated"], r["unexpected"]) == (0, 0, 0), r
    assert r["facts"]["rounds"] > 1 and r["facts"]["server_exit"] == 130, r  # stopped by SIGINT


def test_stream_loader_workers_not_persistent_break_and_iterate_again(tmp_path):
    r = faults.scenario_loader_workers(tmp_path, LAYOUT, persistent=False, take=3)
    assert (r["lost"], r["duplicated"], r["unexpected"]) == (0, 0, 0), r
    assert r["facts"]["rounds"] > 1 and r["facts"]["server_exit"] == 130, r  # stopped by SIGINT


def test_a_plain_dataloader_with_workers_is_a_clear_error(tmp_path):
    import pytest
    import torch

    from v2v_client import V2VPushDataset

    corpus = faults.good_corpus(tmp_path, 1)
    with ServeProcess(["--videos", str(corpus), "--workers", "1", *LAYOUT.args()]) as srv:
        ds = V2VPushDataset(srv.endpoint, timeout_s=30)
        with pytest.raises(RuntimeError, match="StreamLoader"):
            next(iter(torch.utils.data.DataLoader(ds, batch_size=None, num_workers=1)))


def test_stream_loader_checkpoint_resumes_exactly_once(tmp_path):
    """Checkpoint a 2-worker StreamLoader at step 2, read on to step 5, abandon it (a crash),
    and resume a new loader from the step-2 checkpoint: every sample once in what was trained."""
    from v2v_client import StreamLoader, V2VPushDataset

    corpus = faults.good_corpus(tmp_path, 2)
    expected = faults.expected_ids(corpus, LAYOUT)
    trained = []
    with ServeProcess(["--videos", str(corpus), "--workers", "2", "--epochs", "1", "--end-grace-s", "3",
                       *LAYOUT.args()]) as srv:
        loader = StreamLoader(V2VPushDataset(srv.endpoint, timeout_s=60, credits=2), num_workers=2)
        for step, b in enumerate(loader):
            if step < 2:
                trained += b["sample_ids"]
            if step == 1:
                ckpt = json.loads(json.dumps(loader.state_dict()))  # as saved to disk
            if step == 4:
                break
        del loader
        again = StreamLoader(V2VPushDataset(srv.endpoint, timeout_s=60, credits=2), num_workers=2)
        again.load_state_dict(ckpt)
        for b in again:
            trained += b["sample_ids"]
        assert srv.wait(60) == 0, srv.log[-3000:]
    assert sorted(trained) == expected


#: what a StreamLoader may wait past its dataset's ``timeout_s`` before it raises (the StreamLoader
#: docstring's margin, about 2 s, plus room for a loaded 2-core machine)
MARGIN_S = 15.0


def test_stream_loader_raises_within_its_timeout_when_the_server_goes_silent(tmp_path):
    """A server frozen mid-stream (SIGSTOP: no batches, no heartbeats): persistent workers'
    StreamLoader raises StreamTimeout naming the server within timeout_s plus the margin."""
    import os
    import signal
    import time

    import pytest

    from v2v_client import StreamLoader, V2VPushDataset

    timeout_s = 3.0
    corpus = faults.good_corpus(tmp_path, 2)
    with faults._serve(corpus, LAYOUT, "--epochs", "1") as srv:
        loader = StreamLoader(V2VPushDataset(srv.endpoint, timeout_s=timeout_s, credits=1), num_workers=2,
                              persistent_workers=True, prefetch_factor=1)
        it = iter(loader)
        next(it)
        os.kill(srv.proc.pid, signal.SIGSTOP)
        try:
            t0 = time.monotonic()
            with pytest.raises(Exception, match=f"no message from the v2v server at {srv.endpoint}") as e:
                for _ in it:  # batches already queued come first
                    pass
            waited = time.monotonic() - t0
        finally:
            os.kill(srv.proc.pid, signal.SIGCONT)
        del it, loader
    assert type(e.value).__name__ == "StreamTimeout", e.value
    assert waited < timeout_s + MARGIN_S, waited


def test_stream_loader_persistent_worker_killed_mid_iteration(tmp_path):
    """A persistent DataLoader worker SIGKILLed mid-iteration: the loop gets torch's error naming
    the worker's pid at once (not a hang), and a new iteration (workers made anew from the
    records the main process kept) reads the rest of the epoch: every sample exactly once."""
    import os
    import signal
    import time

    import pytest

    from v2v_client import StreamLoader, V2VPushDataset

    corpus = faults.good_corpus(tmp_path, 2)
    expected = faults.expected_ids(corpus, LAYOUT)
    trained = []
    with faults._serve(corpus, LAYOUT, "--epochs", "1", "--end-grace-s", "60") as srv:
        loader = StreamLoader(V2VPushDataset(srv.endpoint, timeout_s=60, credits=2), num_workers=2,
                              persistent_workers=True)
        it = iter(loader)
        for _ in range(2):
            trained += next(it)["sample_ids"]
        pid = loader._iterator._workers[0].pid
        os.kill(pid, signal.SIGKILL)
        t0 = time.monotonic()
        # torch says it from its SIGCHLD handler or from the loop's next timeout, whichever comes first
        with pytest.raises(RuntimeError, match=rf"DataLoader worker \(pid(\(s\))? {pid}\) "
                                               r"(exited unexpectedly|is killed by signal)"):
            for b in it:
                trained += b["sample_ids"]
        assert time.monotonic() - t0 < MARGIN_S
        del it
        for b in loader:  # new workers; the killed one's batches come back after the client timeout
            trained += b["sample_ids"]
        assert sorted(trained) == expected, srv.log[-3000:]
        # the loop's iteration ends once every worker was told drained, which the server says
        # once it has granted everything; the last acks (the loop's receipts, forwarded by the
        # workers) may reach it a moment later
        deadline = time.monotonic() + MARGIN_S
        while "all 1 epoch(s) delivered" not in srv.log and time.monotonic() < deadline:
            time.sleep(0.1)
        assert srv.log.count("all 1 epoch(s) delivered") == 1, srv.log[-3000:]


def test_a_dataloader_worker_stopped_past_its_timeout_with_batches_queued_doubles_nothing(tmp_path):
    """A DataLoader worker stopped (SIGSTOP) past the server's client timeout while batches it
    yielded wait in the loader's queue: the server drops its connection, but those batches were
    granted before they were queued, so they are not sent to the other trainer reading meanwhile;
    the loop receives them, the worker resumes, and every sample reaches one loop once."""
    import os
    import signal
    import threading
    import time

    from v2v_client import StreamLoader, V2VPushDataset

    corpus = faults.good_corpus(tmp_path, 3)
    expected = faults.expected_ids(corpus, LAYOUT)
    trained, other = [], []
    # the server waits for the stopped worker's consumer after the end (the batches granted to it
    # and not yet queued in the loader are made again when it says hello again)
    with faults._serve(corpus, LAYOUT, "--epochs", "1", "--client-timeout", "1.5", "--end-grace-s", "60") as srv:
        loader = StreamLoader(V2VPushDataset(srv.endpoint, timeout_s=60, credits=2), num_workers=1,
                              prefetch_factor=2, persistent_workers=True)
        it = iter(loader)
        trained += next(it)["sample_ids"]
        time.sleep(1.0)  # the worker fills the loader's queue
        pid = loader._iterator._workers[0].pid
        os.kill(pid, signal.SIGSTOP)
        wake = threading.Timer(5.0, os.kill, (pid, signal.SIGCONT))
        wake.start()

        def read_other():
            for b in V2VPushDataset(srv.endpoint, timeout_s=60, credits=1):
                other.extend(b["sample_ids"])
                time.sleep(0.3)

        tb = threading.Thread(target=read_other, daemon=True)
        tb.start()
        try:
            for b in it:
                trained += b["sample_ids"]
        finally:
            wake.join()
        tb.join(60)
        assert srv.log.count("dropping it") >= 1, srv.log[-3000:]  # the worker's connection was dropped
    assert sorted(trained + other) == expected


class _Crash(Exception):
    """What stops the first Lightning run after its checkpoint (a job killed)."""


def _lightning_fit(make_loader, ckpt: str, save_at=None, crash_at=None, resume=False) -> list:
    """Sample ids a Lightning ``Trainer`` (one CPU process) trains on from ``make_loader()``: it
    saves a checkpoint after step ``save_at`` (the ids trained then are returned) and raises at
    step ``crash_at``; ``resume``: fit from the checkpoint at ``ckpt``."""
    import lightning as L
    import torch

    class Tiny(L.LightningModule):
        def __init__(self):
            super().__init__()
            self.w = torch.nn.Parameter(torch.zeros(1))
            self.seen, self.saved = [], None

        def training_step(self, batch, i):
            if i == crash_at:
                raise _Crash()
            self.seen += batch["sample_ids"]
            return ((self.w * batch["voxels"].flatten(1).mean(1) - 1.0) ** 2).mean()

        def on_train_batch_end(self, out, batch, i):
            if i == save_at:
                self.trainer.save_checkpoint(ckpt)
                self.saved = list(self.seen)

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.01)

        def train_dataloader(self):
            return make_loader()

    module = Tiny()
    trainer = L.Trainer(accelerator="cpu", devices=1, max_epochs=1, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False)
    try:
        trainer.fit(module, ckpt_path=ckpt if resume else None)
    except _Crash:
        return module.saved
    return module.seen


@pytest.mark.parametrize("loader", ["StatefulDataLoader", "StreamLoader"])
def test_lightning_resumes_from_a_checkpoint_taken_while_its_fetcher_holds_a_batch(tmp_path, loader):
    """Lightning's fetcher takes one batch ahead of its loop; a checkpoint saved in a step holds
    the loader's state then. The job is killed two steps later and resumed from it: every sample
    once in what was trained (the batch taken ahead is in the state only once received)."""
    from torchdata.stateful_dataloader import StatefulDataLoader

    from v2v_client import StreamLoader, V2VPushDataset

    corpus = faults.good_corpus(tmp_path, 2)
    expected = faults.expected_ids(corpus, LAYOUT)
    with ServeProcess(["--videos", str(corpus), "--workers", "1", "--epochs", "1", "--end-grace-s", "3",
                       *LAYOUT.args()]) as srv:
        def make_loader():
            ds = V2VPushDataset(srv.endpoint, outputs=("voxels",), timeout_s=60, credits=2)
            return StreamLoader(ds, num_workers=2) if loader == "StreamLoader" else StatefulDataLoader(ds, batch_size=None)

        ckpt = str(tmp_path / "step1.ckpt")
        trained = _lightning_fit(make_loader, ckpt, save_at=1, crash_at=4)
        assert len(trained) == 2 * LAYOUT.batch
        trained += _lightning_fit(make_loader, ckpt, resume=True)
        assert srv.wait(60) == 0, srv.log[-3000:]
    assert sorted(trained) == expected

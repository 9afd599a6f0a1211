"""Reading a plan (docs/delivery.md) under the loaders and launchers that
snapshot or split a DataLoader (docs/launchers.md, "Reading a plan"): torchdata's
``StatefulDataLoader`` (its state taken mid-epoch and loaded by a fresh loader, with 0 and 2
DataLoader workers), Hugging Face Accelerate in its two modes (2 CPU ranks started by torchrun,
gloo, ``harness/accelerate_plan_job.py``), Lightning Fabric, PyTorch Ignite, DeepSpeed and a torchrun
elastic restart (``harness/launcher_job.py``), each against a real plan server on 127.0.0.1 over
the bundled clips: every sample id of each epoch once across the ranks (padding excluded), or the
way that cannot hold it refused in one line before any batch."""
from __future__ import annotations

import collections
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from torchdata.stateful_dataloader import StatefulDataLoader

from harness.serve import ServeProcess
from v2v_client import V2VStreamDataset
from tests.test_scale_out import BATCH, corpus, expected_ids, layout
from tests.test_plan_stream import SAMPLES, server  # noqa: F401 - the plan server on the bundled clips, its epoch's size


def _ids(batch) -> list:
    return [sid for sid, pad in zip(batch["sample_ids"], batch["padding"].tolist()) if not pad]


def _once(ids, expected: int = SAMPLES) -> None:
    counts = collections.Counter(ids)
    assert len(ids) == len(counts) == expected, (len(ids), len(counts), sorted(k for k, v in counts.items() if v > 1))


def _epoch_ids(server) -> list:
    """Epoch 0's ids, read whole by one reader."""
    return [sid for b in torch.utils.data.DataLoader(V2VStreamDataset(server, 4), batch_size=None) for sid in _ids(b)]


@pytest.mark.parametrize("workers", [0, 2])
def test_stateful_dataloader_state_mid_epoch_resumes_in_a_fresh_loader_exactly_once(server, workers):
    """Two ranks (rank/world given), each a StatefulDataLoader(ds, batch_size=None, num_workers=K):
    3 steps read, loader.state_dict() taken (and a fourth batch read after it, not counted), then
    a fresh dataset and loader per rank load the state and read on: each rank's batches continue
    at the next step (the position after step 3), and the epoch's ids are each read once."""
    before, after, states = [], [], []
    for rank in range(2):
        loader = StatefulDataLoader(V2VStreamDataset(server, 3, rank=rank, world_size=2), batch_size=None,
                                    num_workers=workers)
        it = iter(loader)
        got = [next(it) for _ in range(3)]
        states.append(loader.state_dict())
        next(it)  # read past the state: not in it
        del it
        before += [sid for b in got for sid in _ids(b)]
        assert [b["position"]["sample_in_epoch"] for b in got] == [6, 12, 18]
    for rank in range(2):
        loader = StatefulDataLoader(V2VStreamDataset(server, 3, rank=rank, world_size=2), batch_size=None,
                                    num_workers=workers)
        loader.load_state_dict(states[rank])
        rest = list(loader)
        assert [b["position"]["sample_in_epoch"] for b in rest] == [24]
        after += [sid for b in rest for sid in _ids(b)]
    _once(before + after)
    assert sorted(before + after) == sorted(_epoch_ids(server))


def test_a_state_taken_without_workers_resumes_at_another_layout_and_a_workers_state_only_in_its_worker(server):
    """A state of a loader without workers is the exact position (its Position part equals the last
    batch's ``position``): a dataset at world size 1 and batch size 5 resumes from it with 2 workers,
    each id once. A DataLoader worker's own state loaded outside that worker is refused in one line."""
    loader = StatefulDataLoader(V2VStreamDataset(server, 3, rank=0, world_size=2), batch_size=None)
    it = iter(loader)
    b = [next(it), next(it)]
    state = loader.state_dict()
    del it
    ds_state = state["dataset_state"]
    assert {k: ds_state[k] for k in ("plan", "epoch", "sample_in_epoch")} == b[-1]["position"]
    other = StatefulDataLoader(V2VStreamDataset(server, 3, rank=1, world_size=2), batch_size=None)
    it = iter(other)
    b += [next(it), next(it)]
    del it
    ds = V2VStreamDataset(server, 5, rank=0, world_size=1)
    ds.load_state_dict(ds_state)
    rest = [sid for x in torch.utils.data.DataLoader(ds, batch_size=None, num_workers=2) for sid in _ids(x)]
    _once([sid for x in b for sid in _ids(x)] + rest)

    workers = StatefulDataLoader(V2VStreamDataset(server, 4), batch_size=None, num_workers=2)
    it = iter(workers)
    next(it)
    worker_state = workers.state_dict()["_snapshot"]["_worker_snapshots"]["worker_1"]["dataset_state"]
    del it
    with pytest.raises(ValueError) as err:
        V2VStreamDataset(server, 4).load_state_dict(worker_state)
    assert "\n" not in str(err.value) and "DataLoader worker 1 of 2" in str(err.value)


def test_stateful_dataloader_state_after_the_epoch_ended_leaves_the_next_epoch_whole(server):
    """A state taken once the epoch's last batch was read (the loader finished) and loaded by a
    fresh loader: the next epoch (set_epoch) is read whole, not the saved epoch's end again."""
    ds = V2VStreamDataset(server, 4)
    loader = StatefulDataLoader(ds, batch_size=None)
    first = [sid for b in loader for sid in _ids(b)]
    state = loader.state_dict()
    ds2 = V2VStreamDataset(server, 4)
    again = StatefulDataLoader(ds2, batch_size=None)
    again.load_state_dict(state)
    ds2.set_epoch(1)
    second = [(b["epoch"], sid) for b in again for sid in _ids(b)]
    _once(first)
    assert {e for e, _ in second} == {1}
    _once([sid for _, sid in second])


def _accelerate(server, out: Path, *args) -> list:
    """``harness.accelerate_plan_job`` on 2 ranks: the ranks' records, by rank."""
    out.mkdir()
    r = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                        "-m", "harness.accelerate_plan_job", server, str(out), *[str(a) for a in args]],
                       capture_output=True, text=True, timeout=180)
    ranks = [json.loads(p.read_text()) for p in sorted(out.glob("rank*.json"))]
    assert len(ranks) == 2, f"exit {r.returncode}: {r.stderr[-3000:]}"
    return ranks


def _each_epoch_once(ranks, epochs) -> None:
    seen = [tuple(p) for r in ranks for p in r["seen"]]
    for epoch in epochs:
        _once([sid for e, sid in seen if e == epoch])


def test_accelerate_dispatch_reads_the_plan_with_plain_prepare(server, tmp_path):
    """accelerator.prepare(DataLoader(ds, batch_size=None, num_workers=2)) with accelerate's default
    (dispatch: process 0 reads, every rank gets a slice), batches of 5 (the epoch's last step
    partly padding), two epochs by loader.set_epoch: each
    rank's slice is the batch that rank reads per rank (its ids decoded from the slice's tensors),
    every step's position the same on both ranks, len(loader) the steps each rank takes, and each
    epoch's ids once across the ranks. With use_stateful_dataloader=True, DataLoader workers under
    dispatch are refused on every rank before any batch (accelerate snapshots between the batches
    of one step, which the workers yield apart)."""
    refused = _accelerate(server, tmp_path / "workers", "--prepare", "loader", "--stateful", "--workers", "2")
    for r in refused:
        assert r["seen"] == [] and "DataLoader workers yield apart" in (r["error"] or ""), r
    ranks = _accelerate(server, tmp_path / "out", "--workers", "2", "--epochs", "2", "--batch-size", "5")
    assert [r["error"] for r in ranks] == [None, None]
    steps = -(-SAMPLES // 10)  # the last step's rows past the epoch's end are padding
    assert [r["steps"] for r in ranks] == [{"0": steps, "1": steps}] * 2
    assert [r["len"] for r in ranks] == [[steps, steps]] * 2
    assert ranks[0]["positions"] == ranks[1]["positions"] == [[e, 10 * (s + 1)] for e in (0, 1) for s in range(steps)]
    _each_epoch_once(ranks, (0, 1))


def test_accelerate_per_rank_refused_by_plain_prepare_and_exact_with_prepare_loader(server, tmp_path):
    """dispatch_batches=False: accelerator.prepare would wrap the dataset in IterableDatasetShard
    (it needs a loader batch size, and keeps 1/N of each rank's batches): refused on every rank
    before any batch, in one line naming prepare_loader; v2v_client.prepare_loader reads each
    rank's own batches (2 DataLoader workers): each id once."""
    refused = _accelerate(server, tmp_path / "plain", "--per-rank")
    for r in refused:
        assert r["seen"] == [] and r["error"].startswith("RuntimeError: accelerate's dispatch_batches=False"), r
        assert "v2v_client.prepare_loader(accelerator" in r["error"]
    ranks = _accelerate(server, tmp_path / "out", "--per-rank", "--prepare", "loader", "--workers", "2")
    assert [r["error"] for r in ranks] == [None, None]
    assert ranks[0]["steps"] == ranks[1]["steps"] == {"0": -(-SAMPLES // 4)}
    assert ranks[0]["positions"] == ranks[1]["positions"]
    _each_epoch_once(ranks, (0,))


@pytest.mark.parametrize("mode", ["dispatch", "per-rank"])
def test_accelerate_save_state_mid_epoch_then_load_state_on_new_ranks(server, tmp_path, mode):
    """use_stateful_dataloader=True through prepare_loader: save_state after step 2 of epoch 0, the
    job left after step 3, new ranks load_state and read epochs 0 (the rest) and 1: each epoch's
    ids once across what the checkpoint holds and the second run (per rank with 2 DataLoader
    workers: their own states restored). Under dispatch, plain prepare with a stateful loader is
    refused first on every rank (every process writes its state to one file, only process 0's
    says anything)."""
    extra = ["--per-rank", "--workers", "2"] if mode == "per-rank" else []
    if mode == "dispatch":
        refused = _accelerate(server, tmp_path / "plain", "--stateful")
        for r in refused:
            assert r["seen"] == [] and "v2v_client.prepare_loader" in (r["error"] or ""), r
    first = _accelerate(server, tmp_path / "a", "--prepare", "loader", "--stateful", "--save-at", "1",
                        "--stop-after", "2", *extra)
    again = _accelerate(server, tmp_path / "b", "--prepare", "loader", "--stateful", "--epochs", "2",
                        "--resume", tmp_path / "a" / "ckpt", *extra)
    assert [r["error"] for r in first + again] == [None] * 4
    assert [r["steps"] for r in first] == [{"0": 3}] * 2
    steps = -(-SAMPLES // 4)
    assert [r["steps"] for r in again] == [{"0": steps - 2, "1": steps}] * 2
    saved = [{"seen": r["saved"]} for r in first]
    _each_epoch_once(saved + again, (0,))
    _each_epoch_once(again, (1,))


@pytest.mark.timeout(600)
@pytest.mark.parametrize("launcher", ["fabric", "ignite", "elastic", "deepspeed"])
def test_a_plan_under_fabric_ignite_deepspeed_and_an_elastic_restart(tmp_path, videos, launcher):
    """Training loops under Lightning Fabric (``setup_dataloaders``), PyTorch Ignite (an Engine over
    ``DataLoader(ds, batch_size=None)``), DeepSpeed (its engine over that DataLoader) and plain DDP
    under ``torchrun --max-restarts 1`` (rank 1 SIGKILLed after step 1 of the first attempt), 2 ranks
    reading ``V2VStreamDataset``: each id of the epoch once across the ranks, the ranks in step;
    ``elastic`` resumes both restarted ranks from the position of the last step both checkpointed."""
    root = corpus(tmp_path, videos, copies=2 if launcher == "elastic" else 1)
    expected = expected_ids(root)
    out = tmp_path / "out"
    out.mkdir()
    extra = ("--max-restarts", "1") if launcher == "elastic" else ()
    with ServeProcess(["--videos", str(root), *layout()]) as srv:
        r = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                            *extra, "-m", "harness.launcher_job", launcher, srv.endpoint, str(out), "--plan",
                            str(BATCH)], capture_output=True, text=True, timeout=400)
    ranks = [json.loads(p.read_text()) for p in sorted(out.glob("rank*.json"))]
    assert len(ranks) == 2, f"exit {r.returncode}: {r.stderr[-3000:]}"
    assert ranks[0]["batches"] == ranks[1]["batches"] > 0
    seen = [s for rank in ranks for s in rank["seen"]]
    counts = collections.Counter(seen)
    assert sorted(seen) == expected, (f"doubled {sorted(k for k, v in counts.items() if v > 1)}, "
                                      f"lost {sorted(set(expected) - set(counts))}")
    if launcher == "elastic":
        assert [(rank["attempt"], rank["resumed_from"]) for rank in ranks] == [(1, 0), (1, 0)]
    if launcher == "ignite":  # its auto_dataloader's batch-size scaling fails on batch_size=None, before any batch
        assert all(rank["refused"].startswith("TypeError: '>=' not supported") for rank in ranks), ranks


def test_prepare_loader_refuses_a_loader_accelerate_prepared_already():
    """prepare_loader over accelerator.prepare's loader would register a second loader (and per
    rank read IterableDatasetShard): refused in one line; its own loader comes back as it is;
    a loader of another dataset, or one batching the plan's batches again, is refused too."""
    from accelerate import Accelerator
    from accelerate.state import AcceleratorState, GradientState

    from v2v_client import prepare_loader

    try:
        acc = Accelerator(cpu=True)
        ds = V2VStreamDataset("tcp://127.0.0.1:9", 2)  # never iterated: no server is asked
        mine = prepare_loader(acc, torch.utils.data.DataLoader(ds, batch_size=None))
        assert prepare_loader(acc, mine) is mine and len(acc._dataloaders) == 1
        plain = acc.prepare(torch.utils.data.DataLoader(ds, batch_size=None))
        with pytest.raises(ValueError, match="^prepare_loader takes the DataLoader itself"):
            prepare_loader(acc, plain)
        with pytest.raises(ValueError, match="^prepare_loader takes the DataLoader itself"):
            prepare_loader(Accelerator(cpu=True), mine)  # another accelerator's
        with pytest.raises(TypeError, match="^prepare_loader reads a V2VStreamDataset; this loader reads list"):
            prepare_loader(acc, torch.utils.data.DataLoader([1, 2], batch_size=None))
        with pytest.raises(ValueError, match=r"^the loader has batch_size=4: V2VStreamDataset yields whole batches"):
            prepare_loader(acc, torch.utils.data.DataLoader(ds, batch_size=4))
    finally:
        AcceleratorState._reset_state(True)
        GradientState._reset_state()

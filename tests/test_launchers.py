"""The stream under the launchers people train with, each run by torchrun with 2 CPU ranks (gloo)
against a real server on 127.0.0.1: every epoch-0 id reaches a training loop exactly once across
the ranks (padding excluded), or the unsupported way fails before the first step with one line
saying what to do instead (docs/launchers.md lists them). Hugging Face Accelerate in both its modes
(``harness/accelerate_job.py``), Lightning Fabric, PyTorch Ignite, torchrun elastic restarts and
DeepSpeed (``harness/launcher_job.py``)."""
from __future__ import annotations

import collections
import json
import subprocess
import sys
from pathlib import Path

import pytest

from harness import faults
from harness.faults import Layout
from harness.serve import ServeProcess

LAYOUT = Layout(L=2, crop=32, windows=2, batch=2)


def _torchrun(module: str, args, out: Path, *torchrun_args: str, clean: bool = False) -> list:
    """Run ``module`` on 2 ranks; the ranks' records (``rank{R}.json`` in ``out``), by rank.
    ``clean``: every rank must also exit with status 0 (a rank that dies leaving fails torchrun)."""
    out.mkdir()
    r = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                        *torchrun_args, "-m", module, *[str(a) for a in args]],
                       capture_output=True, text=True, timeout=300)
    ranks = [json.loads(p.read_text()) for p in sorted(out.glob("rank*.json"))]
    assert len(ranks) == 2, f"exit {r.returncode}: {r.stderr[-3000:]}"
    assert not clean or r.returncode == 0, f"exit {r.returncode}: {r.stderr[-3000:]}"
    return ranks


def _serve(corpus: Path, epochs: int = 1) -> ServeProcess:
    # a grace after the end of the stream: a job resumed from an older checkpoint finds the server
    return ServeProcess(["--videos", str(corpus), "--workers", "2", "--epochs", str(epochs), "--end-grace-s", "60",
                         "--client-timeout", "3", *LAYOUT.args()])


def _three_clips(tmp_path: Path) -> Path:
    """Three of the good clips: 6 samples an epoch, 3 batches of 2 (an odd count of batches: under
    dispatch over 2 ranks, an epoch fills no whole number of steps)."""
    corpus = faults.good_corpus(tmp_path, 1)
    for p in sorted(corpus.glob("*.mp4"))[3:]:
        p.unlink()
    return corpus


def _once_per_epoch(seen_epochs, expected, epochs: int = 2) -> None:
    """Each epoch's ids (``[epoch, id]`` pairs) are ``expected``, each once."""
    by_epoch = collections.defaultdict(list)
    for e, sid in seen_epochs:
        by_epoch[e].append(sid)
    assert sorted(by_epoch) == list(range(epochs)), sorted(by_epoch)
    for e in range(epochs):
        _once(by_epoch[e], expected)


def _once(seen, expected) -> None:
    counts = collections.Counter(seen)
    assert sorted(seen) == expected, (f"doubled {sorted(k for k, v in counts.items() if v > 1)}, "
                                      f"lost {sorted(set(expected) - set(counts))}")


def _accelerate(endpoint, out, *args, clean: bool = False) -> list:
    return _torchrun("harness.accelerate_job", [endpoint, out, *args], out, clean=clean)


def test_accelerate_dispatch_plain_prepare_and_gradient_accumulation(tmp_path):
    """accelerator.prepare(DataLoader(ds, batch_size=None)) with accelerate's default (dispatch):
    each rank's slice is one whole batch, ids decoded from its tensors; with 3 accumulation steps
    the gradients sync at the third step and at the stream's last batch (end_of_dataloader).
    skip_first_batches (it would drop batches the server counts as delivered) is refused first."""
    corpus = faults.good_corpus(tmp_path, 2)
    expected = faults.expected_ids(corpus, LAYOUT)
    with _serve(corpus) as srv:
        skipped = _accelerate(srv.endpoint, tmp_path / "skip", "--mode", "dispatch", "--skip-first", "1")
        ranks = _accelerate(srv.endpoint, tmp_path / "out", "--mode", "plain", "--accumulate", "3")
    assert skipped[0]["batches"] == 0, skipped[0]
    assert skipped[0]["error"].startswith("RuntimeError: accelerate's skip_first_batches would throw away"), skipped
    assert [r["error"] for r in ranks] == [None, None]
    _once([s for r in ranks for s in r["seen"]], expected)
    assert [r["batches"] for r in ranks] == [len(expected) // 4] * 2  # 2 samples a batch, one batch a rank a step
    for r in ranks:
        assert r["sync"] == [False, False, True, True] and r["end"] == [False, False, False, True], r


def test_accelerate_per_rank_refused_by_plain_prepare_and_exact_with_prepare_loader(tmp_path):
    """dispatch_batches=False: plain prepare would wrap the dataset in IterableDatasetShard (1/N of
    each rank's share kept) and is refused before any batch; prepare_loader reads it whole per rank."""
    corpus = faults.good_corpus(tmp_path, 1)
    expected = faults.expected_ids(corpus, LAYOUT)
    with _serve(corpus) as srv:
        refused = _accelerate(srv.endpoint, tmp_path / "plain", "--mode", "plain", "--per-rank-config")
        ranks = _accelerate(srv.endpoint, tmp_path / "out", "--mode", "per-rank")
    for r in refused:
        assert r["batches"] == 0 and r["error"].startswith("RuntimeError: accelerate's dispatch_batches=False"), r
        assert "v2v_client.prepare_loader(accelerator" in r["error"]
    assert [r["error"] for r in ranks] == [None, None]
    assert ranks[0]["batches"] == ranks[1]["batches"]
    _once([s for r in ranks for s in r["seen"]], expected)


@pytest.mark.parametrize("mode", ["dispatch", "per-rank"])
def test_accelerate_save_state_mid_epoch_then_load_state_on_new_ranks(tmp_path, mode):
    """use_stateful_dataloader=True: save_state after step 1, leave after step 2 (what step 2 took
    is not in the checkpoint), new ranks load_state and read on: every id once across what the
    checkpoint holds and the second run. A stateful loader from plain prepare is refused first."""
    corpus = faults.good_corpus(tmp_path, 2)
    expected = faults.expected_ids(corpus, LAYOUT)
    with _serve(corpus) as srv:
        if mode == "dispatch":
            refused = _accelerate(srv.endpoint, tmp_path / "plain", "--mode", "plain", "--stateful")
            assert refused[0]["batches"] == 0 and "v2v_client.prepare_loader" in refused[0]["error"], refused[0]
        first = _accelerate(srv.endpoint, tmp_path / "a", "--mode", mode, "--stateful", "--save-at", "1",
                            "--stop-after", "2")
        again = _accelerate(srv.endpoint, tmp_path / "b", "--mode", mode, "--stateful", "--resume",
                            tmp_path / "a" / "ckpt")
    assert [r["error"] for r in first + again] == [None] * 4
    assert all(r["batches"] == 3 for r in first) and again[0]["batches"] == again[1]["batches"] > 0
    _once([s for r in first for s in r["saved"]] + [s for r in again for s in r["seen"]], expected)


def test_accelerate_dispatch_steps_never_mix_two_epochs(tmp_path):
    """Two epochs of 3 batches each under dispatch over 2 ranks: every step's slices share one
    epoch (a group the end of an epoch cuts short is completed with padding of that epoch), so
    each rank yields the same number of batches per epoch and a loop that ends its epoch on
    batch["epoch"] leaves it at the same step on every rank; each epoch's ids once."""
    corpus = _three_clips(tmp_path)
    expected = faults.expected_ids(corpus, LAYOUT)
    with _serve(corpus, epochs=2) as srv:
        ranks = _accelerate(srv.endpoint, tmp_path / "out", "--mode", "dispatch", clean=True)
    assert [r["error"] for r in ranks] == [None, None]
    assert [r["io_threads"] for r in ranks] == [0, 0]  # the stream ended: its I/O thread too
    assert ranks[0]["epochs"] == ranks[1]["epochs"], [r["epochs"] for r in ranks]
    _once_per_epoch([p for r in ranks for p in r["seen_epochs"]], expected)


@pytest.mark.parametrize("mode", ["dispatch", "per-rank"])
def test_accelerate_save_state_leave_the_loop_and_resume_over_two_epochs(tmp_path, mode):
    """How a job stops for preemption: every rank calls save_state after its step and leaves the
    loop at once (after the 2nd step under dispatch, the 1st per rank), then new ranks load_state
    and read to the end: each epoch's ids once across the checkpoint and the second run, and every
    rank of both runs exits cleanly. Per rank, accelerate's loader has taken one batch ahead of the
    loop when it leaves: that batch must come again."""
    corpus = _three_clips(tmp_path)
    expected = faults.expected_ids(corpus, LAYOUT)
    step = "1" if mode == "dispatch" else "0"
    with _serve(corpus, epochs=2) as srv:
        first = _accelerate(srv.endpoint, tmp_path / "a", "--mode", mode, "--stateful", "--save-at", step,
                            "--stop-after", step, clean=True)
        again = _accelerate(srv.endpoint, tmp_path / "b", "--mode", mode, "--stateful", "--resume",
                            tmp_path / "a" / "ckpt", clean=True)
    assert [r["error"] for r in first + again] == [None] * 4
    if mode == "dispatch":
        assert first[0]["epochs"] == first[1]["epochs"] and again[0]["epochs"] == again[1]["epochs"]
    _once_per_epoch([p for r in first for p in r["saved_epochs"]] + [p for r in again for p in r["seen_epochs"]],
                    expected)


@pytest.mark.parametrize("mode", ["dispatch", "per-rank"])
def test_accelerate_loop_left_and_read_again_gets_what_the_loader_took_ahead(tmp_path, mode):
    """Leave the loop after the first step, then iterate the same loader again to the end: the
    batches accelerate's loader had taken ahead of the loop (per rank the next batch, under
    dispatch the next step's group) reach the second pass; each epoch's ids once."""
    corpus = _three_clips(tmp_path)
    expected = faults.expected_ids(corpus, LAYOUT)
    with _serve(corpus, epochs=2) as srv:
        ranks = _accelerate(srv.endpoint, tmp_path / "out", "--mode", mode, "--stop-after", "0", "--again",
                            clean=True)
    assert [r["error"] for r in ranks] == [None, None]
    assert [r["io_threads"] for r in ranks] == [0, 0]  # read to the end: no I/O thread left running
    _once_per_epoch([p for r in ranks for p in r["seen_epochs"]], expected)


def test_accelerate_prepare_loader_twice_is_the_same_loader(tmp_path):
    """prepare_loader applied to the loader it returned (per rank, stateful) gives that loader
    back: save_state then holds one loader state, and new ranks that load it receive none of the
    samples the checkpoint holds again."""
    corpus = _three_clips(tmp_path)
    expected = faults.expected_ids(corpus, LAYOUT)
    with _serve(corpus, epochs=2) as srv:
        first = _accelerate(srv.endpoint, tmp_path / "a", "--mode", "per-rank", "--stateful", "--prepare-twice",
                            "--save-at", "1", "--stop-after", "1", clean=True)
        again = _accelerate(srv.endpoint, tmp_path / "b", "--mode", "per-rank", "--stateful", "--resume",
                            tmp_path / "a" / "ckpt", clean=True)
    assert [r["twice"] for r in first] == [True, True]
    assert not sorted(tmp_path.glob("a/ckpt/dl_state_dict_*.bin"))  # one loader registered
    _once_per_epoch([p for r in first for p in r["saved_epochs"]] + [p for r in again for p in r["seen_epochs"]],
                    expected)


def _launcher(tmp_path, launcher: str, copies: int = 1, *torchrun_args: str):
    corpus = faults.good_corpus(tmp_path, copies)
    expected = faults.expected_ids(corpus, LAYOUT)
    with _serve(corpus) as srv:
        ranks = _torchrun("harness.launcher_job", [launcher, srv.endpoint, tmp_path / "out"], tmp_path / "out",
                          *torchrun_args)
    assert ranks[0]["batches"] == ranks[1]["batches"] > 0
    _once([s for r in ranks for s in r["seen"]], expected)
    return ranks


def test_lightning_fabric_setup_dataloaders(tmp_path):
    _launcher(tmp_path, "fabric")


def test_ignite_engine_over_the_stream_and_auto_dataloader_refusing_batch_size_none(tmp_path):
    """idist.auto_dataloader(ds, batch_size=None) fails in Ignite's own batch-size scaling (before
    any batch); an Engine over DataLoader(ds, batch_size=None) trains each id once."""
    ranks = _launcher(tmp_path, "ignite")
    assert all(r["refused"] == "TypeError: '>=' not supported between instances of 'NoneType' and 'int'"
               for r in ranks), ranks


def test_torchrun_elastic_restart_after_a_rank_is_killed_mid_epoch(tmp_path):
    """torchrun --max-restarts 1: rank 1 is SIGKILLed after step 1 on the first attempt; the
    restarted ranks resume from the last step both checkpointed (step 0)."""
    ranks = _launcher(tmp_path, "elastic", 2, "--max-restarts", "1")
    assert [(r["attempt"], r["resumed_from"]) for r in ranks] == [(1, 0), (1, 0)]


def test_deepspeed_engine_over_the_stream_and_training_data_refused(tmp_path):
    """deepspeed.initialize(training_data=ds) builds a DistributedSampler over indices: the
    dataset's len() says in one line what to give instead; the engine over
    DataLoader(ds, batch_size=None) trains each id once."""
    ranks = _launcher(tmp_path, "deepspeed")
    for r in ranks:
        assert r["refused"].startswith("TypeError: V2VPushDataset is a stream without a length"), r
        assert "DataLoader(ds, batch_size=None)" in r["refused"]


@pytest.mark.parametrize("launcher", ["fabric", "ignite", "elastic", "deepspeed"])
def test_a_plan_under_fabric_ignite_deepspeed_and_an_elastic_restart(tmp_path, launcher):
    """The same loops reading ``V2VStreamDataset`` from ``v2v-serve --delivery plan``: each id of the
    epoch once across the ranks, the ranks in step; ``elastic`` resumes both restarted ranks from
    the position of the last step both checkpointed."""
    corpus = faults.good_corpus(tmp_path, 2 if launcher == "elastic" else 1)
    expected = faults.expected_ids(corpus, LAYOUT)
    args = ["--delivery", "plan", "--videos", str(corpus), "--workers", "2", *LAYOUT.args()]
    extra = ("--max-restarts", "1") if launcher == "elastic" else ()
    with ServeProcess(args) as srv:
        ranks = _torchrun("harness.launcher_job", [launcher, srv.endpoint, tmp_path / "out", "--plan", LAYOUT.batch],
                          tmp_path / "out", *extra)
    assert ranks[0]["batches"] == ranks[1]["batches"] > 0
    _once([s for r in ranks for s in r["seen"]], expected)
    if launcher == "elastic":
        assert [(r["attempt"], r["resumed_from"]) for r in ranks] == [(1, 0), (1, 0)]
    if launcher == "ignite":  # its auto_dataloader's batch-size scaling, as over push
        assert all(r["refused"].startswith("TypeError: '>=' not supported") for r in ranks), ranks


def _stream_batch(ids, epoch=0, batch_id=0):
    """A batch as V2VPushDataset yields it (frames only), its params carrying nested values."""
    import torch

    n = len(ids)
    return {"frames": torch.arange(n, dtype=torch.float32)[:, None, None, None, None].expand(n, 3, 1, 4, 4).clone(),
            "sample_ids": list(ids), "params": [{"sample_id": s, "stats": {"motion": 0.5}, "flip": False} for s in ids],
            "epoch": epoch, "batch_id": batch_id, "padding": torch.zeros(n, dtype=torch.bool)}


def test_dispatched_batches_survive_accelerates_concatenate_slice_and_placement():
    """A group of batches of different sizes and id lengths, through accelerate's own concatenate,
    slice_tensors and send_to_device as its dispatcher calls them: each slice decodes to exactly
    its batch's ids and params, filler rows flagged as padding."""
    import torch
    from accelerate.utils import concatenate, find_batch_size, send_to_device, slice_tensors

    from v2v_client.launchers import DispatchedBatch, dispatched, pack_rows

    group = [_stream_batch(["a.mp4#0", "b.mp4#0"], batch_id=4), _stream_batch(["a-much-longer-name.mp4#1"], batch_id=5)]
    packed = [pack_rows(b) for b in group]
    width = -(-max(len(r) for p in packed for r in p) // 64) * 64
    cat = concatenate([dispatched(b, p, 2, width) for b, p in zip(group, packed)])
    assert isinstance(cat, DispatchedBatch) and find_batch_size(cat) == 4
    for r, b in enumerate(group):
        part = send_to_device(slice_tensors(cat, slice(2 * r, 2 * r + 2)), torch.device("cpu"))
        n = len(b["sample_ids"])
        assert part["sample_ids"][:n] == b["sample_ids"] and part["params"][:n] == b["params"]
        assert part["padding"].tolist() == [False] * n + [True] * (2 - n)
        assert (part["epoch"], part["batch_id"]) == (0, b["batch_id"]) and part.get("missing") is None
        assert torch.equal(part["frames"][:n], b["frames"])


def test_a_gathered_state_gives_each_rank_its_part_and_refuses_another_world_size():
    from v2v_client.launchers import rank_part

    state = {"v2v_ranks": [{"consumer": "r0"}, {"consumer": "r1"}]}
    assert rank_part(state, lambda: (1, 2)) == {"consumer": "r1"}
    assert rank_part({"consumer": "x"}, lambda: 1 / 0) == {"consumer": "x"}  # a plain state: no position asked
    with pytest.raises(ValueError, match="saved by 2 ranks and is loaded by 3"):
        rank_part(state, lambda: (0, 3))


def test_prepare_loader_refuses_a_loader_accelerate_prepared_already():
    """prepare_loader over accelerator.prepare's loader would register a second loader (and per
    rank read IterableDatasetShard): refused in one line; its own loader comes back as it is."""
    import torch
    from accelerate import Accelerator
    from accelerate.state import AcceleratorState, GradientState

    from v2v_client import V2VPushDataset, prepare_loader

    try:
        acc = Accelerator(cpu=True)
        ds = V2VPushDataset("tcp://127.0.0.1:9")  # never iterated: no connection is made
        mine = prepare_loader(acc, torch.utils.data.DataLoader(ds, batch_size=None))
        assert prepare_loader(acc, mine) is mine and len(acc._dataloaders) == 1
        plain = acc.prepare(torch.utils.data.DataLoader(ds, batch_size=None))
        with pytest.raises(ValueError, match="prepare_loader takes the DataLoader itself"):
            prepare_loader(acc, plain)
        with pytest.raises(ValueError, match="prepare_loader takes the DataLoader itself"):
            prepare_loader(Accelerator(cpu=True), mine)  # another accelerator's
    finally:
        AcceleratorState._reset_state(True)
        GradientState._reset_state()


def test_a_state_without_batches_the_loop_never_received():
    """unseen: the samples (not the padding rows) of each batch leave their epoch's delivered ids,
    and the batch its epoch's count (a fan-in's: the count of the shard its server serves); an
    epoch the state calls complete is left as it is."""
    import torch

    from v2v_client.launchers import unseen

    def batch(ids, epoch, padding=None, **extra):
        return {"sample_ids": ids, "epoch": epoch, "padding": torch.tensor(padding or [False] * len(ids)), **extra}

    state = {"version": 1, "consumer": "c", "completed_epoch": 0, "recipe": "r",
             "delivered": {"1": ["a#0", "a#1", "b#0"], "2": ["c#0"]}, "batches": {"1": 2, "2": 1}}
    out = unseen(state, [batch(["a#1", "b#0"], 1, [False, True]), batch(["z#0"], 0)])
    assert out["delivered"] == {"1": ["a#0", "b#0"], "2": ["c#0"]} and out["batches"] == {"1": 1, "2": 1}
    assert state["delivered"]["1"] == ["a#0", "a#1", "b#0"]  # the state given is not changed
    fanin = {"version": 1, "consumer": "c", "completed_epoch": -1, "delivered": {"0": ["a#0", "b#0"]},
             "shard_batches": {"0/2": {"0": 1}, "1/2": {"0": 1}}, "shard_of": {"tcp://h:1": "0/2", "tcp://h:2": "1/2"}}
    out = unseen(fanin, [batch(["b#0"], 0, endpoint="tcp://h:2")])
    assert out["delivered"] == {"0": ["a#0"]} and out["shard_batches"] == {"0/2": {"0": 1}, "1/2": {"0": 0}}

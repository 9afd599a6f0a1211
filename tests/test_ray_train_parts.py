"""Parts of ``v2v-train --engine ray`` that need no Ray: padding left out of the loss, gradients
weighted by real samples across ranks (2 gloo processes), the consumed-id state."""
from __future__ import annotations

import pytest
import torch
import torch.multiprocessing as mp

from trainer.data import drop_padding
from trainer.ray_train import SampleWeightedAllReduce, _gather_state, load_ray_state


def test_drop_padding_subsets_every_per_sample_entry():
    b = {"voxels": torch.arange(4.0).view(4, 1), "sample_ids": ["a", "b", "c", "a"], "params": ["p"] * 4,
         "padding": torch.tensor([False, False, False, True]), "epoch": 3}
    out, n = drop_padding(b)
    assert n == 3 and out["sample_ids"] == ["a", "b", "c"] and out["voxels"].flatten().tolist() == [0.0, 1.0, 2.0]
    assert out["epoch"] == 3 and not out["padding"].any()
    out, n = drop_padding({**b, "padding": torch.ones(4, dtype=torch.bool)})
    assert n == 0 and len(out["voxels"]) == 0
    plain = {"voxels": torch.zeros(2, 1)}
    assert drop_padding(plain) == (plain, 2)
    same, n = drop_padding({"voxels": b["voxels"], "padding": [False] * 4})
    assert n == 4 and same["voxels"] is b["voxels"]


def test_padding_only_batch_makes_no_step(tmp_path):
    from trainer.config import apply_overrides, load_config
    from trainer.core import Trainer

    cfg = apply_overrides(load_config(None, "evflow"), ["model.num_bins=3", "model.base_num_channels=4"])
    t = Trainer(cfg, str(tmp_path), torch.device("cpu"))
    before = [p.detach().clone() for p in t.model.parameters()]
    batch = {"voxels": torch.ones(2, 2, 3, 32, 32, dtype=torch.int16), "flow": torch.ones(2, 2, 2, 32, 32),
             "padding": torch.tensor([True, True])}
    assert t.train_step(batch)["samples"] == 0 and t.step == 0
    assert all(torch.equal(a, b) for a, b in zip(before, t.model.parameters()))
    batch["padding"] = torch.tensor([True, False])
    assert torch.isfinite(torch.tensor(t.train_step(batch)["loss"])) and t.step == 1


def _rank(rank, world, path, q):
    import torch.distributed as dist

    dist.init_process_group("gloo", init_method=f"file://{path}", rank=rank, world_size=world)
    torch.manual_seed(0)
    model = torch.nn.Linear(3, 1)
    opt = SampleWeightedAllReduce(torch.optim.SGD(model.parameters(), lr=1.0), model.parameters())
    x = torch.tensor([[1.0, 2.0, 3.0], [0.0, 1.0, 0.0], [2.0, 0.0, 1.0]])
    opt.zero_grad()
    if rank == 0:  # three real samples; rank 1 has only padding and no forward at all
        model(x).pow(2).mean().backward()
        opt.samples = 3
    else:
        opt.samples = 0
    opt.step()
    after_one = [p.detach().tolist() for p in model.parameters()]
    # a step in which no rank has a real sample changes nothing (and still returns on both)
    opt.zero_grad()
    opt.samples = 0
    opt.step()
    after_none = [p.detach().tolist() for p in model.parameters()]
    q.put((rank, after_one, after_none))  # plain lists: no fd sharing
    dist.destroy_process_group()


@pytest.mark.timeout(120)
def test_gradients_are_weighted_by_real_samples_across_ranks(tmp_path):
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    procs = [ctx.Process(target=_rank, args=(r, 2, str(tmp_path / "store"), q)) for r in range(2)]
    for p in procs:
        p.start()
    got, idle = {}, {}
    for _ in procs:
        rank, after_one, after_none = q.get(timeout=100)
        got[rank], idle[rank] = after_one, after_none
    for p in procs:
        p.join(30)
    torch.manual_seed(0)
    ref = torch.nn.Linear(3, 1)
    sgd = torch.optim.SGD(ref.parameters(), lr=1.0)
    x = torch.tensor([[1.0, 2.0, 3.0], [0.0, 1.0, 0.0], [2.0, 0.0, 1.0]])
    ref(x).pow(2).mean().backward()
    sgd.step()  # one process on the 3 real samples: what both ranks must hold (DDP's mean would halve it)
    for r in (0, 1):
        for a, b in zip(got[r], ref.parameters()):
            torch.testing.assert_close(torch.tensor(a), b.detach())
        assert idle[r] == got[r]  # the all-padding step of every rank stepped nothing


def _conv_batch():
    """A channels-last conv layer's 3 samples: input (3, 3, 6, 6) and the layer (seed 0)."""
    torch.manual_seed(0)
    conv = torch.nn.Conv2d(3, 8, 3).to(memory_format=torch.channels_last)
    x = torch.randn(3, 3, 6, 6).contiguous(memory_format=torch.channels_last)
    return conv, x


def _rank_channels_last(rank, world, path, q):
    import torch.distributed as dist

    dist.init_process_group("gloo", init_method=f"file://{path}", rank=rank, world_size=world)
    conv, x = _conv_batch()
    adam = torch.optim.Adam(conv.parameters(), lr=1e-2, amsgrad=True, fused=True)  # speed: fast's optimiser
    opt = SampleWeightedAllReduce(adam, conv.parameters())
    mine = x[:2] if rank == 0 else x[2:]  # rank 0 has 2 real samples, rank 1 one
    for _ in range(2):
        opt.zero_grad(set_to_none=True)
        conv(mine).pow(2).mean().backward()
        opt.samples = len(mine)
        opt.step()
    after = [p.detach().clone() for p in conv.parameters()]
    layouts = [conv.weight.grad.is_contiguous(memory_format=torch.channels_last)]
    # a step without a real sample on any rank: the fused kernel skips it on the device
    opt.zero_grad(set_to_none=True)
    opt.samples = 0
    opt.step()
    steps = [float(s["step"]) for s in adam.state.values()]
    idle = [torch.equal(a, p.detach()) for a, p in zip(after, conv.parameters())]
    q.put((rank, [a.tolist() for a in after], layouts, steps, idle))
    dist.destroy_process_group()


@pytest.mark.timeout(120)
def test_reduced_gradients_keep_channels_last_under_the_fused_optimiser(tmp_path):
    """Two ranks, fused Adam, a channels-last conv weight: two steps land where the
    per-parameter Adam loop of one process on all 3 samples lands (within 1e-6; a gradient in
    the wrong layout moves elements by about 2 x lr = 2e-2), with channels-last gradients; a
    step without samples changes nothing, step counts included."""
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    procs = [ctx.Process(target=_rank_channels_last, args=(r, 2, str(tmp_path / "store"), q)) for r in range(2)]
    for p in procs:
        p.start()
    got = {}
    for _ in procs:
        rank, *rest = q.get(timeout=100)
        got[rank] = rest
    for p in procs:
        p.join(30)
    conv, x = _conv_batch()
    ref = torch.optim.Adam(conv.parameters(), lr=1e-2, amsgrad=True)  # the per-parameter loop
    for _ in range(2):
        ref.zero_grad(set_to_none=True)
        conv(x).pow(2).mean().backward()
        ref.step()
    for r in (0, 1):
        after, layouts, steps, idle = got[r]
        for a, b in zip(after, conv.parameters()):
            torch.testing.assert_close(torch.tensor(a), b.detach(), rtol=0, atol=1e-6)
        assert layouts == [True] and steps == [2.0, 2.0] and all(idle)


def test_consumed_state_merges_ranks_and_closes_finished_epochs(tmp_path):
    prev = {"engine": "ray", "consumed": {0: ["a#0"]}, "epochs_done": []}
    sd = _gather_state({0: {"a#1"}, 1: {"a#0"}}, prev, {0: 3, 1: 3}, world=1)
    assert sd == {"engine": "ray", "consumed": {0: ["a#0", "a#1"], 1: ["a#0"]}, "epochs_done": []}
    sd = _gather_state({0: {"a#2"}}, sd, {0: 3, 1: 3}, world=1)
    assert sd["epochs_done"] == [0] and list(sd["consumed"]) == [1]
    assert load_ray_state(None) == {"engine": "ray", "consumed": {}, "epochs_done": []}
    torch.save({"stream_state": {"epoch": 0, "yielded": []}}, tmp_path / "zmq.pt")
    with pytest.raises(ValueError, match="v2v-serve stream position"):
        load_ray_state(str(tmp_path / "zmq.pt"))

"""``speed: fast`` keeps one compiled graph per network and input shape for the whole run
(trainer/speed.py): HyperE2VID's curriculum is a device tensor, batches of another shape run
eagerly. The compiled network here is ``torch.compile(backend="eager", dynamic=False)``:
dynamo's guards, and so its recompiles, are those of the CUDA-graph compile (``mode=
"reduce-overhead"``, which needs a GPU), without inductor's code generation."""
from __future__ import annotations

import os

import pytest
import torch
import torch._dynamo
from torch._dynamo.utils import counters

from harness.toy_steps import TASKS, TOY_MODELS, toy_batch, toy_trainer
from trainer.data import batch_to_device, drop_padding
from trainer.models.hypere2vid import HyperE2VID
from trainer.tasks import curriculum_beta
from trainer.zoo import build_model

torch.set_num_threads(1)


def _hyper_inputs(channels_last):
    torch.manual_seed(0)
    model = build_model("hypere2vid", dict(TOY_MODELS["hypere2vid"])).train()
    if channels_last:  # as speed: fast prepares it
        model.to(memory_format=torch.channels_last)
    voxel, gt = torch.randn(2, 3, 24, 40), torch.rand(2, 1, 24, 40)  # padded to 32 x 48 inside
    _, states = model(torch.randn(2, 3, 24, 40))
    return model, voxel, gt, states


def _strides(t):
    """The strides of ``t``'s dimensions longer than 1 (a size-1 dimension's says nothing)."""
    return [st for st, n in zip(t.stride(), t.shape) if n > 1]


@pytest.mark.parametrize("channels_last", [False, True])
@pytest.mark.parametrize("amp", [False, True])
def test_tensor_beta_and_zero_states_are_bit_identical_to_the_float_and_none(amp, channels_last):
    model, voxel, gt, states = _hyper_inputs(channels_last)
    assert isinstance(model, HyperE2VID)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=amp):
        for beta, float_call in ((0.0, lambda: model(voxel, states)), (1.0, lambda: model(voxel, states, gt, 1.0))):
            img, (lstm, prev) = model(voxel, states, gt, torch.tensor(beta))
            ref_img, (ref_lstm, ref_prev) = float_call()
            assert torch.equal(img, ref_img) and torch.equal(prev, ref_prev), beta
            assert all(torch.equal(a, b) for s, r in zip(lstm, ref_lstm) for a, b in zip(s, r))
        # between the ends the same blend (stages of 1/16 are exact in float32)
        img, _ = model(voxel, states, gt, torch.tensor(0.8125))
        assert torch.equal(img, model(voxel, states, gt, 0.8125)[0])
        assert not torch.equal(img, model(voxel, states, gt, 1.0)[0])  # the value of beta matters
        # a sequence's first call: zero states as tensors give what None gives
        zeros = model.initial_states(voxel)
        img, (lstm, prev) = model(voxel, zeros, gt, torch.tensor(0.0))
        ref_img, (ref_lstm, ref_prev) = model(voxel)
        assert torch.equal(img, ref_img) and torch.equal(prev, ref_prev)
        assert all(a.dtype == b.dtype and torch.equal(a, b) for s, r in zip(lstm, ref_lstm) for a, b in zip(s, r))
        # in the layout and dtypes of the states the network returns (a compiled graph guards on them)
        assert [(z.dtype, z.stride()) for s in zeros[0] for z in s] == [(r.dtype, r.stride()) for s in lstm for r in s]
        assert _strides(zeros[1]) == _strides(prev) and zeros[1].dtype == torch.float32


@pytest.mark.parametrize("task", ["e2vid", "etnet"])
@pytest.mark.parametrize("channels_last", [False, True])
@pytest.mark.parametrize("amp", [False, True])
def test_zero_first_states_are_bit_identical_to_none(task, amp, channels_last):
    """E2VID's and ETNet's ``initial_states``: the output and the next states are those of
    ``states=None``, and the zeros have the dtype and strides of the states the network returns
    (what a compiled graph guards on, so the first step's graph is every step's)."""
    torch.manual_seed(0)
    model = build_model(task, dict(TOY_MODELS[task])).eval()  # eval: ETNet's dropout off
    if channels_last:  # as speed: fast prepares it
        model.to(memory_format=torch.channels_last)
    voxel = torch.randn(2, 3, 24, 40)  # padded to 32 x 48 inside
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=amp):
        zeros = model.initial_states(voxel)
        img, states = model(voxel, zeros)
        ref_img, ref_states = model(voxel)
        assert torch.equal(img, ref_img)
        assert all(torch.equal(a, b) for s, r in zip(states, ref_states) for a, b in zip(s, r))
        assert [(z.dtype, z.shape, _strides(z)) for s in zeros for z in s] == \
            [(r.dtype, r.shape, _strides(r)) for s in ref_states for r in s]
        # the step after: the states carried on, as a sequence's later steps see them
        assert torch.equal(model(voxel, states)[0], model(voxel, ref_states)[0])
    assert not any(z.requires_grad for s in zeros for z in s)
    assert all(z.requires_grad for s in model.initial_states(voxel, requires_grad=True) for z in s)
    with pytest.raises(ValueError, match="voxel must be"):
        model.initial_states(torch.zeros(2, 4, 24, 40))


def test_eraft_zero_warm_start_is_bit_identical_to_none():
    torch.manual_seed(0)
    model = build_model("eraft", dict(TOY_MODELS["eraft"])).train()
    v = torch.randn(3, 2, 3, 40, 56)  # padded to 64 x 64 inside (multiples of 32)
    flows = {}
    for zeros in (False, True):
        model.reset_states(v[0] if zeros else None)
        with torch.no_grad():
            flows[zeros] = [model(v[l - 1], v[l]) for l in (1, 2)]
    assert all(torch.equal(a, b) for a, b in zip(flows[False], flows[True]))
    model.reset_states(v[0])
    assert model.flow_init.shape == (2, 2, 8, 8) and not model.flow_init.any()


def _compiled_trainer(task, **extra):
    """A toy fast trainer whose network is compiled with the eager backend at fixed shapes."""
    t, _ = toy_trainer(task, "fast", **extra)
    t.net = torch.compile(t.model, backend="eager", dynamic=False)
    return t


def test_hypere2vid_curriculum_compiles_once_through_all_stages():
    """16 stages of one step each (max_steps 80, fraction 0.2), then 2 steps at beta 0: one
    graph, made at the first call (the first state is zeros, not None); the recompile limit (8)
    would raise."""
    torch._dynamo.reset()
    counters.clear()
    t = _compiled_trainer("hypere2vid", max_steps=80, curriculum={"fraction": 0.2, "stages": 16})
    betas, graphs = [], []
    with torch._dynamo.config.patch(fail_on_recompile_limit_hit=True):
        for i in range(18):
            betas.append(curriculum_beta(t.step, 80, 0.2, 16))
            t.train_step(toy_batch("hypere2vid", seed=i), sync=False)
            graphs.append(counters["stats"]["unique_graphs"])
    assert len(set(betas)) == 17 and betas[0] == 1.0 and betas[-1] == 0.0  # 16 stages, then off
    assert graphs == [1] * 18, graphs


def _drop_last(batch):
    """``batch`` with its last sample marked padding (left out of the loss: a batch of 1)."""
    return {**batch, "padding": torch.tensor([False] * (len(batch["voxels"]) - 1) + [True])}


@pytest.mark.parametrize("task", TASKS)
def test_batches_of_another_shape_run_eagerly_without_a_compile(task):
    """Full batch, a batch with padding dropped (1 sample), a batch of one shorter sequence, the
    full batch again: the one graph is made in the first step (a sequence's first state and
    E-RAFT's warm start are zero tensors, not None); the others run the model eagerly."""
    torch._dynamo.reset()
    counters.clear()
    t = _compiled_trainer(task)
    full = toy_batch(task)
    b1 = toy_batch(task, seed=1)  # 1 sample, 2 voxel grids instead of 3
    small = {**b1, "voxels": b1["voxels"][:1, :2], "frames": b1["frames"][:1, :3], "flow": b1["flow"][:1, :2],
             "sample_ids": b1["sample_ids"][:1]}
    batches = (full, _drop_last(toy_batch(task, seed=2)), small, toy_batch(task, seed=3))
    graphs = []
    with torch._dynamo.config.patch(fail_on_recompile_limit_hit=True):
        for b in batches:
            t.train_step(b, sync=False)
            graphs.append(counters["stats"]["unique_graphs"])
    assert graphs == [1] * 4, graphs  # recurrent states and warm start as zero tensors: one graph
    nets = [t.network_for(batch_to_device(drop_padding(b)[0], t.device, t.spec.outputs)) for b in batches]
    assert nets == [t.net, t.model, t.model, t.net] and t.compiled_shape == tuple(full["voxels"].shape)
    assert os.path.getsize(t.save_samples()) > 0  # from the copies of the compiled step's predictions

"""``speed: fast`` (trainer/speed.py) against the authors' eager step, on the CPU, at toy sizes
(harness/toy_steps.py): one training step from the same weights and batch.

Tolerances: fp32, all five networks: loss within rtol 1e-5, outputs within atol 1e-5, every
gradient within rtol 1e-4 plus atol 1e-5 x the model's largest gradient (biases right before a
BatchNorm have a true gradient of zero and carry only rounding noise, ~1e-10). bf16, all five:
loss within rtol 1e-4, outputs within atol 8e-3 (two bf16 steps at 1), gradients within rtol
2e-2 plus atol 2e-2 x the largest. The compiled path (``compile: true`` under ``speed: fast``,
inductor on the CPU, dropout drawn through aten as in eager), all five: the fp32 tolerances;
E-RAFT's step through dynamo and AOT autograd with the ``aot_eager`` backend (:data:`COMPILER`:
inductor's cold compile of its kernels alone took four and a half minutes). CUDA graphs (``mode="reduce-overhead"``) cannot run without a GPU
and are not tested.
"""
from __future__ import annotations

import pytest
import torch
import torch._inductor.config

from harness.toy_steps import HOST_READS, TASKS, step_ops, toy_batch, toy_trainer
from trainer.config import ConfigError, load_config
from trainer.data import batch_to_device
from trainer.speed import CHANNELS_LAST

torch.set_num_threads(1)


def one_step(task, speed, amp="fp32", backend=None, **extra):
    """Loss, outputs (float32) and gradients of the first step of the toy ``task``; with
    ``backend``, the trainer's compiled network is ``torch.compile(model, backend=backend)``."""
    t, _ = toy_trainer(task, speed, amp, **extra)
    if backend is not None:
        t.net = torch.compile(t.model, backend=backend)
    stats = t.train_step(toy_batch(task), sync=False)
    preds = t._last[1]
    preds = torch.stack(preds, 1) if isinstance(preds, list) else preds
    grads = {n: p.grad.clone() for n, p in t.model.named_parameters() if p.grad is not None}
    return float(stats["loss"]), preds, grads


def assert_step_close(eager, fast, loss_rtol, out_atol, grad_rtol, grad_atol):
    (la, pa, ga), (lb, pb, gb) = eager, fast
    assert lb == pytest.approx(la, rel=loss_rtol)
    assert torch.allclose(pb, pa, rtol=0, atol=out_atol), (pb - pa).abs().max()
    assert ga.keys() == gb.keys() and ga
    gmax = max(float(g.abs().max()) for g in ga.values())
    for name in ga:
        assert torch.allclose(gb[name], ga[name], rtol=grad_rtol, atol=grad_atol * gmax), name


@pytest.mark.parametrize("task", TASKS)
def test_fast_fp32_step_equals_eager(task):
    assert_step_close(one_step(task, "eager"), one_step(task, "fast"), 1e-5, 1e-5, 1e-4, 1e-5)


@pytest.mark.parametrize("task", TASKS)
def test_fast_bf16_step_equals_eager_bf16(task):
    assert_step_close(one_step(task, "eager", "bf16"), one_step(task, "fast", "bf16"), 1e-4, 8e-3, 2e-2, 2e-2)


#: The compiler each network's compiled step goes through: inductor, except E-RAFT, whose step
#: inductor turns into about 90 C++ kernels (its two encoders' norms and residual blocks are most
#: of them): their cold compile took 271 s of the 300 on 2 idle cores and 350-410 s on 2 loaded
#: ones, whatever the input (1 iteration, 2 levels, radius 1, 32 px: 351 s; the toy's: 380 s).
#: ``aot_eager`` runs the same capture (dynamo, the zero warm start, AOT autograd's joint
#: forward-backward graph and its partition) in seconds; inductor's generated code is checked on
#: the four other networks.
COMPILER = {"eraft": "aot_eager"}


@pytest.mark.parametrize("task", TASKS)
def test_fast_compiled_step_equals_eager(task, inductor_cache):
    # inductor draws dropout masks (ETNet's transformer) from its own generator unless it falls
    # back to aten's: with the fallback both steps draw the same masks
    with torch._inductor.config.patch(fallback_random=True):
        compiled = one_step(task, "fast", backend=COMPILER.get(task), compile=True)
    assert_step_close(one_step(task, "eager"), compiled, 1e-5, 1e-5, 1e-4, 1e-5)


@pytest.mark.parametrize("task", TASKS)
def test_fast_layout_and_optimiser(task):
    eager, _ = toy_trainer(task, "eager")
    fast, _ = toy_trainer(task, "fast")
    assert eager.optimizer.defaults["fused"] is None and fast.optimizer.defaults["fused"] is True
    weights = [p for p in fast.model.parameters() if p.ndim == 4]
    assert all(p.is_contiguous(memory_format=torch.channels_last) for p in weights) == (task in CHANNELS_LAST)
    assert all(p.is_contiguous() for p in eager.model.parameters())
    # the state dicts hold the same keys and values, so checkpoints load across speeds
    sd_e, sd_f = eager.model.state_dict(), fast.model.state_dict()
    assert list(sd_e) == list(sd_f) and all(torch.equal(sd_e[k], sd_f[k]) for k in sd_e)


def test_fused_optimiser_updates_as_the_per_parameter_loop():
    """Adam (amsgrad) and AdamW (weight decay) with the same gradients over two steps."""
    torch.manual_seed(0)
    ps = [torch.randn(8, 4, 3, 3), torch.randn(8)]
    for cls in (torch.optim.Adam, torch.optim.AdamW):
        results = []
        for kw in ({}, {"fused": True}):
            q = [p.clone().requires_grad_() for p in ps]
            opt = cls(q, lr=1e-3, amsgrad=True, weight_decay=0.01, **kw)
            for i in range(2):
                for p in q:
                    p.grad = torch.sin(p.detach() * (i + 1))
                opt.step()
            results.append(q)
        for a, b in zip(*results):
            assert torch.allclose(a, b, rtol=0, atol=1e-7)


@pytest.mark.parametrize("task", TASKS)
def test_fast_forward_and_backward_read_nothing_from_the_device(task):
    """No ``.item()`` / ``float(tensor)`` in the fast step's forward and backward (on CUDA each
    would wait for the device); and the whole fast step dispatches fewer aten ops."""
    t, _ = toy_trainer(task, "fast")
    b = batch_to_device(toy_batch(task), torch.device("cpu"), t.spec.outputs, flow_from=t.spec.flow_from(3))
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        loss, _, _ = t.forward(b)
        loss.backward()
    assert not [e.name for e in prof.events() if e.name in HOST_READS]
    eager, _ = toy_trainer(task, "eager")
    for tr in (t, eager):
        tr.train_step(toy_batch(task), sync=False)
    assert sum(step_ops(t, toy_batch(task, 1)).values()) < sum(step_ops(eager, toy_batch(task, 1)).values())


def test_bf16_weights_are_cast_once_per_step():
    """E2VID bf16: the recurrent network is called once per voxel grid; under ``speed: fast``
    each weight is cast to bf16 once per step, in eager once per call."""
    counts = {}
    for speed in ("eager", "fast"):
        t, _ = toy_trainer("e2vid", speed, "bf16")
        t.train_step(toy_batch("e2vid"), sync=False)
        counts[speed] = step_ops(t, toy_batch("e2vid", 1))["aten::_to_copy"]
    n_weights = len(list(t.model.parameters()))
    assert counts["eager"] - counts["fast"] >= n_weights  # 3 calls: at least 2 casts of each saved


def test_speed_setting_defaults_to_eager_and_checks_its_value(tmp_path):
    assert load_config(None, "e2vid")["speed"] == "eager"
    p = tmp_path / "c.yaml"
    p.write_text("speed: turbo\n")
    with pytest.raises(ConfigError):
        load_config(str(p), "e2vid")


def test_fast_asks_for_tf32_matmuls_on_cuda_only():
    from trainer.speed import matmul_precision

    assert matmul_precision("fast", torch.device("cuda")) == "high"
    assert matmul_precision("eager", torch.device("cuda")) is None
    assert matmul_precision("fast", torch.device("cpu")) is None
    before = torch.get_float32_matmul_precision()
    toy_trainer("etnet", "fast")  # a CPU trainer leaves the process's setting as it was
    assert torch.get_float32_matmul_precision() == before == "highest"


@pytest.mark.parametrize("task, preset", [(t, p) for t in ("e2vid", "hypere2vid", "etnet")
                                          for p in ("v+l1+h", "alex+tc", "alex", "alex+th")] + [("eraft", None)])
def test_fast_loss_over_the_whole_sequence_equals_the_per_step_loss(task, preset):
    """The fast task's loss (one call per term on the stacked sequence) against eager's (one per
    voxel grid; E-RAFT: per pair) on the same network and batch: loss and logged terms within rtol 1e-6 (float32
    summation order), gradients within rtol 1e-5 + 1e-6 x the largest. The perceptual term is
    the 1 - SSIM stand-in (no LPIPS weights are bundled); LPIPS, like it, is a per-image mean."""
    import tempfile

    from harness.toy_steps import toy_config
    from trainer.config import apply_loss_preset
    from trainer.core import Trainer

    out, ops = {}, {}
    model = None
    for speed in ("eager", "fast"):
        cfg = toy_config(task, speed)
        if preset:
            apply_loss_preset(cfg["loss"], preset)
        t = Trainer(cfg, tempfile.mkdtemp(), torch.device("cpu"))
        model = model or t.model  # both tasks run the eager trainer's network
        b = batch_to_device(toy_batch(task), t.device, t.spec.outputs, flow_from=t.spec.flow_from(3))
        model.zero_grad(set_to_none=True)
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
            loss, stats, preds = t.spec.forward(model, b, t._autocast)
        ops[speed] = sum(e.name.startswith("aten::") for e in prof.events())
        loss.backward()
        preds = torch.stack(preds) if isinstance(preds, list) else preds
        out[speed] = (loss.detach(), stats, preds, {n: p.grad.clone() for n, p in model.named_parameters()
                                                                 if p.grad is not None})
    # the same network ops; the loss's fewer calls dispatch fewer ops
    assert ops["fast"] < ops["eager"], ops
    (la, sa, pa, ga), (lb, sb, pb, gb) = out["eager"], out["fast"]
    torch.testing.assert_close(lb, la, rtol=1e-6, atol=0)
    assert sa.keys() == sb.keys() and (task == "eraft" or float(sa["tc"] > 0) == (preset != "alex"))
    for k in sa:
        torch.testing.assert_close(sb[k], sa[k], rtol=1e-6, atol=1e-9, msg=k)
    assert torch.equal(pa, pb)
    gmax = max(float(g.abs().max()) for g in ga.values())
    for n in ga:
        torch.testing.assert_close(gb[n], ga[n], rtol=1e-5, atol=1e-6 * gmax, msg=n)

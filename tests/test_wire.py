"""The wire between server and trainer: a tracked option's compact flow reaches the trainer as
the dense flow the server would have sent. A real v2v-serve on 127.0.0.1 over the real clips;
every test is bounded in time and stops what it starts."""
from __future__ import annotations

import functools

import numpy as np
import pytest
import torch

from harness.serve import ServeProcess
from v2v_client import V2VStreamDataset, expand_flow_grid
from v2v_server.config import ServeConfig
from v2v_server.flow import FlowEstimator, to_float16
from v2v_server.ids import parse_sample_id
from v2v_server.samples import make_sample, video_samples

L, B, CROP, MAXW, SEED = 8, 5, 96, 2, 7


def recipe(**kw) -> ServeConfig:
    return ServeConfig(sequence_length=L, num_bins=B, crop_size=CROP, max_samples_per_video=MAXW, seed=SEED,
                       **kw).validate()


def serve_args(videos, *extra):
    return ["--videos", str(videos), "--workers", "2", "--sequence-length", str(L), "--num-bins", str(B),
            "--crop-size", str(CROP), "--max-samples-per-video", str(MAXW), "--seed", str(SEED),
            "--batch-size", "2", *extra]


@functools.lru_cache(maxsize=None)
def dense_flows(videos, clip: str, epoch: int) -> dict:
    """sample id -> the dense float32 flow the server's own expansion gives."""
    cfg = recipe(flow_dtype="float32")
    return {sid: a["flow"] for sid, a, _ in video_samples(cfg, videos, clip, epoch, ("flow",))}


def want_flow(videos, batch: dict, i: int) -> np.ndarray:
    sid = batch["sample_ids"][i]
    return dense_flows(videos, parse_sample_id(sid)[0], batch["epoch"])[sid]


def first_batches(ds, n: int) -> list:
    it = iter(ds)
    try:
        return [next(it) for _ in range(n)]
    finally:
        it.close()


@pytest.fixture(scope="module")
def server(videos):
    with ServeProcess(serve_args(videos)) as srv:
        yield srv


def test_tracked_flow_reaches_the_trainer_as_the_server_s_dense_flow(server, videos):
    """The wire carries the grid; the trainer gets float32 (B, L, 2, H, W) flow equal to the
    server's dense expansion (bit for bit after float16 rounding, the old wire's precision)."""
    for b in first_batches(V2VStreamDataset(server.endpoint, outputs=("flow",), timeout_s=60), 2):
        fl = b["flow"]
        assert "flow_grid" not in b and fl.dtype == torch.float32 and fl.shape == (len(b["sample_ids"]), L, 2, CROP, CROP)
        for i in range(len(b["sample_ids"])):
            want = want_flow(videos, b, i)
            got = fl[i].numpy()
            assert np.abs(want).max() > 0.5  # real motion, not an all-zero field
            np.testing.assert_array_equal(to_float16(got).view(np.uint16), to_float16(want).view(np.uint16))
            np.testing.assert_allclose(got, want, rtol=2 ** -11, atol=1e-6)


def test_raw_flow_is_the_old_float16_wire_flow(server, videos):
    for b in first_batches(V2VStreamDataset(server.endpoint, outputs=("flow", "voxels"), raw=True, timeout_s=60), 1):
        assert b["flow"].dtype == torch.float16 and b["voxels"].dtype in (torch.int8, torch.int16, torch.int32)
        for i in range(len(b["sample_ids"])):
            np.testing.assert_array_equal(b["flow"][i].numpy().view(np.uint16),
                                          to_float16(want_flow(videos, b, i)).view(np.uint16))


def test_compact_flow_yields_the_grid_for_expansion_on_the_device(server, videos):
    b = first_batches(V2VStreamDataset(server.endpoint, outputs=("flow",), compact_flow=True, timeout_s=60), 1)[0]
    g = b["flow_grid"]
    assert "flow" not in b and g.dtype == torch.float32 and g.shape == (len(b["sample_ids"]), L, 2, 8, 8)
    dense = expand_flow_grid(g, (CROP, CROP))
    for i, sid in enumerate(b["sample_ids"]):
        np.testing.assert_allclose(dense[i].numpy(), want_flow(videos, b, i), rtol=2 ** -11, atol=1e-6)


def test_only_tracked_options_have_a_grid_and_expansion_checks_its_input(real_clip):
    cfg = recipe(flow_preset="ultrafast")
    est = FlowEstimator("ultrafast")
    with pytest.raises(ValueError, match="only tracked options"):
        est.voxel_flow_grids(real_clip[: 2 * B + 1], B)
    from v2v_server.samples import plan_window

    plan = plan_window(cfg, 0, "x.mp4#0", 0, (real_clip.shape[1], real_clip.shape[2]))
    frames = np.zeros((plan.consumed, CROP, CROP), np.uint8)
    out = make_sample(cfg, plan, frames, ("flow",), est, flow_grid=True)
    assert set(out) == {"flow"} and out["flow"].shape == (L, 2, CROP, CROP)  # dense for non-tracked options
    with pytest.raises(ValueError, match=r"\(\.\.\., 2, n, n\)"):
        expand_flow_grid(torch.zeros(3, 8, 8), (CROP, CROP))

"""The data path: samples kept as views of the received frames, batches stacked once."""
from __future__ import annotations

import numpy as np
import pytest

from v2v_server.samples.recipe import SampleRecipe
from v2v_server.service.assembly import make_batch, sample_from_worker
from v2v_wire.protocol import decode_arrays, encode_arrays
from v2v_wire.worker_messages import Sample


def _sample(i, vox_dtype=np.int8):
    arrays = {"voxels": np.full((2, 5, 4, 4), i, vox_dtype), "frames": np.full((3, 4, 4), 10 * i, np.uint8),
              "flow": np.full((2, 2, 4, 4), i / 2, np.float16)}
    specs, frames = encode_arrays(arrays)
    wire = [bytes(f) for f in frames]  # what a worker's message carries
    header = {"type": "sample", "task": 0, "key": ["v.mp4", i, 0], "meta": {"i": i}, "arrays": specs}
    return sample_from_worker(Sample.from_wire(header), wire), wire


def test_samples_view_the_received_frames_and_batches_stack_once():
    samples, wires = zip(*[_sample(i) for i in range(3)])
    s0 = samples[0]
    # no copy on receive: the array is a view of the message's buffer
    assert np.shares_memory(s0.arrays["voxels"], np.frombuffer(wires[0][0], np.int8))
    assert not s0.arrays["voxels"].flags.writeable
    b = make_batch(list(samples))
    assert b.sample_ids == ["v.mp4#0", "v.mp4#1", "v.mp4#2"] and b.nbytes == sum(s.nbytes for s in samples)
    specs, frames = b.wire(("voxels", "flow"))
    assert [s["name"] for s in specs] == ["voxels", "flow"]
    got = decode_arrays(specs, [f.tobytes() for f in frames])
    assert got["voxels"].shape == (3, 2, 5, 4, 4) and (got["voxels"][:, 0, 0, 0, 0] == [0, 1, 2]).all()
    # stacked once: a second wire() sends the same buffers, and the samples' frames are released
    assert b.samples is None
    assert b.wire(("voxels",))[1][0] is frames[0]
    sub = b.subset([2, 0])
    assert sub.sample_ids == ["v.mp4#2", "v.mp4#0"] and (sub.arrays["frames"][:, 0, 0, 0] == [20, 0]).all()


def test_voxels_widen_to_the_batch_and_subset_before_stacking():
    a, _ = _sample(1, np.int8)
    b, _ = _sample(2, np.int16)
    batch = make_batch([a, b])
    sub = batch.subset([1])
    assert sub.samples is not None and sub.sample_ids == ["v.mp4#2"]
    assert batch.arrays["voxels"].dtype == np.int16  # the narrowest type holding both
    assert sub.arrays["voxels"].dtype == np.int16
    with pytest.raises(ValueError, match="at least one"):
        make_batch([])


def test_worker_float16_narrowing_is_numpys_cast_bit_for_bit():
    from v2v_server.ops.config import ServeConfig
    from v2v_server.flow.estimate import to_float16
    from v2v_server.service.worker import wire_arrays

    rng = np.random.default_rng(0)
    flow = (rng.standard_normal((3, 2, 16, 24)) * 40).astype(np.float32)
    # zero, signed zero, half subnormals, ties at the half's precision, the largest half, overflow
    flow.flat[:10] = [0.0, -0.0, 1e-6, -3e-7, 6.1e-5, 1.0 + 2.0**-11, 65504.0, 65520.0, 7e4, -np.inf]
    with np.errstate(over="ignore"):
        want = flow.astype(np.float16)
    got = to_float16(flow)
    assert got.dtype == np.float16 and got.shape == flow.shape
    assert np.array_equal(got.view(np.uint16), want.view(np.uint16))
    assert np.array_equal(to_float16(flow[:, 1, :, 3]).view(np.uint16), want[:, 1, :, 3].view(np.uint16))
    out = wire_arrays(SampleRecipe(), {"flow": flow, "voxels": np.zeros((1, 5, 2, 2), np.int32)})
    assert out["flow"].dtype == np.float16 and out["voxels"].dtype == np.int8

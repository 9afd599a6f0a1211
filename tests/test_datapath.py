"""The data path: samples kept as views of the received frames, a reply's rows stacked once."""
from __future__ import annotations

import numpy as np
import pytest

from v2v_server.samples.recipe import SampleRecipe
from v2v_server.service.assembly import sample_from_worker
from v2v_wire.batches import stack_arrays
from v2v_wire.outputs import narrowest
from v2v_wire.protocol import decode_arrays, encode_arrays
from v2v_wire.worker_messages import Sample


def _sample(i, vox_dtype=np.int8):
    arrays = {"voxels": np.full((2, 5, 4, 4), i, vox_dtype), "frames": np.full((3, 4, 4), 10 * i, np.uint8),
              "flow": np.full((2, 2, 4, 4), i / 2, np.float16)}
    specs, frames = encode_arrays(arrays)
    wire = [bytes(f) for f in frames]  # what a worker's message carries
    header = {"type": "sample", "task": 0, "key": ["v.mp4", i, 0], "meta": {"i": i}, "arrays": specs}
    return sample_from_worker(Sample.from_wire(header), wire), wire


def test_samples_view_the_received_frames_and_a_batch_stacks_them_once():
    samples, wires = zip(*[_sample(i) for i in range(3)])
    s0 = samples[0]
    # no copy on receive: the array is a view of the message's buffer
    assert np.shares_memory(s0.arrays["voxels"], np.frombuffer(wires[0][0], np.int8))
    assert not s0.arrays["voxels"].flags.writeable
    assert s0.sample_id == "v.mp4#0" and s0.meta == {"i": 0} and s0.nbytes == sum(len(w) for w in wires[0])
    # a reply's rows: one stacked copy of each array, in the order given
    stacked = stack_arrays([samples[i].arrays["voxels"] for i in (2, 0, 1)])
    assert stacked.shape == (3, 2, 5, 4, 4) and (stacked[:, 0, 0, 0, 0] == [2, 0, 1]).all()
    assert not any(np.shares_memory(stacked, s.arrays["voxels"]) for s in samples)
    specs, frames = encode_arrays({"voxels": stacked})
    got = decode_arrays(specs, [bytes(f) for f in frames])
    assert got["voxels"].dtype == np.int8 and got["voxels"].tobytes() == stacked.tobytes()


def test_voxels_widen_to_the_batch_and_narrow_again_to_what_holds_them():
    a, _ = _sample(1, np.int8)
    b, _ = _sample(2, np.int16)
    both = stack_arrays([a.arrays["voxels"], b.arrays["voxels"]])
    assert both.dtype == np.int16  # the type holding both
    assert narrowest("voxels", both).dtype == np.int8  # values 1 and 2: int8 holds them
    assert np.array_equal(narrowest("voxels", both), both)
    big = stack_arrays([b.arrays["voxels"], np.full((2, 5, 4, 4), 300, np.int16)])
    assert narrowest("voxels", big).dtype == np.int16 and narrowest("flow", a.arrays["flow"]) is a.arrays["flow"]
    with pytest.raises(ValueError, match="cannot share a batch"):
        stack_arrays([a.arrays["voxels"], np.zeros((2, 5, 4, 8), np.int8)])


def test_worker_float16_narrowing_is_numpys_cast_bit_for_bit():
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

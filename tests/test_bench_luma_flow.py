"""bench/luma_flow.py: a 10-bit encode of a bundled clip decodes to uint16 whose two 8-bit forms
differ, and the flow moves by a fraction of a pixel between them (docs/flow.md, Deeper sources)."""
import av
import numpy as np
import pytest

from bench.luma_flow import STEP, ten_bit_frames
from v2v_server.flow.estimate import FlowEstimator
from v2v_server.luma import to_uint8


def test_ten_bit_frames_round_apart_from_their_top_byte(tmp_path):
    if "libx265" not in av.codecs_available:
        pytest.skip("PyAV's FFmpeg has no libx265 encoder")
    frames = ten_bit_frames(tmp_path, 11)
    assert frames.dtype == np.uint16 and frames.shape == (11, 336, 596)
    rounded, top = to_uint8(frames), (frames >> 8).astype(np.uint8)
    assert 0.05 < np.mean(rounded != top) and np.abs(rounded.astype(int) - top).max() == 1
    est = FlowEstimator("ultrafast")
    a, b = est.voxel_flows(top, STEP), est.voxel_flows(rounded, STEP)
    assert 0 < np.abs(a - b).mean() < 0.1 * np.abs(b).mean()

"""decode_fast: FFmpeg's H.264 deblocking shortcuts keep every frame and its timing and change
pixels only slightly; a bad name is a clear error naming the key."""
import numpy as np
import pytest

from v2v_server.ops.config import ServeConfig
from v2v_server.ops.startup import SAMPLE_VIDEOS
from v2v_server.frames.decode import DECODE_FAST, decode_luma, open_video


def luma(fast: str) -> np.ndarray:
    container, stream, _ = open_video(SAMPLE_VIDEOS / "webvid_like_596x336.mp4", 1, fast)
    return np.stack([g for _, g in zip(range(60), decode_luma(container, stream))])


def test_shortcuts_keep_the_frames_and_change_pixels_a_little():
    full = luma("off")
    for fast in DECODE_FAST:
        got = luma(fast)
        assert got.shape == full.shape
        mse = np.mean((got.astype(float) - full) ** 2)
        if fast == "off":
            assert mse == 0
        else:
            assert 10 * np.log10(255 ** 2 / max(mse, 1e-12)) > 30  # measured 33-58 dB (docs/decode_fast.md)
    assert not np.array_equal(luma("all"), full)  # the option reaches the decoder


def test_bad_decode_fast_names_the_key():
    with pytest.raises(ValueError, match="decode_fast"):
        ServeConfig(decode_fast="fastest")
    with pytest.raises(ValueError, match="decode_fast"):
        open_video(SAMPLE_VIDEOS / "bikes.mp4", 1, "fastest")

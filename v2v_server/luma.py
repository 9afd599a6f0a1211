"""Full-range luma to 8 bits: the one conversion of deeper (uint16) luma for everything that
works in 8 bits, the ground-truth ``frames`` a sample carries and the frames optical flow reads
(DIS and the tracker need 8 bits; RAFT reads them scaled to [-1, 1]). Below every stage of
``v2v_server`` (decode, flow and the sample maker all use it) and the trainer's evaluation inputs.
"""
from __future__ import annotations

import numpy as np

__all__ = ["to_uint8"]


def to_uint8(luma: np.ndarray) -> np.ndarray:
    """Full-range uint16 luma (0..65535) -> uint8 (0..255), rounded to the nearest code
    (``(v + 128) // 257``: 257 x c maps to c exactly); uint8 input is returned as is.

    Args:
        luma: uint8 or uint16 array of any shape, full range.

    Returns:
        uint8 array of the same shape (``luma`` itself when it is uint8, else a new array).

    Raises:
        ValueError: any other dtype, naming it.
    """
    if luma.dtype == np.uint8:
        return luma
    if luma.dtype != np.uint16:
        raise ValueError(f"luma must be uint8 or uint16, got {luma.dtype}")
    return ((luma.astype(np.uint32) + 128) // 257).astype(np.uint8)

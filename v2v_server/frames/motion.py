"""How much a video's log intensity changes from one frame to the next: what decides that a
window is static (``static_windows: skip``) before any simulation.

A frame's change is the mean of ``|L_t - L_{t-1}|`` over every ``STEP``-th row and column of
the frames the windows are cut from (the kept rows), with ``L = log(1e-3 + (F / 255) ^ 2.2)``,
the log intensity the simulation thresholds (V2V's ``I = (F/255)^2.2; L = log(1e-3 + I)``). A
window's motion is the mean change over its frame pairs. It does not depend on the sensor
parameters drawn for a sample: at the paper's most sensitive contrast threshold (c = 0.05) a
window of motion m makes at most about ``m / 0.05`` signal events per pixel per frame pair, so
a window below :data:`STATIC_MOTION` is one that no draw of the recipe turns into more than a
trickle of signal events (docs/fidelity.md, "Static windows", measures it).
"""
from __future__ import annotations

from typing import Callable, Dict, Optional

import numba
import numpy as np

from v2v_server.frames.shots import code_table

#: Window motion (mean |delta L| per frame pair, log-intensity units) below which a window is
#: static: at c = 0.05, under 0.1 signal events per pixel per frame pair (docs/fidelity.md).
STATIC_MOTION = 0.005
#: Rows and columns between the samples a frame's change is measured on.
STEP = 4
#: What measures a window's motion, as the recipe fingerprint and frame-cache entries name it.
MOTION_VERSION = f"logdiff{STEP}-1"


def log_table(expand: Callable[[np.ndarray], np.ndarray], dtype) -> np.ndarray:
    """Log intensity of every code of a stream (``expand``: its code -> full-range map):
    float32 (256,) for uint8 codes, (65536,) for uint16 ones, ``log(1e-3 + (F / 255) ^ 2.2)``
    with F on the 8-bit scale (``shots.code_table``)."""
    f = code_table(expand, dtype).astype(np.float64) / 255.0
    return np.log(1e-3 + f ** 2.2).astype(np.float32)


@numba.njit(cache=True, nogil=True)
def _sample(codes, table, out):  # pragma: no cover - compiled
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            out[i, j] = table[codes[i * STEP, j * STEP]]


@numba.njit(cache=True, nogil=True)
def _mean_abs_diff(a, b):  # pragma: no cover - compiled
    s = 0.0
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            s += abs(a[i, j] - b[i, j])
    return s / a.size


class MotionMeter:
    """The change of log intensity of each frame of a pass from the one before it.

    Feed every frame, in order, to :meth:`score`. Pure: no I/O, no clock.
    """

    def __init__(self):
        self.prev: Optional[np.ndarray] = None
        self.tables: Dict[object, np.ndarray] = {}  # a stream's code map -> its log_table

    def score(self, codes: Optional[np.ndarray], expand) -> float:
        """The frame's change from the previous one, log-intensity units: the mean of ``|L -
        L_prev|`` on every ``STEP``-th row and column. 0.0 for the first frame, a frame of
        another size than the one before, or a frame counted from its packet (``codes`` None).

        Args:
            codes: (H, W) uint8 or uint16 codes as ``decode.decode_codes`` yields them, any strides.
            expand: their code -> full-range map.
        """
        if codes is None:
            self.prev = None
            return 0.0
        table = self.tables.get(expand)
        if table is None:
            table = self.tables[expand] = log_table(expand, codes.dtype)
        cur = np.empty(((codes.shape[0] + STEP - 1) // STEP, (codes.shape[1] + STEP - 1) // STEP), np.float32)
        _sample(codes, table, cur)
        prev, self.prev = self.prev, cur
        if prev is None or prev.shape != cur.shape:
            return 0.0
        return float(_mean_abs_diff(cur, prev))

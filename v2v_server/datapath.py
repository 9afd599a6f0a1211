"""The server's data path: how sample arrays travel from a worker to a client's socket.

This module is the one seam between the data path (owned by the speed work: copies, batch
assembly, wire layout) and the control logic in ``server.py`` (credits, leases, acks, epochs),
which treats a :class:`BatchPayload` as opaque: it asks only for its sample ids, their
parameters, its size, a subset of its samples, and its wire frames.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Sequence, Tuple

import numpy as np

from .protocol import decode_arrays, encode_arrays, narrow_int_dtype


@dataclass
class SamplePayload:
    """One sample as received from a worker.

    Attributes:
        sample_id: stable id ``relative/path.mp4#k``.
        meta: per-sample parameters (msgpack-able dict).
        arrays: name -> array (voxels int32/int16/int8 ``(L, B, H, W)``, frames uint8
            ``(L + 1, 1, H, W)``, flow float16 ``(L, 2, H, W)``).
    """

    sample_id: str
    meta: dict
    arrays: Dict[str, np.ndarray]

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.arrays.values())


def sample_from_worker(header: dict, frames: Sequence) -> SamplePayload:
    """Build a :class:`SamplePayload` from a worker's ``sample`` message (header + raw frames).

    Raises:
        ProtocolError: when the frames do not match the header's array specs.
    """
    arrays = {k: np.array(v) for k, v in decode_arrays(header["arrays"], frames).items()}
    return SamplePayload(header["sample_id"], header["meta"], arrays)


@dataclass
class BatchPayload:
    """The arrays of one batch, samples stacked on a leading axis.

    Attributes:
        sample_ids: ids in batch order.
        meta: per-sample parameters in batch order.
        arrays: name -> stacked array; voxels narrowed to the smallest int type that holds them.
    """

    sample_ids: List[str]
    meta: List[dict]
    arrays: Dict[str, np.ndarray]

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.arrays.values())

    def subset(self, keep: Sequence[int]) -> "BatchPayload":
        """A payload holding only the samples at positions ``keep`` (in that order)."""
        keep = list(keep)
        return BatchPayload([self.sample_ids[i] for i in keep], [self.meta[i] for i in keep],
                            {k: np.ascontiguousarray(v[keep]) for k, v in self.arrays.items()})

    def wire(self, outputs: Sequence[str]) -> Tuple[List[dict], List]:
        """Array specs for the batch header and the frames to send, for the arrays in ``outputs``."""
        return encode_arrays({k: v for k, v in self.arrays.items() if k in outputs})


def make_batch(samples: Sequence[SamplePayload]) -> BatchPayload:
    """Stack samples into one :class:`BatchPayload` (voxels narrowed, never wrapped)."""
    arrays = {}
    for name in samples[0].arrays:
        stacked = np.stack([s.arrays[name] for s in samples])
        if name == "voxels":
            stacked = stacked.astype(narrow_int_dtype(stacked), copy=False)
        arrays[name] = stacked
    return BatchPayload([s.sample_id for s in samples], [s.meta for s in samples], arrays)

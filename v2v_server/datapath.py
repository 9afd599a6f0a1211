"""The server's data path: how sample arrays travel from a worker to a client's socket.

This module is the one seam between the data path (owned by the speed work: copies, batch
assembly, wire layout) and the control logic in ``server.py`` (credits, leases, acks, epochs),
which treats a :class:`BatchPayload` as opaque: it asks only for its sample ids, their
parameters, its size, a subset of its samples, and its wire frames.

Copies. A worker's ``sample`` message is received zero-copy (``recv_multipart(copy=False)``):
a :class:`SamplePayload` holds read-only numpy views of the received ZeroMQ frames, never a
copy. A batch is assembled lazily, the first time it is sent: each array is one
``np.empty((B, ...))`` filled sample by sample from those views (the one copy between a
worker's arrays and the client's socket), kept for re-sends, and handed to ZeroMQ
zero-copy. ``subset`` rebuilds from the samples' views, not from the stacked batch.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from .protocol import decode_arrays, encode_arrays, narrow_int_dtype


@dataclass
class SamplePayload:
    """One sample as received from a worker.

    Attributes:
        sample_id: stable id (``sampler.make_sample_id``).
        meta: per-sample parameters (msgpack-able dict).
        arrays: name -> read-only array viewing the received frame (voxels int8/int16/int32
            ``(L, B, H, W)``, frames uint8 ``(L + 1, H, W)``, flow float16/float32
            ``(L, 2, H, W)``); the views keep the ZeroMQ frames alive.
    """

    sample_id: str
    meta: dict
    arrays: Dict[str, np.ndarray]

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.arrays.values())


def sample_from_worker(header: dict, frames: Sequence) -> SamplePayload:
    """Build a :class:`SamplePayload` from a worker's ``sample`` message (header + raw frames,
    ``zmq.Frame`` or bytes), without copying the arrays.

    Raises:
        ProtocolError: when the frames do not match the header's array specs.
    """
    return SamplePayload(header["sample_id"], header["meta"], decode_arrays(header["arrays"], frames))


def _stack(arrays: Sequence[np.ndarray], dtype) -> np.ndarray:
    """One (B, ...) array filled from B same-shape arrays: a single copy (with a widening
    cast where a sample came narrower than the batch)."""
    out = np.empty((len(arrays),) + arrays[0].shape, dtype)
    for i, a in enumerate(arrays):
        if a.shape != arrays[0].shape:
            raise ValueError(f"sample arrays of shapes {arrays[0].shape} and {a.shape} cannot share a batch")
        np.copyto(out[i], a, casting="safe")
    return out


@dataclass
class BatchPayload:
    """The arrays of one batch, samples stacked on a leading axis.

    Attributes:
        sample_ids: ids in batch order.
        meta: per-sample parameters in batch order.
        samples: the :class:`SamplePayload` of each sample (views of the workers' frames)
            until the batch is stacked, then None (the frames are released: a batch is held
            once, never twice).
    """

    sample_ids: List[str]
    meta: List[dict]
    samples: Optional[List[SamplePayload]]
    _stacked: Optional[Dict[str, np.ndarray]] = field(default=None, repr=False)

    @property
    def arrays(self) -> Dict[str, np.ndarray]:
        """name -> stacked (B, ...) array; voxels in the narrowest int type that holds every
        sample's counts (each sample arrives narrowed by its worker). Built on first use."""
        if self._stacked is None:
            out = {}
            for name in self.samples[0].arrays:
                parts = [s.arrays[name] for s in self.samples]
                out[name] = _stack(parts, np.result_type(*[p.dtype for p in parts]))
            self._stacked = out
            self.samples = None
        return self._stacked

    @property
    def nbytes(self) -> int:
        if self._stacked is not None:
            return sum(a.nbytes for a in self._stacked.values())
        return sum(s.nbytes for s in self.samples)

    def subset(self, keep: Sequence[int]) -> "BatchPayload":
        """A payload holding only the samples at positions ``keep`` (in that order)."""
        keep = list(keep)
        ids, meta = [self.sample_ids[i] for i in keep], [self.meta[i] for i in keep]
        if self._stacked is None:
            return BatchPayload(ids, meta, [self.samples[i] for i in keep])
        arrays = {k: v[keep] for k, v in self._stacked.items()}  # a copy; only on resume
        return BatchPayload(ids, meta, None, {k: narrow_voxels(k, v) for k, v in arrays.items()})

    def wire(self, outputs: Sequence[str]) -> Tuple[List[dict], List]:
        """Array specs for the batch header and the frames to send (zero-copy, one per
        array), for the arrays in ``outputs``."""
        return encode_arrays({k: v for k, v in self.arrays.items() if k in outputs})


def narrow_voxels(name: str, a: np.ndarray) -> np.ndarray:
    """``a`` narrowed to the smallest int type that holds it when ``name`` is "voxels"."""
    return a.astype(narrow_int_dtype(a), copy=False) if name == "voxels" else a


def make_batch(samples: Sequence[SamplePayload]) -> BatchPayload:
    """A :class:`BatchPayload` of ``samples`` (nothing is copied until it is first sent).

    Raises:
        ValueError: for no samples, or samples whose array names differ.
    """
    if not samples:
        raise ValueError("a batch needs at least one sample")
    names = set(samples[0].arrays)
    for s in samples[1:]:
        if set(s.arrays) != names:
            raise ValueError(f"sample {s.sample_id} has arrays {sorted(s.arrays)}, expected {sorted(names)}")
    return BatchPayload([s.sample_id for s in samples], [s.meta for s in samples], list(samples))


__all__ = ["SamplePayload", "BatchPayload", "sample_from_worker", "make_batch", "narrow_voxels"]

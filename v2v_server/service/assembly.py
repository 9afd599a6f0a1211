"""How a sample's arrays travel from a worker into the server: one copy each way in.

* **Shared memory** (the default where ``/dev/shm`` exists): each worker writes a sample's
  arrays into a free slot of its own ``shm.SlotRing`` (a file in ``/dev/shm`` that the pool
  creates and the worker unlinks as soon as it has mapped it) and sends only the header with
  the slot number. The server copies the slot into arrays of the sample's own
  (:func:`sample_from_slot`; the one copy) and gives the slot back at once, so a ring of a few
  slots suffices however long samples wait for their fetch. The sample bytes never cross the
  worker's socket.
* **Socket frames** (fallback; also used for a sample too large for a slot): a worker's
  ``sample`` message is received zero-copy (``recv_multipart(copy=False)``); a
  :class:`SamplePayload` holds read-only numpy views of the received ZeroMQ frames
  (:func:`sample_from_worker`).

**Compressed frames** (``codecs``): a worker asked for codecs in its task sends each array
compressed as extra frames after the sample's array frames (:func:`packed_frames`); the sample
keeps them as received and the server sends them by reference: it never compresses,
decompresses or copies them.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Dict, Sequence

import numpy as np

from v2v_server.service.shm import SlotRing
from v2v_wire.batches import frame_size
from v2v_wire.protocol import MAX_BATCH_BYTES, ProtocolError, decode_arrays
from v2v_wire.worker_messages import Sample

log = logging.getLogger("v2v.datapath")


@dataclass
class SamplePayload:
    """One sample as received from a worker.

    Attributes:
        sample_id: stable id (``ids.make_sample_id``).
        meta: per-sample parameters (msgpack-able dict).
        arrays: name -> read-only array viewing the received frame, or the sample's own copy of
            its slot (voxels int8/int16/int32 ``(L, B, H, W)``, frames uint8 ``(L + 1, H, W)``,
            flow float16/float32 ``(L, 2, H, W)``); the views keep the ZeroMQ frames alive.
        packed: codec -> array name -> (dtype the worker sent it in, its compressed frame)
            (``codecs``), kept as received and sent by reference to the readers that asked
            for that codec.
    """

    sample_id: str
    meta: dict
    arrays: Dict[str, np.ndarray]
    packed: Dict[str, Dict[str, tuple]] = field(default_factory=dict, repr=False)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.arrays.values())


def sample_from_worker(msg: Sample, frames: Sequence, crops_per_window: int = 1) -> SamplePayload:
    """Build a :class:`SamplePayload` from a worker's ``sample`` message (its header ``msg``, then
    raw frames, ``zmq.Frame`` or bytes, then its compressed frames), without copying the arrays.
    ``crops_per_window``: the server's, for the sample's id (``ids.SampleKey.sample_id``).

    Raises:
        ProtocolError: when the frames do not match the header's array specs.
    """
    n = len(msg.arrays)
    s = SamplePayload(msg.key.sample_id(crops_per_window), msg.meta, decode_arrays(list(msg.arrays), frames[:n]))
    s.packed = packed_frames(msg.packed, frames[n:], s.arrays)
    return s


#: Largest compressed frame accepted from a worker, bytes (a sample's largest array, uncompressed,
#: is at most ``slot_bytes``; a compressed one can exceed it only by the codec's small overhead).
MAX_PACKED_BYTES = MAX_BATCH_BYTES


def packed_frames(specs: Sequence[dict], frames: Sequence,
                  arrays: Dict[str, np.ndarray]) -> Dict[str, Dict[str, tuple]]:
    """The compressed frames of a worker's ``sample`` message (``specs``, its ``packed`` list:
    codec, array name and size of each frame after the array frames), by codec and array name, each with
    the dtype of the array it compresses; the frames themselves are kept as they are (never
    decompressed here).

    Raises:
        ProtocolError: for a list that does not match the frames, or names no array of the sample.
    """
    if len(specs) != len(frames):
        raise ProtocolError(f"sample header lists {len(specs)} compressed frames, message has {len(frames)}")
    out: Dict[str, Dict[str, object]] = {}
    for spec, fr in zip(specs, frames):
        if not isinstance(spec, dict) or spec.get("name") not in arrays or not isinstance(spec.get("codec"), str):
            raise ProtocolError(f"bad compressed frame spec {spec!r:.200}")
        size = frame_size(fr)
        if size != spec.get("nbytes") or size > MAX_PACKED_BYTES:
            raise ProtocolError(f"compressed frame of {spec['name']!r}: {size} bytes, spec says {spec.get('nbytes')!r}")
        out.setdefault(spec["codec"], {})[spec["name"]] = (arrays[spec["name"]].dtype, fr)
    return out


def sample_from_slot(msg: Sample, ring: SlotRing, frames: Sequence = (), crops_per_window: int = 1) -> SamplePayload:
    """Build a :class:`SamplePayload` from a worker's ``sample`` header ``msg`` naming a slot of
    ``ring``: the slot's arrays are copied into arrays of the sample's own (after this returns
    the slot may be given back to the worker); ``frames``, the message's frames after the
    header, are its compressed frames (:func:`packed_frames`); ``crops_per_window``: the
    server's, for the sample's id.

    Raises:
        ProtocolError: for a slot out of range, array specs that do not fit a slot, or
            compressed frames that do not match the header.
    """
    views = ring.arrays(msg.slot, list(msg.arrays))
    try:
        packed = packed_frames(msg.packed, frames, views)
        arrays = {k: np.array(v) for k, v in views.items()}
    finally:
        del views
    return SamplePayload(msg.key.sample_id(crops_per_window), msg.meta, arrays, packed)

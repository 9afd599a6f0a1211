"""A batch on the wire: its arrays stacked from samples that may arrive in different widths, and
the array specs and frames of a ``rows`` message, plain or as the workers' compressed frames.

The server's loop (``v2v_server.service.plan_server``) holds a fetch's samples; what its
answer's ``arrays`` list and its frames hold is decided here, next to the rest of the contract:
the array specs (``protocol.encode_arrays``), a compressed array's spec (``codecs.packed_specs``,
read back by ``codecs.decode_batch_arrays``) and the narrowing of voxels (``outputs.narrowest``).
"""
from __future__ import annotations

from typing import Callable, Dict, List, Mapping, Sequence, Tuple

import numpy as np

from v2v_wire.codecs import packed_specs
from v2v_wire.protocol import encode_arrays, output_of


def frame_size(frame) -> int:
    """Bytes of a frame: a ``zmq.Frame`` (its ``buffer``) or any bytes-like object (a numpy array
    counts its bytes, not its first axis)."""
    return len(frame.buffer) if hasattr(frame, "buffer") else memoryview(frame).nbytes


def stack_arrays(parts: Sequence[np.ndarray]) -> np.ndarray:
    """One ``(B, ...)`` array from B same-shape sample arrays, in the dtype that holds every
    one of them (``np.result_type``: voxels that their workers narrowed differently widen to the
    widest; ``outputs.narrowest`` narrows a batch again): a single copy.

    Raises:
        ValueError: for arrays of different shapes.
    """
    dtype = np.result_type(*[p.dtype for p in parts])
    out = np.empty((len(parts),) + parts[0].shape, dtype)
    for i, a in enumerate(parts):
        if a.shape != parts[0].shape:
            raise ValueError(f"sample arrays of shapes {parts[0].shape} and {a.shape} cannot share a batch")
        np.copyto(out[i], a, casting="safe")
    return out


def encode_batch(shapes: Mapping[str, tuple], outputs: Sequence[str], packed: Sequence[Mapping[str, Mapping]],
                 codec: str, stacked: Callable[[], Dict[str, np.ndarray]]) -> Tuple[List[dict], List]:
    """The array specs of a batch header and the frames to send (zero-copy), for the arrays of
    a batch that carry ``outputs`` (``protocol.output_of``).

    Args:
        shapes: each array's name -> the shape of one sample's array, in the batch's array order.
        outputs: the outputs the client asked for.
        packed: per sample in batch order, codec -> array name -> (dtype the worker sent the
            array in, its compressed frame) (empty when no sample has compressed frames).
        codec: the client's compression (``codecs.COMPRESSIONS``).
        stacked: the batch's ``(B, ...)`` arrays by name; called only when some array goes
            plain (every array whose compressed frames every sample has goes as those frames).

    Returns:
        ``(specs, frames)``: per array either its plain spec and one frame
        (``protocol.encode_arrays``) or its compressed spec (``codecs.packed_specs``) and one
        frame per sample, forwarded as the workers sent them.

    Raises:
        ProtocolError: for a stacked array of a dtype not allowed on the wire.
    """
    names = [k for k in shapes if output_of(k) in outputs]
    use = {}
    if codec != "none" and packed:
        for k in names:
            parts = [p.get(codec, {}).get(k) for p in packed]
            if all(q is not None for q in parts):
                use[k] = parts
    plain = {k: v for k, v in stacked().items() if k in names and k not in use} if len(use) < len(names) else {}
    pspecs, pframes = encode_arrays(plain)
    plain_by = {s["name"]: (s, f) for s, f in zip(pspecs, pframes)}
    specs, frames = [], []
    for k in names:
        if k in use:
            parts = use[k]
            dtype = np.result_type(*[d for d, _ in parts]).name
            specs.append(packed_specs(k, dtype, [len(parts)] + list(shapes[k]), codec,
                                      [(d.name, frame_size(f)) for d, f in parts]))
            frames.extend(f for _, f in parts)
        else:
            spec, f = plain_by[k]
            specs.append(spec)
            frames.append(f)
    return specs, frames


__all__ = ["encode_batch", "frame_size", "stack_arrays"]

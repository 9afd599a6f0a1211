"""Per-array compression on the wire: what a worker compresses and a client decompresses.

A reader names it in each fetch (``"compression"``, one of ``COMPRESSIONS``); the server's
workers compress each array of each sample once per codec a fetch asked for in the last 2 minutes
(``pack``; ``plan_server.CODEC_KEEP_S``) and the server's main process forwards those frames by
reference, untouched. A compressed array of a ``rows`` message goes as one frame per row holding
a sample, described in the header's array spec by ``"codec"`` and ``"parts"`` (``[dtype,
compressed bytes]`` per sample, in row order; see ``protocol.py``); :func:`decode_batch_arrays`
turns them back into (B, ...) arrays.

Codecs (measured on real samples, one core, ``python -m bench.wire``; docs/wire.md):

* ``zstd``: Zstandard level 1 (``zstandard``, the reference C library's binding), frames with
  a content checksum (any corruption is an error): voxels 10x smaller, frames 1.9x;
  decompression about 0.9 GB/s (voxels). The choice across hosts.
* ``lz4``: LZ4 block format (``lz4``): voxels 5x, frames 1.6x, at 1.5-2.5x zstd's
  decompression speed: for a trainer host short of CPU on a fast link. The block format has
  no checksum: a malformed block is an error, altered literals are not detected.

The libraries are the ``wire`` extra (``pip install 'v2v[wire]'``), imported on first use.
"""
from __future__ import annotations

import math
from typing import Dict, List, Sequence

import numpy as np

from v2v_wire.protocol import MAX_BATCH_BYTES, WIRE_DTYPES, ProtocolError

#: Compression settings a client may ask for; "none" sends arrays as they are.
COMPRESSIONS = ("none", "lz4", "zstd")
#: Zstandard level of ``zstd`` (1: 10x on voxels, compressing at 0.65 GB/s; level 3 gains 1 % for 25 % more time).
ZSTD_LEVEL = 1

_CODECS: Dict[str, tuple] = {}


class CodecUnavailable(RuntimeError):
    """The library of a codec is not installed (the message says which and how)."""


def _codec(name: str) -> tuple:
    """(compress(bytes-like) -> bytes, decompress(bytes-like, size) -> bytes) of ``name``."""
    c = _CODECS.get(name)
    if c is not None:
        return c
    try:
        if name == "zstd":
            import zstandard

            # with a checksum of the content (XXH64, a few % of the time): a corrupt frame is an error
            comp = zstandard.ZstdCompressor(level=ZSTD_LEVEL, write_checksum=True)
            dec = zstandard.ZstdDecompressor()
            c = (comp.compress, lambda b, n: dec.decompress(b, max_output_size=n))
        elif name == "lz4":
            import lz4.block

            c = (lambda b: lz4.block.compress(b, store_size=False),
                 lambda b, n: lz4.block.decompress(b, uncompressed_size=n))
        else:
            raise ValueError(f"compression must be one of {list(COMPRESSIONS)}, got {name!r}")
    except ImportError:
        lib = {"zstd": "zstandard", "lz4": "lz4"}[name]
        raise CodecUnavailable(f"compression {name!r} needs the {lib} package (pip install 'v2v[wire]')") from None
    _CODECS[name] = c
    return c


def available(name: str) -> bool:
    """True when codec ``name`` can be used on this machine ("none" always can)."""
    if name == "none":
        return True
    try:
        _codec(name)
        return True
    except CodecUnavailable:
        return False


def check_compression(name, field: str = "compression") -> str:
    """``name`` if it is one of ``COMPRESSIONS``.

    Raises:
        ValueError: naming ``field`` otherwise.
    """
    if name not in COMPRESSIONS:
        raise ValueError(f"{field} must be one of {list(COMPRESSIONS)}, got {name!r}")
    return name


def pack(name: str, arrays: Dict[str, np.ndarray]) -> Dict[str, bytes]:
    """Each of ``arrays`` (C-contiguous) compressed with codec ``name`` ("lz4" or "zstd").

    Raises:
        CodecUnavailable: the codec's library is not installed.
    """
    compress = _codec(name)[0]
    return {k: compress(memoryview(np.ascontiguousarray(a)).cast("B")) for k, a in arrays.items()}


def _buffer(frame) -> memoryview:
    return frame.buffer if hasattr(frame, "buffer") else memoryview(frame)


def decode_batch_arrays(specs, frames: Sequence, max_bytes: int = MAX_BATCH_BYTES) -> Dict[str, np.ndarray]:
    """The arrays of a batch message: plain specs take one frame each (``protocol.decode_arrays``:
    read-only zero-copy views); a spec with ``"codec"`` takes one compressed frame per sample
    (``"parts"``: ``[dtype, bytes]`` each), decompressed into a fresh (B, ...) array of the
    spec's dtype (a part of a narrower dtype is widened, as the server's stacking does).

    Raises:
        ProtocolError: naming the array (and part) for a malformed spec, a frame count that does
            not match, an unknown codec, or a part that does not decompress to its declared size
            (a corrupt or truncated frame).
    """
    from v2v_wire.protocol import decode_arrays

    if not isinstance(specs, list):
        raise ProtocolError("header 'arrays' must be a list")
    out: Dict[str, np.ndarray] = {}
    i = 0
    for spec in specs:
        if not isinstance(spec, dict) or "codec" not in spec:
            out.update(decode_arrays([spec], list(frames[i:i + 1]), max_bytes))
            i += 1
            continue
        name, dtype, shape, codec, parts = (spec.get(k) for k in ("name", "dtype", "shape", "codec", "parts"))
        if not isinstance(name, str) or dtype not in WIRE_DTYPES or not isinstance(shape, list) or not shape \
                or len(shape) > 8 or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape):
            raise ProtocolError(f"bad compressed array spec {spec!r:.200}")
        if codec not in COMPRESSIONS or codec == "none":
            raise ProtocolError(f"array {name!r}: unknown codec {codec!r}")
        if not isinstance(parts, list) or len(parts) != shape[0] or not all(
                isinstance(p, list) and len(p) == 2 and p[0] in WIRE_DTYPES and isinstance(p[1], int) for p in parts):
            raise ProtocolError(f"array {name!r}: 'parts' must list [dtype, bytes] for each of its {shape[0]} samples")
        if i + len(parts) > len(frames):
            raise ProtocolError(f"array {name!r}: {len(parts)} compressed frames declared, "
                                f"{len(frames) - i} left in the message")
        dt = np.dtype(dtype)
        row = math.prod(shape[1:])
        if math.prod(shape) * dt.itemsize > max_bytes:
            raise ProtocolError(f"array {name!r}: {dtype}{shape} exceeds {max_bytes} bytes")
        try:
            decompress = _codec(codec)[1]
        except CodecUnavailable as e:
            raise ProtocolError(f"array {name!r}: {e}") from None
        a = np.empty(shape, dt)
        for k, (pdtype, nbytes) in enumerate(parts):
            buf = _buffer(frames[i + k])
            pdt = np.dtype(pdtype)
            if len(buf) != nbytes or not np.can_cast(pdt, dt, "safe"):
                raise ProtocolError(f"array {name!r} part {k}: {len(buf)} bytes of {pdtype}, spec says {nbytes} of "
                                    f"a type that widens to {dtype}")
            want = row * pdt.itemsize
            try:
                raw = decompress(buf, want)
            except Exception as e:  # each library raises its own error type for corrupt input
                raise ProtocolError(f"array {name!r} part {k}: {codec} frame does not decompress "
                                    f"({type(e).__name__}: {str(e)[:120]})") from None
            if len(raw) != want:
                raise ProtocolError(f"array {name!r} part {k}: {codec} frame decompressed to {len(raw)} bytes, "
                                    f"expected {want}")
            np.copyto(a[k], np.frombuffer(raw, pdt).reshape(shape[1:]), casting="safe")
        out[name] = a
        i += len(parts)
    if i != len(frames):
        raise ProtocolError(f"header describes {i} array frames, message has {len(frames)}")
    return out


def packed_specs(name: str, dtype: str, shape: List[int], codec: str, parts: List[tuple]) -> dict:
    """The batch header's spec of a compressed array: ``parts`` = (dtype, bytes) per sample."""
    return {"name": name, "dtype": dtype, "shape": list(shape), "codec": codec,
            "parts": [[d, int(n)] for d, n in parts]}

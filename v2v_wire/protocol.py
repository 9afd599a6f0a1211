"""Wire protocol shared by server, workers and clients.

Every message is one ZeroMQ multipart message: frame 0 is a msgpack header (a map with at
least ``v`` = protocol version and ``type``); array payloads follow as one raw frame each,
described in the header's ``arrays`` list as ``{"name", "dtype", "shape"}``. No pickle
anywhere: headers are size-checked before msgpack decoding, and array frames are checked
against their declared dtype and shape before use.

Message types (``PROTOCOL_VERSION``; typed and checked in ``plan_messages`` and
``worker_messages``):

* client -> server: ``plan_ask``; ``fetch`` (epoch, positions ``start``..``stop``, outputs,
  compression, the plan identity it reads under); a fleet's reader's ``manifest_ask`` (offset)
  and ``make`` (epoch, video, its samples' ordinals). A client message is at most
  ``MAX_CLIENT_MSG`` bytes (a fetch is a few hundred, a make a few KiB at most).
* server -> client: ``plan`` (identity, samples per epoch, stream info: also ``shard``,
  ``corpus`` and ``recipe`` fingerprints), ``rows`` (ids, padding flags, params, one frame per
  array for the rows holding a sample), ``refused`` (one line, and a code a reader acts on:
  ``plan_messages.REFUSALS``), ``error`` (to a client of an older protocol, in the version it
  reads the line at: ``plan_messages.old_client_answer``).
* worker -> server: ``ready``, ``sample``, ``done`` (windows, ``failed`` {window: reason},
  error, the exception that stopped the pass as ``failure``); server -> worker: ``task``,
  ``slot``, ``stop``.

Array forms: each array's dtype, shape and float conversion are in ``outputs.ARRAYS`` (one
``ArraySpec`` per array; ``polarity_counts`` is served only to clients that ask). A tracked flow
option's flow travels as ``flow_grid`` float32 (B, L, 2, n, n), its values at the tracking
grid's points, n per side (the stream info's ``flow_grid_points``, 0 for an option sending dense
flow; ``ARRAY_OUTPUT``: it carries the output ``flow``; the dense field is bilinear between
them with ``flow_grid_taps`` over the stream info's ``crop_size``). Compression (optional): a
fetch may say ``"compression": "lz4" | "zstd"`` (``codecs.COMPRESSIONS``; refused in one line
when the server lacks the library); an array the workers compressed is then sent as one frame
per sample, its spec carrying ``"codec"`` and ``"parts"`` (``[dtype, bytes]`` per sample;
``codecs.decode_batch_arrays``). Workers get the codecs to make in each ``task`` (``codecs``)
and send the compressed frames after their array frames, listed in the sample header's
``packed``.
"""
from __future__ import annotations

import math
from typing import Dict, List, Sequence, Tuple

import msgpack
import numpy as np

# the per-output array contract lives in ``outputs`` (one ArraySpec per array); re-exported here
from v2v_wire.outputs import ARRAY_OUTPUT, DEFAULT_OUTPUTS, OUTPUTS, narrow_int_dtype, output_of  # noqa: F401
from v2v_wire.push_names import OLDER_PROTOCOL

#: The wire protocol's version: 12 is delivery by plan (``plan_messages``: ``plan_ask`` / ``plan``,
#: ``fetch`` / ``rows`` / ``refused``, a refusal carrying its code) with a fleet's reads (``make`` /
#: ``rows``, ``manifest_ask`` / ``manifest``); a peer of another version is refused in one line
#: (:func:`version_problem`).
PROTOCOL_VERSION = 12
#: Largest accepted header, bytes (checked before msgpack decoding).
MAX_HEADER_BYTES = 1 << 20
#: Largest message a client may send the server, bytes. A client sends ``plan_ask``,
#: ``manifest_ask``, ``fetch`` and ``make``, each of a fixed set of fields: the largest fetch (every
#: output, every int at its largest, the plan identity's two 16-digit fingerprints) packs to 244
#: bytes, the largest make (a path of ``plan_messages.MAX_MAKE_PATH`` bytes and
#: ``plan_messages.MAX_MAKE_SAMPLES`` ordinals of 9 bytes at most) to under 11 KiB. 16 KiB bounds
#: what any peer makes the server decode, and echo in a refusal (``tests/test_plan_refusals.py``).
#: The server's socket takes up to twice this (ZMQ_MAXMSGSIZE): a larger message up to that is
#: refused in one line, ZeroMQ cuts the connection of a peer sending more.
MAX_CLIENT_MSG = 16384
#: Largest message or array frame the server sends, bytes: a batch message as the client's socket
#: accepts it (ZMQ_MAXMSGSIZE), a batch's decoded arrays, and a worker's compressed frame.
MAX_BATCH_BYTES = 1 << 31
#: dtypes allowed on the wire.
WIRE_DTYPES = ("int8", "int16", "int32", "uint8", "float16", "float32")



class ProtocolError(ValueError):
    """A malformed, oversized or wrong-version message."""


def is_loopback(endpoint: str) -> bool:
    """True for ipc://, inproc:// and tcp:// endpoints on 127.0.0.0/8, localhost or ::1: a peer
    on this host (the server's security check; the client's choice of no compression)."""
    scheme, _, rest = endpoint.partition("://")
    if scheme in ("ipc", "inproc"):
        return True
    host = rest.rsplit(":", 1)[0].strip("[]")
    if ";" in host:  # tcp://source;dest form: judge the address bound
        host = host.split(";", 1)[0]
    return host in ("localhost", "::1") or host.startswith("127.")


def is_ipv6(endpoint: str) -> bool:
    """Whether a ZeroMQ endpoint names an IPv6 address (``tcp://[::1]:5555``): its socket
    needs ``zmq.IPV6`` set, on both ends."""
    return endpoint.startswith("tcp://[")


def check_outputs(outputs, field: str = "outputs") -> Tuple[str, ...]:
    """The outputs a configuration, a dataset or a fetch asks for, checked against ``OUTPUTS``
    and put in its (wire) order.

    Args:
        outputs: output names (a sequence, or one string: a name or a comma list such as
            ``"voxels,frames"``).
        field: what the caller calls them, named in the error (``outputs``, ``field 'outputs'``).

    Returns:
        the names, each once, in the order of ``OUTPUTS``.

    Raises:
        ValueError: naming ``field``, the allowed outputs and what was given, when it is empty
            or names something else.
    """
    if isinstance(outputs, str):
        outputs = [s.strip() for s in outputs.split(",") if s.strip()]
    try:
        given = list(outputs)
        ok = bool(given) and all(isinstance(o, str) and o in OUTPUTS for o in given)
    except TypeError:  # not iterable
        given, ok = outputs, False
    if not ok:
        raise ValueError(f"{field} must be a non-empty list from {list(OUTPUTS)}, got {given!r}")
    return tuple(o for o in OUTPUTS if o in given)


def pack(header: dict) -> bytes:
    """msgpack-encode a header dict, adding the protocol version ``v``."""
    h = dict(header)
    h.setdefault("v", PROTOCOL_VERSION)
    return msgpack.packb(h, use_bin_type=True)


def bounded_unpackb(buf, max_bytes: int, max_array_len: int = 1 << 20, max_map_len: int = 1 << 16,
                    max_containers: int = 0, error: type = None) -> object:
    """msgpack-decode ``buf`` (bytes or memoryview) within bounds, the one msgpack decoder for
    messages from peers: its size is checked before decoding, strings/binaries are at most
    ``max_bytes``, arrays/maps at most ``max_array_len`` / ``max_map_len`` elements, no ext
    types, and (when ``max_containers`` > 0) at most that many arrays and maps in all.

    Raises:
        ProtocolError (or the subclass ``error``): oversized, malformed, or over any bound.
    """
    error = error or ProtocolError
    if len(buf) > max_bytes:
        raise error(f"message of {len(buf)} bytes exceeds {max_bytes}")
    hooks = {}
    if max_containers > 0:
        count = [0]

        def hook(obj):
            count[0] += 1
            if count[0] > max_containers:
                raise error(f"more than {max_containers} arrays/maps in one message")
            return obj

        hooks = {"list_hook": hook, "object_hook": hook}
    try:
        return msgpack.unpackb(bytes(buf), raw=False, strict_map_key=True, use_list=True,
                               max_bin_len=max_bytes, max_str_len=max_bytes, max_ext_len=0,
                               max_array_len=max_array_len, max_map_len=max_map_len, **hooks)
    except error:
        raise
    except Exception as e:  # msgpack raises several types (ValueError, ExtraData, StackError, ...)
        raise error(f"not valid msgpack within bounds: {type(e).__name__}: {str(e)[:200]}") from None


def unpack(frame, expect_version: int = PROTOCOL_VERSION, max_bytes: int = MAX_HEADER_BYTES) -> dict:
    """Decode and check a header frame (bytes, memoryview or zmq.Frame) with
    :func:`bounded_unpackb` (``max_bytes`` bounds its size).

    Raises:
        ProtocolError: oversized, not msgpack, not a map with ``type``, or wrong version.
    """
    h = bounded_unpackb(frame.buffer if hasattr(frame, "buffer") else frame, max_bytes)
    if not isinstance(h, dict) or not isinstance(h.get("type"), str):
        raise ProtocolError("header must be a map with a string 'type'")
    problem = version_problem(h.get("v"), expect_version)
    if problem:
        raise ProtocolError(problem)
    return h


def version_problem(version, expect_version: int = PROTOCOL_VERSION) -> str:
    """Why a peer's message of protocol ``version`` is not read here (one line), or ``""``."""
    if version == expect_version:
        return ""
    older = isinstance(version, int) and version < expect_version
    return (f"protocol version {version!r:.20}, expected {expect_version}: the peer runs "
            f"{'an older' if older else 'another'} v2v; install the same version on both sides"
            + (f" ({OLDER_PROTOCOL})" if older else ""))


_TAPS: Dict[tuple, tuple] = {}


def flow_grid_taps(n: int, size: int) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The bilinear weights that make a tracked option's dense flow from its grid, along one
    axis of ``size`` pixels: the one definition the server's expansion
    (``flowgrid.expand_grids``) and the client's (``v2v_client.flowgrid``) both read.

    The grid's ``n`` points along an axis sit at ``k (size - 1) / (n - 1)`` px (corners
    included); pixel ``x`` lies at grid coordinate ``u = x (n - 1) / (size - 1)`` (float64) and
    takes the hat functions ``max(0, 1 - |u - k|)`` (rounded to float32) of the two grid points
    around it: ``first[x]`` (clamped to ``n - 2``) with weight ``w0[x]`` and ``first[x] + 1``
    with ``w1[x]``. So the dense value at pixel (y, x) of a grid field ``g`` (n, n) is, in
    float32 with one rounding per product and sum, ``a0[y] t[i0[y]] + a1[y] t[i0[y] + 1]``
    at column x, where ``t[i] = b0[x] g[i, j0[x]] + b1[x] g[i, j0[x] + 1]`` (rows ``i0, a0,
    a1`` = taps of the height, columns ``j0, b0, b1`` = taps of the width).

    Args:
        n: grid points per side (>= 2).
        size: pixels along the axis (>= 1).

    Returns:
        ``first`` int64 (size,), ``w0`` and ``w1`` float32 (size,); read-only, cached.

    Raises:
        ValueError: for ``n < 2`` or ``size < 1``.
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 2 or \
            isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 1:
        raise ValueError(f"flow grid taps need n >= 2 grid points and size >= 1 px, got n={n!r}, size={size!r}")
    key = (int(n), int(size))
    t = _TAPS.get(key)
    if t is None:
        u = np.arange(size, dtype=np.float64) * ((n - 1) / max(size - 1, 1))
        hats = np.maximum(0.0, 1.0 - np.abs(u[:, None] - np.arange(n)[None, :])).astype(np.float32)
        first = np.minimum(np.argmax(hats > 0, axis=1), n - 2)
        rows = np.arange(size)
        t = (first.astype(np.int64), hats[rows, first].copy(), hats[rows, first + 1].copy())
        for a in t:
            a.setflags(write=False)
        _TAPS[key] = t
    return t


def encode_arrays(arrays: Dict[str, np.ndarray]) -> Tuple[List[dict], List[np.ndarray]]:
    """Array specs for the header and the C-contiguous arrays to send as raw frames.

    Raises:
        ProtocolError: for a dtype not in ``WIRE_DTYPES``.
    """
    specs, frames = [], []
    for name, a in arrays.items():
        a = np.ascontiguousarray(a)
        if a.dtype.name not in WIRE_DTYPES:
            raise ProtocolError(f"array {name!r} has dtype {a.dtype}, not allowed on the wire")
        specs.append({"name": name, "dtype": a.dtype.name, "shape": list(a.shape)})
        frames.append(a)
    return specs, frames




def array_spec(spec) -> Tuple[str, np.dtype, List[int]]:
    """``(name, dtype, shape)`` of one entry of a header's ``arrays`` list (a map with ``name``,
    a ``dtype`` of ``WIRE_DTYPES`` and a ``shape`` of at most 8 whole numbers >= 0, booleans
    refused): the one check of an array spec, for socket frames, shared-memory slots and batch
    files alike.

    Raises:
        ProtocolError: naming the malformed field, with the spec (cut to 120 characters).
    """
    if not isinstance(spec, dict):
        raise ProtocolError("array spec must be a map")
    name, dtype, shape = spec.get("name"), spec.get("dtype"), spec.get("shape")
    if not isinstance(name, str) or dtype not in WIRE_DTYPES:
        raise ProtocolError(f"bad array spec {spec!r:.120}")
    if not isinstance(shape, list) or len(shape) > 8 or not all(
            isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape):
        raise ProtocolError(f"bad shape in array spec {spec!r:.120}")
    return name, np.dtype(dtype), shape


def decode_arrays(specs, frames: Sequence, max_bytes: int = MAX_BATCH_BYTES) -> Dict[str, np.ndarray]:
    """Read-only numpy views of raw frames (zero-copy), checked against ``specs``.

    Args:
        specs: the header's ``arrays`` list.
        frames: the message frames after the header (bytes or zmq.Frame).
        max_bytes: largest accepted array, bytes.

    Raises:
        ProtocolError: when counts, names, dtypes, shapes or sizes do not match.
    """
    if not isinstance(specs, list) or len(specs) != len(frames):
        raise ProtocolError(f"header lists {len(specs) if isinstance(specs, list) else '?'} arrays, "
                            f"message has {len(frames)} frames")
    out = {}
    for spec, fr in zip(specs, frames):
        name, dt, shape = array_spec(spec)
        buf = fr.buffer if hasattr(fr, "buffer") else memoryview(fr)
        need = math.prod(shape) * dt.itemsize  # Python ints: a shape that overflows int64 is refused, not wrapped
        if need > max_bytes or need != len(buf):
            raise ProtocolError(f"array {name!r}: {len(buf)} bytes, spec {dt.name}{shape} needs {need}")
        out[name] = np.frombuffer(buf, dtype=dt).reshape(shape)
    return out

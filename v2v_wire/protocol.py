"""Wire protocol shared by server, workers and clients.

Every message is one ZeroMQ multipart message: frame 0 is a msgpack header (a map with at
least ``v`` = protocol version and ``type``); array payloads follow as one raw frame each,
described in the header's ``arrays`` list as ``{"name", "dtype", "shape"}``. No pickle
anywhere: headers are size-checked before msgpack decoding, and array frames are checked
against their declared dtype and shape before use.

Message types (protocol 9; client messages are decoded and schema-checked by ``messages.py``):

* client -> server: ``hello`` (outputs, credits = how many batches it may hold,
  consumer id, ``instance`` (the reader process's token: a consumer is read by one instance at a
  time), ``hello_id`` (echoed in the welcome; increasing over an instance's hellos, by its host's
  monotonic clock: an older one than the consumer's last is refused ``fenced``), optional DDP ``rank``/``world_size``/``group``, ``resume``:
  ``completed_epoch``, ``delivered`` {epoch: the sample ids, one video per line as
  ``path#w1,w2,...`` (``ids.compact_ids``)}, ``batches`` {epoch: batches yielded}, optional
  ``supersedes`` [[consumer, rank, completed epoch], ...]: the consumers a state gathered from every
  rank of a job speaks for, resumed at another world size, each with the epoch its state completed;
  optional ``queued`` {batch id: epoch}: a DataLoader worker's granted batches waiting in the loader's
  queues (their ids are in ``delivered``): their epochs stay open for the connection until it acks them;
  optional
  ``ends_on_drained``: a DataLoader worker that ends its iteration on ``drained``, so it is sent
  no batch after it), ``ack``
  (batch ids; frees exactly those slots), ``hold`` (batch ids the client
  asks to be granted before it hands them on: answered by ``granted``), ``released`` (batch ids given back), ``credit`` (widen the
  window), ``heartbeat`` (``hello_id``: the session's latest hello), ``bye``. A client message
  is at most ``MAX_CLIENT_MSG`` bytes (the
  welcome repeats it as ``max_hello_bytes``); a larger one up to twice that gets an ``error``.
* server -> client: ``welcome`` (stream info: also ``shard``, ``corpus`` and ``recipe``
  fingerprints), ``batch``, ``revoke`` (batch ids), ``granted`` (batch ids of a ``hold`` that are
  the consumer's for good: the client hands a batch on only once granted; ``refused``: those no
  longer the client's), ``heartbeat``, ``epoch_done`` (epoch;
  ``batches`` per rank for a DDP group), ``drained`` (a bounded stream has nothing left for this
  client unless a batch held elsewhere comes back), ``end``, ``shutdown``, ``error`` (``code``
  ``dropped`` / ``unknown_client``: discard what you hold, say hello again (an ``unknown_client``
  answering a heartbeat names its ``hello_id``); ``claimed``: another
  live reader holds the consumer; ``fenced``: a newer connection of this reader took it over; ``resume``: the server can tell the resume state is false;
  ``group``: the DDP group is read at another world size).
* worker -> server: ``ready``, ``sample``, ``done`` (windows, ``failed`` {window: reason},
  error, the exception that stopped the pass as ``failure``); server -> worker: ``task``,
  ``slot``, ``stop`` (typed and checked in ``worker_messages``).

Array forms: each array's dtype, shape and float conversion are in ``outputs.ARRAYS`` (one
``ArraySpec`` per array; ``polarity_counts`` is served only to clients that ask). A tracked flow option's flow travels as ``flow_grid`` float32 (B, L, 2, n, n), its
values at the tracking grid's points, n per side (the welcome's ``flow_grid_points``, 0 for
an option sending dense flow; ``ARRAY_OUTPUT``: it carries the output ``flow``; the
dense field is bilinear between them with ``flow_grid_taps`` over the welcome's
``crop_size``). Compression (optional): a hello may say ``"compression": "lz4" | "zstd"``
(``codecs.COMPRESSIONS``; the server answers ``error`` code ``compression`` when it lacks the
library); a batch array the workers compressed is then sent as one frame per sample, its spec
carrying ``"codec"`` and ``"parts"`` (``[dtype, bytes]`` per sample; ``codecs.decode_batch_arrays``);
other arrays of the same batch may still be plain. Workers get the codecs to make in each
``task`` (``codecs``) and send the compressed frames after their array frames, listed in the
sample header's ``packed``.

Same-host hand-off (optional fields): a hello may say
``"shm": true``; a server bound to ``ipc://`` then names its batch directory in the welcome
(``info.shm_dir``, else null) and may send a batch with no array frames and
``"shm": {"file": "b<N>", "gen": <generation>, "offsets": [<byte offset per array>]}`` next to
the usual ``arrays`` specs: the arrays lie in that file of that directory (see
``v2v_server.service.shm.BatchDir``; ``v2v_client.handoff`` reads and checks them). Batches that are not
one buffer's rows, and every batch to other clients, still carry frames.
"""
from __future__ import annotations

import math
import re
from typing import Dict, List, Sequence, Tuple

import msgpack
import numpy as np

# the per-output array contract lives in ``outputs`` (one ArraySpec per array); re-exported here
from v2v_wire.outputs import ARRAY_OUTPUT, DEFAULT_OUTPUTS, OUTPUTS, narrow_int_dtype, output_of  # noqa: F401

#: Version 10: a plan server's ``rows`` carry the arrays of the rows holding a sample only
#: (``plan_messages.Rows``).
PROTOCOL_VERSION = 10
#: Largest accepted header, bytes (checked before msgpack decoding).
MAX_HEADER_BYTES = 1 << 20
#: Largest message a client may send the server, bytes; a resume hello lists the sample ids a
#: trainer already has, grouped per video (a few bytes per id: millions fit). The server's
#: socket takes up to twice this (ZMQ_MAXMSGSIZE), so a larger hello gets a clear error.
MAX_CLIENT_MSG = 16 * 1024 * 1024
#: Largest message or array frame the server sends, bytes: a batch message as the client's socket
#: accepts it (ZMQ_MAXMSGSIZE), a batch's decoded arrays, and a worker's compressed frame.
MAX_BATCH_BYTES = 1 << 31
#: dtypes allowed on the wire.
WIRE_DTYPES = ("int8", "int16", "int32", "uint8", "float16", "float32")

#: Same-host hand-off (``v2v_server.service.shm.BatchDir`` writes, ``v2v_client.handoff`` reads):
#: bytes at the start of a batch-buffer file before the first array (the generation, uint64 LE);
BATCH_FILE_HEADER = 64
#: names of batch-buffer files inside a server's batch directory (never anything a client chose);
BATCH_FILE_RE = re.compile(r"b[0-9]{1,18}")
#: names of the servers' private batch directories under /dev/shm: ``v2v-batches-<pid>-<random>``.
BATCH_DIR_RE = re.compile(r"v2v-batches-([0-9]{1,10})-[A-Za-z0-9_]{1,32}")


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
    """The outputs a configuration, a dataset or a hello asks for, checked against ``OUTPUTS``
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
    if h.get("v") != expect_version:
        raise ProtocolError(f"protocol version {h.get('v')!r}, expected {expect_version}")
    return h


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


#: Most batches one client may hold in flight (its ``credits``): what a client may ask for and the
#: ceiling of a server's ``max_credits`` (a typo like ``100000`` is an error, not an OOM).
MAX_CREDITS = 1024


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

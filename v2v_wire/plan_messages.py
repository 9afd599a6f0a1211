"""The messages of serving by plan (docs/plan.md), both ways, typed and checked at the edge.

A client asks a server what it serves (:class:`PlanAsk`, answered by :class:`PlanInfo`: the plan's
identity, samples per epoch and the stream's shapes), then fetches positions of an epoch
(:class:`Fetch`), each answered by :class:`Rows` (a header, rows in position order, ``padding``
true for a row without a sample; then the arrays of the rows with a sample only: a padding row
costs no payload) or :class:`Refused` (one line: another plan, or a batch over the limit). The
server keeps no record of either: a client that hears nothing asks again, and a late answer to a
request it no longer waits for is dropped.

Every decoder raises only ``messages.WireError`` (a ``ProtocolError``) naming the field.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import List, Optional, Tuple

from v2v_wire.codecs import check_compression
from v2v_wire.messages import WireError, bounded_unpackb
from v2v_wire.plan import PlanIdentity, PlanMismatch
from v2v_wire.protocol import PROTOCOL_VERSION, check_outputs

__all__ = ["PlanAsk", "PlanInfo", "Fetch", "Rows", "Refused", "PushClientMessage", "ServedByPush", "MAX_FETCH_ROWS",
           "decode_plan_client", "plan_server_message"]

#: Most positions one fetch may name (a batch of one rank at one step).
MAX_FETCH_ROWS = 4096
_MAX_INT = 2 ** 62


def _int(h: dict, name: str, lo: int = 0, hi: int = _MAX_INT) -> int:
    v = h.get(name)
    if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
        raise WireError(f"{h.get('type')}: field {name!r} must be an int in {lo}..{hi}, got {v!r:.80}")
    return v


def _optional_int(h: dict, name: str) -> Optional[int]:
    return None if h.get(name) is None else _int(h, name)


@dataclass(frozen=True)
class PlanAsk:
    """Client -> server: what do you serve?"""

    def to_wire(self) -> dict:
        return {"type": "plan_ask"}


class ServedByPush(WireError):
    """The server answered in push delivery's words: it was started with ``--delivery push``."""


@dataclass(frozen=True)
class PlanInfo:
    """Server -> client: the plan it serves and the stream's shapes.

    Attributes:
        plan: the plan's identity, with the server's word on plans of the same listing it
            served before (``PlanIdentity.changes``: sent as ``changes``, a map of str to str).
        samples: samples per epoch (the manifest's slots x crops per window), or None while
            the server has not learned every video's slots (the plan unfolds as it decodes).
        stream: the recipe's shapes and outputs (``sequence_length``, ``num_bins``,
            ``crop_size``, ``outputs``, ``flow_dtype``, ...), as plain values.
    """

    plan: PlanIdentity
    samples: Optional[int]
    stream: dict = field(default_factory=dict)

    def to_wire(self) -> dict:
        return {"type": "plan", "plan": self.plan.to_dict(), "samples": self.samples, "stream": self.stream,
                "changes": dict(self.plan.changes)}

    @classmethod
    def from_wire(cls, h: dict) -> "PlanInfo":
        try:
            plan = PlanIdentity.from_dict(h.get("plan"))
        except PlanMismatch as e:
            raise WireError(f"plan: {e}") from None
        if not isinstance(h.get("stream"), dict):
            raise WireError("plan: field 'stream' must be a map")
        changes = h.get("changes", {})
        if not isinstance(changes, dict) or not all(isinstance(k, str) and isinstance(v, str)
                                                    for k, v in changes.items()):
            raise WireError("plan: field 'changes' must be a map of strings to strings")
        return cls(replace(plan, changes=changes), _optional_int(h, "samples"), h["stream"])


@dataclass(frozen=True)
class Fetch:
    """Client -> server: positions ``start .. stop - 1`` of ``epoch`` under ``plan``, with the
    arrays of ``outputs``, compressed with ``compression`` (``codecs.COMPRESSIONS``; absent:
    ``"none"``); ``request`` is echoed in the answer."""

    request: int
    epoch: int
    start: int
    stop: int
    outputs: Tuple[str, ...]
    plan: PlanIdentity
    compression: str = "none"

    def to_wire(self) -> dict:
        return {"type": "fetch", "request": self.request, "epoch": self.epoch, "start": self.start,
                "stop": self.stop, "outputs": list(self.outputs), "plan": self.plan.to_dict(),
                "compression": self.compression}

    @classmethod
    def from_wire(cls, h: dict) -> "Fetch":
        start = _int(h, "start")
        stop = _int(h, "stop", start + 1, start + MAX_FETCH_ROWS)
        try:
            outputs = check_outputs(h.get("outputs"), "fetch: field 'outputs'")
            plan = PlanIdentity.from_dict(h.get("plan"))
            compression = check_compression(h.get("compression", "none"), "fetch: field 'compression'")
        except (ValueError, PlanMismatch) as e:
            raise WireError(str(e)) from None
        return cls(_int(h, "request"), _int(h, "epoch", 0, 2 ** 31 - 1), start, stop, outputs, plan, compression)


@dataclass(frozen=True)
class Rows:
    """Server -> client: the answer to fetch ``request``: rows for positions ``start`` .. of
    ``epoch``, each with its sample id (None for a row past the epoch's end), ``padding``,
    ``params`` (the sample's parameters, or why the row holds none) and the arrays' specs (the
    frames follow the header, ``codecs.decode_batch_arrays``). The arrays hold the rows with a
    sample only, in row order (``(samples in it, ...)``; ``(0, ...)`` for rows of padding only):
    a padding row costs no payload, and the reader puts zeros in its place; ``samples``: the
    epoch's samples once the server knows them (None before: a reader of a plan still unfolding
    learns the epoch's end from it)."""

    request: int
    epoch: int
    start: int
    sample_ids: List[Optional[str]]
    padding: List[bool]
    params: List[dict]
    arrays: List[dict]
    samples: Optional[int] = None

    def to_wire(self) -> dict:
        return {"type": "rows", "request": self.request, "epoch": self.epoch, "start": self.start,
                "sample_ids": self.sample_ids, "padding": self.padding, "params": self.params, "arrays": self.arrays,
                "samples": self.samples}

    @classmethod
    def from_wire(cls, h: dict) -> "Rows":
        ids, padding, params, arrays = (h.get(k) for k in ("sample_ids", "padding", "params", "arrays"))
        n = len(ids) if isinstance(ids, list) else -1
        if n < 1 or not all(i is None or isinstance(i, str) for i in ids):
            raise WireError("rows: field 'sample_ids' must be a non-empty list of strings or nil")
        if not isinstance(padding, list) or len(padding) != n or not all(isinstance(p, bool) for p in padding):
            raise WireError(f"rows: field 'padding' must be {n} booleans")
        if not isinstance(params, list) or len(params) != n or not all(isinstance(p, dict) for p in params):
            raise WireError(f"rows: field 'params' must be {n} maps")
        if not isinstance(arrays, list):
            raise WireError("rows: field 'arrays' must be a list of array specs")
        return cls(_int(h, "request"), _int(h, "epoch"), _int(h, "start"), ids, padding, params, arrays,
                   _optional_int(h, "samples"))


@dataclass(frozen=True)
class Refused:
    """Server -> client: fetch ``request`` (-1: the message named none) is refused; ``message``
    says why in one line (another plan, a malformed fetch)."""

    request: int
    message: str

    def to_wire(self) -> dict:
        return {"type": "refused", "request": self.request, "message": self.message}

    @classmethod
    def from_wire(cls, h: dict) -> "Refused":
        if not isinstance(h.get("message"), str):
            raise WireError("refused: field 'message' must be a string")
        return cls(_int(h, "request", -1), h["message"])


#: What a push client (``V2VPushDataset``) sends (``messages.parse_client``).
PUSH_CLIENT_TYPES = ("hello", "ack", "released", "hold", "credit", "heartbeat", "bye")


class PushClientMessage(WireError):
    """A push client's message (:data:`PUSH_CLIENT_TYPES`) reached a server serving by plan."""


def decode_plan_client(frame, max_bytes: int):
    """A client's message to a server serving by plan: :class:`PlanAsk` or :class:`Fetch`.

    Raises:
        WireError: oversized, not msgpack within bounds, another protocol version, an unknown
            type or a bad field (naming it); :class:`PushClientMessage` for a push client's.
    """
    h = bounded_unpackb(frame.buffer if hasattr(frame, "buffer") else frame, max_bytes)
    if not isinstance(h, dict):
        raise WireError("a message must be a map")
    if h.get("v") != PROTOCOL_VERSION:
        raise WireError(f"protocol version {h.get('v')!r}, expected {PROTOCOL_VERSION}")
    kind = h.get("type")
    if kind == "plan_ask":
        return PlanAsk()
    if kind == "fetch":
        return Fetch.from_wire(h)
    if kind in PUSH_CLIENT_TYPES:
        raise PushClientMessage(f"a push client's {kind!r}")
    raise WireError(f"unknown message type {kind!r:.40} (a server serving by plan takes plan_ask and fetch)")


def plan_server_message(h: dict):
    """A server's message (an unpacked header) to a client reading by plan: :class:`PlanInfo`,
    :class:`Rows` or :class:`Refused`.

    Raises:
        WireError: an unknown type or a bad field (naming it).
    """
    kind = h.get("type")
    for cls, name in ((PlanInfo, "plan"), (Rows, "rows"), (Refused, "refused")):
        if kind == name:
            return cls.from_wire(h)
    if kind == "error":  # a push server's answer (messages.parse_client refused a plan_ask)
        raise ServedByPush(f"a server delivering by push answered: {str(h.get('message'))[:200]}; read it with "
                           "v2v_client.V2VPushDataset, or start it without --delivery push")
    raise WireError(f"unknown message type {kind!r:.40} from a server serving by plan (is it serving by plan?)")

"""The messages between a server and its readers (docs/delivery.md), both ways, typed and checked
at the edge.

A client asks a server what it serves (:class:`PlanAsk`, answered by :class:`PlanInfo`: the plan's
identity, samples per epoch and the stream's shapes), then fetches positions of an epoch
(:class:`Fetch`), each answered by :class:`Rows` (a header, rows in position order, ``padding``
true for a row without a sample; then the arrays of the rows with a sample only: a padding row
costs no payload) or :class:`Refused` (one line, and a code from :data:`REFUSALS`: another plan,
a batch over the limit, ...). The server keeps no record of either: a client that hears nothing
asks again, and a late answer to a request it no longer waits for is dropped.

Every decoder raises only :class:`WireError` (a ``ProtocolError``) naming the field, and bounds
what one message may cost: its size before any decoding, every array to ``MAX_ARRAY_LEN``
elements and map to ``MAX_MAP_LEN`` pairs, the containers to ``MAX_CONTAINERS`` (counted while
decoding), so a peer gains nothing by nesting or widening. :class:`BadPeers` rate-limits the log
lines about misbehaving peers and bans a peer that keeps sending garbage for a while.

A client of an older protocol (push delivery's handshake, or an older plan reader's) gets one
``error`` line it reads (:func:`old_client_answer`).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Dict, List, Optional, Tuple

from v2v_wire.codecs import check_compression
from v2v_wire.plan import PlanIdentity, PlanMismatch
from v2v_wire.protocol import PROTOCOL_VERSION, ProtocolError, check_outputs, version_problem
from v2v_wire.protocol import bounded_unpackb as _bounded_unpackb

__all__ = ["PlanAsk", "PlanInfo", "Fetch", "Make", "ManifestAsk", "ManifestPart", "Rows", "Refused", "REFUSALS",
           "WireError", "OldClient", "BadPeers", "MAX_FETCH_ROWS", "MANIFEST_PART", "MAX_MAKE_PATH",
           "MAX_MAKE_SAMPLES", "MAX_INSTANCE", "MAX_HOST_NAME", "Moved", "Withdraw",
           "decode_plan_client", "plan_server_message", "old_client_answer"]

#: Largest element count of any array in a message.
MAX_ARRAY_LEN = 4096
#: Largest number of pairs in any map of a message.
MAX_MAP_LEN = 256
#: Largest number of arrays + maps in one message.
MAX_CONTAINERS = 512


class WireError(ProtocolError):
    """A message that is oversized, not msgpack, too wide or deep, or has a field of the wrong
    type or range (the message names the field)."""


def bounded_unpackb(buf, max_bytes: int) -> object:
    """msgpack-decode ``buf`` with the bounds above (``protocol.bounded_unpackb``).

    Raises:
        WireError: oversized, malformed, or over any bound.
    """
    return _bounded_unpackb(buf, max_bytes, MAX_ARRAY_LEN, MAX_MAP_LEN, MAX_CONTAINERS, WireError)

#: Most positions one fetch may name (a batch of one rank at one step), and samples one make may.
MAX_FETCH_ROWS = 4096
#: Videos one manifest part lists (within ``MAX_ARRAY_LEN``).
MANIFEST_PART = 4096
#: Longest video path a make names, bytes as UTF-8 (a corpus path longer than this is read by
#: position, ``fetch``), and most samples it asks (a reader asks more in several makes).
MAX_MAKE_PATH, MAX_MAKE_SAMPLES = 1024, 1024
#: Longest instance name a server says (``PlanInfo.instance``): a UUID's 32 hex digits with room.
MAX_INSTANCE = 64
#: Most decode workers a server runs (``v2v-serve --workers``; a typo like 2000 is an error, not a
#: fork bomb), and so says in its stream info (:attr:`PlanInfo.workers`).
MAX_WORKERS = 256
#: Longest host name a make's ``route`` or a ``moved`` names (an endpoint, ``tcp://host:port``).
MAX_HOST_NAME = 512
_MAX_INT = 2 ** 62


def _int(h: dict, name: str, lo: int = 0, hi: int = _MAX_INT) -> int:
    v = h.get(name)
    if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
        raise WireError(f"{h.get('type')}: field {name!r} must be an int in {lo}..{hi}, got {v!r:.80}")
    return v


def _optional_rate(h: dict, what: str) -> Optional[float]:
    """Field ``rate`` of message ``what``: a finite number >= 0, or nil.

    Raises:
        WireError: anything else, naming the message and the field."""
    rate = h.get("rate")
    if rate is not None and (isinstance(rate, bool) or not isinstance(rate, (int, float)) or not rate >= 0
                             or rate == float("inf")):
        raise WireError(f"{what}: field 'rate' must be a finite number >= 0 or nil")
    return None if rate is None else float(rate)


def _optional_int(h: dict, name: str) -> Optional[int]:
    return None if h.get(name) is None else _int(h, name)


def _asked(h: dict) -> Tuple[Tuple[str, ...], PlanIdentity, str]:
    """A fetch's or a make's ``outputs``, ``plan`` and ``compression`` (absent: ``"none"``), checked.

    Raises:
        WireError: a bad field, naming the message's type and the field."""
    kind = h.get("type")
    try:
        outputs = check_outputs(h.get("outputs"), f"{kind}: field 'outputs'")
        plan = PlanIdentity.from_dict(h.get("plan"))
        compression = check_compression(h.get("compression", "none"), f"{kind}: field 'compression'")
    except (ValueError, PlanMismatch) as e:
        raise WireError(str(e)) from None
    return outputs, plan, compression


@dataclass(frozen=True)
class PlanAsk:
    """Client -> server: what do you serve?"""

    def to_wire(self) -> dict:
        return {"type": "plan_ask"}


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
        instance: the server process's own name, drawn at its start (1 to :data:`MAX_INSTANCE`
            characters; None: not said): two endpoints answering with one instance are one host
            under two names (``tcp://localhost:P`` and ``tcp://127.0.0.1:P``), which a fleet's
            reader reads once.
        queued: the samples every reader's makes ask of the server and it has not made (None:
            not said, an older server): a fleet's reader pings a host with a ``plan_ask`` and
            routes by this queue (``v2v_wire.fleet.Router.heard``).
        rate: the server's decode capacity in samples/s, as :class:`Rows` says it (None: not
            measured yet, or an older server): a reader that joins a fleet at work, or that
            pings a host, knows it before asking it anything.
        withdraws: the server takes :class:`Withdraw` (False: an older server, never sent one).

    Its ``stream``'s ``feed.workers``, where said, is an int from 1 to :data:`MAX_WORKERS`
    (:attr:`workers`).
    """

    plan: PlanIdentity
    samples: Optional[int]
    stream: dict = field(default_factory=dict)
    instance: Optional[str] = None
    queued: Optional[int] = None
    rate: Optional[float] = None
    withdraws: bool = False

    @property
    def workers(self) -> int:
        """The server's decode workers, as its stream's ``feed.workers`` says (1 where not said)."""
        return int((self.stream.get("feed") or {}).get("workers") or 1)

    def to_wire(self) -> dict:
        return {"type": "plan", "plan": self.plan.to_dict(), "samples": self.samples, "stream": self.stream,
                "changes": dict(self.plan.changes), "instance": self.instance, "queued": self.queued,
                "rate": self.rate, "withdraws": self.withdraws}

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
        feed = h["stream"].get("feed", {})
        workers = feed.get("workers") if isinstance(feed, dict) else None
        if not isinstance(feed, dict) or workers is not None and (
                isinstance(workers, bool) or not isinstance(workers, int) or not 1 <= workers <= MAX_WORKERS):
            raise WireError(f"plan: field 'stream.feed.workers' must be nil or an int from 1 to {MAX_WORKERS}, "
                            f"got {workers if isinstance(feed, dict) else feed!r:.80}")
        instance = h.get("instance")
        if instance is not None and (not isinstance(instance, str) or not 0 < len(instance) <= MAX_INSTANCE):
            raise WireError(f"plan: field 'instance' must be nil or a string of 1 to {MAX_INSTANCE} characters, "
                            f"got {instance!r:.80}")
        withdraws = h.get("withdraws", False)
        if not isinstance(withdraws, bool):
            raise WireError(f"plan: field 'withdraws' must be a bool, got {withdraws!r:.80}")
        return cls(replace(plan, changes=changes), _optional_int(h, "samples"), h["stream"], instance,
                   _optional_int(h, "queued"), _optional_rate(h, "plan"), withdraws)


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
        outputs, plan, compression = _asked(h)
        return cls(_int(h, "request"), _int(h, "epoch", 0, 2 ** 31 - 1), start, stop, outputs, plan, compression)


@dataclass(frozen=True)
class Make:
    """Client -> server: the samples ``ordinals`` (``SampleKey.ordinal``) of ``video`` in
    ``epoch`` under ``plan``, with the arrays of ``outputs`` compressed with ``compression``; or
    (``ordinals`` None) only the video's windows, which a reader's plan unfolds with (the host
    decodes the video to learn them, and keeps its samples for the makes that follow). A reader of
    a fleet asks each video of the host it routes it to (``v2v_wire.fleet``); the answer is
    :class:`Rows` in the order asked (no row for ``None``), with ``windows``. ``position``: the
    position of the epoch by which the video's decode should start, the first that needs it less
    what the fleet reads while one worker decodes it (``v2v_wire.fleet.Router.start_by``): a host
    decodes the videos made for in that order, whoever asked (a copy asked of a second host for a
    step that waits goes first there).
    ``route``: a fleet's reader asks each video of its arbiter (``v2v_wire.fleet.Router.arbiter``),
    which answers :class:`Moved` where the video is made elsewhere: ``""``, make it here unless a
    reader had it placed elsewhere; a host's name, place it there unless this host holds the
    video or placed it already; None (an older reader's; a copy, or the host told): make it here.
    ``move``: the reader moves the video off this host, which said a rate at which it would make
    it late (``v2v_wire.fleet.Router.overdue``): unless its decode started here, it is placed at
    ``route`` with every reader's make of it waiting here (each answered :class:`Moved`). An
    older server ignores it (and makes the video)."""

    request: int
    epoch: int
    video: str
    ordinals: Optional[Tuple[int, ...]]
    outputs: Tuple[str, ...]
    plan: PlanIdentity
    compression: str = "none"
    position: int = 0
    route: Optional[str] = None
    move: bool = False

    def to_wire(self) -> dict:
        return {"type": "make", "request": self.request, "epoch": self.epoch, "video": self.video,
                "ordinals": None if self.ordinals is None else list(self.ordinals), "outputs": list(self.outputs),
                "plan": self.plan.to_dict(), "compression": self.compression, "position": self.position,
                "route": self.route, "move": self.move}

    @classmethod
    def from_wire(cls, h: dict) -> "Make":
        video, ordinals = h.get("video"), h.get("ordinals")
        if not isinstance(video, str) or not video or len(video.encode()) > MAX_MAKE_PATH:
            raise WireError(f"make: field 'video' must be a non-empty path of at most {MAX_MAKE_PATH} bytes")
        if ordinals is not None and (not isinstance(ordinals, list) or not 0 < len(ordinals) <= MAX_MAKE_SAMPLES or
                                     not all(isinstance(o, int) and not isinstance(o, bool) and 0 <= o < _MAX_INT
                                             for o in ordinals)):
            raise WireError(f"make: field 'ordinals' must be nil or 1 to {MAX_MAKE_SAMPLES} ints >= 0")
        route, move = h.get("route"), h.get("move", False)
        if route is not None and (not isinstance(route, str) or len(route) > MAX_HOST_NAME):
            raise WireError(f"make: field 'route' must be nil or a host name of at most {MAX_HOST_NAME} characters, "
                            f"got {route!r:.80}")
        if not isinstance(move, bool):
            raise WireError(f"make: field 'move' must be a bool, got {move!r:.80}")
        outputs, plan, compression = _asked(h)
        return cls(_int(h, "request"), _int(h, "epoch", 0, 2 ** 31 - 1), video,
                   None if ordinals is None else tuple(ordinals), outputs, plan, compression, _int(h, "position"),
                   route, move)


@dataclass(frozen=True)
class Moved:
    """Server -> client: make ``request`` is made at ``host`` (a reader placed its video there
    first, :attr:`Make.route`): the reader asks it of that host (``route`` None)."""

    request: int
    host: str

    def to_wire(self) -> dict:
        return {"type": "moved", "request": self.request, "host": self.host}

    @classmethod
    def from_wire(cls, h: dict) -> "Moved":
        host = h.get("host")
        if not isinstance(host, str) or not 0 < len(host) <= MAX_HOST_NAME:
            raise WireError(f"moved: field 'host' must be a host name of 1 to {MAX_HOST_NAME} characters, "
                            f"got {host!r:.80}")
        return cls(_int(h, "request"), host)


@dataclass(frozen=True)
class Withdraw:
    """Client -> server: this client's make ``request`` is not needed any more (a reader of a
    fleet had its samples from another host first: a backup request's, ``v2v_wire.fleet.Router.copy``);
    dropped while it waits, so a host does not decode a video no reader will read. No answer: a
    make answered or started already goes on. Sent only to a server whose :class:`PlanInfo`
    says ``withdraws`` (an older one refuses the type)."""

    request: int

    def to_wire(self) -> dict:
        return {"type": "withdraw", "request": self.request}

    @classmethod
    def from_wire(cls, h: dict) -> "Withdraw":
        return cls(_int(h, "request"))


@dataclass(frozen=True)
class ManifestAsk:
    """Client -> server: the manifest's videos from index ``offset`` on (:class:`ManifestPart`):
    a reader of a fleet computes the plan itself (``v2v_wire.plan.EpochPlan``)."""

    offset: int = 0

    def to_wire(self) -> dict:
        return {"type": "manifest_ask", "offset": self.offset}

    @classmethod
    def from_wire(cls, h: dict) -> "ManifestAsk":
        return cls(_int(h, "offset"))


@dataclass(frozen=True)
class ManifestPart:
    """Server -> client: up to :data:`MANIFEST_PART` of the manifest's videos from ``offset`` on,
    each with its tag and its slots where the server knows them (None: not yet); ``total``: the
    manifest's videos; ``crops_per_window``: its K; ``tagged``: whether the manifest names its
    videos' tags (``v2v_wire.plan.Manifest.tags``: its fingerprint covers them)."""

    offset: int
    total: int
    crops_per_window: int
    videos: List[str]
    tags: List[Optional[str]]
    slots: List[Optional[int]]
    tagged: bool = True

    def to_wire(self) -> dict:
        return {"type": "manifest", "offset": self.offset, "total": self.total,
                "crops_per_window": self.crops_per_window, "videos": self.videos, "tags": self.tags,
                "slots": self.slots, "tagged": self.tagged}

    @classmethod
    def from_wire(cls, h: dict) -> "ManifestPart":
        videos, tags, slots = h.get("videos"), h.get("tags"), h.get("slots")
        if not isinstance(videos, list) or not all(isinstance(v, str) and v for v in videos):
            raise WireError("manifest: field 'videos' must be a list of paths")
        n = len(videos)
        if not isinstance(tags, list) or len(tags) != n or not all(t is None or isinstance(t, str) for t in tags):
            raise WireError(f"manifest: field 'tags' must be {n} strings or nil")
        if not isinstance(slots, list) or len(slots) != n or not all(
                x is None or (isinstance(x, int) and not isinstance(x, bool) and x >= 0) for x in slots):
            raise WireError(f"manifest: field 'slots' must be {n} ints >= 0 or nil")
        if not isinstance(h.get("tagged"), bool):
            raise WireError("manifest: field 'tagged' must be a boolean")
        return cls(_int(h, "offset"), _int(h, "total"), _int(h, "crops_per_window", 1), videos, tags, slots,
                   h["tagged"])


@dataclass(frozen=True)
class Rows:
    """Server -> client: the answer to fetch ``request``: rows for positions ``start`` .. of
    ``epoch``, each with its sample id (None for a row past the epoch's end), ``padding``,
    ``params`` (the sample's parameters, or why the row holds none) and the arrays' specs (the
    frames follow the header, ``codecs.decode_batch_arrays``). The arrays hold the rows with a
    sample only, in row order (``(samples in it, ...)``; ``(0, ...)`` for rows of padding only):
    a padding row costs no payload, and the reader puts zeros in its place; ``samples``: the
    epoch's samples once the server knows them (None before: a reader of a plan still unfolding
    learns the epoch's end from it); ``windows``: the answer to a :class:`Make`'s video's
    windows (its slots), None for a fetch's; ``rate``: the server's decode capacity in samples/s
    (``v2v_wire.fleet.RateMeter``; None before it is measured), what a fleet's reader weighs it by;
    ``queued``: the samples every reader's makes ask of the server and it has not made, a make's
    answer's (None for a fetch's, or from an older server), what a fleet's readers route by
    (``v2v_wire.fleet.Router.heard``)."""

    request: int
    epoch: int
    start: int
    sample_ids: List[Optional[str]]
    padding: List[bool]
    params: List[dict]
    arrays: List[dict]
    samples: Optional[int] = None
    windows: Optional[int] = None
    rate: Optional[float] = None
    queued: Optional[int] = None

    def to_wire(self) -> dict:
        return {"type": "rows", "request": self.request, "epoch": self.epoch, "start": self.start,
                "sample_ids": self.sample_ids, "padding": self.padding, "params": self.params, "arrays": self.arrays,
                "samples": self.samples, "windows": self.windows, "rate": self.rate, "queued": self.queued}

    @classmethod
    def from_wire(cls, h: dict) -> "Rows":
        ids, padding, params, arrays = (h.get(k) for k in ("sample_ids", "padding", "params", "arrays"))
        n = len(ids) if isinstance(ids, list) else -1
        if n < (0 if h.get("windows") is not None else 1) or not all(i is None or isinstance(i, str) for i in ids):
            raise WireError("rows: field 'sample_ids' must be a non-empty list of strings or nil (empty: a "
                            "make's answer for a video of no window)")
        if not isinstance(padding, list) or len(padding) != n or not all(isinstance(p, bool) for p in padding):
            raise WireError(f"rows: field 'padding' must be {n} booleans")
        if not isinstance(params, list) or len(params) != n or not all(isinstance(p, dict) for p in params):
            raise WireError(f"rows: field 'params' must be {n} maps")
        if not isinstance(arrays, list):
            raise WireError("rows: field 'arrays' must be a list of array specs")
        return cls(_int(h, "request"), _int(h, "epoch"), _int(h, "start"), ids, padding, params, arrays,
                   _optional_int(h, "samples"), _optional_int(h, "windows"), _optional_rate(h, "rows"),
                   _optional_int(h, "queued"))


#: Why a server refuses a message (``Refused.code``), each asking something else of the reader:
#: ``"plan"``: the fetch names another plan than the one served (the reader's position or its
#: servers are wrong; the reader raises ``PlanMismatch``); ``"bad"``: a message that cannot be read
#: (malformed, oversized, a field out of range); ``"outputs"``: an output the server does not serve
#: (``--outputs``); ``"compression"``: a codec whose library the server lacks; ``"too_big"``: a batch
#: with an array over ``MAX_BATCH_BYTES``; ``"make"``: a make naming a video the plan lacks or a
#: sample past the video's windows.
REFUSALS = ("plan", "bad", "outputs", "compression", "too_big", "make")


@dataclass(frozen=True)
class Refused:
    """Server -> client: fetch ``request`` (-1: the message named none) is refused; ``message``
    says why in one line, ``code`` which of :data:`REFUSALS` it is (what a reader acts on: the
    line is for people)."""

    request: int
    message: str
    code: str

    def to_wire(self) -> dict:
        return {"type": "refused", "request": self.request, "message": self.message, "code": self.code}

    @classmethod
    def from_wire(cls, h: dict) -> "Refused":
        if not isinstance(h.get("message"), str):
            raise WireError("refused: field 'message' must be a string")
        if h.get("code") not in REFUSALS:
            raise WireError(f"refused: field 'code' must be one of {list(REFUSALS)}, got {h.get('code')!r:.40}")
        return cls(_int(h, "request", -1), h["message"], h["code"])


class OldClient(WireError):
    """A message of an older protocol version (a client of an older v2v: push delivery's, or an
    older plan reader's ``plan_ask`` or ``fetch``); ``version``: the one it speaks; ``kind``: its
    message type."""

    def __init__(self, message: str, version: int, kind: object = None):
        super().__init__(message)
        self.version = version
        self.kind = kind


#: The message types of a plan reader (:class:`PlanAsk`, :class:`Fetch`), at every version.
_PLAN_READER_TYPES = ("plan_ask", "fetch")


def old_client_answer(e: OldClient) -> dict:
    """The one-line ``error`` an :class:`OldClient` is answered with. A push client reads
    ``error``'s ``message`` at its own version, so it is told at that version; an older plan
    reader checks a message's version before its type, so it is told at this server's version
    and names both versions itself."""
    version = PROTOCOL_VERSION if e.kind in _PLAN_READER_TYPES else e.version
    return {"v": version, "type": "error", "code": "version", "message": f"this v2v server: {e}"}


def decode_plan_client(frame, max_bytes: int):
    """A client's message to a server: :class:`PlanAsk`, :class:`Fetch`, :class:`Make`,
    :class:`Withdraw` or :class:`ManifestAsk`.

    Raises:
        WireError: oversized, not msgpack within bounds, another protocol version, an unknown
            type or a bad field (naming it); :class:`OldClient` for an older protocol version's.
    """
    h = bounded_unpackb(frame.buffer if hasattr(frame, "buffer") else frame, max_bytes)
    if not isinstance(h, dict):
        raise WireError("a message must be a map")
    v = h.get("v")
    if v != PROTOCOL_VERSION:
        if isinstance(v, int) and not isinstance(v, bool) and 0 < v < PROTOCOL_VERSION:
            raise OldClient(version_problem(v), v, h.get("type"))
        raise WireError(version_problem(v))
    kind = h.get("type")
    if kind == "plan_ask":
        return PlanAsk()
    if kind == "fetch":
        return Fetch.from_wire(h)
    if kind == "make":
        return Make.from_wire(h)
    if kind == "manifest_ask":
        return ManifestAsk.from_wire(h)
    if kind == "withdraw":
        return Withdraw.from_wire(h)
    raise WireError(f"unknown message type {kind!r:.40} (a server takes plan_ask, fetch, make, withdraw and "
                    "manifest_ask)")


def plan_server_message(h: dict):
    """A server's message (an unpacked header) to a client reading by plan: :class:`PlanInfo`,
    :class:`Rows`, :class:`ManifestPart`, :class:`Refused` or :class:`Moved`.

    Raises:
        WireError: an unknown type or a bad field (naming it).
    """
    kind = h.get("type")
    for cls, name in ((PlanInfo, "plan"), (Rows, "rows"), (ManifestPart, "manifest"), (Refused, "refused"),
                      (Moved, "moved")):
        if kind == name:
            return cls.from_wire(h)
    raise WireError(f"unknown message type {kind!r:.40} from the server")


class BadPeers:
    """Rate-limited complaints about peers, and bans for repeat offenders (pure: ``now`` is given).

    Args:
        log_per_s: log lines allowed per second over all peers (a token bucket of ``burst``).
        strikes: bad messages within ``window_s`` after which a peer is banned for ``ban_s``.
        max_peers: peers remembered (oldest forgotten first), so the table stays bounded.
    """

    def __init__(self, log_per_s: float = 2.0, burst: int = 10, strikes: int = 3, window_s: float = 10.0,
                 ban_s: float = 60.0, max_peers: int = 10000):
        self.log_per_s, self.burst = log_per_s, burst
        self.strikes, self.window_s, self.ban_s, self.max_peers = strikes, window_s, ban_s, max_peers
        self.tokens = float(burst)
        self.last = None
        self.suppressed = 0
        self.peers: Dict[bytes, list] = {}  # ident -> [first strike time, strikes, banned until]

    def banned(self, ident: bytes, now: float) -> bool:
        p = self.peers.get(ident)
        return p is not None and now < p[2]

    def strike(self, ident: bytes, now: float) -> Tuple[bool, bool]:
        """Count one bad message. Returns ``(log_it, banned_now)``."""
        p = self.peers.get(ident)
        if p is None or now - p[0] > self.window_s:
            p = [now, 0, 0.0]
        self.peers.pop(ident, None)
        self.peers[ident] = p
        while len(self.peers) > self.max_peers:
            self.peers.pop(next(iter(self.peers)))
        p[1] += 1
        banned_now = p[1] >= self.strikes and now >= p[2]
        if banned_now:
            p[2] = now + self.ban_s
        if self.last is not None:
            self.tokens = min(self.burst, self.tokens + (now - self.last) * self.log_per_s)
        self.last = now
        if self.tokens >= 1:
            self.tokens -= 1
            return True, banned_now
        self.suppressed += 1
        return False, banned_now

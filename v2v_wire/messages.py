"""Client -> server messages: bounded decoding and typed, schema-checked messages.

Every client message is decoded by :func:`decode_client`, which never raises anything but
:class:`WireError` (a ``ProtocolError``) and bounds what one message may cost:

* its size (``max_bytes``) before any decoding;
* every array to ``MAX_ARRAY_LEN`` elements and map to ``MAX_MAP_LEN`` pairs (msgpack
  ``max_array_len`` / ``max_map_len``), every string to the message size;
* the total number of containers (``MAX_CONTAINERS``, counted while decoding), which with the
  per-container bound caps the objects one message can create, and the nesting (msgpack's
  fixed parser stack, and the container count).

So a peer gains nothing by nesting or widening: a few MB cost a few MB and milliseconds. The
resume state's sample ids therefore travel as one newline-joined string per epoch.

:class:`BadPeers` rate-limits the log lines about misbehaving peers and bans a peer that keeps
sending garbage for a while (its messages are then dropped before decoding).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Dict, FrozenSet, Optional, Tuple

from v2v_wire.codecs import COMPRESSIONS
from v2v_wire.fields import show
from v2v_wire.ids import SampleKey, compact_ids, expand_ids, parse_sample_ids
from v2v_wire.protocol import OUTPUTS, PROTOCOL_VERSION, ProtocolError, check_outputs
from v2v_wire.protocol import bounded_unpackb as _bounded_unpackb

#: Largest element count of any array in a client message (acks name at most ``max_credits`` ids).
MAX_ARRAY_LEN = 4096
#: Largest number of pairs in any map of a client message (epochs in a resume state).
MAX_MAP_LEN = 256
#: Largest number of arrays + maps in one client message.
MAX_CONTAINERS = 512


class WireError(ProtocolError):
    """A client message that is oversized, not msgpack, too wide or deep, or has a field of
    the wrong type or range (the message names the field)."""


class PlanClientMessage(WireError):
    """A plan reader's message (``plan_ask``, ``fetch``: ``V2VStreamDataset``) reached a push server."""


def bounded_unpackb(buf, max_bytes: int) -> object:
    """msgpack-decode ``buf`` with the bounds above (``protocol.bounded_unpackb``).

    Raises:
        WireError: oversized, malformed, or over any bound.
    """
    return _bounded_unpackb(buf, max_bytes, MAX_ARRAY_LEN, MAX_MAP_LEN, MAX_CONTAINERS, WireError)


# ---------------------------------------------------------------------- typed messages
#: Largest epoch number a resume state may name (a 32-bit signed int).
MAX_EPOCH = 2 ** 31 - 1

#: A consumer a gathered resume state speaks for, ``("g:<group>", rank)`` or ``("c:<consumer id>", 0)``,
#: and the last epoch that consumer's own state called complete.
ConsumerKey = Tuple[str, int, int]


@dataclass(frozen=True)
class Resume:
    """A trainer's position: ``completed_epoch``; per open epoch the sample keys it already
    has (``delivered``) and the batches it yielded (``batches``, for DDP padding); the consumers
    it speaks for besides its own (``supersedes``: a state gathered from every rank of a job
    resumed at another world size, each with its completed epoch); the servers its ids were granted by (``origins``);
    a DataLoader worker's granted batches waiting in the loader's queues (``queued``: batch id -> epoch, their
    ids in ``delivered``; docs/delivery.md, "DataLoader workers")."""

    completed_epoch: int = -1
    delivered: Dict[int, FrozenSet[SampleKey]] = field(default_factory=dict)
    batches: Dict[int, int] = field(default_factory=dict)
    supersedes: Tuple[ConsumerKey, ...] = ()
    origins: Tuple[str, ...] = ()  # the servers (welcome info's ``server``) that granted its ids
    queued: Dict[int, int] = field(default_factory=dict)


@dataclass(frozen=True)
class ResumeIds:
    """A resume state as a client holds and sends it: ``completed_epoch``; per open epoch the
    sample ids its training loop got (``delivered``, strings: the client does not know the
    server's crops per window) and the batches it yielded (``batches``). The server reads it back
    as :class:`Resume` (``queued``: at most ``MAX_MAP_LEN`` batches, as there)."""

    completed_epoch: int = -1
    delivered: Dict[int, Tuple[str, ...]] = field(default_factory=dict)
    batches: Dict[int, int] = field(default_factory=dict)
    supersedes: Tuple[ConsumerKey, ...] = ()
    origins: Tuple[str, ...] = ()
    queued: Dict[int, int] = field(default_factory=dict)

    def to_wire(self) -> dict:
        h = {"completed_epoch": self.completed_epoch,
             "delivered": {str(e): compact_ids(ids) for e, ids in self.delivered.items()},
             "batches": {str(e): n for e, n in self.batches.items()}}
        if self.supersedes:
            h["supersedes"] = [list(k) for k in self.supersedes]
        if self.origins:
            h["origins"] = list(self.origins)
        if self.queued:
            h["queued"] = {str(b): e for b, e in self.queued.items()}
        return h


@dataclass(frozen=True)
class Hello:
    """A client introduces itself (docs/delivery.md, "Who may say hello"): the outputs it wants, its
    credits, the consumer it reads as and where that consumer stands (``resume``: a
    :class:`ResumeIds` when a client builds it, the :class:`Resume` the server reads), its DDP
    position, and how batches reach it."""

    outputs: Tuple[str, ...]
    credits: int
    consumer: str = ""
    resume: Resume = Resume()
    group: Optional[str] = None
    rank: int = 0
    world_size: int = 1
    hello_id: int = 0  # echoed in the welcome, so the client can tell old-session messages apart
    shm: bool = False  # same host: send batches as references into the server's shared-memory files
    compression: str = "none"  # codecs.COMPRESSIONS: how this client wants arrays sent over the socket
    ends_on_drained: bool = False  # a DataLoader worker: its iteration ends on ``drained`` (sent nothing after it)
    instance: str = ""  # the reader process's token (docs/delivery.md, "Who may say hello")

    def to_wire(self) -> dict:
        """The message a client sends (``resume`` must be a :class:`ResumeIds`)."""
        h = {"type": "hello", "outputs": list(self.outputs), "credits": self.credits, "consumer": self.consumer,
             "resume": self.resume.to_wire(), "hello_id": self.hello_id}
        if self.world_size > 1:
            h.update(rank=self.rank, world_size=self.world_size, group=self.group)
        if self.shm:
            h["shm"] = True
        if self.compression != "none":
            h["compression"] = self.compression
        if self.ends_on_drained:
            h["ends_on_drained"] = True
        if self.instance:
            h["instance"] = self.instance
        return h


@dataclass(frozen=True)
class Ack:
    """The training loop received these batches (granted first): the server forgets them and
    frees their slots. An ack of a batch held but not granted grants it too (a client that never
    says ``hold``)."""

    batch_ids: Tuple[int, ...]

    def to_wire(self) -> dict:
        return {"type": "ack", "batch_ids": list(self.batch_ids)}


@dataclass(frozen=True)
class Released:
    """The client gives these batches back unused (revoked, torn, of a completed epoch, or
    granted and never handed on): they go to the queue again."""

    batch_ids: Tuple[int, ...]

    def to_wire(self) -> dict:
        return {"type": "released", "batch_ids": list(self.batch_ids)}


@dataclass(frozen=True)
class Hold:
    """The client asks for these batches to be granted (``stream_messages.Granted``) before it
    hands them on: a granted batch is the consumer's (delivered, no lease, never sent
    elsewhere); an ack follows when the training loop receives it, or ``released``."""

    batch_ids: Tuple[int, ...]

    def to_wire(self) -> dict:
        return {"type": "hold", "batch_ids": list(self.batch_ids)}


@dataclass(frozen=True)
class Credit:
    """The client's new credit (batches it may have in flight)."""

    credit: int

    def to_wire(self) -> dict:
        return {"type": "credit", "credit": self.credit}


@dataclass(frozen=True)
class Heartbeat:
    """The client is alive; ``hello_id``: its session's latest hello (0: none yet), named again
    in an ``unknown_client`` answer (docs/delivery.md, "Messages")."""

    hello_id: int = 0

    def to_wire(self) -> dict:
        return {"type": "heartbeat", "hello_id": self.hello_id}


@dataclass(frozen=True)
class Bye:
    """The client closes its connection: what it holds unacknowledged goes back."""

    def to_wire(self) -> dict:
        return {"type": "bye"}


def _int(h: dict, name: str, lo: int, hi: int, default=None) -> int:
    v = h.get(name, default)
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise WireError(f"field {name!r} must be an integer in [{lo}, {hi}], got {show(v)}")
    return v


def _ids(h: dict, name: str) -> Tuple[int, ...]:
    v = h.get(name)
    if not isinstance(v, list) or not all(isinstance(b, int) and not isinstance(b, bool) and 0 <= b < 2 ** 63
                                          for b in v):
        raise WireError(f"field {name!r} must be a list of batch ids (integers >= 0), got {show(v)}")
    return tuple(v)


#: ``bound(video)``: how many samples ``video`` gives under the server's recipe (``sys.maxsize``
#: while unknown), or None when the server does not serve it (a fan-in's other shards: its ids
#: are skipped unread).
Bound = Callable[[str], Optional[int]]


def _parse_keys(text: str, crops_per_window: int = 1, bound: Optional[Bound] = None) -> FrozenSet[SampleKey]:
    """The keys of a resume epoch's ``ids.compact_ids`` text. With ``bound``, a line of a video the
    server does not serve is skipped unread, and one naming more ids than its video gives is an
    error before any of them is parsed: the cost stays linear in the text, and the memory in what
    the server serves."""
    if bound is None:
        return frozenset(parse_sample_ids(expand_ids(text), crops_per_window))
    keep = []
    for line in text.split("\n"):
        video = line.rpartition("#")[0]
        n = bound(video)
        if n is None:
            continue
        ids = line.count(",") + 1
        if ids > n:
            raise WireError(f"field 'resume.delivered' names {ids} sample ids of {video[:80]!r}, which gives {n}")
        keep.append(line)
    return frozenset(parse_sample_ids(expand_ids("\n".join(keep)), crops_per_window)) if keep else frozenset()


def _epoch(e) -> bool:
    """``e`` is an epoch number as a map key: ASCII digits naming 0 .. ``MAX_EPOCH``."""
    return isinstance(e, str) and e.isascii() and e.isdigit() and len(e) <= 10 and int(e) <= MAX_EPOCH


def _batch_id(b) -> bool:
    """``b`` is a batch id as a map key: ASCII digits naming 0 .. 2**63 - 1 (a server's ids start at its
    start time in ns: docs/delivery.md, "Transport")."""
    return isinstance(b, str) and b.isascii() and b.isdigit() and len(b) <= 19 and int(b) < 2 ** 63


def _supersedes(v) -> Tuple[ConsumerKey, ...]:
    def number(x, lo: int, hi: int) -> bool:
        return isinstance(x, int) and not isinstance(x, bool) and lo <= x < hi

    if not isinstance(v, list) or not all(isinstance(x, list) and len(x) == 3 and isinstance(x[0], str)
                                          and x[0][:2] in ("g:", "c:") and 2 < len(x[0]) <= 130
                                          and number(x[1], 0, 65536) and number(x[2], -1, MAX_EPOCH + 1) for x in v):
        raise WireError(f"field 'resume.supersedes' must list [consumer, rank, completed epoch] triples, "
                        f"got {show(v)}")
    return tuple((name, rank, done) for name, rank, done in v)


def _resume(v, crops_per_window: int = 1, bound: Optional[Bound] = None) -> Resume:
    if v is None:
        return Resume()
    if not isinstance(v, dict):
        raise WireError(f"field 'resume' must be a map, got {show(v)}")
    completed = _int(v, "completed_epoch", -1, MAX_EPOCH, -1)
    delivered, batches = {}, {}
    d = v.get("delivered", {})
    if not isinstance(d, dict):
        raise WireError(f"field 'resume.delivered' must be a map, got {show(d)}")
    for e, ids in d.items():
        if not _epoch(e):
            raise WireError(f"field 'resume.delivered' keys must be epoch numbers (0 .. {MAX_EPOCH}), got {show(e)}")
        if not isinstance(ids, str):
            raise WireError(f"field 'resume.delivered[{e}]' must be a string of sample ids (ids.compact_ids)")
        delivered[int(e)] = _parse_keys(ids, crops_per_window, bound)
    bt = v.get("batches", {})
    if not isinstance(bt, dict):
        raise WireError(f"field 'resume.batches' must be a map, got {show(bt)}")
    for e, n in bt.items():
        if not _epoch(e) or isinstance(n, bool) or not isinstance(n, int) or not 0 <= n < 2 ** 31:
            raise WireError("field 'resume.batches' must map epoch numbers to counts")
        batches[int(e)] = n
    origins = v.get("origins", [])
    if not isinstance(origins, list) or len(origins) > 16 or not all(isinstance(o, str) and 0 < len(o) <= 64
                                                                      for o in origins):
        raise WireError(f"field 'resume.origins' must list at most 16 server ids, got {show(origins)}")
    queued = v.get("queued", {})
    if not isinstance(queued, dict) or not all(_batch_id(b) and type(e) is int and 0 <= e <= MAX_EPOCH
                                                 for b, e in queued.items()):
        raise WireError(f"field 'resume.queued' must map batch ids to epoch numbers, got {show(queued)}")
    return Resume(completed, delivered, batches, _supersedes(v.get("supersedes", [])), tuple(origins),
                  {int(b): int(e) for b, e in queued.items()})


def parse_client(h: dict, max_credits: int, crops_per_window: int = 1, bound: Optional[Bound] = None) -> object:
    """Check a decoded client header against the schema of its ``type`` (resume ids are read
    with the server's ``crops_per_window``, see ``ids.py``, and its videos' ``bound``: see
    :data:`Bound`; None reads them all).

    Returns one of :class:`Hello`, :class:`Ack`, :class:`Released`, :class:`Hold`,
    :class:`Credit`, :class:`Heartbeat`, :class:`Bye`.

    Raises:
        WireError: unknown type, wrong version, or a field of the wrong type or range.
    """
    if not isinstance(h, dict) or not isinstance(h.get("type"), str):
        raise WireError("message must be a map with a string 'type'")
    if h.get("v") != PROTOCOL_VERSION or isinstance(h.get("v"), bool):
        raise WireError(f"protocol version {show(h.get('v'))}, expected {PROTOCOL_VERSION}")
    kind = h["type"]
    if kind == "hello":
        outs = h.get("outputs")
        try:
            outs = check_outputs(outs if isinstance(outs, list) else None, "field 'outputs'")
        except ValueError:
            raise WireError(f"field 'outputs' must be a non-empty list from {list(OUTPUTS)}, "
                            f"got {show(outs)}") from None
        credits = _int(h, "credits", 1, 1 << 20)
        if credits > max_credits:
            raise WireError(f"field 'credits' is {credits}; this server allows at most {max_credits} batches in "
                            f"flight per client")
        consumer = h.get("consumer", "")
        if not isinstance(consumer, str) or len(consumer) > 128:
            raise WireError(f"field 'consumer' must be a string of at most 128 characters, got {show(consumer)}")
        group = h.get("group")
        if group is not None and (not isinstance(group, str) or len(group) > 128):
            raise WireError(f"field 'group' must be a string of at most 128 characters, got {show(group)}")
        world = _int(h, "world_size", 1, 65536, 1)
        rank = _int(h, "rank", 0, world - 1, 0)
        shm = h.get("shm", False)
        if not isinstance(shm, bool):
            raise WireError(f"field 'shm' must be true or false, got {show(shm)}")
        compression = h.get("compression", "none")
        if compression not in COMPRESSIONS:
            raise WireError(f"field 'compression' must be one of {list(COMPRESSIONS)}, got {show(compression)}")
        ends = h.get("ends_on_drained", False)
        if not isinstance(ends, bool):
            raise WireError(f"field 'ends_on_drained' must be true or false, got {show(ends)}")
        instance = h.get("instance", "")
        if not isinstance(instance, str) or len(instance) > 64:
            raise WireError(f"field 'instance' must be a string of at most 64 characters, got {show(instance)}")
        return Hello(outs, credits, consumer, _resume(h.get("resume"), crops_per_window, bound),
                     group, rank, world, _int(h, "hello_id", 0, 2 ** 62, 0), shm, compression, ends, instance)
    if kind == "ack":
        return Ack(_ids(h, "batch_ids"))
    if kind == "released":
        return Released(_ids(h, "batch_ids"))
    if kind == "hold":
        return Hold(_ids(h, "batch_ids"))
    if kind == "credit":
        return Credit(_int(h, "credit", 0, 1 << 20))
    if kind == "heartbeat":
        return Heartbeat(_int(h, "hello_id", 0, 2 ** 62, 0))
    if kind == "bye":
        return Bye()
    if kind in ("plan_ask", "fetch"):
        raise PlanClientMessage(f"a plan reader's {kind!r}")
    raise WireError(f"unknown message type {show(kind)}")


def decode_client(frame, max_bytes: int, max_credits: int, crops_per_window: int = 1,
                  bound: Optional[Bound] = None) -> object:
    """Bounded decoding + schema check of one client frame (bytes, memoryview or zmq.Frame;
    ``bound``: see :func:`parse_client`).

    Raises:
        WireError: for anything but a well-formed message of a known type.
    """
    buf = frame.buffer if hasattr(frame, "buffer") else frame
    return parse_client(bounded_unpackb(buf, max_bytes), max_credits, crops_per_window, bound)


# ---------------------------------------------------------------------- misbehaving peers
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

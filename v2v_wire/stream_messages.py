"""Server -> client messages: small frozen dataclasses, built by the server and checked at the
client's edge.

The server answers a hello with :class:`Welcome`, sends each batch's header as :class:`Batch`
(its arrays follow as frames, or lie in the server's batch file on the same host), asks
batches back with :class:`Revoke`, and says :class:`EpochDone`, :class:`Drained`,
:class:`End`, :class:`Heartbeat`, :class:`Shutdown` and :class:`ServerError`. Each message's
``to_wire()`` is the msgpack header (``protocol.pack`` adds the version), and
:func:`stream_message` reads a decoded header (``protocol.unpack``) back by its ``type``,
checking every field: a missing or ill-typed one raises :class:`StreamMessageError` naming
the message and the field. Array specs and shared-memory references are checked where the
arrays are read (``protocol.decode_batch_arrays``, ``v2v_client.handoff``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple, Union

from v2v_wire.fields import FieldReader, show
from v2v_wire.protocol import ProtocolError


class StreamMessageError(ProtocolError):
    """A server -> client message with a field missing or of the wrong type or range (the
    error names the message and the field)."""


_read = FieldReader(StreamMessageError)
_bad, _int, _list, _opt_str = _read.bad, _read.integer, _read.items, _read.optional_string


@dataclass(frozen=True)
class Welcome:
    """The answer to a hello: the server's stream info (``V2VServer.stream_info``: shapes,
    outputs, timeouts in seconds, identity) and the ``hello_id`` it answers."""

    info: dict
    hello_id: int = 0

    def to_wire(self) -> dict:
        return {"type": "welcome", "info": self.info, "hello_id": self.hello_id}

    @classmethod
    def from_wire(cls, h: dict) -> "Welcome":
        info = h.get("info", {})
        if not isinstance(info, dict):
            raise _bad("welcome", "info", "a map", info)
        return cls(info, _int(h, "welcome", "hello_id", 0, 0))


@dataclass(frozen=True)
class Batch:
    """A batch's header.

    Attributes:
        batch_id: the server's id (the client acknowledges it); -1 for DDP padding.
        epoch: the epoch its samples belong to.
        sample_ids: one id per sample, in batch order.
        params: one parameter map per sample.
        arrays: one array spec per array frame (``protocol.decode_batch_arrays``).
        shm: where a same-host client finds the arrays (``{"file", "gen", "offsets"}``), or None
            (the arrays are the frames after the header).
        padding: a DDP repeat for a rank that has nothing to repeat: never acknowledged.
    """

    batch_id: int
    epoch: int
    sample_ids: Tuple[str, ...]
    params: Tuple[dict, ...]
    arrays: Tuple[dict, ...]
    shm: Optional[dict] = None
    padding: bool = False

    def to_wire(self) -> dict:
        h = {"type": "batch", "batch_id": self.batch_id, "epoch": self.epoch, "sample_ids": list(self.sample_ids),
             "params": list(self.params), "arrays": list(self.arrays)}
        if self.shm is not None:
            h["shm"] = self.shm
        if self.padding:
            h["padding"] = True
        return h

    @classmethod
    def from_wire(cls, h: dict) -> "Batch":
        shm, padding = h.get("shm"), h.get("padding", False)
        if shm is not None and not isinstance(shm, dict):
            raise _bad("batch", "shm", "a map or absent", shm)
        if not isinstance(padding, bool):
            raise _bad("batch", "padding", "true or false", padding)
        return cls(_int(h, "batch", "batch_id", -1), _int(h, "batch", "epoch"), _list(h, "batch", "sample_ids", str),
                   _list(h, "batch", "params", dict), _list(h, "batch", "arrays", dict), shm, padding)


@dataclass(frozen=True)
class Revoke:
    """Batches whose lease ran out: the client gives back those it has not handed on."""

    batch_ids: Tuple[int, ...]

    def to_wire(self) -> dict:
        return {"type": "revoke", "batch_ids": list(self.batch_ids)}

    @classmethod
    def from_wire(cls, h: dict) -> "Revoke":
        return cls(_list(h, "revoke", "batch_ids", int))


@dataclass(frozen=True)
class Granted:
    """The answer to a ``hold``: ``batch_ids`` are the client's consumer's for good (recorded
    as delivered to it, never sent to anybody else, never asked back); ``refused``: those of
    the hold the client no longer holds (taken back: it must not hand them on). A client hands
    a batch to its training loop only once it was granted."""

    batch_ids: Tuple[int, ...]
    refused: Tuple[int, ...] = ()

    def to_wire(self) -> dict:
        h = {"type": "granted", "batch_ids": list(self.batch_ids)}
        if self.refused:
            h["refused"] = list(self.refused)
        return h

    @classmethod
    def from_wire(cls, h: dict) -> "Granted":
        refused = _list(h, "granted", "refused", int) if "refused" in h else ()
        return cls(_list(h, "granted", "batch_ids", int), refused)


@dataclass(frozen=True)
class EpochDone:
    """Every sample of ``epoch`` was delivered; with DDP, ``batches``: the batches each rank
    must yield for it (None without DDP)."""

    epoch: int
    batches: Optional[int] = None

    def to_wire(self) -> dict:
        h = {"type": "epoch_done", "epoch": self.epoch}
        if self.batches is not None:
            h["batches"] = self.batches
        return h

    @classmethod
    def from_wire(cls, h: dict) -> "EpochDone":
        batches = None if h.get("batches") is None else _int(h, "epoch_done", "batches")
        return cls(_int(h, "epoch_done", "epoch"), batches)


@dataclass(frozen=True)
class Drained:
    """Nothing is left for this client now (a DataLoader worker may end its iteration)."""

    def to_wire(self) -> dict:
        return {"type": "drained"}

    @classmethod
    def from_wire(cls, h: dict) -> "Drained":
        return cls()


@dataclass(frozen=True)
class End:
    """The stream ended (every epoch delivered); ``reason`` says why, when given."""

    reason: Optional[str] = None

    def to_wire(self) -> dict:
        return {"type": "end"} if self.reason is None else {"type": "end", "reason": self.reason}

    @classmethod
    def from_wire(cls, h: dict) -> "End":
        return cls(_opt_str(h, "end", "reason"))


@dataclass(frozen=True)
class Heartbeat:
    """The server is alive."""

    def to_wire(self) -> dict:
        return {"type": "heartbeat"}

    @classmethod
    def from_wire(cls, h: dict) -> "Heartbeat":
        return cls()


@dataclass(frozen=True)
class Shutdown:
    """The server is going down (a client that reconnects waits for it, or resumes later)."""

    def to_wire(self) -> dict:
        return {"type": "shutdown"}

    @classmethod
    def from_wire(cls, h: dict) -> "Shutdown":
        return cls()


@dataclass(frozen=True)
class ServerError:
    """An error for this client: ``message`` for people; ``code`` for the client, when it can
    act on it (``"dropped"`` and ``"unknown_client"``: say hello again; ``"compression"``: the
    server lacks the codec; ``"outputs"``: outputs it does not offer), else None. ``hello_id``: the
    hello named by the heartbeat an ``unknown_client`` answers (0: another message's answer)."""

    message: str
    code: Optional[str] = None
    hello_id: int = 0

    def to_wire(self) -> dict:
        h = {"type": "error", "message": self.message}
        if self.code is not None:
            h["code"] = self.code
        if self.hello_id:
            h["hello_id"] = self.hello_id
        return h

    @classmethod
    def from_wire(cls, h: dict) -> "ServerError":
        message = h.get("message", "")
        if not isinstance(message, str):
            raise _bad("error", "message", "a string", message)
        return cls(message, _opt_str(h, "error", "code"), _int(h, "error", "hello_id", 0, 0))


StreamMessage = Union[Welcome, Batch, Revoke, Granted, EpochDone, Drained, End, Heartbeat, Shutdown, ServerError]

_TYPES = {"welcome": Welcome, "batch": Batch, "revoke": Revoke, "granted": Granted, "epoch_done": EpochDone, "drained": Drained,
          "end": End, "heartbeat": Heartbeat, "shutdown": Shutdown, "error": ServerError}


def stream_message(h: dict) -> Optional[StreamMessage]:
    """A decoded header from the server (``protocol.unpack``) as its typed message; None for a
    type this client does not know (a newer server's message it can do without).

    Raises:
        StreamMessageError: no string ``type``, or a field missing or of the wrong type, named.
    """
    kind = h.get("type") if isinstance(h, dict) else None
    if not isinstance(kind, str):
        raise StreamMessageError(f"server message: field 'type' must be a string, got {show(kind)}")
    cls = _TYPES.get(kind)
    return None if cls is None else cls.from_wire(h)


__all__ = ["Batch", "Drained", "End", "EpochDone", "Granted", "Heartbeat", "Revoke", "ServerError", "Shutdown",
           "StreamMessage", "StreamMessageError", "Welcome", "stream_message"]

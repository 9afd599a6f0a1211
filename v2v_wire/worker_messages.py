"""Server <-> worker messages: small frozen dataclasses, checked at the edge.

A worker says :class:`Ready` once; the server hands it one :class:`Task` at a time (one video
of one epoch); the worker answers one :class:`Sample` per sample and a :class:`Done` per task;
the server gives a shared-memory slot back with :class:`Slot` and ends a worker with
:class:`Stop`. Each message's ``to_wire()`` is the msgpack header (``protocol.pack`` adds the
version) and ``from_wire(h)`` reads a decoded header (``protocol.unpack``) back, checking
every field: a missing or ill-typed one raises :class:`WorkerMessageError` naming the message
and the field. :func:`worker_message` and :func:`server_message` read a header of either
direction by its ``type``.

When a task's pass over its video stops on an exception, its :class:`Done` carries a
:class:`Failure`: the exception's type name, its formatted traceback and where it was raised
(``"in worker w3.0 (pid 4242) while making bikes.mp4 (epoch 0) after sample bikes.mp4#1"``), as
PyTorch's DataLoader carries a worker's exception in ``ExceptionWrapper(where=...)``, so the
server can say what failed where instead of repeating a line of text. Array frames and their
specs are checked where they are read (``protocol.decode_arrays``, the slot layout).
"""
from __future__ import annotations

import traceback as _traceback
from dataclasses import dataclass, field
from typing import Dict, Optional, Tuple, Union

from v2v_wire.ids import SampleKey
from v2v_wire.fields import FieldReader, show
from v2v_wire.protocol import ProtocolError


class WorkerMessageError(ProtocolError):
    """A server <-> worker message of an unknown type, or with a field missing or of the wrong
    type or range (the error names the message and the field)."""


_read = FieldReader(WorkerMessageError)
_bad, _int, _str, _list, _map = _read.bad, _read.integer, _read.string, _read.items, _read.mapping


@dataclass(frozen=True)
class Failure:
    """An exception raised in a worker, as the server receives it.

    Attributes:
        exc_type: the exception's class name (``"VideoError"``, ``"MemoryError"``).
        message: ``str(exception)``.
        traceback: the formatted traceback (``traceback.format_exception``), for the log.
        where: in which worker and on what (``"in worker w3.0 (pid 4242) while making
            bikes.mp4 (epoch 0) after sample bikes.mp4#1"``).
    """

    exc_type: str
    message: str
    traceback: str
    where: str

    @classmethod
    def of(cls, exc: BaseException, where: str) -> "Failure":
        """The failure of ``exc``, caught ``where``."""
        return cls(type(exc).__name__, str(exc), "".join(_traceback.format_exception(exc)), where)

    def __str__(self) -> str:
        return f"{self.exc_type}: {self.message} ({self.where})"

    def to_wire(self) -> dict:
        return {"exc_type": self.exc_type, "message": self.message, "traceback": self.traceback,
                "where": self.where}

    @classmethod
    def from_wire(cls, v) -> "Failure":
        """Raises: WorkerMessageError naming the field."""
        if not isinstance(v, dict):
            raise _bad("done", "failure", "a map", v)
        return cls(*(_str(v, "done", k, f"failure.{k}") for k in ("exc_type", "message", "traceback", "where")))


@dataclass(frozen=True)
class Task:
    """Server -> worker: make the samples of ``video`` for ``epoch``.

    Attributes:
        task: the task's id (the server numbers its tasks, ``delivery/plan_schedule.py``), echoed in every reply.
        epoch: the epoch (samples depend on seed, epoch and sample id only).
        video: the corpus-relative path.
        outputs: the outputs to make (``protocol.OUTPUTS`` order).
        skip: ``(window, crop)`` of each sample of the video not to make (the server holds it,
            or knows it failed, for this epoch already).
        codecs: what to compress each sample with (``codecs.COMPRESSIONS``, those fetches asked
            for in the last 2 minutes, ``plan_server.CODEC_KEEP_S``).
    """

    task: int
    epoch: int
    video: str
    outputs: Tuple[str, ...]
    skip: Tuple[Tuple[int, int], ...] = ()
    codecs: Tuple[str, ...] = ()

    def to_wire(self) -> dict:
        return {"type": "task", "task": self.task, "epoch": self.epoch, "video": self.video,
                "outputs": list(self.outputs), "skip": [list(s) for s in self.skip], "codecs": list(self.codecs)}

    @classmethod
    def from_wire(cls, h: dict) -> "Task":
        """Raises: WorkerMessageError naming the field."""
        skip = h.get("skip", [])
        if not isinstance(skip, list) or not all(
                isinstance(s, list) and len(s) == 2 and all(isinstance(i, int) and not isinstance(i, bool) and i >= 0
                                                            for i in s) for s in skip):
            raise _bad("task", "skip", "a list of [window, crop] pairs", skip)
        return cls(_int(h, "task", "task"), _int(h, "task", "epoch"), _str(h, "task", "video"),
                   _list(h, "task", "outputs", str, ()), tuple((w, c) for w, c in skip),
                   _list(h, "task", "codecs", str, ()))


@dataclass(frozen=True)
class Ready:
    """Worker -> server, once at start: ``ring`` whether it mapped its shared-memory slot ring
    (else it sends arrays as socket frames)."""

    ring: bool = False

    def to_wire(self) -> dict:
        return {"type": "ready", "ring": self.ring}

    @classmethod
    def from_wire(cls, h: dict) -> "Ready":
        ring = h.get("ring", False)
        if not isinstance(ring, bool):
            raise _bad("ready", "ring", "true or false", ring)
        return cls(ring)


@dataclass(frozen=True)
class Sample:
    """Worker -> server: one sample of a task, its arrays as the frames after the header, or in
    slot ``slot`` of the worker's ring.

    Attributes:
        task: the task's id.
        key: the sample's key (``ids.SampleKey``, ``"key": [video, window, crop]`` on the wire).
        meta: its parameters (msgpack-able map, passed on to the clients).
        arrays: one ``{"name", "dtype", "shape"}`` per array (checked where the frames or the
            slot are read).
        packed: one ``{"codec", "name", "nbytes"}`` per compressed frame after the array frames.
        slot: the ring slot holding the arrays, or None (they are frames).
        stages: seconds per stage since the worker's previous message (``ops.metrics``).
    """

    task: int
    key: SampleKey
    meta: dict
    arrays: Tuple[dict, ...]
    packed: Tuple[dict, ...] = ()
    slot: Optional[int] = None
    stages: Dict[str, float] = field(default_factory=dict)

    def to_wire(self) -> dict:
        h = {"type": "sample", "task": self.task, "key": self.key.wire(), "meta": self.meta,
             "arrays": list(self.arrays), "stages": self.stages}
        if self.packed:
            h["packed"] = list(self.packed)
        if self.slot is not None:
            h["slot"] = self.slot
        return h

    @classmethod
    def from_wire(cls, h: dict, crops_per_window: int = 1) -> "Sample":
        """``crops_per_window``: the server's (a key's crop must be below it).

        Raises: WorkerMessageError naming the field."""
        try:
            key = SampleKey.from_wire(h.get("key"), crops_per_window)
        except ValueError as e:
            raise WorkerMessageError(f"sample message: field 'key': {e}") from None
        meta = h.get("meta")
        if not isinstance(meta, dict):
            raise _bad("sample", "meta", "a map", meta)  # its contents are the clients' (msgpack-able)
        packed = _list(h, "sample", "packed", dict, ())
        for p in packed:
            if not (isinstance(p.get("codec"), str) and isinstance(p.get("name"), str)
                    and isinstance(p.get("nbytes"), int) and not isinstance(p.get("nbytes"), bool)):
                raise _bad("sample", "packed", "a list of {codec, name, nbytes}", p)
        slot = None if h.get("slot") is None else _int(h, "sample", "slot")
        return cls(_int(h, "sample", "task"), key, meta, _list(h, "sample", "arrays", dict, ()), packed, slot,
                   _map(h, "sample", "stages", (int, float)))


#: Why a pass gave fewer windows than it could, as a code (``window_pass.judged``): ``""``
#: nothing is wrong; ``"short"`` too few frames (or every shot too short): a property of the
#: clip, not a fault; ``"static"`` every window static; ``"failed"`` windows that cannot be
#: made; ``"error"`` what stopped the reading.
CAUSES = ("", "short", "static", "failed", "error")


@dataclass(frozen=True)
class Done:
    """Worker -> server: a task's pass over its video ended.

    Attributes:
        task: the task's id.
        windows: complete windows the file gave (the server learns the video's slots from them,
            ``delivery/plan_schedule.py``).
        failed: window (its digits, as a string) -> why that window cannot be made.
        error: why the pass gave fewer windows than it should (``window_pass.VideoPass.reason``), or None.
        cause: that reason's cause as a code, one of :data:`CAUSES` (``""`` without one).
        failure: the exception that stopped the pass, if one did.
        frames: frames decoded.
        cuts, dropped: shot cuts found, windows they removed.
        stages: seconds per stage since the previous message; store: the task's object-store
            reads (``sources.source.VideoSource.take_stats``).
    """

    task: int
    windows: int = 0
    failed: Dict[str, str] = field(default_factory=dict)
    error: Optional[str] = None
    failure: Optional[Failure] = None
    frames: int = 0
    cuts: int = 0
    dropped: int = 0
    stages: Dict[str, float] = field(default_factory=dict)
    store: Dict[str, object] = field(default_factory=dict)
    cause: str = ""

    def to_wire(self) -> dict:
        return {"type": "done", "task": self.task, "windows": self.windows, "failed": self.failed,
                "error": self.error, "failure": None if self.failure is None else self.failure.to_wire(),
                "frames": self.frames, "cuts": self.cuts, "dropped": self.dropped, "stages": self.stages,
                "store": self.store, "cause": self.cause}

    @classmethod
    def from_wire(cls, h: dict) -> "Done":
        """Raises: WorkerMessageError naming the field."""
        error = h.get("error")
        if error is not None and not isinstance(error, str):
            raise _bad("done", "error", "a string or null", error)
        failure = None if h.get("failure") is None else Failure.from_wire(h["failure"])
        count = {k: _int(h, "done", k, default=0) for k in ("windows", "frames", "cuts", "dropped")}
        cause = h.get("cause", "")
        if cause not in CAUSES:
            raise _bad("done", "cause", f"one of {list(CAUSES)}", cause)
        failed = _map(h, "done", "failed", (str,))
        if not all(k.isascii() and k.isdigit() and len(k) <= 9 for k in failed):
            raise _bad("done", "failed", "a map of window numbers (digits) to strings", failed)
        return cls(_int(h, "done", "task"), count["windows"], failed, error,
                   failure, count["frames"], count["cuts"], count["dropped"],
                   _map(h, "done", "stages", (int, float)), _map(h, "done", "store"), cause)


@dataclass(frozen=True)
class Slot:
    """Server -> worker: slot ``slot`` of the worker's ring was copied out and may be written again."""

    slot: int

    def to_wire(self) -> dict:
        return {"type": "slot", "slot": self.slot}

    @classmethod
    def from_wire(cls, h: dict) -> "Slot":
        return cls(_int(h, "slot", "slot"))


@dataclass(frozen=True)
class Stop:
    """Server -> worker: exit."""

    def to_wire(self) -> dict:
        return {"type": "stop"}

    @classmethod
    def from_wire(cls, h: dict) -> "Stop":
        return cls()


WorkerMessage = Union[Ready, Sample, Done]
ServerMessage = Union[Task, Slot, Stop]


def worker_message(h: dict, crops_per_window: int = 1) -> WorkerMessage:
    """A decoded header from a worker (``protocol.unpack``) as :class:`Ready`, :class:`Sample` or
    :class:`Done` (``crops_per_window``: the server's, see :meth:`Sample.from_wire`).

    Raises:
        WorkerMessageError: an unknown type, or a field missing or of the wrong type, named.
    """
    kind = h.get("type") if isinstance(h, dict) else None
    if kind == "sample":
        return Sample.from_wire(h, crops_per_window)
    if kind == "done":
        return Done.from_wire(h)
    if kind == "ready":
        return Ready.from_wire(h)
    raise WorkerMessageError(f"unknown worker message type {show(kind)}")


def server_message(h: dict) -> ServerMessage:
    """A decoded header from the server as :class:`Task`, :class:`Slot` or :class:`Stop`.

    Raises:
        WorkerMessageError: an unknown type, or a field missing or of the wrong type, named.
    """
    kind = h.get("type") if isinstance(h, dict) else None
    for cls in (Task, Slot, Stop):
        if kind == cls.__name__.lower():
            return cls.from_wire(h)
    raise WorkerMessageError(f"unknown server message type {show(kind)}")


__all__ = ["Done", "Failure", "Ready", "Sample", "ServerMessage", "Slot", "Stop", "Task", "WorkerMessage",
           "WorkerMessageError", "server_message", "worker_message"]

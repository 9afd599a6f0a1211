"""The messages between ``StreamLoader`` in the main process and its DataLoader workers, typed
(no torch): the loop's receipts, the end of an iteration, and the tag a worker puts on each batch
it yields so the main process knows whose it is. docs/delivery.md ("DataLoader workers") says why
a worker acknowledges a batch only on its receipt.

* worker -> main process, inside the batch dict (``batch["receipt"]``): :class:`Handed`;
* main process -> worker, msgpack over the worker's ``multiprocessing.Pipe``: :class:`Receipt`
  (the loop received these batches) and :class:`Abandon` (the loop left this iteration),
  read back by :func:`loader_message`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, List, Tuple, Union

from v2v_wire.protocol import pack, unpack

__all__ = ["Handed", "Receipt", "Abandon", "loader_message", "received_ids"]


@dataclass(frozen=True)
class Handed:
    """A batch DataLoader worker ``worker`` yielded: its ``batch_id``, ``epoch``, and the last
    epoch that worker knew complete when it yielded it (``completed_epoch``)."""

    worker: int
    batch_id: int
    epoch: int
    completed_epoch: int


@dataclass(frozen=True)
class Receipt:
    """The training loop received these batches (the worker acknowledges them to the server)."""

    batch_ids: Tuple[int, ...]

    def to_bytes(self) -> bytes:
        return pack({"type": "receipt", "batch_ids": list(self.batch_ids)})


@dataclass(frozen=True)
class Abandon:
    """The loop left the worker's iteration number ``iteration``: no receipt will come for what
    it queued in the loader (given back to the server)."""

    iteration: int

    def to_bytes(self) -> bytes:
        return pack({"type": "abandon", "iteration": self.iteration})


def loader_message(data: bytes) -> Union[Receipt, Abandon]:
    """A message from the main process, typed.

    Raises:
        ValueError: anything else (the main process and the worker run the same code: a bug).
    """
    h = unpack(data)
    if h.get("type") == "receipt" and isinstance(h.get("batch_ids"), list):
        return Receipt(tuple(int(b) for b in h["batch_ids"]))
    if h.get("type") == "abandon" and isinstance(h.get("iteration"), int):
        return Abandon(h["iteration"])
    raise ValueError(f"not a StreamLoader message: {h!r:.80}")


def received_ids(messages: Iterable[bytes]) -> List[int]:
    """The batch ids of the receipts among ``messages`` (main process -> worker, as written),
    abandons skipped. A persistent worker reads with it what no connection read before its next
    iteration: one that ended (the stream's ``end``) while its last batches waited in the loader's
    queues never read their receipts, and the loop may have received them (docs/delivery.md,
    "DataLoader workers")."""
    out: List[int] = []
    for data in messages:
        msg = loader_message(data)
        if isinstance(msg, Receipt):
            out.extend(msg.batch_ids)
    return out

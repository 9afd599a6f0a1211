"""One server's stream: the consumer's record (ids yielded per open epoch, batches per epoch,
the last completed epoch: :class:`ConsumerRecord`), the hello that carries it, and the iteration
over a :class:`~v2v_client.connection.Connection` that drops re-sent samples and adds DDP
padding (:class:`EndpointStream`). ``V2VStreamDataset`` reads one of these per server (several
through ``fanin.FanInStream``).
"""
from __future__ import annotations

import functools
import queue
import threading
import uuid
from dataclasses import replace
from typing import Dict, Iterator, List, Optional, Set, Tuple

import torch

from v2v_wire.ids import compact_ids

from .connection import Connection
from .options import StreamOptions
from .session import Drained, EpochDone, LoopAbandoned, ServerPadding, StreamError
from .tensors import batch_to_torch, select_samples
from .fanin import read_state

__all__ = ["EndpointStream", "ConsumerRecord", "padding_copy"]


def padding_copy(batch: dict, epoch: int) -> dict:
    """A DDP padding batch of ``epoch`` repeating ``batch``: its tensors cloned, every sample
    flagged in ``padding`` (bool (B,), all True: the loss must ignore them), ``batch_id`` -1."""
    out = {k: (v.clone() if isinstance(v, torch.Tensor) else v) for k, v in batch.items()}
    out.update(padding=torch.ones(len(batch["sample_ids"]), dtype=torch.bool), epoch=epoch, batch_id=-1,
               sample_ids=list(batch["sample_ids"]), params=list(batch["params"]))
    return out


class ConsumerRecord:
    """What one consumer has had from one server, per open epoch: the sample ids yielded, the
    batches yielded (DDP padding included), the last epoch the server declared complete, the
    recipe fingerprint the ids were made under, and, in a DataLoader worker, the batches
    yielded to the DataLoader whose receipt has not come (``pipeline``: batch id -> (epoch,
    sample ids)). Pure and thread-safe: the I/O thread records receipts while the consumer
    iterates."""

    def __init__(self):
        self.lock = threading.Lock()
        self.completed_epoch = -1
        self.delivered: Dict[int, Set[str]] = {}
        self.batches: Dict[int, int] = {}  # batches yielded per open epoch (DDP padding)
        self.recipe: Optional[str] = None  # fingerprint of the recipe the sample ids were made under
        self.pipeline: Dict[int, Tuple[int, List[str]]] = {}

    def state(self) -> dict:
        """The record's part of a stream's ``state_dict`` (plain data)."""
        with self.lock:
            return {"completed_epoch": self.completed_epoch,
                    "delivered": {str(e): sorted(ids) for e, ids in self.delivered.items()},
                    "batches": {str(e): n for e, n in self.batches.items()}, "recipe": self.recipe}

    def load(self, state: dict) -> None:
        """Restore :meth:`state` output (a stream's ``state_dict``).

        Raises:
            ValueError: for a state of another format.
        """
        completed, delivered = read_state(state)
        with self.lock:
            self.completed_epoch, self.delivered = completed, delivered
            self.batches = {int(e): int(n) for e, n in state.get("batches", {}).items()}
            if isinstance(state.get("recipe"), str):
                self.recipe = state["recipe"]

    def resume(self) -> dict:
        """The hello's resume state: the completed epoch, ids yielded (compacted; in a
        DataLoader worker also those in the loader's queues: the loop may still receive them)
        and batches per open epoch."""
        with self.lock:
            ids = {e: set(v) for e, v in self.delivered.items()}
            for e, sids in self.pipeline.values():
                if e > self.completed_epoch:
                    ids.setdefault(e, set()).update(sids)
            return {"completed_epoch": self.completed_epoch,
                    "delivered": {str(e): compact_ids(v) for e, v in ids.items()},
                    "batches": {str(e): n for e, n in self.batches.items()}}

    def check_recipe(self, recipe) -> Optional[str]:
        """A server's recipe fingerprint: why the record refuses it (its ids were made under
        another recipe), or None (the fingerprint is kept)."""
        with self.lock:
            if self.recipe is not None and isinstance(recipe, str) and recipe != self.recipe:
                return (f"it serves another sample recipe ({recipe}) than the one this resume state was made "
                        f"under ({self.recipe}): seed, sequence length, bins, crop or crops per window differ, "
                        f"so its sample ids name other samples. Resume against a server with the same recipe, or "
                        f"start without the state")
            if isinstance(recipe, str):
                self.recipe = recipe
        return None

    def complete(self, epoch: int, batches_due: Optional[int]) -> Optional[int]:
        """The server declared ``epoch`` complete: its ids are forgotten. Returns the padding
        batches still owed (``batches_due``, with DDP: batches every rank must yield, minus
        those yielded; 0 without), or None when the epoch was complete already."""
        with self.lock:
            if epoch <= self.completed_epoch:
                return None
            owed = 0 if batches_due is None else max(0, batches_due - self.batches.get(epoch, 0))
            self.completed_epoch = epoch
            for e in [e for e in self.delivered if e <= epoch]:
                del self.delivered[e]
            for e in [e for e in self.batches if e <= epoch]:
                del self.batches[e]
        return owed

    def is_complete(self, epoch: int) -> bool:
        """Whether the server declared ``epoch`` complete (its batches are given back unused)."""
        with self.lock:
            return epoch <= self.completed_epoch

    def count_padding(self, epoch: int) -> bool:
        """A padding batch of ``epoch`` is yielded (counted); False when the epoch is complete."""
        with self.lock:
            if epoch <= self.completed_epoch:
                return False
            self.batches[epoch] = self.batches.get(epoch, 0) + 1
        return True

    def new_samples(self, epoch: int, batch_id: int, sample_ids: List[str], loader: bool) -> List[int]:
        """Positions of a claimed batch's samples neither yielded nor in the pipeline already.
        They are recorded as yielded (the batch counted), or with ``loader`` put in the
        pipeline until the training loop's receipt (:meth:`received`)."""
        with self.lock:
            seen = self.delivered.setdefault(epoch, set())
            queued = {s for e, ids in self.pipeline.values() if e == epoch for s in ids}
            keep = [i for i, sid in enumerate(sample_ids) if sid not in seen and sid not in queued]
            if loader:
                if keep:
                    self.pipeline[batch_id] = (epoch, [sample_ids[i] for i in keep])
            else:
                seen.update(sample_ids[i] for i in keep)
                self.batches[epoch] = self.batches.get(epoch, 0) + 1
        return keep

    def received(self, batch_ids) -> List[int]:
        """The training loop received these batches: they count as yielded; returns those
        that were in the pipeline."""
        mine = []
        with self.lock:
            for bid in batch_ids:
                entry = self.pipeline.pop(bid, None)
                if entry is not None:
                    epoch, ids = entry
                    if epoch > self.completed_epoch:
                        self.delivered.setdefault(epoch, set()).update(ids)
                        self.batches[epoch] = self.batches.get(epoch, 0) + 1
                    mine.append(bid)
        return mine

    def in_pipeline(self) -> int:
        """Batches yielded to the DataLoader whose receipt has not come."""
        with self.lock:
            return len(self.pipeline)

    def pipeline_ids(self) -> List[int]:
        """Batch ids yielded to the DataLoader whose receipt has not come."""
        with self.lock:
            return list(self.pipeline)

    def clear_pipeline(self) -> None:
        """Forget the batches in the DataLoader's queues (they go back to the server)."""
        with self.lock:
            self.pipeline.clear()


class EndpointStream:
    """The stream of one server for one consumer.

    Args:
        endpoint: the server's ZeroMQ endpoint.
        options: :class:`~v2v_client.options.StreamOptions`, the one place its settings are read from.

    Iterating opens a connection it owns (one per iterator; a new one replaces the previous),
    reads what the connection queues, and yields the batch dicts ``V2VStreamDataset``
    documents: each sample once per epoch, DDP padding where owed, a DataLoader worker's
    batches held until the loop receives them. ``state_dict()`` / ``load_state_dict()`` carry
    the consumer's :class:`ConsumerRecord` (``record``) across restarts.
    """

    def __init__(self, endpoint: str, options: StreamOptions):
        self.endpoint = endpoint
        self.options = options
        self.record = ConsumerRecord()
        self._info: Optional[dict] = None  # the stream info of the last connection closed
        self._conns: list = []
        #: who acknowledges: survives reconnects and restarts (state_dict)
        self.consumer = uuid.uuid4().hex
        self._last: Optional[dict] = None  # last batch yielded: the source of DDP padding
        self._pad_debt: Dict[int, int] = {}  # epoch -> padding batches owed with nothing to repeat yet
        # In a DataLoader worker under ``StreamLoader``: the pipe on which the main process says
        # which batches the training loop received (see ``v2v_client.loader``).
        self.receipts = None
        self.worker: Optional[int] = None
        self.iteration = 0  # the loader's iterations over this worker's pipe so far, less one

    @property
    def info(self) -> Optional[dict]:
        """The server's stream info from the newest connection's welcome (None before any)."""
        for conn in reversed(self._conns):
            if conn.info is not None:
                return conn.info
        return self._info

    def held(self) -> int:
        """Batches the open connections received and neither took nor gave back (at most
        ``options.credits`` per connection)."""
        return sum(conn.held() for conn in list(self._conns))

    def set_position(self, rank: int, world_size: int) -> None:
        """The DDP position the next connection says hello with."""
        self.options = replace(self.options, rank=rank, world_size=world_size)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """Where this consumer stands: epochs the server declared complete, the sample ids
        yielded so far in epochs still open, batches yielded per open epoch, and the consumer
        id the server knows it by. Plain, JSON/torch.save-safe data."""
        r = self.record.state()
        return {"version": 1, "consumer": self.consumer, "completed_epoch": r["completed_epoch"],
                "delivered": r["delivered"], "batches": r["batches"], "recipe": r["recipe"]}

    def load_state_dict(self, state: dict) -> None:
        """Restore ``state_dict()`` output; the next iteration resumes the epoch without
        repeating or skipping samples (the server takes this state as the truth: samples
        yielded after it was saved are sent again).

        Raises:
            ValueError: for a state of another format.
        """
        self.record.load(state)
        if isinstance(state.get("consumer"), str) and state["consumer"]:
            self.consumer = state["consumer"]

    def attach_loader(self, worker: int, receipts, state: Optional[dict]) -> None:
        """Read by DataLoader worker ``worker`` of a ``StreamLoader``: batches are
        acknowledged when the main process reports them received (``receipts``, the read end
        of a ``multiprocessing.Pipe``), not when yielded. ``state``: this worker's record kept
        by the main process, loaded the first time (a worker process made anew resumes from it;
        a persistent one keeps its own, which equals it)."""
        self.close()  # a new iteration in this worker: the previous one is over (its receipts are taken first)
        if self.receipts is None and state is not None:
            self.load_state_dict(state)
        # a persistent worker reads the same pipe in each iteration: the loader's
        # ``LoaderLink.end_iteration`` names the iteration it ends by this count
        self.iteration = self.iteration + 1 if receipts is self.receipts else 0
        self.worker, self.receipts = worker, receipts

    def close(self) -> None:
        """Close every open connection of this stream (also done when iterators are collected);
        batches a DataLoader worker yielded and the loop never received go back to the server."""
        for conn in list(self._conns):
            self._drop(conn)
        self.record.clear_pipeline()

    def _drop(self, conn: Connection, unreceived: bool = False) -> None:
        """Close ``conn`` and forget it, keeping its stream info; ``unreceived``: the loader
        dropped what this DataLoader worker queued (its batches without a receipt go back)."""
        conn.close(unreceived)
        if conn.info is not None:
            self._info = conn.info
        if conn in self._conns:
            self._conns.remove(conn)

    def _connect(self) -> Connection:
        """A connection for a new iterator, saying hello with this stream's options and record."""
        worker = torch.utils.data.get_worker_info()
        consumer = self.consumer if worker is None else f"{self.consumer}/{worker.id}"
        convert = functools.partial(_to_tensors, self.options.raw, self.options.compact_flow)
        conn = Connection(self.endpoint, self.options, self.record, consumer, convert, self.receipts,
                          self.iteration)
        self._conns.append(conn)
        return conn

    # ------------------------------------------------------------------ iteration
    def __iter__(self) -> Iterator[dict]:
        conn = self._connect()
        abandoned = False
        try:
            while True:
                item = self._next_item(conn)
                if isinstance(item, StopIteration):
                    return
                if isinstance(item, LoopAbandoned):
                    abandoned = True  # no receipt will come: what is held goes back with bye
                    return
                if isinstance(item, BaseException):
                    raise item
                if isinstance(item, EpochDone):
                    yield from self._epoch_done(item)
                elif isinstance(item, Drained):
                    if self.receipts is not None and conn.held() == 0:
                        return  # a DataLoader worker: end this iteration so the loader takes the others' batches
                elif isinstance(item, ServerPadding):
                    yield from self._server_padding(item)
                else:
                    yield from self._batch(conn, item)
        except GeneratorExit:
            abandoned = True
            raise
        finally:
            if self.receipts is not None and not abandoned and self.record.pipeline:
                conn.linger()  # ended (drained, end of stream) with batches in the loader's queues
            else:  # receipts already written are taken first; the batches the loop will not receive go back
                self._drop(conn, unreceived=abandoned)
                self.record.clear_pipeline()

    def _next_item(self, conn: Connection):
        """The next item the connection's I/O thread queued (a batch or a control item).

        Raises:
            StreamError: the I/O thread ended without saying why.
        """
        while True:
            try:
                return conn.items.get(timeout=1.0)
            except queue.Empty:
                if conn.ended():
                    raise StreamError(f"the connection to the v2v server at {self.endpoint} ended") from None
                # the I/O thread decides when the server is gone (timeout_s without a message)

    def _epoch_done(self, done: EpochDone) -> List[dict]:
        """Forget a complete epoch; with DDP, the padding batches this rank owes for it."""
        owed = self.record.complete(done.epoch, done.batches if self.options.world_size > 1 else None)
        pads: List[dict] = []
        for _ in range(owed or 0):
            if self._last is None:
                self._pad_debt[done.epoch] = self._pad_debt.get(done.epoch, 0) + 1
            else:
                pads.append(padding_copy(self._last, done.epoch))
        return pads

    def _server_padding(self, padding: ServerPadding) -> Iterator[dict]:
        """A DDP padding batch the server sent (not leased): yielded unless its epoch is complete here."""
        item = padding.item
        item["padding"] = torch.ones(len(item["sample_ids"]), dtype=torch.bool)
        if not self.record.count_padding(item["epoch"]):
            return
        self._last = item
        yield item

    def _batch(self, conn: Connection, item: dict) -> Iterator[dict]:
        """A received batch: given back when its epoch is complete here; else claimed once the
        server granted it (acknowledged, or in a DataLoader worker acknowledged when the loop's
        receipt comes) and its samples recorded in the same step, those already delivered or queued dropped
        (a batch of repeats only becomes DDP padding, or nothing with one rank), preceded by
        any padding owed, and yielded."""
        epoch = item["epoch"]
        if self.record.is_complete(epoch):
            conn.give_back(item)  # never acknowledge what we would drop
            return
        loader = self.receipts is not None
        taken, keep = conn.take(item, lambda: self.record.new_samples(epoch, item["batch_id"], item["sample_ids"],
                                                                      loader), ack=not loader)
        if not taken:
            return  # given back meanwhile (revoked before it was granted, or this client said hello again)
        item["padding"] = torch.zeros(len(item["sample_ids"]), dtype=torch.bool)
        if loader:
            if not keep:
                conn.ack([item["batch_id"]])  # nothing new in it: nothing for the loop to receive
                return
            item["receipt"] = {"worker": self.worker, "batch_id": item["batch_id"], "epoch": epoch,
                               "completed_epoch": self.record.completed_epoch}
        if len(keep) < len(item["sample_ids"]):
            if not keep and self.options.world_size == 1:
                return  # all re-sent duplicates: hand nothing on
            if keep:
                item = select_samples(item, keep)
            else:  # DDP: keep the batch count equal; every sample is a repeat
                item["padding"] = torch.ones(len(item["sample_ids"]), dtype=torch.bool)
        for e in sorted(self._pad_debt):
            for _ in range(self._pad_debt.pop(e)):
                yield padding_copy(item, e)
        self._last = item
        yield item


def _to_tensors(raw: bool, compact_flow: bool, arrays: dict, flow_size, flow_dtype: str) -> dict:
    """A batch's wire arrays as a stream's tensors (a connection's ``convert``:
    ``tensors.batch_to_torch`` with the stream's ``raw`` and ``compact_flow``)."""
    return batch_to_torch(arrays, raw, flow_size, flow_dtype, compact_flow)

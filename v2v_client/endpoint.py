"""One server's stream: the iteration over a :class:`~v2v_client.connection.Connection` that
drops re-sent samples and adds DDP padding (:class:`EndpointStream`), with the reader's record
(``resume.ResumeState``) that every hello carries. ``V2VPushDataset`` reads one of these per
server (several through ``fanin.FanInStream``).
"""
from __future__ import annotations

import functools
import queue
import uuid
from dataclasses import replace
from typing import Iterator, List, Optional

import numpy as np
import torch

from v2v_wire.outputs import ARRAYS
from v2v_wire.stream_messages import Drained, EpochDone

from .connection import Connection
from .options import StreamOptions
from .receipts import Handed, received_ids
from .resume import ResumeState, owed_padding, take_epoch_end
from .session import LoopAbandoned, ServerPadding, StreamError
from .tensors import batch_to_torch, select_samples

__all__ = ["EndpointStream", "padding_copy", "zero_padding"]


def padding_copy(batch: dict, epoch: int) -> dict:
    """A DDP padding batch of ``epoch`` repeating ``batch``: its tensors cloned, every sample
    flagged in ``padding`` (bool (B,), all True: the loss must ignore them), ``batch_id`` -1."""
    out = {k: (v.clone() if isinstance(v, torch.Tensor) else v) for k, v in batch.items()}
    out.update(padding=torch.ones(len(batch["sample_ids"]), dtype=torch.bool), epoch=epoch, batch_id=-1,
               sample_ids=list(batch["sample_ids"]), params=list(batch["params"]))
    return out


def zero_padding(info: dict, options: StreamOptions, epoch: int) -> dict:
    """A DDP padding batch of ``epoch`` with nothing to repeat: one sample of zeros of each of
    ``options.outputs`` (in ``info``'s shapes and wire dtypes: the server's welcome), converted as
    the stream converts its batches, flagged in ``padding`` (bool (1,), True), sample id ``""``,
    ``batch_id`` -1. A tracked flow option's flow is zeros at its grid's points (the welcome's
    ``flow_grid_points``), so padding has ``flow_grid`` where the batches have it (``compact_flow``)."""
    size = int(info.get("crop_size") or 1)
    flow_dtype = info.get("flow_dtype", ARRAYS["flow"].dtypes[0])
    length, points = int(info.get("sequence_length", 1)), int(info.get("flow_grid_points") or 0)
    arrays = {}
    for name in options.outputs or info.get("outputs", ()):
        if name == "flow" and points:
            arrays["flow_grid"] = np.zeros((1, length, 2, points, points), ARRAYS["flow_grid"].dtypes[0])
            continue
        spec = ARRAYS[name]
        shape = spec.shape(length, int(info.get("num_bins", 1)), size)
        arrays[name] = np.zeros((1,) + shape, flow_dtype if spec.narrowing == "recipe" else spec.dtypes[0])
    out = _to_tensors(options.raw, options.compact_flow, arrays, (size, size), flow_dtype)
    out.update(padding=torch.ones(1, dtype=torch.bool), epoch=epoch, batch_id=-1, sample_ids=[""], params=[{}])
    return out


class EndpointStream:
    """The stream of one server for one consumer.

    Args:
        endpoint: the server's ZeroMQ endpoint.
        options: :class:`~v2v_client.options.StreamOptions`, the one place its settings are read from.

    Iterating opens a connection it owns (one per iterator; a new one replaces the previous),
    reads what the connection queues, and yields the batch dicts ``V2VPushDataset``
    documents: each sample once per epoch, DDP padding where owed, a DataLoader worker's
    batches held until the loop receives them. ``state_dict()`` / ``load_state_dict()`` carry
    the reader's ``resume.ResumeState`` (``record``) across restarts.
    """

    def __init__(self, endpoint: str, options: StreamOptions, instance: Optional[str] = None):
        self.endpoint = endpoint
        self.options = options
        #: this reader process's token (the dataset's): the server lets one instance read a consumer at a time
        self.instance = instance or uuid.uuid4().hex
        #: the reader's record; its consumer id (who acknowledges) survives reconnects and restarts
        self.record = ResumeState(uuid.uuid4().hex)
        self._info: Optional[dict] = None  # the stream info of the last connection closed
        self._conns: list = []
        self._last: Optional[dict] = None  # last batch yielded: the source of DDP padding
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

    @property
    def consumer(self) -> str:
        """The id the server knows this reader by (DataLoader workers add ``/<worker id>``)."""
        return self.record.consumer

    @consumer.setter
    def consumer(self, value: str) -> None:
        self.record.consumer = value

    def set_position(self, rank: int, world_size: int, group: Optional[str] = None) -> None:
        """The DDP position (and group) the next connection says hello with."""
        self.options = replace(self.options, rank=rank, world_size=world_size, group=group or self.options.group)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """Where this consumer stands (``ResumeState.state``): epochs the server declared
        complete, the sample ids yielded so far in epochs still open, batches yielded per open
        epoch, and the consumer id the server knows it by. Plain, JSON/torch.save-safe data."""
        return self.record.state()

    def load_state_dict(self, state: dict) -> None:
        """Restore ``state_dict()`` output; the next iteration resumes the epoch without
        repeating or skipping samples (the server takes this state as the truth: samples
        yielded after it was saved are sent again).

        Raises:
            ValueError: for a state of another format.
        """
        self.record.load(state)

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
        self.record.received(received_ids(self._unread_receipts()))  # no connection read them: the hello names them
        self.record.clear_pipeline()

    def _unread_receipts(self) -> List[bytes]:
        """What the main process wrote on this worker's receipt pipe that no connection read."""
        out: List[bytes] = []
        try:
            while self.receipts is not None and self.receipts.poll(0):
                out.append(self.receipts.recv_bytes())
        except (EOFError, OSError):
            pass
        return out

    def _drop(self, conn: Connection, unreceived: bool = False) -> None:
        """Close ``conn`` and forget it, keeping its stream info; ``unreceived``: the loader
        dropped what this DataLoader worker queued (its batches without a receipt go back)."""
        conn.close(unreceived)
        if conn.info is not None:
            self._info = conn.info
        if conn in self._conns:
            self._conns.remove(conn)

    def _connect(self) -> Connection:
        """A connection for a new iterator, saying hello with this stream's options and record. The
        stream reads one connection at a time: an older iterator's connection closes first (that
        iterator raises if it is resumed), so two iterators never read as one consumer.

        Raises:
            ValueError: the record was saved by another DDP rank (``ResumeState.place``).
        """
        o = self.options
        self.record.place(o.group, o.rank, o.world_size)
        worker = torch.utils.data.get_worker_info()
        if worker is None:
            for old in list(self._conns):
                old.items.put(StreamError(f"this V2VPushDataset reading {self.endpoint} was iterated again: one "
                                          f"iterator at a time reads a consumer (the newer one reads on)"))
                self._drop(old)
        consumer = self.consumer if worker is None else f"{self.consumer}/{worker.id}"
        convert = functools.partial(_to_tensors, o.raw, o.compact_flow)
        conn = Connection(self.endpoint, o, self.record, consumer, convert, self.receipts, self.iteration,
                          self.instance)
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
                    yield from self._unpaid_padding(conn.info or {})
                    return
                if isinstance(item, LoopAbandoned):
                    abandoned = True  # no receipt will come: what is held goes back with bye
                    return
                if isinstance(item, BaseException):
                    raise item
                if isinstance(item, EpochDone):
                    yield from self._epoch_done(conn, item)
                elif isinstance(item, Drained):
                    if conn.ends_on(item):
                        return  # a DataLoader worker: end this iteration so the loader takes the others' batches
                elif isinstance(item, ServerPadding):
                    if conn.of_session(item):  # else told the session a hello ended: the server tells the new one
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

    def _epoch_done(self, conn: Connection, done: EpochDone) -> Iterator[dict]:
        """Forget a complete epoch told to the current session (:func:`~v2v_client.resume.take_epoch_end`);
        with DDP, the padding batches this rank owes for it, copies of the last batch (with none yet,
        the record keeps them owed: the next batch or the server's copy pays them), the epoch
        completing in the record with the last of them."""
        ddp = self.options.world_size > 1
        current = conn.of_session(done, lambda now_current: take_epoch_end(self.record, done, ddp, now_current))
        if current and self._last is not None:
            yield from owed_padding(self.record, self._last, padding_copy)

    def _unpaid_padding(self, info: dict) -> Iterator[dict]:
        """At the stream's end, the DDP padding still owed with nothing to repeat (the group's last
        batch went with a server that crashed, so no copy came): :func:`zero_padding` batches, so
        every rank yields the same count (docs/delivery.md, "DDP"), each counted in the record as
        it is yielded (``resume.owed_padding``)."""
        yield from owed_padding(self.record, {}, lambda _source, e: zero_padding(info, self.options, e))

    def _server_padding(self, padding: ServerPadding) -> Iterator[dict]:
        """A DDP padding batch the server sent (not leased): yielded as ``resume.owed_padding``
        says (itself, and copies for what the rank owes)."""
        item = padding.item
        item["padding"] = torch.ones(len(item["sample_ids"]), dtype=torch.bool)
        for out in owed_padding(self.record, item, padding_copy, own=True):
            self._last = item
            yield out

    def _batch(self, conn: Connection, item: dict) -> Iterator[dict]:
        """A received batch: given back when its epoch is complete here; else claimed once the
        server granted it (acknowledged, or in a DataLoader worker acknowledged when the loop's
        receipt comes) and its samples recorded in the same step, those already delivered or queued dropped
        (a batch of repeats only becomes DDP padding, or nothing with one rank), and yielded. Any
        padding owed is yielded first, before the claim: a checkpoint taken between the two must
        not name a batch the loop has not got (docs/delivery.md, "Ends of epochs")."""
        epoch = item["epoch"]
        if self.record.is_complete(epoch):
            conn.give_back(item)  # never acknowledge what we would drop
            return
        yield from owed_padding(self.record, item, padding_copy)
        loader = self.receipts is not None
        taken, keep = conn.take(item, lambda: self.record.claim(epoch, item["batch_id"], item["sample_ids"], loader),
                                ack=not loader)
        if not taken:
            return  # given back meanwhile (revoked before it was granted, or this client said hello again)
        item["padding"] = torch.zeros(len(item["sample_ids"]), dtype=torch.bool)
        if loader:
            if not keep:
                conn.ack([item["batch_id"]])  # nothing new in it: nothing for the loop to receive
                return
            item["receipt"] = Handed(self.worker, item["batch_id"], epoch, self.record.completed_epoch)
        if len(keep) < len(item["sample_ids"]):
            if not keep and self.options.world_size == 1:
                return  # all re-sent duplicates: hand nothing on
            if keep:
                item = select_samples(item, keep)
            else:  # DDP: keep the batch count equal; every sample is a repeat
                item["padding"] = torch.ones(len(item["sample_ids"]), dtype=torch.bool)
        self._last = item
        yield item


def _to_tensors(raw: bool, compact_flow: bool, arrays: dict, flow_size, flow_dtype: str) -> dict:
    """A batch's wire arrays as a stream's tensors (a connection's ``convert``:
    ``tensors.batch_to_torch`` with the stream's ``raw`` and ``compact_flow``)."""
    return batch_to_torch(arrays, raw, flow_size, flow_dtype, compact_flow)

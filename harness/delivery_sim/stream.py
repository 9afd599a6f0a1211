"""One consumer's stream in the simulator: the REAL record (``v2v_client.resume.ResumeState``)
behind a stand-in for ``EndpointStream``'s iteration.

:class:`SimStream` is what ``EndpointStream`` is for one server (the record, whose consumer id
the server knows the reader by, the DDP position, the reader process's ``instance`` token, a
DataLoader worker's receipt pipe); :class:`SimIterator` is one ``iter()`` of it: the record
placed at the stream's DDP position (``ResumeState.place``: a rank's state loaded at another
position is refused before any connection), a
:class:`~harness.delivery_sim.connection.SimConnection`, and step by step what
``EndpointStream.__iter__`` yields: a batch claimed once granted (its samples recorded in the
same step), re-sent samples dropped, DDP padding where owed (as sample ids flagged ``padding``;
no tensors; at the end, what is owed with nothing to repeat), a batch of a completed epoch given
back. Those steps are ``EndpointStream``'s (``_batch``, ``_epoch_done``, ``_server_padding``,
``_unpaid_padding``), which sit beside torch; every decision of the record and the session is
the real objects'.
"""
from __future__ import annotations

import queue
from typing import Callable, Iterator, List, Optional, Tuple

from v2v_client.receipts import Handed
from v2v_client.resume import ResumeState, owed_padding, take_epoch_end
from v2v_client.session import LoopAbandoned, ServerPadding, StreamError
from v2v_wire.stream_messages import Drained, EpochDone

from harness.delivery_sim.connection import ReceiptPipe, SimConnection


class SimStream:
    """One consumer reading one server (``EndpointStream``): ``options`` (``StreamOptions``),
    ``record`` (the real ``ResumeState``: its ``consumer`` is the id the server knows), the
    reader process's ``instance``; a DataLoader worker has ``receipts`` and ``worker`` (its hello
    names ``<consumer>/<worker>``)."""

    def __init__(self, options, consumer: str, instance: str):
        self.options = options
        self.record = ResumeState(consumer)
        self.instance = instance
        self.receipts: Optional[ReceiptPipe] = None
        self.worker: Optional[int] = None
        self.iteration = 0
        self.last: Optional[dict] = None

    @property
    def consumer(self) -> str:
        return self.record.consumer

    def state_dict(self) -> dict:
        return self.record.state()

    def load_state_dict(self, state: dict) -> None:
        self.record.load(state)

    def hello_consumer(self) -> str:
        return self.consumer if self.worker is None else f"{self.consumer}/{self.worker}"


class SimIterator:
    """One iteration of a :class:`SimStream` in process ``host``; ``wake`` is called when
    :meth:`next` may have something new. ``conn`` is None when the record's position was refused
    (``refused``: the ``ValueError``; the iteration raises it)."""

    def __init__(self, stream: SimStream, host, wake: Callable[[], None]):
        self.s = stream
        self.pending: Optional[dict] = None  # the batch waiting for its grant
        self.pads: Iterator[dict] = iter(())  # DDP padding to yield now (``resume.owed_padding``), first
        self.out: List[dict] = []  # loop items ready
        self.finished: Optional[str] = None
        self.abandoned = False
        self.conn: Optional[SimConnection] = None
        self.refused: Optional[ValueError] = None
        o = stream.options
        try:
            stream.record.place(o.group, o.rank, o.world_size)  # EndpointStream._connect
        except ValueError as e:
            self.refused = e
            host.sim.log(host.name, f"resume refused before the first batch: {e}")
            return
        self.conn = SimConnection(host, o, stream.record, stream.hello_consumer(), stream.receipts,
                                  stream.iteration, stream.instance, wake)

    def next(self) -> Tuple[str, object]:
        """The loop's next item: ``("batch", item)`` (``sample_ids``, ``padding`` flags,
        ``epoch``, ``batch_id``, a worker's ``receipt``), ``("wait", None)`` (the consumer
        blocks), ``("end", why)`` or ``("error", exception)``."""
        if self.refused is not None:
            return "error", self.refused
        while True:
            pad = next(self.pads, None)
            if pad is not None:
                return "batch", pad
            if self.out:
                return "batch", self.out.pop(0)
            if self.finished is not None:
                return "end", self.finished
            if self.pending is not None:
                if not self._claim():
                    return "wait", None
                continue
            try:
                item = self.conn.session.items.get_nowait()
            except queue.Empty:
                if self.conn.ended():
                    return self._close("error", StreamError("the connection to the v2v server ended"))
                return "wait", None
            r = self._item(item)
            if r is not None:
                return r

    def _item(self, item) -> Optional[Tuple[str, object]]:
        """``EndpointStream.__iter__``'s dispatch of one item from the connection."""
        s = self.s
        if isinstance(item, StopIteration):
            # EndpointStream._unpaid_padding: zero padding, each counted as the loop takes it, then the end
            self.pads = owed_padding(s.record, {}, _zero_padding)
            self._close("end", str(item))
            return None
        if isinstance(item, LoopAbandoned):
            self.abandoned = True
            return self._close("end", "abandoned")
        if isinstance(item, BaseException):
            return self._close("error", item)
        if isinstance(item, EpochDone):
            self._epoch_done(item)
        elif isinstance(item, Drained):
            if self.conn.ends_on(item):
                return self._close("end", "drained")
        elif isinstance(item, ServerPadding):
            if self.conn.of_session(item):
                self.pads = self._server_padding(_loop_item(item.item, padding=True))
        elif s.record.is_complete(item["epoch"]):
            self.conn.give_back(item)
        else:  # padding owed goes before the claim
            self.pads = owed_padding(s.record, _loop_item(item, padding=True), _padding_copy)
            self.pending = item
        return None

    def _claim(self) -> bool:
        """``EndpointStream._batch`` from its ``conn.take``: False while the grant is awaited."""
        s, item = self.s, self.pending
        loader = s.receipts is not None
        epoch = item["epoch"]
        state, keep = self.conn.try_take(item, lambda: s.record.claim(epoch, item["batch_id"], item["sample_ids"],
                                                                      loader), ack=not loader)
        if state == "wait":
            return False
        self.pending = None
        if state == "gone":
            return True
        out = _loop_item(item, padding=False)
        if loader:
            if not keep:
                self.conn.ack([item["batch_id"]])
                return True
            out["receipt"] = Handed(s.worker, item["batch_id"], epoch, s.record.completed_epoch)
        if len(keep) < len(item["sample_ids"]):
            if not keep and s.options.world_size == 1:
                return True
            if keep:
                out["sample_ids"] = [out["sample_ids"][i] for i in keep]
                out["padding"] = [False] * len(keep)
            else:
                out["padding"] = [True] * len(out["sample_ids"])
        s.last = out
        self.out.append(out)
        return True

    def _epoch_done(self, done: EpochDone) -> None:
        s, ddp = self.s, self.s.options.world_size > 1
        current = self.conn.of_session(done, lambda now_current: take_epoch_end(s.record, done, ddp, now_current))
        if current and s.last is not None:
            self.pads = owed_padding(s.record, s.last, _padding_copy)

    def _server_padding(self, p: dict) -> Iterator[dict]:
        for out in owed_padding(self.s.record, p, _padding_copy, own=True):
            self.s.last = p
            yield out

    def _close(self, kind: str, why) -> Tuple[str, object]:
        """The iteration ends (``EndpointStream.__iter__``'s ``finally``)."""
        self.finished = str(why)
        self.stop()
        return kind, why

    def stop(self, abandoned: bool = False) -> None:
        """Leave the iteration (its end, or the loop's ``break``: ``abandoned``)."""
        s = self.s
        self.abandoned = self.abandoned or abandoned
        if self.finished is None:
            self.finished = "abandoned" if abandoned else "closed"
        if self.conn is None:
            return
        if s.receipts is not None and not self.abandoned and s.record.pipeline:
            self.conn.linger()
        else:
            self.conn.close(unreceived=self.abandoned)
            s.record.clear_pipeline()


def _zero_padding(_source: dict, epoch: int) -> dict:
    """``endpoint.zero_padding`` as the loop sees it: one padding sample of ``epoch``."""
    return {"sample_ids": [""], "padding": [True], "epoch": epoch, "batch_id": -1}


def _loop_item(item: dict, padding: bool) -> dict:
    return {"epoch": item["epoch"], "batch_id": item["batch_id"], "sample_ids": list(item["sample_ids"]),
            "padding": [padding] * len(item["sample_ids"])}


def _padding_copy(batch: dict, epoch: int) -> dict:
    """``endpoint.padding_copy``: a repeat of ``batch`` for ``epoch``, every sample flagged."""
    return {"epoch": epoch, "batch_id": -1, "sample_ids": list(batch["sample_ids"]),
            "padding": [True] * len(batch["sample_ids"])}

"""``StreamLoader``: a torch DataLoader for a ``V2VPushDataset`` read by worker processes.

A DataLoader's workers run ahead of the training loop: each yields up to ``prefetch_factor``
batches into the loader's queues, and an abandoned iteration (``break``, ``max_steps``, a new
``for``) drops whatever is queued. A worker cannot tell which of its batches the loop received,
so it must not acknowledge them when it yields them. ``StreamLoader`` is the part that runs in
the main process: for each batch it hands to the loop it writes a *receipt* (the batch id) to
the worker that made it, over a ``multiprocessing.Pipe`` made before the workers start, and
keeps each worker's record (sample ids received per open epoch). The worker's connection
acknowledges a batch to the server when its receipt arrives; a batch it yielded that the loop
never received is given back to the server when the worker's iterator closes (persistent
workers reset, or workers shut down) and is sent again. So acknowledgement is receipt by the
training loop, whatever the loader does in between.

Workers keep their consumer ids (``<consumer>/<worker id>``) across re-creation; a worker
process made anew resumes from the record the main process kept for it, a persistent one from
its own (the same). ``state_dict()`` / ``load_state_dict()`` checkpoint those records and the
consumer id (torchdata's Stateful convention).

A plain ``DataLoader`` (or torchdata's ``StatefulDataLoader``) with ``num_workers > 0`` cannot
do this: the dataset raises a clear error in its workers. With ``num_workers=0`` any loader
works (the dataset's own I/O thread prefetches ``credits`` batches; acknowledgement happens
when the dataset hands the batch over in the main process).
"""
from __future__ import annotations

import multiprocessing
from typing import Dict, List, Optional, Tuple

import torch

from .launchers import lightning_ahead
from .receipts import Abandon, Handed, Receipt
from .resume import ResumeState

__all__ = ["StreamLoader", "LoaderLink"]


class LoaderLink:
    """What a ``StreamLoader`` gives its dataset for the workers: per worker the read end of
    its receipt pipe and the record the main process keeps (``ResumeState.state()``, plain data
    the worker process is handed)."""

    def __init__(self, num_workers: int, records: Dict[int, dict], context=None):
        ctx = context or multiprocessing
        pipes = [ctx.Pipe(duplex=False) for _ in range(num_workers)]
        self.receipts = [r for r, _ in pipes]
        self._send = [w for _, w in pipes]
        self.records = records
        #: iterations of the loader over these workers so far, less one (persistent workers
        #: serve several; each worker counts its own in ``EndpointStream.attach_loader``)
        self.iteration = 0

    def receipt(self, worker: int, batch_id: int) -> None:
        """Tell ``worker`` the loop received ``batch_id`` (a worker that is gone is ignored: the
        loader raises its own error for it)."""
        self._tell(worker, Receipt((batch_id,)).to_bytes())

    def end_iteration(self) -> None:
        """Tell every worker the loop left iteration ``iteration`` and the loader is about to
        drop what they queued: their batches without a receipt go back to the server, and
        their iterations end at once. Without this a persistent worker's prefetch tasks of the
        left iteration wait for batches while all its credits are held by batches whose
        receipts will never come, and the loader's reset waits for them forever."""
        for w in range(len(self._send)):
            self._tell(w, Abandon(self.iteration).to_bytes())
        self.iteration += 1

    def _tell(self, worker: int, data: bytes) -> None:
        try:
            self._send[worker].send_bytes(data)
        except (OSError, ValueError):
            pass

    def close(self) -> None:
        for c in self._send + self.receipts:
            c.close()


class StreamLoader(torch.utils.data.DataLoader):
    """``torch.utils.data.DataLoader`` over a ``V2VPushDataset``, exact with worker processes.

    Args:
        dataset: a ``V2VPushDataset`` reading one server.
        **kwargs: ``DataLoader`` arguments (``num_workers``, ``persistent_workers``,
            ``prefetch_factor``, ``pin_memory``, ``multiprocessing_context``...); ``batch_size``
            is None (the server makes the batches).

    Yields the dataset's batch dicts. Every batch handed to the loop is acknowledged to the
    server then (see the module docstring); one that a worker yielded but the loop never
    received (an iteration left with ``break``) is sent again, to the next iteration.

    How long it waits: a loop that leaves an iteration (``break``) and iterates again never
    waits on what the left iteration's workers had queued (``LoaderLink.end_iteration``). A
    server silent for the dataset's ``timeout_s`` raises ``StreamTimeout`` naming the server
    within ``timeout_s`` plus about 2 s (the I/O thread's 0.1 s poll, the worker's 1 s wait on
    it, the loader's queue). A worker process that dies raises torch's ``RuntimeError`` naming
    its pid; persistent workers are then shut down, and the next iteration makes them anew from
    the records this process kept (``tests/test_loaders.py`` checks each bound).

    Raises:
        ValueError: ``dataset`` is not a ``V2VPushDataset``, or ``batch_size`` is not None.
    """

    def __init__(self, dataset, **kwargs):
        from .dataset import V2VPushDataset

        if not isinstance(dataset, V2VPushDataset):
            raise ValueError(f"StreamLoader reads a V2VPushDataset, got {type(dataset).__name__}")
        if kwargs.get("batch_size") is not None:
            raise ValueError("StreamLoader: batch_size must be None (the server makes the batches)")
        kwargs["batch_size"] = None
        super().__init__(dataset, **kwargs)
        self._records: Dict[int, ResumeState] = {}  # per worker: what the loop received from it
        self._link: Optional[LoaderLink] = None

    def __bool__(self) -> bool:
        """True: a loader of a stream is one whatever ``len`` says (DataLoader's ``__len__`` asks
        the dataset's, which refuses)."""
        return True

    # ------------------------------------------------------------------ iteration
    def __iter__(self):
        if self.num_workers == 0:
            return super().__iter__()
        if self._link is None or not self.persistent_workers or self._iterator is None:
            # workers are made for this iteration: new pipes, and the records they resume from
            if self._link is not None:
                self._link.close()
            self._link = LoaderLink(self.num_workers, {w: r.state() for w, r in self._records.items()},
                                    self.multiprocessing_context)
            self.dataset.read_by(self._link)
        else:  # persistent workers go on: the previous iteration is over for them first
            self._link.end_iteration()
        return self._receive(super().__iter__())

    def _receive(self, it):
        """The workers' batches, each recorded as received (and its receipt sent) when the loop
        receives it: as it is yielded, or once a Lightning fetcher reading ahead of its loop has
        taken ``lightning_ahead()`` more (``launchers``), so its checkpoints leave those out."""
        ahead = lightning_ahead()
        pending: List[Tuple[Optional[Handed], list]] = []  # yielded, not yet received by the loop
        try:
            for batch in it:
                pending.append((batch.pop("receipt", None), batch["sample_ids"]))
                while len(pending) > ahead:
                    self._received(*pending.pop(0))
                yield batch
            while pending:  # the fetcher hands what it took on now
                self._received(*pending.pop(0))
        except Exception:
            # a worker died or raised: torch keeps persistent workers as they are, so the next
            # iteration would wait on the dead one again; made anew, they resume from the
            # records this process kept
            if self._iterator is not None and self.persistent_workers:
                self._iterator._shutdown_workers()
                self._iterator = None
            raise

    def _received(self, r: Optional[Handed], sample_ids: list) -> None:
        """The loop received a batch with receipt ``r`` (None: no worker's)."""
        if r is not None:
            self._records.setdefault(r.worker, ResumeState()).handed_on(r.epoch, sample_ids, r.completed_epoch)
            self._link.receipt(r.worker, r.batch_id)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """The consumer id and, with workers, each worker's record (epochs completed, sample
        ids the loop received per open epoch); with ``num_workers=0`` the dataset's
        ``state_dict()``. Plain, JSON/torch.save-safe data."""
        if self.num_workers == 0:
            return {"version": 1, "dataset": self.dataset.state_dict()}
        return {"version": 1, "consumer": self.dataset.consumer,
                "workers": {str(w): r.state() for w, r in self._records.items()}}

    def load_state_dict(self, state: dict) -> None:
        """Resume from ``state_dict()``: the next iteration's workers (made anew) start from
        their records, as the same consumers.

        Raises:
            ValueError: a state of another format, or saved with another number of workers.
        """
        if not isinstance(state, dict) or state.get("version") != 1:
            raise ValueError("not a StreamLoader state (expected version 1)")
        if "dataset" in state:
            if self.num_workers:
                raise ValueError("this state was saved with num_workers=0; this loader has workers")
            self.dataset.load_state_dict(state["dataset"])
            return
        workers = {int(w): r for w, r in state.get("workers", {}).items()}
        if self.num_workers == 0 or any(w >= self.num_workers for w in workers):
            raise ValueError(f"this state was saved by a loader with workers {sorted(workers)}; this one has "
                             f"num_workers={self.num_workers}")
        records = {w: ResumeState() for w in workers}
        for w, r in workers.items():
            records[w].load(r)
        self.dataset.consumer = state["consumer"]
        self._records = records
        if self._iterator is not None:  # persistent workers hold their own records: start them anew
            self._iterator._shutdown_workers()
            self._iterator = None

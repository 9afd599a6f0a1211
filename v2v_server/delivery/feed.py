"""The workers' side of the delivery core, pure: which task an idle worker gets (with the outputs
the connected clients ask for), and where each sample a worker makes goes (its open batch).
``core.DeliveryCore`` owns one and hands it its workers' messages."""
from __future__ import annotations

from typing import Callable, Dict, Hashable, Optional, Sequence

from v2v_server.delivery.batcher import Batcher
from v2v_server.delivery.ledger import DeliveryLedger
from v2v_server.delivery.schedule import EpochScheduler, Job
from v2v_wire.ids import SampleKey
from v2v_wire.protocol import OUTPUTS
from v2v_wire.worker_messages import Task


class WorkerFeed:
    """Tasks out to workers, samples in to batches: the outputs workers compute now (``outputs``:
    the union connected clients ask for; None before any hello), each task's outputs, and the
    samples kept (``samples_made``)."""

    def __init__(self, sched: EpochScheduler, ledger: DeliveryLedger, batcher: Batcher):
        self.sched, self.ledger, self.batcher = sched, ledger, batcher
        self.task_outputs: Dict[int, tuple] = {}
        self.outputs: Optional[tuple] = None
        self.samples_made = 0

    def task_for(self, worker: Hashable, now: float, codecs: Sequence[str] = ()) -> Optional[Task]:
        """The ``task`` message for an idle worker, or None (nothing to do, or no client yet).
        Its ``skip`` lists the ``(window, crop)`` of each sample of the video not to make;
        ``codecs``: what the worker compresses each sample with (those clients asked for)."""
        outs = self.ledger.outputs_wanted()
        if outs:
            self.outputs = tuple(o for o in OUTPUTS if o in outs)
        if self.outputs is None:
            return None
        t = self.sched.next_task(worker, now)
        if t is None:
            return None
        self.task_outputs[t.task_id] = self.outputs
        return Task(t.task_id, t.epoch, t.video, self.outputs, tuple((k.window, k.crop) for k in sorted(t.skip)),
                    tuple(codecs))

    def sample(self, worker: Hashable, task_id, key: SampleKey, now: float, build: Callable) -> bool:
        """A worker sent sample ``key`` of ``task_id``'s video; ``build(lane)`` makes the sample
        object (called only when the sample is wanted, with the open batch it joins,
        ``Batcher.lane``, so the data path can copy it into that batch's buffer; it may raise,
        which drops the sample and makes it owed again). Returns True when the sample was kept."""
        key = self.sched.accept_sample(task_id, worker, key, now)
        if key is None:
            return False
        epoch = self.sched.running[task_id].epoch
        outputs = self.task_outputs.get(task_id, ())
        lane = self.batcher.lane(epoch, outputs, self._to_come(epoch))
        try:
            s = build(lane)
        except Exception:
            self.sched.discarded(epoch, [key])
            raise
        self.samples_made += 1
        self.batcher.add(epoch, outputs, key, s, lane)
        return True

    def done(self, worker: Hashable, task_id, windows, failed: dict, error: Optional[str]) -> Optional[Job]:
        """A worker finished a task: ``windows`` complete windows the file gave, ``failed``
        windows (window -> reason), ``error`` when the pass stopped early (see
        ``EpochScheduler.task_done``). Returns the job (None for a late or stranger copy)."""
        job = self.sched.task_done(task_id, worker, windows, failed, error)
        if job is not None:
            self.task_outputs.pop(task_id, None)
        return job

    def _to_come(self, epoch: int) -> Optional[int]:
        """At most how many more samples ``epoch`` brings after the one just accepted, counted
        only until past the shuffle buffer (``lanes x batch_size``): a number over it means at
        least that many, and ``Batcher.lane`` then picks among every open batch, as when the
        count is unknown. None: unknown, or one lane, where no count changes the choice."""
        if self.batcher.lanes == 1:
            return None
        return self.sched.to_come(epoch, self.batcher.lanes * self.batcher.batch_size)

    def drop_delivered(self) -> None:
        """Remove from ready batches and samples waiting for a batch everything some consumer has
        (a resume state said so): they are not sent twice."""
        table = self.ledger.table
        for bid, gone in table.ready_samples(self.sched.is_delivered):
            b = table.get(bid)
            gone_set = set(gone)
            keep = [i for i, k in enumerate(b.keys) if k not in gone_set]
            table.shrink(bid, keep, b.payload.subset(keep) if keep else None)
            self.sched.discarded(b.epoch, gone)
        for epoch, gone in self.batcher.drop(self.sched.is_delivered):
            self.sched.discarded(epoch, gone)

"""The workers' side of the delivery core, pure: which task an idle worker gets (with the outputs
the connected clients ask for), where each sample a worker makes goes (its open batch), and the
clock a task's silence is measured on (:class:`TaskClock`: it runs only while the server reads its
workers). ``core.DeliveryCore`` owns one and hands it its workers' messages."""
from __future__ import annotations

from typing import Callable, Dict, Hashable, List, Optional, Sequence, Tuple

from v2v_server.delivery.batcher import Batcher
from v2v_server.delivery.ledger import DeliveryLedger
from v2v_server.delivery.schedule import EpochScheduler, Job
from v2v_wire.ids import SampleKey
from v2v_wire.protocol import OUTPUTS
from v2v_wire.worker_messages import Task


class TaskClock:
    """The clock a task's silence is measured on (``EpochScheduler.expire``): seconds during which
    the server read its workers' output. A worker's output waits unread while the server does not
    read its workers (back-pressure: enough batches wait for the readers, so a stopped trainer
    stops the reading) and while the server's own loop stalls; a worker blocked on that output
    (its socket or its slot ring full) is silent through no fault of its own, so neither counts.

    Args:
        stall_s: a gap over this many seconds between two :meth:`turn` calls is a stall of the
            server's loop, not counted (the loop turns at least every 0.1 s, ``ledger.STALL_S``);
            None: every gap counts.

    The shell calls :meth:`turn` once per loop turn; until the first call the clock reads the wall
    clock's ``now`` itself (a caller that never calls it counts all the time, as one that always reads).
    """

    def __init__(self, stall_s: Optional[float] = None):
        self.stall_s = stall_s
        self._last: Optional[float] = None  # wall seconds of the last :meth:`turn`
        self._uncounted = 0.0  # wall seconds not counted up to ``_last``

    def _stalled(self, now: float) -> bool:
        return self._last is not None and self.stall_s is not None and now - self._last > self.stall_s

    def at(self, now: float) -> float:
        """The clock's seconds at wall-clock ``now`` (seconds). Within a loop turn the time since the
        last :meth:`turn` counts (the shell asks only in turns that read its workers, or after this
        turn's call), unless it is over ``stall_s``."""
        return (self._last if self._stalled(now) else now) - self._uncounted

    def turn(self, now: float, read: bool) -> None:
        """A turn of the server's loop at wall-clock ``now`` (seconds): since the last one it read its
        workers' output (``read``: it polled them) or not."""
        if self._last is not None and (not read or self._stalled(now)):
            self._uncounted += now - self._last
        self._last = now


class WorkerFeed:
    """Tasks out to workers, samples in to batches: the outputs workers compute now (``outputs``:
    the union connected clients ask for; None before any hello), each task's outputs, and the
    samples kept (``samples_made``); ``clock``: the :class:`TaskClock` (``stall_s``) tasks are timed on."""

    def __init__(self, sched: EpochScheduler, ledger: DeliveryLedger, batcher: Batcher,
                 stall_s: Optional[float] = None):
        self.sched, self.ledger, self.batcher = sched, ledger, batcher
        self.clock = TaskClock(stall_s)
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
        t = self.sched.next_task(worker, self.clock.at(now))
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
        key = self.sched.accept_sample(task_id, worker, key, self.clock.at(now))
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

    def timed_out(self, now: float, reading: bool, task_timeout_s: float) -> List[Tuple[Hashable, Job]]:
        """A loop turn at wall-clock ``now`` that read its workers (``reading``) or not (:meth:`TaskClock.turn`);
        returns the tasks whose worker sent nothing for ``task_timeout_s`` seconds of :attr:`clock`:
        reassigned (``EpochScheduler.expire``), with their workers."""
        self.clock.turn(now, reading)
        return self.sched.expire(self.clock.at(now), task_timeout_s)

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

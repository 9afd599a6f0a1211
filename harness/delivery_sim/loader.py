"""``StreamLoader`` jobs: a training loop over a DataLoader whose worker processes each read the
stream, with the REAL receipts: the main process hands each batch to the loop through the real
``StreamLoader._receive`` (each worker's ``ResumeState.handed_on`` and the typed ``Receipt``),
keeps and checkpoints the records with the real ``StreamLoader.state_dict`` /
``load_state_dict``, and writes receipts and ``abandon`` through the real ``loader.LoaderLink``
(its pipes are the simulator's).

:class:`LoaderJob` is the main process (and the job's lineage); it runs torch's in-order
iteration over an ``IterableDataset`` as ``_MultiProcessingDataLoaderIter`` does:
``prefetch_factor`` requests per worker sent round-robin to the active workers, results taken
in request order, a worker that ends its iteration marked inactive (its requests skipped), the
iteration over when none is active. A loop may leave an iteration early (``break``): persistent
workers are told ``abandon`` and start again; others are shut down (cleanly, or killed) and made
anew from the main process's records. A killed worker makes the iteration raise; the loop then
iterates again, as the docs say. :class:`LoaderWorker` is one worker process: its stream
(consumer ``<consumer>/<worker>``, resuming from the record it was made with) and one
``SimIterator`` per iteration.
"""
from __future__ import annotations

import collections
from typing import Dict, List, Optional

from v2v_client.loader import LoaderLink, StreamLoader
from v2v_client.receipts import received_ids
from v2v_client.resume import ResumeState

from harness.delivery_sim.connection import ReceiptPipe
from harness.delivery_sim.stream import SimIterator, SimStream
from harness.delivery_sim.trainer import Reader, stream_options
from harness.delivery_sim.world import Proc

PIPE_S = 0.0005  # seconds a pipe or queue message takes between processes


class LoaderWorker(Reader):
    """One DataLoader worker process (``w``) of a :class:`LoaderJob`."""

    def __init__(self, job: "LoaderJob", w: int, record: Optional[dict]):
        # the dataset pickled into each worker: the main process's dataset's consumer id and instance
        stream = SimStream(stream_options(job.credits, job.timeout_s), job.consumer, instance=job.instance)
        super().__init__(job.run, f"{job.name}.{job.incarnation}w{w}.{job.made}", stream)
        self.job, self.w = job, w
        self.record = record
        self.requests: collections.deque = collections.deque()
        self.waiting = False
        self.exhausted = False
        self.token = None  # the loader iteration it serves

    def begin(self, receipts: ReceiptPipe, token) -> None:
        """``iter(dataset)`` in this worker: ``EndpointStream.attach_loader`` then a new iteration."""
        s = self.stream
        if self.it is not None:
            self.it.stop()  # attach_loader's close(): the previous iteration's connection ends (receipts first)
            if s.receipts is not None:  # those no connection read
                s.record.received(received_ids(s.receipts.waiting))
                s.receipts.waiting.clear()
            s.record.clear_pipeline()
        if s.receipts is None and self.record is not None:
            s.load_state_dict(self.record)
        s.iteration = s.iteration + 1 if receipts is s.receipts else 0
        s.worker, s.receipts = self.w, receipts
        self.requests.clear()
        self.exhausted = False
        self.token = token
        self.it = SimIterator(s, self, self.wake)

    def request(self, idx: int, token) -> None:
        if token != self.token:  # a request of an iteration this worker left
            return
        self.requests.append(idx)
        self.serve()

    def wake(self) -> None:
        if self.waiting:
            self.waiting = False
            self.sim.after(0.0, self.serve, proc=self.proc)

    def serve(self) -> None:
        """Answer the oldest request with the iterator's next item (after the end: no answer)."""
        while self.requests and not self.proc.dead:
            if self.exhausted:
                self.requests.clear()
                return
            kind, x = self.it.next()
            if kind == "wait":
                self.waiting = True
                return
            idx = self.requests.popleft()
            if kind != "batch":
                self.exhausted = True
            else:
                self.job.flying[id(x)] = x
            self.sim.after(PIPE_S, self.job.result, self, idx, kind, x, self.token, proc=self.job.proc)

    def exit(self, clean: bool) -> None:
        """The loader shuts this worker down: its iterator closed (``clean``: the generator
        finalised as the worker loop returns) or not (SIGTERM after the join times out). A
        stopped process does neither: it dies when it is continued."""
        if self.proc.dead:
            return
        if self.proc.paused_until > self.sim.now:
            self.sim.at(self.proc.paused_until, self._die, proc=None)
        elif clean and self.it is not None:
            self.it.stop(abandoned=True)
            self.proc.dead = True
        else:
            self._die()

    def _die(self) -> None:
        self.kill(False, self.consumer_key())
        self.proc.dead = True

    def pending(self):
        """Also the batches it yielded to the DataLoader without a receipt (in its resume state:
        they reach the loop, or go back when the iteration ends, or are owed again at the next hello)."""
        with self.stream.record.lock:
            queued = [(e, sid) for e, ids in self.stream.record.pipeline.values() for sid in ids]
        return list(super().pending()) + queued

    def consumer_key(self) -> str:
        return f"c:{self.job.consumer}/{self.w}/0"


class _Pipe:
    """A ``multiprocessing.Pipe`` end for ``LoaderLink``: what the main process writes reaches
    worker ``w``'s current process after ``PIPE_S``."""

    def __init__(self, job: "LoaderJob", w: int):
        self.job, self.w, self.read_end = job, w, ReceiptPipe()

    def send_bytes(self, data: bytes) -> None:
        worker = self.job.workers[self.w] if self.w < len(self.job.workers) else None
        if worker is not None and not worker.proc.dead:
            sim = self.job.run.sim
            sim.after(PIPE_S, self.read_end.arrive, data)  # in the pipe, whether the worker runs or not
            sim.after(PIPE_S, self.read_end.poke, proc=worker.proc, lane="io")

    def close(self) -> None:
        pass


class _Context:
    """``LoaderLink``'s ``context``: its ``Pipe()`` makes simulated pipes."""

    def __init__(self, job: "LoaderJob"):
        self.job, self.n = job, 0

    def Pipe(self, duplex: bool = False):  # noqa: N802 (multiprocessing's name)
        p = _Pipe(self.job, self.n)
        self.n += 1
        return p.read_end, p


class LoaderJob:
    """A training job reading through ``StreamLoader(ds, num_workers=workers, ...)`` (the main
    process; its lineage is ``name``).

    Args:
        run: the deployment.
        name: names the processes, the lineage and the consumer id.
        workers, persistent, prefetch: the DataLoader's ``num_workers``, ``persistent_workers``,
            ``prefetch_factor``.
        credits, timeout_s: the dataset's.
        breaks: the chance that the loop leaves its iteration after a batch (``break``, a new ``for``).
        in_memory: checkpoints keep ``loader.state_dict()``'s object itself (else a copy, as
            ``torch.save`` makes).
    """

    def __init__(self, run, name: str, workers: int = 2, persistent: bool = False, prefetch: int = 2,
                 credits: int = 2, timeout_s: float = 30.0, honest: bool = True, ckpt_every: int = 2,
                 step_s=(0.005, 0.05), breaks: float = 0.0, in_memory: bool = False):
        self.run, self.sim, self.name = run, run.sim, name
        self.num_workers, self.persistent, self.prefetch = workers, persistent, prefetch
        self.credits, self.timeout_s = credits, timeout_s
        self.consumer = self.lineage = name
        self.ckpt_every, self.step_s, self.breaks, self.in_memory = ckpt_every, step_s, breaks, in_memory
        run.oracle.lineage(name, honest)
        if honest:
            run.oracle.owners.update(f"c:{name}/{w}/0" for w in range(workers))
        self._records: Dict[int, ResumeState] = {}  # StreamLoader._records (its real methods write it)
        self._iterator = None  # what StreamLoader.load_state_dict shuts down (never a torch iterator here)
        self.instance = name
        self.checkpoints: List[tuple] = [({"version": 1, "consumer": name, "workers": {}}, 0)]
        self.incarnation = self.made = self.steps = 0
        self.proc: Optional[Proc] = None
        self.workers: List[LoaderWorker] = []
        self.link: Optional[LoaderLink] = None
        self.gone = self.waiting = False
        self.failed: Optional[int] = None  # a worker of this iteration died
        self.flying: Dict[int, dict] = {}  # batches a worker sent this process, not yet read
        self.task_info: Dict[int, list] = {}
        run.oracle.live_clients.append(self)

    # ------------------------------------------------------------------ what the oracle asks
    def alive(self) -> bool:
        return self.proc is not None and not self.proc.dead

    def held(self) -> int:
        return 0

    def credit_limit(self) -> int:
        return 0

    def pending(self):
        """Batches in the loader's queues: sent by a worker, not yet given to the loop."""
        items = list(self.flying.values()) + [i[1] for i in self.task_info.values() if len(i) == 2]
        return [(x["epoch"], sid) for x in items for sid, pad in zip(x["sample_ids"], x["padding"]) if not pad]

    # ------------------------------------------------------------------ the job
    def start(self, state: Optional[dict] = None) -> None:
        if self.gone:
            return
        self.incarnation += 1
        self.proc = Proc(f"{self.name}.{self.incarnation}")
        self.instance = self.proc.name  # a new main process: a new dataset
        self._records = {}
        if state is not None:
            StreamLoader.load_state_dict(self, state)  # the real one
        self.workers, self.link = [], None
        self.sim.after(0.0, self._iterate, proc=self.proc)

    def procs(self) -> list:
        return [w for w in self.workers if not w.proc.dead] if self.proc is not None and not self.proc.dead else []

    def kill(self, for_good: bool = False) -> None:
        for w in self.workers:
            w.kill(for_good, w.consumer_key())
        if self.proc is not None and not self.proc.dead:
            self.run.oracle.killed(f"c:{self.consumer}/main", self.pending(), 0, for_good)
            self.proc.dead = True
        if for_good:
            self.gone = True
            self.run.oracle.lineages[self.lineage].dead_for_good = True

    def restart(self, back: int = 0, gap: float = 0.0) -> None:
        """Kill the job; ``gap`` s later start again from ``loader.state_dict()`` of a checkpoint."""
        if self.gone:
            return
        self.kill()
        i = max(0, len(self.checkpoints) - 1 - back)
        state, kept = self.checkpoints[i]
        del self.checkpoints[i + 1:]  # the job goes on from there
        self.run.oracle.rolled_back(self.lineage, kept)
        self.sim.log(self.name, f"restarts in {gap:.2f} s from a loader checkpoint ({kept} samples)")
        self.sim.after(gap, self.start, state)

    def kill_worker(self, w: int) -> None:
        """SIGKILL one worker process: torch notices it (its watchdog) and the iteration raises."""
        if w < len(self.workers) and not self.workers[w].proc.dead and self.proc is not None and not self.proc.dead:
            self.workers[w].kill(False, self.workers[w].consumer_key())
            self.sim.after(self.sim.uniform(0.0, 5.0), self._worker_died, w, proc=self.proc)

    def _worker_died(self, w: int) -> None:
        self.failed = w
        self._wake()

    # ------------------------------------------------------------------ one iteration
    def _iterate(self) -> None:
        """``iter(loader)``: persistent workers are told ``abandon`` and go on; else workers
        are made anew from the records (the old ones shut down)."""
        pf, n = self.prefetch, self.num_workers
        alive = self.workers and all(not w.proc.dead for w in self.workers)
        if self.persistent and alive and self.link is not None and self.failed is None:
            self.link.end_iteration()
        else:
            clean = self.sim.chance(0.5)
            for w in self.workers:
                w.exit(clean)
            self.link = LoaderLink(n, {w: r.state() for w, r in self._records.items()}, _Context(self))
            self.made += 1
            self.workers = [LoaderWorker(self, w, self.link.records.get(w)) for w in range(n)]
        self.token = (self.incarnation, self.made, getattr(self, "token", (0, 0, 0))[2] + 1)
        for w in self.workers:
            self.sim.after(2 * PIPE_S, w.begin, self.link.receipts[w.w], self.token, proc=w.proc)
        self.failed = None
        self.send_idx = self.rcvd_idx = self.outstanding = 0
        self.task_info = {}
        self.status = [True] * n
        self.how: Dict[int, str] = {}
        self.cycle = 0
        for _ in range(pf * n):
            self._put_index()
        self.waiting = False
        self.sim.after(0.0, self._loop, proc=self.proc)

    def _put_index(self) -> None:
        if self.outstanding >= self.prefetch * self.num_workers:
            return
        for _ in range(self.num_workers):
            w = self.cycle % self.num_workers
            self.cycle += 1
            if self.status[w]:
                break
        else:
            return
        self.task_info[self.send_idx] = [w]
        worker = self.workers[w]
        self.sim.after(3 * PIPE_S, worker.request, self.send_idx, self.token, proc=worker.proc)
        self.send_idx += 1
        self.outstanding += 1

    def result(self, worker: LoaderWorker, idx: int, kind: str, x, token) -> None:
        """A worker's answer to request ``idx`` of iteration ``token`` (in this process; the
        answers of an iteration left are dropped, as ``_MultiProcessingDataLoaderIter._reset`` does)."""
        self.flying.pop(id(x), None)
        if token != self.token or worker not in self.workers or idx not in self.task_info:
            return
        self.outstanding -= 1
        if kind == "batch":
            self.task_info[idx].append(x)
        else:
            self.status[worker.w] = False
            self.how[worker.w] = f"{kind}: {x}"
            if kind == "error":
                self.failed = worker.w
            self._put_index()
        self._wake()

    def _wake(self) -> None:
        if self.waiting:
            self.waiting = False
            self.sim.after(0.0, self._loop, proc=self.proc)

    def _next(self):
        """``_MultiProcessingDataLoaderIter._next_data`` for an in-order iterable dataset."""
        if self.failed is not None:
            return "error", f"DataLoader worker {self.failed} exited unexpectedly"
        while True:
            while self.rcvd_idx < self.send_idx:
                info = self.task_info.get(self.rcvd_idx)
                if info and (len(info) == 2 or self.status[info[0]]):
                    break
                self.task_info.pop(self.rcvd_idx, None)
                self.rcvd_idx += 1
            else:
                return "stop", None
            info = self.task_info[self.rcvd_idx]
            if len(info) < 2:
                return "wait", None
            del self.task_info[self.rcvd_idx]
            self.rcvd_idx += 1
            self._put_index()
            return "batch", info[1]

    def _loop(self) -> None:
        """The training loop: ``for batch in loader`` (``StreamLoader._receive``), stepping and checkpointing."""
        kind, x = self._next()
        if kind == "wait":
            self.waiting = True
            return
        if kind == "batch":
            x = next(StreamLoader._receive(self, iter([x])))  # the real main process: record, receipt
            self.run.oracle.yielded(self.lineage, x)
            self.steps += 1
            if self.steps % self.ckpt_every == 0:
                self._checkpoint()
            if self.sim.chance(self.breaks):
                self.sim.log(self.name, "breaks out of its loop")
                self.sim.after(self.sim.uniform(*self.step_s), self._iterate, proc=self.proc)
            else:
                self.sim.after(self.sim.uniform(*self.step_s), self._loop, proc=self.proc)
            return
        if kind == "stop" and all(h in ("end: end of stream", "end: drained") for h in self.how.values()):
            # the iteration ran to its end: the loop is over (harness.faults.scenario_loader_workers's
            # loop too); the docs' Drained rule says nothing can come back to it
            self.run.oracle.ended(self.lineage)
            return
        self.sim.log(self.name, f"iteration over ({kind}: {x or self.how}); iterating again")
        self.sim.after(0.05, self._iterate, proc=self.proc)

    def _checkpoint(self) -> None:
        import copy

        state = StreamLoader.state_dict(self)  # the real one
        self.checkpoints.append((state if self.in_memory else copy.deepcopy(state),
                                 len(self.run.oracle.lineages[self.lineage].history)))

    # what StreamLoader's methods read of a loader
    _received = StreamLoader._received  # the real receipt of a batch the loop received

    @property
    def dataset(self):
        return self

    @property
    def _link(self):
        return self.link

    @property
    def persistent_workers(self) -> bool:
        return self.persistent

    def state_dict(self):  # noqa: D102 (only for StreamLoader.state_dict's num_workers == 0 branch)
        raise AssertionError("a simulated loader has workers")

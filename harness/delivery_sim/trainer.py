"""Trainers: a training loop over one ``V2VPushDataset`` (``num_workers=0``) in a process
that can be paused, killed and restarted from one of its checkpoints.

A :class:`TrainerJob` is one job (one lineage of the oracle, one consumer id unless told
otherwise) and its checkpoints; each (re)start is a :class:`Trainer` process: it iterates its
stream, trains ``step_s`` seconds on each batch, checkpoints every ``ckpt_every`` steps (the
stream's ``state_dict()``), and may stop calling ``next()`` for a while (a validation pass)
while its I/O thread goes on.
"""
from __future__ import annotations

from typing import Iterable, List, Optional, Tuple

from v2v_client.options import StreamOptions
from v2v_server.delivery.schedule import KEEP_EPOCHS

from harness.delivery_sim.oracle import BEHIND
from harness.delivery_sim.stream import SimIterator, SimStream
from harness.delivery_sim.world import Proc

Key = Tuple[int, str]


def stream_options(credits: int = 2, timeout_s: float = 30.0, reconnect: bool = False, rank: int = 0,
                   world_size: int = 1, group: str = "default") -> StreamOptions:
    """The options a simulated dataset reads its server with (no compression, no shared memory)."""
    return StreamOptions(outputs=("voxels",), credits=credits, timeout_s=timeout_s, heartbeat_s=1.0, raw=False,
                         reconnect=reconnect, reconnect_timeout_s=300.0, curve_keys=None, rank=rank,
                         world_size=world_size, group=group, shm=False, compression="none")


class Reader:
    """A process reading one stream: what the oracle asks of every client process."""

    def __init__(self, run, name: str, stream: SimStream):
        self.run, self.sim, self.net = run, run.sim, run.net
        self.proc = Proc(name)
        self.name = name
        self.stream = stream
        self.it: Optional[SimIterator] = None
        run.oracle.live_clients.append(self)

    def alive(self) -> bool:
        return not self.proc.dead

    def conn(self):
        """The live connection of its current iteration, or None."""
        c = self.it.conn if self.it is not None else None
        return c if c is not None and c.alive else None

    def held(self) -> int:
        c = self.conn()
        return c.held() if c is not None else 0

    def credit_limit(self) -> int:
        return self.stream.options.credits

    def pending(self) -> Iterable[Key]:
        """What is on its way to this process's loop: batches asked or granted, the one
        awaiting its grant, items claimed and not yet yielded."""
        if self.it is None or self.it.conn is None:
            return ()
        out = []
        held = self.it.conn.session.held
        for bid in held.asked | held.granted:
            item = held.current.get(bid)
            if item is not None:
                out += [(item["epoch"], s) for s in item["sample_ids"]]
        if self.it.pending is not None:
            p = self.it.pending
            out += [(p["epoch"], s) for s in p["sample_ids"]]
        for x in self.it.out:
            out += [(x["epoch"], s) for s, pad in zip(x["sample_ids"], x["padding"]) if not pad]
        return out

    def pending_batches(self) -> int:
        if self.it is None or self.it.conn is None:
            return 0
        held = self.it.conn.session.held
        return len(held.asked | held.granted) + (self.it.pending is not None) + len(self.it.out)

    def kill(self, for_good: bool, consumer: str) -> None:
        """SIGKILL: the process and its socket go; what it held is on no way to a loop now."""
        if self.proc.dead:
            if for_good:  # died before: its consumer is gone for good now
                self.run.oracle.killed(consumer, (), 0, True)
            return
        self.sim.log(self.name, "killed" + (" for good" if for_good else ""))
        self.run.oracle.killed(consumer, self.pending(), self.pending_batches(), for_good)
        self.proc.dead = True
        if self.it is not None and self.it.conn is not None:
            self.it.conn.killed()


class Trainer(Reader):
    """One process of a :class:`TrainerJob`."""

    def __init__(self, job: "TrainerJob", incarnation: int, state: Optional[dict]):
        name = f"{job.name}.{incarnation}"
        stream = SimStream(job.options, job.consumer, instance=name)  # a new process: a new dataset
        if state is not None:
            stream.load_state_dict(state)
        super().__init__(job.run, name, stream)
        self.job = job
        self.waiting = False
        self.done = False
        self.steps = 0
        self.idle_until = 0.0
        self.sim.after(0.0, self._start, proc=self.proc)

    def _start(self) -> None:
        self.it = SimIterator(self.stream, self, self.wake)
        self._loop()

    def wake(self) -> None:
        if self.waiting and not self.done:
            self.waiting = False
            self.sim.after(0.0, self._loop, proc=self.proc)

    def _loop(self) -> None:
        if self.done:
            return
        if self.sim.now < self.idle_until:  # the loop does something else; the I/O thread goes on
            self.sim.at(self.idle_until, self._loop, proc=self.proc)
            return
        kind, x = self.it.next()
        if kind == "wait":
            self.waiting = True
            return
        if kind == "batch":
            self.run.oracle.yielded(self.job.lineage, x)
            self.steps += 1
            if self.job.stop_epoch is not None and x["epoch"] >= self.job.stop_epoch:  # the user stops there
                self.done = True
                self.it.stop(abandoned=True)
                self.run.oracle.ended(self.job.lineage)
                return
            if self.steps % self.job.ckpt_every == 0:
                self.job.checkpoint(self.stream.state_dict())
            lo, hi = self.job.step_s
            self.sim.after(self.sim.uniform(lo, hi), self._loop, proc=self.proc)
            return
        self.done = True
        if kind == "end" and x == "end of stream":
            self.run.oracle.ended(self.job.lineage)
        elif kind == "error":
            self.job.failed(self, x)

    def break_loop(self) -> None:
        """The loop leaves its ``for`` (``break``, ``max_steps``) and starts a new one: the
        iterator is closed (acks sent, what is granted and not taken given back, ``bye``) and a
        new connection says hello with the record."""
        if self.done or self.it is None:
            return
        self.sim.log(self.name, "breaks out of its loop and iterates again")
        self.it.stop(abandoned=True)
        self.waiting = False
        self.it = SimIterator(self.stream, self, self.wake)
        self.sim.after(0.0, self._loop, proc=self.proc)

    def stop_reading(self, seconds: float) -> None:
        """The loop stops calling ``next()`` for ``seconds`` (a validation pass, a debugger)."""
        self.idle_until = max(self.idle_until, self.sim.now + seconds)
        self.sim.log(self.name, f"stops reading for {seconds:.1f} s")


class TrainerJob:
    """One training job reading one server through a plain dataset.

    Args:
        run: the simulated deployment (``Run``).
        name: names its processes and its lineage.
        options: its ``StreamOptions``.
        consumer: the consumer id (two jobs given the same one are the issue's mistake).
        honest: a dishonest job's failures are not the protocol's.
        ckpt_every, step_s: steps between checkpoints; seconds a step takes (range).
        stop_epoch: on an unbounded stream, the job stops once it got a batch of this epoch.
    """

    def __init__(self, run, name: str, options, consumer: Optional[str] = None, honest: bool = True,
                 ckpt_every: int = 2, step_s: Tuple[float, float] = (0.005, 0.05), stop_epoch: Optional[int] = None):
        self.run, self.name, self.options = run, name, options
        self.timeout_s = options.timeout_s
        self.consumer = consumer or name
        self.lineage = name
        self.ckpt_every, self.step_s = ckpt_every, step_s
        self.stop_epoch = stop_epoch  # an unbounded stream: the user stops after a batch of this epoch
        run.oracle.lineage(name, honest)
        self.key = f"c:{self.consumer}/0"  # as the server keys its consumer
        if honest:
            run.oracle.owners.add(self.key)
        self.checkpoints: List[Tuple[dict, int]] = [({"version": 1, "consumer": self.consumer, "completed_epoch": -1,
                                                      "delivered": {}, "batches": {}}, 0)]
        self.incarnation = 0
        self.proc: Optional[Trainer] = None
        self.gone = False  # died for good: never starts again

    def start(self, state: Optional[dict] = None) -> Optional[Trainer]:
        if self.gone:
            return None
        self.incarnation += 1
        self.proc = Trainer(self, self.incarnation, state)
        return self.proc

    def checkpoint(self, state: dict) -> None:
        self.checkpoints.append((state, len(self.run.oracle.lineages[self.lineage].history)))

    def kill(self, for_good: bool = False) -> None:
        if self.proc is not None:
            self.proc.kill(for_good, self.key)
        if for_good:
            self.gone = True
            self.run.oracle.lineages[self.lineage].dead_for_good = True

    def restart(self, back: int = 0, gap: float = 0.0) -> None:
        """Kill the process; ``gap`` seconds later start again from the newest checkpoint but
        ``back`` (an older one, as a user may pick). The model forgets what came after that
        checkpoint from the kill on."""
        if self.gone:
            return
        self.kill()
        i = max(0, len(self.checkpoints) - 1 - back)
        state, kept = self.checkpoints[i]
        del self.checkpoints[i + 1:]  # the job goes on from there: later checkpoints were another timeline
        self.run.oracle.rolled_back(self.lineage, kept)
        self.run.sim.log(self.name, f"restarts in {gap:.2f} s from checkpoint {i} ({kept} samples)")
        self.run.sim.after(gap, self.start, state)

    def procs(self) -> List[Trainer]:
        return [self.proc] if self.proc is not None and not self.proc.proc.dead else []

    def failed(self, trainer: Trainer, err) -> None:
        """The stream raised: an honest job's error is a finding (the oracle reports it at the end),
        but a refusal the job may get (``Lineage.refusable``). A resume state refused as too far
        behind its consumer's epochs (limit (e)) is read as a user would: the job has no newer
        checkpoint (a restart drops those), so it reads on as a new consumer, without a state."""
        self.run.sim.log(trainer.name, f"stream error: {err}")
        if BEHIND in str(err) and not self.gone:
            completed = trainer.stream.state_dict()["completed_epoch"]
            self.run.oracle.refused_behind(self.lineage, self.key, completed, KEEP_EPOCHS)
            self.consumer = f"{self.consumer}+"
            self.key = f"c:{self.consumer}/0"
            self.run.oracle.owners.add(self.key)
            self.checkpoints = [({"version": 1, "consumer": self.consumer, "completed_epoch": -1, "delivered": {},
                                  "batches": {}}, len(self.run.oracle.lineages[self.lineage].history))]
            self.start()
            return
        self.run.oracle.lineages[self.lineage].error = f"{type(err).__name__}: {err}"

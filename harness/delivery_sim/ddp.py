"""DDP jobs: ``world_size`` rank processes, one dataset each (``rank=r, world_size=n``), stepping
in lockstep (each step's all-reduce waits for every rank's batch), killed and restarted
together (as torchrun restarts a group), possibly at another world size.

A job's group is ``group=`` when given, else the one its loaded state was saved in, else named
from what its launcher set (``options.job_group`` of the job's environment: torchrun's run id
and rendezvous port, the same for an elastic restart, another for another job; none by hand:
``"default"``), as ``dataset.resolve_position`` does. A rank's state loaded at another position
is refused before the first batch (``ResumeState.place``); the job then restarts as the error
says, every rank loading every rank's state (``ResumeState.gathered``, as
``dataset.state_for_rank`` does for a list at another world size).

A rank's batches are DDP padding where the server or the dataset flags them (``padding``): the
oracle keeps only the rest. Every rank must yield the same number of batches: a rank whose
stream ends while another got a batch would leave the job hanging in its next all-reduce, which
the job reports as a liveness failure.
"""
from __future__ import annotations

from typing import Dict, List, Optional, Tuple

from v2v_client.launchers import rank_part
from v2v_client.options import job_group
from v2v_client.resume import ResumeState
from v2v_server.delivery.schedule import KEEP_EPOCHS

from harness.delivery_sim.oracle import BEHIND
from harness.delivery_sim.stream import SimIterator, SimStream
from harness.delivery_sim.trainer import Reader, stream_options


def rank_states(states: List[Optional[dict]], world: int, load: str) -> List[Optional[dict]]:
    """What each of ``world`` new ranks loads of the states a job saved (one per old rank):
    ``"own"``, its own old rank's (none for a rank the old job lacked); ``"gathered"``, every
    rank's states (``dataset.state_for_rank``: its own rank's part at the world size they were
    saved at, ``launchers.rank_part``; else all of them gathered)."""
    if all(st is None for st in states):
        return [None] * world
    if load == "own":
        return [states[r] if r < len(states) else None for r in range(world)]
    if len(states) == world:
        return [rank_part({"v2v_ranks": states}, lambda r=r: (r, world)) for r in range(world)]
    merged = ResumeState.gathered(states).state()
    return [merged] * world


class Rank(Reader):
    """One rank's process of a :class:`DDPJob` incarnation."""

    def __init__(self, job: "DDPJob", rank: int, world: int, incarnation: int, state: Optional[dict]):
        name = f"{job.name}.{incarnation}r{rank}"
        saved = (state or {}).get("group") if (state or {}).get("world_size", 1) > 1 else None
        group = job.group or saved or job_group(job.environ)
        stream = SimStream(stream_options(job.credits, job.timeout_s, rank=rank, world_size=world, group=group),
                           job.consumer, instance=name)
        if state is not None:
            stream.load_state_dict(state)
        super().__init__(job.run, name, stream)
        self.job, self.rank = job, rank
        self.item: Optional[Tuple[str, object]] = None  # what this rank brings to the current step
        self.waiting = False
        self.sim.after(0.0, self._start, proc=self.proc)

    def _start(self) -> None:
        self.it = SimIterator(self.stream, self, self.wake)
        self.step()

    def wake(self) -> None:
        if self.waiting:
            self.waiting = False
            self.sim.after(0.0, self.step, proc=self.proc)

    def step(self) -> None:
        """Ask the stream for this step's batch (once it comes, wait at the all-reduce)."""
        if self.item is not None or self.proc.dead:
            return
        kind, x = self.it.next()
        if kind == "wait":
            self.waiting = True
            return
        if kind == "error":
            self.job.failed(self, x)
            return
        self.item = (kind, x)
        self.job.arrived()

    def pending(self):
        out = list(super().pending())
        if self.item is not None and self.item[0] == "batch":  # claimed, waiting at the all-reduce
            x = self.item[1]
            out += [(x["epoch"], s) for s, pad in zip(x["sample_ids"], x["padding"]) if not pad]
        return out

    def pending_batches(self) -> int:
        return super().pending_batches() + (self.item is not None and self.item[0] == "batch")

    def consumer_key(self) -> str:
        o = self.stream.options
        return f"g:{o.group}/{self.rank}" if o.world_size > 1 else f"c:{self.stream.consumer}/0"


class DDPJob:
    """A DDP job of ``world`` ranks in ``group`` (its lineage: ``name``).

    Args:
        run: the deployment.
        name: names the ranks' processes and the lineage.
        world: the world size it starts with.
        group: the ``group=`` argument (None: derived, module docstring).
        launcher: what the job's launcher set (``options.LAUNCHER_VARIABLES``; default: torchrun's
            run id and rendezvous port of this job; ``{}``: ranks started by hand).
        credits, timeout_s: each rank's dataset's.
        ckpt_every, step_s: steps between checkpoints; a step's seconds (range).
    """

    def __init__(self, run, name: str, world: int, group: Optional[str] = None,
                 launcher: Optional[Dict[str, str]] = None, credits: int = 2, timeout_s: float = 30.0,
                 honest: bool = True, ckpt_every: int = 2, step_s=(0.005, 0.05)):
        self.run, self.name, self.group = run, name, group
        self.environ = {"TORCHELASTIC_RUN_ID": f"{name}-run", "MASTER_PORT": str(29500 + len(name))} \
            if launcher is None else launcher
        self.credits, self.timeout_s = credits, timeout_s
        self.consumer = name
        self.lineage = name
        self.ckpt_every, self.step_s = ckpt_every, step_s
        run.oracle.lineage(name, honest)
        self.world = world
        self.checkpoints: List[Tuple[List[Optional[dict]], int]] = [([None] * world, 0)]
        self.incarnation = 0
        self.ranks: List[Rank] = []
        self.steps = 0
        self.done = False
        self.gone = False  # died for good: never starts again

    def start(self, world: Optional[int] = None, states: Optional[List[Optional[dict]]] = None) -> None:
        if self.gone:
            return
        world = world or self.world
        self.incarnation += 1
        self.world = world
        states = states or [None] * world
        self.ranks = [Rank(self, r, world, self.incarnation, states[r] if r < len(states) else None)
                      for r in range(world)]
        if self.run.oracle.lineages[self.lineage].honest:
            self.run.oracle.owners.update(r.consumer_key() for r in self.ranks)

    def failed(self, rank: Rank, err) -> None:
        """A rank's stream raised: the launcher takes the job down. A rank's state refused before
        its first batch (``ResumeState.place``'s ``ValueError``): the job restarts from the same
        checkpoint, every rank loading every rank's state, as the error says. A state refused as too
        far behind the epochs told a rank it speaks for (limit (e)): the job reads on as a new
        consumer, as the error says (no state, a new ``group=``), as ``TrainerJob.failed`` does. Any
        other error ends the job (its ranks are gone for good; an honest job's error is a finding)."""
        if self.done:
            return
        self.done = True
        if isinstance(err, ValueError):
            self.run.sim.log(self.name, f"rank {rank.rank} refused its state; restarting with every rank's state")
            self.restart(back=0, gap=self.run.sim.uniform(0.0, 1.0), world=self.world, load="gathered")
            return
        if BEHIND in str(err) and not self.gone:
            self._read_on_anew(rank)
            return
        self.run.sim.log(self.name, f"rank {rank.rank} failed: {err}; the job ends")
        self.run.oracle.lineages[self.lineage].error = f"rank {rank.rank}: {type(err).__name__}: {err}"
        self.kill(for_good=True)

    def _read_on_anew(self, rank: Rank) -> None:
        """``rank``'s resume state was refused as too far behind the epochs its consumers were
        told complete (docs/delivery.md, limit (e)): the job has no newer checkpoint (a restart
        drops those), so it reads on as the error says, a new job under a new group= (and a new
        consumer id, what a job of world size 1 is known by), without a state. The consumers the
        state spoke for are never read again; what the model forgot is given up."""
        oracle = self.run.oracle
        completed = rank.stream.state_dict()["completed_epoch"]
        group = rank.stream.options.group
        gone = {r.consumer_key() for r in self.ranks} | {f"c:{self.consumer}/0"} | \
            {f"g:{group}/{r}" for r in range(max(3, self.world))}
        for key in sorted(gone):
            oracle.refused_behind(self.lineage, key, completed, KEEP_EPOCHS)
        self.kill()
        self.done = False
        self.consumer, self.group = f"{self.consumer}+", f"{group}+"
        self.checkpoints = [([None] * self.world, len(oracle.lineages[self.lineage].history))]
        self.start(self.world)

    def arrived(self) -> None:
        """A rank brought its item: once every rank has, the step runs (or the job ends)."""
        if any(r.item is None for r in self.ranks):
            return
        kinds = {r.item[0] for r in self.ranks}
        oracle = self.run.oracle
        if kinds == {"batch"}:
            for r in self.ranks:
                oracle.yielded(self.lineage, r.item[1])
                r.item = None
            self.steps += 1
            if self.steps % self.ckpt_every == 0:
                self.checkpoints.append(([r.stream.state_dict() for r in self.ranks],
                                         len(oracle.lineages[self.lineage].history)))
            lo, hi = self.step_s
            dt = self.run.sim.uniform(lo, hi)
            for r in self.ranks:
                self.run.sim.after(dt, r.step, proc=r.proc)
            return
        self.done = True
        if "batch" in kinds:
            got = [r.rank for r in self.ranks if r.item[0] == "batch"]
            ended = [(r.rank, r.item[1]) for r in self.ranks if r.item[0] != "batch"]
            self.run.sim.fail("liveness", f"{self.name}: rank(s) {got} got a batch while rank(s) {ended} ended: the "
                                          f"job hangs in its next all-reduce")
        if all(r.item[1] == "end of stream" for r in self.ranks):
            oracle.ended(self.lineage)

    def kill(self, for_good: bool = False) -> None:
        for r in self.ranks:
            r.kill(for_good, r.consumer_key())
        if for_good:
            self.gone = True
            self.run.oracle.lineages[self.lineage].dead_for_good = True

    def restart(self, back: int = 0, gap: float = 0.0, world: Optional[int] = None, load: str = "own") -> None:
        """Kill every rank; ``gap`` seconds later start again from a checkpoint (``back``: that
        many older) at ``world`` ranks, each loading what :func:`rank_states` says for ``load``.
        A restart from no state (before the first checkpoint) from or to world size 1 is a new
        job to the server (a reader of world size 1 is known by its consumer id, not its group:
        docs/delivery.md, "Limits"): the old ranks are gone for good, and what they handed to
        their loop stays handed."""
        if self.gone:
            return
        old = list(self.ranks)
        self.kill()
        self.done = False
        i = max(0, len(self.checkpoints) - 1 - back)
        states, kept = self.checkpoints[i]
        del self.checkpoints[i + 1:]  # the job goes on from there
        world = world or len(states)
        if world != len(states) and 1 in (world, len(states)) and all(st is None for st in states):
            for r in old:
                self.run.oracle.killed(r.consumer_key(), (), 0, True)
        else:
            self.run.oracle.rolled_back(self.lineage, kept)
        self.run.sim.log(self.name, f"restarts in {gap:.2f} s at world size {world} from a checkpoint of "
                                    f"{len(states)} rank(s) ({kept} samples), loading {load}")
        self.run.sim.after(gap, self.start, world, rank_states(states, world, load))

    def procs(self) -> List[Rank]:
        return [r for r in self.ranks if not r.proc.dead]

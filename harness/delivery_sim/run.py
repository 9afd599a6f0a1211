"""One simulated deployment: the world, the network, the server (restartable from its journal),
the jobs reading it, the faults, and the checks; :func:`simulate` runs one to its end.

A :class:`Setup` holds a run's choices (what a scenario draws from the seed or fixes): the
corpus, the delivery policy, the server's workers and prefetch, a journal or not, the network's
faults, and when the run is judged (``deadline``: every honest trainer's stream must have ended
by then). A scenario builds a :class:`Run` from a ``Setup``, adds jobs and schedules faults
(``run.at``), then ``simulate`` runs it: the oracle checks after every step and at the end.
"""
from __future__ import annotations

import logging
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from typing import Callable, List, Optional

from v2v_server.delivery.core import DeliveryPolicy
from v2v_wire.messages import Released

from harness.delivery_sim.net import Net, NetFaults
from harness.delivery_sim.oracle import Oracle
from harness.delivery_sim.server import Corpus, ServerConfig, ServerProbe, SimServer
from harness.delivery_sim.workers import WorkerFaults
from harness.delivery_sim.world import Sim, Violation


@dataclass
class Setup:
    """A run's choices (seconds are simulated seconds)."""

    corpus: Corpus
    policy: DeliveryPolicy
    workers: int = 2
    prefetch: int = 4
    journal: bool = False
    net: NetFaults = field(default_factory=NetFaults)
    worker_faults: WorkerFaults = field(default_factory=WorkerFaults)
    sample_s: tuple = (0.002, 0.02)
    deadline: float = 120.0

    def epoch_size(self) -> int:
        return len(self.corpus.epoch_ids())


class Run:
    """The deployment of one seed (``setup``), with ``trace`` lines when asked; ``rng``: the
    random source ``setup`` was drawn from (the run goes on drawing from it)."""

    def __init__(self, seed: int, setup: Setup, trace: bool = False, rng=None):
        self.seed, self.setup = seed, setup
        self.sim = Sim(seed, trace)
        if rng is not None:
            self.sim.rng = rng  # the one random source the setup was drawn from
        self.net = Net(self.sim, setup.net)
        self.state_dir = tempfile.mkdtemp(prefix="v2v-sim-", dir=_tmp_root()) if setup.journal else None
        self.cfg = ServerConfig(setup.corpus, setup.policy, setup.workers, setup.prefetch, self.state_dir,
                                sample_s=setup.sample_s, worker_faults=setup.worker_faults)
        self.oracle = Oracle(self.sim, setup.corpus, setup.policy.epochs, setup.epoch_size())
        self.jobs: list = []
        self.incarnation = 0
        self.server: Optional[SimServer] = None
        self.probe: Optional[ServerProbe] = None
        self._told = -1
        self.last_fault = 0.0
        self.on_announced: List[Callable[[int], None]] = []  # a scenario's actions when an epoch is announced
        try:
            self.start_server()
        except BaseException:  # no run to clean up after: its journal folder goes now
            self.cleanup()
            raise
        self.sim.checks.append(self._check)

    # ------------------------------------------------------------------ the server
    def start_server(self) -> None:
        self.incarnation += 1
        self.server = SimServer(self.sim, self.net, self.cfg, self.incarnation, on_read=self._read,
                                on_timeout=self.oracle.timed_out)
        self.probe = ServerProbe(self.server)
        self.oracle.holders = self.probe.holders
        self.oracle.recorded_to = self.probe.recorded_to
        self._told = -1
        self.sim.log("run", f"server {self.incarnation} starts" + (" from its journal" if self.state_dir else ""))

    def crash_server(self, down_s: float) -> None:
        """SIGKILL the server; a new one starts ``down_s`` later over the same ``--state-dir``."""
        if self.server is None or self.server.proc.dead:
            return
        self.server.crash()
        self.fault_until(self.sim.now + down_s)
        self.sim.after(down_s, self.start_server)

    def stall_server(self, seconds: float) -> None:
        """The server process is stopped (SIGSTOP, swapped out) for ``seconds``."""
        if self.server is not None:
            p = self.server.proc
            p.pause(self.sim.now + seconds, self.sim.rng, self.sim.now)
            self.fault_until(self.sim.now + seconds)
            self.sim.log("run", f"server stalls for {seconds:.2f} s")

    def _read(self, ident: bytes, msg) -> None:
        """The server is about to handle ``msg`` from ``ident``: the batches a ``Released`` gives
        back are no longer its consumer's grant (``Oracle.released``)."""
        if isinstance(msg, Released):
            self.oracle.taken_back(ident, self.probe.takes_back(ident, msg.batch_ids))

    # ------------------------------------------------------------------ faults
    def at(self, t: float, fn: Callable, *args) -> None:
        """A fault (or any scenario action) at simulated time ``t``."""
        self.fault_until(t)
        self.sim.at(t, fn, *args)

    def fault_until(self, t: float) -> None:
        self.last_fault = max(self.last_fault, t)

    # ------------------------------------------------------------------ checks
    def _check(self, proc) -> None:
        """The invariants after a step of ``proc`` (None: a scenario's action): the server's books
        after the server's steps, a client's holdings after its own (nothing else changes them);
        doubles are caught as a batch reaches a loop (``Oracle.yielded``)."""
        probe = self.probe
        if probe is not None and not self.server.proc.dead and (proc is None or proc is self.server.proc):
            for e in probe.plan_epochs():  # failed windows, read while the plan lives (announcing may forget it)
                excused = probe.excused(e, self.setup.corpus)
                if excused:
                    self.oracle.excused[e] = excused
            told = probe.told_upto()
            for e in range(self._told + 1, told + 1):
                self.sim.log("run", f"epoch {e} announced complete")
                self.oracle.on_announce(e)
                for fn in list(self.on_announced):
                    fn(e)
            self._told = max(self._told, told)
            pol = self.setup.policy
            self.oracle.memory(probe, pol.max_credits, 2 * pol.lease_s + pol.revoke_s)
            probe.remember()
        if proc is not None and proc is not getattr(self.server, "proc", None):
            self.oracle.client_memory([c for c in self.oracle.live_clients if getattr(c, "proc", None) is proc])
        for lin in self.oracle.lineages.values():
            if lin.deadline is not None and lin.ended_at is None and self.sim.now > lin.deadline:
                self.sim.fail("liveness", f"{lin.name}'s stream did not end by t={lin.deadline:.1f} s, the bound "
                                          f"(epochs announced: {sorted(self.oracle.announced)})")

    def honest_done(self) -> bool:
        return all(lin.ended_at is not None or lin.dead_for_good or lin.error is not None
                   for lin in self.oracle.lineages.values() if lin.honest)

    def cleanup(self) -> None:
        if self.server is not None and self.server.journal is not None:
            self.server.journal.close()
        if self.state_dir is not None:
            shutil.rmtree(self.state_dir, ignore_errors=True)


@dataclass
class Result:
    """One seed's outcome: ``violation`` (None: every check held), the seed and scenario, the
    simulated seconds and steps it ran, and the trace when asked."""

    seed: int
    scenario: str
    violation: Optional[Violation]
    sim_s: float
    steps: int
    trace: Optional[List[str]] = None
    stats: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.violation is None

    def replay(self) -> str:
        """The one command that replays this seed with its trace."""
        return f"python -m harness.delivery_sim --scenario {self.scenario} --seed {self.seed} --trace"


def simulate(run: Run, scenario: str) -> Result:
    """Run ``run`` until every honest job's stream ended (or its deadline), then the final checks."""
    sim = run.sim
    quiet = logging.getLogger("v2v")
    level = quiet.level
    quiet.setLevel(logging.CRITICAL)
    violation = None
    deadline = max(run.setup.deadline, run.last_fault + run.setup.deadline)
    sim.stop_when = lambda: sim.now >= run.last_fault and run.honest_done()
    try:
        sim.run(deadline)
        sim.stop_when = lambda: False
        sim.run(sim.now + 0.5)  # messages in flight at the end land (an epoch may be announced)
        run.oracle.final(deadline)
    except Violation as v:
        violation = v
    finally:
        quiet.setLevel(level)
        run.cleanup()
    stats = {"yields": run.oracle.yields, "net_sent": run.net.sent, "net_lost": run.net.lost,
             "server_incarnations": run.incarnation}
    return Result(run.seed, scenario, violation, sim.now, sim.steps, sim.trace, stats)


def _tmp_root() -> Optional[str]:
    """A memory-backed folder for journals when there is one (a journal fsyncs each epoch)."""
    return "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else None

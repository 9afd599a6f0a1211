"""Seeded scenario families: everything a run is (corpus, policy, server, network, jobs and
faults) drawn from its seed's one random source.

Each family is ``build(seed, trace, profile) -> Run``; a :class:`Profile` bounds what it draws:
``FULL`` draws everything, ``MAIN`` leaves out what the delivery path is known to fail today
(docs/simulator.md, "Findings": server crashes, more than two epochs, long pauses, broken
connections, partitions, DDP). The test suite runs each family's ``MAIN`` profile green and its
``FULL`` profile as an expected failure where it still fails.

* ``trainers``: 1-3 independent trainers (plain datasets) with pauses of any length, kills and
  restarts from the newest or an older checkpoint, deaths for good, loops that stop reading,
  broken connections, partitions, server stalls and crashes (restarted from the journal),
  dying and hanging workers, failing windows and truncated files;
* ``ddp``: a DDP job (2-3 ranks, restarted at the same world size) beside a trainer, same faults;
* ``loader``: ``StreamLoader`` jobs (2-3 workers) beside a trainer: breaks, persistent workers,
  killed workers, restarts from the loader's checkpoint;
* ``network``: the trainers family over a network that also duplicates and delays messages;
* ``elastic``: a DDP job resumed at another world size (2 -> 1, 1 -> 2, 3 -> 2), each rank
  loading its own rank's state (refused: every rank's state; issue 69 item 3), half of them
  after some ranks stopped past the lease;
* ``mixed``: one of the honest families above.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple

from v2v_server.delivery.core import DeliveryPolicy

from harness.delivery_sim.ddp import DDPJob
from harness.delivery_sim.faults import draw_plan, pause
from harness.delivery_sim.loader import LoaderJob
from harness.delivery_sim.net import NetFaults
from harness.delivery_sim.run import Run, Setup
from harness.delivery_sim.server import Corpus
from harness.delivery_sim.trainer import TrainerJob, stream_options
from harness.delivery_sim.workers import WorkerFaults
from harness.delivery_sim.world import Sim

TRAINER_FAULTS = ("pause", "pause", "restart", "restart", "kill_for_good", "stop_reading", "blip", "cut",
                  "server_stall", "server_crash")


@dataclass(frozen=True)
class Profile:
    """What a family may draw: at most ``max_epochs`` epochs, faults of ``faults``, pauses of
    at most ``max_pause_s`` seconds."""

    name: str
    max_epochs: int
    faults: Tuple[str, ...]
    max_pause_s: float = 90.0
    spikes: bool = True  # messages delayed up to 3 s (a SYN retransmit takes 1 s), connections up to 0.1 s


FULL = Profile("full", 3, TRAINER_FAULTS)
#: what the delivery path survives today: no server crash (F1, F2, F4), two epochs at most (F1: a checkpoint older
#: than the kept epochs), pauses shorter than the client's timeout_s (F5), no broken connection (F11),
#: no partition nor delayed message (F9: a dead process's hello delivered late), no death for good
#: (F14: an epoch reopened by a resume, then its reader dies)
MAIN = Profile("main", 2, tuple(f for f in TRAINER_FAULTS if f not in ("server_crash", "blip", "cut", "kill_for_good")),
               max_pause_s=25.0, spikes=False)
#: what it survives with StreamLoader workers: MAIN, no stop over 1.5 s (a pause that extends a worker's pause
#: not over yet redrew its wake-up delays, so the worker could run two iterations' ``begin`` out of order and
#: answer the older one: the loop waited for good, mixed/main 19720 with 25 s pauses; a simulator defect, F42,
#: fixed since: longer stops are yet to be measured here)
MAIN_LOADER = Profile("main", 2, MAIN.faults, max_pause_s=1.5, spikes=False)


def draw_setup(rng, profile: Profile, journal=None) -> Setup:
    """A corpus, a policy and a server drawn from ``rng`` (small: a seed runs in milliseconds)."""
    n = rng.randint(2, 5)
    windows = {f"v{i}.mp4": rng.randint(1, 4) for i in range(n)}
    corpus = Corpus(windows)
    if rng.random() < 0.2:
        v = rng.choice(sorted(windows))
        corpus.bad.add((v, rng.randrange(windows[v])))
    if rng.random() < 0.15:
        v = rng.choice(sorted(windows))
        corpus.truncated[v] = rng.randrange(windows[v])
    policy = DeliveryPolicy(batch_size=rng.randint(1, 3), epochs=rng.randint(1, profile.max_epochs),
                            lease_s=rng.uniform(1.0, 4.0), client_timeout_s=rng.uniform(2.0, 6.0),
                            revoke_s=rng.uniform(1.0, 4.0), max_credits=4, task_timeout_s=rng.uniform(2.0, 8.0),
                            shuffle=rng.choice(["none", "epoch"]), shuffle_buffer=rng.randint(1, 6),
                            seed=rng.randrange(100), max_samples_per_video=max(windows.values()))
    wf = WorkerFaults(die=rng.choice([0.0, 0.0, 0.01, 0.05]), hang=rng.choice([0.0, 0.0, 0.01]), late=0.5)
    net = NetFaults(latency_s=rng.uniform(0.0001, 0.005), jitter_s=rng.uniform(0.0, 0.01),
                    spike=rng.choice([0.0, 0.0, 0.01, 0.05]) if profile.spikes else 0.0, spike_s=rng.uniform(0.1, 3.0),
                    connect_s=0.1 if profile.spikes else 0.001)
    setup = Setup(corpus, policy, workers=rng.randint(1, 3), prefetch=rng.randint(1, 6),
                  journal=rng.random() < 0.5 if journal is None else journal, net=net, worker_faults=wf)
    setup.deadline = deadline(setup)
    return setup


def deadline(setup: Setup, steps_s: float = 0.05) -> float:
    """Seconds after the last fault by which every honest stream must have ended: the lease,
    revoke and client timeouts, plus the work left at the slowest rates drawn, doubled."""
    p = setup.policy
    work = (p.epochs or 1) * setup.epoch_size() * (setup.sample_s[1] * 3 + steps_s) + p.task_timeout_s * 2
    return 2 * (p.lease_s + (p.revoke_s or p.client_timeout_s) + p.client_timeout_s + work) + 10.0


def span(setup: Setup) -> float:
    """Seconds over which faults are spread: about the length of an undisturbed run."""
    return 0.05 + (setup.policy.epochs or 1) * setup.epoch_size() * 0.02


def _trainer(run: Run, rng, name: str) -> TrainerJob:
    job = TrainerJob(run, name, stream_options(credits=rng.randint(1, 4)), ckpt_every=rng.randint(1, 3))
    job.start()
    return job


def _faults(run: Run, rng, jobs, profile: Profile, n: int, journal_ok: bool) -> None:
    plan = draw_plan(run, jobs, profile.faults, rng.randint(0, n), span(run.setup), journal_ok, profile.max_pause_s)
    run.sim.log("plan", "; ".join(plan) or "no faults")


def trainers(seed: int, trace: bool = False, profile: Profile = FULL, dup: bool = False) -> Run:
    """1-3 trainers under pauses, restarts, deaths, partitions, server stalls and crashes."""
    rng = Sim(seed).rng
    setup = draw_setup(rng, profile)
    if dup:
        setup.net.dup = rng.choice([0.01, 0.05, 0.2])
        setup.net.spike = rng.choice([0.01, 0.05]) if profile.spikes else 0.0
    run = Run(seed, setup, trace, rng)
    jobs = [_trainer(run, rng, f"t{i}") for i in range(rng.randint(1, 3))]
    _faults(run, rng, jobs, profile, 6, setup.journal or len(jobs) == 1)
    return run


def network(seed: int, trace: bool = False, profile: Profile = FULL) -> Run:
    """The trainers family over a network that also duplicates and delays messages."""
    return trainers(seed, trace, profile, dup=True)


def ddp(seed: int, trace: bool = False, profile: Profile = FULL) -> Run:
    """A DDP job (2-3 ranks, lockstep, padding) beside a trainer, under the trainers' faults."""
    rng = Sim(seed).rng
    setup = draw_setup(rng, profile)
    run = Run(seed, setup, trace, rng)
    job = DDPJob(run, "ddp", rng.randint(2, 3), credits=rng.randint(1, 3), ckpt_every=rng.randint(1, 3))
    job.start()
    jobs = [job] + ([_trainer(run, rng, "t0")] if rng.random() < 0.7 else [])
    _faults(run, rng, jobs, profile, 5, setup.journal)
    return run


def elastic(seed: int, trace: bool = False, profile: Profile = FULL) -> Run:
    """A DDP job resumed at another world size, each rank loading its own rank's state."""
    rng = Sim(seed).rng
    setup = draw_setup(rng, profile, journal=True)
    run = Run(seed, setup, trace, rng)
    world = rng.randint(1, 3)
    job = DDPJob(run, "ddp", world, credits=rng.randint(1, 3), ckpt_every=rng.randint(1, 3))
    job.start()
    other = rng.choice([w for w in (1, 2, 3) if w != world])
    t = rng.uniform(0.02, span(setup))
    if rng.random() < 0.5:  # some ranks stop past the lease first: a grant ages while another rank's epoch ends
        p = setup.policy
        d = rng.uniform(p.lease_s, p.lease_s + (p.revoke_s or p.client_timeout_s) + 1.0)
        run.at(t, pause, run, job, d, True)
        run.sim.log("plan", f"pause for {d:.2f} s at t={t:.2f}")
        t += d + rng.uniform(0.0, 1.0)
    run.at(t, job.restart, 0, rng.uniform(0.0, 2.0), other, "own")
    run.sim.log("plan", f"restart at world size {other} at t={t:.2f}")
    return run


def loader(seed: int, trace: bool = False, profile: Profile = FULL) -> Run:
    """StreamLoader jobs (2-3 workers) beside a trainer: breaks, killed workers, restarts."""
    if profile is MAIN:
        profile = MAIN_LOADER
    rng = Sim(seed).rng
    setup = draw_setup(rng, profile)
    run = Run(seed, setup, trace, rng)
    job = LoaderJob(run, "loader", workers=rng.randint(2, 3), persistent=rng.random() < 0.5,
                    prefetch=rng.randint(1, 2), credits=rng.randint(1, 3), ckpt_every=rng.randint(1, 3),
                    breaks=rng.choice([0.0, 0.1, 0.3]))
    job.start()
    jobs = [job] + ([_trainer(run, rng, "t0")] if rng.random() < 0.6 else [])
    for _ in range(rng.randint(0, 2)):
        run.at(rng.uniform(0.0, span(setup)), job.kill_worker, rng.randrange(job.num_workers))
    _faults(run, rng, jobs, profile, 4, setup.journal)
    return run


def mixed(seed: int, trace: bool = False, profile: Profile = FULL) -> Run:
    """One of the honest families (trainers, ddp, loader, network; no ddp in ``MAIN``: F8), by the seed."""
    families = (trainers, loader, network) if profile is MAIN else (trainers, ddp, loader, network)
    return families[seed % len(families)](seed, trace, profile)


FAMILIES = {"trainers": trainers, "ddp": ddp, "loader": loader, "network": network, "elastic": elastic,
            "mixed": mixed}
#: what each family's ``FULL`` profile finds today in seeds 0-59 (None: they hold); other open
#: findings fail at later seeds (``OPEN_FINDINGS``; docs/simulator.md, "Findings")
FAILS_ON_MAIN = {"trainers": None, "ddp": None, "loader": None, "network": None, "elastic": None,
                 "mixed": None}
#: one failing seed of each open finding: (scenario, seed, finding)
OPEN_FINDINGS: list = []

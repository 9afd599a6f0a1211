"""Seeded scenario families: everything a run is (corpus, policy, server, network, jobs and
faults) drawn from its seed's one random source.

Each family is ``build(seed, trace) -> Run``:

* ``trainers``: 1-3 independent trainers (plain datasets) with pauses of any length, kills and
  restarts from the newest or an older checkpoint, deaths for good, loops that stop reading,
  broken connections, partitions, server stalls and crashes (restarted from the journal),
  dying and hanging workers, failing windows and truncated files;
* ``ddp``: a DDP job (2-3 ranks, restarted at the same world size) beside a trainer, same faults;
* ``loader``: ``StreamLoader`` jobs (2-3 workers) beside a trainer: breaks, persistent workers,
  killed workers, restarts from the loader's checkpoint;
* ``network``: the trainers family over a network that also duplicates and delays messages;
* ``elastic``: a DDP job resumed at another world size (2 -> 1, 1 -> 2, 3 -> 2), each rank
  loading its own rank's state (issue 69: fails on main);
* ``mixed``: one of the honest families above.
"""
from __future__ import annotations

from v2v_server.delivery.core import DeliveryPolicy

from harness.delivery_sim.faults import draw_plan
from harness.delivery_sim.net import NetFaults
from harness.delivery_sim.run import Run, Setup
from harness.delivery_sim.server import Corpus
from harness.delivery_sim.trainer import TrainerJob, stream_options
from harness.delivery_sim.workers import WorkerFaults
from harness.delivery_sim.world import Sim

TRAINER_FAULTS = ("pause", "pause", "restart", "restart", "kill_for_good", "stop_reading", "blip", "cut",
                  "server_stall", "server_crash")


def draw_setup(rng, journal=None) -> Setup:
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
    lease = rng.uniform(1.0, 4.0)
    timeout = rng.uniform(2.0, 6.0)
    policy = DeliveryPolicy(batch_size=rng.randint(1, 3), epochs=rng.randint(1, 3), lease_s=lease,
                            client_timeout_s=timeout, revoke_s=rng.uniform(1.0, 4.0), max_credits=4,
                            task_timeout_s=rng.uniform(2.0, 8.0), shuffle=rng.choice(["none", "epoch"]),
                            shuffle_buffer=rng.randint(1, 6), seed=rng.randrange(100),
                            max_samples_per_video=max(windows.values()))
    wf = WorkerFaults(die=rng.choice([0.0, 0.0, 0.01, 0.05]), hang=rng.choice([0.0, 0.0, 0.01]), late=0.5)
    net = NetFaults(latency_s=rng.uniform(0.0001, 0.005), jitter_s=rng.uniform(0.0, 0.01),
                    spike=rng.choice([0.0, 0.0, 0.01, 0.05]), spike_s=rng.uniform(0.1, 3.0))
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


def trainers(seed: int, trace: bool = False, dup: bool = False) -> Run:
    """1-3 trainers under pauses, restarts, deaths, partitions, server stalls and crashes."""
    rng = Sim(seed).rng
    setup = draw_setup(rng)
    if dup:
        setup.net.dup = rng.choice([0.01, 0.05, 0.2])
        setup.net.spike = rng.choice([0.01, 0.05])
    run = Run(seed, setup, trace, rng)
    sim = run.sim
    jobs = [TrainerJob(run, f"t{i}", stream_options(credits=rng.randint(1, 4)), ckpt_every=rng.randint(1, 3))
            for i in range(rng.randint(1, 3))]
    for j in jobs:
        j.start()
    journal_ok = setup.journal or len(jobs) == 1
    plan = draw_plan(run, jobs, TRAINER_FAULTS, rng.randint(0, 6), span(setup), journal_ok)
    sim.log("plan", "; ".join(plan) or "no faults")
    return run


def network(seed: int, trace: bool = False) -> Run:
    """The trainers family over a network that also duplicates and delays messages."""
    return trainers(seed, trace, dup=True)


FAMILIES = {"trainers": trainers, "network": network}

"""The issue's scenarios (issue 69, "Why") and the delivery path's past bugs, as fixed
schedules; the seed only draws the jitter (network delays, worker and step times).

Each is ``build(seed, trace) -> Run``; :data:`NAMED` maps its name to ``(build, xfail)``:
``xfail`` says what the delivery path does wrong there today (the test marks it an expected
failure until the fix lands), or None when it holds.
"""
from __future__ import annotations

from typing import Callable, Dict, Optional, Tuple

from v2v_server.delivery.core import DeliveryPolicy

from harness.delivery_sim.ddp import DDPJob
from harness.delivery_sim.faults import pause, restart, stop_reading
from harness.delivery_sim.families import deadline
from harness.delivery_sim.hostile import Hostile
from harness.delivery_sim.loader import LoaderJob
from harness.delivery_sim.run import Run, Setup
from harness.delivery_sim.server import Corpus
from harness.delivery_sim.trainer import TrainerJob, stream_options
from harness.delivery_sim.world import Sim


def _run(seed: int, trace: bool, epochs: Optional[int] = 2, videos: int = 6, windows: int = 4, batch: int = 2,
         journal: bool = True, timeout: float = 2.0) -> Run:
    """The issue's layout: 24 samples an epoch (6 clips x 4 windows), batches of 2, short timeouts."""
    rng = Sim(seed).rng
    corpus = Corpus({f"clip{i}.mp4": windows for i in range(videos)})
    policy = DeliveryPolicy(batch_size=batch, epochs=epochs, lease_s=2.0, client_timeout_s=timeout, revoke_s=2.0,
                            max_credits=8, task_timeout_s=5.0, shuffle="epoch", shuffle_buffer=4, seed=11,
                            max_samples_per_video=windows)
    setup = Setup(corpus, policy, workers=2, prefetch=4, journal=journal)
    setup.deadline = deadline(setup)
    return Run(seed, setup, trace, rng)


def _trainer(run: Run, name: str, credits: int = 2, **kw) -> TrainerJob:
    job = TrainerJob(run, name, stream_options(credits=credits), **kw)
    job.start()
    return job


def _refusable(run: Run, *names: str) -> None:
    """These jobs may be refused as a second live reader (then they stop; the other reads all)."""
    for name in names:
        run.oracle.lineages[name].refusable = True


def two_trainers_one_consumer(seed: int, trace: bool = False) -> Run:
    """Two trainers resumed with the same consumer id read at once: one is refused, the other reads all."""
    run = _run(seed, trace)
    _trainer(run, "a", consumer="shared")
    _trainer(run, "b", consumer="shared")
    _refusable(run, "a", "b")
    return run


def two_ddp_jobs_default_group(seed: int, trace: bool = False) -> Run:
    """Two DDP jobs (world size 2 each, torchrun) that both leave ``group=`` at its default: each
    is named from its launcher's run, so both read."""
    run = _run(seed, trace)
    DDPJob(run, "job1", 2).start()
    DDPJob(run, "job2", 2).start()
    return run


def two_ddp_jobs_by_hand(seed: int, trace: bool = False) -> Run:
    """Two DDP jobs whose ranks were started by hand (no launcher) with ``group=`` at its default:
    they share the group ``default``, and the second is refused."""
    run = _run(seed, trace)
    DDPJob(run, "job1", 2, launcher={}).start()
    run.at(0.05, DDPJob(run, "job2", 2, launcher={}).start)
    _refusable(run, "job1", "job2")
    return run


def _world_change(seed: int, trace: bool, before: int, after: int, load: str) -> Run:
    run = _run(seed, trace, epochs=3)
    job = DDPJob(run, "ddp", before, ckpt_every=2)
    job.start()
    run.at(0.25, job.restart, 0, 0.5, after, load)  # after a checkpoint and two more batches
    return run


def world_size_2_to_1(seed: int, trace: bool = False) -> Run:
    """A world-size-2 job resumes as one rank from rank 0's state."""
    return _world_change(seed, trace, 2, 1, "own")


def world_size_1_to_2(seed: int, trace: bool = False) -> Run:
    """A one-rank job resumes as two ranks, rank 0 from its state, rank 1 afresh."""
    return _world_change(seed, trace, 1, 2, "own")


def world_size_change_refused(seed: int, trace: bool = False) -> Run:
    """A job saved by 2 ranks (the launchers' gathered state) resumes with 1: refused, resumed with 2."""
    return _world_change(seed, trace, 2, 1, "gathered")


def wakes_after_others_ran_ahead(seed: int, trace: bool = False) -> Run:
    """Trainer A (credits 4) frozen past every timeout while B reads all 6 epochs; then A wakes (its
    I/O thread first: it reads ``dropped`` before the loop takes the batch it holds granted)."""
    run = _run(seed, trace, epochs=6)
    a = _trainer(run, "a", credits=4, step_s=(0.3, 0.3))
    _trainer(run, "b")
    run.at(0.2, lambda: _pause(run, a, 10.0 + 2.0 + 2.0 + 2.0, io_first=True))  # mid-step, grants ahead held
    return run


def _pause(run: Run, job, seconds: float, io_first: bool = False) -> None:
    for p in job.procs():
        p.proc.pause(run.sim.now + seconds, run.sim.rng, run.sim.now)
        if io_first:
            p.proc.wake = {"io": 0.0, "main": 0.002}
        run.sim.log(p.name, f"paused for {seconds:.1f} s")


def sitter_stalls_stream_end(seed: int, trace: bool = False) -> Run:
    """A client holds 4 grants without acknowledging them, heartbeating: the honest trainer's stream must end."""
    run = _run(seed, trace)
    Hostile(run, "sitter", "sitter", credits=4)
    _trainer(run, "honest")
    return run


def sitter_unbounded(seed: int, trace: bool = False) -> Run:
    """The same sitter on an unbounded stream: the open epochs must stay bounded. The honest
    trainer (0.05 s steps) reads 30 epochs in about 18 s, three times the longest the sitter may
    keep it from being told an epoch complete (``2 lease_s + revoke_s``)."""
    run = _run(seed, trace, epochs=None)
    Hostile(run, "sitter", "sitter", credits=4)
    _trainer(run, "honest", stop_epoch=30, step_s=(0.04, 0.06))
    return run


def loop_stops_calling_next(seed: int, trace: bool = False) -> Run:
    """An honest trainer's loop stops calling next() for 10 minutes (validation) with its two look-ahead
    grants; the other trainer's stream must end within the bound."""
    run = _run(seed, trace, epochs=3)
    stuck = _trainer(run, "stuck")
    _trainer(run, "reader")
    run.oracle.lineages["reader"].deadline = run.setup.deadline
    run.at(0.05, stop_reading, run, stuck, 600.0)
    run.fault_until(600.05)  # the stuck loop reads on after it: its stream ends too
    return run


def false_claim(seed: int, trace: bool = False) -> Run:
    """While an honest trainer reads epoch 0, a hello claiming 6 ids of it that were never sent to it."""
    run = _run(seed, trace)
    _trainer(run, "honest")
    run.at(0.3, lambda: Hostile(run, "liar", "claim", epoch=0, ids=[f"clip{i}.mp4#0" for i in range(6)],
                                leave_after=5.0))
    return run


def false_claim_first(seed: int, trace: bool = False) -> Run:
    """The same false hello as the first a fresh server reads, before any epoch is open."""
    run = _run(seed, trace)
    Hostile(run, "liar", "claim", epoch=0, ids=[f"clip{i}.mp4#0" for i in range(6)], leave_after=5.0)
    run.at(0.05, _trainer, run, "honest")
    return run


def completed_epoch_5(seed: int, trace: bool = False) -> Run:
    """A first hello claiming ``completed_epoch: 5`` to a fresh ``--epochs 2`` server."""
    run = _run(seed, trace)
    Hostile(run, "liar", "completed", epoch=5, leave_after=5.0)
    run.at(0.05, _trainer, run, "honest")
    return run


def completed_epoch_huge(seed: int, trace: bool = False) -> Run:
    """A first hello claiming ``completed_epoch`` 999999999 on an unbounded stream; an honest trainer
    reads three epochs, checkpointing, and resumes from its checkpoint on the way."""
    run = _run(seed, trace, epochs=None)
    Hostile(run, "liar", "completed", epoch=999999999, leave_after=2.0)
    run.at(0.05, lambda: run.at(0.5, _trainer(run, "honest", stop_epoch=3).restart, 0, 0.1))
    return run


def huge_hello(seed: int, trace: bool = False) -> Run:
    """A hello of 20000 ids of one clip (the server must keep no more than an epoch for it, and return it)."""
    run = _run(seed, trace)
    Hostile(run, "flood", "huge", epoch=0, ids=["clip0.mp4"], n=20000, leave_after=1.0)
    _trainer(run, "honest")
    return run


def repeated_ids_hold(seed: int, trace: bool = False) -> Run:
    """8 holds each naming one granted id 256 times (safety only: the cost of 4096 is bench.faults's)."""
    run = _run(seed, trace)
    Hostile(run, "repeater", "repeat", repeats=8, width=256)
    _trainer(run, "honest")
    return run


def frozen_client(seed: int, trace: bool = False) -> Run:
    """Client A (4 credits, 0.3 s steps) stopped 5 s past ``--client-timeout 2`` mid-step while B reads."""
    run = _run(seed, trace)
    a = _trainer(run, "a", credits=4, step_s=(0.3, 0.3))
    _trainer(run, "b")
    run.at(0.35, lambda: _pause(run, a, 7.0))
    return run


def break_loop(seed: int, trace: bool = False) -> Run:
    """A trainer leaves its loop four times (``break``) and iterates again, beside another."""
    run = _run(seed, trace)
    t = _trainer(run, "breaker")
    _trainer(run, "other")
    for k in range(4):
        run.at(0.05 + 0.07 * k, lambda: [p.break_loop() for p in t.procs()])
    return run


def loader_breaks(seed: int, trace: bool = False) -> Run:
    """StreamLoader with 2 persistent workers: the loop breaks after batches and iterates again."""
    run = _run(seed, trace, epochs=1)
    LoaderJob(run, "loader", workers=2, persistent=True, breaks=0.3).start()
    return run


def loader_state_in_memory(seed: int, trace: bool = False) -> Run:
    """A StreamLoader checkpoint kept in memory (not torch.save'd) resumed after more batches."""
    run = _run(seed, trace, epochs=1)
    job = LoaderJob(run, "loader", workers=2, in_memory=True, ckpt_every=2)
    job.start()
    run.at(0.2, job.restart, 1, 0.2)
    return run


def restart_paused_while_hello_waits(seed: int, trace: bool = False) -> Run:
    """A trainer restarted from an older checkpoint is paused past ``--client-timeout 2`` while its
    hello waits for proof of life, and again while the hello it then says again waits, beside another."""
    run = _run(seed, trace)
    t = _trainer(run, "t", credits=1)
    _trainer(run, "b")
    run.at(0.2, restart, run, t, 1, 0.0)
    run.at(0.22, pause, run, t, 4.0)
    run.at(4.42, pause, run, t, 4.0)
    return run


def rehello_lost_in_server_crash(seed: int, trace: bool = False) -> Run:
    """A trainer paused past ``--client-timeout 2`` wakes to ``dropped`` and says hello again; the
    server crashes as that hello is on its way and restarts from its journal."""
    run = _run(seed, trace, epochs=1)
    t = _trainer(run, "t", credits=1)
    run.at(0.3, pause, run, t, 3.0)
    run.at(3.302, run.crash_server, 0.5)
    run.fault_until(3.802)
    return run


Entry = Tuple[Callable[..., Run], Optional[str]]

#: name -> (build, what the delivery path does wrong there today, or None)
NAMED: Dict[str, Entry] = {
    "two_trainers_one_consumer": (two_trainers_one_consumer, None),
    "two_ddp_jobs_default_group": (two_ddp_jobs_default_group, None),
    "two_ddp_jobs_by_hand": (two_ddp_jobs_by_hand, None),
    "world_size_2_to_1": (world_size_2_to_1, None),
    "world_size_1_to_2": (world_size_1_to_2, None),
    "world_size_change_refused": (world_size_change_refused, None),
    "wakes_after_others_ran_ahead": (wakes_after_others_ran_ahead, None),
    "sitter_stalls_stream_end": (sitter_stalls_stream_end, None),
    "sitter_unbounded": (sitter_unbounded, None),
    "loop_stops_calling_next": (loop_stops_calling_next, None),
    "false_claim": (false_claim, None),
    "false_claim_first": (false_claim_first, None),
    "completed_epoch_5": (completed_epoch_5, None),
    "completed_epoch_huge": (completed_epoch_huge, None),
    "huge_hello": (huge_hello, None),
    "repeated_ids_hold": (repeated_ids_hold, None),
    "frozen_client": (frozen_client, None),
    "break_loop": (break_loop, None),
    "loader_breaks": (loader_breaks, None),
    "loader_state_in_memory": (loader_state_in_memory, None),
    "restart_paused_while_hello_waits": (restart_paused_while_hello_waits, None),
    "rehello_lost_in_server_crash": (rehello_lost_in_server_crash, None),
}


def _when(run: Run, ready, action, every: float = 0.005) -> None:
    """Run ``action()`` at the first poll (every ``every`` s) at which ``ready()`` holds."""
    def poll():
        if ready():
            action()
        else:
            run.sim.after(every, poll)
    run.sim.after(every, poll)


def journal_restart_after_epoch(seed: int, trace: bool = False) -> Run:
    """The server is killed as epoch 0 is announced (the journal then holds no open epoch's record)
    and restarts from its journal; a second job joins as it comes back: it must not get epoch 0."""
    run = _run(seed, trace, epochs=2)
    _trainer(run, "t", credits=1, step_s=(0.05, 0.05))
    run.fault_until(5.0)

    def crash(epoch: int) -> None:
        if epoch == 0 and run.incarnation == 1:
            run.sim.at(run.sim.now, run.crash_server, 1.0)
            run.sim.at(run.sim.now + 1.0, _trainer, run, "late")
    run.on_announced.append(crash)
    return run


NAMED["journal_restart_after_epoch"] = (journal_restart_after_epoch, None)



def batch_ids_of_two_server_lives(seed: int, trace: bool = False) -> Run:
    """StreamLoader worker 1 holds the first server's batches 0 and 1 in the loader's queue (the loop
    waits on worker 0, stopped) as the server is killed; the restarted server sends worker 1 two
    batches of its own (numbered from 0 again before the fix), and the loop leaves right after
    receiving the old batch 0 (persistent workers: worker 1's next hello comes from its own record).
    The receipt of old batch 0 must not count the new one received, nor the new one's claim
    overwrite the old one in the worker's record."""
    run = _run(seed, trace, epochs=2)
    job = LoaderJob(run, "loader", workers=2, persistent=True, prefetch=3, credits=2, step_s=(0.01, 0.02))
    job.start()

    def stop_worker_0() -> None:
        job.workers[0].proc.pause(run.sim.now + 2.0, run.sim.rng, run.sim.now)
        run.sim.log(job.workers[0].name, "paused for 2.0 s")

    def breaks(p: float) -> None:
        job.breaks = p

    run.at(0.001, stop_worker_0)
    run.fault_until(3.0)
    _when(run, lambda: len(job.workers[1].stream.record.pipeline) >= 2, lambda: run.crash_server(0.3))
    _when(run, lambda: job.steps >= 1, lambda: breaks(1.0))  # the loop leaves after the old batch 0
    _when(run, lambda: job.steps >= 2, lambda: breaks(0.0))
    return run


NAMED["batch_ids_of_two_server_lives"] = (batch_ids_of_two_server_lives, None)

"""Faults a scenario schedules (``Run.at``) on jobs, the network and the server, and the seeded
draw of a fault plan for the random families.

Every fault is a function of the run and a job (``procs()``: its live processes, ``restart``,
``kill``); durations are simulated seconds. ``draw_plan`` picks ``n`` faults from ``kinds`` with
``run.sim.rng``, at times within ``span`` seconds, and returns their description (for the trace).
"""
from __future__ import annotations

from typing import List, Sequence

from harness.delivery_sim.run import Run


def pause(run: Run, job, seconds: float, some: bool = False) -> None:
    """SIGSTOP the job's processes (``some``: a random non-empty subset) for ``seconds``."""
    procs = job.procs()
    if some and len(procs) > 1:
        procs = run.sim.rng.sample(procs, run.sim.rng.randint(1, len(procs)))
    for p in procs:
        p.proc.pause(run.sim.now + seconds, run.sim.rng, run.sim.now)
        run.sim.log(p.name, f"paused for {seconds:.2f} s")
    run.fault_until(run.sim.now + seconds)


def _links(job):
    return [p.conn().link for p in job.procs() if p.conn() is not None]


def blip(run: Run, job, gap: float) -> None:
    """The TCP connections of the job's sockets break; ZeroMQ reconnects after ``gap``."""
    for link in _links(job):
        run.net.blip(link, gap)


def cut(run: Run, job, seconds: float) -> None:
    """A partition between the job and the server for ``seconds``."""
    for link in _links(job):
        run.net.cut(link, run.sim.now + seconds)
    run.fault_until(run.sim.now + seconds)


def stop_reading(run: Run, job, seconds: float) -> None:
    """The training loop stops calling ``next()`` (validation, a debugger); I/O goes on."""
    for p in job.procs():
        if hasattr(p, "stop_reading"):
            p.stop_reading(seconds)
    run.fault_until(run.sim.now + seconds)


def restart(run: Run, job, back: int, gap: float) -> None:
    """Kill the job; ``gap`` s later it resumes from its newest checkpoint but ``back``."""
    if job.procs():
        job.restart(back=back, gap=gap)
        run.fault_until(run.sim.now + gap)


def kill_for_good(run: Run, job) -> None:
    """The running job dies and never comes back (the docs' one exception to nothing lost);
    a job down for a restart is left to it."""
    if job.procs():
        job.kill(for_good=True)


def duration(run: Run, scale: Sequence[float], most: float = 90.0) -> float:
    """A pause length: short, past the lease, past the revoke and client timeouts, or long
    (``scale``: the lease, revoke and client timeout of the run), at most ``most`` seconds."""
    lease, revoke, timeout = scale
    rng = run.sim.rng
    return min(most, rng.choice([rng.uniform(0.01, 0.3), rng.uniform(lease, lease + revoke + 1),
                                 rng.uniform(timeout, 3 * timeout), rng.uniform(20.0, 90.0)]))


def draw_plan(run: Run, jobs: List, kinds: Sequence[str], n: int, span: float, journal_ok: bool,
              most: float = 90.0) -> List[str]:
    """``n`` faults of ``kinds`` on ``jobs`` at times in ``[0, span)``. ``journal_ok``: the
    server may be killed and restarted (with a journal, or with one consumer only); ``most``:
    the longest pause or loop stop, seconds."""
    sim, p = run.sim, run.setup.policy
    scale = (p.lease_s, p.revoke_s or p.client_timeout_s, p.client_timeout_s)
    out = []
    honest = [j for j in jobs if run.oracle.lineages[j.lineage].honest]
    killed_for_good = set()
    for _ in range(n):
        t = sim.uniform(0.0, span)
        kind = sim.pick(list(kinds))
        job = sim.pick(jobs)
        if kind == "pause":
            d = duration(run, scale, most)
            run.at(t, pause, run, job, d, True)
            run.fault_until(t + d)
        elif kind == "restart":
            back = sim.pick([0, 0, 0, 1, 2])
            run.at(t, restart, run, job, back, sim.uniform(0.0, 3.0))
            run.fault_until(t + 3.0)
        elif kind == "kill_for_good":
            if len([j for j in honest if j.name not in killed_for_good]) < 2 or job.name in killed_for_good:
                continue
            killed_for_good.add(job.name)
            run.at(t, kill_for_good, run, job)
        elif kind == "stop_reading":
            d = duration(run, scale, most)
            run.at(t, stop_reading, run, job, d)
            run.fault_until(t + d)
        elif kind == "blip":
            run.at(t, blip, run, job, sim.uniform(0.0, 1.0))
        elif kind == "cut":
            d = sim.uniform(0.05, 0.5 * min(j.timeout_s for j in jobs))
            run.at(t, cut, run, job, d)
            run.fault_until(t + d)
        elif kind == "server_stall":
            d = sim.uniform(0.05, 15.0)
            run.at(t, run.stall_server, d)
            run.fault_until(t + d)
        elif kind == "server_crash":
            if not journal_ok:
                continue
            d = sim.uniform(0.05, 3.0)
            run.at(t, run.crash_server, d)
            run.fault_until(t + d)
        else:
            continue
        out.append(f"{kind}@{t:.2f}:{job.name}")
    return out

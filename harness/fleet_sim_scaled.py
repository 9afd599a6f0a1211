"""A fleet the HPA sizes (``harness.fleet_sim.autoscale``) read by the client's own reader: the
hosts and the real pass of ``harness.fleet_sim_pass`` (one reader), a trainer of fixed appetite,
and pods an HPA (``harness.hpa``) makes and removes.

The trainer wants each step ``step / appetite`` seconds after it took the one before and takes
it once its rows are had; the pass reads up to ``READ_AHEAD`` + ``HELD_STEPS`` steps ahead of it.
A pod is ready ``startup_s`` after it is made; at the next :data:`fleet_sim.RESOLVE_S` boundary
the reader asks it what it serves (``PlanAsk``) and its answer joins it to the reader's router
(``fleet_read.Fleet.join``: ``Router.join``). A pod removed leaves the router at once
(``Router.leave``: the Service publishes ready pods only), its queue, decodes running and the
samples it kept lost and its messages not taken dropped; the pass asks again what it awaited of
it (``Pass.rescue``). A pod made again under a name is a fresh host (its own meter, nothing
made). Each pod's metrics (``fleet_sim.METRIC_WINDOW_S``) are scraped every
:data:`fleet_sim.SCRAPE_S` from its counters: its workers' busy seconds, the samples the
reader's makes named (``v2v_samples_asked_total``), its own ``RateMeter``, and the work asked of
it not made.
"""
from __future__ import annotations

import heapq
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

import numpy as np

from harness.fleet_sim import (ASKED, BACKLOG, BUSY, LONGEST_S, METRIC_WINDOW_S, RESOLVE_S, SCRAPE_LEAD_S, SCRAPE_S,
                               Fleet, Job, _Stalls)
from harness.fleet_sim_pass import PassWorld, _Host, _Reader
from harness.hpa import SYNC_S, Hpa, HpaSpec, PodSample
from v2v_client.fleet_pass import STEAL_S
from v2v_wire.fleet import AHEAD_DECODES, Router
from v2v_wire.plan_messages import PlanAsk, PlanInfo


def _counter_at(log: List[Tuple[float, float, float]], col: int, t: float) -> float:
    """Column ``col`` of a pod's scrape ``log`` (times ascending) at ``t``, linear between scrapes."""
    i = max(0, int(np.searchsorted([e[0] for e in log], t, side="right")) - 1)
    if i + 1 >= len(log) or log[i + 1][0] <= log[i][0]:
        return log[i][col]
    (ta, *a), (tb, *b) = log[i], log[i + 1]
    return a[col - 1] + (b[col - 1] - a[col - 1]) * (t - ta) / (tb - ta)


@dataclass
class _Pod:
    """A pod: when it was made and ready (None: not yet), its generation (a pod made again under
    its name is the next), and whether the reader asked it what it serves."""

    started: float
    ready: Optional[float] = None
    gen: int = 0
    resolved: bool = False


class ScaledWorld(PassWorld):
    """One epoch of fleet ``f`` (``f.hosts``: the pool, the HPA's ``maxReplicas``) read by one
    real pass for trainer ``job`` from the pods the HPA of ``spec`` sizes (module docstring).
    Events past the base's: ``"want"`` the trainer wants its next step, ``"scrape"``, ``"sync"``
    the HPA's, ``"ready"`` and ``"resolve"`` (host, generation) a pod ready and resolved.

    Attributes (the run's): ``waits`` per step taken, ``(when wanted, when had)``; ``syncs`` per
    HPA sync, ``(t, replicas set, ready pods, their workers' busy fraction, mean metric)``."""

    def __init__(self, f: Fleet, job: Job, spec: HpaSpec):
        names = [f"host-{k:03d}" for k in range(f.hosts)]
        router = Router(names[:job.start_hosts], slack=f.slack, hedge_s=f.hedge_s, patience_s=STEAL_S,
                        workers=f.slots)
        # ``Pass.ahead`` of the hosts read at the start once they said their rates, kept all epoch:
        # ``Router.ahead_decodes`` of them, two windows' samples a decode (the corpus's one crop a window)
        ahead = None if job.window_follows else AHEAD_DECODES * job.start_hosts * f.slots * 2
        super().__init__(f, 0, [router], ahead=ahead)
        self.trainer, self.spec, self.hpa, self.router = job, spec, Hpa(spec), router
        self.stalls = _Stalls(f, job.seconds + 600.0)
        self.pods: Dict[int, _Pod] = {k: _Pod(-job.startup_s, 0.0, resolved=True) for k in range(job.start_hosts)}
        self.gens = [0] * f.hosts
        self.busy_ws, self.marked = [0.0] * f.hosts, [0.0] * f.hosts  # busy worker-seconds so far; when counted
        self.logs: Dict[int, List[Tuple[float, float, float]]] = {k: [(0.0, 0.0, 0.0)] for k in self.pods}
        self.scraped: Dict[int, Tuple[float, Dict[str, Optional[float]]]] = {}  # host -> (t, metric -> value)
        self.want_at = 0.0
        self.served: List[Tuple[int, float, float]] = []  # (host, ready, removed) of each pod gone
        self.waits: List[Tuple[float, float]] = []
        self.syncs: List[Tuple[float, int, int, float, Optional[float]]] = []

    # ------------------------------------------------------------------ hosts
    def _mark(self, k: int) -> None:
        """Host ``k``'s busy worker-seconds counted up to now."""
        self.busy_ws[k] += (self.f.slots - self.hosts[k].free) * (self.now - self.marked[k])
        self.marked[k] = self.now

    def start_work(self, h: _Host) -> None:
        """As the base's, ``h``'s busy worker-seconds counted up to now first."""
        self._mark(h.k)
        super().start_work(h)

    def done(self, k: int, video: str) -> None:
        """As the base's, host ``k``'s busy worker-seconds counted up to now first."""
        self._mark(k)
        super().done(k, video)

    def host_message(self, k: int, rank: int, msg) -> None:
        """As the base's, for a pod that runs; to one gone, lost."""
        if k in self.pods:
            super().host_message(k, rank, msg)

    # ------------------------------------------------------------------ the reader and the trainer
    def turn(self, rd: _Reader) -> None:
        """As the base's, a pod resolved that says what it serves joining the router first
        (``Fleet.join``)."""
        for ep, msg, _ in rd.inbox:
            k = self.index[ep]
            pod = self.pods.get(k)
            if isinstance(msg, PlanInfo) and pod is not None and pod.resolved and ep not in self.router.hosts:
                self._mark(k)
                self.logs[k] = [(self.now, self.busy_ws[k], float(self.hosts[k].asked))]
                self.router.join(ep, self.t0 + self.now, workers=self.f.slots)
        super().turn(rd)

    def taken(self) -> int:
        """Steps the trainer has taken."""
        return len(self.step_times)

    def job(self) -> None:
        """The trainer takes each step the reader handed on once it wants it (``want_at``; then
        it wants the next ``step / appetite`` seconds on); the loop's room then takes a step the
        pass held, as the base's."""
        while len(self.step_times) < self.readers[0].yielded and self.now >= self.want_at:
            self.waits.append((self.want_at, self.now))
            self.take_step()
            self.want_at = self.now + self.f.step / self.trainer.appetite_at(self.now)
            self.push(self.want_at, "want", None)

    # ------------------------------------------------------------------ the HPA
    def backlogs(self) -> Dict[int, float]:
        """Pod -> the work asked of it and not made, in seconds at its rate (its own measure,
        else its workers at their speed): what :data:`BACKLOG` exports."""
        out = {}
        for k in self.pods:
            h, n = self.hosts[k], 0.0
            for video, makes in h.waiting.items():
                if makes:
                    m = float(self.slots[video])
                    if video in h.running:
                        m = max(0.0, m - (self.now - h.running[video][0]) * self.speeds[k])
                    n += m
            out[k] = n / (h.meter.rate() or self.f.slots * self.speeds[k])
        return out

    def scrape(self) -> None:
        """Each joined pod's metrics now (:data:`METRIC_WINDOW_S`), from its counters' log since it joined."""
        backlog = self.backlogs()
        for k, p in self.pods.items():
            if p.ready is None or k not in self.logs:
                continue
            self._mark(k)
            log = self.logs[k]
            log.append((self.now, self.busy_ws[k], float(self.hosts[k].asked)))
            values: Dict[str, Optional[float]] = {BACKLOG: backlog[k]}
            capacity = self.hosts[k].meter.rate()
            for m, col, per in (("cpu", 1, self.f.slots), (BUSY, 1, self.f.slots), (ASKED, 2, capacity)):
                if per is None:
                    values[m] = None
                    continue
                t0 = max(self.now - METRIC_WINDOW_S[m], log[0][0])
                values[m] = (log[-1][col] - _counter_at(log, col, t0)) / per / (self.now - t0) if self.now > t0 else None
            while log[0][0] < self.now - LONGEST_S - SCRAPE_S:
                log.pop(0)
            self.scraped[k] = (self.now, values)

    def sync(self) -> None:
        """The HPA's sync (``Hpa.sync``) on the pods' last scrapes; pods made, or removed as a
        ReplicaSet removes them (those not ready first, then the newest ready)."""
        pods = []
        for k, p in self.pods.items():
            s = self.scraped.get(k)
            value = None if s is None else s[1][self.spec.metric]
            pods.append(PodSample(p.ready is not None, p.ready is not None, p.started, p.ready, value,
                                  s[0] if s else 0.0, SCRAPE_S))
        current = len(self.pods)
        desired = self.hpa.sync(self.now, current, pods)
        ready = [k for k, p in self.pods.items() if p.ready is not None and k in self.scraped]
        busy = float(np.mean([self.scraped[k][1]["cpu"] for k in ready])) if ready else 0.0
        values = [p.value for p in pods if p.value is not None]
        self.syncs.append((self.now, desired, len(ready), busy, float(np.mean(values)) if values else None))
        for _ in range(desired - current):
            k = min(set(range(self.f.hosts)) - set(self.pods))
            self.gens[k] += 1
            self.pods[k] = _Pod(self.now, None, self.gens[k])
            self.push(self.now + self.trainer.startup_s, "ready", k, self.gens[k])
        for _ in range(current - desired):
            self.remove(min(self.pods, key=lambda k: (self.pods[k].ready is not None, -(self.pods[k].ready or 0.0))))

    def _pod(self, k: int, gen: int) -> Optional[_Pod]:
        """Pod ``k`` if it is still of generation ``gen``."""
        p = self.pods.get(k)
        return p if p is not None and p.gen == gen else None

    def remove(self, k: int) -> None:
        """Pod ``k`` goes: it leaves the reader's router, its messages not taken and its work are
        lost, and its name is a fresh host's; the reader turns (``Pass.rescue`` asks again what
        it awaited of it)."""
        self._mark(k)
        if self.pods[k].ready is not None:
            self.served.append((k, self.pods[k].ready, self.now))
        del self.pods[k]
        self.logs.pop(k, None)
        self.scraped.pop(k, None)
        self.router.leave(self.names[k])
        self.events = [e for e in self.events if not (e[2] in ("done", "part", "host") and e[3] == k)]
        heapq.heapify(self.events)
        self.hosts[k] = _Host(self.names[k], k, self.f.slots)
        rd = self.readers[0]
        if rd.wake_at > self.now:
            self.wake(rd, self.now)

    def outages(self) -> List[Tuple[float, float]]:
        """``(start, end)`` of each stall of a pod while it served (ready until removed, or now)."""
        served = self.served + [(k, p.ready, self.now) for k, p in self.pods.items() if p.ready is not None]
        out = []
        for k, ready, gone in served:
            for s, e in zip(self.stalls.starts[k], self.stalls.ends[k]):
                if s < gone and e > ready:
                    out.append((max(float(s), ready), min(float(e), gone)))
        return sorted(out)

    def handle(self, kind: str, a, b) -> None:
        """Event ``kind`` at :attr:`now`: this class's (its docstring), else the base's."""
        if kind == "want":
            self.job()
        elif kind == "scrape":
            self.scrape()
            self.push(self.now + SCRAPE_S, "scrape", None)
        elif kind == "sync":
            self.sync()
            self.push(self.now + SYNC_S, "sync", None)
        elif kind == "ready":
            p = self._pod(a, b)
            if p is not None:
                p.ready = self.now
                self.push((self.now // RESOLVE_S + 1) * RESOLVE_S, "resolve", a, b)
        elif kind == "resolve":
            p = self._pod(a, b)
            if p is not None:  # asked what it serves: its PlanInfo joins it (:meth:`turn`)
                p.resolved = True
                self.push(self.now, "host", a, (0, PlanAsk()))
        else:
            super().handle(kind, a, b)

    def run(self) -> None:
        """The job's ``seconds``, event by event.

        Raises:
            ValueError: the epoch ended before them."""
        self.wake(self.readers[0], 0.0)
        self.push(0.0, "want", None)
        self.push(SYNC_S - SCRAPE_LEAD_S, "scrape", None)
        self.push(SYNC_S, "sync", None)
        while self.now < self.trainer.seconds:
            if len(self.step_times) >= self.steps:
                raise ValueError(f"fleet_sim: the epoch ({self.samples} samples) ended at {self.now:.0f} s, "
                                 f"before the job's {self.trainer.seconds:.0f} s: more videos")
            self.now, _, kind, a, b = heapq.heappop(self.events)
            self.handle(kind, a, b)

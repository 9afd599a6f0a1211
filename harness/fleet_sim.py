"""A pure simulator of a decode fleet feeding one job: how many samples per second a fleet of
hosts of unequal speed, which stall now and then, delivers in plan order, against the sum of the
hosts' rates, for the two ways hosts split the work:

* **routed** (``v2v_wire.fleet.Router``): every host serves the one plan; each reader is the
  client's own ``v2v_client.fleet_pass.Pass`` (``harness.fleet_sim_pass``: this module's hosts
  with a server's side of the protocol), which asks each video of the host weighted rendezvous
  hashing and the bounded load pick, and hedges a video it waits on when its host went silent;
* **static**: the corpus split by the hash of each path (``v2v-serve --shard I/N``), each shard's
  own plan, read interleaved (global position ``t`` is shard ``t mod N``'s ``t // N``,
  ``v2v_wire.plan_shards``): a step waits for every shard.

The model: a corpus of WebVid-like clips (durations log-normal around 15 s at 30 frames/s, a
window every 200 frames, the paper's 201-frame samples); the epoch's order is the real
``v2v_wire.plan.EpochPlan`` (shuffle buffer 64); a host has ``slots`` workers that each decode one
video at a time at the host's rate (samples/s per worker ``1 x`` a log-normal factor of sigma
``spread``), a video's decode taking its samples over that rate; stalls arrive at each host as a
Poisson process (``stall_every_s`` apart on average, each ``stall_s`` long on average, exponential)
and stop its workers; each host measures its own capacity (samples over its workers' busy
seconds, each sample counted as its worker makes it, as a server counts them) and says it with
each answer and to each ping. The static split's reader (:class:`_World`, one) reads positions in
order, a step of ``step`` positions at a time, as fast as they are made (the trainer never waits
on itself), and asks each shard's host ahead for the clips of the next ``lookahead`` positions
(default ``AHEAD_DECODES`` decodes per worker of the fleet); each host works the clips asked of it
in order of the first position that needs them. The routed split's readers are the client's own
passes (``harness.fleet_sim_pass``: ``ranks`` of them, each reading its slice of every step with
its own router).

**A fleet the HPA sizes** (:func:`autoscale`): a trainer of fixed appetite (samples/s) reads the
epoch step by step, each once its rows are had and no sooner than its appetite allows, through
one real pass (``harness.fleet_sim_scaled``), which asks ahead as ``Pass.ahead`` says of the hosts
it reads; the fleet's pods are made and removed by a HorizontalPodAutoscaler (``harness.hpa``:
the controller's rule, run every 15 s on the manifest of ``deploy/k8s-autoscale``), each pod ready
``startup_s`` after it is made and joining the reader at its next resolution of the name. Each
pod's metrics are read every 15 s (:data:`METRIC_WINDOW_S`).

Pure and seeded: no socket, no clock; ``python -m harness.fleet_sim`` prints a table (``--waits
S``: instead, each step the routed job waited on S seconds or longer, with the rank it waited for
last and the row that came last, from which host),
``tests/test_fleet.py`` checks the figures docs/scaling.md quotes (``--autoscale``:
``tests/test_fleet_sim_autoscale.py``).
"""
from __future__ import annotations

if __name__ == "__main__":  # Ctrl-C or SIGTERM from the start, the imports below included: one line
    import sys

    from v2v_wire.commands import run_command

    sys.exit(run_command("harness.fleet_sim", "harness.fleet_sim:main"))

import argparse
import heapq
import json
import logging
import sys
from contextlib import contextmanager
from pathlib import Path
from dataclasses import asdict, dataclass, field, replace
from typing import Dict, List, Optional, Sequence, Set, Tuple

import numpy as np

from v2v_wire.commands import json_output_problem, write_whole
from v2v_client.fleet_pass import STEAL_S
from v2v_wire.fleet import AHEAD_DECODES, HEDGE_S, SLACK, RateMeter, Router, video_key
from v2v_wire.plan import EpochPlan, Manifest

from harness.hpa import HpaSpec

#: Frames per sample (the paper's 40 voxels x 5 bins + 1) and frames between window starts.
SAMPLE_FRAMES, WINDOW_STRIDE = 201, 200


@dataclass(frozen=True)
class Fleet:
    """A simulated fleet and job (module docstring).

    Attributes:
        hosts: decode hosts.
        videos: clips in the corpus.
        slots: workers per host.
        spread: sigma of the log-normal spread of the hosts' speeds.
        slow: ``(host index, factor)``: that host's speed times ``factor`` (``None``: none).
        stall_every_s, stall_s: mean seconds between a host's stalls and mean stall length (0: none).
        step: positions per step (every rank's batch).
        lookahead: positions the static split's reader asks ahead of the step it reads (None:
            ``AHEAD_DECODES`` decodes per worker of the fleet, at the corpus's mean samples per
            clip, and a step); the passes ask ahead by their own rule (``Pass.ahead``).
        hedge_s: seconds a host may answer nothing before the videos a reader waits on are
            asked of the next host.
        slack: the router's bounded load (``Router``'s ``slack``).
        ranks: readers in the job, each with its own router, each reading its slice of every step
            (``step / ranks`` positions, as data-parallel ranks read their batches) and asking its
            own positions' clips; a host makes a clip once for every rank that asked it.
        seed: the corpus's, the speeds' and the stalls' draws; the plan's seed too.
    """

    hosts: int = 128
    videos: int = 40_000
    slots: int = 4
    spread: float = 0.2
    slow: Optional[Tuple[int, float]] = None
    stall_every_s: float = 300.0
    stall_s: float = 10.0
    step: int = 96
    lookahead: Optional[int] = None
    hedge_s: float = HEDGE_S
    slack: float = SLACK
    ranks: int = 1
    seed: int = 0

    @property
    def stalling(self) -> bool:
        """Whether the hosts stall: both stall figures > 0 (either 0: no stalls)."""
        return self.stall_every_s > 0 and self.stall_s > 0


@dataclass
class Result:
    """What one simulated epoch gave.

    Attributes:
        mode: ``"routed"`` or ``"static"``.
        samples: samples the epoch held; positions: rows read, padding included.
        seconds: when the reader had read the last step.
        rate: samples per second over the epoch.
        steady_rate: samples per second from 10 % to 90 % of the epoch's positions (the rate of
            a job reading epoch after epoch, whose hosts decode the next one's first clips
            while the last steps are read).
        capacity: the hosts' summed rates, samples/s, less each host's stalled time.
        decodes: clip decodes started per clip in the epoch (above 1: hedged copies).
        made_by: clip -> the host whose decode was read.
        decoding: the share of the hosts' capacity over the epoch spent decoding, copies
            included (its excess over :attr:`share` made samples no reader read); the rest
            idled. None: not counted (the static split).
        idle_end: the share of the hosts' capacity over the epoch that idled in its last tenth
            of seconds, when the hosts had made all but its last clips (None: not counted).
    """

    mode: str
    samples: int
    positions: int
    seconds: float
    rate: float
    steady_rate: float
    capacity: float
    decodes: float
    made_by: Dict[str, str]
    decoding: Optional[float] = None
    idle_end: Optional[float] = None

    @property
    def share(self) -> float:
        """:attr:`rate` over :attr:`capacity`: the whole epoch's share of the hosts' capacity."""
        return self.rate / self.capacity

    @property
    def steady_share(self) -> float:
        """:attr:`steady_rate` over :attr:`capacity` (above 1: the 10 % before the window made
        ahead what it reads)."""
        return self.steady_rate / self.capacity


def corpus(f: Fleet) -> Dict[str, int]:
    """clip -> samples per epoch: durations log-normal with median 15 s (sigma 0.6), 30 frames/s,
    a window every ``WINDOW_STRIDE`` frames that holds ``SAMPLE_FRAMES`` (clips shorter than a
    sample give none)."""
    rng = np.random.default_rng(f.seed)
    frames = (30 * 15 * rng.lognormal(0.0, 0.6, f.videos)).astype(int)
    windows = np.maximum(0, (frames - SAMPLE_FRAMES) // WINDOW_STRIDE + 1)
    return {f"clips/{i:07d}.mp4": int(n) for i, n in enumerate(windows)}


def _speeds(f: Fleet) -> np.ndarray:
    rng = np.random.default_rng([f.seed, 1])
    s = rng.lognormal(0.0, f.spread, f.hosts)
    if f.slow is not None:
        s[f.slow[0]] *= f.slow[1]
    return s


class _Stalls:
    """Each host's stall intervals (seeded), and a worker's finish time across them."""

    def __init__(self, f: Fleet, horizon_s: float):
        rng = np.random.default_rng([f.seed, 2])
        self.starts: List[np.ndarray] = []
        self.ends: List[np.ndarray] = []
        for _ in range(f.hosts):
            if not f.stalling:
                self.starts.append(np.zeros(0))
                self.ends.append(np.zeros(0))
                continue
            n = int(horizon_s / f.stall_every_s * 2) + 4
            gaps = rng.exponential(f.stall_every_s, n)
            lens = rng.exponential(f.stall_s, n)
            starts = np.cumsum(gaps) + np.concatenate([[0.0], np.cumsum(lens)[:-1]])
            self.starts.append(starts)
            self.ends.append(starts + lens)

    def finish(self, host: int, t: float, work_s: float) -> float:
        """When ``work_s`` seconds of work begun at ``t`` end on ``host``, its stalls skipped."""
        starts, ends = self.starts[host], self.ends[host]
        i = int(np.searchsorted(ends, t, side="right"))
        if i < len(starts) and starts[i] <= t:  # begun inside a stall: from its end
            t = ends[i]
            i += 1
        while i < len(starts) and starts[i] < t + work_s:
            work_s -= starts[i] - t
            t = ends[i]
            i += 1
        return t + work_s

    def stalled(self, host: int, until: float) -> float:
        """Seconds ``host`` is stalled in ``[0, until)``."""
        s, e = self.starts[host], self.ends[host]
        return float(np.sum(np.clip(np.minimum(e, until) - s, 0.0, None)))

    def silent(self, host: int, t: float) -> bool:
        """Whether ``host`` is inside a stall at ``t``."""
        i = int(np.searchsorted(self.ends[host], t, side="right"))
        return i < len(self.starts[host]) and self.starts[host][i] <= t


def said_rate(meter: RateMeter, running: Dict[str, List[float]], samples_of, now: float, slots: int,
              at: float) -> Optional[float]:
    """A host's capacity as it says it at ``now`` (samples/s, None before it is measured): its
    ``meter`` counts each sample as a worker makes it, a decode's samples coming evenly over it
    (``running``: clip -> [start, end, samples and busy seconds counted], updated), with the busy
    seconds up to it, as a server counts them (``ServerMetrics.capacity``); ``samples_of(clip)``:
    the clip's samples; ``at``: the meter's clock."""
    for clip, p in running.items():
        start, end, counted, busy = p
        n = samples_of(clip)
        made = min(n - 1, int((now - start) / (end - start) * n)) if end > start else 0
        if made > counted:
            took = made * (end - start) / n
            meter.add(made - counted, (took - busy) / slots, at)
            p[2], p[3] = made, took
    return meter.rate()


def _epoch(slots: Dict[str, int], seed: int, epoch: int) -> EpochPlan:
    return EpochPlan(Manifest.of(slots), seed, epoch, 64)


def _needs(plan: EpochPlan, offset_of=lambda p: p) -> Dict[str, Tuple[int, int]]:
    """clip -> (first global position needing it, its samples)."""
    first: Dict[str, int] = {}
    count: Dict[str, int] = {}
    vids = plan.video_index
    for p, v in enumerate(vids.tolist()):
        name = plan.videos[v]
        g = offset_of(p)
        if name not in first or g < first[name]:
            first[name] = g
        count[name] = count.get(name, 0) + 1
    return {v: (first[v], count[v]) for v in first}


@dataclass
class _Layout:
    """An epoch of static shards as the reader reads it: ``pos_clip`` (the clip of each position,
    None for padding), ``needs`` (clip -> (first position needing it, its samples)), ``home``
    (clip -> its shard)."""

    pos_clip: List[Optional[str]]
    needs: Dict[str, Tuple[int, int]]
    home: Dict[str, int]

    @property
    def length(self) -> int:
        return len(self.pos_clip)

    @property
    def samples(self) -> int:
        return sum(1 for c in self.pos_clip if c is not None)


def _layout(f: Fleet, epoch: int) -> _Layout:
    """The epoch's positions: each shard's plan interleaved (``v2v_wire.plan_shards``)."""
    slots, n = corpus(f), f.hosts
    shard = {v: video_key(v) % n for v in slots}
    plans = [_epoch({v: s for v, s in slots.items() if shard[v] == k}, f.seed, epoch) for k in range(n)]
    length = max(((len(p) - 1) * n + k + 1 for k, p in enumerate(plans) if len(p)), default=0)
    pos_clip: List[Optional[str]] = [None] * length
    needs: Dict[str, Tuple[int, int]] = {}
    for k, p in enumerate(plans):
        for lp, v in enumerate(p.video_index.tolist()):
            pos_clip[lp * n + k] = p.videos[v]
        needs.update(_needs(p, lambda lp, k=k: lp * n + k))
    return _Layout(pos_clip, needs, shard)


class _World:
    """One epoch of static shards read by one reader (module docstring): each host's queue (by
    the first position needing a clip) and free workers, the decodes' ends to come, the clips
    had, and the positions read."""

    def __init__(self, f: Fleet, lay: _Layout):
        self.f, self.lay, self.n = f, lay, f.hosts
        self.speeds = _speeds(f)  # samples/s of one worker of each host
        self.stalls = _Stalls(f, 4 * lay.samples / (float(self.speeds.sum()) * f.slots) + 600.0)
        self.hosts = [f"host-{k:03d}" for k in range(self.n)]
        mean = lay.samples / max(1, len(lay.needs))
        #: positions the reader asks ahead of the step read: ``f.lookahead``, else ``AHEAD_DECODES``
        #: decodes per worker of the fleet of the corpus's mean samples a clip, and a step
        self.lookahead = f.lookahead or int(AHEAD_DECODES * self.n * f.slots * mean) + f.step
        self.by_need = sorted(lay.needs, key=lambda v: lay.needs[v][0])
        self.asked_upto = 0  # index into by_need of the next clip to ask
        self.queues: List[List[Tuple[int, str]]] = [[] for _ in range(self.n)]
        self.free = [f.slots] * self.n
        self.events: List[Tuple[float, int, str]] = []  # (a decode's end, host, clip)
        self.had: Set[str] = set()
        self.decodes, self.now, self.read = 0, 0.0, 0
        self.step_times: List[Tuple[int, float]] = []

    def start_work(self, k: int) -> None:
        """Host ``k``'s free workers start its queue's first clips."""
        while self.free[k] and self.queues[k]:
            _, clip = heapq.heappop(self.queues[k])
            self.free[k] -= 1
            self.decodes += 1
            end = self.stalls.finish(k, self.now, self.lay.needs[clip][1] / self.speeds[k])
            heapq.heappush(self.events, (end, k, clip))

    def ask_ahead(self) -> None:
        """The reader asks each clip of the positions in its window (:attr:`lookahead` past the
        read) of its shard's host, worked in the order of the first position needing it."""
        while self.asked_upto < len(self.by_need):
            clip = self.by_need[self.asked_upto]
            first = self.lay.needs[clip][0]
            if first >= self.read + self.lookahead:
                return
            self.asked_upto += 1
            k = self.lay.home[clip]
            heapq.heappush(self.queues[k], (first, clip))
            self.start_work(k)

    def advance(self) -> None:
        """The read moves on by each step whose clips are all had."""
        while self.read < self.lay.length:
            stop = min(self.lay.length, self.read + self.f.step)
            if any(self.lay.pos_clip[p] is not None and self.lay.pos_clip[p] not in self.had
                   for p in range(self.read, stop)):
                return
            self.read = stop
            self.step_times.append((self.read, self.now))

    def made(self, k: int, clip: str) -> None:
        """Host ``k``'s worker made ``clip``: the reader has it, reads on and asks ahead."""
        self.free[k] += 1
        self.had.add(clip)
        self.advance()
        self.ask_ahead()
        self.start_work(k)

    def run(self) -> None:
        """The epoch, decode by decode, until its last position is read.

        Raises:
            RuntimeError: no decode left before then (stuck)."""
        self.ask_ahead()
        while self.read < self.lay.length:
            if not self.events:
                raise RuntimeError(f"fleet_sim: stuck at position {self.read} of {self.lay.length}")
            self.now, k, clip = heapq.heappop(self.events)
            self.made(k, clip)


def simulate(f: Fleet, mode: str, epoch: int = 0, routers: Optional[Sequence[Router]] = None,
             held: Optional[Dict[str, str]] = None) -> Result:
    """One epoch of fleet ``f`` split as ``mode`` (``"routed"``: read by the client's own
    ``Pass``, ``harness.fleet_sim_pass``; or ``"static"``); ``routers``: each rank's router kept
    from an earlier epoch (routed only; default new ones, ``f.ranks`` of them); ``held``: clip ->
    the host that made it in that epoch (its frame cache holds it).

    Raises:
        ValueError: another mode, naming it, or a number of routers or ranks that does not
            divide the step."""
    if mode not in ("routed", "static"):
        raise ValueError(f"mode must be 'routed' or 'static', got {mode!r}")
    if f.ranks < 1 or f.step % f.ranks or (routers is not None and len(routers) != f.ranks):
        raise ValueError(f"ranks must divide step ({f.step}) and each rank have one router, got ranks={f.ranks} "
                         f"and {None if routers is None else len(routers)} routers")
    if mode == "static" and f.ranks != 1:
        raise ValueError(f"static shards are simulated with one reader, got ranks={f.ranks}")
    if mode == "routed":  # read by the client's own pass (that module builds on this one's fleet)
        from harness.fleet_sim_pass import simulate_pass
        return simulate_pass(f, epoch, routers, held)
    lay = _layout(f, epoch)
    w = _World(f, lay)
    w.run()
    end, length = w.now, lay.length
    lo, hi = int(0.1 * length), int(0.9 * length)
    t_lo = next(t for p, t in w.step_times if p >= lo)
    t_hi = next(t for p, t in w.step_times if p >= hi)
    steady = sum(1 for c in lay.pos_clip[lo:hi] if c is not None)
    capacity = float(sum(w.speeds[k] * f.slots * (1 - w.stalls.stalled(k, end) / end) for k in range(f.hosts)))
    return Result(mode, lay.samples, length, end, lay.samples / end, steady / max(t_hi - t_lo, 1e-9), capacity,
                  w.decodes / max(1, len(lay.needs)), {c: w.hosts[lay.home[c]] for c in lay.needs})


def _routers(f: Fleet) -> List[Router]:
    return [Router([f"host-{k:03d}" for k in range(f.hosts)], slack=f.slack, hedge_s=f.hedge_s, patience_s=STEAL_S,
                   workers=f.slots)
            for _ in range(f.ranks)]


def static_padding(videos: int, shards: Sequence[int], seed: int = 0) -> Dict[int, float]:
    """The share of an epoch's rows that hold no sample when a corpus of ``videos`` WebVid-like
    clips (:func:`corpus`) is split into static shards (``v2v-serve --shard I/N``: the
    servers' ``shard_of``) read interleaved (``plan_shards.shards_samples``), for each count
    of ``shards``."""
    from v2v_server.ops.startup import shard_of
    from v2v_wire.plan_shards import shards_samples

    clips = corpus(Fleet(videos=videos, seed=seed))
    per = {n: [0] * n for n in shards}
    for v, m in clips.items():
        for n, counts in per.items():
            counts[shard_of(v, n)] += m
    total = sum(clips.values())
    return {n: 1 - total / shards_samples(counts) for n, counts in per.items()}


def stay(f: Fleet) -> float:
    """The share of clips one reader's router has decoded on the same host in two epochs in a row
    (a frame cache's hits in the second epoch, over one host's): routed, the fleet unchanged."""
    routers = _routers(f)
    first = simulate(f, "routed", 0, routers).made_by
    second = simulate(f, "routed", 1, routers, first).made_by
    return sum(first.get(c) == h for c, h in second.items()) / max(1, len(second))


# ---------------------------------------------------------------------------- a fleet the HPA sizes

#: Seconds between two readings of a pod's metric (metrics-server's resolution, a Prometheus
#: scrape interval), each the mean over the seconds since the one before; taken 5 s before the
#: HPA's syncs, which read the latest.
SCRAPE_S, SCRAPE_LEAD_S = 15.0, 5.0
#: Seconds a reader takes to see a pod join or leave the Service's name (``fleet_read`` resolves
#: it again every 5 s).
RESOLVE_S = 5.0
#: The HPA the simulator runs by default: the one ``kubectl apply -k deploy/k8s-autoscale`` makes.
DEPLOY_HPA = Path(__file__).resolve().parents[1] / "deploy" / "k8s-autoscale" / "server-hpa.yaml"
#: The metrics the simulator exports for the HPA, each a rate over its window of seconds (None: a
#: gauge), and what a pod's value says:
#:
#: * ``"cpu"``: the busy fraction of the host's workers over metrics-server's resolution (the
#:   CPU of a host whose workers are its cores);
#: * :data:`BUSY`: the same from the host's /metrics over a window Prometheus averages
#:   (``rate(v2v_worker_busy_seconds_total[2m]) / v2v_workers``);
#: * :data:`ASKED`: the samples the readers ask of the host per second over its capacity
#:   (``rate(v2v_samples_asked_total[1m]) / v2v_capacity_samples_per_second``): the share of its
#:   capacity the job asks of it; none before the host has measured its capacity;
#: * :data:`BACKLOG`: the work asked of it and not made, in seconds at its capacity.
BUSY, ASKED, BACKLOG = "v2v_worker_busy", "v2v_asked_share", "v2v_backlog_seconds"
METRIC_WINDOW_S = {"cpu": SCRAPE_S, BUSY: 120.0, ASKED: 60.0, BACKLOG: None}
#: Seconds of a pod's counters the simulator keeps: its longest rate window.
LONGEST_S = max(w for w in METRIC_WINDOW_S.values() if w)
#: Busy fraction of the ready hosts under which a scale-up counts as one while hosts idle.
IDLE_BUSY = 0.5


@dataclass(frozen=True)
class Job:
    """A job of fixed appetite read by a fleet the HPA sizes (:func:`autoscale`).

    Attributes:
        appetite: samples/s the trainer takes while it does not wait on a step.
        halve_at_s: when the appetite halves (None: never).
        seconds: how long the job reads.
        start_hosts: hosts serving when it starts, made with it (``kubectl apply -k
            deploy/k8s-autoscale`` starts the Deployment, its HPA and the trainer's Job at once):
            ready at 0 s, their counters starting then.
        startup_s: seconds from a pod's creation to its ``/readyz`` (scheduling, image, start).
        hpa: the manifest whose HorizontalPodAutoscaler sizes the fleet (its maxReplicas is
            the pool of hosts the simulator draws speeds for).
        metric, target: the metric and target the HPA runs instead of the manifest's (None:
            the manifest's): a key of :data:`METRIC_WINDOW_S` (the CPU's target: a fraction of
            the request).
        window_follows: the reader asks ahead for the hosts it reads now; False: for those it
            read at the start (a reader that sizes its window once a pass; ``fleet_pass.Pass``
            follows the fleet).
    """

    appetite: float = 48.0
    halve_at_s: Optional[float] = 900.0
    seconds: float = 2100.0
    start_hosts: int = 2
    startup_s: float = 30.0
    hpa: str = str(DEPLOY_HPA)
    metric: Optional[str] = None
    target: Optional[float] = None
    window_follows: bool = True

    def appetite_at(self, t: float) -> float:
        """Samples/s the trainer takes at ``t``."""
        return self.appetite / 2 if self.halve_at_s is not None and t >= self.halve_at_s else self.appetite


@dataclass
class Scaled:
    """What an autoscaled run gave.

    Attributes:
        job: the job; metric, target: what the HPA ran on.
        host_rate: samples/s a mean host of the pool makes (its workers at their mean speed,
            less its mean stalled share): the hosts a job needs is its appetite over this.
        syncs: per HPA sync, ``(t, replicas set, ready pods, busy fraction of the ready pods'
            workers over the last scrape, mean metric of the pods that had one)``.
        steps: per step read, ``(when the trainer wanted it, when it had it)``, seconds.
        outages: ``(start, end)`` of each stall of a pod while it served, seconds.
    """

    job: Job
    metric: str
    target: float
    host_rate: float
    syncs: List[Tuple[float, int, int, float, Optional[float]]]
    steps: List[Tuple[float, float]]
    outages: List[Tuple[float, float]] = field(default_factory=list)

    def needed(self, t: float) -> float:
        """Hosts the job needs at ``t``: its appetite over :attr:`host_rate`."""
        return self.job.appetite_at(t) / self.host_rate

    def waited(self, t0: float, t1: float) -> float:
        """The share of the steps wanted in ``[t0, t1)`` the trainer waited on."""
        s = [(w, g) for w, g in self.steps if t0 <= w < t1]
        return sum(g > w + 1e-6 for w, g in s) / max(1, len(s))

    def held(self, t0: float, t1: float) -> float:
        """The most replicas the HPA set in ``[t0, t1)`` over the hosts needed then."""
        return max((n / self.needed(t) for t, n, *_ in self.syncs if t0 <= t < t1), default=0.0)

    def out_for(self, t0: float, t1: float) -> float:
        """The longest a pod that served was stalled within ``[t0, t1)``, seconds."""
        return max([0.0] + [min(e, t1) - max(s, t0) for s, e in self.outages])

    def changes(self) -> List[Tuple[float, int, int, float]]:
        """``(t, replicas before, after, busy fraction of the ready hosts)`` per change."""
        out, last = [], self.job.start_hosts
        for t, n, _, busy, _ in self.syncs:
            if n != last:
                out.append((t, last, n, busy))
                last = n
        return out

    def figures(self, settle_s: float = 300.0) -> Dict[str, float]:
        """The bars docs/scaling.md states: from ``settle_s`` after the start until the appetite
        halves, the share of steps the trainer waited on (``waited``) and the most hosts held
        over those needed (``held``); the share waited on after it halved (``waited_half``),
        the hosts held at the end over those needed then (``end``) and the seconds from the
        halving until the hosts held were at most 1.3 times those needed (``given_back_s``;
        inf: never); scale-downs before the halving and scale-ups after it (either: the fleet
        oscillates), and scale-ups while the ready hosts' workers were busy under
        :data:`IDLE_BUSY` of their time (``ups_while_idle``)."""
        half = self.job.halve_at_s if self.job.halve_at_s is not None else self.job.seconds
        ch = self.changes()
        back = next((t - half for t, n, *_ in self.syncs if t >= half and
                     all(m <= 1.3 * self.needed(u) for u, m, *_ in self.syncs if u >= t)), float("inf"))
        return {"waited": self.waited(settle_s, half), "held": self.held(settle_s, half),
                "waited_half": self.waited(half, self.job.seconds),
                "end": self.syncs[-1][1] / self.needed(self.job.seconds),
                "given_back_s": back,
                "downs_before_half": sum(a < b for t, b, a, _ in ch if t < half),
                "ups_after_half": sum(a > b for t, b, a, _ in ch if t >= half),
                "ups_while_idle": sum(a > b and busy < IDLE_BUSY for t, b, a, busy in ch)}


def autoscale(f: Fleet, job: Job) -> Scaled:
    """Job ``job`` reading one epoch, routed, from a fleet of hosts like ``f``'s (``f.hosts``
    is ignored: the pool is the HPA's ``maxReplicas``) that the HPA of ``job.hpa`` sizes on
    its metric (or ``job.metric``), ``harness.hpa``'s model of the controller, read by one
    real ``Pass`` (``harness.fleet_sim_scaled.ScaledWorld``), which asks ahead as
    ``Pass.ahead`` says of the hosts it reads (``job.window_follows`` off: of those it read at
    the start). Pure and seeded.

    Raises:
        ValueError: the manifest's (``HpaSpec.load``), a job out of range (naming its fields), a
            metric this model does not export, or an epoch that ends before ``job.seconds``.
        RuntimeError: a row the pass read that is not the plan's (``PassWorld.check``)."""
    spec = HpaSpec.load(Path(job.hpa))
    if job.appetite <= 0 or job.startup_s < 0 or job.seconds <= 0 or not 1 <= job.start_hosts <= spec.max_replicas:
        raise ValueError(f"a job takes > 0 samples/s for > 0 s, pods start in >= 0 s and 1 to maxReplicas "
                         f"({spec.max_replicas}) hosts serve at its start, got appetite={job.appetite}, "
                         f"seconds={job.seconds}, startup_s={job.startup_s}, start_hosts={job.start_hosts}")
    if job.metric is not None:
        spec = replace(spec, metric=job.metric, target=job.target if job.target is not None else spec.target)
    if spec.metric not in METRIC_WINDOW_S:
        raise ValueError(f"{job.hpa}: metric {spec.metric!r}: the simulator exports {', '.join(METRIC_WINDOW_S)}")
    from harness.fleet_sim_scaled import ScaledWorld  # the real pass's world (that module builds on this one)

    f = replace(f, hosts=spec.max_replicas, ranks=1)
    w = ScaledWorld(f, job, spec)
    w.run()
    stall = f.stall_s / (f.stall_every_s + f.stall_s) if f.stalling else 0.0
    rate = float(np.mean(w.speeds)) * f.slots * (1 - stall)
    return Scaled(job, spec.metric, spec.target, rate, w.syncs, w.waits, w.outages())


def _metric(text: str) -> Tuple[str, float]:
    """``--metric``'s ``NAME=TARGET`` (argparse names the option on error)."""
    name, _, target = text.partition("=")
    try:
        value = float(target)
    except ValueError:
        value = -1.0
    if name not in METRIC_WINDOW_S or value <= 0:
        raise argparse.ArgumentTypeError(f"{text!r}: want NAME=TARGET, NAME one of {', '.join(METRIC_WINDOW_S)}, "
                                         "TARGET a number > 0")
    return name, value


@contextmanager
def _passes_quiet():
    """The passes' log lines (a host placed a clip at a silent one) kept out of the table: hundreds
    over a simulated fleet's stalls, where the table is what the run says; the level put back after."""
    client_log = logging.getLogger("v2v.client")
    level = client_log.level
    client_log.setLevel(logging.ERROR)
    try:
        yield
    finally:
        client_log.setLevel(level)


def _print_autoscale(a: argparse.Namespace) -> int:
    """``--autoscale``: the figures of each run (the manifest's HPA, then each ``--metric``)."""
    f = Fleet(videos=a.videos, slots=a.slots, spread=a.spread, stall_every_s=a.stall_every_s, stall_s=a.stall_s,
              seed=a.seed)
    try:
        job = Job(a.appetite, startup_s=a.startup_s, hpa=a.hpa, window_follows=not a.window_at_start)
        with _passes_quiet():
            runs = [autoscale(f, job)] + [autoscale(f, replace(job, metric=m, target=t)) for m, t in a.metric]
    except (OSError, ValueError) as e:  # the manifest's problems name it
        print(f"harness.fleet_sim: {e}", file=sys.stderr)
        return 2
    r0 = runs[0]
    print(f"a job taking {a.appetite:g} samples/s ({r0.needed(0):.2f} hosts of {r0.host_rate:.2f} samples/s), half "
          f"from {r0.job.halve_at_s:g} s; hosts of {f.slots} workers, ready {a.startup_s:g} s after they are made; "
          f"{a.hpa}'s HPA")
    print(f"{'metric':<22} {'target':>6} {'waited':>7} {'held':>5} {'waited/2':>8} {'back s':>7} {'end':>5} "
          f"{'downs':>5} {'ups/2':>5} {'idle ups':>8}  hosts set (t s: n)")
    for r in runs:
        g = r.figures()
        print(f"{r.metric:<22} {r.target:>6.2f} {g['waited']:>7.1%} {g['held']:>5.2f} {g['waited_half']:>8.1%} "
              f"{g['given_back_s']:>7.0f} {g['end']:>5.2f} {g['downs_before_half']:>5} {g['ups_after_half']:>5} "
              f"{g['ups_while_idle']:>8}  " + " ".join(f"{t:.0f}:{n}" for t, _, n, _ in r.changes()))
    if a.trace:
        print(f"{'t s':>6} {'hosts':>5} {'ready':>5} {'busy':>5} {'metric':>7} {'waited':>7}")
        for t, n, ready, busy, m in r0.syncs[3::4]:
            print(f"{t:>6.0f} {n:>5} {ready:>5} {busy:>5.2f} {'-' if m is None else f'{m:.2f}':>7} "
                  f"{r0.waited(t - 60, t):>7.1%}")
    return 0


def _sizes(text: str) -> List[int]:
    """``--padding``'s corpus sizes: comma-separated ints >= 1 (argparse names the option on error)."""
    try:
        sizes = [int(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: not comma-separated numbers of videos") from None
    if any(v < 1 for v in sizes):
        raise argparse.ArgumentTypeError(f"{text!r}: each corpus holds at least one video")
    return sizes


def _print_waits(f: Fleet, at_least_s: float) -> int:
    """``--waits``: the routed epoch's steps waited on ``at_least_s`` or longer
    (``fleet_sim_pass.PassWorld.waited``), one line each."""
    if not at_least_s > 0:
        print(f"harness.fleet_sim: --waits must be > 0 seconds, got {at_least_s}", file=sys.stderr)
        return 2
    from harness.fleet_sim_pass import PassWorld
    with _passes_quiet():
        world = PassWorld(f)
        r = world.run()
    waits = world.waited(at_least_s)
    print(f"{f.hosts} hosts, speed spread sigma {f.spread}, {f.ranks} rank(s), seed {f.seed}: the epoch took "
          f"{r.seconds:.1f} s, {r.share:.3f} of the hosts' capacity, at {r.decodes:.3f} decodes a clip; "
          f"{len(waits)} step(s) waited on {at_least_s:g} s or longer, {sum(w.waited_s for w in waits):.1f} s in all")
    print(f"{'step':>6} {'taken at':>9} {'waited':>7} {'first rank had it':>18} {'last rank':>9}  "
          "last row (from, when)")
    for w in waits:
        print(f"{w.step:>6} {w.taken_at:>8.1f}s {w.waited_s:>6.1f}s {w.first_at:>17.1f}s {w.rank:>9}  {w.sample} "
              f"({w.host}, {w.arrived_at:.1f} s)")
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m harness.fleet_sim", description=__doc__.split("\n\n")[0])
    ap.add_argument("--hosts", type=int, default=Fleet.hosts)
    ap.add_argument("--videos", type=int, default=Fleet.videos)
    ap.add_argument("--slots", type=int, default=Fleet.slots)
    ap.add_argument("--spread", type=float, default=Fleet.spread)
    ap.add_argument("--slow", type=float, default=None, help="host 0's speed times this factor")
    ap.add_argument("--stall-every-s", type=float, default=Fleet.stall_every_s)
    ap.add_argument("--stall-s", type=float, default=Fleet.stall_s)
    ap.add_argument("--step", type=int, default=Fleet.step, help="positions per step, every rank's batch")
    ap.add_argument("--ranks", type=int, default=Fleet.ranks,
                    help="readers, each with its own router and its slice of every step (routed only)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--seeds", type=int, default=1,
                    help="run seeds --seed .. --seed + N - 1 and print each split's mean, with the share's range: "
                         "one seed's whole-epoch share moves by several hundredths with the corpus's and the "
                         "speeds' draws (docs/scaling.md)")
    ap.add_argument("--json", default=None, help="also write the results here (not with --waits, --padding or "
                                                "--autoscale, which print a table only)")
    ap.add_argument("--waits", type=float, default=None, metavar="SECONDS",
                    help="print only the steps the routed job waited on this long or longer (seed --seed), each with "
                         "the rank it waited for last and the row that came last: where a whole epoch's time goes")
    ap.add_argument("--padding", default=None, metavar="VIDEOS,...", type=_sizes,
                    help="print only the static shards' padding for these corpus sizes (2, 8, 32, 128 shards)")
    ap.add_argument("--autoscale", action="store_true",
                    help="print only a job of fixed appetite read by a fleet an HPA sizes (Job's fields below)")
    ap.add_argument("--appetite", type=float, default=Job.appetite, help="samples/s the trainer takes (--autoscale)")
    ap.add_argument("--startup-s", type=float, default=Job.startup_s, help="seconds from a pod's creation to ready")
    ap.add_argument("--hpa", default=Job.hpa, help="the manifest whose HPA sizes the fleet (--autoscale)")
    ap.add_argument("--metric", action="append", default=[], metavar="NAME=TARGET", type=_metric,
                    help=f"also run the HPA on this metric and target instead (one of {', '.join(METRIC_WINDOW_S)})")
    ap.add_argument("--trace", action="store_true", help="with --autoscale: each minute of the manifest's run")
    ap.add_argument("--window-at-start", action="store_true",
                    help="with --autoscale: the reader asks ahead for the hosts it read at the start only")
    a = ap.parse_args(argv)
    printed = [name for name, given in (("--waits", a.waits is not None), ("--padding", a.padding),
                                        ("--autoscale", a.autoscale)) if given]
    if a.json and printed:  # they print their tables only: a --json not written would pass unnoticed
        print(f"harness.fleet_sim: --json {a.json}: not written with {printed[0]}, which prints its table only; "
              "drop one of them", file=sys.stderr)
        return 2
    problem = json_output_problem(Path(a.json)) if a.json else ""
    if problem:
        print(f"harness.fleet_sim: --json {a.json}: {problem}", file=sys.stderr)
        return 2
    for name in ("hosts", "videos", "slots", "seeds"):
        if getattr(a, name) < 1:
            print(f"harness.fleet_sim: --{name} must be >= 1, got {getattr(a, name)}", file=sys.stderr)
            return 2
    for name in ("stall_every_s", "stall_s"):
        if not getattr(a, name) >= 0:  # 0: no stalls
            print(f"harness.fleet_sim: --{name.replace('_', '-')} must be >= 0 (0: no stalls), got {getattr(a, name)}",
                  file=sys.stderr)
            return 2
    if a.padding:
        print(f"{'videos':>10} " + " ".join(f"{n:>6} shards" for n in (2, 8, 32, 128)))
        for v in a.padding:
            pad = static_padding(v, (2, 8, 32, 128), a.seed)
            print(f"{v:>10,} " + " ".join(f"{pad[n]:>13.1%}" for n in (2, 8, 32, 128)))
        return 0
    if a.autoscale:
        return _print_autoscale(a)
    if a.ranks < 1 or a.step < 1 or a.step % a.ranks:
        print(f"harness.fleet_sim: --ranks must divide --step ({a.step}), got {a.ranks}", file=sys.stderr)
        return 2
    f = Fleet(a.hosts, a.videos, a.slots, a.spread, None if a.slow is None else (0, a.slow), a.stall_every_s,
              a.stall_s, step=a.step, ranks=a.ranks, seed=a.seed)
    if a.waits is not None:
        return _print_waits(f, a.waits)
    with _passes_quiet():
        runs = [[simulate(g, "routed"), simulate(replace(g, ranks=1), "static")]  # static: one reader
                for g in (replace(f, seed=a.seed + i) for i in range(a.seeds))]
    seeds = f"seed {a.seed}" if a.seeds == 1 else f"seeds {a.seed}..{a.seed + a.seeds - 1} (means; share: min-max)"
    stalls = f"stalls every {f.stall_every_s} s for {f.stall_s} s on average" if f.stalling else "no stalls"
    print(f"{f.hosts} hosts x {f.slots} workers, {f.videos} clips, speed spread sigma {f.spread}, {stalls}, "
          f"{f.ranks} rank(s) reading, {seeds}")
    print(f"{'split':<8} {'samples/s':>10} {'capacity':>9} {'share':>6} {'10-90 %':>8} {'decodes/clip':>13} "
          f"{'padding':>8} {'decoding':>9} {'idle at end':>12}" + (f" {'share min-max':>14}" if a.seeds > 1 else ""))
    for col in zip(*runs):
        def mean(x, col=col):
            return sum(x(r) for r in col) / len(col)

        def counted(x, col=col):  # a share the split counts, else "-"
            return "-" if x(col[0]) is None else f"{mean(x):.3f}"
        shares = [r.share for r in col]
        print(f"{col[0].mode:<8} {mean(lambda r: r.rate):>10.1f} {mean(lambda r: r.capacity):>9.1f} "
              f"{mean(lambda r: r.share):>6.3f} {mean(lambda r: r.steady_share):>8.3f} "
              f"{mean(lambda r: r.decodes):>13.3f} {mean(lambda r: 1 - r.samples / r.positions):>8.1%} "
              f"{counted(lambda r: r.decoding):>9} {counted(lambda r: r.idle_end):>12}"
              + (f" {min(shares):>6.3f}-{max(shares):.3f}" if a.seeds > 1 else ""))
    if a.json:
        write_whole(a.json, json.dumps({"fleet": asdict(f), "seeds": a.seeds, "results": [
            {k: v for k, v in dict(asdict(r), share=r.share, steady_share=r.steady_share, seed=a.seed + i).items()
             if k != "made_by"} for i, rows in enumerate(runs) for r in rows]}, indent=1))
    return 0

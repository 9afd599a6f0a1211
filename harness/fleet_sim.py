"""A pure simulator of a decode fleet feeding one job: how many samples per second a fleet of
hosts of unequal speed, which stall now and then, delivers in plan order, against the sum of the
hosts' rates, for the two ways hosts split the work:

* **routed** (``v2v_wire.fleet.Router``): every host serves the one plan; the reader asks each
  video of the host weighted rendezvous hashing and the bounded load pick, and hedges a video it
  waits on when its host went silent;
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
seconds) and says it with each answer. The reader reads positions in order, a step of ``step``
positions at a time, as fast as they are made (the trainer never waits on itself), and asks ahead for the videos
of the next ``lookahead`` positions. Each host works the videos asked of it in order of the first
position that needs them.

Pure and seeded: no socket, no clock; ``python -m harness.fleet_sim`` prints a table,
``tests/test_fleet.py`` checks the figures docs/scaling.md quotes.
"""
from __future__ import annotations

if __name__ == "__main__":  # Ctrl-C or SIGTERM from the start, the imports below included: one line
    import sys

    from v2v_wire.commands import run_command

    sys.exit(run_command("harness.fleet_sim", "harness.fleet_sim:main"))

import argparse
import heapq
import json
import sys
from pathlib import Path
from dataclasses import asdict, dataclass
from typing import Dict, List, Optional, Sequence, Set, Tuple

import numpy as np

from v2v_wire.commands import writable_problem, write_whole
from v2v_client.fleet_pass import STEAL_S
from v2v_wire.fleet import RateMeter, Router, video_key
from v2v_wire.plan import EpochPlan, Manifest

#: Decodes per worker a reader asks ahead by default: a clip of many windows decodes for many
#: times the mean, and the steps after it must find their clips made meanwhile (6 gives 0.72 of
#: the hosts' rate at 128 hosts, 10 gives 0.97: docs/scaling.md).
LOOKAHEAD_DECODES = 10

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
        lookahead: positions the reader asks ahead of the step it reads (None: ``LOOKAHEAD_DECODES``
            decodes per worker of the fleet, at the corpus's mean samples per clip).
        hedge_s: seconds a host may answer nothing before the videos a reader waits on are
            asked of the next host.
        slack: the router's bounded load (``Router``'s ``slack``).
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
    hedge_s: float = 10.0
    slack: float = 0.25
    seed: int = 0


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

    @property
    def share(self) -> float:
        """:attr:`steady_rate` over :attr:`capacity`."""
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
            if f.stall_every_s <= 0 or f.stall_s <= 0:
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
    """An epoch as the reader reads it: ``pos_clip`` (the clip of each position, None for padding),
    ``needs`` (clip -> (first position needing it, its samples)), ``home`` (static: clip -> shard)."""

    pos_clip: List[Optional[str]]
    needs: Dict[str, Tuple[int, int]]
    home: Optional[Dict[str, int]]

    @property
    def length(self) -> int:
        return len(self.pos_clip)

    @property
    def samples(self) -> int:
        return sum(1 for c in self.pos_clip if c is not None)


def _layout(f: Fleet, mode: str, epoch: int) -> _Layout:
    """The epoch's positions: the one plan (routed), or each shard's plan interleaved (static)."""
    slots, n = corpus(f), f.hosts
    if mode == "routed":
        plan = _epoch(slots, f.seed, epoch)
        return _Layout([plan.videos[i] for i in plan.video_index.tolist()], _needs(plan), None)
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
    """One simulated epoch's state: each host's queue (by the first position needing a clip) and
    free workers, the events to come (a decode's end; the reader's clock), what was made where,
    and the positions read (module docstring)."""

    def __init__(self, f: Fleet, lay: _Layout, router: Optional[Router], held: Optional[Dict[str, str]] = None):
        self.f, self.lay, self.router, self.n = f, lay, router, f.hosts
        self.held = held or {}  # clip -> the host that made it the epoch before (its frame cache holds it)
        self.speeds = _speeds(f)  # samples/s of one worker of each host
        self.stalls = _Stalls(f, 4 * lay.samples / (float(self.speeds.sum()) * f.slots) + 600.0)
        self.hosts = [f"host-{k:03d}" for k in range(self.n)]
        self.index = {h: k for k, h in enumerate(self.hosts)}
        mean = lay.samples / max(1, len(lay.needs))
        self.lookahead = f.lookahead or int(LOOKAHEAD_DECODES * self.n * f.slots * mean) + f.step
        self.t0 = max((s.heard for s in router.hosts.values()), default=0.0) if router else 0.0
        self.meters = [RateMeter() for _ in range(self.n)]  # each host's own measure of its capacity
        self.by_need = sorted(lay.needs, key=lambda v: lay.needs[v][0])
        self.asked_upto = 0  # index into by_need of the next clip to ask
        self.queues: List[List[Tuple[int, str]]] = [[] for _ in range(self.n)]
        self.free = [f.slots] * self.n
        self.events: List[Tuple[float, int, str]] = []  # (time, host or -1 for the reader's clock, clip)
        self.done_at: Dict[str, float] = {}
        self.running: Dict[Tuple[int, str], float] = {}  # (host, clip) decoding -> since when
        self.outstanding: Set[str] = set()  # clips asked and not made yet
        self.made_by: Dict[str, str] = {}  # clip -> the host whose copy was read
        self.decodes, self.now, self.read, self.head_since = 0, 0.0, 0, 0.0
        self.step_times: List[Tuple[int, float]] = []

    def start_work(self, k: int) -> None:
        while self.free[k] and self.queues[k]:
            _, clip = heapq.heappop(self.queues[k])
            if clip in self.done_at or (k, clip) in self.running:
                continue
            self.free[k] -= 1
            self.running[(k, clip)] = self.now
            self.decodes += 1
            end = self.stalls.finish(k, self.now, self.lay.needs[clip][1] / self.speeds[k])
            heapq.heappush(self.events, (end, k, clip))

    def ask(self, clip: str, k: int) -> None:
        self.outstanding.add(clip)
        heapq.heappush(self.queues[k], (self.lay.needs[clip][0], clip))
        self.start_work(k)

    def ask_ahead(self) -> None:
        needs = self.lay.needs
        while self.asked_upto < len(self.by_need) and needs[self.by_need[self.asked_upto]][0] < \
                self.read + self.lookahead:
            clip = self.by_need[self.asked_upto]
            self.asked_upto += 1
            if self.router is not None:
                due = (needs[clip][0] - self.read) / self.router.capacity()  # as the reader's Pass.due
                self.ask(clip, self.index[self.router.route(0, clip, needs[clip][1], self.t0 + self.now, due=due,
                                                            position=needs[clip][0], held=self.held.get(clip))])
            else:
                self.ask(clip, self.lay.home[clip])

    def advance(self) -> None:
        while self.read < self.lay.length:
            stop = min(self.lay.length, self.read + self.f.step)
            if any(c is not None and c not in self.done_at for c in self.lay.pos_clip[self.read:stop]):
                return
            self.read, self.head_since = stop, self.now
            self.step_times.append((self.read, self.now))

    def hedge(self) -> None:
        """The reader's clock: the clips asked of silent hosts are asked of their next hosts; those
        the step being read has waited on for ``STEAL_S`` are copied (``Router.copy``)."""
        r, at = self.router, self.t0 + self.now
        silent = {h for h in self.hosts if r.suspect(h, at)}
        waiting = [(0, c, self.lay.needs[c][1]) for c in self.outstanding if silent.intersection(r.asked.get((0, c), ()))]
        for _, c, h in r.hedges(sorted(waiting, key=lambda w: self.lay.needs[w[1]][0]), at):
            self.ask(c, self.index[h])
        waited = self.now - self.head_since
        if waited < STEAL_S:
            return
        for c in dict.fromkeys(self.lay.pos_clip[self.read:self.read + self.f.step]):
            if c is not None and c not in self.done_at:
                h = r.copy(0, c, self.lay.needs[c][1], at, r.asked.get((0, c), ()), self.lay.needs[c][0])
                if h is not None:
                    self.ask(c, self.index[h])

    def made(self, k: int, clip: str) -> None:
        """Host ``k``'s worker made ``clip``: the first copy is read."""
        self.free[k] += 1
        r, at = self.router, self.t0 + self.now
        self.meters[k].add(self.lay.needs[clip][1], (self.now - self.running.pop((k, clip))) / self.f.slots, at)
        if clip not in self.done_at:
            self.done_at[clip] = self.now
            self.outstanding.discard(clip)
            if r is not None:
                r.answered(self.hosts[k], 0, clip, at, True, self.meters[k].rate())
                r.finished(0, clip)
                self.made_by[clip] = self.hosts[k]
            self.advance()
            self.ask_ahead()
        elif r is not None:
            r.answered(self.hosts[k], 0, clip, at, True, self.meters[k].rate())
        self.start_work(k)

    def run(self) -> None:
        self.ask_ahead()
        tick = min(self.f.hedge_s, STEAL_S) / 2
        heapq.heappush(self.events, (tick, -1, ""))
        while self.read < self.lay.length:
            if not self.events:
                raise RuntimeError(f"fleet_sim: stuck at position {self.read} of {self.lay.length}")
            self.now, k, clip = heapq.heappop(self.events)
            if k >= 0:
                self.made(k, clip)
                continue
            if self.router is not None:
                self.hedge()
            heapq.heappush(self.events, (self.now + tick, -1, ""))


def simulate(f: Fleet, mode: str, epoch: int = 0, router: Optional[Router] = None,
             held: Optional[Dict[str, str]] = None) -> Result:
    """One epoch of fleet ``f`` split as ``mode`` (``"routed"`` or ``"static"``); ``router``: a
    reader's router kept from an earlier epoch (routed only; default a new one); ``held``: clip ->
    the host that made it in that epoch (its frame cache holds it).

    Raises:
        ValueError: another mode, naming it."""
    if mode not in ("routed", "static"):
        raise ValueError(f"mode must be 'routed' or 'static', got {mode!r}")
    lay = _layout(f, mode, epoch)
    if mode == "routed" and router is None:
        router = Router([f"host-{k:03d}" for k in range(f.hosts)], slack=f.slack, hedge_s=f.hedge_s, patience_s=STEAL_S)
    w = _World(f, lay, router if mode == "routed" else None, held)
    w.run()
    end, length = w.now, lay.length
    lo, hi = int(0.1 * length), int(0.9 * length)
    t_lo = next(t for p, t in w.step_times if p >= lo)
    t_hi = next(t for p, t in w.step_times if p >= hi)
    steady = sum(1 for c in lay.pos_clip[lo:hi] if c is not None)
    capacity = float(sum(w.speeds[k] * f.slots * (1 - w.stalls.stalled(k, end) / end) for k in range(f.hosts)))
    made_by = w.made_by if mode == "routed" else {c: w.hosts[lay.home[c]] for c in lay.needs}
    return Result(mode, lay.samples, length, end, lay.samples / end, steady / max(t_hi - t_lo, 1e-9), capacity,
                  w.decodes / max(1, len(lay.needs)), made_by)


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
    router = Router([f"host-{k:03d}" for k in range(f.hosts)], slack=f.slack, hedge_s=f.hedge_s, patience_s=STEAL_S)
    first = simulate(f, "routed", 0, router).made_by
    second = simulate(f, "routed", 1, router, first).made_by
    return sum(first.get(c) == h for c, h in second.items()) / max(1, len(second))


def _sizes(text: str) -> List[int]:
    """``--padding``'s corpus sizes: comma-separated ints >= 1 (argparse names the option on error)."""
    try:
        sizes = [int(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: not comma-separated numbers of videos") from None
    if any(v < 1 for v in sizes):
        raise argparse.ArgumentTypeError(f"{text!r}: each corpus holds at least one video")
    return sizes


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m harness.fleet_sim", description=__doc__.split("\n\n")[0])
    ap.add_argument("--hosts", type=int, default=Fleet.hosts)
    ap.add_argument("--videos", type=int, default=Fleet.videos)
    ap.add_argument("--slots", type=int, default=Fleet.slots)
    ap.add_argument("--spread", type=float, default=Fleet.spread)
    ap.add_argument("--slow", type=float, default=None, help="host 0's speed times this factor")
    ap.add_argument("--stall-every-s", type=float, default=Fleet.stall_every_s)
    ap.add_argument("--stall-s", type=float, default=Fleet.stall_s)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None, help="also write the results here")
    ap.add_argument("--padding", default=None, metavar="VIDEOS,...", type=_sizes,
                    help="print only the static shards' padding for these corpus sizes (2, 8, 32, 128 shards)")
    a = ap.parse_args(argv)
    problem = writable_problem(Path(a.json)) if a.json else ""
    if problem:
        print(f"harness.fleet_sim: --json {a.json}: {problem}", file=sys.stderr)
        return 2
    for name in ("hosts", "videos", "slots"):
        if getattr(a, name) < 1:
            print(f"harness.fleet_sim: --{name} must be >= 1, got {getattr(a, name)}", file=sys.stderr)
            return 2
    if a.padding:
        print(f"{'videos':>10} " + " ".join(f"{n:>6} shards" for n in (2, 8, 32, 128)))
        for v in a.padding:
            pad = static_padding(v, (2, 8, 32, 128), a.seed)
            print(f"{v:>10,} " + " ".join(f"{pad[n]:>13.1%}" for n in (2, 8, 32, 128)))
        return 0
    f = Fleet(a.hosts, a.videos, a.slots, a.spread, None if a.slow is None else (0, a.slow), a.stall_every_s,
              a.stall_s, seed=a.seed)
    rows = [simulate(f, m) for m in ("routed", "static")]
    print(f"{f.hosts} hosts x {f.slots} workers, {f.videos} clips, speed spread sigma {f.spread}, "
          f"stalls every {f.stall_every_s} s for {f.stall_s} s on average")
    print(f"{'split':<8} {'samples/s':>10} {'steady':>8} {'capacity':>9} {'share':>6} {'decodes/clip':>13} {'padding':>8}")
    for r in rows:
        print(f"{r.mode:<8} {r.rate:>10.1f} {r.steady_rate:>8.1f} {r.capacity:>9.1f} {r.share:>6.3f} "
              f"{r.decodes:>13.3f} {1 - r.samples / r.positions:>8.1%}")
    if a.json:
        write_whole(a.json, json.dumps({"fleet": asdict(f), "results": [
            {k: v for k, v in dict(asdict(r), share=r.share).items() if k != "made_by"} for r in rows]}, indent=1))
    return 0

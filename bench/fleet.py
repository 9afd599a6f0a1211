"""A fleet of real ``v2v-serve`` hosts on loopback, read as one plan (docs/scaling.md, "One plan,
any fleet"), against the same hosts split as static shards.

Run: ``python -m bench.fleet [--json docs/fleet.json]``. Each host is a ``v2v-serve`` of one
worker pinned to its own core (``taskset -c``); host B is made slow by a SIGSTOP/SIGCONT duty
cycle on its workers (stopped ``1 - duty`` of each 0.3 s period). Rates are read over whole
epochs of at least :data:`MEASURED` samples past a warm-up (the first ``warmup`` batches): a short
window past the warm-up reads the stock the hosts made ahead, not their rate. Rows:

* ``rates``: A alone, B (slowed) alone, A and B read as one plan, A and B as static shards
  (``--shard 0/2``, ``--shard 1/2``): the pair's samples/s over the sum of A's and B's, each over
  epoch 0 past the warm-up, the 10-90 % window beside, with the samples made of the epoch over
  those read and of the next epoch (:func:`rate`).
* ``stop``: B SIGSTOPped for ``--stop-s`` seconds (server and workers) after the second batch:
  the longest gap between batches, each id once, and each sample's bytes equal to one server's read.
* ``kill``: B SIGKILLed after the second batch: the same.
* ``join``: a host started after the third batch, named in the reader's list from the start:
  seconds from its start to its first sample made, and the rate before and after.
* ``cache``: epoch 2's frame-cache hit ratio (hits / lookups, each host's ``/metrics``; a lookup is
  one pass over a video, counted when the pass ends) of A alone, then of A and B as one fleet
  (each its own cache): the fleet's over the lone host's, and the share of videos whose host
  changed between the fleet's two epochs.
* ``moved``: A and B read epoch 1 as a fleet, then A, B and C (on core 1 with B) read it again
  with a fresh reader: the share of videos whose host changed, observed (the host that served
  its rows) and of the owner alone (``rank_hosts`` over the hosts' names, equal weights).
* ``ranks``: a job of ``--ranks`` ranks (``rank=r, world_size=N``, a thread each) reads epoch 1
  of A and B as one fleet: the samples the hosts made (their ``/metrics``) over the samples the
  ranks read (1.0 when each video is decoded once, above when ranks ask a video of two hosts),
  the share of videos served by both, and the job's samples/s.

* ``batches``: one host read by one reader (one fetch in flight) at each of ``BATCHES`` rows a
  batch, ``EPOCHS`` whole epochs each, a fresh host for each batch size: each epoch's samples
  made (the host's feed, ``samples_made_by_epoch``, once its workers are idle) over those read,
  and its samples/s over epoch 0's.
* ``readers``: A, and B slowed, each read alone by a one-rank job, then A and B read as one fleet by
  real DDP jobs (``torchrun``, gloo, ``harness.plan_job``: a DDP step a batch of 4) of each of
  ``READERS``' ranks and DataLoader workers, fresh hosts each: samples/s over the whole epoch
  (from the job's first step to its last: the stock made ahead at the start is read within it),
  over the sum of A's and B's alone; the 10-90 % window beside; the samples the hosts made of the
  epoch over those read, and of the next epoch (made ahead, not read).
* ``restart``: a job reads half of epoch 1 of one host and is cut off (its reader closed, its
  asks left behind); a new job then reads epoch 1 whole: its samples/s over a fresh host's, and
  the samples of epoch 1 made while it read over those it read (what the cut-off job read is
  made again: 1.0 when nothing else is).

The ``cache``, ``moved`` and ``ranks`` rows read with batches of one row, so that each batch's ``servers``
names the host of its one sample. The ``cache`` row's entries take about 25 MB a video in the
temporary folder, twice over (the lone host's and the fleet's): 11 GB for its corpus of
:data:`CACHE_COPIES` links to each clip (the other rows read ``--copies``).

Needs ``taskset`` (util-linux) and 2 cores.
"""
from __future__ import annotations

if __name__ == "__main__":  # Ctrl-C or SIGTERM from the start, the imports below included: one line
    import sys

    from v2v_wire.commands import run_command

    sys.exit(run_command("bench.fleet", "bench.fleet:main"))

import argparse
import hashlib
import itertools
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Set, Tuple

import numpy as np

from harness.faults import worker_pids
from harness.serve import ServeProcess, free_port
from v2v_client import V2VStreamDataset
from v2v_client.plan_dataset import open_stream
from v2v_wire.commands import json_output_problem, write_whole
from v2v_wire.fleet import rank_hosts
from v2v_wire.ids import parse_sample_id

OUTPUTS = ("voxels", "frames")
ROWS = ("rates", "stop", "kill", "join", "cache", "moved", "ranks", "batches", "restart", "readers")
#: The ``readers`` row's jobs: (ranks, DataLoader workers a rank; 0: its main process reads).
READERS = ((1, 0), (2, 0), (4, 0), (2, 2))
#: Rows per batch the ``batches`` row reads one host at, and its epochs each.
BATCHES = (1, 4, 8, 12, 16, 32)
EPOCHS = 4
#: GiB of frame cache of each ``cache`` row host: the bundled clips' kept frames (about 25 MB a
#: video, 240 videos at the default size) fit whole, so a miss in epoch 2 is never the budget's.
CACHE_GB = 16
#: Links to each bundled clip in the ``cache`` and ``moved`` rows' corpus (240 videos): its frame
#: caches take about 25 MB a video, twice over.
CACHE_COPIES = 60
#: Samples a rate reads past its warm-up at least: a whole epoch, not the stock made ahead.
MEASURED = 1600
#: The bundled clips the corpus links to.
CLIPS = Path(__file__).resolve().parent.parent / "v2v_server" / "sample_videos"


def layout(seed: int = 1) -> List[str]:
    return ["--sequence-length", "8", "--crop-size", "64", "--max-samples-per-video", "3", "--shot-cuts", "off",
            "--batch-size", "4", "--seed", str(seed), "--workers", "1", "--flow-preset", "ultrafast"]


def make_corpus(root: Path, copies: int) -> Path:
    """``copies`` links to each bundled clip: enough videos for a router to balance."""
    root.mkdir(parents=True, exist_ok=True)
    for p in sorted(CLIPS.glob("*.mp4")):
        for c in range(copies):
            dst = root / f"{p.stem}_{c:03d}{p.suffix}"
            if not dst.exists():
                os.link(p, dst) if os.stat(p).st_dev == os.stat(root).st_dev else shutil.copy(p, dst)
    return root


def host(corpus: Path, core: int, extra: List[str] = (), endpoint: Optional[str] = None) -> ServeProcess:
    args = ["--videos", str(corpus), *layout(), *extra]
    if endpoint:
        args += ["--bind", endpoint]
    return ServeProcess(args, wrap=["taskset", "-c", str(core)], ready_timeout_s=120)


class Slow:
    """A SIGSTOP/SIGCONT duty cycle on a server's workers: they run ``duty`` of each ``period_s``."""

    def __init__(self, server: ServeProcess, duty: float, period_s: float = 0.3):
        self.server, self.duty, self.period_s = server, duty, period_s
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> "Slow":
        self._t.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._t.join(5)
        self._signal(signal.SIGCONT)

    def _signal(self, sig) -> None:
        for pid in worker_pids(self.server.proc.pid):
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass

    def _run(self) -> None:
        while not self._stop.is_set():
            self._signal(signal.SIGSTOP)
            time.sleep(self.period_s * (1 - self.duty))
            self._signal(signal.SIGCONT)
            time.sleep(self.period_s * self.duty)


def rate(servers: Sequence[ServeProcess], endpoint: str, warmup: int) -> dict:
    """Epoch 0 of ``endpoint`` (``servers``, each with its ``/metrics``) read whole in batches of 4:
    samples/s from the end of the first ``warmup`` batches to the epoch's end (the stock made
    ahead at the start is read within it), over the 10-90 % window beside, and the samples the
    servers made of the epoch over those read and of the next epoch (made ahead, not read).

    Raises:
        ValueError: fewer than :data:`MEASURED` samples past the warm-up (a corpus too small)."""
    ds = V2VStreamDataset(endpoint, batch_size=4, outputs=OUTPUTS, timeout_s=300)
    times, read = [], []
    for b in ds:
        times.append(time.perf_counter())
        read.append((read[-1] if read else 0) + int((~b["padding"]).sum()))
    if read[-1] - read[warmup] < MEASURED:
        raise ValueError(f"{endpoint}: {read[-1] - read[warmup]} samples past the warm-up, fewer than {MEASURED}: "
                         "a larger --copies")
    lo, hi = (int(np.searchsorted(read, f * read[-1])) for f in (0.1, 0.9))
    made_now, ahead = epoch_made(servers, 0), epoch_made(servers, 1)
    return {"samples_per_s": (read[-1] - read[warmup]) / (times[-1] - times[warmup]),
            "samples_per_s_10_90": (read[hi] - read[lo]) / (times[hi] - times[lo]),
            "samples_read": read[-1], "made_over_read": made_now / read[-1], "made_ahead": ahead}


def digest(batch, j: int) -> str:
    h = hashlib.sha1()
    for k in OUTPUTS:
        h.update(batch[k][j].numpy().tobytes())
    return h.hexdigest()


def read_epoch(endpoint: str, after: Optional[callable] = None, retry_s: float = 10.0) -> dict:
    """One epoch: ``{ids: [...], digests: {id: sha1}, gaps: [s between batches], times: [...]}``;
    ``after(i)`` is called after batch ``i``."""
    out = {"ids": [], "digests": {}, "gaps": [], "times": []}
    ds = V2VStreamDataset(endpoint, outputs=OUTPUTS, timeout_s=300, retry_s=retry_s)
    last = time.monotonic()
    for i, b in enumerate(ds):
        now = time.monotonic()
        out["gaps"].append(now - last)
        out["times"].append(now)
        last = now
        for j, sid in enumerate(b["sample_ids"]):
            if not b["padding"][j]:
                out["ids"].append(sid)
                out["digests"][sid] = digest(b, j)
        if after is not None:
            after(i)
    return out


def check(got: dict, want: dict) -> dict:
    return {"each_once": sorted(got["ids"]) == sorted(want["ids"]) and len(set(got["ids"])) == len(got["ids"]),
            "bytes_equal": got["digests"] == want["digests"], "longest_gap_s": round(max(got["gaps"][1:] or [0]), 2)}


def rates(corpus: Path, a, ra: dict) -> dict:
    """B slowed alone, A and B as a fleet, A and B as static shards (A alone: ``ra``, :func:`rate`)."""
    with host(corpus, 1, metrics()) as B, Slow(B, a.duty):
        rb = rate([B], B.endpoint, a.warmup)
    with host(corpus, 0, metrics()) as A, host(corpus, 1, metrics()) as B, Slow(B, a.duty):
        pair = rate([A, B], f"{A.endpoint},{B.endpoint}", a.warmup)
    with host(corpus, 0, ["--shard", "0/2", *metrics()]) as A, host(corpus, 1, ["--shard", "1/2", *metrics()]) as B, \
            Slow(B, a.duty):
        static = rate([A, B], f"{A.endpoint},{B.endpoint}", a.warmup)
    total = ra["samples_per_s"] + rb["samples_per_s"]
    out = {"a_alone": ra, "b_alone_slowed": rb, "fleet": pair, "static_shards": static,
           "fleet_share": pair["samples_per_s"] / total, "static_share": static["samples_per_s"] / total}
    print(f"rates (samples/s over the whole epoch past {a.warmup} batches): A {ra['samples_per_s']:.2f}, B slowed "
          f"{rb['samples_per_s']:.2f}, fleet {pair['samples_per_s']:.2f} ({out['fleet_share']:.2f} of the sum, "
          f"{pair['made_over_read']:.3f} made a sample read), static shards {static['samples_per_s']:.2f} "
          f"({out['static_share']:.2f})", flush=True)
    return out


def fault_row(corpus: Path, a, fault: str, want: dict) -> dict:
    """B SIGSTOPped for ``a.stop_s`` (``"stop"``) or SIGKILLed (``"kill"``) after the second batch."""
    with host(corpus, 0) as A, host(corpus, 1) as B:
        def after(i):
            if i != 1:
                return
            if fault == "kill":
                _kill_tree(B, signal.SIGKILL)
            else:
                _kill_tree(B, signal.SIGSTOP)
                threading.Timer(a.stop_s, _kill_tree, (B, signal.SIGCONT)).start()
        got = read_epoch(f"{A.endpoint},{B.endpoint}", after)
        out = check(got, want)
        print(f"{fault}: {out}", flush=True)
        if fault == "stop":  # B continued before it is stopped for good
            time.sleep(max(0.0, a.stop_s - (got["times"][-1] - got["times"][0])) + 1)
    return out


def join_row(corpus: Path, want: dict) -> dict:
    """A host started after the third batch, listed from the start: when it makes its first
    sample, and the reader's batches/s before and after its start."""
    late_ep = f"tcp://127.0.0.1:{free_port()}"
    started: Dict[str, float] = {}
    late: List[ServeProcess] = []

    def poll():  # when the joiner's first sample is made, seen from outside
        while "first" not in started and "done" not in started:
            try:
                feed = open_stream(late_ep, timeout_s=2).server_feed()
                if feed and feed["samples_made"] > 0:
                    started["first"] = time.monotonic()
            except (TimeoutError, OSError):
                pass
            time.sleep(0.5)

    def join(i):
        if i == 2:
            started["at"] = time.monotonic()
            late.append(host(corpus, 1, endpoint=late_ep).start())
            threading.Thread(target=poll, daemon=True).start()

    with host(corpus, 0) as A:
        try:
            got = read_epoch(f"{A.endpoint},{late_ep}", join)
        finally:
            started["done"] = time.monotonic()
            for s in late:
                s.stop()
    t, at = got["times"], started.get("at", got["times"][-1])
    k = next((i for i, x in enumerate(t) if x >= at), len(t) - 1)
    before = (k - 1) / (t[k - 1] - t[0]) if k > 1 else float("nan")
    after_rate = (len(t) - 1 - k) / (t[-1] - t[k]) if len(t) - 1 > k else float("nan")
    out = {"seconds_to_first_sample": (started["first"] - at) if "first" in started else None,
           "batches_per_s_before": before, "batches_per_s_after": after_rate,
           "each_once": sorted(got["ids"]) == sorted(want["ids"]), "bytes_equal": got["digests"] == want["digests"]}
    print(f"join: {out}", flush=True)
    return out


def cache_host(corpus: Path, core: int, cache_dir: Path) -> ServeProcess:
    """A host with a frame cache under ``cache_dir`` and its /metrics on a free port (:func:`looked`)."""
    return host(corpus, core, ["--frame-cache-gb", str(CACHE_GB), "--cache-dir", str(cache_dir),
                               *metrics()])


def scrape(server: ServeProcess) -> Dict[str, int]:
    """``server``'s ``/metrics`` (its ``--metrics-port``): each series' value, a metric's labelled
    series summed under its name."""
    port = server.args[server.args.index("--metrics-port") + 1]
    page = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10).read().decode()
    out: Dict[str, int] = {}
    for line in page.splitlines():
        if line and not line.startswith("#"):
            name = line.split("{")[0].split()[0]
            out[name] = out.get(name, 0) + int(float(line.split()[-1]))
    return out


def looked(server: ServeProcess) -> Tuple[int, int, int]:
    """``(hits, misses, workers busy)``: ``server``'s frame-cache lookups so far (misses of every
    cause) and its workers making samples now."""
    m = scrape(server)
    return m.get("v2v_frame_cache_hits_total", 0), m.get("v2v_frame_cache_misses_total", 0), \
        m.get("v2v_workers_busy", 0)


def settled(servers: Sequence[ServeProcess], quiet_s: float = 1.0, limit_s: float = 120.0,
            counts=looked) -> List[tuple]:
    """Each server's ``counts`` (:func:`looked`: frame-cache ``(hits, misses)``), its last item the
    workers busy and left out, once no worker is busy and no count has changed for ``quiet_s``: a
    pass is counted when it ends, past its video's last sample (it decodes on to fill the entry),
    a lone server makes ahead into the next epoch (within its shuffle buffer), and a fleet's host
    finishes the copies that lost."""
    last, since, deadline = None, time.monotonic(), time.monotonic() + limit_s
    while time.monotonic() < deadline:
        now = [counts(s) for s in servers]
        if now != last or any(c[-1] for c in now):
            last, since = now, time.monotonic()
        elif time.monotonic() - since >= quiet_s:
            break
        time.sleep(0.5)
    return [c[:-1] for c in last]


def read_hosts(ds: V2VStreamDataset, epoch: int) -> Dict[str, Set[str]]:
    """Epoch ``epoch`` of ``ds`` (batches of one row): video -> the hosts that served its rows."""
    ds.set_epoch(epoch)
    out: Dict[str, Set[str]] = {}
    for b in ds:
        if not b["padding"][0]:
            out.setdefault(parse_sample_id(b["sample_ids"][0]).video, set()).update(b["servers"])
    return out


def changed(a: Dict[str, Set[str]], b: Dict[str, Set[str]]) -> float:
    """The share of the videos of ``a`` whose hosts in ``b`` are not the same."""
    return sum(1 for v, hosts in a.items() if b.get(v) != hosts) / max(1, len(a))


def off_owner(read: Dict[str, Set[str]], hosts: List[str], weights: Optional[Dict[str, float]] = None) -> float:
    """The share of the videos of ``read`` served by other hosts than their owner among ``hosts``
    at ``weights`` (default equal; ``rank_hosts``): what weights, bounded load and copies moved."""
    return sum(1 for v, h in read.items() if h != {rank_hosts(v, hosts, weights)[0]}) / max(1, len(read))


def weight_fit(read: Dict[str, Set[str]], hosts: List[str]) -> dict:
    """The weights (steps of 2 ** (1/4), the router's; the first host's 0) under which the fewest
    videos of ``read`` are off their owner among ``hosts``, and that share: what weights explain,
    the rest being bounded load and copies."""
    best = (off_owner(read, hosts), [0] * len(hosts))
    for steps in itertools.product(range(-4, 5), repeat=max(0, len(hosts) - 1)):
        share = off_owner(read, hosts, {h: 2 ** (k / 4) for h, k in zip(hosts, (0, *steps))})
        if share < best[0]:
            best = (share, [0, *steps])
    return {"steps": dict(zip(hosts, best[1])), "off_owner": best[0]}


def epochs_looked(servers: Sequence[ServeProcess]) -> dict:
    """Epochs 1 and 2 (index 0, 1) read from ``servers`` as one plan by one reader: epoch 2's
    frame-cache hits and misses summed over the servers (a video passed twice is looked up twice),
    its hit ratio, and the share of videos whose host changed between the epochs."""
    hosts = [s.endpoint for s in servers]
    ds = V2VStreamDataset(",".join(hosts), batch_size=1, outputs=OUTPUTS, timeout_s=300)
    first = read_hosts(ds, 0)
    before = settled(servers)
    second = read_hosts(ds, 1)
    after = settled(servers)
    hits = sum(h for h, _ in after) - sum(h for h, _ in before)
    misses = sum(m for _, m in after) - sum(m for _, m in before)
    return {"hits": hits, "misses": misses, "hit_ratio": hits / max(1, hits + misses),
            "epoch1_hits": sum(h for h, _ in before), "epoch1_misses": sum(m for _, m in before),
            "videos": len(second), "videos_moved": changed(first, second),
            "off_owner": [off_owner(r, hosts) for r in (first, second)],
            "weight_fit": [weight_fit(r, hosts) for r in (first, second)],
            "videos_of_two_hosts": sum(1 for h in second.values() if len(h) > 1) / max(1, len(second))}


def cache_row(corpus: Path, d: Path) -> dict:
    """Epoch 2's frame-cache hit ratio of A alone, then of A and B as one fleet (each its own
    cache, cold at the start): the fleet's over the lone host's; the bar is 0.95."""
    with cache_host(corpus, 0, d / "cache-alone") as A:
        one = epochs_looked([A])
    with cache_host(corpus, 0, d / "cache-a") as A, cache_host(corpus, 1, d / "cache-b") as B:
        pair = epochs_looked([A, B])
    out = {"alone": one, "fleet": pair, "fleet_over_alone": pair["hit_ratio"] / max(1e-9, one["hit_ratio"])}
    print(f"cache: epoch 2 frame-cache hits: A alone {one['hit_ratio']:.3f} ({one['hits']} of "
          f"{one['hits'] + one['misses']}), A and B as a fleet {pair['hit_ratio']:.3f} ({pair['hits']} of "
          f"{pair['hits'] + pair['misses']}): "
          f"{out['fleet_over_alone']:.3f} of the lone host's (bar 0.95); videos whose host changed between the "
          f"fleet's epochs {pair['videos_moved']:.3f}, off their owner {pair['off_owner'][0]:.3f} and "
          f"{pair['off_owner'][1]:.3f}", flush=True)
    return out


def moved_row(corpus: Path) -> dict:
    """The share of videos whose host changes when a third host joins two (bar: 1/3 + 0.05): epoch 1
    read by A and B, then by A, B and C with a fresh reader, so that only the fleet differs between
    the reads (another epoch queues other videos together, which moves videos by bounded load
    alone: the ``cache`` row's change between epochs). C shares core 1 with B."""
    with host(corpus, 0) as A, host(corpus, 1) as B:
        pair = [A.endpoint, B.endpoint]
        two = read_hosts(V2VStreamDataset(",".join(pair), batch_size=1, outputs=OUTPUTS, timeout_s=300), 0)
        with host(corpus, 1) as C:
            trio = [*pair, C.endpoint]
            three = read_hosts(V2VStreamDataset(",".join(trio), batch_size=1, outputs=OUTPUTS, timeout_s=300), 0)
    owner = sum(1 for v in two if rank_hosts(v, pair)[0] != rank_hosts(v, trio)[0]) / max(1, len(two))
    to_c = sum(1 for v, hosts in three.items() if C.endpoint in hosts) / max(1, len(three))
    out = {"videos": len(two), "owner_moved": owner, "observed_moved": changed(two, three),
           "served_by_joiner": to_c, "bar": 1 / 3 + 0.05, "off_owner": [off_owner(two, pair), off_owner(three, trio)],
           "weight_fit": [weight_fit(two, pair), weight_fit(three, trio)]}
    print(f"moved: a third host joining two: {out['observed_moved']:.3f} of {len(two)} videos changed host "
          f"(owner alone {owner:.3f}, bar {out['bar']:.3f}); the joiner served {to_c:.3f}; off their owner "
          f"{out['off_owner'][0]:.3f} of two hosts, {out['off_owner'][1]:.3f} of three", flush=True)
    return out


def made(server: ServeProcess) -> Tuple[int, int]:
    """``(samples made, workers busy)`` of ``server`` so far."""
    m = scrape(server)
    return m.get("v2v_samples_made_total", 0), m.get("v2v_workers_busy", 0)


def ranks_row(corpus: Path, ranks: int) -> dict:
    """A job of ``ranks`` ranks, a thread each, reads epoch 1 of A and B as one fleet: the samples
    the hosts made (once no worker is busy and the count holds for a second) over those read."""
    with host(corpus, 0, metrics()) as A, host(corpus, 1, metrics()) as B:
        pair = ",".join([A.endpoint, B.endpoint])
        hosts: List[Dict[str, Set[str]]] = [{} for _ in range(ranks)]
        read = [0] * ranks

        def run(r: int) -> None:
            ds = V2VStreamDataset(pair, batch_size=1, rank=r, world_size=ranks, outputs=OUTPUTS, timeout_s=300)
            for b in ds:
                if not b["padding"][0]:
                    hosts[r].setdefault(parse_sample_id(b["sample_ids"][0]).video, set()).update(b["servers"])
                    read[r] += 1

        threads = [threading.Thread(target=run, args=(r,), daemon=True) for r in range(ranks)]
        t0 = time.perf_counter()
        for t in threads:
            t.start()
        for t in threads:
            t.join(1200)
        seconds = time.perf_counter() - t0
        total = sum(m for m, in settled([A, B], counts=made))
    served: Dict[str, Set[str]] = {}
    for h in hosts:
        for v, s in h.items():
            served.setdefault(v, set()).update(s)
    out = {"ranks": ranks, "samples_read": sum(read), "samples_made": total, "made_over_read": total / max(1, sum(read)),
           "videos_of_two_hosts": sum(1 for s in served.values() if len(s) > 1) / max(1, len(served)),
           "samples_per_s": sum(read) / seconds}
    print(f"ranks: {ranks} ranks read A and B: the hosts made {out['made_over_read']:.3f} samples a sample read; "
          f"{out['videos_of_two_hosts']:.3f} of the videos served by both; {out['samples_per_s']:.1f} samples/s",
          flush=True)
    return out


#: The ``batches`` and ``restart`` rows' hosts: up to 10 samples a video (the bundled clips give
#: 10, 10, 6 and 3 windows), so that a decode makes more than a batch's worth of some videos, and
#: the server's own batch size (``DeliveryPolicy.batch_size``, the samples it keeps once fetched).
WHOLE_VIDEOS = ["--max-samples-per-video", "10", "--batch-size", "12"]


def metrics() -> List[str]:
    """A host's ``/metrics`` on a free port (:func:`scrape`)."""
    return ["--metrics-port", str(free_port())]


def metered(corpus: Path) -> ServeProcess:
    """Host A with :data:`WHOLE_VIDEOS` and its ``/metrics`` (:func:`made`)."""
    return host(corpus, 0, [*WHOLE_VIDEOS, *metrics()])


def read_count(ds: V2VStreamDataset, stop: Optional[int] = None) -> Tuple[int, float]:
    """``(samples read, seconds)`` of one pass of ``ds``, cut off after ``stop`` samples if given."""
    n, t0 = 0, time.perf_counter()
    for b in ds:
        n += int((~b["padding"]).sum())
        if stop is not None and n >= stop:
            break
    return n, time.perf_counter() - t0


def made_of(server: ServeProcess, epoch: int) -> int:
    """Samples of ``epoch`` ``server`` made so far (its feed's ``samples_made_by_epoch``), once
    its workers are idle: what it made ahead of the epoch, while its reader read the one before,
    counts in it."""
    settled([server], counts=made)
    return open_stream(server.endpoint, timeout_s=30).server_feed()["samples_made_by_epoch"].get(epoch, 0)


def batches_row(corpus: Path, batches: Sequence[int] = BATCHES, epochs: int = EPOCHS) -> dict:
    """For each of ``batches`` rows a batch, a fresh host read ``epochs`` whole epochs by one
    reader with one fetch in flight: each epoch's samples made over read and samples/s."""
    out = {}
    for batch in batches:
        with metered(corpus) as A:
            ds = V2VStreamDataset(A.endpoint, batch_size=batch, outputs=OUTPUTS, timeout_s=300, prefetch=1)
            per = []
            for epoch in range(epochs):
                ds.set_epoch(epoch)
                n, seconds = read_count(ds)
                m = made_of(A, epoch)
                per.append({"samples_read": n, "samples_made": m, "made_over_read": m / n, "samples_per_s": n / seconds})
        read, total = sum(e["samples_read"] for e in per), sum(e["samples_made"] for e in per)
        out[batch] = {"epochs": per, "made_over_read": total / read,
                      "worst_made_over_read": max(e["made_over_read"] for e in per),
                      "slowest_over_epoch_0": min(e["samples_per_s"] for e in per) / per[0]["samples_per_s"]}
        print(f"batches: batch {batch}: made over read per epoch {[round(e['made_over_read'], 3) for e in per]}; "
              f"samples/s {[round(e['samples_per_s'], 1) for e in per]}", flush=True)
    return out


def restart_row(corpus: Path, batch: int = 4) -> dict:
    """Epoch 1 of a fresh host, then of a host whose last job was cut off half-way through it."""
    def job(endpoint: str) -> V2VStreamDataset:
        ds = V2VStreamDataset(endpoint, batch_size=batch, outputs=OUTPUTS, timeout_s=300)
        ds.set_epoch(1)
        return ds

    with metered(corpus) as A:
        fresh, seconds = read_count(job(A.endpoint))
        fresh_rate = fresh / seconds
    with metered(corpus) as A:
        read_count(job(A.endpoint), stop=fresh // 2)  # cut off: what it asked ahead stays asked
        before = made_of(A, 1)
        n, seconds = read_count(job(A.endpoint))
        after = made_of(A, 1)
    out = {"fresh_samples_per_s": fresh_rate, "after_cut_samples_per_s": n / seconds,
           "over_fresh": n / seconds / fresh_rate, "made_over_read": (after - before) / n}
    print(f"restart: a job after one cut off mid-epoch reads {out['over_fresh']:.2f} of a fresh host's rate, "
          f"{out['made_over_read']:.3f} made a sample read", flush=True)
    return out


def job_epoch(endpoint: str, ranks: int, workers: int, out: Path) -> dict:
    """Epoch 0 of ``endpoint`` read by a DDP job of ``ranks`` ranks of ``workers`` DataLoader workers
    (``harness.plan_job``, batches of 4): samples read, samples/s over the whole epoch (the rows
    after the job's first step over the seconds from it to the last) and over its 10-90 % window."""
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    r = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(ranks),
                        "-m", "harness.plan_job", endpoint, str(out), "--epochs", "1", "--batch-size", "4",
                        "--workers", str(workers)], capture_output=True, text=True, timeout=3600)
    if r.returncode != 0:
        raise RuntimeError(f"harness.plan_job on {endpoint}: exit {r.returncode}: {r.stderr[-2000:]}")
    steps = sorted((t, n) for p in out.glob("rank*.json") for _, t, n in json.loads(p.read_text())["times"])
    t = np.array([x for x, _ in steps])
    read = np.cumsum([n for _, n in steps])
    lo, hi = np.searchsorted(read, 0.1 * read[-1]), np.searchsorted(read, 0.9 * read[-1])
    return {"samples_read": int(read[-1]), "samples_per_s": float((read[-1] - read[0]) / (t[-1] - t[0])),
            "samples_per_s_10_90": float((read[hi] - read[lo]) / max(1e-9, t[hi] - t[lo]))}


def epoch_made(servers: Sequence[ServeProcess], epoch: int) -> int:
    """Samples of ``epoch`` the ``servers`` made, once their workers are idle (:func:`made_of`)."""
    return sum(made_of(s, epoch) for s in servers)


def readers_row(corpus: Path, d: Path, duty: float, readers: Sequence[Tuple[int, int]] = READERS) -> dict:
    """A and B (slowed) alone, then as one fleet read by each of ``readers``' jobs."""
    with host(corpus, 0) as A:
        ra = job_epoch(A.endpoint, 1, 0, d / "alone")["samples_per_s"]
    with host(corpus, 1) as B, Slow(B, duty):
        rb = job_epoch(B.endpoint, 1, 0, d / "alone")["samples_per_s"]
    out = {"a_alone": ra, "b_alone_slowed": rb, "jobs": []}
    print(f"readers: A alone {ra:.1f} samples/s, B slowed {rb:.1f} samples/s", flush=True)
    for ranks, workers in readers:
        with host(corpus, 0, metrics()) as A, host(corpus, 1, metrics()) as B, Slow(B, duty):
            job = job_epoch(f"{A.endpoint},{B.endpoint}", ranks, workers, d / "job")
            made_now, ahead = epoch_made([A, B], 0), epoch_made([A, B], 1)
        job.update(ranks=ranks, workers=workers, share=job["samples_per_s"] / (ra + rb),
                   share_10_90=job["samples_per_s_10_90"] / (ra + rb),
                   made_over_read=made_now / job["samples_read"], made_ahead=ahead)
        out["jobs"].append(job)
        print(f"readers: {ranks} rank(s) x {workers} DataLoader worker(s): {job['share']:.2f} of the hosts' sum over the "
              f"whole epoch of {job['samples_read']} ({job['share_10_90']:.2f} over 10-90 %), "
              f"{job['made_over_read']:.3f} made a sample read, {ahead} of the next epoch made ahead", flush=True)
    return out


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--copies", type=int, default=150, help="links to each bundled clip in the corpus (an epoch of "
                                                           "3 samples a video: enough to measure a whole epoch)")
    p.add_argument("--warmup", type=int, default=40, help="batches of 4 read unmeasured first in a rate's epoch")
    p.add_argument("--duty", type=float, default=1 / 3, help="the slow host's workers run this share of the time")
    p.add_argument("--stop-s", type=float, default=30.0)
    p.add_argument("--ranks", type=int, default=4, help="ranks of the ranks row's job")
    p.add_argument("--rows", default=",".join(ROWS), help="which rows to run (comma-separated)")
    p.add_argument("--json", help="also write the results here")
    a = p.parse_args(argv)
    rows = set(a.rows.split(","))
    unknown = rows - set(ROWS)
    if unknown:
        print(f"bench.fleet: --rows {','.join(sorted(unknown))}: not rows of this bench ({', '.join(ROWS)})",
              file=sys.stderr)
        return 2
    for name in ("ranks", "copies"):
        if getattr(a, name) < 1:
            print(f"bench.fleet: --{name} must be >= 1, got {getattr(a, name)}", file=sys.stderr)
            return 2
    if a.json:
        out = Path(a.json)
        problem = json_output_problem(out) or ("is one of the bench's clips" if out.resolve().parent == CLIPS else "")
        if problem:
            print(f"bench.fleet: --json {out}: {problem}", file=sys.stderr)
            return 2
    if shutil.which("taskset") is None or (os.cpu_count() or 1) < 2:
        print("bench.fleet needs taskset and 2 cores", file=sys.stderr)
        return 2
    res: Dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="v2v-fleet-") as d:
        corpus = make_corpus(Path(d) / "corpus", a.copies)
        if rows & {"rates", "stop", "kill", "join"}:
            with host(corpus, 0, metrics()) as A:
                want = read_epoch(A.endpoint)  # one server's epoch: the ids and bytes every row must give
            if "rates" in rows:
                with host(corpus, 0, metrics()) as A:
                    ra = rate([A], A.endpoint, a.warmup)
        if "rates" in rows:
            res["rates"] = rates(corpus, a, ra)
        for fault in ("stop", "kill"):
            if fault in rows:
                res[fault] = fault_row(corpus, a, fault, want)
        if "join" in rows:
            res["join"] = join_row(corpus, want)
        if rows & {"cache", "moved"}:  # the cache row's entries: about 25 MB a video, twice over
            cached = make_corpus(Path(d) / "corpus60", CACHE_COPIES)
            if "cache" in rows:
                res["cache"] = cache_row(cached, Path(d))
            if "moved" in rows:
                res["moved"] = moved_row(cached)
        if "ranks" in rows:
            res["ranks"] = ranks_row(corpus, a.ranks)
        if "readers" in rows:
            res["readers"] = readers_row(corpus, Path(d), a.duty)
        if rows & {"batches", "restart"}:  # 580 samples an epoch: WHOLE_VIDEOS
            small = make_corpus(Path(d) / "corpus20", 20)
            if "batches" in rows:
                res["batches"] = batches_row(small)
            if "restart" in rows:
                res["restart"] = restart_row(small)
    if a.json:
        write_whole(a.json, json.dumps(res, indent=1) + "\n")
    return 0


def _kill_tree(server: ServeProcess, sig) -> None:
    """``sig`` to a server and its workers."""
    for pid in [server.proc.pid, *worker_pids(server.proc.pid)]:
        try:
            os.kill(pid, sig)
        except ProcessLookupError:
            pass

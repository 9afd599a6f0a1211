"""A fleet of real ``v2v-serve`` hosts on loopback, read as one plan (docs/scaling.md, "One plan,
any fleet"), against the same hosts split as static shards.

Run: ``python -m bench.fleet [--json docs/fleet.json]``. Each host is a ``v2v-serve`` of one
worker pinned to its own core (``taskset -c``); host B is made slow by a SIGSTOP/SIGCONT duty
cycle on its workers (stopped ``1 - duty`` of each 0.3 s period). Rates are read past the made-ahead
stock: the first ``warmup`` batches are read unmeasured. Rows:

* ``rates``: A alone, B (slowed) alone, A and B read as one plan, A and B as static shards
  (``--shard 0/2``, ``--shard 1/2``): the pair's samples/s over the sum of A's and B's.
* ``stop``: B SIGSTOPped for ``--stop-s`` seconds (server and workers) after the second batch:
  the longest gap between batches, each id once, and each sample's bytes equal to one server's read.
* ``kill``: B SIGKILLed after the second batch: the same.
* ``join``: a host started after the third batch, named in the reader's list from the start:
  seconds from its start to its first sample made, and the rate before and after.

Needs ``taskset`` (util-linux) and 2 cores.
"""
from __future__ import annotations

if __name__ == "__main__":  # Ctrl-C or SIGTERM from the start, the imports below included: one line
    import sys

    from v2v_wire.commands import run_command

    sys.exit(run_command("bench.fleet", "bench.fleet:main"))

import argparse
import hashlib
import json
import os
import shutil
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Dict, List, Optional

from harness.faults import worker_pids
from harness.serve import ServeProcess, free_port
from v2v_client import V2VStreamDataset
from v2v_client.plan_dataset import open_stream
from v2v_wire.commands import writable_problem, write_whole

OUTPUTS = ("voxels", "frames")
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


def rate(endpoint: str, batches: int, warmup: int) -> float:
    """Samples/s over ``batches`` batches after ``warmup`` unmeasured ones (epochs in turn)."""
    stream = iter(open_stream(endpoint, outputs=OUTPUTS, timeout_s=300))
    samples, t0 = 0, None
    for i in range(warmup + batches):
        b = next(stream)
        if i == warmup:
            t0 = time.perf_counter()
        elif i > warmup:
            samples += int((~b["padding"]).sum())
    return samples / (time.perf_counter() - t0)


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


def rates(corpus: Path, a, ra: float) -> dict:
    """B slowed alone, A and B as a fleet, A and B as static shards (A alone: ``ra``)."""
    with host(corpus, 1) as B, Slow(B, a.duty):
        rb = rate(B.endpoint, a.batches, a.warmup)
    with host(corpus, 0) as A, host(corpus, 1) as B, Slow(B, a.duty):
        pair = rate(f"{A.endpoint},{B.endpoint}", a.batches, a.warmup)
    with host(corpus, 0, ["--shard", "0/2"]) as A, host(corpus, 1, ["--shard", "1/2"]) as B, Slow(B, a.duty):
        static = rate(f"{A.endpoint},{B.endpoint}", a.batches, a.warmup)
    out = {"a_alone": ra, "b_alone_slowed": rb, "fleet": pair, "static_shards": static,
           "fleet_share": pair / (ra + rb), "static_share": static / (ra + rb)}
    print(f"rates (samples/s): A {ra:.2f}, B slowed {rb:.2f}, fleet {pair:.2f} ({pair / (ra + rb):.2f} of the "
          f"sum), static shards {static:.2f} ({static / (ra + rb):.2f})", flush=True)
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


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--copies", type=int, default=60, help="links to each bundled clip in the corpus")
    p.add_argument("--batches", type=int, default=40, help="measured batches per rate (batch size 4)")
    p.add_argument("--warmup", type=int, default=40, help="batches read unmeasured first")
    p.add_argument("--duty", type=float, default=1 / 3, help="the slow host's workers run this share of the time")
    p.add_argument("--stop-s", type=float, default=30.0)
    p.add_argument("--rows", default="rates,stop,kill,join", help="which rows to run (comma-separated)")
    p.add_argument("--json", help="also write the results here")
    a = p.parse_args(argv)
    rows = set(a.rows.split(","))
    unknown = rows - {"rates", "stop", "kill", "join"}
    if unknown:
        print(f"bench.fleet: --rows {','.join(sorted(unknown))}: not rows of this bench (rates, stop, kill, join)",
              file=sys.stderr)
        return 2
    if a.json:
        out = Path(a.json)
        problem = writable_problem(out) or ("is one of the bench's clips" if out.resolve().parent == CLIPS else "")
        if problem:
            print(f"bench.fleet: --json {out}: {problem}", file=sys.stderr)
            return 2
    if shutil.which("taskset") is None or (os.cpu_count() or 1) < 2:
        print("bench.fleet needs taskset and 2 cores", file=sys.stderr)
        return 2
    res: Dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="v2v-fleet-") as d:
        corpus = make_corpus(Path(d) / "corpus", a.copies)
        with host(corpus, 0) as A:
            want = read_epoch(A.endpoint)  # one server's epoch: the ids and bytes every row must give
            ra = rate(A.endpoint, a.batches, a.warmup) if "rates" in rows else 0.0
        if "rates" in rows:
            res["rates"] = rates(corpus, a, ra)
        for fault in ("stop", "kill"):
            if fault in rows:
                res[fault] = fault_row(corpus, a, fault, want)
        if "join" in rows:
            res["join"] = join_row(corpus, want)
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

"""Fault scenarios of a fleet (``bench.faults``): peers that break the protocol listed beside a
real host, and Ctrl-C or SIGTERM while every host is silent. The hostile peers are ZeroMQ ROUTER
sockets of this process (:class:`Peer`); the hosts are real ``v2v-serve`` processes on 127.0.0.1
and the readers real processes (``v2v-loadtest``, or a ``V2VStreamDataset`` in a child Python)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

import msgpack
import zmq

from bench.fleet import scrape
from harness.faults import ROOT, Layout, _serve, expected_ids, good_corpus, per_epoch, row
from harness.serve import ServeProcess, free_port
from v2v_client.fetch import Link
from v2v_wire.plan_messages import PlanInfo, Rows
from v2v_wire.protocol import pack

#: A reply frame of 500 MB: a peer claiming a batch far past what the recipe makes.
HUGE_BYTES = 500 << 20
#: Seconds from SIGINT or SIGTERM to a fleet reader's exit, whatever its hosts do (issue 98).
EXIT_S = 2.0


class Peer:
    """A peer listed in a fleet: a ZeroMQ ROUTER socket on 127.0.0.1 answering each message with
    ``answer(header, frames)``'s frames (None: no answer), in a thread; ``kinds`` counts the
    message types it was sent. :meth:`close` stops it."""

    def __init__(self, answer: Callable[[dict, list], Optional[list]]):
        self.endpoint = f"tcp://127.0.0.1:{free_port()}"
        self.answer, self.kinds = answer, {}
        self.ctx = zmq.Context()
        self.sock = self.ctx.socket(zmq.ROUTER)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.bind(self.endpoint)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        while not self.stop.is_set():
            if not self.sock.poll(100):
                continue
            ident, *frames = self.sock.recv_multipart()
            h = msgpack.unpackb(frames[0])
            self.kinds[h["type"]] = self.kinds.get(h["type"], 0) + 1
            out = self.answer(h, frames[1:])
            if out:
                self.sock.send_multipart([ident, *out], copy=False)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)
        self.sock.close()
        self.ctx.term()


def hostile_peers(real: PlanInfo) -> Dict[str, Peer]:
    """name -> a :class:`Peer` that breaks the fleet's protocol its own way, ``real`` being what a
    real host of the fleet serves: ``garbage`` (not msgpack), ``version`` (protocol 11), ``huge``
    (a :data:`HUGE_BYTES` frame), ``made-up plan`` (a plan of another recipe fingerprint), and
    ``impersonator`` (``real``'s plan, then rows whose arrays do not match their header)."""
    huge = bytearray(HUGE_BYTES)
    made_up = PlanInfo(replace(real.plan, recipe="0123456789abcdef"), real.samples, real.stream)

    def impersonate(h, frames):
        if h["type"] == "plan_ask":
            return [pack(real.to_wire())]
        if h["type"] != "make":
            return [b"\xc1 not msgpack"]
        n = len(h.get("ordinals") or ())
        rows = Rows(h["request"], h["epoch"], 0, [None] * n, [False] * n, [{}] * n,
                    [{"name": "voxels", "dtype": "int8", "shape": [n + 1, 8]}])
        return [pack(rows.to_wire()), bytes(8 * (n + 1))]

    return {"garbage": Peer(lambda h, f: [b"\xc1 not msgpack"]),
            "version": Peer(lambda h, f: [msgpack.packb({"v": 11, "type": "plan"})]),
            "huge": Peer(lambda h, f: [huge]),
            "made-up plan": Peer(lambda h, f: [pack(made_up.to_wire())]),
            "impersonator": Peer(impersonate)}


def close_all(peers) -> None:
    for p in peers:
        p.close()


#: A reader of ``epochs`` (argv[2]) epochs of the fleet at argv[1], one ``V2VStreamDataset`` asked
#: what it serves in this process (a peer is named then, once), read by a DataLoader of argv[3]
#: workers (0: in this process) with a training step of argv[4] seconds a batch, printing one JSON
#: line: the ids read (``epoch:id``) and its peak RSS (``VmHWM``: its own memory since its exec;
#: the ``ru_maxrss`` a parent gets counts the parent's pages before the exec too).
READER = """import json, logging, re, sys, time
from pathlib import Path
logging.basicConfig(level=logging.WARNING, format="%(message)s")
import torch
from v2v_client import V2VStreamDataset
ds = V2VStreamDataset(sys.argv[1], outputs=("voxels",), timeout_s=60, retry_s=2.0)
ds.plan_info()
ids = []
for epoch in range(int(sys.argv[2])):
    ds.set_epoch(epoch)
    workers = int(sys.argv[3])
    for b in ds if not workers else torch.utils.data.DataLoader(ds, batch_size=None, num_workers=workers):
        ids += [f"{epoch}:{s}" for s, p in zip(b["sample_ids"], b["padding"].tolist()) if not p]
        time.sleep(float(sys.argv[4]))
peak = re.search(r"VmHWM:\\s+(\\d+)", Path("/proc/self/status").read_text())[1]
print(json.dumps({"ids": ids, "rss_mb": int(peak) / 1024}))
"""


def read_fleet(connect: str, epochs: int, workers: int = 0,
               step_s: float = 0.0) -> Tuple[int, List[str], Optional[dict]]:
    """:data:`READER` run on ``connect``: ``(exit status, its stderr lines, its JSON line or None)``."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run([sys.executable, "-c", READER, connect, str(epochs), str(workers), str(step_s)],
                       capture_output=True, text=True, timeout=300, env=env)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    return r.returncode, lines, json.loads(r.stdout.splitlines()[-1]) if r.returncode == 0 else None


def scenario_fleet_hostile_peers(tmp: Path, layout: Layout) -> dict:
    """A real host listed first with five hostile peers (:func:`hostile_peers`), two epochs read by
    one reader: every sample from the real host, each peer named once, the 500 MB frame never
    taken in."""
    corpus = good_corpus(tmp, 1)
    want = per_epoch(expected_ids(corpus, layout), (0, 1))
    with _serve(corpus, layout, workers=1) as real:
        with Link(real.endpoint, 60) as link:
            info = link.ask()
        peers = hostile_peers(info)
        try:
            status, lines, out = read_fleet(",".join([real.endpoint] + [p.endpoint for p in peers.values()]), 2)
        finally:
            close_all(peers.values())
        rc = real.stop()
    named = {n: sum(p.endpoint in ln for ln in lines) for n, p in peers.items()}
    rss = out["rss_mb"] if out else None
    return row("5 hostile peers beside a real host (garbage, protocol 11, a 500 MB frame, a made-up plan, bad "
               "rows), 2 epochs", want, out["ids"] if out else [], None,
               f"reader exit {status}; each peer named {sorted(set(named.values()))} time(s); impersonator asked "
               f"{peers['impersonator'].kinds.get('make', 0)} make(s); reader peak RSS "
               f"{'-' if rss is None else round(rss)} MB; server exit {rc}",
               named=named, rss_mb=rss, status=status, errors=lines[-3:])


def silent_fleet_interrupt(host_args: List[str], sig: int) -> Tuple[int, List[str], float]:
    """``v2v-loadtest`` reading a fleet of two hosts (``host_args``), both SIGSTOPped once it has
    read a sample, then sent ``sig``: ``(its exit status, its stderr lines, seconds from the
    signal to its exit)``. The hosts are woken (SIGCONT) and stopped after."""
    hosts = [ServeProcess([*host_args, "--metrics-port", str(free_port())], ready_timeout_s=120) for _ in range(2)]
    code = "import sys\nfrom v2v_wire.commands import loadtest\nsys.exit(loadtest())"
    proc, took = None, float("nan")
    try:
        for h in hosts:
            h.start()
        proc = subprocess.Popen([sys.executable, "-c", code, "--connect", ",".join(h.endpoint for h in hosts),
                                 "--batches", "100000", "--timeout", "60", "--outputs", "voxels,frames"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
        deadline = time.monotonic() + 120
        while not sum(scrape(h).get("v2v_samples_sent_total", 0) for h in hosts):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the loadtest never read a sample: {proc.stderr.read()[-2000:]}")
            time.sleep(0.1)
        for h in hosts:
            os.kill(h.proc.pid, signal.SIGSTOP)
        time.sleep(1.5)  # every host silent: the reading thread waits on them
        t0 = time.monotonic()
        proc.send_signal(sig)
        proc.wait(60)
        took = time.monotonic() - t0
        err = proc.stderr.read()
    finally:
        for h in hosts:
            if h.proc is not None and h.proc.poll() is None:
                os.kill(h.proc.pid, signal.SIGCONT)
            h.stop()
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, [ln for ln in err.splitlines() if ln.strip()], took


def scenario_fleet_silent_interrupt(tmp: Path, layout: Layout) -> dict:
    """``v2v-loadtest`` reading two hosts, both SIGSTOPped, then SIGINT; again with SIGTERM."""
    corpus = good_corpus(tmp, 1)
    args = ["--videos", str(corpus), "--workers", "1", *layout.args()]
    runs = {s.name: silent_fleet_interrupt(args, s) for s in (signal.SIGINT, signal.SIGTERM)}
    said = {n: sum(("interrupted" in ln or "stopped" in ln) and ln.startswith("v2v-loadtest: ") for ln in lines) == 1
            for n, (_, lines, _) in runs.items()}
    notes = "; ".join(f"{n}: exit {rc} {took:.2f} s after it, one line {said[n]}" for n, (rc, _, took) in runs.items())
    return row("v2v-loadtest interrupted while both hosts of its fleet are SIGSTOPped", [], [], None, notes,
               seconds={n: took for n, (_, _, took) in runs.items()}, status={n: rc for n, (rc, _, _) in runs.items()},
               one_line=said)


SCENARIOS = {
    "fleet_hostile_peers": scenario_fleet_hostile_peers,
    "fleet_silent_interrupt": scenario_fleet_silent_interrupt,
}

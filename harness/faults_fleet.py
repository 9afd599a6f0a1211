"""Fault scenarios of a fleet (``v2v-serve`` hosts of one corpus read as one plan,
``v2v_client.fleet_read``): a host gone for good, one host under two names, a file replaced under
the fleet as a deploy does (each host restarted in turn), peers that break the protocol listed
beside a real host, and Ctrl-C or SIGTERM while every host is silent. Real servers on 127.0.0.1
read by ``V2VStreamDataset`` (in this process, or in a child Python) or ``v2v-loadtest``; the
hostile peers are ZeroMQ ROUTER sockets of this process (:class:`Peer`). Same row format as
``harness/faults.py``; ``python -m bench.faults`` runs them, ``tests/test_faults_fleet.py`` and
``tests/test_fleet_faults.py`` run them short.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import uuid
from dataclasses import replace
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

import msgpack
import zmq

from bench.fleet import scrape
from harness.faults import (GOOD_VIDEOS, ROOT, Layout, _clean, _ids, _next_after, _serve, _stop, dataset,
                            expected_ids, good_corpus, per_epoch, read_all, real_ids, row)
from harness.serve import ServeProcess, free_port
from v2v_client.fetch import Link
from v2v_wire.plan import PlanMismatch
from v2v_wire.plan_messages import PlanInfo, Rows
from v2v_wire.protocol import pack


class _Lines(logging.Handler):
    """The lines logged to ``logger`` at WARNING and above while in a ``with`` block."""

    def __init__(self, logger: str, on_line: Optional[Callable[[str], None]] = None):
        super().__init__(logging.WARNING)
        self.logger, self.lines, self.on_line = logging.getLogger(logger), [], on_line

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())
        if self.on_line is not None:
            self.on_line(self.lines[-1])

    def __enter__(self) -> "_Lines":
        self.logger.addHandler(self)
        return self

    def __exit__(self, *exc) -> None:
        self.logger.removeHandler(self)


def scenario_first_host_killed(tmp: Path, layout: Layout, timeout_s: float = 20.0) -> dict:
    """Two hosts read as one fleet, the first listed SIGKILLed after epoch 0's first batch and
    left dead: epoch 0 ends on the other host, and epoch 1 (a new pass, which asks the fleet for
    its manifest again) is read whole from it, its first batch after about ``ASK_NEXT_S``, not
    after ``timeout_s`` (the reader's, its default 20 s) and an error."""
    corpus = good_corpus(tmp, 2)
    expected = per_epoch(expected_ids(corpus, layout), (0, 1))
    log: list = []
    error: Optional[str] = None
    with _serve(corpus, layout, workers=1) as a, _serve(corpus, layout, workers=1) as b:
        ds = dataset(f"{a.endpoint},{b.endpoint}", timeout_s=timeout_s)
        t_kill = None
        for batch in ds:
            log.append((time.monotonic(), real_ids(batch, tag=True)))
            if t_kill is None:
                os.kill(a.proc.pid, signal.SIGKILL)
                t_kill = time.monotonic()
        ds.set_epoch(1)
        t1 = time.monotonic()
        try:
            read_all(ds, log, tag=True)
        except TimeoutError as e:
            error = f"TimeoutError: {e}"
        waited = _next_after(log, t1)
        ended = time.monotonic() - t1
        rc = _stop(b)
        clean = _clean(b)
    epoch1 = sum(1 for s in _ids(log) if s.startswith("1:"))
    first = "none" if waited is None else f"{waited:.1f} s"
    return row("first-listed fleet host SIGKILLed mid-epoch 0 and left dead, epochs 0 and 1", expected, _ids(log),
               _next_after(log, t_kill), f"epoch 1: {epoch1} samples, its first batch after {first} "
               f"(timeout_s {timeout_s:g}); error: {error or 'none'}; other host exit {rc}",
               epoch1_first_s=waited, epoch1_s=ended, epoch1_samples=epoch1, error=error, server_exit=rc, clean=clean)


def scenario_one_host_two_names(tmp: Path, layout: Layout) -> dict:
    """One host listed twice, as ``tcp://localhost:P`` and ``tcp://127.0.0.1:P``: it says one
    instance under both, so the reader reads it once, under the first name, and says so in one
    line; the host makes each sample read once."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log: list = []
    served: List[str] = []
    with _serve(corpus, layout) as srv:
        names = [f"tcp://localhost:{srv.endpoint.rsplit(':', 1)[1]}", srv.endpoint]
        with _Lines("v2v.client") as lines:
            for batch in dataset(",".join(names)):
                log.append((time.monotonic(), real_ids(batch)))
                served += [ep for ep in batch["servers"] if ep not in served]
        with Link(srv.endpoint, 30) as link:
            made = link.ask().stream["feed"]["samples_made"]
        rc = _stop(srv)
        clean = _clean(srv)
    said = [s for s in lines.lines if names[0] in s and names[1] in s]
    read = len(_ids(log))
    return row("one fleet host under two names (localhost and 127.0.0.1)", expected, _ids(log), None,
               f"read as {len(served)} host(s) ({', '.join(served)}); {made} samples made for {read} read; "
               f"said in {len(said)} line(s); server exit {rc}", hosts=served, made=made, read=read, said=said,
               server_exit=rc, clean=clean)


#: The file a deploy replaces (by another clip under its name, another size and modification time).
REPLACED = "bikes.mp4"


def _deployed(folder: Path, clips: List[str]) -> None:
    """``folder`` holding ``clips`` and a copy of each (``NAME_1.mp4``), every file's modification
    time the same on every host (a deploy's copy keeps it: ``rsync -a``), so hosts list one plan."""
    folder.mkdir(parents=True)
    for c in clips:
        for name in (c, c.replace(".mp4", "_1.mp4")):
            shutil.copy(GOOD_VIDEOS / c, folder / name)
            os.utime(folder / name, (1_500_000_000, 1_500_000_000))


def _replace(folder: Path) -> None:
    """:data:`REPLACED` in ``folder`` replaced by another clip (another size and tag)."""
    shutil.copy(GOOD_VIDEOS / "bigbuckbunny.mp4", folder / REPLACED)
    os.utime(folder / REPLACED, (1_600_000_000, 1_600_000_000))


def _restart(srv, folder: Path) -> None:
    """Host ``srv`` stopped, its copy of :data:`REPLACED` replaced, and started again on its address."""
    srv.stop()
    _replace(folder)
    srv.start()


def _digests(ds, epoch: int) -> Dict[str, str]:
    """Sample id -> SHA-1 of its voxels, of ``epoch`` read whole from ``ds``."""
    ds.set_epoch(epoch)
    return {sid: hashlib.sha1(b["voxels"][j].numpy().tobytes()).hexdigest()
            for b in ds for j, sid in enumerate(b["sample_ids"]) if not b["padding"][j]}


def scenario_file_replaced_under_fleet(tmp: Path, layout: Layout) -> dict:
    """Two hosts, each its own copy of one corpus, read as one fleet while a deploy replaces
    :data:`REPLACED` by another clip under its name and restarts each host in turn: host a after
    epoch 0's first batch, host b as epoch 1's pass leaves a out. Each sample read is compared
    with what one server makes of its id under the old and the new file (a sample's bytes are a
    function of seed, epoch, id and file): no pass may hold both versions. Epoch 0 ends on b
    (old); epoch 1's pass fails in one line naming the file and saying to start the epoch over;
    started over, it reads the new plan whole."""
    clips = [REPLACED, "bbb_camera_596x336.mp4", "webvid_like_596x336.mp4"]
    ha, hb = tmp / "a", tmp / "b"
    _deployed(ha, clips)
    _deployed(hb, clips)
    expected = per_epoch(expected_ids(ha, layout), (0, 1))
    log: list = []
    versions: Dict[str, set] = {}  # pass -> versions of REPLACED its samples come from
    with _serve(ha, layout, workers=1) as a, _serve(hb, layout, workers=1) as b:
        ref = {("old", e): _digests(dataset(b.endpoint), e) for e in (0, 1)}
        ds = dataset(f"{a.endpoint},{b.endpoint}", timeout_s=30)

        def read(name: str, after_first: Optional[Callable[[], None]] = None) -> None:
            for n, batch in enumerate(ds):
                log.append((time.monotonic(), real_ids(batch, tag=True)))
                for j, sid in enumerate(batch["sample_ids"]):
                    if sid.startswith(REPLACED + "#") and not batch["padding"][j]:
                        d = hashlib.sha1(batch["voxels"][j].numpy().tobytes()).hexdigest()
                        got = [v for v in ("old", "new") if ref.get((v, batch["epoch"]), {}).get(sid) == d]
                        versions.setdefault(name, set()).update(got or ["neither"])
                if n == 0 and after_first is not None:
                    after_first()

        def b_restarts(line: str) -> None:  # b's turn of the deploy, as epoch 1's pass leaves a out
            if armed and line.startswith(a.endpoint) and "left out of the fleet for this pass" in line and not said:
                said.append(line)
                _restart(b, hb)

        said: List[str] = []
        armed: List[bool] = []
        error: Optional[str] = None
        with _Lines("v2v.client", b_restarts) as lines:
            read("epoch 0", lambda: _restart(a, ha))  # a's turn of the deploy, after epoch 0's first batch
            t_b = time.monotonic()
            ds.set_epoch(1)
            armed.append(True)
            try:
                read("epoch 1, first pass")
            except PlanMismatch as e:
                error = str(e)
            first_pass = [s for _, ids in log for s in ids if s.startswith("1:")]
            log = [(t, ids) for t, ids in log if not any(s.startswith("1:") for s in ids)]
            ref[("new", 1)] = _digests(dataset(b.endpoint), 1)
            t_over = time.monotonic()
            ds.set_epoch(1)
            read("epoch 1, started over")
        rc = (_stop(a), _stop(b))
        clean = _clean(a) and _clean(b)
    switched = [ln for ln in lines.lines if "no host serves the plan read last" in ln]
    mixed = sorted(name for name, v in versions.items() if len(v) != 1)
    return row("a file replaced under a two-host fleet, each host restarted in turn (a deploy), epochs 0 and 1",
               expected, _ids(log), _next_after(log, t_over),
               f"{REPLACED}'s samples by pass: " + "; ".join(f"{k}: {'/'.join(sorted(v))}" for k, v in versions.items())
               + f"; passes mixing two versions: {len(mixed)}; epoch 1's first pass read {len(first_pass)} sample(s) "
               f"and failed: {error or 'no error'}; started over, it read the new plan whole; server exits {rc}",
               versions={k: sorted(v) for k, v in versions.items()}, mixed=mixed, error=error, said=said,
               switched=switched, first_pass=first_pass, t_b=t_b, server_exit=rc, clean=clean)


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


def another_host(real: PlanInfo) -> PlanInfo:
    """What a real host says (``real``), as a second host of its fleet says it: under an instance
    of its own (one copying ``real``'s is read as the same host, ``fleet_read.alias_of``)."""
    return replace(real, instance=uuid.uuid4().hex)


def hostile_peers(real: PlanInfo) -> Dict[str, Peer]:
    """name -> a :class:`Peer` that breaks the fleet's protocol its own way, ``real`` being what a
    real host of the fleet serves: ``garbage`` (not msgpack), ``version`` (protocol 11), ``huge``
    (a :data:`HUGE_BYTES` frame), ``made-up plan`` (a plan of another recipe fingerprint), and
    ``impersonator`` (``real``'s plan as another host, :func:`another_host`, then rows whose
    arrays do not match their header)."""
    huge = bytearray(HUGE_BYTES)
    made_up = PlanInfo(replace(real.plan, recipe="0123456789abcdef"), real.samples, real.stream)
    twin = another_host(real)

    def impersonate(h, frames):
        if h["type"] == "plan_ask":
            return [pack(twin.to_wire())]
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
    "fleet_first_host_killed": scenario_first_host_killed,
    "fleet_one_host_two_names": scenario_one_host_two_names,
    "fleet_file_replaced": scenario_file_replaced_under_fleet,
    "fleet_hostile_peers": scenario_fleet_hostile_peers,
    "fleet_silent_interrupt": scenario_fleet_silent_interrupt,
}

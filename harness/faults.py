"""Fault scenarios against a real v2v-serve on 127.0.0.1: is any sample lost or doubled?

Each ``scenario_*`` runs a server (and clients, killers, fuzzers) and returns a row: the
scenario, samples expected / delivered / lost / duplicated, seconds to recover, ``facts`` (the
measured values a test asserts on) and ``notes`` (the same facts in words, for the table that
``python -m bench.faults`` prints). ``tests/test_faults.py`` and ``tests/test_exactly_once.py``
run short versions of them.
"""
from __future__ import annotations

import collections
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable, List, Optional, Tuple

import zmq

from v2v_client import V2VPushDataset
from v2v_server.ops.config import ServeConfig
from v2v_server.frames.check import check_corpus
from v2v_server.sources.local import LocalSource
from harness.data import SAMPLE_VIDEOS
from harness.serve import ServeProcess, free_port
from v2v_wire.protocol import PROTOCOL_VERSION, pack
from v2v_server.sources.folder_scan import scan_corpus

ROOT = Path(__file__).resolve().parents[1]
GOOD_VIDEOS = SAMPLE_VIDEOS


class Layout:
    """Small samples so scenarios run in seconds: L voxels x 5 bins, crop, windows per video."""

    def __init__(self, L: int = 4, crop: int = 64, windows: int = 2, batch: int = 2, shot_cuts: str = "avoid"):
        self.L, self.crop, self.windows, self.batch, self.shot_cuts = L, crop, windows, batch, shot_cuts

    def args(self) -> List[str]:
        return ["--sequence-length", str(self.L), "--crop-size", str(self.crop), "--max-samples-per-video",
                str(self.windows), "--batch-size", str(self.batch), "--seed", "11", "--flow-preset", "ultrafast",
                "--shot-cuts", self.shot_cuts]

    def cfg(self) -> ServeConfig:
        return ServeConfig(sequence_length=self.L, crop_size=self.crop, max_samples_per_video=self.windows,
                           workers=2, shot_cuts=self.shot_cuts)


def expected_ids(corpus: Path, layout: Layout, exclude=()) -> List[str]:
    """Every sample id one epoch of ``corpus`` holds, from ``--check``'s verdicts."""
    vids = [p.as_posix() for p in scan_corpus(corpus, layout.cfg().video_extensions)[0]]
    vids = [v for v in vids if v not in exclude]
    out, recipe = [], layout.cfg().recipe
    for r in check_corpus(recipe.windows, recipe.decode, LocalSource(corpus), vids):
        failed = set(r.failed_windows)  # windows --check says cannot be made (e.g. frame size changes)
        out += [f"{r.path}#{k}" for k in range(r.windows + len(failed)) if k not in failed]
    return sorted(out)


def good_corpus(tmp: Path, copies: int = 1) -> Path:
    d = tmp / "good"
    d.mkdir(parents=True, exist_ok=True)
    for p in sorted(GOOD_VIDEOS.glob("*.mp4")):
        for c in range(copies):
            shutil.copy(p, d / (p.name if c == 0 else f"{p.stem}_{c}{p.suffix}"))
    return d


def row(name: str, expected: List[str], delivered: List[str], recover_s: Optional[float], notes: str = "",
        **facts) -> dict:
    """One scenario's result: counts of ``expected`` ids against ``delivered`` ones (with
    repeats), ``facts`` (measured values, for tests) and ``notes`` (the same in words)."""
    cnt = collections.Counter(delivered)
    exp = set(expected)
    return {"scenario": name, "expected": len(exp), "delivered": len(cnt), "lost": len(exp - set(cnt)),
            "duplicated": sum(v - 1 for v in cnt.values()), "unexpected": len(set(cnt) - exp),
            "recover_s": None if recover_s is None else round(recover_s, 2), "facts": facts, "notes": notes}


def worker_pids(server_pid: int) -> List[int]:
    """The server's worker processes (spawned multiprocessing children, not the resource tracker)."""
    out = []
    try:
        kids = Path(f"/proc/{server_pid}/task/{server_pid}/children").read_text().split()
    except OSError:
        return out
    for k in kids:
        try:
            cmd = Path(f"/proc/{k}/cmdline").read_bytes().replace(b"\0", b" ")
        except OSError:
            continue
        if b"spawn_main" in cmd and b"resource_tracker" not in cmd:
            out.append(int(k))
    return out


def read_all(ds: V2VPushDataset, log: list, stop_after: Optional[int] = None) -> None:
    """Iterate ``ds`` to its end, appending (time, sample ids) per batch to ``log``."""
    it = iter(ds)
    try:
        for b in it:
            log.append((time.monotonic(), list(b["sample_ids"])))
            if stop_after is not None and len(log) >= stop_after:
                return
    finally:
        it.close()


def _ids(log) -> List[str]:
    return [s for _, ids in log for s in ids]


def _next_after(log, t: float) -> Optional[float]:
    later = [tt for tt, _ in log if tt > t]
    return (min(later) - t) if later else None


# ---------------------------------------------------------------------------------- scenarios
def scenario_worker_kill(tmp: Path, layout: Layout, kills: int = 3, copies: int = 2) -> dict:
    corpus = good_corpus(tmp, copies)
    expected = expected_ids(corpus, layout)
    log: list = []
    kill_times: List[float] = []
    with _serve(corpus, layout, "--epochs", "1") as srv:
        ds = V2VPushDataset(srv.endpoint, timeout_s=60, credits=1)

        def killer():
            while not log:
                time.sleep(0.05)
            rng = random.Random(0)
            for _ in range(kills):
                pids = worker_pids(srv.proc.pid)
                if not pids or srv.proc.poll() is not None:
                    return
                os.kill(rng.choice(pids), signal.SIGKILL)
                kill_times.append(time.monotonic())
                time.sleep(0.5)

        th = threading.Thread(target=killer, daemon=True)
        th.start()
        read_all(ds, log)
        th.join(10)
        srv.wait(30)
        restarts = srv.log.count("restarting")
    rec = [r for r in (_next_after(log, t) for t in kill_times) if r is not None]
    return row(f"worker SIGKILL x{len(kill_times)} mid-epoch", expected, _ids(log), max(rec) if rec else None,
               f"{restarts} worker restart(s) logged", restarts=restarts)


CLIENT_SCRIPT = r"""
import json, os, sys
from v2v_client import V2VPushDataset
endpoint, ckpt = sys.argv[1], sys.argv[2]
ds = V2VPushDataset(endpoint, timeout_s=60, credits=2)
ids = []
if os.path.exists(ckpt):
    saved = json.load(open(ckpt))
    ds.load_state_dict(saved["stream"])
    ids = saved["ids"]
for b in ds:
    ids += b["sample_ids"]                      # the "training step"
    tmp = ckpt + ".tmp"
    json.dump({"stream": ds.state_dict(), "ids": ids}, open(tmp, "w"))
    os.replace(tmp, ckpt)                       # checkpoint after every step
    print("step", len(ids), flush=True)
"""


def _trainer_process(script: str, *args: str) -> subprocess.Popen:
    """``script`` run by a child Python that imports this checkout, with ``args``; its stdout a text pipe."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.Popen([sys.executable, "-c", script, *args], stdout=subprocess.PIPE, text=True, env=env)


def scenario_client_kill(tmp: Path, layout: Layout, kill_after_steps: int = 2) -> dict:
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    ckpt = tmp / "trainer_ckpt.json"
    with ServeProcess(["--videos", str(corpus), "--workers", "2", "--epochs", "1", "--client-timeout", "2",
                       *layout.args()]) as srv:
        p = _trainer_process(CLIENT_SCRIPT, srv.endpoint, str(ckpt))
        steps = 0
        for line in p.stdout:
            steps += line.startswith("step")
            if steps >= kill_after_steps:
                break
        p.send_signal(signal.SIGKILL)
        p.wait(10)
        t_kill = time.monotonic()
        p2 = _trainer_process(CLIENT_SCRIPT, srv.endpoint, str(ckpt))
        first = None
        for line in p2.stdout:
            if first is None and line.startswith("step"):
                first = time.monotonic() - t_kill
        rc = p2.wait(120)
        srv.wait(30)
    ids = json.loads(ckpt.read_text())["ids"]
    return row("client SIGKILL, restart from state_dict", expected, ids, first, f"restarted client exit {rc}", client_exit=rc)


def scenario_server_restart(tmp: Path, layout: Layout, kill_after_batches: int = 2) -> dict:
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    args = ["--videos", str(corpus), "--workers", "2", "--epochs", "1", *layout.args()]
    log: list = []
    batch_ids: tuple = ([], [])  # of the killed server, of the restarted one
    srv = ServeProcess(args).start()
    srv2 = None
    try:
        ds = V2VPushDataset(srv.endpoint, timeout_s=2.0, reconnect=True, reconnect_timeout_s=60, credits=1)
        it = iter(ds)
        for b in it:
            log.append((time.monotonic(), list(b["sample_ids"])))
            batch_ids[0].append(b["batch_id"])
            if len(log) >= kill_after_batches:
                break
        srv.proc.send_signal(signal.SIGKILL)
        srv.proc.wait(10)
        t_kill = time.monotonic()
        srv2 = ServeProcess(args[:] + ["--bind", srv.endpoint]).start()
        for b in it:
            log.append((time.monotonic(), list(b["sample_ids"])))
            batch_ids[1].append(b["batch_id"])
        it.close()
        srv2.wait(30)
    finally:
        srv.stop()
        if srv2 is not None:
            srv2.stop()
    return row("server SIGKILL + restart, client resumes", expected, _ids(log), _next_after(log, t_kill),
               "client reconnect=True with its delivered-sample state", batch_ids=batch_ids)


def scenario_stalled_client(tmp: Path, layout: Layout, lease_s: float = 2.0, stall_s: float = 6.0) -> dict:
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log_a: list = []
    log_b: list = []
    held: List[str] = []
    with ServeProcess(["--videos", str(corpus), "--workers", "2", "--epochs", "1", "--lease", str(lease_s),
                       *layout.args()]) as srv:
        a = V2VPushDataset(srv.endpoint, timeout_s=60, credits=3)
        b = V2VPushDataset(srv.endpoint, timeout_s=60, credits=1)
        ita = iter(a)
        first = next(ita)
        log_a.append((time.monotonic(), first["sample_ids"]))
        t_stall = time.monotonic()
        tb = threading.Thread(target=read_all, args=(b, log_b), daemon=True)
        tb.start()
        time.sleep(0.5)
        conn = a._stream._conns[0]
        held = [s for item in list(conn.items.queue) if isinstance(item, dict) for s in item["sample_ids"]]
        time.sleep(stall_s)  # the training loop of A hangs; its I/O thread still heartbeats
        for bt in ita:
            log_a.append((time.monotonic(), bt["sample_ids"]))
        tb.join(120)
        srv.wait(30)
    got_b = [(t, ids) for t, ids in log_b if set(ids) & set(held)]
    rec = (min(t for t, _ in got_b) - t_stall - lease_s) if got_b else None
    return row(f"client stalled {stall_s:.0f} s > lease {lease_s:.0f} s", expected, _ids(log_a) + _ids(log_b), rec,
               f"{len(held)} held sample(s) re-sent to another client", held=len(held))


def scenario_bad_corpus(tmp: Path, layout: Layout) -> dict:
    from harness.corpus import make_fault_corpus

    corpus = tmp / "faulty"
    exp = make_fault_corpus(corpus, GOOD_VIDEOS, layout.L * 5 + 1)
    expected = expected_ids(corpus, layout, exclude={"deleted_during_epoch.mp4"})
    log: list = []
    with _serve(corpus, layout, "--epochs", "1") as srv:
        (corpus / "deleted_during_epoch.mp4").unlink()
        read_all(V2VPushDataset(srv.endpoint, timeout_s=60), log)
        rc = srv.wait(60)
        text = srv.log
    skipped = [k for k, v in exp.items() if v == "skipped"]
    lines = text.splitlines()
    logged = [k for k in skipped if sum(f"{corpus / k}:" in ln and "skipped" in ln for ln in lines) == 1]
    ignored = [k for k, v in exp.items() if v == "ignored" and f"ignored {corpus / k}:" in text]
    return row("corpus with every kind of bad file", expected, _ids(log), None,
               f"{len(logged)}/{len(skipped)} bad files logged once, "
               f"{len(ignored)}/{sum(v == 'ignored' for v in exp.values())} non-videos logged, server exit {rc}",
               bad_logged_once=len(logged), bad_files=len(skipped), non_videos_logged=len(ignored),
               non_videos=sum(v == 'ignored' for v in exp.values()), server_exit=rc)


def fuzz_messages(rng: random.Random, n: int) -> List[List[bytes]]:
    """Random and mutated client messages: garbage, truncated, oversized, wrong version,
    unknown types, bad fields, extra frames."""
    valid = [pack({"type": "hello", "outputs": ["voxels"], "credits": 1}), pack({"type": "ack", "batch_ids": [0]}),
             pack({"type": "heartbeat"}), pack({"type": "credit", "credit": 3})]
    out = []
    for _ in range(n):
        k = rng.randrange(9)
        base = bytearray(rng.choice(valid))
        if k == 0:
            msg = [rng.randbytes(rng.randrange(0, 200))]
        elif k == 1:
            msg = [bytes(base[: rng.randrange(len(base))])]
        elif k == 2:
            for _ in range(rng.randrange(1, 6)):
                base[rng.randrange(len(base))] = rng.randrange(256)
            msg = [bytes(base)]
        elif k == 3:
            msg = [pack({"type": "hello", "v": rng.choice([0, 2, 99, "1", None]), "outputs": ["voxels"]})]
        elif k == 4:
            msg = [pack({"type": rng.choice(["hack", "", "batch", "welcome", "task", "x" * 1000])})]
        elif k == 5:
            msg = [pack({"type": "hello", "outputs": rng.choice([None, [], ["events"], "voxels", [1, 2]]),
                         "credits": rng.choice([-1, 10 ** 12, "many", None]), "resume": rng.choice(
                             [None, 5, {"completed_epoch": "x"}, {"delivered": {"0": ["../../etc/passwd#0", 7]}}])})]
        elif k == 6:
            msg = [bytes(base), rng.randbytes(50)]
        elif k == 7:
            msg = [b"\x00" * (20 * 1024 * 1024)]  # over ZMQ_MAXMSGSIZE: the connection is cut
        else:
            msg = [pack({"type": "ack", "batch_ids": rng.choice([[-1], ["a"], [2 ** 64 - 1], None, {"a": 1}]),
                         "credit": rng.choice([1, -5, 10 ** 9, 1.5])})]
        out.append(msg)
    return out


def run_fuzzer(endpoint: str, n: int, seconds: float, seed: int = 0) -> int:
    """Send up to ``n`` fuzz messages within ``seconds``, a fresh socket every few; returns the count sent."""
    rng = random.Random(seed)
    ctx = zmq.Context()
    sent = 0
    deadline = time.monotonic() + seconds
    try:
        msgs = fuzz_messages(rng, n)
        for i in range(0, len(msgs), 5):
            if time.monotonic() > deadline:
                break
            s = ctx.socket(zmq.DEALER)
            s.setsockopt(zmq.LINGER, 0)
            s.connect(endpoint)
            for m in msgs[i:i + 5]:
                s.send_multipart(m)
                sent += 1
            time.sleep(0.02)
            while s.poll(10):
                s.recv_multipart()
            s.close(0)
    finally:
        ctx.term()
    return sent


def scenario_fuzzing_peer(tmp: Path, layout: Layout, n: int = 400) -> dict:
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log: list = []
    with _serve(corpus, layout, "--epochs", "1") as srv:
        ds = V2VPushDataset(srv.endpoint, timeout_s=60, credits=2)
        sent = []
        def fuzz():
            while not log:  # the trainer says hello first, so it chooses the stream's outputs
                time.sleep(0.02)
            sent.append(run_fuzzer(srv.endpoint, n, 30.0))

        th = threading.Thread(target=fuzz, daemon=True)
        th.start()
        read_all(ds, log)
        th.join(60)
        rc = srv.wait(30)
        dropped = srv.log.count("dropping client")
    return row("fuzzing peer during a normal run", expected, _ids(log), None,
               f"{sent[0] if sent else 0} fuzz messages, {dropped} peer drop(s) logged, server exit {rc}",
               fuzz_messages=sent[0] if sent else 0, peer_drops=dropped, server_exit=rc)


# ------------------------------------------------------------------ delivery failure modes
def _serve(corpus: Path, layout: Layout, *extra: str, workers: int = 2, **kw) -> ServeProcess:
    """A v2v-serve on ``corpus`` with ``layout``'s samples and ``extra`` arguments (``kw``:
    ``ServeProcess``'s ``env``, ``wrap``)."""
    return ServeProcess(["--videos", str(corpus), "--workers", str(workers), *layout.args(), *extra], **kw)


def scenario_break_loop(tmp: Path, layout: Layout, breaks: int = 4) -> dict:
    """Trainers that take a batch and ``break`` (max_steps, a rank stopping first) while
    another trainer reads on: the acks of what was taken go out before ``bye``."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log: list = []
    with _serve(corpus, layout, "--epochs", "1") as srv:
        rest = V2VPushDataset(srv.endpoint, timeout_s=60, credits=1)
        quitter = V2VPushDataset(srv.endpoint, timeout_s=60, credits=4)
        for _ in range(breaks):
            for b in quitter:
                log.append((time.monotonic(), list(b["sample_ids"])))
                break
        read_all(rest, log)
        rc = srv.wait(30)
    return row(f"trainer breaks out of its loop x{breaks}", expected, _ids(log), None,
               f"acks flushed before bye; server exit {rc}", server_exit=rc)


SILENT_CLIENT = r"""
import sys, time
from v2v_client import V2VPushDataset
ds = V2VPushDataset(sys.argv[1], timeout_s=20, credits=3)
for b in ds:
    print("ids", " ".join(b["sample_ids"]), flush=True)
    time.sleep(0.2)
"""


def _stopped_while_another_reads(endpoint: str, p: subprocess.Popen, stop: Callable[[], List[str]], stopped_s: float,
                                 other_step_s: float) -> Tuple[List[str], list]:
    """Trainer A (process ``p``, printing ``ids ...`` lines) is stopped by ``stop()``, which
    returns the ids A printed until then and leaves A stopped (SIGSTOP); trainer B then reads
    ``endpoint``, ``other_step_s`` seconds a batch so the stream outlives the stop. After
    ``stopped_s`` seconds A is resumed and both read to the end. Returns (the ids A printed,
    B's log); A is killed if anything fails on the way."""
    log_b: list = []

    def slow_reader(ds):
        for b in ds:
            log_b.append((time.monotonic(), list(b["sample_ids"])))
            time.sleep(other_step_s)

    try:
        ids = stop()
        other = V2VPushDataset(endpoint, timeout_s=60, credits=1)
        tb = threading.Thread(target=slow_reader, args=(other,), daemon=True)
        tb.start()
        time.sleep(stopped_s)
        p.send_signal(signal.SIGCONT)
        for line in p.stdout:
            ids += line.split()[1:]
        p.wait(60)
        tb.join(60)
    finally:
        if p.poll() is None:
            p.send_signal(signal.SIGCONT)
            p.kill()
    return ids, log_b


STOPPED_CLIENT = r"""
import os, signal, sys
from v2v_client import V2VPushDataset
ds = V2VPushDataset(sys.argv[1], timeout_s=float(sys.argv[2]), credits=1)
for n, b in enumerate(ds, 1):
    print("ids", " ".join(b["sample_ids"]), flush=True)
    if n == 1:
        os.kill(os.getpid(), signal.SIGSTOP)
"""


def scenario_stopped_past_timeout_across_restart(tmp: Path, layout: Layout, timeout_s: float = 3.0) -> dict:
    """A trainer (``timeout_s``) stopped (SIGSTOP) after its first batch while the server is
    killed and restarted from its ``--state-dir`` on the same endpoint, and woken past its
    timeout: the new server does not know it, so nothing waits in its socket; it must not count
    its own stall as the server's silence, but say a heartbeat, be told ``unknown_client``,
    say hello again and read the rest of the epoch."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    args = ["--videos", str(corpus), "--workers", "2", "--epochs", "1", "--state-dir", str(tmp / "state"),
            *layout.args()]
    srv = ServeProcess(args).start()
    srv2 = None
    p = _trainer_process(STOPPED_CLIENT, srv.endpoint, str(timeout_s))
    try:
        ids = p.stdout.readline().split()[1:]
        time.sleep(0.3)
        srv.proc.send_signal(signal.SIGKILL)
        srv.proc.wait(10)
        srv2 = ServeProcess(args[:] + ["--bind", srv.endpoint]).start()
        time.sleep(timeout_s + 2.0)  # stopped past its timeout
        t_wake = time.monotonic()
        p.send_signal(signal.SIGCONT)
        log = [(time.monotonic(), line.split()[1:]) for line in p.stdout if line.startswith("ids")]
        rc = p.wait(60)
        srv2.wait(30)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(10)
        srv.stop()
        if srv2 is not None:
            srv2.stop()
    return row(f"trainer stopped {timeout_s + 2:.0f} s > its timeout across a server restart", expected,
               ids + _ids(log), _next_after(log, t_wake), f"client exit {rc}", client_exit=rc)


def scenario_silent_client(tmp: Path, layout: Layout, client_timeout_s: float = 2.0) -> dict:
    """A trainer process suspended (SIGSTOP) longer than the server's client timeout, then
    resumed: it was dropped and its batches went to another trainer, so it must hand none
    of what it held to its training loop."""
    corpus = good_corpus(tmp, 3)
    expected = expected_ids(corpus, layout)
    with _serve(corpus, layout, "--epochs", "1", "--client-timeout", str(client_timeout_s)) as srv:
        p = _trainer_process(SILENT_CLIENT, srv.endpoint)

        def stop() -> List[str]:
            ids = p.stdout.readline().split()[1:]
            time.sleep(0.3)  # its queue fills up to its credits
            p.send_signal(signal.SIGSTOP)
            return ids

        ids, log_b = _stopped_while_another_reads(srv.endpoint, p, stop, client_timeout_s * 2 + 1, other_step_s=1.0)
        rc = srv.wait(30)
        drops = srv.log.count("dropping it")
    return row(f"trainer suspended {client_timeout_s * 2 + 1:.0f} s > client timeout", expected, ids + _ids(log_b),
               None, f"{drops} drop(s) logged; server exit {rc}", drops=drops, server_exit=rc)


FROZEN_CLIENT = r"""
import os, signal, sys, time
from v2v_client import V2VPushDataset
credits, step_s, stop_at = int(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
ds = V2VPushDataset(sys.argv[1], timeout_s=60, credits=credits)
for n, b in enumerate(ds, 1):
    print("ids", " ".join(b["sample_ids"]), flush=True)
    if n == stop_at:  # stopped right at the yield, before its ack may have left the process
        os.kill(os.getpid(), signal.SIGSTOP)
    time.sleep(step_s)
"""


def busy_cores(n: int) -> List[subprocess.Popen]:
    """``n`` processes that keep a core busy each (stop them with ``stop_busy``)."""
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def stop_busy(procs: List[subprocess.Popen]) -> None:
    for p in procs:
        p.kill()
        p.wait(10)


def scenario_frozen_client(tmp: Path, layout: Layout, client_timeout_s: float = 2.0, freeze_s: float = 5.0,
                           credits: int = 4, step_s: float = 0.3, at_yield: bool = False, busy: int = 2) -> dict:
    """Client A (``credits``, ``step_s`` steps) is frozen (SIGSTOP) for ``freeze_s`` seconds, past
    the server's ``client_timeout_s``, while client B reads, with ``busy`` processes keeping the
    cores busy. By default the test stops A from outside at whatever point it is (between
    receiving a batch and yielding it, or elsewhere); with ``at_yield`` A stops itself right as
    its second batch is yielded. Every batch A yielded was granted first, so the server gave
    none of them to B; what A held and had not yet been granted went to B."""
    corpus = good_corpus(tmp, 3)
    expected = expected_ids(corpus, layout)
    hogs = busy_cores(busy)
    try:
        # a grace period after the end: A, dropped while frozen, may hold granted batches it has
        # not yielded, which the server counts as A's until A's resume hello names what it took
        # (B can finish the rest of the epoch while A is still stopped)
        with _serve(corpus, layout, "--epochs", "1", "--client-timeout", str(client_timeout_s),
                    "--end-grace-s", "5") as srv:
            p = _trainer_process(FROZEN_CLIENT, srv.endpoint, str(credits), str(step_s), "2" if at_yield else "0")

            def stop() -> List[str]:
                ids = p.stdout.readline().split()[1:]
                if at_yield:
                    ids += p.stdout.readline().split()[1:]
                    deadline = time.monotonic() + 30
                    while Path(f"/proc/{p.pid}/stat").read_text().split(")")[1].split()[0] != "T":
                        assert time.monotonic() < deadline, "the client never stopped itself"
                        time.sleep(0.01)
                else:
                    time.sleep(step_s * 1.5)  # mid-way through a step, its queue filled up to its credits
                    p.send_signal(signal.SIGSTOP)
                return ids

            ids, log_b = _stopped_while_another_reads(srv.endpoint, p, stop, freeze_s, other_step_s=0.5)
            rc = srv.wait(60)
            drops = srv.log.count("dropping it")
    finally:
        stop_busy(hogs)
    where = "at its yield" if at_yield else "mid-step"
    return row(f"trainer frozen {freeze_s:.0f} s {where} > client timeout, {busy} busy cores", expected,
               ids + _ids(log_b), None, f"{drops} drop(s) logged; server exit {rc}", drops=drops, server_exit=rc,
               a_batches=len(ids))


def _take(it, n: int, log: list) -> None:
    for _ in range(n):
        b = next(it)
        log.append((time.monotonic(), list(b["sample_ids"])))


def scenario_old_checkpoint(tmp: Path, layout: Layout, ckpt_step: int = 2) -> dict:
    """Checkpoint at step k, crash after step k + 1, restart from the step-k checkpoint against
    the same server: the samples of step k + 1 are sent again (the resume state is the truth)."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    kept: list = []  # what the restored model has seen
    with _serve(corpus, layout, "--epochs", "1", "--client-timeout", "3") as srv:
        ds = V2VPushDataset(srv.endpoint, timeout_s=60, credits=2)
        it = iter(ds)
        _take(it, ckpt_step, kept)
        state = ds.state_dict()
        lost_step: list = []
        _take(it, 1, lost_step)  # trained on, then the process dies before the next checkpoint
        del it  # the crash: no bye, the server notices the silence
        ds2 = V2VPushDataset(srv.endpoint, timeout_s=60, credits=2)
        ds2.load_state_dict(state)
        read_all(ds2, kept)
        rc = srv.wait(30)
    return row(f"restart from a checkpoint older than the last ack (step {ckpt_step} of {ckpt_step + 1})",
               expected, _ids(kept), None, f"{len(_ids(lost_step))} sample(s) of the lost step sent again; "
                                           f"server exit {rc}", resent=len(_ids(lost_step)), server_exit=rc)


def scenario_partial_file(tmp: Path, layout: Layout, epochs: int = 2) -> dict:
    """A clip whose frame size changes inside window 1: that window fails in each epoch (with
    a reason; ``--check`` says so) and the file's other windows are served in every epoch.
    Windows at k x stride (``shot_cuts: off``): the shot detector takes a change of frame size
    for a cut, and under ``avoid`` no window would hold it."""
    from harness.corpus import write_size_change_video

    layout = Layout(layout.L, layout.crop, 3, layout.batch, "off")  # three windows: the middle one fails
    corpus = good_corpus(tmp, 1)
    span = layout.L * 5 + 1
    write_size_change_video(corpus / "size_change.mpg", span + span // 2, 2 * span)
    one = expected_ids(corpus, layout)
    expected = [f"{e}:{sid}" for e in range(epochs) for sid in one]
    log: list = []
    with _serve(corpus, layout, "--epochs", str(epochs)) as srv:
        ds = V2VPushDataset(srv.endpoint, timeout_s=60)
        for b in ds:
            log.append((time.monotonic(), [f"{b['epoch']}:{s}" for s in b["sample_ids"]]))
        rc = srv.wait(30)
        logged = srv.log.count("frame size changed")
    got = _ids(log)
    per_epoch = [sum(1 for s in got if s.startswith(f"{e}:size_change.mpg#")) for e in range(epochs)]
    return row(f"clip changes frame size in window 1, {epochs} epochs", expected, got, None,
               f"size_change.mpg windows served per epoch {per_epoch}; failure logged {logged}x; server exit {rc}",
               windows_per_epoch=list(per_epoch), failure_logged=logged, server_exit=rc)


def _raw_peer(endpoint: str, credits: int = 2):
    ctx = zmq.Context()
    s = ctx.socket(zmq.DEALER)
    s.setsockopt(zmq.LINGER, 0)
    s.connect(endpoint)
    s.send(pack({"type": "hello", "outputs": ["voxels"], "credits": credits, "consumer": "raw"}))
    return ctx, s


def scenario_revoke_ignored(tmp: Path, layout: Layout, lease_s: float = 1.0, revoke_s: float = 2.0) -> dict:
    """A peer that heartbeats but never answers ``revoke`` holds two batches: its revoke
    expires, it is dropped, and the batches reach a real trainer (the epoch ends)."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log: list = []
    held: List[str] = []
    codes: List[str] = []
    with _serve(corpus, layout, "--epochs", "1", "--lease", str(lease_s), "--revoke-timeout", str(revoke_s)) as srv:
        ctx, s = _raw_peer(srv.endpoint)
        stop = threading.Event()

        def hog():
            from v2v_wire.protocol import unpack
            while not stop.is_set():
                if s.poll(100):
                    h = unpack(s.recv_multipart()[0])
                    if h["type"] == "batch":
                        held.extend(h["sample_ids"])
                    if h["type"] == "error":
                        codes.append(h.get("code") or "")
                s.send(pack({"type": "heartbeat"}))

        th = threading.Thread(target=hog, daemon=True)
        th.start()
        while not held:
            time.sleep(0.05)
        t0 = time.monotonic()
        read_all(V2VPushDataset(srv.endpoint, timeout_s=60, credits=1), log)
        took = time.monotonic() - t0
        stop.set()
        th.join(5)
        s.close()
        ctx.term()
        rc = srv.wait(30)
    return row(f"peer ignores revoke (lease {lease_s:.0f} s, revoke timeout {revoke_s:.0f} s)", expected, _ids(log),
               None, f"{len(held)} held, peer told {sorted(set(codes))}; epoch done in {took:.1f} s; server exit {rc}",
               held=len(held), codes=sorted(set(codes)), server_exit=rc)


def scenario_slow_trainer(tmp: Path, layout: Layout, lease_s: float = 0.5, step_s: float = 0.7, credits: int = 2,
                          copies: int = 1) -> dict:
    """A trainer whose steps are slower than the lease, alone on the stream: the batches beyond
    the two granted ahead of its loop are revoked and re-sent, and that never grows what it
    holds beyond its credits."""
    corpus = good_corpus(tmp, copies)
    expected = expected_ids(corpus, layout)
    log: list = []
    peak = 0
    with _serve(corpus, layout, "--epochs", "1", "--lease", str(lease_s)) as srv:
        ds = V2VPushDataset(srv.endpoint, timeout_s=60, credits=credits)
        it = iter(ds)
        for b in it:
            log.append((time.monotonic(), list(b["sample_ids"])))
            peak = max(peak, ds.held())
            time.sleep(step_s)
            peak = max(peak, ds.held())
        rc = srv.wait(30)
        resent = srv.log.count("go back to the queue")
    return row(f"trainer steps {step_s} s slower than lease {lease_s} s", expected, _ids(log), None,
               f"most batches held {peak} (credits {credits}); {resent} re-queue(s); server exit {rc}",
               peak_held=peak, requeues=resent, server_exit=rc)


def scenario_hung_worker(tmp: Path, layout: Layout, task_timeout_s: float = 3.0, client_timeout_s: float = 2.0
                         ) -> dict:
    """A worker stopped (SIGSTOP) mid-task: its task is reassigned after the task timeout and
    the worker replaced; a trainer whose timeout is shorter than the stall keeps waiting on
    the heartbeating server instead of raising StreamTimeout."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log: list = []
    err = None
    with _serve(corpus, layout, "--epochs", "1", "--task-timeout", str(task_timeout_s), workers=1) as srv:
        ds = V2VPushDataset(srv.endpoint, timeout_s=client_timeout_s, credits=1)
        it = iter(ds)
        stopped = []
        try:
            for b in it:
                log.append((time.monotonic(), list(b["sample_ids"])))
                if not stopped:
                    pids = worker_pids(srv.proc.pid)
                    if pids:
                        os.kill(pids[0], signal.SIGSTOP)
                        stopped.append(pids[0])
        except Exception as e:  # noqa: BLE001 - reported in the row
            err = f"{type(e).__name__}: {e}"
        finally:
            for pid in stopped:
                try:
                    os.kill(pid, signal.SIGCONT)
                except OSError:
                    pass
        rc = srv.wait(30)
        timeouts = srv.log.count("task reassigned")
    return row(f"worker stopped mid-task (task timeout {task_timeout_s:.0f} s, client timeout "
               f"{client_timeout_s:.0f} s)", expected, _ids(log), None,
               f"{timeouts} task timeout(s); trainer error: {err or 'none'}; server exit {rc}",
               task_timeouts=timeouts, trainer_error=err or None, server_exit=rc)


def scenario_reader_stopped_past_task_timeout(tmp: Path, layout: Layout, task_timeout_s: float = 2.0,
                                              stop_s: float = 8.0) -> dict:
    """A trainer takes a batch, then stops reading for ``stop_s`` (several task timeouts: a
    validation pass, a checkpoint upload, a debugger) and reads on. Enough batches wait for it
    that the server stops reading its busy workers (back-pressure); their silence while unread is
    no hang: no task times out, no worker is replaced. ``facts``: ``busy`` (workers busy as the
    stop ends, from ``/metrics``), ``restarts`` and ``task_timeouts`` (the server's last status line)."""
    import urllib.request

    corpus = good_corpus(tmp, 3)
    expected = expected_ids(corpus, layout)
    log: list = []
    port = free_port()
    with _serve(corpus, layout, "--epochs", "1", "--task-timeout", str(task_timeout_s), "--shuffle-buffer",
                str(layout.batch), "--metrics-port", str(port)) as srv:
        it = iter(V2VPushDataset(srv.endpoint, timeout_s=60, credits=1))
        try:
            b = next(it)
            log.append((time.monotonic(), list(b["sample_ids"])))
            time.sleep(stop_s)  # the loop stops; its I/O thread still heartbeats
            page = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
            busy = next(float(ln.split()[1]) for ln in page.splitlines() if ln.startswith("v2v_workers_busy "))
            for b in it:
                log.append((time.monotonic(), list(b["sample_ids"])))
        finally:
            it.close()
        rc = srv.wait(30)
    m = re.search(r"stopped: .* (\d+) worker restart\(s\), (\d+) task timeout\(s\)", srv.log)
    restarts, timeouts = (int(m.group(1)), int(m.group(2))) if m else (None, None)
    return row(f"trainer stopped {stop_s:.0f} s, task timeout {task_timeout_s:.0f} s", expected, _ids(log), None,
               f"{busy:.0f} worker(s) busy at the end of the stop; {restarts} worker restart(s), {timeouts} task "
               f"timeout(s); server exit {rc}", busy=busy, restarts=restarts, task_timeouts=timeouts, server_exit=rc)


def bad_peer_messages() -> List[List[bytes]]:
    """Messages that used to crash or stall the server, and a flood of garbage."""
    import msgpack

    bomb = msgpack.packb({"type": "hello", "v": PROTOCOL_VERSION, "outputs": ["voxels"], "credits": 1,
                          "resume": {"delivered": {"0": [[[]] * 1000] * 1000}}})
    deep = b"\x91" * 100000 + b"\xc0"
    return ([[pack({"type": "ack", "batch_ids": ["a", None, 1.5]})],
             [pack({"type": "hello", "outputs": ["voxels"], "credits": 1,
                    "resume": {"completed_epoch": -1, "delivered": {"٣": "a.mp4#٣"}}})],
             [pack({"type": "hello", "outputs": ["voxels"], "credits": 1, "resume": {"delivered": {"0": "x.mp4#١"}}})],
             [pack({"type": "ack", "batch_ids": {"x": 1}})], [pack({"type": "credit", "credit": "many"})],
             [pack({"type": "hello", "outputs": ["voxels"], "credits": 10 ** 6})], [bomb], [deep]]
            + [[b"\xc1garbage"]] * 2000)


def scenario_bad_peer(tmp: Path, layout: Layout) -> dict:
    """Wrongly-typed fields, non-ASCII digits, a nested-msgpack bomb and a garbage flood from
    one peer while a trainer reads: the server stays up, logs a bounded number of lines."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log: list = []
    with _serve(corpus, layout, "--epochs", "1") as srv:
        ds = V2VPushDataset(srv.endpoint, timeout_s=60, credits=2)
        it = iter(ds)
        _take(it, 1, log)
        ctx = zmq.Context()
        msgs = bad_peer_messages()
        for i, m in enumerate(msgs):
            if i % 50 == 0 or i < 10:
                s = ctx.socket(zmq.DEALER)
                s.setsockopt(zmq.LINGER, 0)
                s.connect(srv.endpoint)
            s.send_multipart(m)
        for b in it:
            log.append((time.monotonic(), list(b["sample_ids"])))
        ctx.destroy(0)
        rc = srv.wait(30)
        lines = srv.log.count("dropping client")
        crashed = "Traceback" in srv.log
    return row("malformed, mistyped and bomb messages + 2000 garbage", expected, _ids(log), None,
               f"{len(msgs)} bad messages, {lines} log line(s), traceback {crashed}; server exit {rc}",
               bad_messages=len(msgs), log_lines=lines, traceback=crashed, server_exit=rc)


def scenario_ddp_ranks(tmp: Path, layout: Layout, world: int = 4) -> dict:
    """``world`` DDP ranks on one stream: every rank yields the same number of batches per
    epoch (repeats flagged in ``padding``); the non-padding samples are each epoch once."""
    corpus = good_corpus(tmp, 1)
    expected = expected_ids(corpus, layout)
    logs: List[list] = [[] for _ in range(world)]
    counts: List[collections.Counter] = [collections.Counter() for _ in range(world)]
    errors: list = []
    with _serve(corpus, layout, "--epochs", "1") as srv:
        def rank(r):
            try:
                ds = V2VPushDataset(srv.endpoint, timeout_s=60, credits=1, rank=r, world_size=world)
                for b in ds:
                    counts[r][b["epoch"]] += 1
                    real = [s for s, p in zip(b["sample_ids"], b["padding"].tolist()) if not p]
                    logs[r].append((time.monotonic(), real))
            except Exception as e:  # noqa: BLE001
                errors.append(e)

        ths = [threading.Thread(target=rank, args=(r,), daemon=True) for r in range(world)]
        for t in ths:
            t.start()
        for t in ths:
            t.join(120)
        rc = srv.wait(30)
    per_rank = [c[0] for c in counts]
    return row(f"{world} DDP ranks on one stream", expected, [s for lg in logs for s in _ids(lg)], None,
               f"batches per rank {per_rank}; errors {len(errors)}; server exit {rc}",
               batches_per_rank=list(per_rank), errors=len(errors), server_exit=rc)


def scenario_ddp_late_rank(tmp: Path, layout: Layout, delay_s: float = 3.0) -> dict:
    """Two ranks checkpoint, the server is killed and restarted, rank 0 resumes at once and
    rank 1 ``delay_s`` later (longer than its own timeout_s): rank 0 is sent nothing rank 1's
    state holds, rank 1 does not time out, and each sample arrives once."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    args = ["--videos", str(corpus), "--workers", "2", "--epochs", "1", *layout.args()]
    logs: List[list] = [[], []]
    states: list = [None, None]
    errors: list = []
    srv = ServeProcess(args).start()
    srv2 = None
    try:
        dss = [V2VPushDataset(srv.endpoint, timeout_s=60, credits=2, rank=r, world_size=2) for r in range(2)]
        its = [iter(d) for d in dss]
        for r in range(2):
            _take(its[r], 2, logs[r])
            states[r] = dss[r].state_dict()
        srv.proc.send_signal(signal.SIGKILL)
        srv.proc.wait(10)
        for it in its:
            it.close()
        srv2 = ServeProcess(args + ["--bind", srv.endpoint]).start()

        def rank(r):
            try:
                if r == 1:
                    time.sleep(delay_s)
                ds = V2VPushDataset(srv.endpoint, timeout_s=2.0, credits=2, rank=r, world_size=2)
                ds.load_state_dict(states[r])
                for b in ds:
                    real = [s for s, p in zip(b["sample_ids"], b["padding"].tolist()) if not p]
                    logs[r].append((time.monotonic(), real))
            except Exception as e:  # noqa: BLE001
                errors.append(f"rank {r}: {type(e).__name__}: {e}")

        ths = [threading.Thread(target=rank, args=(r,), daemon=True) for r in range(2)]
        for t in ths:
            t.start()
        for t in ths:
            t.join(120)
        rc = srv2.wait(30)
    finally:
        srv.stop()
        if srv2 is not None:
            srv2.stop()
    return row(f"2 DDP ranks resume after a server restart, rank 1 {delay_s:.0f} s late", expected,
               _ids(logs[0]) + _ids(logs[1]), None, f"errors: {errors or 'none'}; server exit {rc}",
               errors=list(errors), server_exit=rc)


def scenario_fair_sharing(tmp: Path, layout: Layout, clients: int = 20) -> dict:
    """``clients`` trainers read one stream at once: each gets a near-equal share. The trainers
    dial before the server starts (ZeroMQ holds their hellos until it binds), so all of them are
    there when its first batch is ready: a share measures the fair rotation, not how long 20
    threads took to connect on a loaded machine while the first ones drained the stream."""
    corpus = good_corpus(tmp, 4)
    expected = expected_ids(corpus, layout)
    logs: List[list] = [[] for _ in range(clients)]
    srv = _serve(corpus, layout, "--epochs", "1", "--batch-size", "1")
    ths = [threading.Thread(target=read_all, args=(V2VPushDataset(srv.endpoint, timeout_s=60, credits=1),
                                                    logs[i]), daemon=True) for i in range(clients)]
    for t in ths:
        t.start()
    with srv:
        for t in ths:
            t.join(180)
        rc = srv.wait(30)
    share = sorted(len(lg) for lg in logs)
    return row(f"{clients} trainers on one stream", expected, [s for lg in logs for s in _ids(lg)], None,
               f"batches per trainer min {share[0]} max {share[-1]}; server exit {rc}",
               min_batches=share[0], max_batches=share[-1], server_exit=rc)



def scenario_undecodable_name(tmp: Path, layout: Layout) -> dict:
    """A clip whose file name is not valid UTF-8 (bytes ``caf\\xe9``, a Latin-1 name) beside good
    ones: it is ignored with one log line naming it (escaped), the others are served, the
    server ends the epoch and exits 0."""
    import os

    corpus = good_corpus(tmp, 1)
    expected = expected_ids(corpus, layout)
    bad = os.fsdecode(bytes(corpus) + b"/caf\xe9.mp4")
    shutil.copy(next(corpus.glob("*.mp4")), bad)
    log: list = []
    with _serve(corpus, layout, "--epochs", "1") as srv:
        read_all(V2VPushDataset(srv.endpoint, timeout_s=60), log)
        rc = srv.wait(30)
        text = srv.log
    logged = text.count("caf\\xe9.mp4: file name is not valid UTF-8")
    return row("a file name that is not valid UTF-8", expected, _ids(log), None,
               f"ignored and logged {logged}x; server exit {rc}; traceback {'Traceback' in text}",
               logged=logged, server_exit=rc, traceback="Traceback" in text)



def scenario_resume_after_end(tmp: Path, layout: Layout, ckpt_step: int = 2, grace_s: float = 20.0) -> dict:
    """torchdata's StatefulDataLoader checkpoints at step ``ckpt_step``, reads the epoch to its
    end (the server declares it complete and ends the stream) and the trainer is resumed from
    that older checkpoint against the same ``--epochs 1`` server, still up in its grace period:
    it gets exactly the samples after the checkpoint, then the server exits by itself once no
    trainer is connected for ``--end-grace-s``."""
    from torchdata.stateful_dataloader import StatefulDataLoader

    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    first: list = []
    resumed: list = []
    with _serve(corpus, layout, "--epochs", "1", "--end-grace-s", str(grace_s)) as srv:
        loader = StatefulDataLoader(V2VPushDataset(srv.endpoint, timeout_s=60), batch_size=None)
        ckpt = None
        for step, b in enumerate(loader):
            first.append(list(b["sample_ids"]))
            if step + 1 == ckpt_step:
                ckpt = loader.state_dict()
        t_end = time.monotonic()
        ended_alive = srv.proc.poll() is None  # still serving after the end of the stream
        again = StatefulDataLoader(V2VPushDataset(srv.endpoint, timeout_s=60), batch_size=None)
        again.load_state_dict(ckpt)
        for b in again:
            resumed.append(list(b["sample_ids"]))
        resume_s = time.monotonic() - t_end
        rc = srv.wait(grace_s + 30)
        gone_after = time.monotonic() - t_end
    trained = [s for ids in first[:ckpt_step] for s in ids] + [s for ids in resumed for s in ids]
    after_ckpt = sorted(s for ids in first[ckpt_step:] for s in ids)
    return row(f"StatefulDataLoader resumed from step {ckpt_step} after the epoch ended", expected, trained, resume_s,
               f"server alive after the end {ended_alive}; resumed run got {len(trained) - sum(map(len, first[:ckpt_step]))} "
               f"samples (the {len(after_ckpt)} after the checkpoint); server exit {rc} after {gone_after:.0f} s",
               ended_alive=ended_alive, resumed_equal=sorted(s for ids in resumed for s in ids) == after_ckpt,
               server_exit=rc, exit_after_s=round(gone_after, 1))



def scenario_loader_workers(tmp: Path, layout: Layout, persistent: bool, take: int = 3) -> dict:
    """``StreamLoader(ds, num_workers=2)``: take ``take`` batches and ``break`` (max_steps),
    then iterate again, until an iteration runs to the end of the ``--epochs 1`` stream.
    Batches the workers prefetched but the loop never received are sent again, to the next
    iteration; none that it received is."""
    from v2v_client import StreamLoader

    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log: list = []
    rounds = 0
    # an iteration may start after the end of the stream: the server waits for it (its grace period)
    with _serve(corpus, layout, "--epochs", "1", "--end-grace-s", "60") as srv:
        loader = StreamLoader(V2VPushDataset(srv.endpoint, timeout_s=60, credits=2), num_workers=2,
                              persistent_workers=persistent)
        finished = False
        while not finished and rounds < 20:
            rounds += 1
            finished = True
            for i, b in enumerate(loader):
                log.append((time.monotonic(), list(b["sample_ids"])))
                if i + 1 == take:
                    finished = False
                    break
        ended = srv.log.count("all 1 epoch(s) delivered")
        rc = srv.stop()  # SIGINT: a clean stop, exit 130 (128 + SIGINT), as for every command
    kind = "persistent" if persistent else "non-persistent"
    return row(f"StreamLoader, 2 {kind} workers, break after {take} batches and iterate again", expected,
               _ids(log), None, f"{rounds} iterations; stream ended {ended}x; server exit {rc}", rounds=rounds,
               ended=ended, server_exit=rc)



def _acks_journaled(state_dir: Path) -> int:
    """Acknowledged batches recorded so far in a server's ``--state-dir`` journal."""
    import msgpack

    try:
        with open(state_dir / "delivered.journal", "rb") as f:
            return sum(1 for r in msgpack.Unpacker(f, raw=False) if isinstance(r, dict) and "d" in r)
    except (OSError, ValueError, msgpack.UnpackException):
        return 0


def scenario_independent_restart(tmp: Path, layout: Layout, journal: bool = True, late_s: float = 3.0) -> dict:
    """Two trainers that are not one DDP group read one stream, each checkpoints after 2
    batches, the server is killed (SIGKILL) and restarted (with ``--state-dir`` when
    ``journal``); trainer A resumes at once and reads to the end, trainer B resumes ``late_s``
    later. With the journal the restarted server knows B's samples: A is sent none of them."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    args = ["--videos", str(corpus), "--workers", "2", "--epochs", "1", "--end-grace-s", "5", *layout.args()]
    if journal:
        args += ["--state-dir", str(tmp / "state")]
    trained: list = []
    srv = ServeProcess(args).start()
    srv2 = None
    try:
        states = []
        for _ in range(2):
            ds = V2VPushDataset(srv.endpoint, timeout_s=60, credits=1)
            it = iter(ds)
            _take(it, 2, trained)
            states.append(ds.state_dict())
            it.close()
        # what the server journaled survives its death; an ack still in flight then does not, and its
        # samples would go to A before B's resume state claims them: wait until all 4 acks are journaled
        deadline = time.monotonic() + (15 if journal else 0.5)
        while time.monotonic() < deadline and (not journal or _acks_journaled(tmp / "state") < 4):
            time.sleep(0.1)
        srv.proc.send_signal(signal.SIGKILL)
        srv.proc.wait(10)
        srv2 = ServeProcess(args + ["--bind", srv.endpoint]).start()
        a, b = (V2VPushDataset(srv.endpoint, timeout_s=60, credits=1) for _ in range(2))
        a.load_state_dict(states[0])
        read_all(a, trained)
        time.sleep(late_s)
        b.load_state_dict(states[1])
        read_all(b, trained)
        rc = srv2.wait(60)
    finally:
        srv.stop()
        if srv2 is not None:
            srv2.stop()
    what = "with --state-dir" if journal else "without a journal"
    return row(f"two independent trainers resume {late_s:.0f} s apart after a server restart, {what}", expected,
               _ids(trained), None, f"server exit {rc}", server_exit=rc)



def scenario_lightning_ddp(tmp: Path, layout: Layout) -> dict:
    """Lightning's own ``ddp`` launcher, 2 CPU ranks (gloo), the dataset built before
    ``fit`` (``harness/lightning_ddp.py``): both ranks form one DDP group, yield the same number
    of batches and train every sample once between them."""
    import json
    import subprocess
    import sys

    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    out = tmp / "ranks"
    out.mkdir()
    with _serve(corpus, layout, "--epochs", "1") as srv:
        r = subprocess.run([sys.executable, "-m", "harness.lightning_ddp", srv.endpoint, str(out)],
                           capture_output=True, text=True, timeout=600)
        rc = srv.wait(30)
    ranks = [json.loads(p.read_text()) for p in sorted(out.glob("rank*.json"))]
    seen = [s for r_ in ranks for s in r_["seen"]]
    counts = [r_["batches"] for r_ in ranks]
    return row("Lightning DDP, 2 gloo ranks, dataset built before fit", expected, seen, None,
               f"batches per rank {counts}; trainer exit {r.returncode}; server exit {rc}",
               batches_per_rank=counts, trainer_exit=r.returncode, server_exit=rc)


SCENARIOS = {
    "worker_kill": scenario_worker_kill,
    "client_kill": scenario_client_kill,
    "server_restart": scenario_server_restart,
    "stalled_client": scenario_stalled_client,
    "bad_corpus": scenario_bad_corpus,
    "fuzzing_peer": scenario_fuzzing_peer,
    "break_loop": scenario_break_loop,
    "silent_client": scenario_silent_client,
    "frozen_client": scenario_frozen_client,
    "frozen_at_yield": lambda tmp, layout: scenario_frozen_client(tmp, layout, at_yield=True),
    "old_checkpoint": scenario_old_checkpoint,
    "partial_file": scenario_partial_file,
    "revoke_ignored": scenario_revoke_ignored,
    "slow_trainer": scenario_slow_trainer,
    "hung_worker": scenario_hung_worker,
    "reader_stopped_past_task_timeout": scenario_reader_stopped_past_task_timeout,
    "bad_peer": scenario_bad_peer,
    "ddp_ranks": scenario_ddp_ranks,
    "ddp_late_rank": scenario_ddp_late_rank,
    "fair_sharing": scenario_fair_sharing,
    "undecodable_name": scenario_undecodable_name,
    "resume_after_end": scenario_resume_after_end,
    "loader_workers": lambda tmp, layout: scenario_loader_workers(tmp, layout, True),
    "loader_workers_fresh": lambda tmp, layout: scenario_loader_workers(tmp, layout, False),
    "independent_restart": scenario_independent_restart,
    "lightning_ddp": scenario_lightning_ddp,
}



"""Fault scenarios against a real v2v-serve on 127.0.0.1: is any sample lost or doubled?

Run: ``python -m bench.faults [--quick] [--out docs/faults.md]``. Prints a table: scenario,
samples expected, delivered, lost, duplicated, seconds to recover. ``tests/test_faults.py``
runs short versions of the same scenarios.
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Dict, List, Optional

import zmq

from v2v_client import V2VStreamDataset
from v2v_server.config import ServeConfig
from v2v_server.corpus import check_corpus
from v2v_server.process import ServeProcess
from v2v_server.protocol import pack
from v2v_server.video import scan_corpus

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data" / "videos"
GOOD_VIDEOS = SHARED if SHARED.is_dir() else ROOT / "v2v_server" / "sample_videos"


class Layout:
    """Small samples so scenarios run in seconds: L voxels x 5 bins, crop, windows per video."""

    def __init__(self, L: int = 4, crop: int = 64, windows: int = 2, batch: int = 2):
        self.L, self.crop, self.windows, self.batch = L, crop, windows, batch

    def args(self) -> List[str]:
        return ["--sequence-length", str(self.L), "--crop-size", str(self.crop), "--max-samples-per-video",
                str(self.windows), "--batch-size", str(self.batch), "--seed", "11", "--flow-preset", "ultrafast"]

    def cfg(self) -> ServeConfig:
        return ServeConfig(sequence_length=self.L, crop_size=self.crop, max_samples_per_video=self.windows,
                           workers=2).validate()


def expected_ids(corpus: Path, layout: Layout, exclude=()) -> List[str]:
    """Every sample id one epoch of ``corpus`` holds, from ``--check``'s verdicts."""
    vids = [p.as_posix() for p in scan_corpus(corpus, layout.cfg().video_extensions)[0]]
    vids = [v for v in vids if v not in exclude]
    return sorted(f"{r['path']}#{k}" for r in check_corpus(layout.cfg(), corpus, vids) for k in range(r["windows"]))


def good_corpus(tmp: Path, copies: int = 1) -> Path:
    d = tmp / "good"
    d.mkdir(parents=True, exist_ok=True)
    for p in sorted(GOOD_VIDEOS.glob("*.mp4")):
        for c in range(copies):
            shutil.copy(p, d / (p.name if c == 0 else f"{p.stem}_{c}{p.suffix}"))
    return d


def row(name: str, expected: List[str], delivered: List[str], recover_s: Optional[float], notes: str = "") -> dict:
    cnt = collections.Counter(delivered)
    exp = set(expected)
    return {"scenario": name, "expected": len(exp), "delivered": len(cnt), "lost": len(exp - set(cnt)),
            "duplicated": sum(v - 1 for v in cnt.values()), "unexpected": len(set(cnt) - exp),
            "recover_s": None if recover_s is None else round(recover_s, 2), "notes": notes}


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


def read_all(ds: V2VStreamDataset, log: list, stop_after: Optional[int] = None) -> None:
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
    with ServeProcess(["--videos", str(corpus), "--workers", "2", "--epochs", "1", *layout.args()]) as srv:
        ds = V2VStreamDataset(srv.endpoint, timeout_s=60, credits=1)

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
               f"{restarts} worker restart(s) logged")


CLIENT_SCRIPT = r"""
import json, os, sys
from v2v_client import V2VStreamDataset
endpoint, ckpt = sys.argv[1], sys.argv[2]
ds = V2VStreamDataset(endpoint, timeout_s=60, credits=2)
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


def scenario_client_kill(tmp: Path, layout: Layout, kill_after_steps: int = 2) -> dict:
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    ckpt = tmp / "trainer_ckpt.json"
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    with ServeProcess(["--videos", str(corpus), "--workers", "2", "--epochs", "1", "--client-timeout", "2",
                       *layout.args()]) as srv:
        p = subprocess.Popen([sys.executable, "-c", CLIENT_SCRIPT, srv.endpoint, str(ckpt)], stdout=subprocess.PIPE,
                             text=True, env=env)
        steps = 0
        for line in p.stdout:
            steps += line.startswith("step")
            if steps >= kill_after_steps:
                break
        p.send_signal(signal.SIGKILL)
        p.wait(10)
        t_kill = time.monotonic()
        p2 = subprocess.Popen([sys.executable, "-c", CLIENT_SCRIPT, srv.endpoint, str(ckpt)], stdout=subprocess.PIPE,
                              text=True, env=env)
        first = None
        for line in p2.stdout:
            if first is None and line.startswith("step"):
                first = time.monotonic() - t_kill
        rc = p2.wait(120)
        srv.wait(30)
    ids = json.loads(ckpt.read_text())["ids"]
    return row("client SIGKILL, restart from state_dict", expected, ids, first, f"restarted client exit {rc}")


def scenario_server_restart(tmp: Path, layout: Layout, kill_after_batches: int = 2) -> dict:
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    args = ["--videos", str(corpus), "--workers", "2", "--epochs", "1", *layout.args()]
    log: list = []
    srv = ServeProcess(args).start()
    srv2 = None
    try:
        ds = V2VStreamDataset(srv.endpoint, timeout_s=2.0, reconnect=True, reconnect_timeout_s=60, credits=1)
        it = iter(ds)
        for b in it:
            log.append((time.monotonic(), list(b["sample_ids"])))
            if len(log) >= kill_after_batches:
                break
        srv.proc.send_signal(signal.SIGKILL)
        srv.proc.wait(10)
        t_kill = time.monotonic()
        srv2 = ServeProcess(args[:] + ["--bind", srv.endpoint]).start()
        for b in it:
            log.append((time.monotonic(), list(b["sample_ids"])))
        it.close()
        srv2.wait(30)
    finally:
        srv.stop()
        if srv2 is not None:
            srv2.stop()
    return row("server SIGKILL + restart, client resumes", expected, _ids(log), _next_after(log, t_kill),
               "client reconnect=True with its delivered-sample state")


def scenario_stalled_client(tmp: Path, layout: Layout, lease_s: float = 2.0, stall_s: float = 6.0) -> dict:
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log_a: list = []
    log_b: list = []
    held: List[str] = []
    with ServeProcess(["--videos", str(corpus), "--workers", "2", "--epochs", "1", "--lease", str(lease_s),
                       *layout.args()]) as srv:
        a = V2VStreamDataset(srv.endpoint, timeout_s=60, credits=3)
        b = V2VStreamDataset(srv.endpoint, timeout_s=60, credits=1)
        ita = iter(a)
        first = next(ita)
        log_a.append((time.monotonic(), first["sample_ids"]))
        t_stall = time.monotonic()
        tb = threading.Thread(target=read_all, args=(b, log_b), daemon=True)
        tb.start()
        time.sleep(0.5)
        conn = a._conns[0]
        held = [s for item in list(conn.items.queue) if isinstance(item, dict) for s in item["sample_ids"]]
        time.sleep(stall_s)  # the training loop of A hangs; its I/O thread still heartbeats
        for bt in ita:
            log_a.append((time.monotonic(), bt["sample_ids"]))
        tb.join(120)
        srv.wait(30)
    got_b = [(t, ids) for t, ids in log_b if set(ids) & set(held)]
    rec = (min(t for t, _ in got_b) - t_stall - lease_s) if got_b else None
    return row(f"client stalled {stall_s:.0f} s > lease {lease_s:.0f} s", expected, _ids(log_a) + _ids(log_b), rec,
               f"{len(held)} held sample(s) re-sent to another client")


def scenario_bad_corpus(tmp: Path, layout: Layout) -> dict:
    from bench.fault_corpus import make_fault_corpus

    corpus = tmp / "faulty"
    exp = make_fault_corpus(corpus, GOOD_VIDEOS, layout.L * 5 + 1)
    expected = expected_ids(corpus, layout, exclude={"deleted_during_epoch.mp4"})
    log: list = []
    with ServeProcess(["--videos", str(corpus), "--workers", "2", "--epochs", "1", *layout.args()]) as srv:
        (corpus / "deleted_during_epoch.mp4").unlink()
        read_all(V2VStreamDataset(srv.endpoint, timeout_s=60), log)
        rc = srv.wait(60)
        text = srv.log
    skipped = [k for k, v in exp.items() if v == "skipped"]
    logged = [k for k in skipped if text.count(f"skipped {corpus / k}:") == 1]
    ignored = [k for k, v in exp.items() if v == "ignored" and f"ignored {corpus / k}:" in text]
    return row("corpus with every kind of bad file", expected, _ids(log), None,
               f"{len(logged)}/{len(skipped)} bad files logged once, "
               f"{len(ignored)}/{sum(v == 'ignored' for v in exp.values())} non-videos logged, server exit {rc}")


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
    with ServeProcess(["--videos", str(corpus), "--workers", "2", "--epochs", "1", *layout.args()]) as srv:
        ds = V2VStreamDataset(srv.endpoint, timeout_s=60, credits=2)
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
               f"{sent[0] if sent else 0} fuzz messages, {dropped} peer drop(s) logged, server exit {rc}")


SCENARIOS = {
    "worker_kill": scenario_worker_kill,
    "client_kill": scenario_client_kill,
    "server_restart": scenario_server_restart,
    "stalled_client": scenario_stalled_client,
    "bad_corpus": scenario_bad_corpus,
    "fuzzing_peer": scenario_fuzzing_peer,
}


def format_table(rows: List[dict]) -> str:
    head = "| scenario | expected | delivered | lost | duplicated | seconds to recover | notes |\n|---|---|---|---|---|---|---|"
    lines = [head]
    for r in rows:
        rec = "-" if r["recover_s"] is None else f"{r['recover_s']:.2f}"
        lines.append(f"| {r['scenario']} | {r['expected']} | {r['delivered']} | {r['lost']} | {r['duplicated']} | "
                     f"{rec} | {r['notes']} |")
    return "\n".join(lines)


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--only", nargs="*", choices=sorted(SCENARIOS), help="scenarios to run (default: all)")
    p.add_argument("--out", help="also write the table (markdown) here")
    p.add_argument("--kills", type=int, default=4, help="worker kills in the worker scenario")
    a = p.parse_args(argv)
    layout = Layout(L=8, crop=96, windows=3, batch=2)
    rows = []
    for name in a.only or list(SCENARIOS):
        with tempfile.TemporaryDirectory(prefix=f"v2v-{name}-") as d:
            kw = {"kills": a.kills, "copies": 6} if name == "worker_kill" else {}
            t = time.monotonic()
            r = SCENARIOS[name](Path(d), layout, **kw)
            r["notes"] += f"; {time.monotonic() - t:.0f} s"
            rows.append(r)
            print(json.dumps(r), file=sys.stderr)
    table = format_table(rows)
    print(table)
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text("# Fault scenarios\n\nCommand: `python -m bench.faults --out docs/faults.md`\n\n"
                               + table + "\n")
    bad = [r for r in rows if r["lost"] or r["duplicated"] or r["unexpected"]]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())

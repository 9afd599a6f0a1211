"""Fault scenarios against a real ``v2v-serve`` serving by plan on 127.0.0.1, read by
``V2VStreamDataset``: is any sample lost or doubled?

Each ``scenario_*`` runs a server (and trainers, killers, fuzzers) and returns a row: the
scenario, samples expected / delivered / lost / duplicated (sample ids, padding rows excluded;
with several epochs an id is ``epoch:id``), seconds to recover, ``facts`` (the measured values a
test asserts on) and ``notes`` (the same facts in words, for the table ``python -m bench.faults``
prints). A server serving by plan never ends by itself: a scenario stops it with SIGINT (exit
130, one line). ``tests/test_faults.py`` runs short versions of them.
"""
from __future__ import annotations

import collections
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable, List, Optional

import zmq

from v2v_client import V2VStreamDataset
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
        """The ``v2v-serve`` flags of this layout."""
        return ["--sequence-length", str(self.L), "--crop-size", str(self.crop), "--max-samples-per-video",
                str(self.windows), "--batch-size", str(self.batch), "--seed", "11", "--flow-preset", "ultrafast",
                "--shot-cuts", self.shot_cuts]

    def cfg(self) -> ServeConfig:
        """The ``ServeConfig`` of this layout (what ``--check`` is run under)."""
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


def per_epoch(ids: List[str], epochs) -> List[str]:
    """``ids`` of each of ``epochs``, as ``epoch:id``."""
    return [f"{e}:{s}" for e in epochs for s in ids]


def good_corpus(tmp: Path, copies: int = 1) -> Path:
    """``tmp/good``: ``copies`` copies of each bundled clip."""
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


def _serve(corpus: Path, layout: Layout, *extra: str, workers: int = 2, **kw) -> ServeProcess:
    """A v2v-serve serving ``corpus`` by plan with ``layout``'s samples and ``extra`` arguments
    (``kw``: ``ServeProcess``'s ``env``, ``wrap``, ``ready_timeout_s``)."""
    kw.setdefault("ready_timeout_s", 120)
    return ServeProcess(["--videos", str(corpus), "--workers", str(workers), *layout.args(), *extra], **kw)


def dataset(endpoint, **kw) -> V2VStreamDataset:
    """A plan reader with the scenarios' timeouts (a restarted server is asked again after 2 s)."""
    kw.setdefault("timeout_s", 120)
    kw.setdefault("retry_s", 2.0)
    return V2VStreamDataset(endpoint, **kw)


def real_ids(batch: dict, tag: bool = False) -> List[str]:
    """The batch's sample ids, padding rows left out (``epoch:id`` with ``tag``)."""
    ids = [s for s, pad in zip(batch["sample_ids"], batch["padding"].tolist()) if not pad]
    return [f"{batch['epoch']}:{s}" for s in ids] if tag else ids


def read_all(batches, log: list, stop_after: Optional[int] = None, tag: bool = False) -> Optional[dict]:
    """Iterate ``batches`` (a dataset or a DataLoader over one) to its end or ``stop_after``
    batches, appending (time, real sample ids) per batch to ``log``; the last batch's position."""
    it, position = iter(batches), None
    try:
        for n, b in enumerate(it, 1):
            log.append((time.monotonic(), real_ids(b, tag)))
            position = b["position"]
            if stop_after is not None and n >= stop_after:
                break
    finally:
        del it
    return position


def _ids(log) -> List[str]:
    return [s for _, ids in log for s in ids]


def _next_after(log, t: float) -> Optional[float]:
    later = [tt for tt, _ in log if tt > t]
    return (min(later) - t) if later else None


def _trainer_process(script: str, *args: str) -> subprocess.Popen:
    """``script`` run by a child Python that imports this checkout, with ``args``; its stdout a text pipe."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.Popen([sys.executable, "-c", script, *args], stdout=subprocess.PIPE, text=True, env=env)


def _stop(srv: ServeProcess) -> int:
    """Stop a plan server (it never ends by itself): SIGINT, its exit code (130: one line)."""
    return srv.stop()


def _clean(srv: ServeProcess) -> bool:
    return "Traceback" not in srv.log


#: A trainer process: reads one epoch (argv[4], default 0) of the plan at argv[1] in steps of
#: argv[3] seconds, printing each batch's real ids (``ids [...]``) before its step; after each step
#: it checkpoints the batch's position and every id trained on to argv[2] (atomically), and
#: starts from that checkpoint when it exists.
TRAINER = r"""
import json, os, sys, time
from v2v_client import V2VStreamDataset
endpoint, ckpt, step_s = sys.argv[1], sys.argv[2], float(sys.argv[3])
ds = V2VStreamDataset(endpoint, timeout_s=120, retry_s=2.0)
ds.set_epoch(int(sys.argv[4]) if len(sys.argv) > 4 else 0)
ids = []
if os.path.exists(ckpt):
    saved = json.load(open(ckpt))
    ds.load_state_dict(saved["position"])
    ids = saved["ids"]
for b in ds:
    new = [s for s, pad in zip(b["sample_ids"], b["padding"].tolist()) if not pad]
    print("ids", json.dumps(new), flush=True)
    time.sleep(step_s)                          # the training step
    ids += new
    json.dump({"position": b["position"], "ids": ids}, open(ckpt + ".tmp", "w"))
    os.replace(ckpt + ".tmp", ckpt)             # the checkpoint after every step
    print("step", len(ids), flush=True)
print("done", flush=True)
"""


def _printed_ids(line: str) -> List[str]:
    return json.loads(line[4:]) if line.startswith("ids ") else []


# ---------------------------------------------------------------------------------- crashes
def scenario_worker_kill(tmp: Path, layout: Layout, kills: int = 3, copies: int = 2) -> dict:
    """Workers killed (SIGKILL) one after another while a trainer reads: each is restarted, its
    samples made again, and the epoch's positions hold every sample once."""
    corpus = good_corpus(tmp, copies)
    expected = expected_ids(corpus, layout)
    log: list = []
    kill_times: List[float] = []
    with _serve(corpus, layout) as srv:
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
        read_all(dataset(srv.endpoint, prefetch=1), log)
        th.join(10)
        rc, clean = _stop(srv), _clean(srv)
        restarts = srv.log.count("restarting")
    rec = [r for r in (_next_after(log, t) for t in kill_times) if r is not None]
    return row(f"worker SIGKILL x{len(kill_times)} mid-epoch", expected, _ids(log), max(rec) if rec else None,
               f"{restarts} worker restart(s) logged; server exit {rc}", restarts=restarts, server_exit=rc,
               clean=clean)


def scenario_client_kill(tmp: Path, layout: Layout, kill_after_steps: int = 2) -> dict:
    """A trainer process killed (SIGKILL) after ``kill_after_steps`` steps and started again: it
    resumes at its checkpoint's position; what it trained on is each sample once."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    ckpt = tmp / "trainer_ckpt.json"
    with _serve(corpus, layout) as srv:
        p = _trainer_process(TRAINER, srv.endpoint, str(ckpt), "0")
        steps = 0
        for line in p.stdout:
            steps += line.startswith("step")
            if steps >= kill_after_steps:
                break
        p.send_signal(signal.SIGKILL)
        p.wait(10)
        t_kill = time.monotonic()
        p2 = _trainer_process(TRAINER, srv.endpoint, str(ckpt), "0")
        first = None
        for line in p2.stdout:
            if first is None and line.startswith("ids"):
                first = time.monotonic() - t_kill
        rc = p2.wait(120)
        src = _stop(srv)
    ids = json.loads(ckpt.read_text())["ids"]
    return row("trainer SIGKILL, restart from its checkpoint's position", expected, ids, first,
               f"restarted trainer exit {rc}; server exit {src}", client_exit=rc, server_exit=src)


def scenario_server_restart(tmp: Path, layout: Layout, kill_after_batches: int = 2) -> dict:
    """The server killed (SIGKILL) after ``kill_after_batches`` batches and started again on the
    same address: the trainer's iteration asks its unanswered fetches again and reads on."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log: list = []
    srv = _serve(corpus, layout).start()
    srv2 = None
    try:
        it = iter(dataset(srv.endpoint, prefetch=1))
        for b in it:
            log.append((time.monotonic(), real_ids(b)))
            if len(log) >= kill_after_batches:
                break
        srv.proc.send_signal(signal.SIGKILL)
        srv.proc.wait(10)
        t_kill = time.monotonic()
        srv2 = _serve(corpus, layout, "--bind", srv.endpoint).start()
        for b in it:
            log.append((time.monotonic(), real_ids(b)))
        rc = _stop(srv2)
    finally:
        srv.stop()
        if srv2 is not None:
            srv2.stop()
    return row("server SIGKILL + restart, trainer reads on", expected, _ids(log), _next_after(log, t_kill),
               f"the same iteration read on; restarted server exit {rc}", server_exit=rc, clean=_clean(srv2))


def busy_cores(n: int) -> List[subprocess.Popen]:
    """``n`` processes that keep a core busy each (stop them with ``stop_busy``)."""
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def stop_busy(procs: List[subprocess.Popen]) -> None:
    """Kill and reap what ``busy_cores`` started."""
    for p in procs:
        p.kill()
        p.wait(10)


def _state(pid: int) -> str:
    return Path(f"/proc/{pid}/stat").read_text().split(")")[1].split()[0]


def stopped_while_another_reads(endpoint: str, stop: Callable[[subprocess.Popen], List[str]], stopped_s: float,
                                tmp: Path, epochs=(0,), step_s: float = 0.2) -> tuple:
    """Trainer A (a ``TRAINER`` process, steps of ``step_s``) is stopped (SIGSTOP) by
    ``stop(A)``, which returns the ids A printed until then; job B reads ``epochs`` of
    ``endpoint`` meanwhile. After ``stopped_s`` seconds A is resumed (SIGCONT) and reads to its
    end. Returns (the ids A trained on, B's log (``epoch:id``), B's seconds, A's exit)."""
    p = _trainer_process(TRAINER, endpoint, str(tmp / "a.json"), str(step_s))
    log_b: list = []
    try:
        stop(p)
        t0 = time.monotonic()
        b = dataset(endpoint)
        for e in epochs:
            b.set_epoch(e)
            read_all(b, log_b, tag=True)
        b_s = time.monotonic() - t0
        time.sleep(max(0.0, stopped_s - b_s))
        p.send_signal(signal.SIGCONT)
        p.stdout.read()
        rc = p.wait(120)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(10)
    return json.loads((tmp / "a.json").read_text())["ids"], log_b, b_s, rc


def scenario_stopped_trainer(tmp: Path, layout: Layout, stop_s: float = 5.0, where: str = "suspended",
                             busy: int = 0) -> dict:
    """Trainer A is stopped (SIGSTOP) for ``stop_s`` seconds while another job reads the same
    server, with ``busy`` processes keeping the cores busy: ``suspended`` after its first step,
    ``mid-step`` half-way through its second step (its fetches in flight answered meanwhile),
    ``at its yield`` right after a batch came out of the iterator. Woken, A reads its epoch on:
    each of the two jobs reads its epoch exactly once."""
    corpus = good_corpus(tmp, 3 if busy else 2)
    one = expected_ids(corpus, layout)
    hogs = busy_cores(busy)
    try:
        with _serve(corpus, layout) as srv:
            def stop(p):
                want = {"suspended": ("step", 1), "mid-step": ("ids", 2), "at its yield": ("ids", 1)}[where]
                seen = 0
                for line in p.stdout:
                    seen += line.startswith(want[0])
                    if seen == want[1]:
                        break
                if where == "mid-step":
                    time.sleep(0.15)  # half-way through the step of 0.3 s
                p.send_signal(signal.SIGSTOP)
                while _state(p.pid) != "T":
                    time.sleep(0.01)

            ids_a, log_b, _, rc_a = stopped_while_another_reads(srv.endpoint, stop, stop_s, tmp, step_s=0.3)
            rc = _stop(srv)
            clean = _clean(srv)
    finally:
        stop_busy(hogs)
    extra = f", {busy} busy cores" if busy else ""
    what = "suspended" if where == "suspended" else f"frozen {where}"
    return row(f"trainer {what}, {stop_s:.0f} s, while another job reads{extra}",
               per_epoch(one, ["a", 0]), [f"a:{s}" for s in ids_a] + _ids(log_b), None,
               f"the woken trainer exit {rc_a}; the other job read {len(_ids(log_b))}; server exit {rc}",
               a_exit=rc_a, server_exit=rc, clean=clean)


# ---------------------------------------------------------------------------------- bad input
def scenario_bad_corpus(tmp: Path, layout: Layout) -> dict:
    """A corpus holding every kind of bad file (``harness.corpus.make_fault_corpus``), one deleted
    once serving began: each bad file is logged once, every usable sample read once."""
    from harness.corpus import make_fault_corpus

    corpus = tmp / "faulty"
    exp = make_fault_corpus(corpus, GOOD_VIDEOS, layout.L * 5 + 1)
    expected = expected_ids(corpus, layout, exclude={"deleted_during_epoch.mp4"})
    log: list = []
    with _serve(corpus, layout) as srv:
        (corpus / "deleted_during_epoch.mp4").unlink()
        read_all(dataset(srv.endpoint), log)
        rc, clean = _stop(srv), _clean(srv)
        text = srv.log
    skipped = [k for k, v in exp.items() if v == "skipped"]
    lines = text.splitlines()
    logged = [k for k in skipped if sum(f"{corpus / k}" in ln and "skipped" in ln for ln in lines) == 1]
    ignored = [k for k, v in exp.items() if v == "ignored" and f"ignored {corpus / k}:" in text]
    return row("corpus with every kind of bad file", expected, _ids(log), None,
               f"{len(logged)}/{len(skipped)} bad files logged once, "
               f"{len(ignored)}/{sum(v == 'ignored' for v in exp.values())} non-videos logged, server exit {rc}",
               bad_logged_once=len(logged), bad_files=len(skipped), non_videos_logged=len(ignored),
               non_videos=sum(v == 'ignored' for v in exp.values()), server_exit=rc, clean=clean)


def fuzz_messages(rng: random.Random, n: int, plan: dict) -> List[List[bytes]]:
    """Random and mutated client messages of a plan's protocol: garbage, truncated, oversized,
    wrong version, unknown types, bad fields (``plan``: a real plan identity, to mutate), extra frames."""
    fetch = {"type": "fetch", "request": 1, "epoch": 0, "start": 0, "stop": 2, "outputs": ["voxels"], "plan": plan}
    valid = [pack({"type": "plan_ask"}), pack(fetch)]
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
            msg = [pack({**fetch, "v": rng.choice([0, 2, 99, "1", None])})]
        elif k == 4:
            msg = [pack({"type": rng.choice(["hack", "", "rows", "plan", "hello", "ack", "x" * 1000])})]
        elif k == 5:
            msg = [pack({**fetch, rng.choice(["request", "epoch", "start", "stop"]): rng.choice(
                [-1, 2 ** 64 - 1, -2 ** 63, "many", None, 1.5, [1]])})]
        elif k == 6:
            msg = [bytes(base), rng.randbytes(50)]
        elif k == 7:
            msg = [b"\x00" * (20 * 1024 * 1024)]  # over ZMQ_MAXMSGSIZE: the connection is cut
        else:
            msg = [pack({**fetch, "plan": rng.choice([None, {}, {**plan, "seed": "x"}, {**plan, "recipe": 7},
                                                      "plan", {**plan, "shard": [5, 2]}])})]
        out.append(msg)
    return out


def run_fuzzer(endpoint: str, n: int, seconds: float, plan: dict, seed: int = 0) -> int:
    """Send up to ``n`` fuzz messages within ``seconds``, a fresh socket every few; returns the count sent."""
    rng = random.Random(seed)
    ctx = zmq.Context()
    sent = 0
    deadline = time.monotonic() + seconds
    try:
        msgs = fuzz_messages(rng, n, plan)
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
    """A peer sends ``n`` fuzz messages while a trainer reads its epoch: the trainer's epoch is
    whole, each bad message refused (logged a bounded number of times), no traceback."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log: list = []
    with _serve(corpus, layout) as srv:
        ds = dataset(srv.endpoint)
        plan = ds.plan_info().plan.to_dict()
        sent = []
        th = threading.Thread(target=lambda: sent.append(run_fuzzer(srv.endpoint, n, 60.0, plan)), daemon=True)
        th.start()
        read_all(ds, log)
        th.join(90)
        alive = srv.proc.poll() is None
        rc, clean = _stop(srv), _clean(srv)
        logged = srv.log.count("bad message from client")
    return row("fuzzing peer during a normal run", expected, _ids(log), None,
               f"{sent[0] if sent else 0} fuzz messages, {logged} line(s) logged, alive after {alive}, "
               f"traceback {not clean}; server exit {rc}", fuzz_messages=sent[0] if sent else 0,
               logged=logged, alive=alive, server_exit=rc, clean=clean)


def bad_peer_messages(plan: dict) -> List[List[bytes]]:
    """Messages with wrongly typed fields, non-ASCII digits, a nested-msgpack bomb, a deep
    nesting and a flood of garbage."""
    import msgpack

    fetch = {"type": "fetch", "v": PROTOCOL_VERSION, "request": 1, "epoch": 0, "start": 0, "stop": 2,
             "outputs": ["voxels"], "plan": plan}
    bomb = msgpack.packb({**fetch, "outputs": [[[]] * 1000] * 1000})
    deep = b"\x91" * 100000 + b"\xc0"
    return ([[pack({**fetch, "start": "٣"})], [pack({**fetch, "epoch": "١"})], [pack({**fetch, "stop": {"x": 1}})],
             [pack({**fetch, "outputs": "voxels"})], [pack({**fetch, "plan": {**plan, "samples": [1] * 10 ** 5}})],
             [pack({**fetch, "request": 2 ** 64 - 1})], [bomb], [deep]]
            + [[b"\xc1garbage"]] * 2000)


def scenario_bad_peer(tmp: Path, layout: Layout) -> dict:
    """Wrongly-typed fields, non-ASCII digits, a nested-msgpack bomb and a garbage flood from
    peers while a trainer reads: the server stays up, logs a bounded number of lines."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log: list = []
    with _serve(corpus, layout) as srv:
        ds = dataset(srv.endpoint)
        it = iter(ds)
        b = next(it)
        log.append((time.monotonic(), real_ids(b)))
        ctx = zmq.Context()
        msgs = bad_peer_messages(ds.plan_info().plan.to_dict())
        for i, m in enumerate(msgs):
            if i % 50 == 0 or i < 10:
                s = ctx.socket(zmq.DEALER)
                s.setsockopt(zmq.LINGER, 0)
                s.connect(srv.endpoint)
            s.send_multipart(m)
        for b in it:
            log.append((time.monotonic(), real_ids(b)))
        ctx.destroy(0)
        rc, clean = _stop(srv), _clean(srv)
        lines = srv.log.count("bad message from client")
    return row("malformed, mistyped and bomb messages + 2000 garbage", expected, _ids(log), None,
               f"{len(msgs)} bad messages, {lines} log line(s), traceback {not clean}; server exit {rc}",
               bad_messages=len(msgs), log_lines=lines, traceback=not clean, server_exit=rc)


def scenario_undecodable_name(tmp: Path, layout: Layout) -> dict:
    """A clip whose file name is not valid UTF-8 (bytes ``caf\\xe9``, a Latin-1 name) beside good
    ones: it is ignored with one log line naming it (escaped), the others are served."""
    corpus = good_corpus(tmp, 1)
    expected = expected_ids(corpus, layout)
    bad = os.fsdecode(bytes(corpus) + b"/caf\xe9.mp4")
    shutil.copy(next(corpus.glob("*.mp4")), bad)
    log: list = []
    with _serve(corpus, layout) as srv:
        read_all(dataset(srv.endpoint), log)
        rc, clean = _stop(srv), _clean(srv)
        logged = srv.log.count("caf\\xe9.mp4: file name is not valid UTF-8")
    return row("a file name that is not valid UTF-8", expected, _ids(log), None,
               f"ignored and logged {logged}x; server exit {rc}; traceback {not clean}",
               logged=logged, server_exit=rc, traceback=not clean)


def scenario_partial_file(tmp: Path, layout: Layout, epochs: int = 2) -> dict:
    """A clip whose frame size changes inside window 1: that window's position is padding in each
    epoch (``--check`` says it cannot be made) and the file's other windows are read in every
    epoch. Windows at k x stride (``shot_cuts: off``): the shot detector takes a change of frame
    size for a cut, and under ``avoid`` no window would hold it."""
    from harness.corpus import write_size_change_video

    layout = Layout(layout.L, layout.crop, 3, layout.batch, "off")  # three windows: the middle one fails
    corpus = good_corpus(tmp, 1)
    span = layout.L * 5 + 1
    write_size_change_video(corpus / "size_change.mpg", span + span // 2, 2 * span)
    expected = per_epoch(expected_ids(corpus, layout), range(epochs))
    log: list = []
    with _serve(corpus, layout) as srv:
        ds = dataset(srv.endpoint)
        for e in range(epochs):
            ds.set_epoch(e)
            read_all(ds, log, tag=True)
        rc, clean = _stop(srv), _clean(srv)
        logged = srv.log.count("frame size changed")
    got = _ids(log)
    windows = [sum(1 for s in got if s.startswith(f"{e}:size_change.mpg#")) for e in range(epochs)]
    return row(f"clip changes frame size in window 1, {epochs} epochs", expected, got, None,
               f"size_change.mpg windows read per epoch {windows}; failure logged {logged}x; server exit {rc}",
               windows_per_epoch=windows, failure_logged=logged, server_exit=rc, clean=clean)


# ---------------------------------------------------------------------------------- loops
def scenario_break_loop(tmp: Path, layout: Layout, breaks: int = 4) -> dict:
    """A trainer takes a batch and ``break``s out of its loop (max_steps, a validation pass),
    ``breaks`` times, each time iterating again from the last batch's position, then reads to
    the end: each sample once. An iteration left behind holds nothing the next one waits for."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log: list = []
    with _serve(corpus, layout) as srv:
        ds = dataset(srv.endpoint)
        for _ in range(breaks):
            for b in ds:
                log.append((time.monotonic(), real_ids(b)))
                ds.load_state_dict(b["position"])
                break
        read_all(ds, log)
        rc, clean = _stop(srv), _clean(srv)
    return row(f"trainer breaks out of its loop x{breaks}, iterates again from its position", expected, _ids(log),
               None, f"{breaks + 1} iterations; server exit {rc}", server_exit=rc, clean=clean)


def scenario_old_checkpoint(tmp: Path, layout: Layout, ckpt_step: int = 2) -> dict:
    """Checkpoint at step k, crash after step k + 1, restart from the step-k checkpoint: the
    samples of step k + 1 are read again, the same rows (a position names them), and what the
    restored model has seen is each sample once."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    kept: list = []  # what the restored model has seen
    with _serve(corpus, layout) as srv:
        ds = dataset(srv.endpoint)
        position = read_all(ds, kept, stop_after=ckpt_step)
        lost: list = []
        it = iter(ds)
        for _ in range(ckpt_step + 1):  # the crashed process read on past its checkpoint
            b = next(it)
        lost.append((time.monotonic(), real_ids(b)))
        del it
        again = dataset(srv.endpoint)
        again.load_state_dict(position)
        n = len(kept)
        read_all(again, kept)
        rc, clean = _stop(srv), _clean(srv)
    same = kept[n][1] == lost[0][1]
    return row(f"restart from a checkpoint older than the last step (step {ckpt_step} of {ckpt_step + 1})",
               expected, _ids(kept), None, f"{len(_ids(lost))} sample(s) of the lost step read again, the same "
               f"rows {same}; server exit {rc}", resent=len(_ids(lost)), same_rows=same, server_exit=rc,
               clean=clean)


def _ready(port: int) -> bool:
    """Whether the server's ``/readyz`` answers 200 (a worker said it is ready)."""
    import urllib.error
    import urllib.request

    try:
        return urllib.request.urlopen(f"http://127.0.0.1:{port}/readyz", timeout=5).status == 200
    except urllib.error.HTTPError:
        return False


def scenario_hung_worker(tmp: Path, layout: Layout, task_timeout_s: float = 3.0, client_timeout_s: float = 15.0,
                        copies: int = 2) -> dict:
    """The only worker, ready and idle, is stopped (SIGSTOP) before the trainer's first fetch: the
    first task goes to it, it says nothing, and after the task timeout the task is given to a new
    worker; the trainer reads on. A plan server says nothing while it makes rows, so the trainer's
    ``client_timeout_s`` is above the task timeout and a worker's start. (A worker stopped before
    it said it is ready is replaced ``worker_side.START_S`` after its start:
    ``tests/test_stream.py``.)"""
    corpus = good_corpus(tmp, copies)
    expected = expected_ids(corpus, layout)
    log: list = []
    err = None
    port = free_port()
    with _serve(corpus, layout, "--task-timeout", str(task_timeout_s), "--metrics-port", str(port), workers=1) as srv:
        deadline = time.monotonic() + 60
        while not _ready(port) and time.monotonic() < deadline:
            time.sleep(0.05)
        stopped = worker_pids(srv.proc.pid)[:1]
        for pid in stopped:
            os.kill(pid, signal.SIGSTOP)
        t_stop = time.monotonic()
        try:
            read_all(dataset(srv.endpoint, timeout_s=client_timeout_s), log)
        except Exception as e:  # noqa: BLE001 - reported in the row
            err = f"{type(e).__name__}: {e}"
        finally:
            for pid in stopped:
                try:
                    os.kill(pid, signal.SIGCONT)
                except OSError:
                    pass
        rc, clean = _stop(srv), _clean(srv)
        timeouts = srv.log.count("task reassigned")
    return row(f"worker stopped with a task (task timeout {task_timeout_s:.0f} s, trainer timeout "
               f"{client_timeout_s:.0f} s)", expected, _ids(log), _next_after(log, t_stop),
               f"{timeouts} task timeout(s); trainer error: {err or 'none'}; server exit {rc}",
               task_timeouts=timeouts, trainer_error=err, server_exit=rc, clean=clean)


SCENARIOS = {
    "worker_kill": scenario_worker_kill,
    "client_kill": scenario_client_kill,
    "server_restart": scenario_server_restart,
    "suspended_trainer": scenario_stopped_trainer,
    "frozen_mid_step": lambda tmp, layout: scenario_stopped_trainer(tmp, layout, where="mid-step", busy=2),
    "frozen_at_yield": lambda tmp, layout: scenario_stopped_trainer(tmp, layout, where="at its yield", busy=2),
    "bad_corpus": scenario_bad_corpus,
    "fuzzing_peer": scenario_fuzzing_peer,
    "bad_peer": scenario_bad_peer,
    "undecodable_name": scenario_undecodable_name,
    "partial_file": scenario_partial_file,
    "break_loop": scenario_break_loop,
    "old_checkpoint": scenario_old_checkpoint,
    "hung_worker": scenario_hung_worker,
}

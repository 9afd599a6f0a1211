"""Fault scenarios of the deployed topology (shards behind a fan-in, shared memory in
containers, other PID namespaces, IPv6, metrics scrapes) against real ``v2v-serve`` processes
on the loopback interface. Same row format as ``harness/faults.py``; ``python -m bench.faults``
runs both sets, ``tests/test_faults_deploy.py`` runs them short.
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import List, Optional

from harness.faults import Layout, _ids, _serve, _take, expected_ids, good_corpus, read_all, row
from harness.serve import ServeProcess, free_port
from harness.train_recorder import trained_until
from v2v_client import StreamError, V2VPushDataset


def private_tmpfs(size: str, mount_at: Path) -> Optional[List[str]]:
    """A command prefix that runs a program with a private tmpfs of ``size`` mounted at
    ``mount_at`` (``unshare -m``: its own mount namespace), or None where this machine does
    not permit it."""
    mount_at.mkdir(parents=True, exist_ok=True)
    wrap = ["unshare", "-m", "sh", "-c", f'mount -t tmpfs -o size={size} tmpfs "$0" && exec "$@"', str(mount_at)]
    try:
        ok = subprocess.run([*wrap, "true"], capture_output=True, timeout=30).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        ok = False
    return wrap if ok else None


def scenario_small_shm(tmp: Path, layout: Layout, size: str = "1m") -> dict:
    """The server's shared memory (``V2V_SHM_DIR``) is a tmpfs of ``size`` (Docker's default
    /dev/shm is 64 MiB): slot rings reserve their pages when made, so one that does not fit
    is refused at start with a log line (workers send arrays over the socket) instead of a
    worker dying of SIGBUS at a later write."""
    shm = tmp / "shm"
    wrap = private_tmpfs(size, shm)
    if wrap is None:
        return {"skipped": "unshare -m / mount -t tmpfs not permitted here"}
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log: list = []
    srv = _serve(corpus, layout, "--epochs", "1", env={"V2V_SHM_DIR": str(shm)}, wrap=wrap).start()
    try:
        read_all(V2VPushDataset(srv.endpoint, timeout_s=60), log)
        rc = srv.wait(60)
    finally:
        srv.stop()
    text = srv.log
    fallback = text.count("no shared-memory slot ring")
    restarts = text.count("died (exit code")
    return row(f"/dev/shm of {size} (a private tmpfs, unshare -m)", expected, _ids(log), None,
               f"rings refused at start {fallback}x; worker deaths {restarts}; server exit {rc}",
               rings_refused=fallback, worker_deaths=restarts, server_exit=rc)



def _two_shards(corpus: Path, layout: Layout, *extra: str, shards=("0/2", "1/2")):
    base = ["--videos", str(corpus), "--workers", "1", *layout.args(), *extra]
    return ServeProcess(base + ["--shard", shards[0]]), ServeProcess(base + ["--shard", shards[1]])


def scenario_fan_in_resume(tmp: Path, layout: Layout, ckpt_step: int = 2, crash_step: int = 5) -> dict:
    """A trainer reads two shards through the fan-in, checkpoints at step ``ckpt_step``, reads on
    to ``crash_step`` (acknowledged), dies and resumes from the checkpoint: the fan-in is one
    consumer to both servers, so each sends again what came after the checkpoint."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    trained: list = []
    a, b = _two_shards(corpus, layout, "--epochs", "1", "--end-grace-s", "10")
    with a, b:
        ds = V2VPushDataset(f"{a.endpoint},{b.endpoint}", timeout_s=60, credits=2)
        it = iter(ds)
        _take(it, ckpt_step, trained)
        state = json.loads(json.dumps(ds.state_dict()))
        _take(it, crash_step - ckpt_step, [])  # trained on, then lost with the process
        it.close()
        again = V2VPushDataset(f"{a.endpoint},{b.endpoint}", timeout_s=60, credits=2)
        again.load_state_dict(state)
        read_all(again, trained)
        rc = (a.wait(60), b.wait(60))
    return row(f"two shards, fan-in resumed from step {ckpt_step} after dying at step {crash_step}", expected,
               _ids(trained), None, f"server exits {list(rc)}", server_exits=list(rc))


def scenario_mismatched_shards(tmp: Path, layout: Layout) -> dict:
    """Servers that are not one sharding (0/2 + 1/3, the same shard twice, a missing shard,
    listings one file apart, another seed): the fan-in refuses each with one error naming the
    servers, before handing on any batch."""
    corpus = good_corpus(tmp, 1)
    other = tmp / "other"
    shutil.copytree(corpus, other)
    next(other.glob("*.mp4")).unlink()
    cases = ((("0/2", "1/3"), corpus, []), (("0/2", "0/2"), corpus, []), (("0/3", "1/3"), corpus, []),
             (("0/2", "1/2"), other, []), (("0/2", "1/2"), corpus, ["--seed", "12"]))
    refused, handed = [], 0
    for shards, root2, extra in cases:
        a = _serve(corpus, layout, "--shard", shards[0], workers=1)
        b = _serve(root2, layout, *extra, "--shard", shards[1], workers=1)
        with a, b:
            try:
                for _ in V2VPushDataset(f"{a.endpoint},{b.endpoint}", outputs=("voxels",), timeout_s=60):
                    handed += 1
                    break
            except (ValueError, StreamError) as e:
                refused.append(a.endpoint in str(e) and b.endpoint in str(e))
    n = len(cases)
    return row(f"fan-in over servers that are not one sharding or one recipe ({n} cases)", [], [], None,
               f"refused {len(refused)} of {n} with both servers named: {all(refused)}; batches handed on {handed}",
               refused=len(refused), cases=n, named=all(refused), handed=handed)


def scenario_resume_other_recipe(tmp: Path, layout: Layout) -> dict:
    """A ``state_dict()`` saved against one recipe, loaded against a server of another seed,
    sequence length or crops per window: a clear error naming both recipes, no batch handed on."""
    corpus = good_corpus(tmp, 1)
    with _serve(corpus, layout) as srv:
        ds = V2VPushDataset(srv.endpoint, outputs=("voxels",), timeout_s=60)
        next(iter(ds))
        state = json.loads(json.dumps(ds.state_dict()))
    changes = (["--seed", "12"], ["--sequence-length", str(layout.L + 2)], ["--crops-per-window", "2"])
    refused, handed = 0, 0
    for change in changes:
        with _serve(corpus, layout, *change) as srv:
            again = V2VPushDataset(srv.endpoint, outputs=("voxels",), timeout_s=60)
            again.load_state_dict(state)
            try:
                next(iter(again))
                handed += 1
            except StreamError as e:
                refused += "another sample recipe" in str(e)
    return row("resume under another recipe (seed, sequence length, crops per window)", [], [], None,
               f"refused {refused} of {len(changes)} with a clear error; batches handed on {handed}",
               refused=refused, cases=len(changes), handed=handed)


def scenario_big_resume_state(tmp: Path, layout: Layout) -> dict:
    """A resume state of 700 k sample ids (70 k videos of 10 windows) is sent grouped per video and
    read; one of 700 k ids of 700 k different videos is over the limit: a clear error on the
    client, in place of a silent drop and a wait without end."""
    corpus = good_corpus(tmp, 1)
    many = [f"elsewhere/v{i:05d}.mp4#{w}" for i in range(70_000) for w in range(10)]
    huge = [f"elsewhere/a-long-folder-name/and-a-longer-file-name-{i:07d}.mp4#0" for i in range(700_000)]
    with _serve(corpus, layout) as srv:
        ds = V2VPushDataset(srv.endpoint, outputs=("voxels",), timeout_s=60)
        ds.load_state_dict({"version": 1, "completed_epoch": -1, "delivered": {"0": many}})
        t0 = time.monotonic()
        served = next(iter(ds))["voxels"].shape[0] > 0
        t_many = time.monotonic() - t0
        ds2 = V2VPushDataset(srv.endpoint, outputs=("voxels",), timeout_s=60)
        ds2.load_state_dict({"version": 1, "completed_epoch": -1, "delivered": {"0": huge}})
        t0 = time.monotonic()
        try:
            next(iter(ds2))
            error = None
        except StreamError as e:
            error = str(e)
        t_huge = time.monotonic() - t0
    clear = error is not None and "too large" in error
    return row("resume states of 700 k ids", [], [], None,
               f"70 k videos: served after {t_many:.1f} s; 700 k videos: clear error {clear} after {t_huge:.1f} s",
               served=served, clear_error=clear)


def pid_namespace() -> Optional[List[str]]:
    """A command prefix that runs a program as PID 1 of a new PID namespace (``unshare -p -f
    --mount-proc``; its pid means nothing outside, as in a container), or None where this
    machine does not permit it."""
    wrap = ["unshare", "-p", "-f", "--mount-proc", "--kill-child"]
    try:
        ok = shutil.which("unshare") and subprocess.run([*wrap, "true"], capture_output=True, timeout=30).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        ok = False
    return wrap if ok else None


@contextlib.contextmanager
def counting_shm_reads():
    """Counts the batches this process reads through the shared-memory hand-off (a list that
    grows by one per read)."""
    from v2v_client import handoff

    reads: list = []
    real = handoff.ShmReader.read
    handoff.ShmReader.read = lambda self, h, copy=True: reads.append(1) or real(self, h, copy)
    try:
        yield reads
    finally:
        handoff.ShmReader.read = real


def _batch_dirs(root: Path) -> List[str]:
    return sorted(p.name for p in root.iterdir() if p.name.startswith("v2v-batches-"))


def scenario_train_killed_two_shards(tmp: Path, layout: Layout, checkpoint_every: int = 2,
                                     kill_after: int = 5) -> dict:
    """``v2v-train`` reads two shards (the compose/Kubernetes topology), checkpoints every
    ``checkpoint_every`` steps and is killed with SIGKILL once step ``kill_after`` is done (it
    sends the signal itself, so the step is known: ``harness.train_recorder``);
    ``--resume auto`` then trains to the end of the epoch. What the model learnt is the steps up
    to the checkpoint it resumed from plus the resumed run: each sample exactly once."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    out, rec1, rec2 = tmp / "run", tmp / "killed.jsonl", tmp / "resumed.jsonl"
    # a shard that finished its epoch waits this long for the resumed trainer (v2v-train starts in ~10 s)
    a, b = _two_shards(corpus, layout, "--epochs", "1", "--end-grace-s", "25")
    with a, b:
        common = ["--task", "e2vid", "--connect", f"{a.endpoint},{b.endpoint}", "--out", str(out), "--device", "cpu",
                  "--no-progress", "--set", "model.base_num_channels=4", "--set", "stream.timeout_s=60",
                  "--set", "log.image_every=1000", "--set", f"log.checkpoint_every={checkpoint_every}"]
        proc = subprocess.Popen([sys.executable, "-m", "harness.train_recorder", str(rec1), *common,
                                 "--max-steps", "1000"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                 env=dict(os.environ, V2V_SIGKILL_AFTER_STEP=str(kill_after)))
        try:
            proc.wait(300)
        except subprocess.TimeoutExpired:
            proc.kill()
        err = proc.communicate()[1]
        import torch

        ck_step = int(torch.load(out / "checkpoint_last.pt", weights_only=False)["step"])
        r = subprocess.run([sys.executable, "-m", "harness.train_recorder", str(rec2), *common, "--max-steps", "1000",
                            "--resume", "auto"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                           timeout=600)
        rc = (a.wait(90), b.wait(90))
    killed_steps = max((json.loads(x)["step"] for x in rec1.read_text().splitlines()), default=0)
    trained = [s for e, s in trained_until(str(rec1), ck_step) + trained_until(str(rec2), 10 ** 9) if e == 0]
    notes = (f"killed after step {killed_steps} (exit {proc.returncode}), resumed from the step-{ck_step} checkpoint; "
             f"resumed run exit {r.returncode}; server exits {list(rc)}")
    return row("v2v-train SIGKILL against two shards, --resume auto", expected, trained, None, notes,
               killed_after=killed_steps, checkpoint_step=ck_step, kill_exit=proc.returncode,
               resumed_exit=r.returncode, server_exits=list(rc), stderr=(err + r.stderr)[-2000:])


def scenario_second_server_pid_namespace(tmp: Path, layout: Layout) -> dict:
    """Two servers share one shared-memory directory (containers with ``--ipc=host``), the
    second started as PID 1 of its own PID namespace while a trainer reads the first through
    the hand-off: the second's start-up cleanup leaves the first's live batch directory alone
    (a live server holds an flock; no pid is trusted), and both epochs arrive exactly once
    through shared memory."""
    wrap = pid_namespace()
    if wrap is None:
        return {"skipped": "unshare -p is not permitted here"}
    shm = tmp / "shm"
    shm.mkdir()
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    env = {"V2V_SHM_DIR": str(shm)}
    base = ["--videos", str(corpus), "--workers", "1", "--epochs", "1", *layout.args()]
    got_a: list = []
    got_b: list = []
    with tempfile.TemporaryDirectory(prefix="v2v-ipc-") as d, counting_shm_reads() as reads:
        with ServeProcess(base + ["--bind", f"ipc://{d}/a.sock"], env=env) as a:
            it = iter(V2VPushDataset(a.endpoint, timeout_s=60, shm=True))
            _take(it, 1, got_a)  # a's batch directory is in use
            before = _batch_dirs(shm)
            with ServeProcess(base + ["--bind", f"ipc://{d}/b.sock"], env=env, wrap=wrap) as b:
                during = _batch_dirs(shm)
                for batch in it:
                    got_a.append((time.monotonic(), list(batch["sample_ids"])))
                reads_a = len(reads)
                read_all(V2VPushDataset(b.endpoint, timeout_s=60, shm=True), got_b)
                rc_b = b.wait(60)
            rc_a = a.wait(60)
        left = _batch_dirs(shm)
    kept = set(before) <= set(during) and len(during) == len(before) + 1
    ids_a, ids_b = _ids(got_a), _ids(got_b)
    both_once = sorted(ids_b) == sorted(set(ids_b)) == sorted(expected)
    return row("a second server as PID 1 of its own PID namespace, one shared-memory directory", expected, ids_a,
               None, f"first server's batch directory kept: {kept}; reads through shared memory {reads_a} + "
               f"{len(reads) - reads_a}; second server's epoch exactly once: {both_once}; directories left "
               f"{len(left)}; server exits [{rc_a}, {rc_b}]",
               kept=kept, shm_reads=[reads_a, len(reads) - reads_a], second_exactly_once=both_once,
               left=left, server_exits=[rc_a, rc_b])


def scenario_symlinked_shm(tmp: Path, layout: Layout) -> dict:
    """The server's shared-memory directory is reached through a symbolic link (one planted in
    a shared /dev/shm): the client refuses to read batches through it, says hello again without
    the hand-off and receives the epoch over the socket, exactly once."""
    real, link = tmp / "shm-real", tmp / "shm-link"
    real.mkdir()
    os.symlink(real, link)
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log: list = []
    with tempfile.TemporaryDirectory(prefix="v2v-ipc-") as d, counting_shm_reads() as reads:
        with _serve(corpus, layout, "--epochs", "1", "--bind", f"ipc://{d}/s.sock",
                    env={"V2V_SHM_DIR": str(link)}) as srv:
            read_all(V2VPushDataset(srv.endpoint, timeout_s=60, shm=True), log)
            rc = srv.wait(60)
    return row("batch directory behind a symbolic link", expected, _ids(log), None,
               f"reads through shared memory {len(reads)}; server exit {rc}", shm_reads=len(reads), server_exit=rc)


def scenario_ipv6(tmp: Path, layout: Layout) -> dict:
    """Server bound to ``tcp://[::1]:PORT``, a trainer connecting to it: zmq.IPV6 on both ends."""
    try:
        with socket.socket(socket.AF_INET6) as s:
            s.bind(("::1", 0))
            port = s.getsockname()[1]
    except OSError as e:
        return {"skipped": f"no IPv6 loopback here ({e})"}
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log: list = []
    endpoint = f"tcp://[::1]:{port}"
    with _serve(corpus, layout, "--epochs", "1", "--bind", endpoint) as srv:
        read_all(V2VPushDataset(endpoint, timeout_s=60), log)
        rc = srv.wait(60)
    return row("IPv6: server and trainer on tcp://[::1]", expected, _ids(log), None, f"server exit {rc}",
               server_exit=rc)


SCRAPER = """
import sys, time, urllib.request
url, rate = sys.argv[1], float(sys.argv[2])
n, errors, t0 = 0, 0, time.monotonic()
while True:
    try:
        urllib.request.urlopen(url, timeout=5).read()
    except OSError:
        errors += 1
    n += 1
    print(n, errors, flush=True)
    time.sleep(max(0.0, t0 + n / rate - time.monotonic()))
"""


def scenario_scrape_storm(tmp: Path, layout: Layout, rate: float = 200.0) -> dict:
    """A trainer reads an epoch while another process fetches ``/metrics`` ``rate`` times a
    second: every scrape answered, every sample once (the cost in batches/s: bench.scrape_storm)."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    port = free_port()
    log: list = []
    with _serve(corpus, layout, "--epochs", "1", "--metrics-port", str(port)) as srv:
        scraper = subprocess.Popen([sys.executable, "-c", SCRAPER, f"http://127.0.0.1:{port}/metrics", str(rate)],
                                   stdout=subprocess.PIPE, text=True)
        t0 = time.monotonic()
        try:
            read_all(V2VPushDataset(srv.endpoint, timeout_s=60), log)
        finally:
            wall = time.monotonic() - t0
            scraper.kill()
            lines = scraper.communicate()[0].split()
        rc = srv.wait(60)
    scrapes, errors = (int(lines[-2]), int(lines[-1])) if len(lines) >= 2 else (0, 0)
    return row(f"{rate:.0f} scrapes of /metrics a second during the epoch", expected, _ids(log), None,
               f"{scrapes} scrapes in {wall:.1f} s, {errors} failed; server exit {rc}",
               scrapes=scrapes, scrape_errors=errors, seconds=wall, server_exit=rc)


SCENARIOS = {
    "small_shm_1m": lambda tmp, layout: scenario_small_shm(tmp, layout, "1m"),
    "small_shm_64m": lambda tmp, layout: scenario_small_shm(tmp, layout, "64m"),
    "second_server_pid_namespace": scenario_second_server_pid_namespace,
    "symlinked_shm": scenario_symlinked_shm,
    "fan_in_resume": scenario_fan_in_resume,
    "train_killed_two_shards": scenario_train_killed_two_shards,
    "mismatched_shards": scenario_mismatched_shards,
    "resume_other_recipe": scenario_resume_other_recipe,
    "big_resume_state": scenario_big_resume_state,
    "ipv6": scenario_ipv6,
    "scrape_storm": scenario_scrape_storm,
}

"""Fault scenarios of the deployed topology (shards read as one plan, shared memory in
containers, other PID namespaces, IPv6, metrics scrapes) against real ``v2v-serve`` processes
serving by plan on the loopback interface, read by ``V2VStreamDataset``. Same row format as
``harness/faults.py``; ``python -m bench.faults`` runs them, ``tests/test_faults_deploy.py`` runs
them short.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import List, Optional

from harness.faults import (Layout, _clean, _ids, _serve, _stop, dataset, expected_ids, good_corpus, read_all,
                            real_ids, row)
from harness.serve import free_port
from harness.train_recorder import trained_until
from v2v_wire.plan import PlanMismatch


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
    """The server's shared memory (``V2V_SHM_DIR``, where its workers' slot rings live) is a tmpfs
    of ``size`` (Docker's default /dev/shm is 64 MiB): slot rings reserve their pages when made, so
    one that does not fit is refused at start with a log line (workers send arrays over the
    socket) instead of a worker dying of SIGBUS at a later write."""
    shm = tmp / "shm"
    wrap = private_tmpfs(size, shm)
    if wrap is None:
        return {"skipped": "unshare -m / mount -t tmpfs not permitted here"}
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log: list = []
    with _serve(corpus, layout, env={"V2V_SHM_DIR": str(shm)}, wrap=wrap) as srv:
        read_all(dataset(srv.endpoint), log)
        rc, clean = _stop(srv), _clean(srv)
    text = srv.log
    fallback = text.count("no shared-memory slot ring")
    restarts = text.count("died (exit code")
    return row(f"/dev/shm of {size} (a private tmpfs, unshare -m)", expected, _ids(log), None,
               f"rings refused at start {fallback}x; worker deaths {restarts}; server exit {rc}",
               rings_refused=fallback, worker_deaths=restarts, server_exit=rc, clean=clean)


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


def scenario_second_server_pid_namespace(tmp: Path, layout: Layout) -> dict:
    """Two servers share one shared-memory directory (containers with ``--ipc=host``), the
    second started as PID 1 of its own PID namespace while a trainer reads the first: the
    second's start-up sweep of dead servers' files leaves the first's workers alone (a live
    server holds an flock; no pid is trusted): both epochs are read exactly once, no worker of
    the first dies, nothing is left in the directory."""
    wrap = pid_namespace()
    if wrap is None:
        return {"skipped": "unshare -p is not permitted here"}
    shm = tmp / "shm"
    shm.mkdir()
    corpus = good_corpus(tmp, 2)
    one = expected_ids(corpus, layout)
    env = {"V2V_SHM_DIR": str(shm)}
    log: list = []
    with _serve(corpus, layout, workers=1, env=env) as a:
        it = iter(dataset(a.endpoint))
        b0 = next(it)
        log.append((time.monotonic(), [f"a:{s}" for s in real_ids(b0)]))
        with _serve(corpus, layout, workers=1, env=env, wrap=wrap) as b:
            for batch in it:
                log.append((time.monotonic(), [f"a:{s}" for s in real_ids(batch)]))
            read_all(dataset(b.endpoint), log, tag=True)
            rc_b = _stop_namespaced(b)
        rc_a = _stop(a)
    deaths = a.log.count("died (exit code")
    left = sorted(os.listdir(shm))
    return row("a second server as PID 1 of its own PID namespace, one shared-memory directory",
               [f"{e}:{s}" for e in ("a", 0) for s in one], _ids(log), None,
               f"first server's worker deaths {deaths}; files left {len(left)}; server exits [{rc_a}, {rc_b}]",
               worker_deaths=deaths, left=left, server_exits=[rc_a, rc_b], clean=_clean(a) and _clean(b))


def _stop_namespaced(srv) -> int:
    """Stop a server started under ``pid_namespace()``: SIGINT to the server (the wrapper's
    child, PID 1 of the namespace; the wrapper passes on no signal), its exit code through the wrapper."""
    for kid in Path(f"/proc/{srv.proc.pid}/task/{srv.proc.pid}/children").read_text().split():
        os.kill(int(kid), signal.SIGINT)
    try:
        srv.proc.wait(30)
    except subprocess.TimeoutExpired:
        pass
    return srv.stop()


def _two_shards(corpus: Path, layout: Layout, *extra: str, shards=("0/2", "1/2")):
    return (_serve(corpus, layout, *extra, "--shard", shards[0], workers=1),
            _serve(corpus, layout, *extra, "--shard", shards[1], workers=1))


def scenario_fan_in_resume(tmp: Path, layout: Layout, ckpt_step: int = 2, crash_step: int = 5) -> dict:
    """A trainer reads two shards as one plan, checkpoints (the position) at step ``ckpt_step``,
    reads on to ``crash_step``, dies, and a new reader resumes from the checkpoint: what the model
    kept is each sample once, and the steps after the checkpoint are read again."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    trained: list = []
    a, b = _two_shards(corpus, layout)
    with a, b:
        endpoints = f"{a.endpoint},{b.endpoint}"
        ds = dataset(endpoints)
        position = json.loads(json.dumps(read_all(ds, trained, stop_after=ckpt_step)))
        lost: list = []
        read_all(dataset(endpoints, ), lost, stop_after=crash_step)  # the run that died: its steps past the checkpoint are lost
        again = dataset(endpoints)
        again.load_state_dict(position)
        read_all(again, trained)
        rc = [_stop(a), _stop(b)]
        clean = _clean(a) and _clean(b)
    again_read = len(set(_ids(lost[ckpt_step:])) & set(_ids(trained)))
    return row(f"two shards, resumed from step {ckpt_step}'s position after dying at step {crash_step}", expected,
               _ids(trained), None, f"{again_read} sample(s) of the lost steps read again; server exits {rc}",
               read_again=again_read, server_exits=rc, clean=clean)


def scenario_mismatched_shards(tmp: Path, layout: Layout) -> dict:
    """Servers that are not one sharding (0/2 + 1/3, the same shard twice, a missing shard,
    listings one file apart, another seed): the reader refuses each with one error naming the
    servers, before yielding any batch."""
    corpus = good_corpus(tmp, 1)
    other = tmp / "other"
    shutil.copytree(corpus, other)
    next(other.glob("*.mp4")).unlink()
    cases = ((("0/2", "1/3"), corpus, []), (("0/2", "0/2"), corpus, []), (("0/3", "1/3"), corpus, []),
             (("0/2", "1/2"), other, []), (("0/2", "1/2"), corpus, ["--seed", "12"]))
    refused, handed, errors = [], 0, []
    for shards, root2, extra in cases:
        a = _serve(corpus, layout, "--shard", shards[0], workers=1)
        b = _serve(root2, layout, *extra, "--shard", shards[1], workers=1)
        with a, b:
            try:
                for _ in dataset(f"{a.endpoint},{b.endpoint}", outputs=("voxels",), timeout_s=60):
                    handed += 1
                    break
            except Exception as e:  # noqa: BLE001 - the row reports what it was
                refused.append(a.endpoint in str(e) and b.endpoint in str(e))
                errors.append(f"{type(e).__name__}: {str(e).splitlines()[0][:200]}")
    n = len(cases)
    return row(f"fan-in over servers that are not one sharding or one recipe ({n} cases)", [], [], None,
               f"refused {len(refused)} of {n} with both servers named: {all(refused)}; batches yielded {handed}",
               refused=len(refused), cases=n, named=all(refused), handed=handed, errors=errors)


def scenario_resume_other_recipe(tmp: Path, layout: Layout) -> dict:
    """A position saved against one recipe, loaded against a server of another seed, sequence
    length or crops per window: a ``PlanMismatch`` naming what differs, no batch yielded."""
    corpus = good_corpus(tmp, 1)
    with _serve(corpus, layout) as srv:
        position = json.loads(json.dumps(read_all(dataset(srv.endpoint, outputs=("voxels",)), [], stop_after=1)))
        _stop(srv)
    changes = (["--seed", "12"], ["--sequence-length", str(layout.L + 2)], ["--crops-per-window", "2"])
    refused, handed, errors = 0, 0, []
    for change in changes:
        with _serve(corpus, layout, *change) as srv:
            again = dataset(srv.endpoint, outputs=("voxels",), timeout_s=60)
            try:
                again.load_state_dict(position)
                next(iter(again))
                handed += 1
            except PlanMismatch as e:
                refused += "\n" not in str(e)
                errors.append(str(e)[:200])
    return row("resume under another recipe (seed, sequence length, crops per window)", [], [], None,
               f"refused {refused} of {len(changes)} in one line (PlanMismatch); batches yielded {handed}",
               refused=refused, cases=len(changes), handed=handed, errors=errors)


def scenario_train_killed_two_shards(tmp: Path, layout: Layout, checkpoint_every: int = 2,
                                     kill_after: int = 5) -> dict:
    """``v2v-train`` reads two shards (the compose/Kubernetes topology), checkpoints every
    ``checkpoint_every`` steps and is killed with SIGKILL once step ``kill_after`` is done (it
    sends the signal itself, so the step is known: ``harness.train_recorder``);
    ``--resume auto`` then trains to the end of epoch 0 (``--max-steps``: its steps, counted by
    a reader first). What the model
    learnt is the steps up to the checkpoint it resumed from plus the resumed run: each sample
    exactly once."""
    import torch

    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    out, rec1, rec2 = tmp / "run", tmp / "killed.jsonl", tmp / "resumed.jsonl"
    a, b = _two_shards(corpus, layout)
    with a, b:
        steps: list = []  # epoch 0's steps: shards of unequal size pad the shorter one's positions
        read_all(dataset(f"{a.endpoint},{b.endpoint}", batch_size=layout.batch, outputs=("voxels",)), steps)
        common = ["--task", "e2vid", "--connect", f"{a.endpoint},{b.endpoint}", "--out", str(out), "--device", "cpu",
                  "--no-progress", "--set", "model.base_num_channels=4", "--set", "stream.timeout_s=60",
                  "--set", "log.image_every=1000", "--set", f"log.checkpoint_every={checkpoint_every}",
                  "--max-steps", str(len(steps))]
        proc = subprocess.Popen([sys.executable, "-m", "harness.train_recorder", str(rec1), *common],
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                env=dict(os.environ, V2V_SIGKILL_AFTER_STEP=str(kill_after)))
        try:
            proc.wait(300)
        except subprocess.TimeoutExpired:
            proc.kill()
        err = proc.communicate()[1]
        ck_step = int(torch.load(out / "checkpoint_last.pt", weights_only=False)["step"])
        r = subprocess.run([sys.executable, "-m", "harness.train_recorder", str(rec2), *common, "--resume", "auto"],
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, timeout=600)
        rc = [_stop(a), _stop(b)]
    killed_steps = max((json.loads(x)["step"] for x in rec1.read_text().splitlines()), default=0)
    trained = [s for e, s in trained_until(str(rec1), ck_step) + trained_until(str(rec2), 10 ** 9) if e == 0]
    notes = (f"killed after step {killed_steps} (exit {proc.returncode}), resumed from the step-{ck_step} checkpoint; "
             f"resumed run exit {r.returncode}; server exits {rc}")
    return row("v2v-train SIGKILL against two shards, --resume auto", expected, trained, None, notes,
               killed_after=killed_steps, checkpoint_step=ck_step, kill_exit=proc.returncode,
               resumed_exit=r.returncode, server_exits=rc, stderr=(err + r.stderr)[-2000:])


def scenario_ipv6(tmp: Path, layout: Layout) -> dict:
    """Server bound to ``tcp://[::1]:PORT``, a trainer reading it: zmq.IPV6 on both ends."""
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
    with _serve(corpus, layout, "--bind", endpoint) as srv:
        read_all(dataset(endpoint), log)
        rc, clean = _stop(srv), _clean(srv)
    return row("IPv6: server and trainer on tcp://[::1]", expected, _ids(log), None, f"server exit {rc}",
               server_exit=rc, clean=clean)


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
    second: every scrape answered, every sample once."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    port = free_port()
    log: list = []
    with _serve(corpus, layout, "--metrics-port", str(port)) as srv:
        scraper = subprocess.Popen([sys.executable, "-c", SCRAPER, f"http://127.0.0.1:{port}/metrics", str(rate)],
                                   stdout=subprocess.PIPE, text=True)
        t0 = time.monotonic()
        try:
            read_all(dataset(srv.endpoint), log)
        finally:
            wall = time.monotonic() - t0
            scraper.kill()
            lines = scraper.communicate()[0].split()
        rc, clean = _stop(srv), _clean(srv)
    scrapes, errors = (int(lines[-2]), int(lines[-1])) if len(lines) >= 2 else (0, 0)
    return row(f"{rate:.0f} scrapes of /metrics a second during the epoch", expected, _ids(log), None,
               f"{scrapes} scrapes in {wall:.1f} s, {errors} failed; server exit {rc}",
               scrapes=scrapes, scrape_errors=errors, seconds=wall, server_exit=rc, clean=clean)


SCENARIOS = {
    "small_shm_1m": lambda tmp, layout: scenario_small_shm(tmp, layout, "1m"),
    "small_shm_64m": lambda tmp, layout: scenario_small_shm(tmp, layout, "64m"),
    "second_server_pid_namespace": scenario_second_server_pid_namespace,
    "fan_in_resume": scenario_fan_in_resume,
    "train_killed_two_shards": scenario_train_killed_two_shards,
    "mismatched_shards": scenario_mismatched_shards,
    "resume_other_recipe": scenario_resume_other_recipe,
    "ipv6": scenario_ipv6,
    "scrape_storm": scenario_scrape_storm,
}

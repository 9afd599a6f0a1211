"""Fault scenarios of how trainers read a plan (``V2VStreamDataset`` against a real ``v2v-serve``
serving by plan on 127.0.0.1): DDP ranks, resumes at another world size, loaders with workers,
several jobs on one server, trainers stopped while others read, and peers sending positions and
fetches that lie. Same row format as ``harness/faults.py``; ``python -m bench.faults`` runs them.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import List

import torch
import zmq

from harness.faults import (ROOT, Layout, _clean, _ids, _serve, _stop, dataset, expected_ids, good_corpus,
                            per_epoch, read_all, real_ids, row, stopped_while_another_reads)
from v2v_wire.protocol import pack, unpack


def server_rss_mb(pid: int) -> float:
    """The resident memory of process ``pid``, MB (``/proc``)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def _threads(targets) -> None:
    """Run each callable in its own thread and wait for all (300 s at most each)."""
    ths = [threading.Thread(target=t, daemon=True) for t in targets]
    for t in ths:
        t.start()
    for t in ths:
        t.join(300)


def _ranks(endpoint: str, world: int, logs: List[list], errors: list, stop_after=None, delay=None, tag=False,
           load=None, epoch: int = 0, batch_size=None) -> List[dict]:
    """``world`` DDP ranks (threads, each its own dataset) of one job reading ``epoch`` (or from
    position ``load``), up to ``stop_after`` steps, rank r starting ``delay[r]`` s late; returns
    each rank's last position; ``errors`` gets each rank's error."""
    positions: List[dict] = [None] * world

    def rank(r):
        try:
            time.sleep((delay or [0] * world)[r])
            ds = dataset(endpoint, rank=r, world_size=world, batch_size=batch_size)
            ds.set_epoch(epoch)
            if load is not None:
                ds.load_state_dict(load)
            positions[r] = read_all(ds, logs[r], stop_after=stop_after, tag=tag)
        except Exception as e:  # noqa: BLE001 - the row reports it
            errors.append(f"rank {r}: {type(e).__name__}: {str(e).splitlines()[0]}")

    _threads([lambda r=r: rank(r) for r in range(world)])
    return positions


def scenario_ddp_ranks(tmp: Path, layout: Layout, world: int = 4) -> dict:
    """``world`` DDP ranks read one epoch: every rank takes the same number of steps (the last
    rows padding), the real rows are the epoch's samples once."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    logs: List[list] = [[] for _ in range(world)]
    errors: list = []
    with _serve(corpus, layout) as srv:
        _ranks(srv.endpoint, world, logs, errors)
        rc, clean = _stop(srv), _clean(srv)
    steps = [len(lg) for lg in logs]
    return row(f"{world} DDP ranks on one plan", expected, [s for lg in logs for s in _ids(lg)], None,
               f"steps per rank {steps}; errors {len(errors)}; server exit {rc}", steps=steps, errors=errors,
               server_exit=rc, clean=clean)


def scenario_ddp_restart_late_rank(tmp: Path, layout: Layout, delay_s: float = 3.0, ckpt_step: int = 2) -> dict:
    """Two ranks read ``ckpt_step`` steps and checkpoint (rank 0's position); the server is killed
    (SIGKILL) and started again; the job resumes from that position, rank 1 ``delay_s`` late:
    what the ranks trained on is each sample once."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    logs: List[list] = [[], []]
    errors: list = []
    srv = _serve(corpus, layout).start()
    srv2 = None
    try:
        position = _ranks(srv.endpoint, 2, logs, errors, stop_after=ckpt_step)[0]
        srv.proc.send_signal(signal.SIGKILL)
        srv.proc.wait(10)
        srv2 = _serve(corpus, layout, "--bind", srv.endpoint).start()
        _ranks(srv.endpoint, 2, logs, errors, delay=[0, delay_s], load=position)
        rc, clean = _stop(srv2), _clean(srv2)
    finally:
        srv.stop()
        if srv2 is not None:
            srv2.stop()
    return row(f"2 DDP ranks resume after a server restart, rank 1 {delay_s:.0f} s late", expected,
               [s for lg in logs for s in _ids(lg)], None, f"errors: {'; '.join(errors) or 'none'}; server exit {rc}",
               errors=errors, server_exit=rc, clean=clean)


def scenario_many_trainers(tmp: Path, layout: Layout, n: int = 20, jobs: bool = False) -> dict:
    """``n`` readers at once: the ranks of one job (the epoch once across them) or, with
    ``jobs``, ``n`` jobs each reading the whole epoch (each job's epoch once)."""
    corpus = good_corpus(tmp, 2)
    one = expected_ids(corpus, layout)
    logs: List[list] = [[] for _ in range(n)]
    errors: list = []
    t0 = time.monotonic()
    with _serve(corpus, layout) as srv:
        if jobs:
            def job(j):
                try:
                    read_all(dataset(srv.endpoint), logs[j])
                except Exception as e:  # noqa: BLE001 - the row reports it
                    errors.append(f"job {j}: {type(e).__name__}: {e}")

            _threads([lambda j=j: job(j) for j in range(n)])
        else:
            _ranks(srv.endpoint, n, logs, errors, batch_size=1)
        wall = time.monotonic() - t0
        rc, clean = _stop(srv), _clean(srv)
    steps = [len(lg) for lg in logs]
    got = [f"{j}:{s}" for j, lg in enumerate(logs) for s in _ids(lg)] if jobs else [s for lg in logs for s in _ids(lg)]
    expected = per_epoch(one, range(n)) if jobs else one
    return row(f"{n} {'jobs' if jobs else 'DDP ranks of one job'} on one server", expected, got, None,
               f"steps per reader min {min(steps)} max {max(steps)}; {wall:.1f} s; errors {len(errors)}; "
               f"server exit {rc}", steps=steps, errors=errors, server_exit=rc, clean=clean)


def scenario_resume_after_end(tmp: Path, layout: Layout, ckpt_step: int = 2, workers: int = 2) -> dict:
    """torchdata's StatefulDataLoader (``workers`` DataLoader workers) snapshots its state at step
    ``ckpt_step`` and reads the epoch to its end; a new loader over a new dataset loads the
    snapshot and reads the rest: steps up to the snapshot plus the rest are each sample once."""
    from torchdata.stateful_dataloader import StatefulDataLoader

    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log: list = []
    with _serve(corpus, layout) as srv:
        loader = StatefulDataLoader(dataset(srv.endpoint), batch_size=None, num_workers=workers)
        state, whole = None, []
        for b in loader:
            whole.append((time.monotonic(), real_ids(b)))
            if len(whole) == ckpt_step:
                state = loader.state_dict()
        log += whole[:ckpt_step]
        again = StatefulDataLoader(dataset(srv.endpoint), batch_size=None, num_workers=workers)
        again.load_state_dict(state)
        t0 = time.monotonic()
        read_all(again, log)
        first = log[ckpt_step][0] - t0 if len(log) > ckpt_step else None
        rc, clean = _stop(srv), _clean(srv)
    return row(f"StatefulDataLoader ({workers} workers) resumed from step {ckpt_step} after the epoch ended",
               expected, _ids(log), first, f"resumed run read {len(_ids(log[ckpt_step:]))} samples (the "
               f"{len(_ids(whole[ckpt_step:]))} after the snapshot); server exit {rc}",
               resumed=len(_ids(log[ckpt_step:])), after=len(_ids(whole[ckpt_step:])), server_exit=rc, clean=clean)


def scenario_loader_workers(tmp: Path, layout: Layout, persistent: bool, take: int = 3) -> dict:
    """A DataLoader with 2 workers (``persistent`` or not): take ``take`` batches and ``break``
    (max_steps), load the last batch's position in the main process, iterate again, until the
    epoch ends: each sample once (the workers read ahead; what they read past the break is
    not yielded, and the position says where to go on)."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log: list = []
    passes = 0
    with _serve(corpus, layout) as srv:
        ds = dataset(srv.endpoint)
        loader = torch.utils.data.DataLoader(ds, batch_size=None, num_workers=2, persistent_workers=persistent)
        while passes < 50:
            passes += 1
            n = len(log)
            position = read_all(loader, log, stop_after=take)
            if len(log) - n < take:
                break
            ds.load_state_dict(position)
        rc, clean = _stop(srv), _clean(srv)
    kind = "persistent" if persistent else "non-persistent"
    return row(f"DataLoader, 2 {kind} workers, break after {take} batches and iterate again from the position",
               expected, _ids(log), None, f"{passes} iterations; server exit {rc}", iterations=passes,
               server_exit=rc, clean=clean)


def scenario_lightning_ddp(tmp: Path, layout: Layout) -> dict:
    """Lightning's own ``ddp`` launcher, 2 CPU ranks (gloo), the dataset built before fit
    (``harness.lightning_ddp``, a DataLoader of 2 workers): the same steps on both ranks,
    the epoch's samples once across them."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    out = tmp / "out"
    out.mkdir()
    with _serve(corpus, layout) as srv:
        env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
        proc = subprocess.Popen([sys.executable, "-m", "harness.lightning_ddp", srv.endpoint, str(out)],
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env,
                                start_new_session=True)  # rank 1 is rank 0's child: a hang is killed whole
        try:
            err = proc.communicate(timeout=300)[1]
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            err = proc.communicate(timeout=30)[1]
        except BaseException:  # the bench interrupted: its own session would outlive it
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(30)
            raise
        rc, clean = _stop(srv), _clean(srv)
    ranks = [json.loads(p.read_text()) for p in sorted(out.glob("rank*.json"))]
    batches = [r["batches"] for r in ranks]
    return row("Lightning DDP, 2 gloo ranks, dataset built before fit", expected,
               [s for r in ranks for s in r["seen"]], None,
               f"batches per rank {batches}; trainer exit {proc.returncode}; server exit {rc}",
               batches=batches, trainer_exit=proc.returncode, server_exit=rc, clean=clean, stderr=err[-2000:])


def scenario_two_ddp_jobs(tmp: Path, layout: Layout) -> dict:
    """Two DDP jobs of 2 ranks each read one server at once, of other batch sizes and epochs:
    each job's epoch is its samples once across its ranks."""
    corpus = good_corpus(tmp, 2)
    one = expected_ids(corpus, layout)
    logs: List[List[list]] = [[[], []], [[], []]]
    errors: list = []
    with _serve(corpus, layout) as srv:
        _threads([lambda: _ranks(srv.endpoint, 2, logs[0], errors, tag=True, epoch=0, batch_size=2),
                  lambda: _ranks(srv.endpoint, 2, logs[1], errors, tag=True, epoch=1, batch_size=3)])
        rc, clean = _stop(srv), _clean(srv)
    got = [s for job in logs for lg in job for s in _ids(lg)]
    return row("two DDP jobs (2 ranks each) on one server, epochs 0 and 1", per_epoch(one, (0, 1)), got, None,
               f"steps per rank {[[len(lg) for lg in job] for job in logs]}; errors {len(errors)}; server exit {rc}",
               errors=errors, server_exit=rc, clean=clean)


def scenario_world_size_change(tmp: Path, layout: Layout, old: int = 2, new: int = 1, ckpt_step: int = 2) -> dict:
    """A job of world size ``old`` stops after ``ckpt_step`` steps; a job of world size ``new``
    resumes from rank 0's position (a position is the same on every rank, at any world size):
    what both trained on is each sample once."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    before: List[list] = [[] for _ in range(old)]
    after: List[list] = [[] for _ in range(new)]
    errors: list = []
    with _serve(corpus, layout) as srv:
        positions = _ranks(srv.endpoint, old, before, errors, stop_after=ckpt_step)
        same = all(p == positions[0] for p in positions)
        _ranks(srv.endpoint, new, after, errors, load=positions[0])
        rc, clean = _stop(srv), _clean(srv)
    got = [s for lg in before + after for s in _ids(lg)]
    return row(f"DDP job resumed at world size {new} from {old}", expected, got, None,
               f"positions the same on every rank {same}; errors {'; '.join(errors) or 'none'}; server exit {rc}",
               same_positions=same, errors=errors, server_exit=rc, clean=clean)


def scenario_wake_after_others_ran_ahead(tmp: Path, layout: Layout, epochs: int = 6, stop_s: float = 10.0) -> dict:
    """Trainer A is stopped (SIGSTOP) after its first step for ``stop_s`` seconds while job B
    reads ``epochs`` epochs; woken, A reads its epoch on: A's epoch once, each of B's once."""
    corpus = good_corpus(tmp, 2)
    one = expected_ids(corpus, layout)
    with _serve(corpus, layout) as srv:
        def stop(p):
            for line in p.stdout:
                if line.startswith("step"):
                    break
            p.send_signal(signal.SIGSTOP)

        ids_a, log_b, b_s, rc_a = stopped_while_another_reads(srv.endpoint, stop, stop_s, tmp, range(epochs))
        rc, clean = _stop(srv), _clean(srv)
    return row(f"trainer woken {stop_s:.0f} s after another read {epochs} epochs", per_epoch(one, ["a", *range(epochs)]),
               [f"a:{s}" for s in ids_a] + _ids(log_b), None,
               f"B read {len(_ids(log_b))} samples in {b_s:.1f} s while A was stopped; A got {len(ids_a)} (exit {rc_a}); "
               f"server exit {rc}", a_exit=rc_a, server_exit=rc, clean=clean)


def scenario_loop_stops_reading(tmp: Path, layout: Layout, pause_s: float = 6.0, task_timeout_s: float = 2.0) -> dict:
    """A trainer's loop stops calling ``next()`` after one batch for ``pause_s`` seconds (a long
    validation pass; three task timeouts) while another job reads its epoch: both epochs whole,
    no worker called hung."""
    corpus = good_corpus(tmp, 2)
    one = expected_ids(corpus, layout)
    log_a: list = []
    log_b: list = []
    with _serve(corpus, layout, "--task-timeout", str(task_timeout_s)) as srv:
        it = iter(dataset(srv.endpoint))
        b = next(it)
        log_a.append((time.monotonic(), [f"a:{s}" for s in real_ids(b)]))
        t0 = time.monotonic()
        read_all(dataset(srv.endpoint), log_b, tag=True)
        b_s = time.monotonic() - t0
        time.sleep(max(0.0, pause_s - b_s))
        for b in it:
            log_a.append((time.monotonic(), [f"a:{s}" for s in real_ids(b)]))
        rc, clean = _stop(srv), _clean(srv)
        hung = srv.log.count("task reassigned")
    return row(f"a trainer's loop stops reading for {pause_s:.0f} s (task timeout {task_timeout_s:.0f} s)",
               per_epoch(one, ["a", 0]), _ids(log_a) + _ids(log_b), None,
               f"the other read {len(_ids(log_b))} samples in {b_s:.1f} s; the first read {len(_ids(log_a))}; "
               f"workers called hung {hung}; server exit {rc}", hung=hung, server_exit=rc, clean=clean)


def _outcome(endpoint: str, position, timeout_s: float = 60.0) -> str:
    """What a dataset that loads ``position`` does: refused (where, the error's type) or read
    (how many real rows)."""
    got: list = []

    def run():
        try:
            ds = dataset(endpoint, timeout_s=20)
            try:
                ds.load_state_dict(position)
            except Exception as e:  # noqa: BLE001 - the outcome is the answer
                got.append(f"refused at load ({type(e).__name__})")
                return
            log: list = []
            read_all(ds, log)
            got.append(f"read {len(_ids(log))} rows")
        except Exception as e:  # noqa: BLE001 - the outcome is the answer
            got.append(f"refused reading ({type(e).__name__})")

    th = threading.Thread(target=run, daemon=True)
    th.start()
    th.join(timeout_s)
    return got[0] if got else f"no answer in {timeout_s:.0f} s"


def scenario_lying_positions(tmp: Path, layout: Layout) -> dict:
    """Positions that lie (past the epoch's end, negative, an epoch beyond any, another plan,
    malformed) loaded by readers while an honest trainer reads: each is refused in one line or
    reads only what its position names; the honest epoch is whole."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log: list = []
    with _serve(corpus, layout) as srv:
        honest = dataset(srv.endpoint)
        it = iter(honest)
        b = next(it)
        log.append((time.monotonic(), real_ids(b)))
        good = b["position"]
        cases = {"past the end": {**good, "sample_in_epoch": 10 ** 9}, "negative": {**good, "sample_in_epoch": -1},
                 "epoch 2**40": {**good, "epoch": 2 ** 40}, "another seed": {**good, "plan": {**good["plan"], "seed": 99}},
                 "a string": "position", "no plan": {"epoch": 0, "sample_in_epoch": 0},
                 "bool offset": {**good, "sample_in_epoch": True}}
        answers = {name: _outcome(srv.endpoint, pos) for name, pos in cases.items()}
        for b in it:
            log.append((time.monotonic(), real_ids(b)))
        rc, clean = _stop(srv), _clean(srv)
    return row("positions that lie, loaded while a trainer reads", expected, _ids(log), None,
               f"answers {answers}; server exit {rc}", answers=answers, server_exit=rc, clean=clean)


def _hostile_peer(endpoint: str, fetches: List[dict], timeout_s: float = 60.0) -> dict:
    """Send ``fetches`` from one peer; count the answers (by type) that come within ``timeout_s``."""
    ctx = zmq.Context()
    s = ctx.socket(zmq.DEALER)
    s.setsockopt(zmq.LINGER, 0)
    s.connect(endpoint)
    counts: dict = {}
    try:
        for f in fetches:
            s.send(pack(f))
        deadline = time.monotonic() + timeout_s
        while sum(counts.values()) < len(fetches) and s.poll(max(1, int((deadline - time.monotonic()) * 1000))):
            kind = unpack(s.recv_multipart()[0]).get("type")
            counts[kind] = counts.get(kind, 0) + 1
    finally:
        s.close(0)
        ctx.term()
    return counts


def scenario_hostile_fetches(tmp: Path, layout: Layout, epochs: int = 50, repeats: int = 500) -> dict:
    """A peer fetches one row of each of ``epochs`` epochs drawn up to 2**31 - 1 (each a plan the
    server unfolds), then ``repeats`` fetches of the largest range a fetch may name, while an
    honest trainer reads: the honest epoch is whole; the server's memory and the answers counted."""
    import random

    from v2v_wire.plan_messages import MAX_FETCH_ROWS

    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log: list = []
    with _serve(corpus, layout) as srv:
        honest = dataset(srv.endpoint)
        plan = honest.plan_info().plan.to_dict()
        rss0 = server_rss_mb(srv.proc.pid)
        rng = random.Random(5)
        fetch = {"type": "fetch", "request": 0, "start": 0, "stop": 1, "outputs": ["voxels"], "plan": plan}
        many = [{**fetch, "request": i, "epoch": rng.randrange(2 ** 31)} for i in range(epochs)]
        wide = [{**fetch, "request": i, "epoch": 0, "stop": MAX_FETCH_ROWS} for i in range(repeats)]
        result: dict = {}
        t0 = time.monotonic()
        th = threading.Thread(target=lambda: result.update(epochs=_hostile_peer(srv.endpoint, many, 120),
                                                            wide=_hostile_peer(srv.endpoint, wide, 60)), daemon=True)
        th.start()
        read_all(honest, log)
        honest_s = time.monotonic() - t0
        th.join(200)
        rss1 = server_rss_mb(srv.proc.pid)
        alive = srv.proc.poll() is None
        rc, clean = _stop(srv), _clean(srv)
    return row(f"fetches of {epochs} far epochs and {repeats} of the widest range, while a trainer reads", expected,
               _ids(log), None, f"answers {result}; the honest epoch read in {honest_s:.1f} s; server memory "
               f"{rss0:.0f} -> {rss1:.0f} MB; alive {alive}; server exit {rc}", answers=result,
               rss_mb=[rss0, rss1], alive=alive, server_exit=rc, clean=clean)


SCENARIOS = {
    "ddp_ranks": scenario_ddp_ranks,
    "ddp_restart_late_rank": scenario_ddp_restart_late_rank,
    "many_ranks": scenario_many_trainers,
    "many_jobs": lambda tmp, layout: scenario_many_trainers(tmp, layout, n=8, jobs=True),
    "resume_after_end": scenario_resume_after_end,
    "loader_workers": lambda tmp, layout: scenario_loader_workers(tmp, layout, True),
    "loader_workers_fresh": lambda tmp, layout: scenario_loader_workers(tmp, layout, False),
    "lightning_ddp": scenario_lightning_ddp,
    "two_ddp_jobs": scenario_two_ddp_jobs,
    "world_size_2_to_1": lambda tmp, layout: scenario_world_size_change(tmp, layout, 2, 1),
    "world_size_1_to_2": lambda tmp, layout: scenario_world_size_change(tmp, layout, 1, 2),
    "wake_after_others_ran_ahead": scenario_wake_after_others_ran_ahead,
    "loop_stops_reading": scenario_loop_stops_reading,
    "lying_positions": scenario_lying_positions,
    "hostile_fetches": scenario_hostile_fetches,
}

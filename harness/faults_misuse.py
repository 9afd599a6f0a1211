"""Fault scenarios of careless and hostile clients against a real v2v-serve on 127.0.0.1: two
trainers on one consumer id, two DDP jobs on one default group, a resume at another world size, a
trainer that wakes after the others ran epochs ahead, a reader sitting on its grants, resume
states that lie, and messages that cost more than their size (issue 69). Each ``scenario_*``
returns a ``faults.row``: samples expected, delivered, lost, doubled, ``facts`` for the tests.
``python -m bench.faults`` runs them with the other scenarios; ``tests/test_exactly_once.py``
runs short versions.
"""
from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path
from typing import List, Optional

import zmq

from harness.faults import (ROOT, Layout, _ids, _raw_peer, _serve, _take, _trainer_process, expected_ids,
                            good_corpus, read_all, row)
from v2v_client import StreamError, V2VPushDataset
from v2v_wire.protocol import pack, unpack

__all__ = ["SCENARIOS", "server_rss_mb"]


def server_rss_mb(pid: int) -> float:
    """The resident memory of process ``pid``, MB (``/proc``)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _refused(ds: V2VPushDataset, got: list, errors: list) -> None:
    """Iterate ``ds``; batches to ``got``, the first line of an error to ``errors``."""
    try:
        for b in ds:
            got.append(list(b["sample_ids"]))
    except (StreamError, ValueError) as e:
        errors.append(str(e).splitlines()[0])


# ---------------------------------------------------------------------------------- one reader per consumer
def scenario_two_readers_one_consumer(tmp: Path, layout: Layout, step_s: float = 0.3) -> dict:
    """Trainer A reads; trainer B (another process's dataset) loads A's state and reads too, as
    the same consumer: B is refused with one line naming the consumer, A reads every sample."""
    corpus = good_corpus(tmp, 3)
    expected = expected_ids(corpus, layout)
    log: list = []
    got_b: list = []
    errors: list = []
    with _serve(corpus, layout, "--epochs", "1", "--client-timeout", "3") as srv:
        a = V2VPushDataset(srv.endpoint, timeout_s=60, credits=2)
        it = iter(a)
        _take(it, 1, log)
        b = V2VPushDataset(srv.endpoint, timeout_s=60, credits=2)
        b.load_state_dict(a.state_dict())
        t0 = time.monotonic()
        th = threading.Thread(target=_refused, args=(b, got_b, errors), daemon=True)
        th.start()
        for x in it:
            log.append((time.monotonic(), list(x["sample_ids"])))
            time.sleep(step_s)
        th.join(60)
        refused_after = time.monotonic() - t0
        rc = srv.wait(30)
    return row("two trainers read one consumer id at once", expected, _ids(log) + [s for ids in got_b for s in ids],
               None, f"second trainer: {errors[0] if errors else 'not refused'}; its batches {len(got_b)}; server exit "
               f"{rc}", refused=errors[:1], second_batches=len(got_b), server_exit=rc,
               refused_within_s=round(refused_after, 1))


def _ddp_job(endpoint: str, world: int, logs: List[list], errors: list, step_s: float, started: threading.Event,
             group: Optional[str] = None) -> List[threading.Thread]:
    """``world`` DDP ranks (threads) of one job reading ``endpoint`` with ``group`` (None: the
    default, as a user who leaves it); each rank's real samples to ``logs[rank]``."""
    def rank(r: int) -> None:
        try:
            kw = {} if group is None else {"group": group}  # None: as a user who leaves it at its default
            ds = V2VPushDataset(endpoint, timeout_s=60, credits=1, rank=r, world_size=world, **kw)
            for b in ds:
                started.set()
                logs[r].append((time.monotonic(), [s for s, p in zip(b["sample_ids"], b["padding"].tolist()) if not p]))
                time.sleep(step_s)
        except (StreamError, ValueError) as e:
            errors.append(str(e).splitlines()[0])
    ths = [threading.Thread(target=rank, args=(r,), daemon=True) for r in range(world)]
    for t in ths:
        t.start()
    return ths


def scenario_two_ddp_jobs_one_group(tmp: Path, layout: Layout, step_s: float = 0.8) -> dict:
    """Two DDP jobs (world size 2 each, ranks started by hand: no launcher to name them) on one
    server, both leaving ``group=`` at its default: the second job's ranks are refused with a line
    saying to set ``group=``; the first job reads every sample once."""
    corpus = good_corpus(tmp, 3)
    expected = expected_ids(corpus, layout)
    logs: List[list] = [[], [], [], []]
    errors_1: list = []
    errors_2: list = []
    with _serve(corpus, layout, "--epochs", "1", "--client-timeout", "3") as srv:
        started = threading.Event()
        job1 = _ddp_job(srv.endpoint, 2, logs[:2], errors_1, step_s, started)
        started.wait(60)
        job2 = _ddp_job(srv.endpoint, 2, logs[2:], errors_2, step_s, threading.Event())
        for t in job1 + job2:
            t.join(120)
        rc = srv.wait(30)
    second = [s for lg in logs[2:] for s in _ids(lg)]
    return row("two DDP jobs on one server, both with the default group", expected,
               [s for lg in logs[:2] for s in _ids(lg)] + second, None,
               f"second job: {errors_2[0] if errors_2 else 'not refused'} ({len(errors_2)} rank(s) refused, "
               f"{len(second)} samples); first job errors {len(errors_1)}; server exit {rc}",
               refused=sorted(set(errors_2)), second_samples=len(second), first_errors=errors_1, server_exit=rc)


# ---------------------------------------------------------------------------------- resume at another world size
def scenario_world_size_change(tmp: Path, layout: Layout, old: int = 2, new: int = 1) -> dict:
    """A job of world size ``old`` (threads) checkpoints each rank after 2 batches, takes 2 more
    and stops; it resumes at world size ``new``. From one rank's state alone the resume is refused
    before the first batch with one line saying what to load; from every rank's state gathered,
    every sample is trained once (what the old ranks took after their checkpoints again)."""
    corpus = good_corpus(tmp, 3)
    expected = expected_ids(corpus, layout)
    kept: list = []  # what the restored models have seen
    refusal: list = []
    with _serve(corpus, layout, "--epochs", "1", "--client-timeout", "2", "--end-grace-s", "30") as srv:
        states: list = [None] * old

        def first(r: int) -> None:  # a rank of the job that stops: 2 steps, a checkpoint, 2 more steps
            ds = V2VPushDataset(srv.endpoint, timeout_s=60, credits=1, rank=r, world_size=old, group="job")
            it = iter(ds)
            for step in range(4):
                b = next(it)
                if step < 2:
                    kept.extend(s for s, p in zip(b["sample_ids"], b["padding"].tolist()) if not p)
                if step == 1:
                    states[r] = ds.state_dict()
            it.close()  # the job stops (its later steps are lost with it)

        ths = [threading.Thread(target=first, args=(r,), daemon=True) for r in range(old)]
        for t in ths:
            t.start()
        for t in ths:
            t.join(120)
        if old > 1:  # one rank's state speaks for that rank alone
            alone = V2VPushDataset(srv.endpoint, timeout_s=60, credits=1, rank=0, world_size=new, group="job")
            alone.load_state_dict(states[0])
            try:
                next(iter(alone))
            except ValueError as e:
                refusal.append(str(e).splitlines()[0])
        resumed = [V2VPushDataset(srv.endpoint, timeout_s=60, credits=1, rank=r, world_size=new, group="job")
                   for r in range(new)]
        logs: List[list] = [[] for _ in range(new)]
        errors: list = []

        def rank(r: int) -> None:
            try:
                resumed[r].load_state_dict({"v2v_ranks": states})
                for b in resumed[r]:
                    logs[r].append((time.monotonic(), [s for s, p in zip(b["sample_ids"], b["padding"].tolist())
                                                       if not p]))
            except (StreamError, ValueError) as e:
                errors.append(str(e).splitlines()[0])
        ths = [threading.Thread(target=rank, args=(r,), daemon=True) for r in range(new)]
        for t in ths:
            t.start()
        for t in ths:
            t.join(120)
        rc = srv.stop()
    return row(f"DDP job resumed at world size {new} from {old}", expected, kept + [s for lg in logs for s in _ids(lg)],
               None, f"from rank 0's state alone: {refusal[0] if refusal else 'not refused'}; from every rank's "
               f"state: errors {errors or 'none'}; server exit {rc}", refused=refusal, errors=errors, server_exit=rc)


# ---------------------------------------------------------------------------------- liveness with safety
WAKING_CLIENT = r"""
import os, signal, sys, time
from v2v_client import V2VPushDataset
ds = V2VPushDataset(sys.argv[1], timeout_s=120, credits=int(sys.argv[2]))
for n, b in enumerate(ds, 1):
    print("ids", " ".join(f"{b['epoch']}:{s}" for s in b["sample_ids"]), flush=True)
    if n == 1:
        time.sleep(0.5)  # its grants ahead come in; then it is stopped from outside
    time.sleep(0.05)
"""


def scenario_wake_after_others_ran_ahead(tmp: Path, layout: Layout, epochs: int = 3, freeze_s: float = 10.0) -> dict:
    """Trainer A (credits 4) is stopped (SIGSTOP) after its first batch, past every timeout, while
    trainer B reads every epoch to its end; A wakes: the batches granted to it come back to it (or
    went elsewhere), and every sample of every epoch reaches one loop once."""
    corpus = good_corpus(tmp, 2)
    one = expected_ids(corpus, layout)
    expected = [f"{e}:{s}" for e in range(epochs) for s in one]
    log_b: list = []
    with _serve(corpus, layout, "--epochs", str(epochs), "--client-timeout", "2", "--lease", "2",
                "--end-grace-s", "60") as srv:
        p = _trainer_process(WAKING_CLIENT, srv.endpoint, "4")
        try:
            ids = p.stdout.readline().split()[1:]
            time.sleep(1.0)
            p.send_signal(signal.SIGSTOP)
            t0 = time.monotonic()
            b = V2VPushDataset(srv.endpoint, timeout_s=60, credits=1)
            for x in b:
                log_b.append((time.monotonic(), [f"{x['epoch']}:{s}" for s in x["sample_ids"]]))
            b_done = time.monotonic() - t0
            time.sleep(max(0.0, freeze_s - b_done))
            p.send_signal(signal.SIGCONT)
            for line in p.stdout:
                ids += line.split()[1:]
            a_rc = p.wait(120)
        finally:
            if p.poll() is None:
                p.send_signal(signal.SIGCONT)
                p.kill()
        rc = srv.stop()
    return row(f"trainer woken {freeze_s:.0f} s after another read all {epochs} epochs", expected, ids + _ids(log_b),
               None, f"B read {len(_ids(log_b))} samples in {b_done:.1f} s while A was stopped; A got "
               f"{len(ids)} (exit {a_rc}); server exit {rc}", b_seconds=round(b_done, 1), a_samples=len(ids),
               a_exit=a_rc, server_exit=rc)


def _sitting_peer(endpoint: str, held: list, stop: threading.Event, credits: int = 4) -> threading.Thread:
    """A peer that asks for the grant of every batch it is sent and never acknowledges one: it
    sits on ``credits`` grants, heartbeating, until ``stop``; the ids granted to it go to ``held``."""
    def run():
        ctx, s = _raw_peer(endpoint, credits)
        asked = {}
        try:
            while not stop.is_set():
                if s.poll(100):
                    h = unpack(s.recv_multipart()[0])
                    if h["type"] == "batch":
                        asked[h["batch_id"]] = h["sample_ids"]
                        s.send(pack({"type": "hold", "batch_ids": [h["batch_id"]]}))
                    elif h["type"] == "granted":
                        for bid in h["batch_ids"]:
                            held.extend(asked.pop(bid, []))
                s.send(pack({"type": "heartbeat"}))
        finally:
            s.close(0)
            ctx.term()
    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


def scenario_sitting_on_grants(tmp: Path, layout: Layout, lease_s: float = 2.0) -> dict:
    """A peer sits on 4 grants forever (never acknowledges, heartbeats); the honest trainer of an
    ``--epochs 1`` server reads every other sample and is told the stream ended within ``lease_s``
    (the grants' bound) of its last batch, instead of waiting with no end."""
    corpus = good_corpus(tmp, 3)
    expected = expected_ids(corpus, layout)
    log: list = []
    held: list = []
    stop = threading.Event()
    with _serve(corpus, layout, "--epochs", "1", "--lease", str(lease_s), "--end-grace-s", "5") as srv:
        peer = _sitting_peer(srv.endpoint, held, stop)
        while not held:
            time.sleep(0.05)
        ds = V2VPushDataset(srv.endpoint, timeout_s=60, credits=1)
        it = iter(ds)
        last = None
        errors = []
        try:
            for b in it:
                log.append((time.monotonic(), list(b["sample_ids"])))
                last = time.monotonic()
            ended_after = time.monotonic() - last if last is not None else None
        except StreamError as e:
            errors.append(str(e).splitlines()[0])
            ended_after = None
        stop.set()
        peer.join(10)
        rc = srv.wait(30)
    return row("a peer sits on 4 grants, never acknowledging", expected, _ids(log) + held, None,
               f"the honest trainer's stream ended {ended_after if ended_after is None else round(ended_after, 1)} s "
               f"after its last batch (lease {lease_s} s); peer held {len(held)} samples; errors {errors or 'none'}; "
               f"server exit {rc}", ended_after_s=None if ended_after is None else round(ended_after, 2),
               held=len(held), errors=errors, server_exit=rc)


def scenario_loop_stops_reading(tmp: Path, layout: Layout, pause_s: float = 6.0) -> dict:
    """An honest trainer's loop stops calling ``next()`` after one batch (a long validation pass)
    while its I/O thread holds its grants ahead; another trainer reads every other sample and
    its stream ends; the first then reads on and gets what it held: every sample once."""
    corpus = good_corpus(tmp, 3)
    expected = expected_ids(corpus, layout)
    log: list = []
    log_b: list = []
    with _serve(corpus, layout, "--epochs", "1", "--lease", "2", "--end-grace-s", "30") as srv:
        a = V2VPushDataset(srv.endpoint, timeout_s=60, credits=4)
        it = iter(a)
        _take(it, 1, log)
        t0 = time.monotonic()
        read_all(V2VPushDataset(srv.endpoint, timeout_s=60, credits=1), log_b)
        b_done = time.monotonic() - t0
        time.sleep(max(0.0, pause_s - b_done))
        for x in it:
            log.append((time.monotonic(), list(x["sample_ids"])))
        rc = srv.stop()
    return row(f"a trainer's loop stops reading for {pause_s:.0f} s", expected, _ids(log) + _ids(log_b), None,
               f"the other read {len(_ids(log_b))} samples and ended in {b_done:.1f} s; the first read "
               f"{len(_ids(log))}; server exit {rc}", b_seconds=round(b_done, 1), b_samples=len(_ids(log_b)),
               server_exit=rc)


# ---------------------------------------------------------------------------------- resume states that lie
def _hello(endpoint: str, resume: dict, consumer: str = "liar", credits: int = 1, timeout_s: float = 30.0) -> dict:
    """Say hello as ``consumer`` with ``resume``; the server's answer (its header)."""
    ctx = zmq.Context()
    s = ctx.socket(zmq.DEALER)
    s.setsockopt(zmq.LINGER, 0)
    s.connect(endpoint)
    try:
        s.send(pack({"type": "hello", "outputs": ["voxels"], "credits": credits, "consumer": consumer,
                     "resume": resume}))
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if s.poll(200):
                h = unpack(s.recv_multipart()[0])
                if h["type"] in ("welcome", "error"):
                    s.send(pack({"type": "bye"}))
                    return h
        return {"type": "no answer"}
    finally:
        s.close(0)
        ctx.term()


def _expensive_holds(endpoint: str, n: int = 60, width: int = 4096) -> float:
    """A peer granted one batch names it ``width`` times in each of ``n`` holds; seconds it took."""
    ctx, s = _raw_peer(endpoint, 1)
    t0 = time.monotonic()
    try:
        bid = None
        while bid is None and time.monotonic() - t0 < 30:
            if s.poll(200):
                h = unpack(s.recv_multipart()[0])
                if h["type"] == "batch":
                    bid = h["batch_id"]
        t0 = time.monotonic()
        for _ in range(n):
            s.send(pack({"type": "hold", "batch_ids": [bid] * width}))
        answered = 0
        while answered < n and time.monotonic() - t0 < 60:
            if s.poll(200) and unpack(s.recv_multipart()[0])["type"] == "granted":
                answered += 1
        s.send(pack({"type": "released", "batch_ids": [bid]}))
        s.send(pack({"type": "bye"}))
        return time.monotonic() - t0
    finally:
        s.close(0)
        ctx.term()


def scenario_lying_resume_states(tmp: Path, layout: Layout, big: int = 1_000_000) -> dict:
    """While an honest trainer reads an ``--epochs 2`` server, peers say hello with resume states
    that lie: ids of epoch 0 never sent to them, ``completed_epoch`` 5 and 999999999, ``big`` ids;
    and one granted a batch names it 4096 times in each of 60 holds. Each lie is refused with one
    line, the holds cost time linear in their size, the honest trainer reads every sample once and
    never times out, and the server's memory is back within 10 % once the peers left."""
    corpus = good_corpus(tmp, 2)
    one = expected_ids(corpus, layout)
    expected = [f"{e}:{s}" for e in range(2) for s in one]
    log: list = []
    answers: dict = {}
    with _serve(corpus, layout, "--epochs", "2", "--end-grace-s", "5") as srv:
        ds = V2VPushDataset(srv.endpoint, timeout_s=10, credits=1)
        it = iter(ds)
        b = next(it)
        log.append((time.monotonic(), [f"0:{s}" for s in b["sample_ids"]]))
        rss_before = server_rss_mb(srv.proc.pid)
        video = one[0].rpartition("#")[0]
        answers["never sent"] = _hello(srv.endpoint, {"completed_epoch": -1, "delivered": {
            "0": "\n".join(f"{v}#0,1" for v in sorted({s.rpartition('#')[0] for s in one})[:3])}})
        answers["completed 5"] = _hello(srv.endpoint, {"completed_epoch": 5})
        answers["completed 999999999"] = _hello(srv.endpoint, {"completed_epoch": 999999999})
        t0 = time.monotonic()
        answers[f"{big} ids"] = _hello(srv.endpoint, {"completed_epoch": -1, "delivered": {
            "0": f"{video}#" + ",".join(map(str, range(big)))}})
        big_s = time.monotonic() - t0
        holds_s = _expensive_holds(srv.endpoint)
        errors = []
        gap = 0.0
        try:
            last = time.monotonic()
            for b in it:
                log.append((time.monotonic(), [f"{b['epoch']}:{s}" for s in b["sample_ids"]]))
                gap, last = max(gap, time.monotonic() - last), time.monotonic()
        except StreamError as e:
            errors.append(str(e).splitlines()[0])
        time.sleep(1.0)
        rss_after = server_rss_mb(srv.proc.pid)
        rc = srv.wait(30)
    codes = {k: (a.get("code") or a["type"]) for k, a in answers.items()}
    return row("resume states that lie, and holds naming one id 4096 times", expected, _ids(log), None,
               f"answers {codes}; {big} ids answered in {big_s:.1f} s; 60 holds in {holds_s:.1f} s; honest errors "
               f"{errors or 'none'}; server memory {rss_before:.0f} -> {rss_after:.0f} MB; server exit {rc}",
               codes=codes, messages={k: a.get("message", "") for k, a in answers.items()}, big_s=round(big_s, 2),
               holds_s=round(holds_s, 2), errors=errors, rss_before_mb=round(rss_before, 1),
               rss_after_mb=round(rss_after, 1), longest_wait_s=round(gap, 2), server_exit=rc)


def scenario_first_hello_far_ahead(tmp: Path, layout: Layout) -> dict:
    """The first hello to a fresh ``--epochs 2`` server claims epoch 5 complete: it is refused,
    and the honest trainer that comes next reads both epochs."""
    corpus = good_corpus(tmp, 1)
    one = expected_ids(corpus, layout)
    expected = [f"{e}:{s}" for e in range(2) for s in one]
    log: list = []
    with _serve(corpus, layout, "--epochs", "2") as srv:
        answer = _hello(srv.endpoint, {"completed_epoch": 5})
        for b in V2VPushDataset(srv.endpoint, timeout_s=60):
            log.append((time.monotonic(), [f"{b['epoch']}:{s}" for s in b["sample_ids"]]))
        rc = srv.wait(30)
    return row("first hello claims epoch 5 of an --epochs 2 server", expected, _ids(log), None,
               f"answer: {answer.get('code') or answer['type']}: {answer.get('message', '')[:80]}; server exit {rc}",
               code=answer.get("code"), message=answer.get("message", ""), server_exit=rc)


SCENARIOS = {
    "two_readers_one_consumer": scenario_two_readers_one_consumer,
    "two_ddp_jobs_one_group": scenario_two_ddp_jobs_one_group,
    "world_size_2_to_1": lambda tmp, layout: scenario_world_size_change(tmp, layout, 2, 1),
    "world_size_1_to_2": lambda tmp, layout: scenario_world_size_change(tmp, layout, 1, 2),
    "wake_after_others_ran_ahead": lambda tmp, layout: scenario_wake_after_others_ran_ahead(tmp, layout, 6),
    "sitting_on_grants": scenario_sitting_on_grants,
    "loop_stops_reading": scenario_loop_stops_reading,
    "lying_resume_states": scenario_lying_resume_states,
    "first_hello_far_ahead": scenario_first_hello_far_ahead,
}

"""A fleet under faults: peers that break the protocol beside real hosts, and Ctrl-C while every
host is silent. Real ``v2v-serve`` hosts on 127.0.0.1 on the bundled clips, hostile peers as ZeroMQ
ROUTER sockets of the test (``harness.faults_fleet``), real ``v2v-loadtest`` processes reading; every
test is bounded and stops what it starts."""
from __future__ import annotations

import json
import signal
import subprocess
import sys

import pytest

from harness.faults_fleet import (EXIT_S, HUGE_BYTES, Peer, another_host, close_all, hostile_peers, read_fleet,
                                  silent_fleet_interrupt)
from harness.serve import ServeProcess
from v2v_client.fetch import Link
from v2v_wire.plan import PlanIdentity
from v2v_wire.plan_messages import PlanInfo, Refused
from v2v_wire.protocol import pack

from tests.test_fleet_read import setup


@pytest.mark.timeout(300)
@pytest.mark.parametrize("sig", (signal.SIGINT, signal.SIGTERM), ids=lambda s: signal.Signals(s).name)
def test_a_loadtest_interrupted_while_every_host_is_stopped_says_one_line_within_2_s(tmp_path, videos, sig):
    """``v2v-loadtest`` reads a fleet of two hosts; both are SIGSTOPped mid-read, so its reading
    thread waits on silent sockets (for ``--timeout`` 60 s); the signal ends it with its one line
    within :data:`EXIT_S`."""
    _, _, base = setup(tmp_path, videos)
    status, lines, took = silent_fleet_interrupt(base, sig)
    said = "v2v-loadtest: " + ("stopped (SIGTERM)" if sig == signal.SIGTERM else "interrupted (Ctrl-C)")
    assert status == 128 + sig, lines[-10:]
    assert lines and lines[-1].startswith(said) and "Traceback" not in "\n".join(lines), lines[-10:]
    assert took < EXIT_S, f"exit {took:.1f} s after the signal"


#: ``v2v-loadtest`` as its script runs it, saying its peak RSS (``VmHWM``: its own memory since its
#: exec, where the ``ru_maxrss`` a parent gets also counts the parent's pages before the exec)
LOADTEST = """import atexit, re, sys
from pathlib import Path
atexit.register(lambda: print("peak RSS kB", re.search(r"VmHWM:\\s+(\\d+)", Path("/proc/self/status").read_text())[1],
                              file=sys.stderr))
from v2v_wire.commands import loadtest
sys.exit(loadtest())"""


def loadtest(connect: str, batches: int, timeout_s: float = 60.0) -> tuple:
    """Run ``v2v-loadtest`` on ``connect``: ``(exit status, its stderr lines, its JSON report or
    None, its peak RSS in MB)``."""
    r = subprocess.run([sys.executable, "-c", LOADTEST, "--connect", connect, "--batches", str(batches), "--warmup",
                        "0", "--timeout", str(timeout_s), "--outputs", "voxels,frames", "--json"],
                       capture_output=True, text=True, timeout=240)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    peak = [int(ln.split()[-1]) / 1024 for ln in lines if ln.startswith("peak RSS kB")]
    report = json.loads(r.stdout.splitlines()[-1]) if r.returncode == 0 and r.stdout.strip() else None
    return r.returncode, [ln for ln in lines if not ln.startswith("peak RSS kB")], report, peak[0] if peak else None


@pytest.mark.timeout(400)
def test_hostile_peers_beside_a_real_host_are_each_named_once_and_left_out(tmp_path, videos):
    """A real host listed with peers that answer garbage, another protocol version, a 500 MB
    frame, a made-up plan, and the real host's plan with rows that do not match their header:
    ``v2v-loadtest`` reads two epochs whole from the real host, names each peer once (not again
    in the second pass), and never takes the 500 MB frame in (its peak RSS stays far below it)."""
    _, want, base = setup(tmp_path, videos)
    with ServeProcess(base) as real:
        with Link(real.endpoint, 60) as link:
            info = link.ask()
        peers = hostile_peers(info)
        try:
            connect = ",".join([real.endpoint] + [p.endpoint for p in peers.values()])
            status, lines, report, rss = loadtest(connect, 2 * -(-len(want) // 2))  # two epochs: two passes
        finally:
            close_all(peers.values())
    assert status == 0, lines[-10:]
    assert report["unique_samples"] == report["samples"] == 2 * len(want) and report["epochs_seen"] == [0, 1], report
    assert set(report["per_server"]) == {real.endpoint}, report["per_server"]
    for name, p in peers.items():
        named = [ln for ln in lines if p.endpoint in ln]
        assert len(named) == 1 and "left out" in named[0], (name, named)
    assert peers["impersonator"].kinds.get("make"), peers["impersonator"].kinds  # it was routed videos
    assert rss < HUGE_BYTES / 2 ** 20, f"the reader's peak RSS is {rss:.0f} MB"
    assert not any("Traceback" in ln for ln in lines), lines


@pytest.mark.timeout(300)
def test_a_fleet_of_hostile_peers_only_is_one_line_naming_each_and_why(tmp_path):
    """No host left: ``v2v-loadtest`` exits 1 with one line naming each peer and why it was
    left out, the 500 MB frame never taken in."""
    real = PlanInfo(PlanIdentity("0" * 16, "1" * 16, 5, 64), None, {})
    peers = hostile_peers(real)
    try:
        chosen = [peers[n] for n in ("garbage", "version", "huge")]
        status, lines, _, rss = loadtest(",".join(p.endpoint for p in chosen), 1, timeout_s=5)
    finally:
        close_all(peers.values())
    assert status == 1, lines[-10:]
    assert rss < HUGE_BYTES / 2 ** 20, f"the reader's peak RSS is {rss:.0f} MB"
    last = lines[-1]
    assert last.startswith("v2v-loadtest: ") and all(p.endpoint in last for p in chosen), lines
    assert "not valid msgpack" in last and "protocol version 11" in last and "no answer" in last, last


@pytest.mark.timeout(300)
def test_a_host_that_refuses_a_make_stays_in_the_fleet(tmp_path, videos):
    """A peer serving the real host's plan as another host (``another_host``) that refuses every
    make (code ``make``: one request refused, not the protocol broken) is not left out: each
    video it refuses is asked of the real host (and never of it again in the pass: not as a copy
    of what the head waits on, nor as a hedge), and both epochs are read whole. (Whether the
    second pass asks it again is the router's choice: a video stays with the host whose frame
    cache holds it while that one makes it in time.)"""
    _, want, base = setup(tmp_path, videos)
    refusals = []

    def refuse(h, frames):
        if h["type"] == "plan_ask":
            return [pack(real.to_wire())]
        if h["type"] != "make":
            return [b"\xc1 not msgpack"]
        refusals.append((h["epoch"], h["video"], tuple(h["ordinals"] or ()), h.get("move", False)))
        return [pack(Refused(h["request"], f"make: {h['video']!r:.100} is not made here (a test's refusal)",
                             "make").to_wire())]

    with ServeProcess(base) as host:
        with Link(host.endpoint, 60) as link:
            real = another_host(link.ask())
        peer = Peer(refuse)
        try:
            status, lines, report, _ = loadtest(f"{host.endpoint},{peer.endpoint}", 2 * -(-len(want) // 2))
        finally:
            peer.close()
    assert status == 0, lines[-10:]
    assert report["unique_samples"] == report["samples"] == 2 * len(want) and report["epochs_seen"] == [0, 1], report
    assert not [ln for ln in lines if peer.endpoint in ln and "left out" in ln], lines
    # asked makes, each once a pass: a make refused is not asked of it again, as a copy or a hedge;
    # a move of it to an idle host (``share_idle``) is the same make asked once more, sent before its
    # refusal came back (the pass forgets a refused make, so it never moves it afterwards)
    asked = [(e, v, o) for e, v, o, move in refusals if not move]
    assert asked and len(asked) == len(set(asked)), refusals
    moves = [(e, v, o) for e, v, o, move in refusals if move]
    assert len(moves) == len(set(moves)) and set(moves) <= set(asked), refusals


@pytest.mark.timeout(300)
def test_peers_left_out_are_named_once_by_a_job_of_dataloader_workers_over_two_epochs(tmp_path, videos):
    """A real host with a peer of a made-up plan and one answering garbage, read by a dataset asked
    in the job's process and read by two DataLoader workers over two epochs (four passes, each
    longer than the fleet's resolve period, when the list is asked again): each peer is named
    once, and every sample is read."""
    from tests.test_scale_out import corpus, expected_ids, layout

    root = corpus(tmp_path, videos, copies=3)
    want = expected_ids(root)
    with ServeProcess(["--videos", str(root), *layout()]) as real:
        with Link(real.endpoint, 60) as link:
            info = link.ask()
        peers = hostile_peers(info)
        try:
            chosen = [peers["made-up plan"], peers["garbage"]]
            # steps of 1.5 s: each pass outlasts RESOLVE_S (5 s), so each worker's fleet asks its list again
            status, lines, out = read_fleet(",".join([real.endpoint] + [p.endpoint for p in chosen]), 2, workers=2,
                                            step_s=1.5)
        finally:
            close_all(peers.values())
    assert status == 0, lines[-10:]
    assert sorted(out["ids"]) == sorted(f"{e}:{s}" for e in (0, 1) for s in want)
    for p in chosen:
        assert sum(p.endpoint in ln for ln in lines) == 1, [ln for ln in lines if p.endpoint in ln]

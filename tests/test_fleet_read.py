"""A fleet: several ``v2v-serve`` hosts of one corpus (no ``--shard``) read as the one plan a single
server serves, each video made by the host the reader routes it to (``v2v_client.fleet_read``).
Real servers on 127.0.0.1 on the bundled clips; every test is bounded and stops what it starts."""
from __future__ import annotations

import logging
import os
import signal

import pytest
import torch

from harness.serve import ServeProcess
from v2v_client import V2VStreamDataset

from tests.test_plan_shards import read
from tests.test_scale_out import OUTPUTS, corpus, expected_ids, layout


def first_steps(ds, steps):
    """The ids of the first ``steps`` batches of ``ds`` and the position after them."""
    ids, position = [], None
    for i, batch in enumerate(ds):
        ids += [s for s, p in zip(batch["sample_ids"], batch["padding"].tolist()) if not p]
        position = batch["position"]
        if i == steps - 1:
            break
    return ids, position


def setup(tmp_path, videos):
    """The test corpus, every sample id one epoch of it holds, and a host's ``v2v-serve`` arguments."""
    root = corpus(tmp_path, videos)
    return root, expected_ids(root), ["--videos", str(root), *layout()]


def same_content(a, b, ids):
    return all(torch.equal(a[s][0], b[s][0]) and torch.equal(a[s][1], b[s][1]) for s in ids)


@pytest.mark.timeout(900)
def test_a_fleet_reads_one_servers_plan_and_a_position_resumes_at_any_fleet_size(tmp_path, videos):
    """Two hosts read together give one server's sequence, id for id and byte for byte, with no
    padding but the last step's; a position taken from the two resumes on one host and on three."""
    root, want, base = setup(tmp_path, videos)
    with ServeProcess(base) as one:
        single, order1, pad1, _ = read(V2VStreamDataset(one.endpoint, outputs=OUTPUTS, timeout_s=120))
        with ServeProcess(base) as b, ServeProcess(base) as c:
            pair = f"{one.endpoint},{b.endpoint}"
            fleet, order2, pad2, _ = read(V2VStreamDataset(pair, outputs=OUTPUTS, timeout_s=120))
            assert order2 == order1 and sorted(order1) == want  # the one plan's order
            assert pad2 == pad1
            assert same_content(single, fleet, want)
            first, position = first_steps(V2VStreamDataset(pair, outputs=OUTPUTS, timeout_s=120), 2)
            assert first == order1[:len(first)]
            for hosts in (one.endpoint, f"{one.endpoint},{b.endpoint},{c.endpoint}"):
                again = V2VStreamDataset(hosts, outputs=OUTPUTS, timeout_s=120)
                again.load_state_dict(position)
                got, rest, _, _ = read(again)
                assert first + rest == order1, hosts
                assert same_content(single, got, rest)


@pytest.mark.timeout(600)
def test_a_host_killed_mid_epoch_costs_the_fleet_nothing_but_time(tmp_path, videos):
    """One host SIGKILLed after the first step: its videos go to the other host; every id once,
    with the content one server gives."""
    root, want, base = setup(tmp_path, videos)
    with ServeProcess(base) as one:
        single, order, _, _ = read(V2VStreamDataset(one.endpoint, outputs=OUTPUTS, timeout_s=120))
    with ServeProcess(base) as a, ServeProcess(base) as b:
        ds = V2VStreamDataset(f"{a.endpoint},{b.endpoint}", outputs=OUTPUTS, timeout_s=120, retry_s=2)
        got, ids = {}, []
        for i, batch in enumerate(ds):
            for j, sid in enumerate(batch["sample_ids"]):
                if not batch["padding"][j]:
                    got[sid] = (batch["voxels"][j].clone(), batch["frames"][j].clone())
                    ids.append(sid)
            if i == 0:
                os.kill(b.proc.pid, signal.SIGKILL)
        assert ids == order and sorted(ids) == want
        assert same_content(single, got, want)


@pytest.mark.timeout(600)
def test_a_host_serving_another_plan_is_named_and_left_out(tmp_path, videos, caplog):
    """A host started with another seed is named in one line with what differs; the job reads
    the first host's plan from the rest."""
    root, want, base = setup(tmp_path, videos)
    other = list(base)
    other[other.index("--seed") + 1] = "6"  # layout's is 5
    with ServeProcess(base) as a, ServeProcess(other) as b:
        with caplog.at_level(logging.WARNING, logger="v2v.client"):
            _, order, _, _ = read(V2VStreamDataset(f"{a.endpoint},{b.endpoint}", outputs=OUTPUTS, timeout_s=120))
        assert sorted(order) == want
        named = [r.getMessage() for r in caplog.records if b.endpoint in r.getMessage()]
        assert named and "left out of the fleet" in named[0] and "seed 6 (this plan: 5)" in named[0]


def test_the_largest_make_fits_a_client_message_and_a_longer_one_is_refused_naming_the_field():
    from v2v_wire.plan import PlanIdentity
    from v2v_wire.plan_messages import MAX_MAKE_PATH, MAX_MAKE_SAMPLES, Make, WireError, decode_plan_client
    from v2v_wire.protocol import MAX_CLIENT_MSG, OUTPUTS, pack

    plan = PlanIdentity("f" * 16, "e" * 16, 2 ** 62, 2 ** 31)
    largest = Make(2 ** 62, 2 ** 31 - 1, "v" * MAX_MAKE_PATH, tuple([2 ** 62 - 1] * MAX_MAKE_SAMPLES), OUTPUTS, plan,
                   "zstd")
    frame = pack(largest.to_wire())
    assert len(frame) <= MAX_CLIENT_MSG
    assert decode_plan_client(frame, MAX_CLIENT_MSG) == largest
    for bad, field in ((Make(1, 0, "v" * (MAX_MAKE_PATH + 1), (0,), OUTPUTS, plan), "video"),
                       (Make(1, 0, "a.mp4", tuple(range(MAX_MAKE_SAMPLES + 1)), OUTPUTS, plan), "ordinals")):
        with pytest.raises(WireError, match=f"make: field '{field}'"):
            decode_plan_client(pack(bad.to_wire()), MAX_CLIENT_MSG)


def test_the_fetch_side_imports_without_torch():
    """The reader's sockets, fetch loops and fleet read without torch: only the dataset makes tensors."""
    import subprocess
    import sys

    code = ("import sys; sys.modules['torch'] = None\n"
            "import v2v_client.fetch, v2v_client.servers, v2v_client.fleet_read, v2v_client.fleet_pass\n"
            "try:\n    import v2v_client.plan_dataset\nexcept ImportError:\n    print('dataset needs torch')\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "dataset needs torch"  # the check can fail: torch is blocked


@pytest.mark.timeout(300)
def test_a_make_the_plan_cannot_take_is_refused_in_one_line_and_the_server_serves_on(tmp_path, videos):
    """A make naming a video the plan lacks, or a sample past a known video's windows: one refusal
    with code ``make`` naming it; the same server then answers a good make with its rows and its
    decode capacity."""
    from v2v_client.fetch import Link
    from v2v_wire.plan_messages import Make, Refused, Rows

    root, want, base = setup(tmp_path, videos)
    with ServeProcess(base) as one, Link(one.endpoint, 60) as link:
        plan = link.ask().plan
        video, window = want[0].split("#")

        def answer(make):
            link._send(make.to_wire())
            got = link._recv(__import__("time").monotonic() + 60)
            assert got is not None
            return got[0]

        for bad, named in ((Make(1, 0, "nowhere.mp4", (0,), OUTPUTS, plan), "nowhere.mp4"),
                           (Make(2, 0, video, (0,), OUTPUTS, plan), None)):
            msg = answer(bad)
            if named is None:  # the video's windows are not known before its decode: made, not refused
                assert isinstance(msg, Rows) and msg.sample_ids == [f"{video}#0"]
                continue
            assert isinstance(msg, Refused) and msg.code == "make" and named in msg.message
            assert "\n" not in msg.message
        # a sample past its windows: refused once they are known, else one padding row once its
        # decode learns them (never a make that waits for ever, nor a video decoded again and again)
        msg = answer(Make(3, 0, video, (10 ** 6,), OUTPUTS, plan))
        if isinstance(msg, Refused):
            assert msg.code == "make" and "1000000" in msg.message
        else:
            assert isinstance(msg, Rows) and msg.padding == [True] and "past" in msg.params[0]["padding"]
        last = answer(Make(4, 0, video, (int(window),), OUTPUTS, plan))
        assert isinstance(last, Rows)
        assert last.rate > 0  # the host's own measure of its decode capacity, what readers weigh it by


@pytest.mark.timeout(600)
def test_a_make_withdrawn_while_it_waits_is_never_decoded(tmp_path, videos):
    """One worker decodes the first of three makes; the third is withdrawn while it waits (a
    reader had its samples from another host first): the second is answered, the third never,
    and the host decodes the two videos only (what its feed says it made)."""
    import time

    from v2v_client.fetch import Link
    from v2v_client.plan_dataset import open_stream
    from v2v_wire.plan_messages import Make, Rows, Withdraw

    root, want, base = setup(tmp_path, videos)
    firsts = list(dict.fromkeys(s.split("#")[0] for s in want))[:3]
    with ServeProcess(base) as one, Link(one.endpoint, 60) as link:
        info = link.ask()
        assert info.withdraws  # it says it takes a Withdraw: a reader sends one to no other server
        for request, video in enumerate(firsts, 1):
            link._send(Make(request, 0, video, (0,), OUTPUTS, info.plan).to_wire())
        link._send(Withdraw(3).to_wire())
        answered, end = set(), time.monotonic() + 120
        while len(answered) < 2 and time.monotonic() < end:
            got = link._recv(end)
            if got is not None and isinstance(got[0], Rows):
                answered.add(got[0].request)
        assert answered == {1, 2}
        time.sleep(3)  # the worker is idle: nothing waits on the third video
        assert link._recv(time.monotonic() + 1) is None
        feed = open_stream(one.endpoint, timeout_s=30).server_feed()
        samples = {v: sum(1 for s in want if s.split("#")[0] == v) for v in firsts}  # a decode makes all of a video's
        assert feed["samples_made_by_epoch"].get(0) == samples[firsts[0]] + samples[firsts[1]]


@pytest.mark.timeout(600)
def test_a_make_moved_off_a_host_takes_every_readers_waiting_make_with_it_and_is_never_decoded_there(
        tmp_path, videos):
    """A real host of one worker decodes one reader's first video while a second video waits
    there for two readers. One reader asks it again as a move (``Make.move``, a host it picked):
    the host answers both readers' makes of it with ``Moved`` to that host, the move included,
    and decodes only the first video (what its feed says it made)."""
    import time

    from v2v_client.fetch import Link
    from v2v_client.plan_dataset import open_stream
    from v2v_wire.plan_messages import Make, Moved, Rows

    root, want, base = setup(tmp_path, videos)
    first, second = list(dict.fromkeys(s.split("#")[0] for s in want))[:2]
    elsewhere = "tcp://127.0.0.1:9"
    with ServeProcess(base) as one, Link(one.endpoint, 60) as a, Link(one.endpoint, 60) as b:
        info = a.ask()
        a._send(Make(1, 0, first, (0,), OUTPUTS, info.plan).to_wire())
        a._send(Make(2, 0, second, (0,), OUTPUTS, info.plan, position=5).to_wire())
        b._send(Make(1, 0, second, (0,), OUTPUTS, info.plan, position=5).to_wire())
        time.sleep(0.5)  # both makes of the second video wait behind the first's decode
        a._send(Make(3, 0, second, (0,), OUTPUTS, info.plan, position=5, route=elsewhere, move=True).to_wire())
        got = {"a": [], "b": []}
        end = time.monotonic() + 120
        while (len(got["a"]) < 3 or not got["b"]) and time.monotonic() < end:
            for name, link in (("a", a), ("b", b)):
                m = link._recv(time.monotonic() + 0.2)
                if m is not None:
                    got[name].append(m[0])
        assert sorted((m.request, m.host) for m in got["a"] if isinstance(m, Moved)) == [(2, elsewhere), (3, elsewhere)]
        assert [(m.request, m.host) for m in got["b"]] == [(1, elsewhere)]
        assert [m.request for m in got["a"] if isinstance(m, Rows)] == [1]
        time.sleep(2)  # the worker is idle: nothing waits on the second video
        feed = open_stream(one.endpoint, timeout_s=30).server_feed()
        assert feed["samples_made_by_epoch"].get(0) == sum(1 for s in want if s.split("#")[0] == first)


@pytest.mark.timeout(600)
def test_a_fleet_pass_fails_a_stopped_host_over_while_its_loop_holds_a_step(tmp_path, videos):
    """The pass's thread turns while the loop holds the step it took (``Fleet.fetch_all``): a
    host stopped meanwhile (SIGSTOP, for the rest of the epoch) is pinged, found silent after
    ``HEDGE_S`` and its videos asked of the other host, so the loop, back after holding its step
    that long, never waits ``HEDGE_S`` on the stopped host (a pass turned only when its loop
    asks waits it then); the thread waits meanwhile (a few seconds of CPU over the hold, not
    the hold's length: it sleeps in its poll until a host or the loop wakes it); every id once,
    and the pass's thread ends with the epoch."""
    import threading
    import time

    from v2v_client.fleet_read import HEDGE_S

    root = corpus(tmp_path, videos, copies=3)
    want = expected_ids(root)
    base = ["--videos", str(root), *layout()]
    with ServeProcess(base) as a, ServeProcess(base) as b:
        it = iter(V2VStreamDataset(f"{a.endpoint},{b.endpoint}", batch_size=1, outputs=OUTPUTS, timeout_s=120))
        first = next(it)
        ids = [s for s, p in zip(first["sample_ids"], first["padding"].tolist()) if not p]
        os.kill(b.proc.pid, signal.SIGSTOP)
        try:
            cpu = time.process_time()
            time.sleep(HEDGE_S + 8)  # the loop holds its step: the pass's thread turns on
            cpu = time.process_time() - cpu  # waiting on the hosts and the loop, not spinning
            gaps, t = [], time.monotonic()
            for batch in it:
                gaps.append(time.monotonic() - t)
                t = time.monotonic()
                ids += [s for s, p in zip(batch["sample_ids"], batch["padding"].tolist()) if not p]
        finally:
            os.kill(b.proc.pid, signal.SIGCONT)
        assert sorted(ids) == want and len(ids) == len(set(ids))
        assert max(gaps) < HEDGE_S / 2, gaps
        assert cpu < 4.0, f"the pass's thread used {cpu:.1f} s of CPU while the loop held a step"
    assert not [th for th in threading.enumerate() if th.name == "v2v-fleet-pass"]

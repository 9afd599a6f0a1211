"""Stateful property tests of the pure delivery core (scheduler + ledger + batching).

A hypothesis ``RuleBasedStateMachine`` drives ``v2v_server.delivery.core.DeliveryCore`` with simulated
workers and trainers: trainers join, take, ack, break out of their loop, go silent, come back,
crash and resume from any older checkpoint; workers die, hang and send late copies; files fail
part-way. After every step:

* no sample id reaches a training loop twice in an epoch (over the histories the trainers'
  models actually kept: a trainer resumed from a checkpoint forgets what came after it);
* nothing is lost: when an epoch is announced complete every window of it was trained on
  or failed with a reason (and at the end every epoch completes);
* a client never holds more batches than it was granted, and the server's memory is bounded
  by prefetch and credits.

The simulated trainer follows the client protocol of ``v2v_client.dataset`` (acks flushed
before bye, revokes answered unless taken, discard on ``dropped``/long silence, resume state
sent in every hello).
"""
from __future__ import annotations

import collections
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import pytest
from hypothesis import HealthCheck, settings, strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, precondition, rule

from v2v_server.delivery.core import Batcher, DeliveryCore, DeliveryPolicy
from v2v_server.delivery.journal import Journal
from v2v_server.delivery.ledger import BatchRecord, DeliveryLedger
from v2v_server.delivery.schedule import EpochScheduler
from v2v_wire.ids import SampleKey, parse_sample_id, parse_sample_ids
from v2v_wire.messages import Ack, Bye, Heartbeat, Hello, Hold, Released, Resume

# corpus: windows per video; bad.mp4's window 1 changes frame size (fails every epoch), trunc.mp4
# fails to decode inside window 2 (the pass stops there every epoch), empty.mp4 has no window
WINDOWS = {"a.mp4": 3, "b.mp4": 2, "bad.mp4": 3, "trunc.mp4": 4, "empty.mp4": 0}
SIZE_CHANGE = {("bad.mp4", 1)}
DECODE_ERROR = {("trunc.mp4", 2)}
EPOCHS = 2
LEASE, TIMEOUT, REVOKE, TASK_TIMEOUT = 5.0, 10.0, 4.0, 20.0
PREFETCH = 2
MAX_CREDITS = 3
#: how often the interesting things happened (read by bench/ or a curious reader; not asserted)
SEEN = collections.Counter()


def expected_windows() -> set:
    out = set()
    for v, n in WINDOWS.items():
        for k in range(n):
            if (v, k) in SIZE_CHANGE:
                continue
            if any(v == dv and k >= dk for dv, dk in DECODE_ERROR):
                continue
            out.add((v, k))
    return out


def failed_windows(plan) -> set:
    """Windows the scheduler says failed in this epoch (with a reason); a file given up after
    repeated crashes has nothing from its failed window on."""
    out = set()
    for v, j in (plan.jobs.items() if plan is not None else ()):
        out |= {(v, k.window) for k in j.failed}
        if j.gave_up:
            first = min(j.failed).window
            out |= {(v, k) for k in range(first, WINDOWS[v])}
    return out


def windows_of(sid: str) -> tuple:
    """``(video, window)`` of a sample id (one crop per window here)."""
    key = parse_sample_id(sid)
    return key.video, key.window


@dataclass
class FakeSample:
    sample_id: str


@dataclass
class FakePayload:
    sample_ids: List[str]

    def subset(self, keep):
        return FakePayload([self.sample_ids[i] for i in keep])


def make_batch(samples):
    return FakePayload([s.sample_id for s in samples])


@dataclass
class SimWorker:
    ident: bytes
    task: Optional[dict] = None
    pos: int = 0
    failed: Dict[str, str] = field(default_factory=dict)
    hung: bool = False


@dataclass
class SimTrainer:
    """One trainer process (its dataset + training loop), as the client library behaves."""

    name: str
    gen: int = 0
    credits: int = 2
    connected: bool = False
    paused_since: Optional[float] = None
    inbox: list = field(default_factory=list)
    queue: list = field(default_factory=list)  # batches received, not yet taken
    taken: set = field(default_factory=set)
    current: dict = field(default_factory=dict)  # batch id -> token of its live queued copy
    completed: int = -1
    delivered: Dict[int, set] = field(default_factory=dict)  # the dataset's state
    history: list = field(default_factory=list)  # (epoch, sample id) trained on, in order
    checkpoints: list = field(default_factory=list)  # (completed, delivered copy, len(history))

    @property
    def ident(self) -> bytes:
        return f"{self.name}.{self.gen}".encode()

    def hello(self) -> Hello:
        d = {e: frozenset(parse_sample_id(s) for s in ids) for e, ids in self.delivered.items()}
        return Hello(("voxels",), self.credits, consumer=self.name, resume=Resume(self.completed, d))


class DeliveryMachine(RuleBasedStateMachine):
    def __init__(self):
        super().__init__()
        self.now = 0.0
        self.core = DeliveryCore(list(WINDOWS), DeliveryPolicy(batch_size=2, epochs=EPOCHS, lease_s=LEASE,
                                                               client_timeout_s=TIMEOUT, revoke_s=REVOKE,
                                                               max_credits=MAX_CREDITS, task_timeout_s=TASK_TIMEOUT,
                                                               shuffle="epoch", shuffle_buffer=6),
                                 make_batch)
        self.workers = [SimWorker(b"w0.0"), SimWorker(b"w1.0")]
        self.late: List[SimWorker] = []  # replaced workers that may still send
        self.trainers = [SimTrainer("t0"), SimTrainer("t1"), SimTrainer("t2", credits=1)]
        self.announced_checked = set()
        self.idle = {w.ident for w in self.workers}
        self.join(0)

    # ------------------------------------------------------------------ plumbing
    def deliver(self, msgs):
        """Hand each trainer its messages as the wire carries them (typed messages as headers)."""
        by_ident = {t.ident: t for t in self.trainers}
        for ident, m in msgs:
            t = by_ident.get(ident)
            if t is not None:
                t.inbox.append(m if isinstance(m, dict) else m.to_wire())

    def server_turn(self):
        for w in self.workers:
            if w.ident in self.idle:
                msg = self.core.task_for(w.ident, self.now)
                if msg is None:
                    break
                self.idle.discard(w.ident)
                w.task, w.pos, w.failed = msg, 0, {}
        sends, msgs = self.core.tick(self.now)
        self.deliver([(i, {"type": "batch", "batch_id": b.batch_id, "epoch": b.epoch,
                           "sample_ids": list(b.payload.sample_ids)}) for i, b in sends])
        self.deliver(msgs)
        self.check_announced()

    def replace_worker(self, w: SimWorker, keep_late: bool):
        slot, gen = w.ident.decode()[1:].split(".")
        new = SimWorker(f"w{slot}.{int(gen) + 1}".encode())
        self.workers[self.workers.index(w)] = new
        self.idle.discard(w.ident)
        self.idle.add(new.ident)
        if keep_late and w.task is not None:
            w.hung = False
            self.late.append(w)

    def work(self, w: SimWorker) -> None:
        """One step of a worker: one sample, a failed window, or done."""
        t = w.task
        video, epoch = t.video, t.epoch
        n = WINDOWS[video]
        while True:
            k = w.pos
            if k >= n:
                self.core.done(w.ident, t.task, n, w.failed, None)
                w.task = None
                self.idle.add(w.ident)
                return
            if (video, k) in DECODE_ERROR:  # decoding fails there, whether the window is wanted or not
                self.core.done(w.ident, t.task, k, w.failed, "decoding failed: truncated")
                w.task = None
                self.idle.add(w.ident)
                return
            if (k, 0) in t.skip:
                w.pos += 1
                continue
            if (video, k) in SIZE_CHANGE:
                w.failed[str(k)] = "frame size changed"
                w.pos += 1
                continue
            w.pos += 1
            self.core.sample(w.ident, t.task, SampleKey(video, k), self.now,
                             lambda lane: FakeSample(SampleKey(video, k).sample_id()))
            return

    # ------------------------------------------------------------------ trainer behaviour
    def io(self, t: SimTrainer) -> None:
        """The trainer's I/O thread handles everything in its inbox."""
        if self.paused(t):
            return
        while t.inbox:
            m = t.inbox.pop(0)
            kind = m["type"]
            if not t.connected:
                continue
            if kind == "batch":
                m = dict(m, token=object())
                t.current[m["batch_id"]] = m["token"]
                t.queue.append(m)
            elif kind == "revoke":
                SEEN["revoke"] += 1
                rel = [b for b in m["batch_ids"] if b in t.current and b not in t.taken]
                for b in rel:
                    del t.current[b]  # released: its queued copy is dead (and holds no arrays)
                if rel:
                    self.deliver(self.core.message(t.ident, Released(tuple(rel)), self.now))
            elif kind == "epoch_done":
                t.completed = max(t.completed, m["epoch"])
                for e in [e for e in t.delivered if e <= m["epoch"]]:
                    del t.delivered[e]
            elif kind == "error" and m.get("code") in ("dropped", "unknown_client"):
                SEEN["dropped"] += 1
                self.discard_and_rehello(t)

    def discard_and_rehello(self, t: SimTrainer) -> None:
        t.current.clear()
        t.queue.clear()
        self.deliver(self.core.hello(t.ident, t.hello(), self.now))

    def paused(self, t: SimTrainer) -> bool:
        return t.paused_since is not None

    # ------------------------------------------------------------------ rules
    @rule(i=st.integers(0, 2))
    def join(self, i):
        t = self.trainers[i]
        if t.connected or self.paused(t):
            return
        t.connected = True
        t.gen += 1  # a new iterator: a new connection identity
        t.inbox.clear()
        self.deliver(self.core.hello(t.ident, t.hello(), self.now))
        self.server_turn()

    @rule(i=st.integers(0, 2), n=st.integers(1, 4))
    def train(self, i, n):
        """The I/O thread catches up, then the training loop takes up to ``n`` batches."""
        for _ in range(n):
            self.io(self.trainers[i])
            self.train_step(i)

    def train_step(self, i):
        """The training loop takes one batch (ack, filter, yield, checkpoint)."""
        t = self.trainers[i]
        if not t.connected or self.paused(t) or not t.queue:
            return
        m = t.queue.pop(0)
        if t.current.get(m["batch_id"]) is not m["token"]:
            return
        del t.current[m["batch_id"]]
        e = m["epoch"]
        if e <= t.completed:  # an epoch it was told is complete: give it back, never ack what it drops
            self.deliver(self.core.message(t.ident, Released((m["batch_id"],)), self.now))
            return
        t.taken.add(m["batch_id"])
        self.deliver(self.core.message(t.ident, Ack((m["batch_id"],)), self.now))
        if e > t.completed:
            seen = t.delivered.setdefault(e, set())
            for s in m["sample_ids"]:
                if s not in seen:
                    seen.add(s)
                    t.history.append((e, s))
        t.checkpoints.append((t.completed, {k: set(v) for k, v in t.delivered.items()}, len(t.history)))
        SEEN["trained_batch"] += 1
        self.server_turn()

    @rule(i=st.integers(0, 2))
    def io_step(self, i):
        self.io(self.trainers[i])
        self.server_turn()

    @rule(i=st.integers(0, 2))
    def break_loop(self, i):
        """Leave the loop (max_steps, a rank stopping first): acks flushed, then bye; what was
        queued and not taken is dropped locally (the server re-sends it)."""
        t = self.trainers[i]
        if not t.connected or self.paused(t):
            return
        self.io(t)
        self.deliver(self.core.message(t.ident, Bye(), self.now))
        t.connected = False
        t.queue.clear()
        t.current.clear()
        self.server_turn()

    @rule(i=st.integers(0, 2))
    def pause(self, i):
        t = self.trainers[i]
        if t.connected and not self.paused(t):
            t.paused_since = self.now

    @rule(i=st.integers(0, 2))
    def wake(self, i):
        t = self.trainers[i]
        if not self.paused(t):
            return
        silent = self.now - t.paused_since
        t.paused_since = None
        if silent > 0.8 * TIMEOUT:  # it knows the server may have dropped it: hold nothing
            SEEN["long_silence"] += 1
            t.inbox.clear()
            self.discard_and_rehello(t)
        self.io(t)
        self.server_turn()

    @precondition(lambda self: any(t.checkpoints for t in self.trainers))
    @rule(data=st.data())
    def crash_and_resume(self, data):
        """A trainer dies and restarts from any older checkpoint (its model forgets the rest)."""
        i = data.draw(st.sampled_from([i for i, t in enumerate(self.trainers) if t.checkpoints]), label="trainer")
        t = self.trainers[i]
        SEEN["crash"] += 1
        SEEN["crash_with_checkpoints"] += len(t.checkpoints) > 1
        if t.checkpoints:
            j = data.draw(st.integers(0, len(t.checkpoints) - 1), label="checkpoint")
            completed, delivered, n = t.checkpoints[j]
            del t.checkpoints[j + 1:]
            SEEN["rollback"] += len(t.history) > n
            t.completed, t.delivered, t.history = completed, {k: set(v) for k, v in delivered.items()}, t.history[:n]
        else:
            t.completed, t.delivered, t.history = -1, {}, []
        t.queue.clear()
        t.inbox.clear()
        t.taken.clear()
        t.current.clear()
        t.paused_since = None
        t.connected = False  # the old connection just goes silent
        self.join(i)

    @rule(dt=st.sampled_from([0.5, 1.0, 3.0, 6.0]))
    def advance(self, dt):
        self.now += dt
        for t in self.trainers:
            if t.connected and not self.paused(t):
                self.deliver(self.core.message(t.ident, Heartbeat(), self.now))
        for w, job in self.core.timed_out(self.now):
            sw = next((x for x in self.workers if x.ident == w), None)
            if sw is not None:
                self.replace_worker(sw, keep_late=True)
        self.server_turn()

    @rule(n=st.integers(1, 6))
    def worker_steps(self, n):
        for _ in range(n):
            for w in self.workers:
                if w.task is not None and not w.hung and len(self.core.ledger.ready) < PREFETCH:
                    self.work(w)
            self.server_turn()

    @rule(i=st.integers(0, 1))
    def kill_worker(self, i):
        w = self.workers[i]
        self.core.worker_lost(w.ident)
        self.replace_worker(w, keep_late=False)
        self.server_turn()

    @rule(i=st.integers(0, 1))
    def hang_worker(self, i):
        if self.workers[i].task is not None:
            self.workers[i].hung = True

    @precondition(lambda self: bool(self.late))
    @rule()
    def late_copy(self):
        """A replaced (hung) worker wakes up and sends what it was making: ignored."""
        w = self.late.pop(0)
        SEEN["late_copy"] += 1
        before = sum(len(b.keys) for b in self.core.ledger.batches.values())
        made = self.core.samples_made
        if w.task is not None and w.pos < WINDOWS[w.task.video]:
            k = w.pos
            key = SampleKey(w.task.video, k)
            kept = self.core.sample(w.ident, w.task.task, key, self.now, lambda lane: FakeSample(key.sample_id()))
            assert not kept and self.core.samples_made == made
            self.core.done(w.ident, w.task.task, WINDOWS[w.task.video], {}, None)
        assert sum(len(b.keys) for b in self.core.ledger.batches.values()) == before

    # ------------------------------------------------------------------ invariants
    def trained(self):
        return collections.Counter(x for t in self.trainers for x in t.history)

    @invariant()
    def no_sample_twice_per_epoch(self):
        dup = [k for k, n in self.trained().items() if n > 1]
        assert not dup, f"trained twice: {dup}"

    @invariant()
    def credits_never_exceed_grants(self):
        for c in self.core.ledger.clients.values():
            assert self.core.ledger.table.held_count(c.ident) <= c.credits <= MAX_CREDITS
        for t in self.trainers:  # what a trainer holds locally is bounded by its credits
            assert len(t.current) <= min(t.credits, MAX_CREDITS)
            assert len([m for m in t.queue if t.current.get(m["batch_id"]) is m["token"]]) <= len(t.current)

    @invariant()
    def memory_bounded(self):
        n = len(self.core.ledger.batches) + sum(len(g) for g in self.core.batcher.pending.values()) / 2
        bound = PREFETCH + 2 * len(WINDOWS) + sum(min(t.credits, MAX_CREDITS) for t in self.trainers) * 2
        assert n <= bound, (n, bound)

    def check_announced(self):
        """An epoch announced complete holds every expected window: trained once, failed, or
        recorded for a consumer whose trainer has not said so yet (one that crashed after it was
        granted them and whose resume waits for its old connection to be dropped: its resume
        state makes them owed again, to it; the teardown checks they are trained then)."""
        for e in range(len(self.announced_checked), self.core.ends.told_upto + 1):
            self.announced_checked.add(e)
            got = {windows_of(s) for (ep, s) in self.trained() if ep == e}
            plan = self.core.sched.plans.get(e)
            failed = failed_windows(plan)
            recorded = {(k.video, k.window) for ks in (plan.records.values() if plan else ()) for k in ks}
            missing = expected_windows() - got - failed - recorded
            assert not missing, f"epoch {e} announced complete but {sorted(missing)} were never trained on"
            # only injected faults or repeated crashes may fail a window
            for v, j in (plan.jobs.items() if plan else []):
                for key, why in j.failed.items():
                    k = key.window
                    past_error = any(v == dv and k >= dk for dv, dk in DECODE_ERROR)
                    assert (v, k) in SIZE_CHANGE or past_error or "crash" in why or k >= WINDOWS[v], (v, k, why)

    def teardown(self):
        """Let everyone recover and run: every epoch completes, each expected window once."""
        for t in self.trainers:
            t.paused_since = None
        for w in list(self.workers):
            if w.hung:
                self.core.worker_lost(w.ident)
                self.replace_worker(w, keep_late=False)
        for i, t in enumerate(self.trainers):
            if not t.connected:
                self.join(i)
        for _ in range(3000):
            if self.core.finished():
                break
            self.now += 0.5
            for i, t in enumerate(self.trainers):
                self.io(t)
                self.deliver(self.core.message(t.ident, Heartbeat(), self.now))
                while t.queue:
                    self.train_step(i)
            for i, w in enumerate(self.workers):
                if w.task is not None and len(self.core.ledger.ready) < PREFETCH:
                    self.work(w)
            self.server_turn()
        assert self.core.finished(), "the stream never finished"
        counts = self.trained()
        for e in range(EPOCHS):
            plan = self.core.sched.plans.get(e)
            failed = failed_windows(plan)
            got = {windows_of(s) for (ep, s) in counts if ep == e}
            assert expected_windows() - failed <= got, (e, expected_windows() - failed - got)
        assert all(n == 1 for n in counts.values())


DeliveryMachine.TestCase.settings = settings(max_examples=250, stateful_step_count=80, deadline=None,
                                             suppress_health_check=list(HealthCheck))
TestDeliveryCore = DeliveryMachine.TestCase


# ---------------------------------------------------------------------- direct tests of the parts
def test_resume_state_is_authoritative_over_acks():
    """Checkpoint at step 4, crash after step 5, restart from step 4: step 5's samples are owed again."""
    s = EpochScheduler(["a.mp4"], epochs=1)
    t = s.next_task("w", 0.0)
    for k in range(3):
        assert s.accept_sample(t.task_id, "w", SampleKey("a.mp4", k), 0.0) == SampleKey("a.mp4", k)
    s.task_done(t.task_id, "w", 3)
    s.delivered("c", 0, [SampleKey("a.mp4", 0), SampleKey("a.mp4", 1), SampleKey("a.mp4", 2)])
    assert s.plans[0].complete
    s.apply_resume("c", -1, {0: {SampleKey("a.mp4", 0)}})  # the checkpoint knew only window 0
    assert s.owed(0) == {SampleKey("a.mp4", 1), SampleKey("a.mp4", 2)} and not s.plans[0].complete
    t2 = s.next_task("w", 1.0)
    assert t2.epoch == 0 and t2.skip == frozenset({SampleKey("a.mp4", 0)})


def test_a_failing_window_is_lost_for_that_epoch_only():
    s = EpochScheduler(["a.mp4"], epochs=2)
    t = s.next_task("w", 0.0)
    s.accept_sample(t.task_id, "w", SampleKey("a.mp4", 0), 0.0)
    s.task_done(t.task_id, "w", 1, error="decoding failed")  # the pass stopped inside window 1
    s.delivered("c", 0, [SampleKey("a.mp4", 0)])
    assert s.plans[0].complete and s.plans[0].jobs["a.mp4"].failed == {SampleKey("a.mp4", 1): "decoding failed"}
    t = s.next_task("w", 1.0)
    assert (t.epoch, t.video, t.skip) == (1, "a.mp4", frozenset())  # the next epoch tries the whole file again


def test_hung_task_is_reassigned_and_its_late_copy_ignored():
    s = EpochScheduler(["a.mp4"], epochs=1)
    t = s.next_task("w1", 0.0)
    assert s.accept_sample(t.task_id, "w1", SampleKey("a.mp4", 0), 1.0) is not None
    assert s.expire(5.0, 10.0) == []
    [(w, job)] = s.expire(12.0, 10.0)
    assert w == "w1" and job.state == "queued"
    t2 = s.next_task("w2", 12.0)
    assert t2.task_id != t.task_id and t2.skip == frozenset({SampleKey("a.mp4", 0)})  # live in a batch already
    assert s.accept_sample(t.task_id, "w1", SampleKey("a.mp4", 1), 13.0) is None  # the late copy
    assert s.task_done(t.task_id, "w1", 3) is None


def _core_with_a_task(task_timeout_s: float, stall_s=None):
    """A core with one client and worker ``w``'s task, given at t = 0 and sent its first sample."""
    core = DeliveryCore(["a.mp4"], DeliveryPolicy(batch_size=1, epochs=1, lease_s=1e6, client_timeout_s=1e6,
                                                  task_timeout_s=task_timeout_s), make_batch, stall_s=stall_s)
    core.hello(b"c", Hello(("voxels",), 2), 0.0)
    assert core.timed_out(0.0, True) == []
    msg = core.task_for(b"w", 0.0)
    assert core.sample(b"w", msg.task, SampleKey("a.mp4", 0), 0.0, lambda lane: FakeSample("a.mp4#0"))
    return core, msg


def test_a_task_is_not_timed_out_while_the_server_does_not_read_its_worker():
    """The shell stops reading its workers (enough batches wait for a stopped trainer): an hour
    of that is no silence of the worker; once read again, only the silence while read counts."""
    core, msg = _core_with_a_task(task_timeout_s=5.0)
    assert core.timed_out(1.0, True) == []
    for t in range(2, 3601):  # a loop turn a second, none reading the workers
        assert core.timed_out(float(t), False) == []
    assert core.timed_out(3603.0, True) == []  # read 1 s before the stop, 3 s after it: 4 s of silence
    assert core.sample(b"w", msg.task, SampleKey("a.mp4", 1), 3603.0, lambda lane: FakeSample("a.mp4#1"))
    assert core.timed_out(3607.0, True) == []  # 4 s since the sample, read all along
    [(w, job)] = core.timed_out(3609.0, True)
    assert w == b"w" and job.video == "a.mp4" and job.state == "queued"


def test_a_task_silent_while_its_worker_is_read_times_out():
    core, _ = _core_with_a_task(task_timeout_s=5.0)
    for t in range(1, 5):
        assert core.timed_out(float(t), True) == []
    assert core.timed_out(4.5, True) == []
    [(w, _)] = core.timed_out(5.5, True)
    assert w == b"w"


def test_a_stall_of_the_servers_loop_is_not_a_workers_silence():
    """A gap between two turns of the loop over ``stall_s`` (the process stopped) is not counted."""
    core, _ = _core_with_a_task(task_timeout_s=5.0, stall_s=1.0)
    assert core.timed_out(0.5, True) == []
    assert core.timed_out(60.0, True) == []  # stopped from 0.5 s to 60 s: not counted
    for t in range(61, 65):
        assert core.timed_out(float(t), True) == []
    [(w, _)] = core.timed_out(65.0, True)  # 0.5 s before the stall, 5 s after it
    assert w == b"w"


def test_ack_of_unknown_or_resent_batch_frees_no_credit():
    led = DeliveryLedger(lease_s=1.0, client_timeout_s=100.0, max_credits=64, revoke_s=50.0)
    led.join(b"a", "A", ("voxels",), 1, 0.0)
    led.join(b"b", "B", ("voxels",), 1, 0.0)
    for i in range(4):
        led.add_batch(BatchRecord(i, 0, [("v", i)], None, outputs=frozenset({"voxels"})))
    sends, _ = led.sends(0.0)
    assert sorted(i for i, _ in sends) == [b"a", b"b"]
    held_a = next(b.batch_id for i, b in sends if i == b"a")
    revokes, drops = led.expire(2.0)  # leases expired: asked back
    assert revokes and not drops
    a = led.clients[b"a"]
    assert led.ack(b"a", [held_a]) == [] and led.free(a) == 0  # not granted: an ack frees nothing
    assert led.hold(b"a", [held_a, held_a, 99, 3]) == ([held_a], [led.batches[held_a]])  # each id once
    assert [b.batch_id for b in led.ack(b"a", [held_a, held_a, 99, 3])] == [held_a] and led.free(a) == 1
    sends, _ = led.sends(2.0)
    assert len(sends) == 1 and led.free(a) == 0  # one slot, never more


def test_unanswered_revoke_expires_and_drops_the_client():
    led = DeliveryLedger(lease_s=1.0, client_timeout_s=100.0, max_credits=64, revoke_s=3.0)
    led.join(b"a", "A", ("voxels",), 2, 0.0)
    led.add_batch(BatchRecord(0, 0, [("v", 0)], None, outputs=frozenset({"voxels"})))
    led.sends(0.0)
    led.touch(b"a", 1.5)
    revokes, drops = led.expire(1.5)
    assert revokes == {b"a": [0]}
    led.touch(b"a", 5.0)  # it heartbeats but never answers the revoke
    revokes, drops = led.expire(5.0)
    assert [d[0] for d in drops] == [b"a"] and list(led.ready) == [0] and b"a" not in led.clients


def test_a_granted_batch_has_no_lease_and_is_never_taken_back():
    led = DeliveryLedger(lease_s=1.0, client_timeout_s=100.0, max_credits=64, revoke_s=3.0)
    led.join(b"a", "A", ("voxels",), 3, 0.0)
    for i in range(3):
        led.add_batch(BatchRecord(i, 0, [("v", i)], None, outputs=frozenset({"voxels"})))
    led.sends(0.0)
    ok, new = led.hold(b"a", [0, 7])  # asked before its lease ran out; 7 is not its batch
    assert ok == [0] and [b.batch_id for b in new] == [0]
    led.touch(b"a", 1.5)
    assert led.expire(1.5) == ({b"a": [1, 2]}, [])  # only the batches not granted are asked back
    ok, new = led.hold(b"a", [1])  # asked for after the revoke was sent: granted, the revoke withdrawn
    assert ok == [1] and led.hold(b"a", [1]) == ([1], [])  # asked again: granted already, nothing new
    led.touch(b"a", 500.0)
    assert led.expire(500.0) == ({}, [(b"a", "did not answer the revoke of batch(es) [2] within 3 s")])
    # dropped: the batch leased goes back; the granted ones stay its consumer's (it may have yielded
    # them): stranded until its next hello says whether its loop got them
    assert list(led.ready) == [2] and led.table.states() == {"ready": 1, "leased": 0, "revoked": 0, "granted": 0,
                                                        "stranded": 2}
    kept, back = led.settle("A", lambda b: b.batch_id == 0)  # the resume state names batch 0's samples
    assert [b.batch_id for b in kept] == [0] and [b.batch_id for b in back] == [1] and led.ready == [1, 2]


def test_a_granted_batch_given_back_goes_to_the_queue_and_an_ack_frees_its_slot():
    led = DeliveryLedger(lease_s=10.0, client_timeout_s=100.0, max_credits=64)
    led.join(b"a", "A", ("voxels",), 2, 0.0)
    for i in range(2):
        led.add_batch(BatchRecord(i, 0, [("v", i)], None, outputs=frozenset({"voxels"})))
    led.sends(0.0)
    led.hold(b"a", [0, 1])
    assert led.free(led.clients[b"a"]) == 0  # granted and not acknowledged: still its slots
    assert [b.batch_id for b in led.ack(b"a", [0])] == [0] and led.free(led.clients[b"a"]) == 1
    back, ungranted = led.released(b"a", [1])
    assert back == [1] and [b.batch_id for b in ungranted] == [1] and list(led.ready) == [1]


def test_twenty_clients_share_fairly():
    led = DeliveryLedger(lease_s=100.0, client_timeout_s=100.0, max_credits=64)
    idents = [bytes([i]) for i in range(20)]
    for i in idents:
        led.join(i, i, ("voxels",), 4, 0.0)
    got = collections.Counter()
    for n in range(400):
        led.add_batch(BatchRecord(n, 0, [("v", n)], None, outputs=frozenset({"voxels"})))
        for ident, b in led.sends(0.0)[0]:
            got[ident] += 1
            led.hold(ident, [b.batch_id])
            led.ack(ident, [b.batch_id])
    assert len(got) == 20 and max(got.values()) - min(got.values()) <= 1


def test_a_batch_moves_between_states_only_by_the_tables_transitions():
    """The table's transitions (docs/delivery.md, "The server's table"): each asks its batch to
    be in the states it leaves; any other move is a TransitionError, and the indexes follow."""
    from v2v_server.delivery.table import BatchTable, TransitionError

    t = BatchTable()
    t.add(BatchRecord(0, 0, [SampleKey("v", 0)]))
    with pytest.raises(TransitionError, match="batch 0 is ready, not leased or revoked"):
        t.grant(0, "A", 0.0)
    t.lease(0, b"a", 5.0)
    assert t.held_by(b"a") == [0] and t.ready() == [] and t.get(0).state == "leased"
    t.revoke(0, 9.0)
    t.grant(0, "A", 1.0)
    with pytest.raises(TransitionError):
        t.revoke(0, 2.0)  # a grant is never asked back
    t.strand(0)
    assert t.held_by(b"a") == [] and t.stranded_of("A") == [0]
    t.requeue(0)
    assert t.ready() == [0] and t.get(0).avoid is None and t.stranded_of("A") == []
    t.lease(0, b"b", 5.0)
    t.grant(0, "B", 2.0)
    assert t.retire(0).consumer == "B" and 0 not in t.batches and (t.sent, t.resent, t.acked) == (2, 1, 1)
    with pytest.raises(TransitionError, match="batch 0 is gone"):
        t.requeue(0)


def test_ddp_group_waits_for_all_ranks():
    led = DeliveryLedger(lease_s=100.0, client_timeout_s=10.0, max_credits=64)
    led.join(b"r0", ("g", 0), ("voxels",), 2, 0.0, group="g", rank=0, world_size=2)
    led.add_batch(BatchRecord(0, 0, [("v", 0)], None, outputs=frozenset({"voxels"})))
    assert led.sends(1.0)[0] == []  # rank 1 has not said hello yet: its resume state may hold samples
    led.join(b"r1", ("g", 1), ("voxels",), 2, 2.0, group="g", rank=1, world_size=2)
    assert len(led.sends(2.0)[0]) == 1


def test_outputs_are_the_union_and_stale_batches_are_remade():
    core = DeliveryCore(["a.mp4"], DeliveryPolicy(batch_size=1, epochs=1, lease_s=100.0, client_timeout_s=100.0,
                                                  max_credits=4, task_timeout_s=100.0), make_batch)
    core.hello(b"v", Hello(("voxels",), 2), 0.0)
    msg = core.task_for(b"w", 0.0)
    assert msg.outputs == ("voxels",)
    core.sample(b"w", msg.task, SampleKey("a.mp4", 0), 0.0, lambda lane: FakeSample("a.mp4#0"))
    core.forget(b"v")
    core.hello(b"f", Hello(("voxels", "flow"), 2), 0.0)
    sends, _ = core.tick(0.0)
    assert sends == [] and core.sched.owed(0) == set()  # not sent without flow; window 0 must be made again
    core.done(b"w", msg.task, 1, {}, None)
    msg2 = core.task_for(b"w", 1.0)
    assert msg2.outputs == ("voxels", "flow") and msg2.skip == ()


@pytest.mark.parametrize("sid,ok", [("a.mp4#3", True), ("a#b.mp4#0", True), ("a.mp4#٣", False), ("a.mp4#", False),
                                     ("#1", False), (7, False), ("a.mp4#-1", False)])
def test_sample_id_parsing_rejects_non_ascii_digits(sid, ok):
    assert bool(parse_sample_ids([sid])) == ok


def test_a_sample_counts_only_under_its_own_key_in_its_own_task():
    """The scheduler keys samples by ``SampleKey``: a key naming another video than the task's,
    or a crop beyond ``crops_per_window``, is dropped; with K = 2 a failed window fails both
    its crops and the file's sample count is windows x K."""
    s = EpochScheduler(["a.mp4", "b.mp4"], epochs=1, crops_per_window=2)
    t = s.next_task("w", 0.0)
    other = "b.mp4" if t.video == "a.mp4" else "a.mp4"
    assert s.accept_sample(t.task_id, "w", SampleKey(other, 0, 0), 0.0) is None
    assert s.accept_sample(t.task_id, "w", SampleKey(t.video, 0, 2), 0.0) is None
    assert s.accept_sample(t.task_id, "w", (t.video, 0), 0.0) is None
    assert s.accept_sample(t.task_id, "w", SampleKey(t.video, 0, 1), 0.0) == SampleKey(t.video, 0, 1)
    s.task_done(t.task_id, "w", 3, {"1": "frame size changed"})
    job = s.plans[0].jobs[t.video]
    assert job.samples == 6
    assert job.failed == {SampleKey(t.video, 1, 0): "frame size changed", SampleKey(t.video, 1, 1): "frame size changed"}
    assert s.owed(0) == {SampleKey(t.video, w, c) for w, c in [(0, 0), (2, 0), (2, 1)]}


def test_an_epoch_makes_a_job_when_a_video_is_first_looked_up():
    """Opening an epoch makes no job per video (``schedule.Jobs``): the plan holds the jobs
    handed out or asked for, knows the epoch's size, and counts the done ones."""
    s = EpochScheduler([f"v{i}.mp4" for i in range(5)], epochs=1, shuffle_seed=0)
    t = s.next_task("w", 0.0)
    plan = s.plans[0]
    assert list(plan.jobs) == [t.video] and plan.progress() == (5, 0)
    other = next(v for v in s.videos if v != t.video)
    assert other not in plan.jobs and plan.jobs.get(other) is None
    assert plan.jobs[other].state == "queued" and plan.jobs[other].epoch == 0 and other in plan.jobs
    with pytest.raises(KeyError):
        plan.jobs["not_listed.mp4"]
    s.task_done(t.task_id, "w", 0)  # a file too short for a window: its job is done
    assert plan.progress() == (5, 1) and plan.jobs[t.video].state == "done"
    while (t := s.next_task("w", 1.0)) is not None:
        s.task_done(t.task_id, "w", 0)
    assert plan.progress() == (5, 5) and plan.complete and len(plan.jobs) == 5


def test_a_resume_state_replaces_a_record_of_an_epoch_not_open_yet():
    """A restarted server holds the journal's record of an epoch it has not opened (a grant
    ahead); the consumer's next hello, whose loop never got that grant, replaces it: its samples
    are made in that epoch (the record had stayed, and they reached no loop)."""
    s = EpochScheduler(["a.mp4"], epochs=2)
    s.apply_resume("c", -1, {1: {SampleKey("a.mp4", 0)}})  # the journal, read at start
    s.apply_resume("c", -1, {})  # the consumer's hello
    t = s.next_task("w", 0.0)
    s.task_done(t.task_id, "w", 2)
    s.delivered("c", 0, [SampleKey("a.mp4", 0), SampleKey("a.mp4", 1)])
    t = s.next_task("w", 1.0)
    assert (t.epoch, t.skip) == (1, frozenset())


class TinyStream:
    """A core serving one 4-window video in batches of 1 (3 epochs, no shuffle), one worker that
    makes whatever its task does not skip, and readers that hold then acknowledge every batch
    sent to them, unless told to keep it (``keep``: granted, never acknowledged) or to say
    nothing of it (``mute``: a paused reader)."""

    def __init__(self, journal=None, epochs: int = 3):
        self.core = DeliveryCore(["a.mp4"], DeliveryPolicy(batch_size=1, epochs=epochs, lease_s=5.0, client_timeout_s=100.0,
                                                           max_credits=4, task_timeout_s=100.0, shuffle="none"),
                                 make_batch, journal=journal)
        self.now = 0.0
        self.got: Dict[bytes, list] = collections.defaultdict(list)  # ident -> (epoch, sample id), in order
        self.told: Dict[bytes, list] = collections.defaultdict(list)  # ident -> (epoch, batches) of each epoch_done
        self.keep: set = set()  # readers that hold what they get and acknowledge nothing
        self.mute: set = set()  # readers that say nothing of what they get

    def hello(self, ident: bytes, consumer: str, resume: Resume = Resume(), **ddp) -> None:
        self.take(self.core.hello(ident, Hello(("voxels",), 1, consumer=consumer, resume=resume, **ddp), self.now))

    def take(self, msgs) -> None:
        for ident, m in msgs:
            if m.to_wire()["type"] == "epoch_done":
                self.told[ident].append((m.epoch, m.batches))

    def read_every_epoch(self, ident: bytes, consumer: str) -> None:
        """Reader ``consumer`` reads all three epochs on ``ident`` (told each complete) and leaves."""
        self.hello(ident, consumer)
        for _ in range(20):
            self.turn()
        assert [e for e, _ in self.told[ident]] == [0, 1, 2]
        self.core.message(ident, Bye(), self.now)
        self.turn()

    def turn(self) -> None:
        self.now += 1.0
        task = self.core.task_for(b"w", self.now)
        if task is not None:
            for k in range(4):
                if (k, 0) not in task.skip:
                    key = SampleKey("a.mp4", k)
                    self.core.sample(b"w", task.task, key, self.now, lambda lane, key=key: FakeSample(key.sample_id()))
            self.core.done(b"w", task.task, 4, {}, None)
        sends, msgs = self.core.tick(self.now)
        for ident, b in sends:
            self.got[ident] += [(b.epoch, sid) for sid in b.payload.sample_ids]
            if b.batch_id >= 0 and ident not in self.mute:
                self.core.message(ident, Hold((b.batch_id,)), self.now)
                if ident not in self.keep:
                    self.core.message(ident, Ack((b.batch_id,)), self.now)
        self.take(msgs)


def test_a_reader_back_after_the_others_ran_every_epoch_gets_its_rolled_back_samples_again():
    """Reader a took one batch of epoch 0 and left; b read all three epochs (the server keeps
    two complete ones, so epoch 0's books go); a resumes from a checkpoint taken before that
    batch. Its model lost the sample: a, having been told no epoch complete, finds epoch 0 kept
    for it (its own record, not the epoch's), and gets that sample again, the only one made
    (docs/delivery.md limit (e); simulator finding F1, ``trainers`` seed 144)."""
    s = TinyStream()
    s.hello(b"a", "a")
    s.turn()
    [(_, mine)] = s.got[b"a"]
    s.core.message(b"a", Bye(), s.now)
    s.hello(b"b", "b")
    for _ in range(20):
        s.turn()
    assert [e for e, _ in s.told[b"b"]] == [0, 1, 2] and len(s.got[b"b"]) == 11
    s.hello(b"a.2", "a", Resume(-1, {}))
    for _ in range(5):
        s.turn()
    assert s.got[b"a.2"] == [(0, mine)] and [e for e, _ in s.told[b"a.2"]] == [0, 1, 2]


def _second_process_reads_after(old_speaks_at) -> list:
    """Consumer "a" read by process p1; a hello of process p2 for it at t=1; p1's connection
    speaks at each of ``old_speaks_at`` (several messages at once each time), p2's heartbeats
    every second. Returns what the server told p2's connection, up to t=150."""
    s = TinyStream()  # client_timeout_s 100, no stall detection
    said = []
    s.core.hello(b"old", Hello(("voxels",), 1, consumer="a", instance="p1", hello_id=1), 0.0)
    said += s.core.hello(b"new", Hello(("voxels",), 1, consumer="a", instance="p2", hello_id=2), 1.0)
    for t in range(2, 151):
        if t in old_speaks_at:
            for _ in range(3):
                said += s.core.message(b"old", Heartbeat(1), float(t))
        said += s.core.message(b"new", Heartbeat(2), float(t))
        said += s.core.tick(float(t))[1]
    return [m.to_wire() for ident, m in said if ident == b"new"]


def test_a_dead_readers_last_messages_read_late_at_once_never_refuse_its_restart():
    """A restarted trainer's hello waits for its killed process's connection. That process's last
    messages, held by a network cut (or read late by a stalled server), arrive together 5 s after
    the hello: they prove nothing, so the hello is let in once the old connection is dropped for
    silence, not refused ``claimed`` (simulator seeds mixed 14499, 18822, 28580: an honest trainer
    failed). A process that speaks twice, 2 s apart, after the hello lives: refused."""
    told = _second_process_reads_after({6})
    assert [m["type"] for m in told] == ["welcome"], told
    told = _second_process_reads_after({6, 9})
    assert told and told[0]["type"] == "error" and told[0]["code"] == "claimed", told


def test_a_ddp_rank_given_back_a_grant_of_an_epoch_the_others_finished_is_padded():
    """A DDP job (2 ranks) left holding a grant of epoch 0 each, unacknowledged, while a trainer
    read every epoch; the job restarts from a checkpoint before them: each rank's hello gives
    its grant back and the ranks read them again. Epoch 0 is kept for the ranks, so its
    ``epoch_done`` says how many batches each rank yields (the job hung in an all-reduce when
    it carried no count: simulator finding F7, ``ddp`` seed 90)."""
    s = TinyStream()
    s.keep = {b"r0", b"r1"}
    s.hello(b"r0", "j", group="g", rank=0, world_size=2)
    s.hello(b"r1", "j", group="g", rank=1, world_size=2)
    s.turn()
    assert len(s.got[b"r0"]) == len(s.got[b"r1"]) == 1
    s.core.message(b"r0", Bye(), s.now)
    s.core.message(b"r1", Bye(), s.now)
    s.hello(b"b", "b")
    for _ in range(20):
        s.turn()
    assert [e for e, _ in s.told[b"b"]] == [0, 1, 2]
    s.hello(b"r0.2", "j", Resume(-1, {}), group="g", rank=0, world_size=2)
    s.hello(b"r1.2", "j", Resume(-1, {}), group="g", rank=1, world_size=2)
    for _ in range(5):
        s.turn()
    got = [len(s.got[b"r0.2"]), len(s.got[b"r1.2"])]
    assert sum(got) == 2, got  # the two grants given back, read again
    for ident in (b"r0.2", b"r1.2"):
        assert s.told[ident][0] == (0, max(got)), s.told[ident]  # the rank that got fewer pads up to it


def test_a_resume_more_than_keep_epochs_behind_what_its_consumer_was_told_is_refused_in_one_line():
    """Reader a read all three epochs and was told each complete; the server keeps its records
    of the newest two only. Its resume from a checkpoint taken before epoch 0 ended would lose
    what its model forgot of epoch 0 in silence, so it is refused before any batch, in one line
    naming the consumer, the state's epoch, the newest epoch told and what to load; a resume
    within two epochs and a new consumer are let in (docs/delivery.md limit (e); simulator
    finding F20, ``trainers`` seed 701)."""
    s = TinyStream()
    s.read_every_epoch(b"a", "a")
    [(_, err)] = s.core.hello(b"a.2", Hello(("voxels",), 1, consumer="a", resume=Resume(-1, {})), s.now)
    assert err.to_wire()["type"] == "error" and err.code == "resume" and "\n" not in err.message
    assert "consumer 'a'" in err.message and "epoch -1" in err.message and "up to 2" in err.message
    assert "checkpoint saved after epoch 0 ended" in err.message
    s.turn()
    assert not s.got[b"a.2"]
    for ident, consumer, resume in [(b"a.3", "a", Resume(0, {})), (b"c", "c", Resume(-1, {}))]:
        [(_, welcome)] = s.core.hello(ident, Hello(("voxels",), 1, consumer=consumer, resume=resume), s.now)
        assert welcome.to_wire()["type"] == "welcome", welcome
        s.core.message(ident, Bye(), s.now)


def test_a_resume_behind_what_a_rank_beyond_its_world_size_was_told_is_refused_in_one_line():
    """A DDP job of three ranks: ranks 0 and 1 left in epoch 0, rank 2 read on and was told all
    three epochs complete (the server keeps its records of the newest two only). The job restarts
    from nothing at world size 2: rank 0's hello speaks for rank 2 (beyond its world size, no
    connection reads it), whose epoch-0 samples the job's model lost and the server no longer
    knows. Let in, those samples reached no loop; it is refused before any batch, in one line
    naming rank 2 and what to load (docs/delivery.md limit (e); simulator ``elastic`` seed 9643, F53)."""
    s = TinyStream()
    for r in range(3):
        s.hello(b"r%d" % r, "j", group="g", rank=r, world_size=3)
    s.turn()
    s.turn()
    for r in (0, 1):
        s.core.message(b"r%d" % r, Bye(), s.now)
    for _ in range(130):  # past the group's wait (client_timeout_s): rank 2 reads on alone
        s.turn()
    assert [e for e, _ in s.told[b"r2"]] == [0, 1, 2] and not s.told[b"r0"] and not s.told[b"r1"], dict(s.told)
    s.core.message(b"r2", Bye(), s.now)
    s.turn()
    [(_, err)] = s.core.hello(b"n0", Hello(("voxels",), 1, consumer="j", resume=Resume(-1, {}), group="g", rank=0,
                                           world_size=2), s.now)
    assert err.to_wire()["type"] == "error" and err.code == "resume" and "\n" not in err.message, err
    assert "rank 2 epochs up to 2" in err.message and "checkpoint saved after epoch 0 ended" in err.message


def test_a_loader_worker_told_epochs_its_loader_never_learned_gets_its_rolled_back_sample_again():
    """StreamLoader worker x/0 took one batch of epoch 0 (its loop received it) and left; b read
    every epoch; x/0's next iteration was told epochs 0-2 complete at once and sent nothing, so
    its loader, which learns an epoch complete only with a batch yielded after it, never learned
    them. The job restarts from a checkpoint taken before that batch: limit (e) counts a worker's
    epochs from what its loader learned (none), so the server kept x/0's record of epoch 0, lets
    the state in and sends the sample again (it reached no loop, in silence: simulator finding
    F36, ``mixed`` seed 5954)."""
    s = TinyStream()
    s.hello(b"x.1", "x/0", ends_on_drained=True)
    s.turn()
    [(_, mine)] = s.got[b"x.1"]
    s.core.message(b"x.1", Bye(), s.now)
    s.read_every_epoch(b"b", "b")
    s.hello(b"x.2", "x/0", Resume(-1, {0: frozenset({parse_sample_id(mine)})}), ends_on_drained=True)
    for _ in range(3):
        s.turn()
    assert [e for e, _ in s.told[b"x.2"]] == [0, 1, 2] and not s.got[b"x.2"]
    s.core.message(b"x.2", Bye(), s.now)
    s.hello(b"x.3", "x/0", Resume(-1, {}), ends_on_drained=True)
    for _ in range(5):
        s.turn()
    assert s.got[b"x.3"] == [(0, mine)] and [e for e, _ in s.told[b"x.3"]] == [0, 1, 2]


def test_a_loader_worker_resume_more_than_keep_epochs_behind_what_its_loader_learned_is_refused():
    """Worker x/0 read all five epochs on one connection: each batch after the first epoch's end
    was leased after an end was told, and its acknowledgement says the loop received it, so its
    loader learned epochs up to 3 complete. A state saved before epoch 0 ended is refused in one
    line, as a trainer's; one within two epochs of it is let in (docs/delivery.md limit (e))."""
    s = TinyStream(epochs=5)
    s.hello(b"x.1", "x/0", ends_on_drained=True)
    for _ in range(30):
        s.turn()
    assert [e for e, _ in s.told[b"x.1"]] == [0, 1, 2, 3, 4] and len(s.got[b"x.1"]) == 20
    s.core.message(b"x.1", Bye(), s.now)
    s.turn()
    hello = Hello(("voxels",), 1, consumer="x/0", resume=Resume(-1, {}), ends_on_drained=True)
    [(_, err)] = s.core.hello(b"x.2", hello, s.now)
    assert err.to_wire()["type"] == "error" and err.code == "resume" and "\n" not in err.message
    assert "up to 3" in err.message and "checkpoint saved after epoch 1 ended" in err.message
    hello = Hello(("voxels",), 1, consumer="x/0", resume=Resume(1, {}), ends_on_drained=True)
    [(_, welcome)] = s.core.hello(b"x.3", hello, s.now)
    assert welcome.to_wire()["type"] == "welcome", welcome


def test_a_ddp_rank_sent_a_batch_it_never_held_is_padded_by_the_server():
    """A DDP job of 5 ranks reading 4 samples per epoch: rank 4, paused, is sent a batch of
    epoch 1 that it never holds (it will be revoked: the rank never yields it), and nothing of
    epoch 0. Told epoch 0 complete with its count, it is sent a padding batch of epoch 0: it has
    nothing else to repeat (it hung in an all-reduce when only a rank never *sent* a batch got
    one: simulator finding F19, ``ddp`` seed 174)."""
    s = TinyStream()
    s.mute = {b"r4"}
    for r in range(5):
        s.hello(b"r%d" % r, "j", group="g", rank=r, world_size=5)
    for _ in range(3):
        s.turn()
    assert [e for e, _ in s.got[b"r0"]][:2] == [0, 1] and s.got[b"r4"][0][0] == 1  # its first batch is of epoch 1
    assert s.told[b"r4"][0] == (0, 1)
    assert [e for e, _ in s.got[b"r4"]] == [1, 0]  # then a padding batch of epoch 0


def test_a_ddp_group_with_no_rank_connected_keeps_what_a_returning_rank_repeats():
    """Rank 1 of a group was granted the epoch's only batch and left; rank 0, dropped, has not
    said hello again yet: no rank of the group is connected when the server prunes. Rank 0,
    back, is told the epoch complete with a count of 1: it still gets a padding copy (the
    group's last batch was forgotten with its last connection, and the job hung in an
    all-reduce: simulator finding F24, ``elastic`` seed 149)."""
    from v2v_server.delivery.ledger import ClientRecord
    from v2v_server.delivery.padding import GroupPadding
    pad = GroupPadding()
    pad.acked("g", 1, BatchRecord(0, 0, [SampleKey("a.mp4", 0)], FakeSample("a.mp4#0")))
    pad.prune(set(), lambda epoch: False)
    back = ClientRecord(b"r0", ("g:g", 0), ("voxels",), 2, 0.0, group="g", rank=0, world_size=2)
    batches, copy = pad.epoch_done(back, 0)
    assert batches == 1 and copy is not None and copy.batch_id == -1 and copy.epoch == 0
    pad.prune(set(), lambda epoch: True)  # its epochs forgotten: nothing of the group is kept
    assert pad.epoch_done(back, 0) == (0, None)


def test_a_ddp_groups_count_once_told_is_not_lowered_by_a_grant_given_back_later():
    """Rank 1 of a group was granted two batches of epoch 0, rank 0 one; rank 0 is told the
    epoch complete with a count of 2 (a grant is yielded). Rank 1, paused past the client
    timeout, says hello again naming only the first: the second goes back to the queue. Rank 1
    is still told 2, and pads up to it with the server's copy on its new connection (told 1, it
    yielded one batch fewer than ranks 0, and the job hung in an all-reduce: simulator finding
    F34, ``ddp`` seed 1774). Forgotten with the epoch."""
    from v2v_server.delivery.ledger import ClientRecord
    from v2v_server.delivery.padding import GroupPadding
    pad = GroupPadding()
    for rank, bid in [(0, 0), (1, 1), (1, 2)]:
        pad.acked("g", rank, BatchRecord(bid, 0, [SampleKey("a.mp4", bid)], FakeSample(f"a.mp4#{bid}")))
    first = ClientRecord(b"r0", ("g:g", 0), ("voxels",), 2, 0.0, group="g", rank=0, world_size=2, granted=1)
    assert pad.epoch_done(first, 0) == (2, None)
    pad.resumed("g", 1, -1, {0: 1})  # rank 1's hello names batch 1, not batch 2
    back = ClientRecord(b"r1.2", ("g:g", 1), ("voxels",), 2, 0.0, group="g", rank=1, world_size=2)
    batches, copy = pad.epoch_done(back, 0)
    assert batches == 2 and copy is not None and copy.epoch == 0
    pad.prune(set(), lambda epoch: True)
    assert pad.epoch_done(back, 0) == (0, None)


def test_a_ddp_groups_count_once_told_is_not_raised_by_a_grant_given_back_later():
    """Ranks 0 and 1 of a group of three hold their grants of epoch 0 (one for rank 0, two for rank
    1, which reads two ahead); rank 2, granted one, is told the epoch complete with a count of 2.
    Rank 0 leaves without its batch, then says hello again: the batch goes back to the queue while
    rank 1, which has just acknowledged its two, has free slots. It goes to rank 0, below the count
    told, not to rank 1 at it: given to rank 1, the group's count rose to 3, told to ranks 0 and
    1 while rank 2 had ended on 2, and the job hung in an all-reduce (simulator ``mixed`` seed
    44061, F41)."""
    s = TinyStream()
    s.hello(b"r0", "j", group="g", rank=0, world_size=3)
    s.take(s.core.hello(b"r1", Hello(("voxels",), 2, consumer="j", group="g", rank=1, world_size=3), s.now))
    s.hello(b"r2", "j", group="g", rank=2, world_size=3)
    s.keep |= {b"r0", b"r1"}
    for _ in range(8):  # past the lease: the grants held by ranks 0 and 1 no longer hold rank 2's end back
        s.turn()
    assert [e for e, _ in s.got[b"r1"]] == [0, 0] and s.told[b"r2"][:1] == [(0, 2)], (dict(s.got), dict(s.told))
    assert s.told[b"r0"] == [] and s.told[b"r1"] == []
    given_back = s.got[b"r0"][0]
    s.core.message(b"r0", Bye(), s.now)
    s.keep -= {b"r0", b"r1"}
    ids = [b.batch_id for b in s.core.ledger.batches.values() if b.consumer == ("g:g", 1)]
    s.core.message(b"r1", Ack(tuple(ids)), s.now)
    s.hello(b"r0.2", "j", Resume(-1, {}), group="g", rank=0, world_size=3)
    for _ in range(8):
        s.turn()
    assert s.got[b"r0.2"][0] == given_back, dict(s.got)
    assert s.told[b"r0.2"][:1] == [(0, 2)] and s.told[b"r1"][:1] == [(0, 2)], dict(s.told)


def test_a_ddp_rank_at_its_groups_count_is_told_the_end_of_an_epoch_another_ranks_hello_reopened():
    """Rank 1 of a group of two holds its two grants of epoch 0 while rank 0 is told the epoch with a
    count of 2, and the stream's end, and leaves. Then rank 1 acknowledges its grants, and a rank-0
    hello of no process token (its proof of life is not asked) resets rank 0's record: epoch 0 is owed again, a
    batch of it waits for a rank 0, and none comes. Rank 1 yielded the count: no batch of the epoch
    can go to it, so it is told the epoch's end and the stream's; it waited for ever (simulator
    ``mixed`` seed 117485, F47)."""
    s = TinyStream(epochs=1)
    s.hello(b"r0", "j", group="g", rank=0, world_size=2)
    s.take(s.core.hello(b"r1", Hello(("voxels",), 2, consumer="j", group="g", rank=1, world_size=2), s.now))
    s.keep.add(b"r1")
    for _ in range(8):  # past the lease: rank 1's grants no longer hold rank 0's end back
        s.turn()
    assert len(s.got[b"r1"]) == 2 and s.told[b"r0"] == [(0, 2)] and s.told[b"r1"] == [], (dict(s.got), dict(s.told))
    s.core.message(b"r0", Bye(), s.now)
    s.keep.discard(b"r1")
    s.core.message(b"r1", Ack(tuple(b.batch_id for b in s.core.ledger.batches.values())), s.now)
    s.mute.add(b"old0")
    s.hello(b"old0", "j", Resume(-1, {}), group="g", rank=0, world_size=2)
    s.turn()
    s.core.message(b"old0", Bye(), s.now)  # its process is dead: the batches leased to it come back
    for _ in range(4):
        s.turn()
    assert s.core.ledger.batches and s.told[b"r1"] == [(0, 2)], (dict(s.told), s.core.ledger.batches)


def test_a_killed_ddp_ranks_hello_held_by_a_cut_never_resets_what_the_restarted_rank_read():
    """A DDP job is killed while a network cut holds its rank 0's hello; the job restarts (new
    processes) and its two ranks read the stream's one epoch, are told its end and leave. A trainer
    beside the job says hello; then the cut heals and the killed rank's hello arrives, naming
    nothing, its connection silent from then on. Another process than the rank's last one, it
    waits for its proof of life and is forgotten after the client timeout, so rank 0's record
    stands and nothing the job read is made again for the trainer (simulator finding F48,
    ``mixed`` seeds 138433, 146305: a trainer got a sample the restarted rank had yielded)."""
    s = TinyStream(epochs=1)
    for r in (0, 1):
        s.take(s.core.hello(b"r%d" % r, Hello(("voxels",), 1, consumer="j", group="g", rank=r, world_size=2,
                                               instance=f"job2.{r}", hello_id=2), s.now))
    for _ in range(8):
        s.turn()
    assert s.told[b"r0"] == s.told[b"r1"] == [(0, 2)], dict(s.told)
    for r in (b"r0", b"r1"):
        s.core.message(r, Bye(), s.now)
    s.hello(b"t", "t")
    s.mute.add(b"old0")
    s.take(s.core.hello(b"old0", Hello(("voxels",), 1, consumer="j", group="g", rank=0, world_size=2,
                                       instance="job1.0", hello_id=1), s.now))
    for _ in range(150):  # past the client timeout (100 s)
        s.turn()
    job = {x for r in (b"r0", b"r1") for x in s.got[r]}
    assert len(job) == 4 and not job & set(s.got[b"t"]) and not s.got[b"old0"], dict(s.got)


def test_a_ddp_ranks_hello_forgotten_for_silence_holds_its_groups_ends_back():
    """A reader (world size 1) read the stream's one epoch and left; its job resumes at world size 2,
    rank 0 loading the reader's checkpoint, which lacks the epoch's last sample (the model lost it).
    Rank 1 (no state) is let in at once; rank 0's hello, speaking for a consumer another process
    read, waits for its proof of life, and its connection falls silent past the client timeout (a
    network delaying its heartbeats): its hello is forgotten for silence. Rank 1 is not told the
    epoch's end meanwhile: told it with a count of 0, it left, and rank 0, let in once its connection
    spoke again, reopened the epoch for a sample no rank of the group could take (simulator
    ``elastic`` seeds 7355, 17093, F53)."""
    s = TinyStream(epochs=1)
    s.take(s.core.hello(b"p1", Hello(("voxels",), 1, consumer="j", instance="p1", hello_id=1), s.now))
    for _ in range(8):
        s.turn()
    assert len(s.got[b"p1"]) == 4 and [e for e, _ in s.told[b"p1"]] == [0], (dict(s.got), dict(s.told))
    s.core.message(b"p1", Bye(), s.now)
    *kept, (_, lost) = s.got[b"p1"]
    state = Resume(-1, {0: frozenset(parse_sample_id(sid) for _, sid in kept)}, supersedes=(("c:j", 0, -1),))
    s.mute.add(b"r0")
    s.take(s.core.hello(b"r0", Hello(("voxels",), 1, consumer="j", resume=state, group="g", rank=0, world_size=2,
                                     instance="job2.0", hello_id=2), s.now))
    s.take(s.core.hello(b"r1", Hello(("voxels",), 1, consumer="j", group="g", rank=1, world_size=2,
                                     instance="job2.1", hello_id=2), s.now))
    for _ in range(150):  # past the client timeout (100 s) and the group's wait for its ranks
        s.core.message(b"r1", Heartbeat(2), s.now)
        s.turn()
    assert s.told[b"r1"] == [] and not s.got[b"r0"], dict(s.told)
    s.mute.discard(b"r0")
    for _ in range(10):  # rank 0's connection speaks again: its hello waits again, then is let in
        for r in (b"r0", b"r1"):
            s.core.message(r, Heartbeat(2), s.now)
        s.turn()
    assert [sid for _, sid in s.got[b"r0"]] == [lost], dict(s.got)
    assert s.told[b"r0"] == s.told[b"r1"] and [e for e, _ in s.told[b"r1"]] == [0], dict(s.told)


def test_a_count_told_to_the_ranks_of_another_world_size_binds_none_of_a_resized_job():
    """Three ranks were told epoch 0 with a count of 2; the job, killed, resumes at world size 2,
    each new rank counting the 2 batches the gathered state says the most a rank yielded. A batch
    of epoch 0 given back may go to either (the old ranks read no more): bound by the old count,
    it waited for good and the job's stream never ended (``elastic`` seed 44 with F41's rule)."""
    from v2v_server.delivery.ledger import ClientRecord
    from v2v_server.delivery.padding import GroupPadding
    pad = GroupPadding()
    pad.resized("g", 3)
    for rank, bid in [(0, 0), (0, 1), (1, 2), (2, 3)]:
        pad.acked("g", rank, BatchRecord(bid, 0, [SampleKey("a.mp4", bid)], FakeSample(f"a.mp4#{bid}")))
    old = ClientRecord(b"r1", ("g:g", 1), ("voxels",), 2, 0.0, group="g", rank=1, world_size=3, granted=1)
    assert pad.epoch_done(old, 0) == (2, None) and pad.room(old, 0) == 1
    pad.resized("g", 2)
    for rank in (0, 1):
        pad.resumed("g", rank, -1, {0: 2})
        new = ClientRecord(b"n%d" % rank, ("g:g", rank), ("voxels",), 2, 0.0, group="g", rank=rank, world_size=2)
        assert pad.room(new, 0) is None


def test_a_ddp_rank_back_after_the_others_ran_every_epoch_is_told_its_groups_count():
    """Rank 0 of a group of two leaves with nothing; rank 1, granted one batch of epoch 0, and a
    trainer read every epoch, and the server forgets epoch 0. Rank 0, back, is told epoch 0 with
    the group's count, 1: the counts of an epoch are kept while a rank of the group was told fewer
    than ``keep_epochs`` newer epochs complete, as its records are (they went with the epoch: told
    it with no count, rank 0 padded nothing, and the job hung in an all-reduce: simulator
    ``mixed`` seeds 33857, 56221, F43)."""
    s = TinyStream()
    s.hello(b"r0", "j", group="g", rank=0, world_size=2)
    s.hello(b"r1", "j", group="g", rank=1, world_size=2)
    s.mute.add(b"r0")
    s.turn()
    assert [e for e, _ in s.got[b"r1"]] == [0], dict(s.got)
    s.core.message(b"r0", Bye(), s.now)  # what was sent to it goes back to the queue
    s.hello(b"b", "b")
    for _ in range(110):  # past the group's wait (client_timeout_s): rank 1 reads on alone
        s.turn()
    assert [e for e, _ in s.told[b"b"]] == [0, 1, 2] and s.told[b"r1"][0] == (0, 1), dict(s.told)
    assert 0 not in s.core.sched.plans
    s.hello(b"r0.2", "j", Resume(-1, {}), group="g", rank=0, world_size=2)
    for _ in range(110):  # rank 1 and the trainer, silent, were dropped: the group's wait again
        s.turn()
    assert s.told[b"r0.2"][:1] == [(0, 1)], dict(s.told)


def test_a_ddp_rank_told_an_epoch_the_server_never_opened_is_told_its_groups_count():
    """A restarted server (no journal) is first said hello by a trainer that completed epoch 0,
    so it starts at epoch 1; then a DDP job's ranks come back, rank 0 having yielded one batch
    of epoch 0 and rank 1 none. Epoch 0 has no plan here, but the ranks' states count it: each
    is told epoch 0 with the group's count, and rank 1 pads up to it (told with no count, it
    padded nothing and the job hung in an all-reduce: simulator ``mixed`` seed 5129)."""
    s = TinyStream()
    s.hello(b"b", "b", Resume(0, {}))
    s.hello(b"r1", "j", Resume(-1, {}), group="g", rank=1, world_size=2)
    s.hello(b"r0", "j", Resume(-1, {0: frozenset({SampleKey("a.mp4", 0)})}, {0: 1}), group="g", rank=0, world_size=2)
    for _ in range(3):
        s.turn()
    assert 0 not in s.core.sched.plans
    assert s.told[b"r0"][0] == (0, 1) and s.told[b"r1"][0] == (0, 1), dict(s.told)


def _ddp_ranks_where_rank_0_took_three_of_epoch_0(journal) -> TinyStream:
    """Ranks 0 and 1 of group g on a journaled server: rank 1 says nothing for three turns, so
    rank 0 is granted three batches of epoch 0; rank 1 then takes the one leased to it."""
    s = TinyStream(journal)
    s.hello(b"r0", "j", group="g", rank=0, world_size=2)
    s.hello(b"r1", "j", group="g", rank=1, world_size=2)
    s.mute.add(b"r1")
    for _ in range(3):
        s.turn()
    assert [e for e, _ in s.got[b"r0"]].count(0) == 3 and s.got[b"r1"] == [(0, "a.mp4#1")]
    return s


def test_a_server_restarted_from_its_journal_counts_a_ddp_ranks_grants_of_before(tmp_path):
    """Rank 0 was granted three batches of epoch 0, then paused past the group's wait; the server
    crashed and restarted from its journal. Rank 1 comes back with nothing yielded and reads on
    alone: it is told epoch 0 with rank 0's count, 3, and pads up to it (told 1, its own count,
    it ended while rank 0, back, yielded three: simulator ``mixed`` seed 5749, F32)."""
    _ddp_ranks_where_rank_0_took_three_of_epoch_0(Journal(str(tmp_path), "r"))
    s = TinyStream(Journal(str(tmp_path), "r"))  # the crash: no bye, no close
    s.hello(b"r1.2", "j", Resume(-1, {}), group="g", rank=1, world_size=2)
    for _ in range(110):  # past the group's wait (client_timeout_s)
        s.turn()
    assert s.got[b"r1.2"][0] == (0, "a.mp4#1") and [e for e, _ in s.got[b"r1.2"]].count(0) == 1
    assert s.told[b"r1.2"][0] == (0, 3), dict(s.told)


def test_a_ddp_count_told_before_a_server_crash_is_told_again_after_it(tmp_path):
    """Ranks were told epoch 0 with a count of 3 (rank 0's; rank 1 had 1), then the server
    crashed and the job restarted: rank 0's state completed epoch 0 (it names no count of it),
    rank 1's was saved before it read that end. Rank 1 is told 3 again, not the 1 its own state
    counts (it padded nothing while rank 0 had yielded three: simulator ``ddp`` seed 2558, F33)."""
    s = _ddp_ranks_where_rank_0_took_three_of_epoch_0(Journal(str(tmp_path), "r"))
    s.mute.discard(b"r1")
    [bid] = s.core.ledger.table.held_by(b"r1")
    s.core.message(b"r1", Hold((bid,)), s.now)
    s.core.message(b"r1", Ack((bid,)), s.now)
    for _ in range(3):
        s.turn()
    assert s.told[b"r0"][0] == s.told[b"r1"][0] == (0, 3), dict(s.told)
    t = TinyStream(Journal(str(tmp_path), "r"))
    t.hello(b"r0.2", "j", Resume(0, {}), group="g", rank=0, world_size=2)
    t.hello(b"r1.2", "j", Resume(-1, {0: frozenset({SampleKey("a.mp4", 1)})}, {0: 1}), group="g", rank=1,
            world_size=2)
    for _ in range(3):
        t.turn()
    assert t.told[b"r1.2"][0] == (0, 3), dict(t.told)


def test_a_ddp_count_told_before_a_server_crash_binds_a_ranks_hello_after_it(tmp_path):
    """Reader t took every batch of epoch 0; ranks 0 and 1 of group g, joined late, were told it
    complete with a count of 0, then the server crashed. After the restart t rolls back to a
    checkpoint of nothing (epoch 0's samples are owed again) and rank 1, its state saved before it
    read that end, comes back: it is told 0 again and granted no batch of epoch 0 (told 3, it
    yielded three while rank 0 had ended on 0: simulator ``mixed`` seed 133089, F49)."""
    s = TinyStream(Journal(str(tmp_path), "r"))
    s.hello(b"t", "t")
    for _ in range(3):
        s.turn()
    s.keep.add(b"t")
    s.turn()
    s.hello(b"r0", "j", group="g", rank=0, world_size=2)
    s.hello(b"r1", "j", group="g", rank=1, world_size=2)
    s.mute |= {b"r0", b"r1"}
    s.turn()
    s.core.message(b"t", Ack(tuple(s.core.ledger.table.held_by(b"t"))), s.now)
    s.turn()
    assert s.told[b"r0"] == s.told[b"r1"] == [(0, 0)], dict(s.told)
    t = TinyStream(Journal(str(tmp_path), "r"))  # the crash: no bye, no close
    t.hello(b"r1.2", "j", Resume(-1, {}), group="g", rank=1, world_size=2)
    t.hello(b"t.2", "t", Resume(-1, {}))
    t.keep.add(b"t.2")
    for _ in range(110):  # past the group's wait (client_timeout_s)
        t.turn()
    assert t.told[b"r1.2"][0] == (0, 0) and 0 not in [e for e, _ in t.got[b"r1.2"]], (dict(t.told), dict(t.got))


def test_a_reader_that_still_speaks_after_the_end_is_told_it_again():
    """The last ``epoch_done`` and ``end`` can be lost in a cut of the connection that ZeroMQ
    mends behind the socket (no hello follows): a reader told the end that still heartbeats did
    not get it, and is told its last epoch's end and ``end`` again; one that left is told nothing
    (simulator finding F28, ``mixed`` seed 1084)."""
    s = TinyStream()
    s.hello(b"a", "a")
    for _ in range(30):
        s.turn()
    assert [e for e, _ in s.told[b"a"]] == [0, 1, 2] and len(s.got[b"a"]) == 12
    again = s.core.message(b"a", Heartbeat(), s.now)
    assert [(i, m.to_wire()["type"]) for i, m in again] == [(b"a", "epoch_done"), (b"a", "end")]
    assert again[0][1].epoch == 2
    assert s.core.message(b"a", Bye(), s.now) == []
    assert s.core.message(b"b", Heartbeat(), s.now)[0][1].to_wire()["type"] == "error"  # never said hello
    [(_, unknown)] = s.core.message(b"b", Heartbeat(5), s.now)  # names the hello its session said last
    assert (unknown.code, unknown.hello_id) == ("unknown_client", 5)


def test_a_ddp_rank_that_still_speaks_after_the_end_is_told_its_last_count_again():
    """F28's rule for a DDP rank: its last ``epoch_done`` and ``end`` lost in a cut ZeroMQ mended,
    it is told that end again with the count its group was told (told ``end`` alone, it would pay
    no padding of the last epoch and yield fewer batches than its group: the job hangs in an
    all-reduce; an earlier end lost, it says hello again, F38)."""
    s = TinyStream()
    for ident, rank in ((b"r0", 0), (b"r1", 1)):
        s.hello(ident, "j", group="g", rank=rank, world_size=2)
    for _ in range(30):
        s.turn()
    last = s.told[b"r0"][-1]
    assert last[0] == 2 and last[1] is not None and s.told[b"r1"][-1] == last, dict(s.told)
    again = s.core.message(b"r1", Heartbeat(), s.now)
    assert [(i, m.to_wire()["type"]) for i, m in again] == [(b"r1", "epoch_done"), (b"r1", "end")]
    assert (again[0][1].epoch, again[0][1].batches) == last


def test_a_reopened_closed_epoch_is_made_again_after_a_server_crash(tmp_path):
    """Reader a read all three epochs (the journal closed them) and resumed from a checkpoint of
    epoch 0: its hello reopened epochs 1 and 2, whose samples reach no loop until made again. The
    server crashed before it made them: restarted from its journal, it makes them again for a's next
    hello (the journal kept only what a still holds, and epochs it closed make again only what left a
    record since: the reset's samples reached no loop, simulator ``mixed`` seed 152517, F51)."""
    s = TinyStream(Journal(str(tmp_path), "r"))
    s.read_every_epoch(b"a", "a")
    s.hello(b"a.2", "a", Resume(0, {}))
    t = TinyStream(Journal(str(tmp_path), "r"))  # the crash: no bye, no close
    t.hello(b"a.3", "a", Resume(0, {}))
    for _ in range(10):
        t.turn()
    assert sorted(t.got[b"a.3"]) == [(e, f"a.mp4#{k}") for e in (1, 2) for k in range(4)], dict(t.got)
    assert [e for e, _ in t.told[b"a.3"]] == [1, 2]


def test_a_ddp_count_told_before_a_reset_binds_the_ranks_after_a_server_crash(tmp_path):
    """Ranks 0 and 1 of group g read all three epochs, told each with a count of 2; the job restarted
    from a checkpoint of epoch 0 (the ranks' hellos reset their grants of epochs 1 and 2), and the
    server crashed. Restarted from its journal, it tells the ranks of the job epochs 1 and 2 with the
    counts told before (the grants, reset, count none) and sends them the reopened epochs' samples (told 0,
    no rank could take them: simulator ``mixed`` seed 152517, F51)."""
    s = TinyStream(Journal(str(tmp_path), "r"))
    for ident, rank in ((b"r0", 0), (b"r1", 1)):
        s.hello(ident, "j", group="g", rank=rank, world_size=2)
    for _ in range(30):
        s.turn()
    assert s.told[b"r0"] == s.told[b"r1"] == [(0, 2), (1, 2), (2, 2)], dict(s.told)
    for ident, rank in ((b"r0", 0), (b"r1", 1)):
        s.core.message(ident, Bye(), s.now)
        s.hello(ident + b".2", "j", Resume(0, {}), group="g", rank=rank, world_size=2)
    t = TinyStream(Journal(str(tmp_path), "r"))  # the crash: no bye, no close
    for ident, rank in ((b"r0.3", 0), (b"r1.3", 1)):
        t.hello(ident, "j", Resume(0, {}), group="g", rank=rank, world_size=2)
    for _ in range(20):
        t.turn()
    assert t.told[b"r0.3"] == t.told[b"r1.3"] == [(1, 2), (2, 2)], dict(t.told)
    got = sorted(t.got[b"r0.3"] + t.got[b"r1.3"])
    assert got == [(e, f"a.mp4#{k}") for e in (1, 2) for k in range(4)], dict(t.got)


def test_a_server_restarted_from_its_journal_keeps_an_epoch_a_reader_holds_for_a_reader_ahead(tmp_path):
    """Reader j was granted a batch of epoch 0 and paused; t read the rest and was told epoch 0
    complete; the server crashed (epoch 0 still open in its journal). After the restart t says hello
    first (epoch 0 completed), then j from a checkpoint of nothing: epoch 0 is served again, not
    skipped for t, and j gets its sample again (told epoch 0 complete with it unread: simulator
    ``mixed`` seed 185529, F52)."""
    s = TinyStream(Journal(str(tmp_path), "r"))
    s.hello(b"j", "j")
    s.keep.add(b"j")
    s.turn()
    s.hello(b"t", "t")
    for _ in range(6):
        s.turn()
    held = [k for e, k in s.got[b"j"] if e == 0]
    assert held and s.told[b"t"][:1] == [(0, None)] and not s.told[b"j"], (dict(s.got), dict(s.told))
    t = TinyStream(Journal(str(tmp_path), "r"))  # the crash: no bye, no close
    t.hello(b"t.2", "t", Resume(0, {}))
    t.hello(b"j.2", "j", Resume(-1, {}))
    for _ in range(30):
        t.turn()
    assert [k for e, k in t.got[b"j.2"] if e == 0] == held and 0 not in [e for e, _ in t.got[b"t.2"]], dict(t.got)

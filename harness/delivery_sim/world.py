"""The simulator's world: one seeded random source, a simulated clock, an event queue, and the
processes whose events it runs (a process can be paused for any length, or killed).

Everything that happens is an event ``(time, due, sequence, process, lane, function, args)``
taken from one heap in order (an event deferred by a pause keeps its ``due`` time and sequence,
so a thread's events keep their order); ``Sim.rng`` (one ``random.Random(seed)``) decides every delay, choice and
fault, so a seed replays the same run (the core iterates sets of strings: replays also need
one ``PYTHONHASHSEED``, which the command line fixes). After every event the checks run
(``Sim.checks``, given the process whose step it was: a check may skip what that step cannot
change); the first one that fails stops the run with a :class:`Violation` naming the
step, and the trace (``trace=True``) holds every message and decision up to it.
"""
from __future__ import annotations

import heapq
import random
from typing import Callable, List, Optional


class Violation(AssertionError):
    """An invariant broke: ``kind`` (``doubled``, ``lost``, ``liveness``, ``memory``, ``error``,
    ``refused``, ``timeout``, ``runaway``), what happened, and the simulated time and step it was found at."""

    def __init__(self, kind: str, what: str, now: float = 0.0, step: int = 0):
        super().__init__(f"{kind} at t={now:.3f} s, step {step}: {what}")
        self.kind, self.what, self.now, self.step = kind, what, now, step


class Proc:
    """A process (a trainer, a DataLoader worker, the server, a decode worker): its events run
    only while it lives and is not paused. ``paused_until``: simulated seconds; an event due
    while paused runs when the pause ends, in its original order within its thread (``lane``:
    ``"io"`` for a client's I/O thread, ``"main"`` for its loop); the threads resume in the
    order ``wake`` (lane -> seconds after the pause) draws."""

    def __init__(self, name: str):
        self.name = name
        self.dead = False
        self.paused_until = 0.0
        self.wake: dict = {}

    def pause(self, until: float, rng, now: float) -> None:
        """Stop until ``until``; on waking each thread goes on after its own short delay. A pause
        within one whose threads have not all woken keeps their delays: a thread's events deferred by
        the first would otherwise run after those of the second (a connection's messages reordered)."""
        wake = {"io": rng.uniform(0.0, 0.003), "main": rng.uniform(0.0, 0.003)}
        if now >= self.paused_until + max(self.wake.values(), default=0.0):
            self.wake = wake
        self.paused_until = max(self.paused_until, until)

    def __repr__(self) -> str:
        return f"Proc({self.name}{', dead' if self.dead else ''})"


class Sim:
    """The clock, the random source and the event queue.

    Args:
        seed: the one seed every decision is drawn from.
        trace: keep a line per event worth telling (``log``); else ``log`` costs nothing.
    """

    def __init__(self, seed: int, trace: bool = False):
        self.seed = seed
        self.rng = random.Random(seed)
        self.now = 0.0
        self.steps = 0
        self._q: list = []
        self._seq = 0
        self.trace: Optional[List[str]] = [] if trace else None
        self.checks: List[Callable[[Optional[Proc]], None]] = []  # called with the process whose step ran
        self.stop_when: Callable[[], bool] = lambda: False
        self.max_steps = 3_000_000

    def at(self, t: float, fn: Callable, *args, proc: Optional[Proc] = None, lane: str = "main") -> None:
        """Run ``fn(*args)`` at simulated time ``t`` (not before now), as part of ``proc``'s
        thread ``lane``."""
        self._seq += 1
        t = max(t, self.now)
        heapq.heappush(self._q, (t, t, self._seq, proc, lane, fn, args))

    def after(self, dt: float, fn: Callable, *args, proc: Optional[Proc] = None, lane: str = "main") -> None:
        self.at(self.now + dt, fn, *args, proc=proc, lane=lane)

    def log(self, who: str, what) -> None:
        """One trace line (``what`` may be a callable, made only when tracing)."""
        if self.trace is not None:
            self.trace.append(f"{self.now:10.4f} #{self.steps:<6} {who}: {what() if callable(what) else what}")

    def run(self, until: float) -> None:
        """Run events in order until simulated time ``until``, or ``stop_when()``; the checks
        run after each event.

        Raises:
            Violation: the first check that fails.
        """
        q = self._q
        while q and not self.stop_when():
            t, due, seq, proc, lane, fn, args = q[0]
            if t > until:
                break
            heapq.heappop(q)
            if proc is not None:
                if proc.dead:
                    continue
                resumes = proc.paused_until + proc.wake.get(lane, 0.0)  # this thread runs again then
                if resumes > t and proc.paused_until > 0.0:
                    # deferred, keeping its place among the thread's events (first due, first run)
                    heapq.heappush(q, (resumes, due, seq, proc, lane, fn, args))
                    continue
            self.now = t
            self.steps += 1
            if self.steps > self.max_steps:
                self.fail("runaway", f"more than {self.max_steps} steps: a busy loop in the simulated processes")
            fn(*args)
            for check in self.checks:
                check(proc)
        if not q or (q[0][0] > until and not self.stop_when()):
            self.now = max(self.now, until)

    def fail(self, kind: str, what: str) -> None:
        """Raise a :class:`Violation` at the current step."""
        self.log("CHECK", f"{kind}: {what}")
        raise Violation(kind, what, self.now, self.steps)

    # ------------------------------------------------------------------ draws
    def chance(self, p: float) -> bool:
        return p > 0 and self.rng.random() < p

    def uniform(self, lo: float, hi: float) -> float:
        return self.rng.uniform(lo, hi)

    def pick(self, seq):
        return seq[self.rng.randrange(len(seq))]

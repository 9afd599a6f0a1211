"""Cost of the grant protocol (docs/delivery.md, "The protocol") on the fast path, against
the ack-only protocol it replaced, in one run.

Run: ``python -m bench.lease [--batches 40000] [--read 40] [--step-ms 20] [--rounds 4] [--fill-s 12]``.

* **Server main loop** (``DeliveryCore``, no sockets, as ``bench.journal``): microseconds of core
  time per batch spent on the client's messages when it only acknowledges (``ack``: granted,
  delivered and its slot freed in one message) and when it asks for the grant first (``hold``
  answered by ``granted``, then ``ack``); medians of ``--rounds`` alternating runs each way.
* **Trainer** (a real ``v2v-serve`` on 127.0.0.1, tiny samples, 64 batches made ahead during
  ``--fill-s`` before each round so the loop waits on the protocol and not on the workers; one
  ``V2VPushDataset`` with 4 credits and a training step of ``--step-ms``): milliseconds the training loop waits in
  ``next()`` per batch and batches per second, with the grant protocol and with the ack-only
  client (``HeldBatches`` taking whatever it still holds, asking for nothing: the rule that could
  double a batch), alternating ``--rounds`` times against the same server.
"""
from __future__ import annotations

import argparse
import contextlib
import statistics
import time

from v2v_server.delivery.core import DeliveryCore, DeliveryPolicy
from v2v_wire.ids import SampleKey
from v2v_wire.messages import Ack, Hello, Hold


class _Payload:
    def __init__(self, ids):
        self.sample_ids = ids

    def subset(self, keep):
        return _Payload([self.sample_ids[i] for i in keep])


def core_cost(batches: int, grant: bool, batch_size: int = 12) -> float:
    """Seconds of core time per batch spent on the client's messages about it (``ack``; or
    ``hold`` then ``ack``) over ``batches`` batches."""
    videos = [f"v{i:03d}.mp4" for i in range(100)]
    policy = DeliveryPolicy(batch_size=batch_size, epochs=None, lease_s=1e9, client_timeout_s=1e9)
    core = DeliveryCore(videos, policy, lambda samples: _Payload([s["sample_id"] for s in samples]))
    core.hello(b"t", Hello(("voxels",), 64, "trainer"), 0.0)
    now, done, busy = 0.0, 0, 0.0
    while done < batches:
        task = core.task_for("w", now)
        if task is None:
            break
        for k in range(10):
            key = SampleKey(task.video, k)
            core.sample("w", task.task, key, now, lambda lane, key=key: {"sample_id": key.sample_id()})
        core.done("w", task.task, 10, {}, None)
        sends, _ = core.tick(now)
        t0 = time.perf_counter()
        for ident, b in sends:
            if grant:
                core.message(ident, Hold((b.batch_id,)), now)
            core.message(ident, Ack((b.batch_id,)), now)
            done += 1
        busy += time.perf_counter() - t0
        now += 0.01
    return busy / max(1, done)


@contextlib.contextmanager
def ack_only():
    """Within the ``with`` block, ``v2v_client.session.HeldBatches`` follows the ack-only rule,
    the baseline of this bench and of tests/test_lease_protocol.py: a batch still held is taken
    at once and no grant is asked for (so a batch the server meanwhile gave another client is
    yielded too). The grant rule is restored on leaving the block."""
    from v2v_client.session import HeldBatches

    saved = HeldBatches.claim, HeldBatches.to_ask

    def claim(self, item, on_claim, wait):
        with self.lock:
            if self.current.get(item["batch_id"]) is not item:
                return False, None
            del self.current[item["batch_id"]]
            return True, on_claim()

    HeldBatches.claim, HeldBatches.to_ask = claim, lambda self, item=None: []
    try:
        yield
    finally:
        HeldBatches.claim, HeldBatches.to_ask = saved


def read(endpoint: str, n: int, step_s: float, fill_s: float) -> tuple:
    """(ms waited in ``next()`` per batch (median), batches per second) over ``n`` batches, after
    ``fill_s`` seconds in which the server fills its queue (so the loop waits on the protocol,
    not on the workers)."""
    from v2v_client import V2VPushDataset

    time.sleep(fill_s)
    it = iter(V2VPushDataset(endpoint, timeout_s=60, credits=4))
    next(it)
    waits = []
    t_start = time.perf_counter()
    for _ in range(n):
        t0 = time.perf_counter()
        next(it)
        waits.append(time.perf_counter() - t0)
        time.sleep(step_s)
    rate = n / (time.perf_counter() - t_start)
    it.close()
    return statistics.median(waits) * 1e3, rate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batches", type=int, default=40000, help="batches through the core per protocol")
    ap.add_argument("--read", type=int, default=40, help="batches the trainer reads per round")
    ap.add_argument("--fill-s", type=float, default=12.0, help="seconds the server fills its queue before a round")
    ap.add_argument("--step-ms", type=float, default=20.0, help="the trainer's training step")
    ap.add_argument("--rounds", type=int, default=4)
    args = ap.parse_args()
    runs = {False: [], True: []}
    for r in range(2 * args.rounds):  # alternating, medians: the machine may be shared
        runs[r % 2 == 1].append(core_cost(args.batches // (2 * args.rounds), r % 2 == 1))
    base, grant = statistics.median(runs[False]), statistics.median(runs[True])
    print("| server main loop: the client's messages | us per batch | ratio |\n|---|---|---|")
    print(f"| ack only | {base * 1e6:.1f} | 1.00 |")
    print(f"| hold, granted, ack | {grant * 1e6:.1f} | {grant / base:.2f} |")

    from harness.data import SAMPLE_VIDEOS
    from harness.faults import Layout
    from harness.serve import ServeProcess

    layout = Layout(L=4, crop=32, windows=50, batch=2)
    got = {"ack only": [], "grant": []}
    with ServeProcess(["--videos", str(SAMPLE_VIDEOS), "--workers", "2", "--prefetch-batches", "64",
                       *layout.args()]) as srv:
        read(srv.endpoint, 4, 0.0, args.fill_s)  # warm-up: workers started, outputs known
        for r in range(args.rounds):  # ABBA...: neither protocol always reads first
            for name in (("ack only", "grant") if r % 2 == 0 else ("grant", "ack only")):
                with ack_only() if name == "ack only" else contextlib.nullcontext():
                    got[name].append(read(srv.endpoint, args.read, args.step_ms / 1e3, args.fill_s))
    print(f"\n| trainer, {args.step_ms:.0f} ms steps, 4 credits | ms waited in next() per batch (median of rounds) "
          f"| batches/s | ratio of batches/s |\n|---|---|---|---|")
    base_rate = statistics.median(r for _, r in got["ack only"])
    for name, rows in got.items():
        wait = statistics.median(w for w, _ in rows)
        rate = statistics.median(r for _, r in rows)
        print(f"| {name} | {wait:.3f} | {rate:.1f} | {rate / base_rate:.3f} |")


if __name__ == "__main__":
    main()

"""Cost of the delivery journal (``v2v-serve --state-dir``) on the server's main loop.

Run: ``python -m bench.journal [--batches 20000] [--batch-size 12]``. Drives the delivery core
(``DeliveryCore``: scheduler + ledger, no sockets) through whole epochs of acknowledged batches,
once without and once with a journal in a temporary folder (one append per acknowledged batch,
one ``fsync`` per loop turn that grants, as the server's client side makes a grant durable before
it leaves, a rewrite when an epoch completes), and prints microseconds of main-loop time per
acknowledged batch and the ratio against the run without. A turn here grants about one batch: the
worst case of a stream whose batches come one per turn.
"""
from __future__ import annotations

import argparse
import tempfile
import time

from v2v_server.delivery.core import DeliveryCore, DeliveryPolicy
from v2v_server.delivery.journal import Journal
from v2v_wire.messages import Ack, Hello
from v2v_wire.ids import SampleKey


class _Payload:
    def __init__(self, ids):
        self.sample_ids = ids

    def subset(self, keep):
        return _Payload([self.sample_ids[i] for i in keep])


def run(batches: int, batch_size: int, journal_dir=None) -> float:
    """Seconds of core time per acknowledged batch over ``batches`` batches."""
    videos = [f"v{i:03d}.mp4" for i in range(100)]  # 1000 samples per epoch: many epochs complete
    policy = DeliveryPolicy(batch_size=batch_size, epochs=None, lease_s=1e9, client_timeout_s=1e9)
    journal = Journal(journal_dir, "bench") if journal_dir else None
    core = DeliveryCore(videos, policy, lambda samples: _Payload([s["sample_id"] for s in samples]), journal)
    core.hello(b"t", Hello(("voxels",), 64, "trainer"), 0.0)
    worker, now, acked, busy = "w", 0.0, 0, 0.0
    while acked < batches:
        task = core.task_for(worker, now)
        if task is None:
            break
        for k in range(10):
            key = SampleKey(task.video, k)
            core.sample(worker, task.task, key, now, lambda lane, key=key: {"sample_id": key.sample_id()})
        core.done(worker, task.task, 10, {}, None)
        t0 = time.perf_counter()
        sends, _ = core.tick(now)
        for ident, b in sends:
            core.message(ident, Ack((b.batch_id,)), now)
            acked += 1
        if journal is not None:
            journal.durable(now)  # before the turn's grants leave (service/client_side.py)
        busy += time.perf_counter() - t0
        now += 0.01
    if journal is not None:
        journal.close()
    return busy / max(1, acked)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batches", type=int, default=20000)
    ap.add_argument("--batch-size", type=int, default=12)
    args = ap.parse_args()
    base = run(args.batches, args.batch_size)
    with tempfile.TemporaryDirectory() as d:
        with_journal = run(args.batches, args.batch_size, d)
    print("| main loop | us per acknowledged batch | ratio |\n|---|---|---|")
    print(f"| no journal | {base * 1e6:.1f} | 1.00 |")
    print(f"| --state-dir (append per ack, fsync per granting turn) | {with_journal * 1e6:.1f} | "
          f"{with_journal / base:.2f} |")


if __name__ == "__main__":
    main()

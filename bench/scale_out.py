"""One server vs the corpus split over two shards read by one trainer (fan-in), same machine.

Run: ``python -m bench.scale_out [--batches 8] [--out docs/scale_out.md]``.

Rows (samples/s read by plan, the shards read as one plan through ``V2VStreamDataset``
(``v2v_client.loadtest.run_loadtest``), ratio to the first row measured in the same run, and
each server's share of the samples made, from its ``feed`` figures): one unsharded server with
2 workers (baseline); the corpus
split over ``--shard 0/2`` and ``--shard 1/2`` with 1 worker each, read together; the same
with 2 workers each. On a machine with 2 cores the second row has the same CPU as the first
and cannot be faster: sharding buys hosts, not speed per core. The table also prints the
per-worker rate that the sizing arithmetic of docs/scaling.md starts from.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path
from typing import List, Optional

from harness.faults import good_corpus
from v2v_client.plan_dataset import open_stream
from v2v_client.loadtest import run_loadtest
from v2v_wire.plan import SHUFFLE_BUFFER
from harness.serve import ServeProcess

from v2v_wire.protocol import DEFAULT_OUTPUTS as ALL


def measure(corpus: Path, shards: int, workers_each: int, batches: int, extra: List[str]) -> dict:
    """Start ``shards`` servers (``--shard i/shards`` each, ``workers_each`` workers) and read
    ``batches`` batches from all of them as one plan, after one batch and the servers' made-ahead
    stock (a shuffle buffer each), read unmeasured; ``made_share``: each server's share of the
    samples made by the end of the row."""
    base = ["--videos", str(corpus), "--shot-cuts", "off", "--workers", str(workers_each), "--batch-size", "4", "--seed", "1", *extra]
    procs = []
    try:
        for i in range(shards):
            procs.append(ServeProcess(base + (["--shard", f"{i}/{shards}"] if shards > 1 else [])).start())
        warmup = 1 + -(-shards * SHUFFLE_BUFFER // 4)
        r = run_loadtest(",".join(p.endpoint for p in procs), batches, outputs=ALL, timeout_s=300, warmup=warmup)
        made = [open_stream(p.endpoint, timeout_s=60).server_feed()["samples_made"] for p in procs]
        return {**r, "made_share": [m / max(1, sum(made)) for m in made]}
    finally:
        for p in procs:
            p.stop()


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batches", type=int, default=8, help="measured batches per row (batch size 4)")
    p.add_argument("--copies", type=int, default=2, help="copies of each bundled clip in the corpus")
    p.add_argument("--sequence-length", type=int, default=40, help="L (default 40, the paper's)")
    p.add_argument("--out", help="also write the table (markdown) here")
    a = p.parse_args(argv)
    extra = ["--sequence-length", str(a.sequence_length)]
    rows = [("1 server, 2 workers (baseline)", 1, 2), ("2 shards x 1 worker, one trainer", 2, 1),
            ("2 shards x 2 workers, one trainer (4 workers on 2 cores)", 2, 2)]
    with tempfile.TemporaryDirectory(prefix="v2v-scale-") as d:
        corpus = good_corpus(Path(d), a.copies)
        results = []
        for name, shards, w in rows:
            r = measure(corpus, shards, w, a.batches, extra)
            results.append((name, shards, w, r))
            print(f"{name}: {r['samples_per_s']:.2f} samples/s", file=sys.stderr)
    base = results[0][3]["samples_per_s"]
    lines = ["| setting | workers | samples/s | MB/s | samples/s vs baseline | per server (share of samples made) |",
             "|---|---:|---:|---:|---:|---|"]
    for name, shards, w, r in results:
        per = ", ".join(f"{v:.2f}" for v in r["made_share"])
        lines.append(f"| {name} | {shards * w} | {r['samples_per_s']:.2f} | {r['mbytes_per_s']:.0f} | "
                     f"{r['samples_per_s'] / base:.2f}x | {per} |")
    per_worker = base / 2
    lines += ["", f"Per-worker rate (baseline / 2 workers): {per_worker:.2f} samples/s at L = {a.sequence_length}, "
                  "128 x 128 crops, all outputs, on this machine's cores."]
    table = "\n".join(lines)
    print(table)
    if a.out:
        Path(a.out).write_text(
            "# One server vs two shards\n\nCommand: `python -m bench.scale_out --out docs/scale_out.md` (bundled clips "
            f"x{a.copies}, L = {a.sequence_length} x 5 bins, 128 x 128 crops, batches of 4, {a.batches} measured "
            "batches a row, all outputs, one trainer reading every server as one plan through `V2VStreamDataset`, on this "
            "project's 2-core CPU machine shared with other work). Two cores decode at the same speed whether one "
            "server or two own them, so no gain is expected here: the rows check that splitting the corpus costs "
            "nothing, and the per-worker rate feeds the sizing arithmetic of docs/scaling.md.\n\n" + table + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

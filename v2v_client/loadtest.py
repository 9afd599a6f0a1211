"""``v2v-loadtest``: measure what a v2v server (or several shards) delivers, read as a trainer reads
it: a plan's epochs in turn through ``V2VStreamDataset``, read ahead of the loop
(``read_ahead.ReadAhead``, as ``v2v-train`` reads them)."""
from __future__ import annotations

import argparse
import json
import sys
import time
from typing import List, Optional

from v2v_wire.protocol import DEFAULT_OUTPUTS
from v2v_wire.push_names import LOADTEST_FLAGS, loadtest_flag_problem

from .plan_dataset import open_stream
from .read_ahead import ReadAhead


def run_loadtest(endpoint, batches: int, outputs=DEFAULT_OUTPUTS, timeout_s: float = 60.0, step_s: float = 0.0,
                 warmup: int = 1) -> dict:
    """Read ``batches`` batches (after ``warmup`` unmeasured ones) and measure throughput.

    ``step_s`` simulates a training step of that many seconds per batch, so the wait
    fraction shows whether the stream keeps up with a trainer of that speed.

    ``endpoint``: one server, or several shards (a list or ``"a,b"``), read as one plan, its
    epochs in turn, as a trainer would. Padding rows are not counted as samples.

    Returns a dict: ``batches``, ``samples``, ``unique_samples``, ``seconds`` (wall time of
    the measured part), ``batches_per_s``, ``samples_per_s``, ``mbytes_per_s`` (MB = 1e6
    bytes of tensors delivered), ``wait_fraction`` (share of the time spent waiting for
    data), ``epochs_seen``, ``ended_early`` (the server ended the stream first), and
    ``per_server``: {endpoint: {``samples``, ``samples_per_s``, ``share``}}, each server's
    samples of those counted (each batch's ``servers``: the rows each shard served), over the
    same measured wall time; its ``samples`` sum to ``samples``.
    """
    stream = ReadAhead(open_stream(endpoint, outputs=outputs, timeout_s=timeout_s))  # as v2v-train reads
    it = iter(stream)
    n = samples = nbytes = 0
    ids = set()
    epochs = set()
    waited = 0.0
    ended = False
    t0 = None
    per: dict = {}
    try:
        for i in range(warmup + batches):
            t_wait = time.perf_counter()
            try:
                b = next(it)
            except StopIteration:
                ended = True
                break
            now = time.perf_counter()
            if i < warmup:
                continue
            if t0 is None:
                t0 = t_wait
            waited += now - t_wait
            n += 1
            served = [s for s, pad in zip(b["sample_ids"], b["padding"].tolist()) if not pad]
            samples += len(served)
            ids.update((b["epoch"], s) for s in served)
            epochs.add(b["epoch"])
            bb = sum(v.numel() * v.element_size() for k, v in b.items() if hasattr(v, "numel"))
            nbytes += bb
            for server, k in b["servers"].items():
                per[server] = per.get(server, 0) + k
            if step_s > 0:
                time.sleep(step_s)
    finally:
        it.close()
        if isinstance(stream, ReadAhead):
            stream.close()
    secs = (time.perf_counter() - t0) if t0 is not None else 0.0
    secs = max(secs, 1e-9)
    return {
        "endpoint": endpoint, "batches": n, "samples": samples, "unique_samples": len(ids),
        "seconds": round(secs, 4), "batches_per_s": n / secs, "samples_per_s": samples / secs,
        "mbytes_per_s": nbytes / 1e6 / secs, "wait_fraction": waited / secs if n else 1.0,
        "epochs_seen": sorted(epochs), "ended_early": ended, "step_s": step_s,
        "per_server": {ep: {"samples": k, "samples_per_s": k / secs, "share": k / samples}
                       for ep, k in sorted(per.items())},
    }


def format_report(r: dict) -> str:
    out = (f"{r['batches']} batches, {r['samples']} samples ({r['unique_samples']} unique) in {r['seconds']:.2f} s: "
           f"{r['batches_per_s']:.2f} batches/s, {r['samples_per_s']:.2f} samples/s, "
           f"{r['mbytes_per_s']:.1f} MB/s, waiting {100 * r['wait_fraction']:.0f}% of the time")
    if len(r.get("per_server", {})) > 1:
        out += "".join(f"\n  {ep}: {v['samples']} samples, {v['samples_per_s']:.2f} samples/s "
                       f"({100 * v['share']:.0f}%)" for ep, v in r["per_server"].items())
    return out


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="v2v-loadtest", description="Read batches from v2v-serve and report throughput.")
    p.add_argument("--connect", action="append",
                   help="server endpoint (default tcp://127.0.0.1:5555); repeat it or give a comma list to read several servers (a fleet, or shards) "
                        "together and report each one's rate")
    p.add_argument("--batches", type=int, default=20, help="batches to measure (default 20)")
    p.add_argument("--warmup", type=int, default=1, help="batches read before measuring (default 1)")
    p.add_argument("--outputs", default="voxels,frames,flow", help="comma list of outputs to ask for")
    for flag in LOADTEST_FLAGS:  # push delivery's: refused in one line
        p.add_argument(flag, dest=f"push_{flag.lstrip('-')}", help=argparse.SUPPRESS)
    p.add_argument("--timeout", type=float, default=60.0, help="seconds of server silence before failing")
    p.add_argument("--step-ms", type=float, default=0.0, help="simulated training step per batch, ms")
    p.add_argument("--json", action="store_true", help="print one JSON object on the last line")
    a = p.parse_args(argv)
    if a.batches < 1:
        p.error("--batches must be >= 1")
    for flag in LOADTEST_FLAGS:
        if getattr(a, f"push_{flag.lstrip('-')}") is not None:
            print(f"v2v-loadtest: {loadtest_flag_problem(flag)}", file=sys.stderr)
            return 2
    try:
        r = run_loadtest(",".join(a.connect or ["tcp://127.0.0.1:5555"]), a.batches, tuple(s for s in a.outputs.split(",") if s),
                         a.timeout, a.step_ms / 1000.0, a.warmup)
    except (TimeoutError, RuntimeError, ValueError) as e:
        print(f"v2v-loadtest: {e}", file=sys.stderr)
        return 1
    print(format_report(r))
    if a.json:
        print(json.dumps(r))
    return 0


if __name__ == "__main__":
    from v2v_wire.commands import main_of_module

    sys.exit(main_of_module("v2v-loadtest", main))

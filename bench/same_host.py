"""What moving a batch costs a trainer on the server's host: ``python -m bench.same_host``.

A plan's rows travel as one ZeroMQ message (a header, then one frame per array: the batch's
rows of each output), so a trainer beside its server reads them over loopback TCP (or
``ipc://``). This times that transfer at the paper's shapes against the one copy a hand-off
through shared memory would cost, and against the time a worker takes to make the batch.

* **batch**: ``--batch`` samples (default 12) of the default outputs as the wire carries them:
  voxels int8 (L=40, 5 bins, 128 x 128), frames uint8 (41, 1, 128, 128), the tracked flow's
  grid float32 (40, 2, 8, 8): 3.97 MB a sample ([wire.md](../docs/wire.md)).
* **tcp / ipc**: a server process (a ROUTER holding the batch's arrays) answers each request
  of a client (a DEALER) with the batch, sent zero-copy; the client receives it zero-copy and
  views each frame as its array, as ``V2VStreamDataset`` does (``fetch.Link._recv``).
  Wall time per batch (request to arrays in hand, one request at a time: no overlap) and CPU
  time per batch of each process.
* **memcpy**: one copy of the batch's bytes into a preallocated buffer (what a server writing
  the batch into a shared-memory file costs; the trainer then maps it).
* **to float32**: the trainer's conversion of the batch's voxels and frames to float32, which
  every path does after the transfer (for scale).

Prints a markdown table; ``--json PATH`` writes the numbers.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import statistics
import sys
import tempfile
import time

import numpy as np

SHAPES = {"voxels": ((40, 5, 128, 128), np.int8), "frames": ((41, 1, 128, 128), np.uint8),
          "flow_grid": ((40, 2, 8, 8), np.float32)}


def batch_arrays(batch: int):
    rng = np.random.default_rng(0)
    return {k: rng.integers(0, 100, (batch, *s)).astype(d) for k, (s, d) in SHAPES.items()}


def _cpu() -> float:
    t = os.times()
    return t.user + t.system


def _server(endpoint: str, batch: int, n: int, ready, out) -> None:
    import zmq
    arrays = batch_arrays(batch)
    ctx = zmq.Context()
    sock = ctx.socket(zmq.ROUTER)
    sock.bind(endpoint)
    ready.set()
    cpu0 = None
    for i in range(n + 1):
        who, _ = sock.recv_multipart()
        if i == 1:
            cpu0 = _cpu()  # the first batch is the warm-up
        sock.send_multipart([who, b"rows"] + [memoryview(a) for a in arrays.values()], copy=False)
    out.put(_cpu() - cpu0)
    sock.close(linger=1000)
    ctx.term()


def transfer(endpoint: str, batch: int, n: int):
    import zmq
    ready, out = mp.Event(), mp.Queue()
    p = mp.Process(target=_server, args=(endpoint, batch, n, ready, out))
    p.start()
    ready.wait(30)
    ctx = zmq.Context()
    sock = ctx.socket(zmq.DEALER)
    sock.connect(endpoint)
    walls, nbytes, cpu0 = [], 0, None
    for i in range(n + 1):
        if i == 1:
            cpu0 = _cpu()
        t = time.perf_counter()
        sock.send(b"fetch")
        frames = sock.recv_multipart(copy=False)
        got = [np.frombuffer(f.buffer, dtype=d).reshape(batch, *s)
               for f, (s, d) in zip(frames[1:], SHAPES.values())]
        if i >= 1:
            walls.append(time.perf_counter() - t)
            nbytes = sum(a.nbytes for a in got)
    client_cpu = _cpu() - cpu0
    server_cpu = out.get(timeout=60)
    p.join(30)
    sock.close(linger=0)
    ctx.term()
    return {"ms_per_batch_median": 1e3 * statistics.median(walls), "ms_per_batch_p90": 1e3 * sorted(walls)[int(0.9 * len(walls))],
            "GB_per_s": nbytes / statistics.median(walls) / 1e9, "client_cpu_ms_per_batch": 1e3 * client_cpu / n,
            "server_cpu_ms_per_batch": 1e3 * server_cpu / n, "MB_per_batch": nbytes / 1e6}


def timed(fn, n: int):
    fn()
    walls = []
    for _ in range(n):
        t = time.perf_counter()
        fn()
        walls.append(time.perf_counter() - t)
    return 1e3 * statistics.median(walls)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=12)
    ap.add_argument("--batches", type=int, default=40, help="timed batches per row (after one)")
    ap.add_argument("--port", type=int, default=5599)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    arrays = batch_arrays(a.batch)
    mb = sum(x.nbytes for x in arrays.values()) / 1e6
    flat = np.concatenate([x.reshape(-1).view(np.uint8) for x in arrays.values()])
    dst = np.empty_like(flat)
    rows = {}
    rows["memcpy"] = {"ms_per_batch_median": timed(lambda: np.copyto(dst, flat), a.batches)}
    rows["memcpy"]["GB_per_s"] = mb / 1e3 / (rows["memcpy"]["ms_per_batch_median"] / 1e3)
    rows["tcp://127.0.0.1"] = transfer(f"tcp://127.0.0.1:{a.port}", a.batch, a.batches)
    with tempfile.TemporaryDirectory() as d:
        rows["ipc://"] = transfer(f"ipc://{d}/s", a.batch, a.batches)
    rows["to float32 (voxels, frames)"] = {"ms_per_batch_median": timed(
        lambda: (arrays["voxels"].astype(np.float32), arrays["frames"].astype(np.float32)), max(5, a.batches // 4))}
    print(f"batch of {a.batch} at the paper's shapes, default outputs as the wire carries them: {mb:.1f} MB; "
          f"{os.cpu_count()} CPUs")
    print()
    print("| path | ms per batch (median) | p90 | GB/s | client CPU ms per batch | server CPU ms per batch |")
    print("|---|---:|---:|---:|---:|---:|")
    for k, r in rows.items():
        f = lambda x: f"{r[x]:.1f}" if x in r else ""
        print(f"| {k} | {f('ms_per_batch_median')} | {f('ms_per_batch_p90')} | "
              f"{r['GB_per_s']:.2f} |" if "GB_per_s" in r else f"| {k} | {f('ms_per_batch_median')} | | |", end="")
        print(f" {f('client_cpu_ms_per_batch')} | {f('server_cpu_ms_per_batch')} |")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"command": "python -m bench.same_host " + " ".join(argv if argv is not None else sys.argv[1:]),
                       "batch": a.batch, "MB_per_batch": mb, "cpus": os.cpu_count(), "rows": rows}, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

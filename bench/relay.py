"""The relay's cost per byte, measured at full rate: ``python -m bench.relay``.

In a full stream on a small machine the relay moves a few MB/s and its fixed costs
(heartbeats, polling) dominate CPU per GB; this bench isolates the per-byte cost. Three
processes on one host: a *worker* sends pre-made samples (voxels int8, frames uint8, flow
float16 at L = 40, 128x128, as ``v2v-serve`` makes them) as fast as the socket takes them;
the *relay* runs the server's data path (``recv_multipart(copy=False)`` ->
``datapath.sample_from_worker`` -> ``make_batch`` -> ``BatchPayload.wire`` ->
``send_multipart(copy=False)``); the *client* receives and decodes each batch to tensors
the way ``V2VStreamDataset(raw=True)`` does. Each reports its CPU-seconds (all threads,
ZeroMQ's I/O threads included) per GB. ``--old`` runs the data path before this work
(``np.array`` copy per sample, ``np.stack`` per batch) for comparison.
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
import time
from typing import List, Optional

import numpy as np

B = 8


def _sample_arrays():
    rng = np.random.default_rng(0)
    return {"voxels": rng.integers(-3, 4, (40, 5, 128, 128)).astype(np.int8),
            "frames": rng.integers(0, 256, (41, 128, 128)).astype(np.uint8),
            "flow": rng.normal(0, 2, (40, 2, 128, 128)).astype(np.float16)}


def _worker(endpoint: str, n: int) -> None:
    import zmq

    from v2v_server.protocol import encode_arrays, pack

    ctx = zmq.Context()
    s = ctx.socket(zmq.PUSH)
    s.setsockopt(zmq.SNDHWM, 4)
    s.connect(endpoint)
    specs, frames = encode_arrays(_sample_arrays())
    for i in range(n):
        s.send_multipart([pack({"type": "sample", "sample_id": f"v.mp4#{i}", "meta": {}, "arrays": specs})] + frames,
                         copy=False)
    s.close(linger=-1)
    ctx.term()


def _relay(src: str, dst: str, n: int, old: bool, q) -> None:
    import zmq

    from v2v_server import datapath
    from v2v_server.protocol import narrow_int_dtype, pack, unpack

    ctx = zmq.Context()
    pull = ctx.socket(zmq.PULL)
    pull.setsockopt(zmq.RCVHWM, 4)
    pull.bind(src)
    push = ctx.socket(zmq.PUSH)
    push.setsockopt(zmq.SNDHWM, 4)
    push.bind(dst)
    pending, sent = [], 0
    t0 = None
    for i in range(n):
        frames = pull.recv_multipart(copy=False)
        if t0 is None:
            t0 = time.process_time()
        h = unpack(frames[0])
        if old:  # before: a copy per sample, np.stack per batch
            arrays = {k: np.array(v) for k, v in datapath.decode_arrays(h["arrays"], frames[1:]).items()}
            pending.append(datapath.SamplePayload(h["sample_id"], h["meta"], arrays))
        else:
            pending.append(datapath.sample_from_worker(h, frames[1:]))
        if len(pending) == B:
            if old:
                arrays = {k: np.stack([s.arrays[k] for s in pending]) for k in pending[0].arrays}
                arrays["voxels"] = arrays["voxels"].astype(narrow_int_dtype(arrays["voxels"]), copy=False)
                specs, out = datapath.encode_arrays(arrays)
            else:
                specs, out = datapath.make_batch(pending).wire(("voxels", "frames", "flow"))
            push.send_multipart([pack({"type": "batch", "arrays": specs,
                                       "sample_ids": [s.sample_id for s in pending]})] + out, copy=False)
            sent += sum(a.nbytes for a in out)
            pending = []
    q.put(("relay", time.process_time() - t0, sent))
    pull.close(0)
    push.close(linger=-1)
    ctx.term()


def _client(src: str, batches: int, q) -> None:
    import zmq

    from v2v_client.dataset import batch_to_torch
    from v2v_server.protocol import decode_arrays, unpack

    ctx = zmq.Context()
    pull = ctx.socket(zmq.PULL)
    pull.connect(src)
    got = 0
    t0 = None
    for _ in range(batches):
        frames = pull.recv_multipart(copy=False)
        if t0 is None:
            t0 = time.process_time()
        h = unpack(frames[0])
        t = batch_to_torch(decode_arrays(h["arrays"], frames[1:]), raw=True)
        got += sum(v.numel() * v.element_size() for v in t.values())
    q.put(("client", time.process_time() - t0, got))
    pull.close(0)
    ctx.term()


def measure(batches: int, old: bool, tmp: str) -> dict:
    """Run worker -> relay -> client over ipc:// for ``batches`` batches of 8."""
    q = mp.get_context("spawn").Queue()
    ctx = mp.get_context("spawn")
    a, b = f"ipc://{tmp}/w.sock", f"ipc://{tmp}/c.sock"
    n = batches * B
    procs = [ctx.Process(target=_relay, args=(a, b, n, old, q)), ctx.Process(target=_client, args=(b, batches, q)),
             ctx.Process(target=_worker, args=(a, n))]
    for p in procs:
        p.start()
    out = {}
    for _ in range(2):
        name, cpu, nbytes = q.get(timeout=600)
        out[name] = cpu / (nbytes / 1e9)
        out[name + "_gb"] = nbytes / 1e9
    for p in procs:
        p.join(60)
    return out


def main(argv: Optional[List[str]] = None) -> int:
    import tempfile

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batches", type=int, default=60)
    a = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="v2v-relay-") as d:
        old = measure(a.batches, True, d)
        new = measure(a.batches, False, d)
    buf = np.ones(100_000_000, np.uint8)
    dst = np.empty_like(buf)
    t = time.process_time()
    for _ in range(5):
        np.copyto(dst, buf)
    memcpy = (time.process_time() - t) / 0.5
    print("| data path | relay CPU-s/GB | client CPU-s/GB (raw=True) | GB |\n|---|---:|---:|---:|")
    print(f"| (one memcpy on this machine, for scale) | {memcpy:.2f} | - | - |")
    print(f"| before (copy per sample + np.stack) | {old['relay']:.2f} | - | {old['relay_gb']:.2f} |")
    print(f"| now (views + one stacking copy; raw views on the client) | {new['relay']:.2f} | {new['client']:.2f} | "
          f"{new['relay_gb']:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The relay's cost per byte, measured at full rate: ``python -m bench.relay``.

In a full stream on a small machine the relay moves a few MB/s and its fixed costs
(heartbeats, polling) dominate CPU per GB; this bench isolates the per-byte cost. Three
processes on one host: a *worker* sends pre-made samples (voxels int8, frames uint8, flow
float16 at L = 40, 128x128, as ``v2v-serve`` makes them) as fast as the relay takes them;
the *relay* runs one of the server's data paths and pushes 8-sample batches
(``BatchPayload.wire`` -> ``send_multipart(copy=False)``) over ``ipc://`` to a *client* that
decodes each batch to tensors the way ``V2VPushDataset(raw=True)`` does. Each reports its
CPU-seconds per GB sent (``getrusage``: all threads, ZeroMQ's I/O threads included; user and
system split) and its minor page faults per GB. Paths, measured in the same run:

* ``old``: a copy per sample (``np.array``) and a ``np.stack`` per batch, the baseline;
* ``socket``: arrays as ZeroMQ frames, kept as views, stacked once when the batch is sent
  (the fallback where ``/dev/shm`` is unavailable);
* ``shm``: the worker writes into its shared-memory slot ring and sends the header only; the
  relay copies the slot into the batch buffer's row and gives the slot back
  (``assembly.sample_from_slot`` / ``BatchAssembler``), so the batch is assembled by the time
  it is made and the sample bytes never cross the worker's socket.
* ``handoff``: ``shm``, with the batch buffers in files of a private ``/dev/shm`` directory
  (``shm.BatchDir``); each batch goes to the client as a header naming file, generation
  and offsets (``BatchPayload.shm_ref``), no array frames; the client maps the file, copies
  the arrays into a reused private buffer (``v2v_client.handoff.ShmReader``, what
  ``V2VPushDataset(raw=True, shm="auto")`` does over ``ipc://``) and acknowledges, and the
  relay keeps at most 4 unacknowledged batches (the default credits), as the server does.

``--transport tcp`` sends relay -> client over tcp://127.0.0.1 instead (no hand-off there);
``--compression lz4,zstd`` has the worker send its arrays compressed too (``codecs``) and the
relay forward those frames by reference (``BatchPayload.wire(outputs, codec)``), the client
decompressing them; ``--real`` sends one real sample (compact flow) instead of random arrays,
which do not compress like real voxels. The table adds the relay's CPU per GB of samples
delivered (uncompressed), beside per GB sent.
"""
from __future__ import annotations

import argparse
import dataclasses
import multiprocessing as mp
import resource
import sys
import time
from typing import List, Optional

import numpy as np

B = 8
PATHS = ("old", "socket", "shm", "handoff")
#: unacknowledged batches the relay keeps on the handoff path (V2VPushDataset's default credits)
CREDITS = 4


def _sample_arrays(real: Optional[str] = None):
    """The sample the worker sends: synthetic (random voxels, frames and dense float16 flow), or
    the arrays saved in ``real`` (an .npz of a real sample's wire arrays, ``real_sample``)."""
    if real:
        with np.load(real) as z:
            return {k: z[k] for k in z.files}
    rng = np.random.default_rng(0)
    return {"voxels": rng.integers(-3, 4, (40, 5, 128, 128)).astype(np.int8),
            "frames": rng.integers(0, 256, (41, 128, 128)).astype(np.uint8),
            "flow": rng.normal(0, 2, (40, 2, 128, 128)).astype(np.float16)}


def real_sample(path: str) -> None:
    """Save the first sample of the bundled 596 x 336 clip (default recipe) as a worker sends
    it (voxels int8, frames uint8, the tracked flow as ``flow_grid``) to ``path`` (.npz)."""
    from v2v_server.samples.recipe import SampleRecipe
    from v2v_server.ops.startup import SAMPLE_VIDEOS
    from v2v_server.samples.make import video_samples
    from v2v_server.sources.local import LocalSource
    from v2v_server.service.worker import wire_arrays
    from v2v_wire.outputs import DEFAULT_OUTPUTS

    cfg = SampleRecipe(shot_cuts="off")
    _, arrays, _ = next(video_samples(cfg, LocalSource(SAMPLE_VIDEOS), "webvid_like_596x336.mp4", 0, DEFAULT_OUTPUTS, flow_grid=True))
    np.savez(path, **wire_arrays(cfg, arrays))


class _Clock:
    """CPU seconds (user, system) and minor page faults of this process since ``start()``
    (or since the first ``recv`` when never started)."""

    r0 = None

    def start(self) -> None:
        self.r0 = resource.getrusage(resource.RUSAGE_SELF)

    def recv(self, sock) -> list:
        """``sock.recv_multipart(copy=False)``, starting the clock on the first message (set-up
        and waiting for the first message are not counted)."""
        frames = sock.recv_multipart(copy=False)
        if self.r0 is None:
            self.start()
        return frames

    def read(self) -> dict:
        r = resource.getrusage(resource.RUSAGE_SELF)
        return {"user": r.ru_utime - self.r0.ru_utime, "sys": r.ru_stime - self.r0.ru_stime,
                "faults": r.ru_minflt - self.r0.ru_minflt}


def _worker(endpoint: str, release: str, n: int, ring_spec: Optional[dict], real: Optional[str] = None,
            codec: str = "none") -> None:
    import zmq

    from v2v_server.service.shm import SlotRing
    from v2v_wire.ids import SampleKey
    from v2v_wire.protocol import encode_arrays, pack
    from v2v_wire.worker_messages import Sample
    from v2v_server.service.worker import pack_arrays

    ctx = zmq.Context()
    s = ctx.socket(zmq.PUSH)
    s.setsockopt(zmq.SNDHWM, 4)
    s.connect(endpoint)
    arrays = _sample_arrays(real)
    specs, frames = encode_arrays(arrays)
    packed_specs, packed = pack_arrays(arrays, [codec])  # once: the worker's CPU is not what is measured
    ring = rel = None
    if ring_spec is not None:
        ring = SlotRing.attach(ring_spec, unlink=False)
        rel = ctx.socket(zmq.PULL)
        rel.connect(release)
    for i in range(n):
        h = Sample(0, SampleKey("v.mp4", i), {}, tuple(specs), tuple(packed_specs))
        if ring is None:
            s.send_multipart([pack(h.to_wire())] + frames + packed, copy=False)
            continue
        while not ring.free:  # block until the relay gives a slot back
            ring.free.append(int(rel.recv()))
        slot = ring.free.pop(0)
        ring.put(slot, arrays)
        s.send_multipart([pack(dataclasses.replace(h, slot=slot).to_wire())] + packed, copy=False)
    s.close(linger=-1)
    if rel is not None:
        rel.close(0)
    ctx.term()
    if ring is not None:
        ring.close()


def _relay(src: str, release: str, dst: str, n: int, path: str, ring_spec: Optional[dict], q,
           acks: Optional[str] = None, codec: str = "none") -> None:
    import zmq

    from v2v_server.service.assembly import BatchAssembler, SamplePayload, sample_from_slot, sample_from_worker
    from v2v_server.service.shm import BatchDir, SlotRing
    from v2v_wire.protocol import decode_arrays, unpack
    from v2v_wire.worker_messages import Sample

    ctx = zmq.Context()
    pull = ctx.socket(zmq.PULL)
    pull.setsockopt(zmq.RCVHWM, 4)
    pull.bind(src)
    push = ctx.socket(zmq.PUSH)
    push.setsockopt(zmq.SNDHWM, 4)
    push.bind(dst)
    ring = rel = ack = files = None
    inflight = {}  # handoff: batch id -> payload until the client acknowledges it
    if path == "handoff":
        files = BatchDir.create()
        ack = ctx.socket(zmq.PULL)
        ack.bind(acks)
    if path in ("shm", "handoff"):
        ring = SlotRing.attach(ring_spec, unlink=False)
        assembler = BatchAssembler(B, files=files)
        rel = ctx.socket(zmq.PUSH)
        rel.setsockopt(zmq.SNDTIMEO, 2000)
        rel.bind(release)
    pending, sent, sent_batches, data = [], 0, 0, 0
    clock = _Clock()
    for i in range(n):
        frames = clock.recv(pull)
        h = Sample.from_wire(unpack(frames[0]))
        if path == "old":  # before: a copy per sample, np.stack per batch
            arrays = {k: np.array(v) for k, v in decode_arrays(list(h.arrays), frames[1:]).items()}
            pending.append(SamplePayload(h.key.sample_id(), h.meta, arrays))
        elif path in ("shm", "handoff"):
            pending.append(sample_from_slot(h, ring, assembler, frames[1:]))
            try:  # the slot back to the worker (which may have finished and gone)
                rel.send(str(h.slot).encode())
            except zmq.Again:
                pass
        else:
            pending.append(sample_from_worker(h, frames[1:]))
        del frames
        if len(pending) == B:
            data += sum(x.nbytes for x in pending)
            sent += _send_batch(path, pending, push, codec, files, inflight, ack, sent_batches)
            sent_batches += path == "handoff"
            pending = []
    push.close(linger=-1)  # every batch handed to the kernel before the clock stops
    while inflight:  # handoff: the client has copied every batch out before the files go
        inflight.pop(int(ack.recv()), None)
    q.put(("relay", clock.read(), sent, data))
    if ack is not None:
        ack.close(0)
        assembler.close()
    pull.close(0)
    if rel is not None:
        rel.close(0)
    ctx.term()
    if ring is not None:
        ring.close()


def _send_batch(path: str, pending: list, push, codec: str, files, inflight: dict, ack, batch_id: int) -> int:
    """Send the batch of the ``pending`` samples the way ``path`` does (``old``: a stacked copy;
    ``handoff``: by reference into ``files``, held in ``inflight`` until ``ack`` says the client
    copied it, at most ``CREDITS`` of them; else the zero-copy batch, ``codec`` compressed); the
    bytes sent."""
    from v2v_server.service.assembly import make_batch
    from v2v_wire.protocol import encode_arrays, narrow_int_dtype, pack

    outputs = ("voxels", "frames", "flow")
    ids = [s.sample_id for s in pending]
    if path == "handoff":
        while len(inflight) >= CREDITS:  # the client's window is full: wait for an ack
            inflight.pop(int(ack.recv()), None)
        batch = make_batch(pending)
        specs, ref = batch.shm_ref(outputs)
        inflight[batch_id] = batch
        push.send(pack({"type": "batch", "batch_id": batch_id, "arrays": specs, "shm": ref, "dir": files.path,
                        "sample_ids": ids}))
        return sum(batch.arrays[x["name"]].nbytes for x in specs)
    if path == "old":  # before: a copy per sample, np.stack per batch
        arrays = {k: np.stack([s.arrays[k] for s in pending]) for k in pending[0].arrays}
        arrays["voxels"] = arrays["voxels"].astype(narrow_int_dtype(arrays["voxels"]), copy=False)
        specs, out = encode_arrays(arrays)
        push.send_multipart([pack({"type": "batch", "arrays": specs, "sample_ids": ids})] + out, copy=False)
    else:  # the buffer's rows stay leased until ZeroMQ has sent them
        batch = make_batch(pending)
        specs, out = batch.wire(outputs, codec)
        batch.send(push, [pack({"type": "batch", "arrays": specs, "sample_ids": ids})], out)
    return sum(a.nbytes if isinstance(a, np.ndarray) else len(a.buffer) for a in out)


def _client(src: str, batches: int, q, acks: Optional[str] = None) -> None:
    import zmq

    from v2v_client.tensors import batch_to_torch
    from v2v_client.handoff import ShmReader
    from v2v_wire.codecs import decode_batch_arrays
    from v2v_wire.protocol import unpack

    ctx = zmq.Context()
    pull = ctx.socket(zmq.PULL)
    pull.connect(src)
    ack = reader = None
    if acks is not None:
        ack = ctx.socket(zmq.PUSH)
        ack.connect(acks)
        reader = ShmReader(keep=CREDITS + 4)
    got = 0
    clock = _Clock()
    for _ in range(batches):
        frames = clock.recv(pull)
        h = unpack(frames[0])
        if "shm" in h:  # copy out of the relay's batch file, then acknowledge
            reader.set_dir(h["dir"])
            t = batch_to_torch(reader.read(h), raw=True)
            ack.send(str(h["batch_id"]).encode())
        else:
            t = batch_to_torch(decode_batch_arrays(h["arrays"], frames[1:]), raw=True, compact_flow=True)
        got += sum(v.numel() * v.element_size() for v in t.values())
        del t, frames
    q.put(("client", clock.read(), got, got))
    pull.close(0)
    if ack is not None:
        ack.close(linger=-1)
        reader.close()
    ctx.term()


def measure(batches: int, path: str, tmp: str, transport: str = "ipc", codec: str = "none",
            real: Optional[str] = None) -> dict:
    """Run worker -> relay -> client for ``batches`` batches of 8 on ``path`` (one of
    ``PATHS``), relay to client over ``transport`` ("ipc", or "tcp" on 127.0.0.1), arrays
    compressed by the worker with ``codec``; returns per process ``{"user", "sys", "faults",
    "gb", "data_gb"}`` (``gb``: bytes sent or received; ``data_gb``: the samples' uncompressed
    bytes)."""
    from harness.serve import free_port
    from v2v_server.service.shm import SlotRing, slot_bytes

    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    a, r = f"ipc://{tmp}/w.sock", f"ipc://{tmp}/r.sock"
    b = f"ipc://{tmp}/c.sock" if transport == "ipc" else f"tcp://127.0.0.1:{free_port()}"
    k = f"ipc://{tmp}/k.sock" if path == "handoff" else None
    n = batches * B
    ring = SlotRing.create(3, slot_bytes(40, 5, 128)) if path in ("shm", "handoff") else None
    spec = ring.spec if ring else None
    try:
        procs = [ctx.Process(target=_relay, args=(a, r, b, n, path, spec, q, k, codec)),
                 ctx.Process(target=_client, args=(b, batches, q, k)),
                 ctx.Process(target=_worker, args=(a, r, n, spec, real, codec))]
        for p in procs:
            p.start()
        out = {}
        for _ in range(2):
            name, cpu, nbytes, data = q.get(timeout=600)
            out[name] = dict(cpu, gb=nbytes / 1e9, data_gb=data / 1e9)
        for p in procs:
            p.join(60)
    finally:
        if ring is not None:
            ring.unlink()
            ring.close()
    return out


def memcpy_s_per_gb() -> float:
    """CPU-seconds per GB of one ``np.copyto`` of 100 MB on this machine (for scale)."""
    buf = np.ones(100_000_000, np.uint8)
    dst = np.empty_like(buf)
    np.copyto(dst, buf)
    t = time.process_time()
    for _ in range(5):
        np.copyto(dst, buf)
    return (time.process_time() - t) / 0.5


def main(argv: Optional[List[str]] = None) -> int:
    import tempfile

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batches", type=int, default=60)
    p.add_argument("--paths", default=",".join(PATHS), help="comma-separated subset of " + ", ".join(PATHS))
    p.add_argument("--rounds", type=int, default=1, help="measure every path this many times, interleaved")
    p.add_argument("--transport", choices=("ipc", "tcp"), default="ipc", help="relay -> client socket")
    p.add_argument("--compression", default="none", help="comma-separated codecs (v2v_wire.codecs), each a run")
    p.add_argument("--real", action="store_true", help="a real sample (compact flow) instead of synthetic arrays")
    a = p.parse_args(argv)
    paths = [x for x in a.paths.split(",") if x]
    for x in paths:
        if x not in PATHS:
            p.error(f"unknown path {x!r}; choose from {', '.join(PATHS)}")
    codecs = [c for c in a.compression.split(",") if c]
    if a.transport == "tcp" and "handoff" in paths:
        paths.remove("handoff")  # a same-host hand-off needs ipc://
    rows = []
    with tempfile.TemporaryDirectory(prefix="v2v-relay-") as d:
        real = None
        if a.real:
            real = f"{d}/sample.npz"
            real_sample(real)
        for _ in range(a.rounds):
            for c in codecs:
                for x in paths:
                    if c != "none" and x in ("old", "handoff"):
                        continue  # compression is for the socket paths
                    rows.append((x if c == "none" else f"{x}, {c}", measure(a.batches, x, d, a.transport, c, real)))
    memcpy = memcpy_s_per_gb()
    print(f"relay -> client over {a.transport}://, {'a real sample' if a.real else 'synthetic samples'}\n")
    print("| data path | relay CPU-s/GB | relay user | relay system | relay faults/GB | relay CPU-s per GB of samples | "
          "client CPU-s/GB (raw=True) | client user | client system | GB sent | GB of samples |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    print(f"| one memcpy (np.copyto 100 MB), for scale | {memcpy:.2f} | | | | | | | | | |")
    for x, m in rows:
        r, c = m["relay"], m["client"]
        gr, gc = r["gb"], c["gb"]
        cpu = r["user"] + r["sys"]
        print(f"| {x} | {cpu / gr:.2f} | {r['user'] / gr:.2f} | {r['sys'] / gr:.2f} | "
              f"{r['faults'] / gr:.0f} | {cpu / r['data_gb']:.2f} | {(c['user'] + c['sys']) / gc:.2f} | "
              f"{c['user'] / gc:.2f} | {c['sys'] / gc:.2f} | {gr:.2f} | {r['data_gb']:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

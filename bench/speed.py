"""The speed table, every row measured in one run on one machine: ``python -m bench.speed``.

Every rate is per core: samples per CPU-second of the process doing the work (so other
load on a shared machine inflates wall time, not the ratios), on the WebVid-like clip
(596x336 H.264, 25 fps; ``--clip`` another), 128x128 crops, L = 40 x 5 bins (201 frames per sample).

Rows:

* bare decode: PyAV, Y plane only, one thread -> frames per CPU-second / 201 = the decode
  bound in samples/s;
* reference-style loader (the V2V authors' data loader, transcribed): per sample reopen and
  seek with cv2.VideoCapture, read BGR, cvtColor to gray, crop, float64 V2V with noise and
  hot pixels in numpy, no flow;
* ours, one worker core (``samples.video_samples`` + the wire narrowing, in this process):
  voxels only, and every output at the default flow preset; both again with ``decode_fast``
  ``bidir`` (docs/decode_fast.md: the fastest setting whose voxel error stays under V2V's own
  noise); ``crops_per_window`` 4;
* the stream: ``v2v-serve --workers 2`` read by plan (the plan's epochs in turn through
  ``V2VStreamDataset(raw=True)``, four fetches in flight): the server main process's
  CPU-seconds per GB sent, the client process's CPU-seconds per GB received, stream samples/s
  with 1 and 2 workers, time to the first batch;
* memory: server tree RSS under a trainer that stalls, against the bound of docs/speed.md (Memory bound).
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path
from typing import Callable, List, Optional

import numpy as np

from bench.throughput import tree_rss_mb  # the benches' one reader of a process tree's RSS

CLIP = "webvid_like_596x336.mp4"
SPAN = 201


def clip_path(name: str = CLIP) -> Path:
    """The measured clip (``--clip``): a bundled clip's name or a path."""
    here = Path(__file__).resolve().parents[1] / "v2v_server" / "sample_videos" / name
    return here if here.exists() else Path(name)


def make_corpus(root: Path, copies: int, clip: Optional[Path] = None) -> Path:
    """A corpus of ``copies`` copies of the measured clip (the WebVid-like one: 2 windows each)."""
    root.mkdir(parents=True, exist_ok=True)
    for i in range(copies):
        shutil.copyfile(clip or clip_path(), root / f"clip{i:03d}.mp4")
    return root


# ---------------------------------------------------------------------------- baselines
def bare_decode(path: Path, repeats: int) -> float:
    """Frames per CPU-second: PyAV decode, Y plane viewed, one thread."""
    from v2v_server.frames.decode import decode_luma, open_video

    n = 0
    t = time.process_time()
    for _ in range(repeats):
        c, s, _ = open_video(path, 1)
        for y in decode_luma(c, s):
            n += 1
    return n / (time.process_time() - t)


def _v2v_float64(frames: np.ndarray, cp: float, cn: float, sigma: float, hot: np.ndarray,
                 rng: np.random.Generator, num_bins: int = 5) -> np.ndarray:
    """The reference repo's style: float64 numpy, one pass per array operation."""
    logi = np.log(1e-3 + (frames.astype(np.float64) / 255.0) ** 2.2)
    pot = rng.uniform(-cn, cp, frames.shape[1:])
    out = np.empty((len(frames) - 1,) + frames.shape[1:], np.int32)
    for i in range(1, len(frames)):
        dl = pot + (logi[i] - logi[i - 1]) + rng.normal(0, sigma, frames.shape[1:]) + hot
        npos = np.maximum(np.floor(dl / cp), 0)
        nneg = np.maximum(np.floor(-dl / cn), 0)
        pot = dl - cp * npos + cn * nneg
        out[i - 1] = npos - nneg
    return out.reshape(-1, num_bins, *frames.shape[1:])


def reference_loader(path: Path, samples: int, crop: int = 128) -> float:
    """Samples per CPU-second of a reference-style loader (see module doc)."""
    import cv2

    cv2.setNumThreads(1)
    rng = np.random.default_rng(0)
    t = time.process_time()
    for k in range(samples):
        cap = cv2.VideoCapture(str(path))
        total = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        start = int(rng.integers(0, max(1, total - SPAN)))
        cap.set(cv2.CAP_PROP_POS_FRAMES, start)
        frames = []
        for _ in range(SPAN):
            ok, bgr = cap.read()
            if not ok:
                break
            g = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
            frames.append(g[:crop, :crop])
        cap.release()
        f = np.stack(frames)
        hot = np.zeros(f.shape[1:])
        m = rng.random(f.shape[1:]) < 0.0005
        hot[m] = rng.normal(0, 5, int(m.sum()))
        _v2v_float64(f, 0.2, 0.25, 0.05, hot, rng)
    return samples / (time.process_time() - t)


# ---------------------------------------------------------------------------- ours, one core
def worker_core(corpus: Path, outputs, crops: int = 1, videos: int = 2, decode_fast: str = "off",
                flow_grid: bool = False, busy: Optional[dict] = None, caches=None, epoch: int = 0) -> float:
    """Samples per CPU-second of one worker's work (decode, crop, simulate, flow, narrowing)
    in this process, one thread, with the recipe's ``decode_fast`` setting. ``flow_grid``:
    the tracked flow as its grid, as a served worker sends it. ``busy``, when given, receives
    ``samples`` and the seconds spent per stage (``SamplePass.seconds``: ``simulate``,
    ``flow``, ``stats``). ``caches``: the host's caches to read through (``HostCaches``: the
    frame cache), None for none; ``epoch``: the epoch drawn."""
    import cv2

    from v2v_server.samples.recipe import SampleRecipe
    from v2v_server.flow.estimate import FlowEstimator
    from v2v_server.samples.make import video_samples
    from v2v_server.sources.local import LocalSource
    from v2v_server.service.worker import wire_arrays

    cv2.setNumThreads(1)
    cfg = SampleRecipe(shot_cuts="off", seed=1, crops_per_window=crops, decode_fast=decode_fast)
    names = sorted(p.name for p in corpus.iterdir())[:videos]
    flow = FlowEstimator(cfg.flow_preset) if "flow" in outputs else None
    busy = {} if busy is None else busy
    n = 0
    t = time.process_time()
    for name in names:
        run = video_samples(cfg, LocalSource(corpus), name, epoch, outputs, (), flow, flow_grid, caches)
        for sid, arrays, meta in run:
            wire_arrays(cfg, arrays)
            n += 1
        for k, v in asdict(run.seconds).items():
            busy[k] = busy.get(k, 0.0) + v
    busy["samples"] = busy.get("samples", 0) + n
    return n / (time.process_time() - t)


def warm_kernel() -> None:
    """Compile (or load) the kernel's int8 and int16 count variants on a tiny clip: which one a
    sample takes depends on its thresholds, and a first use inside a measured round (a compile
    after the kernel's source changed) read 4x slower there."""
    from v2v_server.simulation.simulate import SensorParams, simulate_voxels

    frames = np.random.default_rng(0).integers(0, 256, (6, 8, 8)).astype(np.uint8)
    for c in (0.2, 0.01):  # int8 straight from the kernel; int16 below the int8 bound
        simulate_voxels(frames, SensorParams(c, c, 0.05, np.zeros((8, 8), np.float32)), 5, narrow=True)


# ---------------------------------------------------------------------------- the stream
def _cpu_s(pid: int) -> float:
    """User + system CPU-seconds of one process (all its threads, not its children)."""
    f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


def reader(endpoint: str, outputs=("voxels", "frames", "flow"), prefetch: int = 4):
    """An iterator over the plan's epochs in turn at ``endpoint``, raw wire dtypes, ``prefetch``
    fetches in flight (the benches' trainer with no step)."""
    from v2v_client import PlanEpochs, V2VStreamDataset

    return iter(PlanEpochs(V2VStreamDataset(endpoint, outputs=outputs, prefetch=prefetch, timeout_s=300, raw=True)))


def served(b: dict) -> tuple:
    """(samples, bytes of their arrays) of batch ``b``: its rows that carry a sample, not padding."""
    n = len(b["padding"])
    rows = n - int(b["padding"].sum())
    return rows, sum(v.numel() * v.element_size() for v in b.values() if hasattr(v, "numel")) * rows // n


def stream(corpus: Path, workers: int, batches: int, outputs, extra: List[str], endpoint: Optional[str] = None) -> dict:
    """Through ``v2v-serve`` read by plan (:func:`reader`): samples/s, time to the first batch,
    and CPU-seconds per GB of the server main process and of this (client) process, measured
    after two batches and the server's made-ahead stock (:func:`made_ahead`)."""
    from harness.serve import ServeProcess

    args = ["--videos", str(corpus), "--shot-cuts", "off", "--workers", str(workers), "--batch-size", "8", "--seed", "1", *extra]
    if endpoint:
        args += ["--bind", endpoint]
    with ServeProcess(args) as srv:
        t0 = time.perf_counter()
        it = reader(srv.endpoint, outputs)
        next(it)
        first = time.perf_counter() - t0
        next(it)
        stock = 0
        while stock < made_ahead(extra):  # samples the server made before the window asked
            stock += served(next(it))[0]
        s0, c0, w0 = _cpu_s(srv.proc.pid), time.process_time(), time.perf_counter()
        nbytes = samples = 0
        for _ in range(batches):
            rows, size = served(next(it))
            samples, nbytes = samples + rows, nbytes + size
        s1, c1, w1 = _cpu_s(srv.proc.pid), time.process_time(), time.perf_counter()
        it.close()
    gb = nbytes / 1e9
    return {"first_batch_s": first, "samples_per_s": samples / (w1 - w0), "gb": gb,
            "server_cpu_s_per_gb": (s1 - s0) / gb, "client_cpu_s_per_gb": (c1 - c0) / gb}


def _threads_cpu_s(pid: int) -> tuple:
    """(main thread, every other thread) CPU-seconds of process ``pid``."""
    main = other = 0.0
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            f = Path(f"/proc/{pid}/task/{tid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:  # the thread ended meanwhile
            continue
        s = (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")
        main, other = (main + s, other) if tid == str(pid) else (main, other + s)
    return main, other


def worker_pids(server_pid: int) -> List[int]:
    """The worker processes of a ``v2v-serve`` (its children, less multiprocessing's resource tracker)."""
    kids = Path(f"/proc/{server_pid}/task/{server_pid}/children").read_text().split()
    return [int(k) for k in kids if "resource_tracker" not in Path(f"/proc/{k}/cmdline").read_text()]


def made_ahead(extra: List[str]) -> int:
    """Samples a plan server started with ``extra`` makes ahead of the fetches: its shuffle buffer."""
    from v2v_wire.plan import SHUFFLE_BUFFER

    return int(extra[extra.index("--shuffle-buffer") + 1]) if "--shuffle-buffer" in extra else SHUFFLE_BUFFER


def producer(corpus: Path, workers: int, samples: int, extra: List[str], outputs=("voxels", "frames", "flow")) -> dict:
    """The producer alone: ``v2v-serve --workers N`` read as fast as a raw client takes it.

    Returns a dict: ``samples_per_s`` (wall), ``per_worker`` (wall samples/s / N),
    ``per_worker_cpu_s`` (samples per CPU-second of the worker processes, all their threads),
    ``core_share`` (workers' CPU-seconds / (N x wall seconds): below 1 when a worker waited for
    a core, a slot or the server), ``other_threads`` (share of the workers' CPU-seconds spent
    outside their main threads: decoder, OpenCV, BLAS or numba pools), ``threads`` (threads per
    worker), ``server_cpu_s`` per sample and ``server_cpu_s_per_gb`` (the server main process, per GB
    of the batches' arrays received) and ``gb``. Measured after two batches and the server's
    made-ahead stock (:func:`made_ahead`), read unmeasured: the workers then make what the
    window reads. Raises ``RuntimeError`` when the workers used no CPU during the measured
    samples (all of them made before the window).
    """
    from harness.serve import ServeProcess

    args = ["--videos", str(corpus), "--shot-cuts", "off", "--workers", str(workers), "--batch-size", "4", "--seed", "1", *extra]
    with ServeProcess(args, ready_timeout_s=300) as srv:
        it = reader(srv.endpoint, outputs)
        for _ in range(2):  # workers started, kernels loaded
            next(it)
        stock = 0
        while stock < made_ahead(extra):  # samples the server made before the window asked
            stock += served(next(it))[0]
        pids = worker_pids(srv.proc.pid)
        c0, s0, w0 = [_threads_cpu_s(p) for p in pids], _cpu_s(srv.proc.pid), time.perf_counter()
        n = nbytes = 0
        while n < samples:
            rows, size = served(next(it))
            n, nbytes = n + rows, nbytes + size
        c1, s1, w1 = [_threads_cpu_s(p) for p in pids], _cpu_s(srv.proc.pid), time.perf_counter()
        threads = max(len(os.listdir(f"/proc/{p}/task")) for p in pids)
        it.close()
    main = sum(b[0] - a[0] for a, b in zip(c0, c1))
    other = sum(b[1] - a[1] for a, b in zip(c0, c1))
    if main + other <= 0:
        raise RuntimeError(f"producer: the workers used no CPU while the {n} measured samples arrived: they were "
                           "all made before the window (made ahead by the server and fetched ahead by the client); measure "
                           "more samples")
    wall = w1 - w0
    return {"workers": workers, "samples": n, "samples_per_s": n / wall, "per_worker": n / wall / workers,
            "per_worker_cpu_s": n / (main + other), "core_share": (main + other) / (workers * wall),
            "other_threads": other / (main + other), "threads": threads, "server_cpu_s": (s1 - s0) / n,
            "gb": nbytes / 1e9, "server_cpu_s_per_gb": (s1 - s0) / max(nbytes / 1e9, 1e-12)}


def stalled_memory(corpus: Path, stall_s: float, workers: int = 2, batch: int = 8, prefetch: int = 1) -> dict:
    """Server tree RSS while a trainer with ``prefetch`` fetches in flight takes nothing for ``stall_s``."""
    from harness.serve import ServeProcess
    from v2v_wire.plan import SHUFFLE_BUFFER
    from v2v_wire.protocol import DEFAULT_OUTPUTS

    args = ["--videos", str(corpus), "--shot-cuts", "off", "--workers", str(workers), "--batch-size", str(batch), "--seed", "1"]
    with ServeProcess(args) as srv:
        it = reader(srv.endpoint, DEFAULT_OUTPUTS, prefetch)
        rows, size = served(next(it))
        sample_mb = size / 1e6 / rows
        time.sleep(3.0)
        start = tree_rss_mb(srv.proc.pid)
        peak = start
        t_end = time.time() + stall_s
        while time.time() < t_end:
            time.sleep(1.0)
            peak = max(peak, tree_rss_mb(srv.proc.pid))
        idle = srv_idle_rss = tree_rss_mb(srv.proc.pid)
        it.close()
    # the bound on what the data path holds: workers x (window buffers + 3 shared-memory slots) + the
    # server's store (the shuffle buffer made ahead, a batch kept once fetched, the largest video's
    # samples: 2 windows of the clip) + the replies of the fetches in flight
    window_mb = SPAN * 128 * 128 / 1e6
    bound = workers * (window_mb + 3 * sample_mb) + (SHUFFLE_BUFFER + batch + 2 + prefetch * batch) * sample_mb
    return {"start_mb": start, "peak_mb": peak, "end_mb": idle, "growth_mb": peak - start,
            "data_bound_mb": bound, "sample_mb": sample_mb, "srv_idle": srv_idle_rss}


# ---------------------------------------------------------------------------- main
def per_core_rows(corpus: Path, clip: Path, rounds: int, row: Callable) -> None:
    """The per-core rows (``row(name, value, unit, ratio, target)`` each): bare decoding, the
    reference-style loader and one worker core's rates, measured in ``rounds`` interleaved rounds."""
    from v2v_server.samples.recipe import SampleRecipe

    default_flow = SampleRecipe(shot_cuts="off").flow_preset
    outs = ("voxels", "frames", "flow")
    # warm the decoder and load every compiled function (kernel, flow) once, unmeasured: a
    # first call that loads numba's cache is ~0.1-0.3 s slower and would bias its row
    worker_core(corpus, ("voxels",), videos=1)
    worker_core(corpus, outs, crops=4, videos=1)
    worker_core(corpus, ("voxels",), videos=1, decode_fast="bidir")
    warm_kernel()
    # the per-core rows are ratios: each round measures every row once, in turn, so that a change of
    # the shared machine's speed hits all rows of a round alike; the ratios are the medians
    # of the per-round ratios, the rates the medians of the rounds
    rnd = {k: [] for k in ("fps", "ref", "vox", "allo", "k4", "voxb", "allb")}
    for _ in range(rounds):
        rnd["fps"].append(bare_decode(clip, 3))
        rnd["ref"].append(reference_loader(clip, 4))
        rnd["vox"].append(worker_core(corpus, ("voxels",)))
        rnd["voxb"].append(worker_core(corpus, ("voxels",), decode_fast="bidir"))
        rnd["allb"].append(worker_core(corpus, outs, decode_fast="bidir"))
        # crops 1 and crops 4 in alternating order (ABBA over rounds): whichever row runs
        # first after the voxels-only one read ~4 % slower on this machine (6 rounds)
        for k in ((1, 4) if len(rnd["k4"]) % 2 == 0 else (4, 1)):
            rnd["allo" if k == 1 else "k4"].append(worker_core(corpus, outs, crops=k))
    med = lambda v: float(np.median(v))  # noqa: E731
    per = lambda num, den: med([x / y for x, y in zip(rnd[num], rnd[den])])  # noqa: E731
    fps = med(rnd["fps"])
    bound, ref, vox, allo, k4 = fps / SPAN, med(rnd["ref"]), med(rnd["vox"]), med(rnd["allo"]), med(rnd["k4"])
    dec = lambda k: per(k, "fps") * SPAN  # noqa: E731  (share of the decode bound, per round)
    note = f" (median of {rounds} interleaved rounds)"
    row("bare decode (PyAV, Y plane, 1 thread)", bound, "samples/CPU-s", f"{fps:.0f} frames/CPU-s")
    row("reference-style loader (cv2 seek, BGR, float64 V2V, no flow)", ref, "samples/CPU-s",
        f"{dec('ref'):.0%} of decode bound")
    row("ours, one worker core, voxels only", vox, "samples/CPU-s",
        f"{dec('vox'):.0%} of decode bound, {per('vox', 'ref'):.1f}x reference{note}", ">= 85 %")
    row(f"ours, one worker core, every output (flow {default_flow})", allo, "samples/CPU-s",
        f"{dec('allo'):.0%} of decode bound, {per('allo', 'ref'):.1f}x reference", ">= 85 %")
    row("ours, one worker core, voxels only, decode_fast bidir", med(rnd["voxb"]), "samples/CPU-s",
        f"{per('voxb', 'vox'):.2f}x decode_fast off")
    row(f"ours, one worker core, every output (flow {default_flow}), decode_fast bidir", med(rnd["allb"]),
        "samples/CPU-s", f"{per('allb', 'allo'):.2f}x decode_fast off")
    k4r = [x / y for x, y in zip(rnd["k4"], rnd["allo"])]
    row("crops_per_window 4, every output", k4, "samples/CPU-s",
        f"{med(k4r):.2f}x crops 1 (rounds: {', '.join(f'{r:.2f}' for r in k4r)})", ">= 2.5x")


def stream_rows(corpus: Path, folder: str, batches: int, stall: float, row: Callable) -> None:
    """The rows through a served stream (``row`` as :func:`per_core_rows`): the server main
    process's CPU per GB, the client's, 1 and 2 workers' rates, and the server's memory over a ``stall`` s stall;
    ``folder``: where the ``ipc://`` socket goes."""
    outs = ("voxels", "frames", "flow")
    s1 = stream(corpus, 1, batches, outs, [])
    s2 = stream(corpus, 2, batches, outs, ["--crops-per-window", "4"])
    # a short 2-core stream: polling and the workers' competition for the cores are in these per-GB rows
    row("server main process CPU per GB (2 workers, crops 4, whole stream)", s2["server_cpu_s_per_gb"],
        "CPU-s/GB", f"{s2['gb']:.2f} GB of samples")
    ipc = f"ipc://{folder}/v2v.sock"
    s3 = stream(corpus, 2, batches, outs, ["--crops-per-window", "4"], endpoint=ipc)
    row("server main process CPU per GB over ipc:// (same host, whole stream)", s3["server_cpu_s_per_gb"], "CPU-s/GB",
        f"{s3['samples_per_s']:.1f} samples/s")
    row("client CPU per GB of samples, raw=True (flow expanded from the grid)", s2["client_cpu_s_per_gb"],
        "CPU-s/GB", "")
    row("stream, 1 worker, every output", s1["samples_per_s"], "samples/s",
        f"first batch after {s1['first_batch_s']:.1f} s")
    s2b = stream(corpus, 2, batches, outs, [])
    row("stream, 2 workers, every output", s2b["samples_per_s"], "samples/s",
        f"{s2b['samples_per_s'] / s1['samples_per_s']:.2f}x 1 worker (2 cores, shared); first batch after "
        f"{s2b['first_batch_s']:.1f} s", "~2x")
    mem = stalled_memory(corpus, stall)
    row(f"server tree RSS growth over a {stall:.0f} s stall", mem["growth_mb"], "MB",
        f"from {mem['start_mb']:.0f} MB; data-path bound {mem['data_bound_mb']:.0f} MB", "<= bound")


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--copies", type=int, default=6, help="copies of the WebVid-like clip in the corpus (2 windows each)")
    p.add_argument("--batches", type=int, default=6, help="measured stream batches (of 8) per stream row")
    p.add_argument("--stall", type=float, default=60.0, help="seconds the stalled trainer takes nothing")
    p.add_argument("--rounds", type=int, default=3, help="interleaved rounds of the per-core rows")
    p.add_argument("--out", help="also write the table (markdown) here")
    p.add_argument("--clip", default=CLIP, help="the clip every row measures: a bundled clip's name or a path "
                                                "(at least 201 frames)")
    a = p.parse_args(argv)
    clip = clip_path(a.clip)
    rows = []

    def row(name, value, unit, ratio="", target=""):
        rows.append((name, value, unit, ratio, target))
        print(f"{name}: {value:.3g} {unit} {ratio}", file=sys.stderr)

    with tempfile.TemporaryDirectory(prefix="v2v-speed-") as d:
        corpus = make_corpus(Path(d) / "webvid", a.copies, clip)
        per_core_rows(corpus, clip, a.rounds, row)
        stream_rows(corpus, d, a.batches, a.stall, row)
    lines = ["| measurement | value | unit | ratio / note | target |", "|---|---:|---|---|---|"]
    for name, value, unit, ratio, target in rows:
        lines.append(f"| {name} | {value:.3g} | {unit} | {ratio} | {target} |")
    table = "\n".join(lines)
    print(table)
    if a.out:
        Path(a.out).write_text(table + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

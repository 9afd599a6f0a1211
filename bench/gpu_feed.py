"""How fast one accelerator consumes training samples per model, how busy it is, and how many
decode workers feed it.

Run on a GPU host: ``python -m bench.gpu_feed [--workers 14] [--steps 20] [--speed eager,fast]
[--out docs]``; on a CPU (or with ``--smoke``) it runs at toy sizes as a smoke test of the
measurement (no figure of it says anything about a GPU).

For each model at the paper's training batch (``PAPER_BATCH``: E2VID, HyperE2VID and EV-FlowNet
12, ETNet 6, E-RAFT 10), crop and sequence length (40 voxel grids of 5 bins, 128 x 128), for
each ``amp`` (float32, bf16) and each ``--speed`` value, with the trainer's own step
(``trainer.core.Trainer.train_step(sync=False)``), each row in a fresh process (no compiled
graph, CUDA graph or cached memory of an earlier row). Without ``--videos`` the corpus is
one copy of the WebVid-like clip per sample of the largest batch (2 windows each at the
paper's recipe) in a temporary folder, so that every model trains at its own batch (the bundled
clips give 3 samples per epoch at the paper's recipe). HyperE2VID's curriculum runs through its
16 stages during the cached run (``max_steps`` 5 x the cached run's steps, ``fraction`` 0.2),
so its recompiles, if any, show. Each row records:

* ``batch``: the batch sizes the row's steps really trained at (``/``-separated when several);
* ``graphs``, ``recompiles``: graphs dynamo compiled over the row, and how many of them after
  the row's first step (``torch._dynamo.utils.counters["stats"]["unique_graphs"]``); 0 for an
  eager network (on a CPU, ``--compile`` compiles it with inductor, so they count);
* ``cudagraph_skips``: compiled graphs inductor ran without a CUDA graph
  (``counters["inductor"]["cudagraph_skips"]``);

* ``cached``: steps on batches taken once from the server and kept on the host (the device
  alone: host -> device copy, forward, backward, optimiser step); steps/s, samples/s, the
  peak device memory (``torch.cuda.max_memory_allocated``) and the GPU busy fraction (NVML's
  utilisation, through ``pynvml`` when importable, else ``nvidia-smi`` polled, averaged over
  the timed steps; none on a CPU);
* ``launches``: one step under ``torch.profiler``: on CUDA the kernel launches (CUDA runtime
  and driver launch calls, a CUDA graph's launch counted once); on a CPU the aten operators
  dispatched (every level of the dispatcher, so a convolution counts its inner calls too);
* ``live``: steps fed by a ``v2v-serve`` on this host serving by plan with ``--workers`` worker
  processes (and ``--serve-args``, e.g. ``"--frame-cache-gb 20 --cache-dir /tmp/fc"`` for a
  frame cache, warm from the cached run on), read as ``v2v-train`` reads it
  (``trainer.data.read_path``: ``ReadAhead`` over the plan's epochs); steps/s, samples/s
  consumed and the fraction of the wall time the loop waited for a batch;
* ``workers_needed``: ``ceil(cached samples/s / (live samples/s / workers))`` when the live run
  waited for data (wait fraction > 0.05); otherwise ``<= workers``.

``--speed`` sets the trainer's top-level ``speed`` setting (eager | fast) per row; a trainer
whose configuration has no ``speed`` key refuses the option (exit 2); without it every row
runs the configuration's default. ``--models ""`` leaves the trainer rows out.

The producer section (``--producer 1,2,...``; the paper's sample on any device, toy sizes with
``--smoke``) serves copies of the WebVid-like clip alone with N workers, every output
(``bench.speed.producer``): samples/s per worker, samples per worker CPU-second as a share of
the decode bound measured in the same run, the workers' share of a core (below 1: a worker
waited for a core or for the server), their CPU outside the main thread (decoder, OpenCV, BLAS
or numba thread pools) and threads per worker; then ``TRADES`` at the largest count.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import List, Optional

import torch

from bench.speed import bare_decode, clip_path, make_corpus, producer, warm_kernel, worker_core
from harness.serve import ServeProcess
from trainer.config import default_config, merge
from trainer.core import Trainer, resolve_device
from trainer.data import make_stream, read_path
from trainer.tasks import stream_outputs

MODELS = ("e2vid", "hypere2vid", "evflow", "etnet", "eraft")
#: The paper's training batch per model (the V2V authors' configs).
PAPER_BATCH = {"e2vid": 12, "hypere2vid": 12, "evflow": 12, "etnet": 6, "eraft": 10}
#: The paper's sample: crop side (pixels), voxel grids per sample, bins.
PAPER = {"crop": 128, "sequence_length": 40, "num_bins": 5}
#: Toy sizes of the CPU smoke run (batch 2 for every model), and the models shrunk to match.
SMOKE = {"crop": 32, "sequence_length": 2, "num_bins": 5}
SMOKE_BATCH = 2
SMOKE_MODELS = {"e2vid": {"base_num_channels": 4}, "evflow": {"base_num_channels": 4},
                "hypere2vid": {"base_num_channels": 4},
                "etnet": {"d_model": 16, "nhead": 2, "encoder_layers": 1, "decoder_layers": 1, "dim_feedforward": 32},
                "eraft": {"iters": 2, "corr_levels": 2, "corr_radius": 2}}
#: Profiler event names counted as one kernel launch each on CUDA.
LAUNCH_EVENTS = ("cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx",
                 "cudaLaunchCooperativeKernel", "cudaGraphLaunch")


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class BusySampler:
    """GPU utilisation (percent, NVML's "utilization.gpu") sampled every ``period_s`` in a thread
    while the ``with`` block runs; ``mean`` is None on a CPU or when neither ``pynvml`` nor
    ``nvidia-smi`` is there."""

    def __init__(self, device: torch.device, period_s: float = 0.1):
        self.device, self.period_s, self.samples = device, period_s, []
        self._stop = threading.Event()
        self._read = self._reader() if device.type == "cuda" else None

    def _reader(self):
        index = self.device.index if self.device.index is not None else torch.cuda.current_device()
        visible = os.environ.get("CUDA_VISIBLE_DEVICES", "").split(",")
        if index < len(visible) and visible[index].strip().isdigit():  # NVML counts every GPU of the host
            index = int(visible[index])
        try:
            import pynvml  # nvidia-ml-py

            pynvml.nvmlInit()
            handle = pynvml.nvmlDeviceGetHandleByIndex(index)
            return lambda: float(pynvml.nvmlDeviceGetUtilizationRates(handle).gpu)
        except Exception:  # not installed, or no NVML library: fall back to the command line tool
            if shutil.which("nvidia-smi") is None:
                return None
            cmd = ["nvidia-smi", f"--id={index}", "--query-gpu=utilization.gpu", "--format=csv,noheader,nounits"]
            return lambda: float(subprocess.run(cmd, capture_output=True, text=True, timeout=5).stdout.split()[0])

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            try:
                self.samples.append(self._read())
            except Exception:  # a failed poll is a missing sample, not a failed bench
                pass

    def __enter__(self):
        if self._read is not None:
            self._thread = threading.Thread(target=self._run, name="gpu-busy", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        if self._read is not None:
            self._thread.join()

    @property
    def mean(self) -> Optional[float]:
        return sum(self.samples) / len(self.samples) / 100.0 if self.samples else None


def launches_per_step(trainer: Trainer, batch: dict) -> dict:
    """One ``train_step`` under ``torch.profiler``: ``{"count", "what"}``, the CUDA kernel
    launches (``LAUNCH_EVENTS``) on a CUDA device, else the aten operators dispatched."""
    from torch.profiler import ProfilerActivity, profile

    cuda = trainer.device.type == "cuda"
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=acts) as prof:
        trainer.train_step(batch, sync=False)
        _sync(trainer.device)
    events = prof.key_averages()
    if cuda:
        return {"count": sum(e.count for e in events if e.key in LAUNCH_EVENTS), "what": "CUDA kernel launches"}
    return {"count": sum(e.count for e in events if e.key.startswith("aten::")), "what": "aten ops dispatched (CPU)"}


def _trainer(task: str, amp: str, speed: Optional[str], smoke: bool, device: torch.device, out: Path,
             curriculum_steps: int = 0, compile_network: bool = False) -> Trainer:
    """The row's trainer; ``curriculum_steps``: HyperE2VID's curriculum runs through all its
    stages in that many steps (``max_steps`` 5 x that, ``fraction`` 0.2), else never ends;
    ``compile_network``: the trainer's ``compile: true``."""
    model = dict(SMOKE_MODELS[task]) if smoke else {}
    model["num_bins"] = (SMOKE if smoke else PAPER)["num_bins"]
    upd = {"model": model, "amp": amp, "max_steps": 10**9, "compile": compile_network}
    if task == "hypere2vid" and curriculum_steps > 0:
        upd.update(max_steps=5 * curriculum_steps, curriculum={"fraction": 0.2, "stages": 16})
    if speed is not None:
        upd["speed"] = speed
    return Trainer(merge(default_config(task), upd), str(out), device)


def _timed(trainer: Trainer, batches, steps: int, warmup: int, busy: bool = False) -> dict:
    """Run ``warmup`` then ``steps`` steps on ``batches`` (an iterator); time the latter."""
    dev = trainer.device
    for _ in range(warmup):
        trainer.train_step(next(batches), sync=False)
    _sync(dev)
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
    wait, samples, sizes = 0.0, 0, set()
    with BusySampler(dev if busy else torch.device("cpu")) as gpu:
        t0 = time.perf_counter()
        for _ in range(steps):
            a = time.perf_counter()
            b = next(batches)
            wait += time.perf_counter() - a
            n = trainer.train_step(b, sync=False)["samples"]
            samples += n
            sizes.add(n)
        _sync(dev)
        el = time.perf_counter() - t0
    out = {"steps_per_s": steps / el, "samples_per_s": samples / el, "data_wait_fraction": wait / el,
           "peak_mem_gib": torch.cuda.max_memory_allocated(dev) / 2**30 if dev.type == "cuda" else None,
           "batch_sizes": sorted(sizes)}
    if busy:
        out["gpu_busy"] = gpu.mean
    return out


def measure(task: str, amp: str, speed: Optional[str], endpoint: str, a, smoke: bool, device: torch.device,
            tmp: Path) -> dict:
    """One row: ``cached`` (with GPU busy), ``launches`` and ``live`` runs of ``task`` (module
    docstring), in this process (:func:`measure_fresh` runs it in a new one)."""
    from torch._dynamo.utils import counters

    trainer = _trainer(task, amp, speed, smoke, device, tmp / f"{task}_{amp}_{speed}", a.warmup + a.steps,
                       compile_network=a.compile)
    stream = make_stream(endpoint, task, timeout_s=600, outputs=stream_outputs(trainer.cfg))
    feed = read_path(stream, device)  # v2v-train's: a plan read ahead of the loop
    loader = iter(feed)
    cache = [next(loader) for _ in range(2)]

    def cycle():
        while True:
            yield from cache

    graphs0 = counters["stats"]["unique_graphs"]
    after_first = []

    def first_then(it):  # the graphs made by the row's first step
        yield next(it)
        after_first.append(counters["stats"]["unique_graphs"])
        yield from it

    cached = _timed(trainer, first_then(cycle()), a.steps, a.warmup, busy=True)
    row = {"model": task, "amp": amp, "speed": trainer.cfg.get("speed", "-"), "pid": os.getpid(),
           "workers": a.workers, "cached": cached, "launches": launches_per_step(trainer, cache[0]),
           "live": _timed(trainer, loader, a.steps, a.warmup)}
    feed.close()
    graphs = counters["stats"]["unique_graphs"]
    row["batch"] = "/".join(str(n) for n in sorted(set(cached["batch_sizes"]) | set(row["live"]["batch_sizes"])))
    row["graphs"] = graphs - graphs0
    row["recompiles"] = graphs - after_first[0]
    row["cudagraph_skips"] = counters["inductor"]["cudagraph_skips"]
    if task == "hypere2vid":
        c = trainer.cfg["curriculum"]
        row["curriculum"] = f"beta 1 -> 0 in {c['stages']} stages over {a.warmup + a.steps} steps"
    live = row["live"]
    if live["data_wait_fraction"] > 0.05:
        row["workers_needed"] = math.ceil(cached["samples_per_s"] / (live["samples_per_s"] / a.workers))
    else:
        row["workers_needed"] = f"<= {a.workers}"
    return row


def measure_fresh(task: str, amp: str, speed: Optional[str], endpoint: str, a, smoke: bool, device: torch.device,
                  tmp: Path) -> dict:
    """:func:`measure` in a fresh process (``spawn``): no compiled graph, CUDA graph, dynamo
    counter or cached device memory of an earlier row. Raises ``RuntimeError`` when the row
    fails or its process dies, with the cause chained."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(1, mp_context=mp.get_context("spawn")) as ex:
        try:
            return ex.submit(measure, task, amp, speed, endpoint, a, smoke, device, tmp).result()
        except Exception as e:  # BrokenProcessPool when the process died
            raise RuntimeError(f"row {task}/{amp}/{speed}: {type(e).__name__}: {e}") from e


#: The producer's trades beyond the decode bound (docs/speed.md: what each costs in diversity),
#: measured at the largest worker count of ``--producer``: a label and its v2v-serve arguments.
TRADES = (("crops_per_window 4", ["--crops-per-window", "4"]), ("decode_fast bidir", ["--decode-fast", "bidir"]),
          ("crops_per_window 4 + bidir", ["--crops-per-window", "4", "--decode-fast", "bidir"]))


def producer_rows(counts: List[int], samples: int, sizes: dict, tmp: Path, trades: bool = True) -> dict:
    """The producer alone at ``sizes`` on copies of the WebVid-like clip: the default recipe
    for each worker count, then (``trades``) each of ``TRADES`` at the largest count; the
    decode bound (``bench.speed.bare_decode``, samples per CPU-second) is measured before and
    after the rows and averaged; ``share_of_bound`` = samples per worker CPU-second / the bound."""
    corpus = make_corpus(tmp / "webvid", max(4, 2 * max(counts)))
    extra = ["--sequence-length", str(sizes["sequence_length"]), "--crop-size", str(sizes["crop"]),
             "--num-bins", str(sizes["num_bins"])]
    span = sizes["sequence_length"] * sizes["num_bins"] + 1  # frames per sample (one per bin, plus the first)
    # compile (or load) every numba function the workers run and write numba's cache, so that no
    # worker compiles inside a measured row (a first compile there read 2x slower per sample)
    worker_core(corpus, ("voxels", "frames", "flow"), videos=1)
    warm_kernel()
    bounds = [bare_decode(clip_path(), 2) / span]
    rows = [dict(producer(corpus, n, samples, extra), recipe="default") for n in counts]
    for label, args in (TRADES if trades else ()):
        rows.append(dict(producer(corpus, max(counts), samples, extra + args), recipe=label))
    bounds.append(bare_decode(clip_path(), 2) / span)
    bound = sum(bounds) / 2
    for r in rows:
        r["share_of_bound"] = r["per_worker_cpu_s"] / bound
    return {"decode_bound": bound, "decode_bound_runs": bounds, "sizes": sizes, "rows": rows}


def _pct(x: Optional[float]) -> str:
    return "-" if x is None else f"{x:.0%}"


def trainer_table(rows: List[dict]) -> str:
    """The per-model rows as a markdown table."""
    what = rows[0]["launches"]["what"] if rows else ""
    lines = ["| model | batch | amp | speed | cached steps/s | cached samples/s | GPU busy | peak GiB | "
             f"{what} per step | graphs | recompiles | CUDA-graph skips | live samples/s | data wait | workers | "
             "workers needed |",
             "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        c, lv = r["cached"], r["live"]
        mem = f"{c['peak_mem_gib']:.1f}" if c["peak_mem_gib"] is not None else "-"
        lines.append(f"| {r['model']} | {r['batch']} | {r['amp']} | {r['speed']} | {c['steps_per_s']:.2f} | "
                     f"{c['samples_per_s']:.1f} | {_pct(c.get('gpu_busy'))} | {mem} | {r['launches']['count']:,} | "
                     f"{r['graphs']} | {r['recompiles']} | {r['cudagraph_skips']} | "
                     f"{lv['samples_per_s']:.1f} | {_pct(lv['data_wait_fraction'])} | {r['workers']} | "
                     f"{r['workers_needed']} |")
    return "\n".join(lines)


def producer_table(p: dict) -> str:
    """The producer section as a markdown table."""
    runs = ", ".join(f"{b:.2f}" for b in p["decode_bound_runs"])
    z = p["sizes"]
    lines = [f"Sample: {z['sequence_length']} voxel grids of {z['num_bins']} bins, {z['crop']} x {z['crop']} crop, "
             "every output (voxels, frames, tracked flow), copies of the WebVid-like clip (596 x 336). Decode bound "
             f"(PyAV, Y plane, one thread, same run): {p['decode_bound']:.2f} samples/CPU-s (before / after the "
             f"rows: {runs}).", "",
             "| recipe | workers | samples/s | per worker (wall) | per worker CPU-s | share of decode bound | core share | "
             "CPU outside main thread | threads per worker | relay CPU-ms per sample |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in p["rows"]:
        lines.append(f"| {r['recipe']} | {r['workers']} | {r['samples_per_s']:.2f} | {r['per_worker']:.2f} | "
                     f"{r['per_worker_cpu_s']:.2f} | {r['share_of_bound']:.0%} | {r['core_share']:.0%} | "
                     f"{r['other_threads']:.1%} | {r['threads']} | {1000 * r['server_cpu_s']:.1f} |")
    return "\n".join(lines)


def markdown(res: dict) -> str:
    """``docs/gpu_feed.md``: device, torch version, command, the tables."""
    s = res["sizes"]
    head = ["# Feeding a GPU: trainer steps per model and the producer (`bench/gpu_feed.py`)", "",
            f"Command: `{res['command']}`", "", f"Device: {res['device']}; torch {res['torch']}; {res['cpus']} CPUs.", ""]
    if res["rows"]:
        head += [f"Trainer sample: {s['sequence_length']} voxel grids of {s['num_bins']} bins, {s['crop']} x "
                 f"{s['crop']} crop; corpus: {res.get('videos', '-')}; batch: the sizes each row's steps trained "
                 "at; each row in a fresh process. graphs: compiled by dynamo over the row; recompiles: graphs "
                 "made after the row's first step; CUDA-graph skips: inductor's cudagraph_skips."
                 + (" Every row's network compiled (`--compile`: the trainer's compile: true)." if res.get("compile")
                    else ""), ""]
        hyper = [r["curriculum"] for r in res["rows"] if r.get("curriculum")]
        if hyper:
            head += [f"HyperE2VID's curriculum: {hyper[0]} (the cached run).", ""]
    if res["smoke"] and res["rows"]:
        head += ["**No GPU here: the GPU table (the paper's sizes on a CUDA device) has not been produced.** "
                 "What follows is the CPU smoke run at toy sizes; it checks that the measurement runs; "
                 "its rates say nothing about an accelerator and no GPU figure is estimated from it. On a CPU the "
                 "launch column counts aten operators dispatched per step, not CUDA kernel launches. The producer "
                 "rows are this machine's own figures.", ""]
    parts = head + (["## Trainer", "", trainer_table(res["rows"])] if res["rows"] else [])
    if res.get("producer"):
        parts += ["", "## Producer alone", "", producer_table(res["producer"])]
    return "\n".join(parts) + "\n"


def _speeds(values: str) -> List[Optional[str]]:
    """``--speed`` values, checked against this trainer's configuration (None: its default)."""
    if not values:
        return [None]
    if "speed" not in default_config("e2vid"):
        raise SystemExit("--speed: this trainer's configuration has no 'speed' setting (eager only); leave it out")
    return values.split(",")


def _args(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="toy sizes (always on a CPU)")
    ap.add_argument("--models", default=",".join(MODELS))
    ap.add_argument("--amp", default="fp32,bf16")
    ap.add_argument("--speed", default="", help="trainer speed settings to compare, e.g. eager,fast "
                                                "(default: the configuration's)")
    ap.add_argument("--workers", type=int, default=8, help="v2v-serve worker processes of the live runs")
    ap.add_argument("--serve-args", default="", help="more v2v-serve arguments of the live runs' server, e.g. "
                                                     "'--frame-cache-gb 20 --cache-dir /tmp/fc'")
    ap.add_argument("--producer", default="", help="worker counts of the producer-alone rows, e.g. 1,2,4,8,14 "
                                                   "(empty: none)")
    ap.add_argument("--no-trades", action="store_true", help="producer rows of the default recipe only")
    ap.add_argument("--producer-samples", type=int, default=48, help="measured samples per producer row")
    ap.add_argument("--steps", type=int, default=20, help="timed steps per run")
    ap.add_argument("--warmup", type=int, default=3, help="untimed steps before each run")
    ap.add_argument("--videos", help="corpus folder (default: copies of the WebVid-like clip in a temporary folder, "
                                     "enough windows for the largest batch)")
    ap.add_argument("--compile", action="store_true",
                    help="the trainer's compile: true on every row. On a CPU inductor then compiles the network, "
                         "so the graphs and recompiles columns count real graphs (an eager network makes none); "
                         "speed: fast on CUDA compiles whatever this says")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--out", help="write gpu_feed.json and gpu_feed.md to this folder")
    return ap.parse_args(argv)


def main(argv: Optional[List[str]] = None) -> int:
    a = _args(argv)
    device = resolve_device(a.device)
    smoke = a.smoke or device.type != "cuda"
    sizes = SMOKE if smoke else PAPER
    speeds = _speeds(a.speed)
    res = {"command": "python -m bench.gpu_feed " + shlex.join(sys.argv[1:] if argv is None else argv),
           "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu (smoke: toy sizes)",
           "torch": torch.__version__, "cpus": os.cpu_count(), "smoke": smoke, "sizes": sizes, "compile": a.compile,
           "rows": []}
    models = [m for m in a.models.split(",") if m]
    with tempfile.TemporaryDirectory(prefix="v2v-gpu-feed-") as tmp:
        batches = sorted({SMOKE_BATCH if smoke else PAPER_BATCH[m] for m in models})
        # without --videos: a copy of the WebVid-like clip per sample of the largest batch (2
        # windows each at the paper's recipe: two full batches per epoch)
        videos, copies = a.videos, max(batches, default=0)
        if videos is None and models:
            videos = str(make_corpus(Path(tmp) / "corpus", copies))
        res["videos"] = a.videos or f"{copies} copies of {clip_path().name}"
        for batch in batches:
            serve = ["--videos", videos, "--shot-cuts", "off", "--workers", str(a.workers), "--batch-size", str(batch),
                     "--sequence-length", str(sizes["sequence_length"]), "--crop-size", str(sizes["crop"]),
                     "--num-bins", str(sizes["num_bins"]), *shlex.split(a.serve_args)]
            with ServeProcess(serve, ready_timeout_s=300) as srv:
                for task in [m for m in models if (SMOKE_BATCH if smoke else PAPER_BATCH[m]) == batch]:
                    for amp in a.amp.split(","):
                        for speed in speeds:
                            res["rows"].append(measure_fresh(task, amp, speed, srv.endpoint, a, smoke, device,
                                                             Path(tmp)))
                            print(json.dumps(res["rows"][-1]), flush=True)
        if a.producer:
            res["producer"] = producer_rows([int(n) for n in a.producer.split(",")], a.producer_samples,
                                            SMOKE if a.smoke else PAPER, Path(tmp), trades=not a.no_trades)
    text = markdown(res)
    print(text)
    if a.out:
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "gpu_feed.json").write_text(json.dumps(res, indent=2))
        (out / "gpu_feed.md").write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""How fast one accelerator consumes training samples per model, and how many decode workers
feed it.

Run on a GPU host: ``python -m bench.gpu_feed [--workers 8] [--steps 30] [--out docs/gpu_feed.md]``;
on a CPU (or with ``--smoke``) it runs at toy sizes as a smoke test of the measurement.

For each model (e2vid, hypere2vid, etnet, evflow) at the paper's batch size, crop and
sequence length (12 samples of 40 voxel grids of 5 bins, 128 x 128) and for float32 and bf16
(``amp``), with the trainer's own step (``trainer.core.Trainer.train_step(sync=False)``):

* ``cached``: steps on batches taken once from the server and kept on the host (the device
  alone: host -> device copy, forward, backward, optimiser step); steps/s, samples/s and the
  peak device memory (``torch.cuda.max_memory_allocated``; none on a CPU);
* ``live``: steps fed by a ``v2v-serve`` on this host with ``--workers`` worker processes
  (``trainer.data.make_loader`` over ``V2VStreamDataset``, compact flow expanded on the
  device); steps/s, samples/s consumed, and the fraction of the wall time the loop waited for
  a batch;
* ``workers_needed``: the worker processes that would feed the device at its ``cached``
  rate, ``ceil(cached samples/s / (live samples/s / workers))``, when the live run waited for
  data (wait fraction > 0.05); otherwise the live workers already keep up and the figure is
  ``<= workers``.

Each run warms up (``--warmup`` steps, not timed; compiled kernels and cuDNN's choices are
made then). The device is synchronised at the end of each timed run only.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import List, Optional

import torch

from harness.serve import ServeProcess
from trainer.config import default_config, merge
from trainer.core import Trainer, resolve_device
from trainer.data import make_loader, make_stream
from trainer.tasks import stream_outputs

MODELS = ("e2vid", "hypere2vid", "etnet", "evflow")
#: The paper's training batch: batch size, crop side (pixels), voxel grids per sample, bins.
PAPER = {"batch": 12, "crop": 128, "sequence_length": 40, "num_bins": 5}
#: Toy sizes of the CPU smoke run, and the models shrunk to match.
SMOKE = {"batch": 2, "crop": 32, "sequence_length": 2, "num_bins": 5}
SMOKE_MODELS = {"e2vid": {"base_num_channels": 4}, "evflow": {"base_num_channels": 4},
                "hypere2vid": {"base_num_channels": 4},
                "etnet": {"d_model": 16, "nhead": 2, "encoder_layers": 1, "decoder_layers": 1, "dim_feedforward": 32}}


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _trainer(task: str, amp: str, sizes: dict, smoke: bool, device: torch.device, out: Path) -> Trainer:
    model = dict(SMOKE_MODELS[task]) if smoke else {}
    model["num_bins"] = sizes["num_bins"]
    cfg = merge(default_config(task), {"model": model, "amp": amp, "max_steps": 10**9})
    return Trainer(cfg, str(out), device)


def _timed(trainer: Trainer, batches, steps: int, warmup: int) -> dict:
    """Run ``warmup`` then ``steps`` steps on ``batches`` (an iterator); time the latter."""
    dev = trainer.device
    for _ in range(warmup):
        trainer.train_step(next(batches), sync=False)
    _sync(dev)
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
    wait, samples, t0 = 0.0, 0, time.perf_counter()
    for _ in range(steps):
        a = time.perf_counter()
        b = next(batches)
        wait += time.perf_counter() - a
        samples += trainer.train_step(b, sync=False)["samples"]
    _sync(dev)
    el = time.perf_counter() - t0
    return {"steps_per_s": steps / el, "samples_per_s": samples / el, "data_wait_fraction": wait / el,
            "peak_mem_gib": torch.cuda.max_memory_allocated(dev) / 2**30 if dev.type == "cuda" else None}


def measure(task: str, amp: str, endpoint: str, sizes: dict, steps: int, warmup: int, workers: int, smoke: bool,
            device: torch.device, tmp: Path) -> dict:
    """One row: ``cached`` and ``live`` runs of ``task`` with ``amp`` (module docstring)."""
    trainer = _trainer(task, amp, sizes, smoke, device, tmp / f"{task}_{amp}")
    stream = make_stream(endpoint, task, credits=4, timeout_s=600, outputs=stream_outputs(trainer.cfg))
    loader = iter(make_loader(stream, device))
    cache = [next(loader) for _ in range(2)]

    def cycle():
        while True:
            yield from cache

    row = {"model": task, "amp": amp, "workers": workers,
           "cached": _timed(trainer, cycle(), steps, warmup), "live": _timed(trainer, loader, steps, warmup)}
    stream.close()
    live, cached = row["live"], row["cached"]
    if live["data_wait_fraction"] > 0.05:
        row["workers_needed"] = math.ceil(cached["samples_per_s"] / (live["samples_per_s"] / workers))
    else:
        row["workers_needed"] = f"<= {workers}"
    return row


def markdown(rows: List[dict], device: str, sizes: dict) -> str:
    head = (f"Device: {device}; batch {sizes['batch']} x {sizes['sequence_length']} voxel grids of "
            f"{sizes['num_bins']} bins, {sizes['crop']} x {sizes['crop']} crop.\n\n"
            "| model | amp | cached steps/s | cached samples/s | peak GiB | live steps/s | live samples/s | "
            "data wait | workers | workers needed |\n|---|---|---|---|---|---|---|---|---|---|")
    lines = [head]
    for r in rows:
        c, lv = r["cached"], r["live"]
        mem = f"{c['peak_mem_gib']:.1f}" if c["peak_mem_gib"] is not None else "-"
        lines.append(f"| {r['model']} | {r['amp']} | {c['steps_per_s']:.2f} | {c['samples_per_s']:.1f} | {mem} | "
                     f"{lv['steps_per_s']:.2f} | {lv['samples_per_s']:.1f} | {lv['data_wait_fraction']:.0%} | "
                     f"{r['workers']} | {r['workers_needed']} |")
    return "\n".join(lines)


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="toy sizes (always on a CPU)")
    ap.add_argument("--models", default=",".join(MODELS))
    ap.add_argument("--amp", default="fp32,bf16")
    ap.add_argument("--workers", type=int, default=8, help="v2v-serve worker processes of the live runs")
    ap.add_argument("--steps", type=int, default=20, help="timed steps per run")
    ap.add_argument("--warmup", type=int, default=3, help="untimed steps before each run")
    ap.add_argument("--videos", default=str(Path(__file__).parents[1] / "v2v_server" / "sample_videos"))
    ap.add_argument("--device", default="auto")
    ap.add_argument("--out", help="write gpu_feed.json and gpu_feed.md to this folder")
    a = ap.parse_args(argv)
    device = resolve_device(a.device)
    smoke = a.smoke or device.type != "cuda"
    sizes = SMOKE if smoke else PAPER
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu (smoke: toy sizes)"
    serve = ["--videos", a.videos, "--workers", str(a.workers), "--batch-size", str(sizes["batch"]),
             "--sequence-length", str(sizes["sequence_length"]), "--crop-size", str(sizes["crop"]),
             "--num-bins", str(sizes["num_bins"])]
    rows = []
    with tempfile.TemporaryDirectory(prefix="v2v-gpu-feed-") as tmp, ServeProcess(serve, ready_timeout_s=300) as srv:
        for task in a.models.split(","):
            for amp in a.amp.split(","):
                rows.append(measure(task, amp, srv.endpoint, sizes, a.steps, a.warmup, a.workers, smoke, device,
                                    Path(tmp)))
                print(json.dumps(rows[-1]), flush=True)
    text = markdown(rows, name, sizes)
    print(text)
    if a.out:
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "gpu_feed.json").write_text(json.dumps({"device": name, "sizes": sizes, "rows": rows}, indent=2))
        (out / "gpu_feed.md").write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

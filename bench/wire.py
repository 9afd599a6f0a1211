"""What a sample costs on the wire: ``python -m bench.wire``.

Two parts, both on real samples (the bundled clips, the default recipe: L = 40, 5 bins,
128 x 128 crops, flow ``tracked``):

1. **Bytes and codec speed** (in this process, one core): bytes per sample of each output as
   the wire carries it, for the baseline (dense float16 flow, uncompressed: the wire before the
   compact flow) and for each compression setting (``v2v_wire.codecs``: none, lz4, zstd) with
   the compact flow (``flow_grid``); each codec's compress and decompress speed (GB/s of
   uncompressed bytes, one core, best of several rounds) per output; and what the client's
   expansion of ``flow_grid`` (``v2v_client.flowgrid``) costs per sample against the float16 ->
   float32 conversion of the dense flow it replaces.
2. **End to end over tcp://127.0.0.1** (``--seconds`` per setting, after a warm-up): a
   ``v2v-serve`` child process (``--workers``) and, in this process, the plan's epochs in turn
   through ``V2VStreamDataset(compression=...)``; samples/s (padding rows not counted), wire
   bytes per sample (the server's ``v2v_sent_bytes_total``), CPU seconds of the server's main
   process (``/proc/<pid>/stat``: it sends the rows; the workers are other processes) and of this client process (all its threads) per GB sent and per sample.
   On a small shared machine the workers, not the wire, set the sample rate; the CPU columns
   are what matters there.

Prints markdown tables (docs/wire.md holds the reference run) and, with ``--json``, writes
the numbers.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CLIPS = ROOT / "v2v_server" / "sample_videos"
CODECS = ("none", "lz4", "zstd")


def real_samples(epochs: int = 2):
    """(compact wire arrays, baseline wire arrays) of every sample of the bundled clips."""
    from v2v_server.samples.recipe import SampleRecipe
    from v2v_server.flow.estimate import FlowEstimator
    from v2v_server.samples.make import video_samples
    from v2v_server.sources.local import LocalSource
    from v2v_server.service.worker import wire_arrays
    from v2v_wire.outputs import DEFAULT_OUTPUTS

    cfg = SampleRecipe(shot_cuts="off")
    flow = FlowEstimator(cfg.flow_preset)
    compact, dense = [], []
    for epoch in range(epochs):
        for clip in sorted(p.name for p in CLIPS.glob("*.mp4")):
            for _, a, _ in video_samples(cfg, LocalSource(CLIPS), clip, epoch, DEFAULT_OUTPUTS, (), flow, flow_grid=True):
                compact.append(wire_arrays(cfg, a))
            for _, a, _ in video_samples(cfg, LocalSource(CLIPS), clip, epoch, ("flow",), (), flow):
                dense.append(wire_arrays(cfg, a)["flow"])
    base = [dict(c, flow=d) for c, d in zip(compact, dense)]
    for b in base:
        b.pop("flow_grid")
    return cfg, compact, base


def _best(fn, min_s: float = 0.3, rounds: int = 3) -> float:
    """Best seconds per call of ``fn`` over ``rounds`` rounds of at least ``min_s`` each."""
    best = float("inf")
    for _ in range(rounds):
        n, t0 = 0, time.perf_counter()
        while True:
            fn()
            n += 1
            dt = time.perf_counter() - t0
            if dt >= min_s:
                break
        best = min(best, dt / n)
    return best


def codec_table(compact, base) -> dict:
    """Bytes per sample per output and setting; codec speeds per output."""
    from v2v_wire import codecs

    names = list(compact[0])
    rows = {"baseline": {k: float(np.mean([s[k].nbytes for s in base])) for k in base[0]}}
    speed = {}
    for codec in CODECS:
        if codec == "none":
            rows[codec] = {k: float(np.mean([s[k].nbytes for s in compact])) for k in names}
            continue
        comp, dec = codecs._codec(codec)
        rows[codec], speed[codec] = {}, {}
        for k in names:
            raw = [memoryview(np.ascontiguousarray(s[k])).cast("B") for s in compact]
            packed = [comp(r) for r in raw]
            nb = sum(len(r) for r in raw)
            rows[codec][k] = float(np.mean([len(p) for p in packed]))
            tc = _best(lambda: [comp(r) for r in raw])
            td = _best(lambda: [dec(p, len(r)) for p, r in zip(packed, raw)])
            speed[codec][k] = {"ratio": nb / sum(len(p) for p in packed), "compress_gbs": nb / tc / 1e9,
                               "decompress_gbs": nb / td / 1e9}
    return {"bytes": rows, "speed": speed}


def expansion_cost(cfg, compact, base) -> dict:
    """Client CPU ms per sample: flow_grid -> float32 flow (v2v_client.flowgrid: the numba loop
    on the CPU; beside it the torch ops it uses on other devices, run on the CPU) against the
    float16 -> float32 conversion of the baseline's dense flow, over 8-sample batches."""
    import torch

    from v2v_client.flowgrid import _expand_torch, expand_flow_grid

    torch.set_num_threads(1)
    g = torch.from_numpy(np.stack([s["flow_grid"] for s in (compact * 8)[:8]]))
    d = np.stack([s["flow"] for s in (base * 8)[:8]])
    size = (cfg.crop_size, cfg.crop_size)
    return {"expand_ms": _best(lambda: expand_flow_grid(g, size)) / 8 * 1e3,
            "torch_cpu_ms": _best(lambda: _expand_torch(g, *size)) / 8 * 1e3,
            "f16_to_f32_ms": _best(lambda: torch.from_numpy(d.astype(np.float32))) / 8 * 1e3}


def _proc_cpu(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` (its threads, not its children)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _sent_bytes(port: int) -> float:
    text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
    m = re.search(r"^v2v_sent_bytes_total (\S+)$", text, re.M)
    return float(m.group(1)) if m else 0.0


def end_to_end(codec: str, workers: int, seconds: float, warmup_s: float) -> dict:
    """One server, one client asking for ``codec``, over tcp://127.0.0.1."""
    from harness.serve import ServeProcess, free_port
    from v2v_client import PlanEpochs, V2VStreamDataset

    port = free_port()
    with ServeProcess(["--videos", str(CLIPS), "--shot-cuts", "off", "--workers", str(workers), "--metrics-port", str(port),
                       "--batch-size", "8"]) as srv:
        it = iter(PlanEpochs(V2VStreamDataset(srv.endpoint, compression=codec, timeout_s=120)))
        try:
            t_end = time.monotonic() + warmup_s
            while time.monotonic() < t_end:
                next(it)
            b0, c0, p0, t0 = _sent_bytes(port), time.process_time(), _proc_cpu(srv.proc.pid), time.monotonic()
            n = 0
            while time.monotonic() - t0 < seconds:
                n += int((~next(it)["padding"]).sum())
            dt = time.monotonic() - t0
            sent = _sent_bytes(port) - b0
            client, server = time.process_time() - c0, _proc_cpu(srv.proc.pid) - p0
        finally:
            it.close()
    gb = sent / 1e9
    return {"samples": n, "samples_per_s": n / dt, "wire_bytes_per_sample": sent / max(n, 1),
            "server_main_cpu_s_per_gb": server / gb if gb else float("nan"),
            "client_cpu_s_per_gb": client / gb if gb else float("nan"),
            "server_main_cpu_ms_per_sample": server / max(n, 1) * 1e3,
            "client_cpu_ms_per_sample": client / max(n, 1) * 1e3}


def _mb(x: float) -> str:
    return f"{x / 1e6:.3f}"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=20.0, help="measured seconds per setting, end to end")
    p.add_argument("--warmup", type=float, default=8.0, help="seconds read before measuring, end to end")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--skip-e2e", action="store_true", help="only the offline part")
    p.add_argument("--json", type=Path, help="write the numbers here")
    args = p.parse_args(argv)

    cfg, compact, base = real_samples()
    out = {"samples": len(compact), **codec_table(compact, base), "expansion": expansion_cost(cfg, compact, base)}
    rows = out["bytes"]
    outs = [("voxels", "voxels"), ("frames", "frames"), ("flow", "flow_grid")]
    print(f"## Bytes per sample on the wire ({len(compact)} real samples, default recipe)\n")
    print("| setting | voxels MB | frames MB | flow MB | total MB | vs baseline |")
    print("|---|---:|---:|---:|---:|---:|")
    total_base = sum(rows["baseline"].values())
    for name in ("baseline",) + CODECS:
        r = rows[name]
        vals = [r.get(a if name != "baseline" else o, 0.0) for o, a in outs]
        label = "baseline: dense float16 flow, none" if name == "baseline" else f"compact flow, {name}"
        print(f"| {label} | " + " | ".join(_mb(v) for v in vals) + f" | {_mb(sum(vals))} | "
              f"{total_base / sum(vals):.1f}x smaller |")
    print("\n## Codecs, one core (GB/s of uncompressed bytes)\n")
    print("| codec | array | ratio | compress GB/s | decompress GB/s |")
    print("|---|---|---:|---:|---:|")
    for codec, per in out["speed"].items():
        for k, v in per.items():
            print(f"| {codec} | {k} | {v['ratio']:.2f} | {v['compress_gbs']:.2f} | {v['decompress_gbs']:.2f} |")
    e = out["expansion"]
    print(f"\nclient flow, per sample (one thread): flow_grid -> float32 flow {e['expand_ms']:.2f} ms; "
          f"baseline dense float16 -> float32 {e['f16_to_f32_ms']:.2f} ms "
          f"({e['expand_ms'] / e['f16_to_f32_ms']:.2f}x); the same expansion in torch ops on the CPU "
          f"{e['torch_cpu_ms']:.2f} ms")
    if not args.skip_e2e:
        out["e2e"] = {c: end_to_end(c, args.workers, args.seconds, args.warmup) for c in CODECS}
        print(f"\n## End to end over tcp://127.0.0.1 ({args.workers} workers, {args.seconds:.0f} s per setting)\n")
        print("| compression | samples/s | wire MB/sample | server main CPU-s/GB | client CPU-s/GB | "
              "server main CPU ms/sample | client CPU ms/sample |")
        print("|---|---:|---:|---:|---:|---:|---:|")
        for c, r in out["e2e"].items():
            print(f"| {c} | {r['samples_per_s']:.2f} | {_mb(r['wire_bytes_per_sample'])} | "
                  f"{r['server_main_cpu_s_per_gb']:.2f} | {r['client_cpu_s_per_gb']:.2f} | "
                  f"{r['server_main_cpu_ms_per_sample']:.2f} | {r['client_cpu_ms_per_sample']:.2f} |")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

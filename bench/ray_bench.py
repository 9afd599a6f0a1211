"""V2V through Ray Data against v2v-serve on this machine, same corpus, layout and worker count.

Run: ``python -m bench.ray_bench [--workers 2] [--copies 2] [--epochs 1] [--faults] [--out FILE]``
(needs the ``ray`` extra).

Rows (samples/s; ratio against v2v-serve measured in the same run):

* ``in-process``: ``samples.video_samples`` over the corpus in one process, the work itself;
  its time per sample is the compute both engines must spend;
* ``v2v-serve``: ``--workers N``, epochs ``0 .. --epochs - 1`` read by plan through
  ``V2VStreamDataset`` (server start excluded; padding rows not counted);
* ``ray data``: ``v2v_dataset(...).iter_batches()`` with an actor pool of N (``ray.init``
  excluded, actor start included: that is what an epoch costs);
* overhead per sample: worker-seconds per sample (wall x N / samples) minus the in-process
  time per sample.

``--decode`` adds the descriptor choice: decoding every window of a video in one pass (what
both engines do) against a seek per window (keyframe seek, then decoding up to the window).
``--faults`` kills one V2V actor in the middle of a video and counts the rows by id.
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import List, Optional

from harness.faults import good_corpus
from v2v_client import V2VStreamDataset
from v2v_server.ops.config import ServeConfig
from harness.serve import ServeProcess
from v2v_server.flow.estimate import FlowEstimator
from v2v_server.samples.make import video_samples
from v2v_server.sources.local import LocalSource
from v2v_server.sources.folder_scan import find_videos

LAYOUT = dict(sequence_length=8, num_bins=5, crop_size=128, max_samples_per_video=10, seed=1)


def layout_args(cfg: ServeConfig) -> List[str]:
    return ["--sequence-length", str(cfg.sequence_length), "--num-bins", str(cfg.num_bins), "--crop-size",
            str(cfg.crop_size), "--max-samples-per-video", str(cfg.max_samples_per_video), "--seed", str(cfg.seed)]


def in_process(cfg: ServeConfig, corpus: Path) -> dict:
    import cv2

    cv2.setNumThreads(1)
    flow = FlowEstimator(cfg.flow_preset)
    t0, n = time.perf_counter(), 0
    for rel in find_videos(corpus, cfg.video_extensions):
        for _ in video_samples(cfg, LocalSource(corpus), rel.as_posix(), 0, ("voxels", "frames", "flow"), (), flow):
            n += 1
    return {"samples": n, "wall_s": time.perf_counter() - t0}


def serve(cfg: ServeConfig, corpus: Path, workers: int, epochs: int) -> dict:
    """Epochs ``0 .. epochs - 1`` of ``v2v-serve --workers N`` read by plan: samples and wall seconds."""
    args = ["--videos", str(corpus), "--shot-cuts", "off", "--workers", str(workers), "--batch-size", "4",
            *layout_args(cfg)]
    with ServeProcess(args) as srv:
        ds = V2VStreamDataset(srv.endpoint, timeout_s=300, raw=True)
        t0, n = time.perf_counter(), 0
        for epoch in range(epochs):
            ds.set_epoch(epoch)
            for b in ds:
                n += len(b["padding"]) - int(b["padding"].sum())
        wall = time.perf_counter() - t0
    return {"samples": n, "wall_s": wall}


def ray_data(cfg: ServeConfig, corpus: Path, workers: int, epochs: int) -> dict:
    from v2v_server.ray_data import scan_corpus_windows, v2v_dataset

    t0 = time.perf_counter()
    rc = scan_corpus_windows(corpus, cfg)
    scan = time.perf_counter() - t0
    ds = v2v_dataset(rc, cfg, epoch=list(range(epochs)), concurrency=workers)
    n = 0
    for b in ds.iter_batches(batch_size=4, batch_format="numpy"):
        n += len(b["sample_id"])
    return {"samples": n, "wall_s": time.perf_counter() - t0, "scan_s": scan}


def decode_choice(cfg: ServeConfig, corpus: Path) -> dict:
    """Decode seconds for all windows: one sequential pass per video vs one seek per window."""
    import av

    from v2v_server.frames.decode import decode_luma, open_video

    span, one_pass, seeks, windows = cfg.recipe.frames_per_sample, 0.0, 0.0, 0
    for rel in find_videos(corpus, cfg.video_extensions):
        path = corpus / rel
        t0 = time.perf_counter()
        c, s, _ = open_video(path)
        n = 0
        for _ in decode_luma(c, s):
            n += 1
            if n >= span * cfg.max_samples_per_video:
                break
        one_pass += time.perf_counter() - t0
        k_max = min(cfg.max_samples_per_video, n // span)
        windows += k_max
        for k in range(k_max):
            t0 = time.perf_counter()
            with av.open(str(path)) as c:
                st = c.streams.video[0]
                rate = st.average_rate or st.guessed_rate
                target = int(round(k * span / float(rate) / float(st.time_base)))  # pts of frame k*span
                c.seek(target, stream=st, backward=True, any_frame=False)
                got = 0
                for f in c.decode(st):
                    if f.pts is not None and f.pts < target:
                        continue
                    f.planes[0]
                    got += 1
                    if got >= span:
                        break
            seeks += time.perf_counter() - t0
    return {"windows": windows, "one_pass_s": one_pass, "seek_per_window_s": seeks}


def faults(cfg: ServeConfig, corpus: Path, workers: int) -> dict:
    """Kill (os._exit) the V2V actor once, after the 2nd row of the first video it starts."""
    from v2v_server.ray_data import SampleMaker, scan_corpus_windows, v2v_dataset

    marker = Path(tempfile.mkdtemp(prefix="v2v-raykill-")) / "killed"

    class KillOnce(SampleMaker):
        def video_rows(self, video, epoch, entries):
            for i, row in enumerate(super().video_rows(video, epoch, entries)):
                yield row
                if i == 1 and not marker.exists():
                    marker.write_text(video)
                    os._exit(1)

    rc = scan_corpus_windows(corpus, cfg)
    t0 = time.perf_counter()
    rows = v2v_dataset(rc, cfg, outputs=("voxels",), concurrency=workers, maker=KillOnce).take_all()
    cnt = collections.Counter(r["sample_id"] for r in rows if not r["padding"])
    want = {f"{v}#{k}" for v, n in rc.windows.items() for k in range(n)}
    return {"expected": len(want), "rows": len(rows), "lost": len(want - set(cnt)),
            "duplicated": sum(v - 1 for v in cnt.values()), "killed": marker.read_text() if marker.exists() else None,
            "wall_s": time.perf_counter() - t0}


def _descendants(pid: int) -> List[int]:
    out, stack = [], [pid]
    while stack:
        p = stack.pop()
        try:
            kids = [int(k) for t in os.listdir(f"/proc/{p}/task")
                    for k in Path(f"/proc/{p}/task/{t}/children").read_text().split()]
        except OSError:
            continue
        out += kids
        stack += kids
    return out


def rank_fault(corpus: Path, timeout_s: float = 500.0) -> dict:
    """``v2v-train --engine ray`` on 2 ranks, ``--max-failures 1``; SIGKILL one rank's process
    after the first checkpoint; report what the driver did and whether every sample was trained once."""
    import signal
    import subprocess

    import torch

    tmp = Path(tempfile.mkdtemp(prefix="v2v-rankfault-"))
    (tmp / "serve.yaml").write_text("sequence_length: 4\nnum_bins: 3\ncrop_size: 32\nmax_samples_per_video: 4\nshot_cuts: \"off\"\n")
    out = tmp / "run"
    cmd = [sys.executable, "-m", "trainer.train", "--engine", "ray", "--videos", str(corpus), "--serve-config",
           str(tmp / "serve.yaml"), "--task", "evflow", "--out", str(out), "--device", "cpu", "--no-progress",
           "--num-workers", "2", "--cpus-per-worker", "0.5", "--batch-size", "1", "--max-failures", "1",
           "--set", "model.num_bins=3", "--set", "model.base_num_channels=4", "--set", "log.checkpoint_every=2",
           "--set", "log.image_every=0"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    killed, t_kill = None, None
    try:
        while proc.poll() is None and time.perf_counter() - t0 < timeout_s:
            if killed is None and (out / "checkpoint_0000002.pt").exists():
                for pid in _descendants(proc.pid):
                    try:
                        if b"RayTrainWorker" in Path(f"/proc/{pid}/cmdline").read_bytes():
                            os.kill(pid, signal.SIGKILL)
                            killed, t_kill = pid, time.perf_counter()
                            break
                    except OSError:
                        continue
            time.sleep(0.2)
    finally:
        if proc.poll() is None:
            proc.kill()
    rc = proc.wait()
    log = (out / "train.log").read_text() if (out / "train.log").exists() else ""
    ck = torch.load(out / "checkpoint_last.pt", weights_only=False) if (out / "checkpoint_last.pt").exists() else {}
    summary = json.loads((out / "summary.json").read_text()) if (out / "summary.json").exists() else {}
    import re

    restarts = re.findall(r"Ray Train run failed \((.*?)\); restarting", log, flags=re.S)
    return {"exit": rc, "killed_pid": killed, "restarts": len(restarts),
            "restart_reason": " ".join(restarts[0].split())[:160] if restarts else None,
            "final_step": ck.get("step"), "state": (ck.get("stream_state") or {}).get("epochs_done"),
            "samples_after_restart": summary.get("samples"), "steps_after_restart": summary.get("steps"),
            "wall_s": time.perf_counter() - t0, "kill_to_end_s": (time.perf_counter() - t_kill) if t_kill else None}


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--copies", type=int, default=2, help="copies of each bundled clip in the corpus")
    p.add_argument("--epochs", type=int, default=1)
    p.add_argument("--decode", action="store_true", help="also time a seek per window against one pass")
    p.add_argument("--faults", action="store_true", help="also kill a V2V actor mid-video")
    p.add_argument("--rank-fault", action="store_true", help="also kill a Ray Train rank mid-epoch")
    p.add_argument("--out", help="write the table (markdown) here too")
    a = p.parse_args(argv)
    import ray

    cfg = ServeConfig(shot_cuts="off", **LAYOUT)
    corpus = good_corpus(Path(tempfile.mkdtemp(prefix="v2v-raybench-")), a.copies)
    base = in_process(cfg, corpus)
    per = base["wall_s"] / base["samples"]
    z = serve(cfg, corpus, a.workers, a.epochs)
    t0 = time.perf_counter()
    ray.init(num_cpus=a.workers, include_dashboard=False, log_to_driver=False)
    ray.data.DataContext.get_current().enable_progress_bars = False
    init_s = time.perf_counter() - t0
    r = ray_data(cfg, corpus, a.workers, a.epochs)
    r2 = ray_data(cfg, corpus, a.workers, a.epochs)  # second epoch-run: the cluster is warm
    lines = [f"corpus: {len(find_videos(corpus, cfg.video_extensions))} clips, layout {LAYOUT}, "
             f"{a.workers} worker(s), {os.cpu_count()} CPU(s), load {os.getloadavg()[0]:.1f}",
             "", "| engine | samples | wall s | samples/s | vs v2v-serve | overhead s/sample (worker-s) |",
             "|---|---|---|---|---|---|"]
    zs = z["samples"] / z["wall_s"]
    for name, m, w in (("in-process (1 proc)", {**base, "samples": base["samples"] * a.epochs,
                                                 "wall_s": base["wall_s"] * a.epochs}, 1),
                       ("v2v-serve", z, a.workers), ("ray data (cold actors)", r, a.workers),
                       ("ray data (2nd run)", r2, a.workers)):
        sps = m["samples"] / m["wall_s"]
        over = m["wall_s"] * w / m["samples"] - per
        lines.append(f"| {name} | {m['samples']} | {m['wall_s']:.1f} | {sps:.2f} | {sps / zs:.2f} | {over:+.3f} |")
    lines.append(f"\nray.init: {init_s:.1f} s; corpus scan (packet count): {r['scan_s'] * 1000:.0f} ms; "
                 f"in-process compute {per:.3f} s/sample")
    out = {"in_process": base, "serve": z, "ray": r, "ray_warm": r2, "ray_init_s": init_s}
    if a.decode:
        d = decode_choice(cfg, corpus)
        out["decode"] = d
        lines.append(f"decode of {d['windows']} windows: one pass per video {d['one_pass_s']:.2f} s, a seek per "
                     f"window {d['seek_per_window_s']:.2f} s ({d['seek_per_window_s'] / d['one_pass_s']:.2f}x)")
    if a.faults:
        f = faults(cfg, corpus, a.workers)
        out["faults"] = f
        lines.append(f"V2V actor killed mid-video ({f['killed']}): {f['rows']} rows for {f['expected']} ids, "
                     f"lost {f['lost']}, duplicated {f['duplicated']}, {f['wall_s']:.1f} s")
    ray.shutdown()
    if a.rank_fault:
        f = rank_fault(corpus)
        out["rank_fault"] = f
        lines.append(f"Ray Train rank SIGKILLed after checkpoint 2: exit {f['exit']}, {f['restarts']} restart(s) from "
                     f"the checkpoint ({f['restart_reason']}), final step {f['final_step']}, epochs done {f['state']}, "
                     f"{f['samples_after_restart']} samples trained after the restart, "
                     f"{f['kill_to_end_s'] or 0:.0f} s from kill to end")
    text = "\n".join(lines)
    print(text)
    print(json.dumps(out, default=float))
    if a.out:
        Path(a.out).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

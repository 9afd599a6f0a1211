"""Worker process: decodes videos and runs V2V for the tasks the server hands it.

A worker connects a DEALER socket to the server's worker endpoint, says ``ready``, and for
each ``task`` (one video of one epoch) streams one ``sample`` message per window, then a
``done`` message with the frame count or the reason the video could not be used. Sends block
at a small high-water mark, so a worker never runs ahead of what the server is willing to
hold. A worker whose parent has gone exits by itself.
"""
from __future__ import annotations

import logging
import os
import signal
import sys
from pathlib import Path

import zmq

from .config import ServeConfig
from .protocol import encode_arrays, narrow_int_dtype, pack, unpack
from .sampler import FlowEstimator, video_samples
from .video import VideoError

log = logging.getLogger("v2v.worker")

#: Messages a worker may have queued towards the server before its sends block.
WORKER_HWM = 2


def _parent_alive(parent_pid: int) -> bool:
    return os.getppid() == parent_pid


def _send(sock: zmq.Socket, frames, parent_pid: int) -> None:
    """Send, waiting in bounded steps for room; exit if the server process has gone."""
    while not sock.poll(1000, zmq.POLLOUT):
        if not _parent_alive(parent_pid):
            raise SystemExit(0)
    sock.send_multipart(frames, copy=False)


def wire_arrays(cfg: ServeConfig, arrays: dict) -> dict:
    """Narrow a sample's arrays to their wire dtypes: voxels int8/int16/int32 (the narrowest
    that holds every count), frames uint8, flow ``cfg.flow_dtype``."""
    out = {}
    for name, a in arrays.items():
        if name == "voxels":
            a = a.astype(narrow_int_dtype(a), copy=False)
        elif name == "flow":
            a = a.astype(cfg.flow_dtype, copy=False)
        out[name] = a
    return out


def run_task(cfg: ServeConfig, root: Path, task: dict, sock: zmq.Socket, parent_pid: int, flows: dict) -> None:
    """Make every sample of one task and send it, then send ``done``."""
    stats: dict = {}
    sent = 0
    error = None
    preset = cfg.flow_preset
    flow = flows.setdefault(preset, FlowEstimator(preset)) if "flow" in task["outputs"] else None
    try:
        for sid, arrays, meta in video_samples(
            cfg, root, task["video"], task["epoch"], task["outputs"], task.get("skip", ()), flow, stats
        ):
            specs, frames = encode_arrays(wire_arrays(cfg, arrays))
            header = {"type": "sample", "task": task["task"], "sample_id": sid,
                      "window": int(sid.rsplit("#", 1)[1]), "meta": meta, "arrays": specs}
            _send(sock, [pack(header)] + frames, parent_pid)
            sent += 1
    except VideoError as e:
        error = str(e)
    except Exception as e:  # any failure on one file is that file's verdict, not the worker's death
        error = f"{type(e).__name__}: {e}"
    if error is None and stats.get("windows", 0) == 0:
        error = (f"{stats.get('frames', 0)} frames, shorter than one window of "
                 f"{cfg.frames_per_sample} frames")
    done = {"type": "done", "task": task["task"], "samples": sent, "frames": stats.get("frames", 0),
            "windows": stats.get("windows", 0), "error": error,
            "failed": {str(k): str(v) for k, v in stats.get("failed", {}).items()}}
    _send(sock, [pack(done)], parent_pid)


def worker_main(cfg_dict: dict, root: str, endpoint: str, identity: bytes, parent_pid: int) -> None:
    """Entry point of a worker process (started with the ``spawn`` method)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the server decides when workers stop
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    logging.basicConfig(level=logging.INFO, format="v2v-worker %(process)d: %(message)s")
    import cv2

    cv2.setNumThreads(1)
    cfg = ServeConfig.from_dict(cfg_dict, source="worker config")
    ctx = zmq.Context()
    sock = ctx.socket(zmq.DEALER)
    sock.setsockopt(zmq.IDENTITY, identity)
    sock.setsockopt(zmq.SNDHWM, WORKER_HWM)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(endpoint)
    flows: dict = {}
    try:
        _send(sock, [pack({"type": "ready"})], parent_pid)
        while True:
            if not sock.poll(1000):
                if not _parent_alive(parent_pid):
                    return
                continue
            frames = sock.recv_multipart()
            h = unpack(frames[0])
            if h["type"] == "stop":
                return
            if h["type"] == "task":
                run_task(cfg, Path(root), h, sock, parent_pid, flows)
    finally:
        sock.close(0)
        ctx.term()

"""``v2v-serve``: serve V2V training batches over ZeroMQ."""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import List, Optional

from .config import FLOW_PRESETS, load_config
from .protocol import OUTPUTS
from .flow_options import DEFAULT_FLOW
from .server import V2VServer, install_signal_handlers
from .logs import setup_logging
from .corpus import SAMPLE_VIDEOS, check_corpus, format_check, select_shard
from .video import scan_corpus


log = logging.getLogger("v2v.serve")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="v2v-serve",
        description="Decode videos, simulate discrete voxel grids with V2V (Lou et al. 2025) and stream "
                    "batches of voxels, frames and optical flow to trainers over ZeroMQ.",
    )
    p.add_argument("--videos", help="corpus folder (searched recursively); default: the bundled sample clips")
    p.add_argument("--workers", type=int, help="worker processes (default 2)")
    p.add_argument("--bind", help="ZeroMQ endpoint to bind (default tcp://127.0.0.1:5555; port 0 = any free port)")
    p.add_argument("--config", help="YAML config file; command-line flags override it")
    p.add_argument("--seed", type=int, help="base seed: sample content depends only on (seed, epoch, sample_id)")
    p.add_argument("--epochs", type=int, help="end the stream after this many epochs (default: unbounded)")
    p.add_argument("--batch-size", type=int, help="samples per batch (default 12)")
    p.add_argument("--sequence-length", type=int, help="voxel grids per sample, L (default 40)")
    p.add_argument("--num-bins", type=int, help="temporal bins per voxel grid, B (default 5)")
    p.add_argument("--frames-per-bin", type=int, help="frame pairs summed into one bin (default 1)")
    p.add_argument("--crop-size", type=int, help="square crop side in pixels (default 128)")
    p.add_argument("--keep-top-fraction", type=float,
                   help="fraction of each frame's height, from the top, that crops come from (default 0.54: "
                        "WebVid's watermark; 1.0 for clips without one)")
    p.add_argument("--max-samples-per-video", type=int, help="windows per video per epoch (default 10)")
    p.add_argument("--crops-per-window", type=int, help="random crops per decoded window, each its own sample "
                   "(default 1; ids path#window.crop when > 1; crops of a window share content and motion)")
    p.add_argument("--outputs", help=f"comma list of outputs clients may ask for, from {','.join(OUTPUTS)}")
    p.add_argument("--flow-preset", choices=FLOW_PRESETS, help=f"optical flow option (default {DEFAULT_FLOW}; see docs/flow.md)")
    p.add_argument("--flow-dtype", choices=("float16", "float32"), help="wire dtype of flow (default float16)")
    p.add_argument("--refine", help="off | uniform:K | adaptive:PX | adaptive-dl:L: insert sub-frames where motion "
                                    "needs them (docs/fidelity.md); default off")
    p.add_argument("--lease", type=float, dest="lease_s", help="seconds before an unacknowledged batch is re-sent")
    p.add_argument("--client-timeout", type=float, dest="client_timeout_s",
                   help="seconds of client silence before its batches go back to the queue (default 10)")
    p.add_argument("--task-timeout", type=float, dest="task_timeout_s",
                   help="seconds a worker may send nothing on a task before it is reassigned (default 300)")
    p.add_argument("--revoke-timeout", type=float, dest="revoke_s",
                   help="seconds a client may leave a revoke unanswered before it is dropped "
                        "(default: --client-timeout)")
    p.add_argument("--max-credits", type=int, help="most batches one client may hold (default 64)")
    p.add_argument("--prefetch-batches", type=int, help="batches assembled ahead of the clients (default 2)")
    p.add_argument("--curve-secret-key", help="CurveZMQ: server secret key file (v2v-keygen)")
    p.add_argument("--curve-allow", help="CurveZMQ: folder of allowed client public key files")
    p.add_argument("--insecure", action="store_true", default=None,
                   help="allow a non-loopback --bind without CurveZMQ (not recommended)")
    p.add_argument("--shard", help="serve only shard I of N of the corpus, as I/N (0 <= I < N): a stable hash of each "
                                   "file's relative path picks its shard, so N servers with 0/N .. N-1/N on the same "
                                   "corpus serve every sample once per epoch")
    p.add_argument("--metrics-port", type=int, help="serve Prometheus /metrics, /healthz and /readyz over HTTP on "
                                                    "this port (0 = any free port; default off)")
    p.add_argument("--metrics-host", help="address of the metrics endpoint (default 127.0.0.1; 0.0.0.0 in a "
                                          "container so probes can reach it)")
    p.add_argument("--check", action="store_true",
                   help="decode every file of the corpus, print its verdict (usable windows or why not) and exit")
    p.add_argument("--log-level", default="INFO", help="logging level (default INFO)")
    p.add_argument("--log-format", choices=("text", "json"),
                   help="text (default) or json: one JSON object per line, for log shippers")
    return p


def config_from_args(args: argparse.Namespace):
    """Merge defaults, ``--config`` and flags into a validated ``ServeConfig``."""
    overrides = {k: getattr(args, k) for k in (
        "videos", "workers", "bind", "seed", "epochs", "batch_size", "sequence_length", "num_bins",
        "frames_per_bin", "crop_size", "keep_top_fraction", "max_samples_per_video", "crops_per_window", "outputs", "flow_preset", "flow_dtype", "lease_s", "refine",
        "client_timeout_s", "curve_secret_key", "curve_allow", "insecure", "shard", "metrics_port", "metrics_host", "log_format",
        "task_timeout_s", "revoke_s", "max_credits", "prefetch_batches")}
    return load_config(args.config, overrides)


def main(argv: Optional[List[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    setup_logging(args.log_level, args.log_format or "text", "v2v-serve")
    try:
        cfg = config_from_args(args)
    except (ValueError, FileNotFoundError) as e:
        print(f"v2v-serve: configuration error: {e}", file=sys.stderr)
        return 2
    root = Path(cfg.videos) if cfg.videos else SAMPLE_VIDEOS
    if not root.is_dir():
        print(f"v2v-serve: --videos {root}: not a folder", file=sys.stderr)
        return 2
    found, rejected = scan_corpus(root, cfg.video_extensions)
    videos = [p.as_posix() for p in found]
    index, count = cfg.shard_spec
    if count > 1:
        mine = select_shard(videos, index, count)
        log.info("shard %d/%d: %d of %d video file(s)", index, count, len(mine), len(videos))
        videos = mine
    if args.check:
        results = check_corpus(cfg, root, videos)
        print(format_check(results, rejected))
        return 0 if any(r["usable"] for r in results) else 2
    for rel, reason in rejected:
        log.info("ignored %s: %s", root / rel, reason)
    if not videos:
        print(f"v2v-serve: --videos {root}: no video files ({', '.join(cfg.video_extensions)})"
              + (f" in shard {cfg.shard}" if count > 1 else ""), file=sys.stderr)
        return 2
    server = V2VServer(cfg, root, videos)
    install_signal_handlers(server)
    try:
        return server.run()
    except Exception as e:  # bind errors and the like: one clear line
        if isinstance(e, OSError) or e.__class__.__module__.startswith("zmq"):
            print(f"v2v-serve: cannot serve on {cfg.bind}: {e}", file=sys.stderr)
            return 2
        raise


if __name__ == "__main__":
    sys.exit(main())

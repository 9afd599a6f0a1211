"""``v2v-serve``: serve V2V training batches over ZeroMQ."""
from __future__ import annotations

import argparse
import logging
import sys
from typing import List, Optional

from v2v_server.ops.config import DeliveryPolicy, SampleRecipe, ServeConfig, ServingSettings, load_config
from v2v_server.ops.startup import SAMPLE_VIDEOS, start_source
from v2v_server.sources.store import StoreSettings
from v2v_server.settings import add_flags, flag_values
from v2v_server.ops.plan_start import plan_manifest
from v2v_server.service.plan_server import PlanServer, install_signal_handlers
from v2v_server.ops.logs import LEVELS, setup_logging
from v2v_server.frames.check import check_corpus, format_check
from v2v_server.frames.corpus_index import index_path
from v2v_server.sources.errors import StoreError
from v2v_server.ops.warm import cache_line, format_warm, warm_cache
from v2v_wire.push_names import SERVER_KEYS, server_key_problem


log = logging.getLogger("v2v.serve")


def build_parser() -> argparse.ArgumentParser:
    """``v2v-serve``'s flags: one per configuration key (``v2v_server.ops.config``), plus the
    command's own (``--config``, ``--check``, ``--log-level``)."""
    p = argparse.ArgumentParser(
        prog="v2v-serve",
        description="Decode videos, simulate discrete voxel grids with V2V (Lou et al. 2025) and stream "
                    "batches of voxels, frames and optical flow to trainers over ZeroMQ.",
    )
    p.add_argument("--config", help="YAML config file; command-line flags override it (keys: docs/config.md)")
    p.add_argument("--check", action="store_true",
                   help="decode every file of the corpus, print its verdict (usable windows or why not) and exit")
    p.add_argument("--warm-cache", action="store_true",
                   help="fill this host's frame cache (frame_cache_gb > 0) with every video of the corpus or "
                        "shard, print what was stored and exit (docs/frame_cache.md)")
    p.add_argument("--log-level", default="INFO", type=str.upper, choices=LEVELS, help="logging level (default INFO)")
    for title, part in (("sample recipe", SampleRecipe), ("delivery", DeliveryPolicy), ("serving", ServingSettings),
                        ("object store", StoreSettings)):
        add_flags(p, part, title)
    for name, (flags, _) in SERVER_KEYS.items():  # push delivery's: refused in one line by main
        p.add_argument(*flags, dest=f"removed_{name}", nargs="?", const="", default=None, help=argparse.SUPPRESS)
    return p


def _removed_flag(args: argparse.Namespace) -> str:
    """One line for the first flag given of push delivery's (``push_names.SERVER_KEYS``), else
    ``""`` (``--delivery plan`` is what every server does: taken, ``push_names.TAKEN``)."""
    for name, (flags, _) in SERVER_KEYS.items():
        value = getattr(args, f"removed_{name}")
        if value is not None and server_key_problem(name, value):
            return server_key_problem(name, value)
    return ""


def config_from_args(args: argparse.Namespace) -> ServeConfig:
    """Merge defaults, ``--config`` and flags into a validated ``ServeConfig``.

    Raises:
        ValueError, FileNotFoundError: as ``load_config``.
    """
    return load_config(args.config, flag_values(args, ServeConfig))


def _serve_plan(start) -> int:
    """Serving: the manifest (each video's windows the corpus index knows), then
    :class:`PlanServer` until a signal stops it."""
    cfg = start.config
    try:
        manifest = plan_manifest(start)
    except ValueError as e:
        print(f"v2v-serve: {e}", file=sys.stderr)
        return 2
    server = PlanServer(cfg, start.source, start.caches, manifest, start.corpus, start.skipped)
    stopped_by = install_signal_handlers(server)
    try:
        status = server.run()
        return 128 + stopped_by[0] if stopped_by else status
    except OSError as e:  # the address cannot be bound
        print(f"v2v-serve: {e}", file=sys.stderr)
        return 2


def main(argv: Optional[List[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    setup_logging(args.log_level, args.log_format or "text", "v2v-serve")
    if _removed_flag(args):
        print(f"v2v-serve: {_removed_flag(args)}", file=sys.stderr)
        return 2
    try:
        cfg = config_from_args(args)
    except (ValueError, FileNotFoundError) as e:
        print(f"v2v-serve: configuration error: {e}", file=sys.stderr)
        return 2
    try:
        start = start_source(cfg)
    except (StoreError, FileNotFoundError, ValueError) as e:  # the store, the cache folder or the video list file
        print(f"v2v-serve: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:  # while a store is listed or a table is read (its query stopped)
        raise type(e)(f"stopped while listing {cfg.video_list or cfg.videos or SAMPLE_VIDEOS}") from None
    cfg, source, caches, videos = start.config, start.source, start.caches, start.videos
    if args.check:
        results = check_corpus(cfg.recipe.windows, cfg.recipe.decode, source, videos, cfg.workers, caches)
        print(format_check(results, start.rejected, cfg.recipe.crops_per_window))
        if caches.frame_cache is not None:
            print(cache_line(source, caches.frame_cache, cfg, videos))
        return 0 if any(r.usable for r in results) else 2
    if args.warm_cache:
        try:
            results = warm_cache(cfg, source, caches, videos)
        except ValueError as e:
            print(f"v2v-serve: {e}", file=sys.stderr)
            return 2
        print(format_warm(results, caches.frame_cache))
        return 0 if any(r["state"] in ("stored", "cached") for r in results) else 2
    for rel, reason in start.rejected:  # a listed video that is missing is named here, once
        (log.warning if source.video_list else log.info)("ignored %s: %s", source.where_ignored(rel), reason)
    if not videos:
        print(f"v2v-serve: --videos {source.root}: no video files ({', '.join(cfg.video_extensions)})"
              + (f" in shard {cfg.shard}" if cfg.shard else ""), file=sys.stderr)
        return 2
    if start.skipped:  # gives no sample: not opened again while its identity holds
        log.info("%d video(s) not opened: the corpus index %s knows they give no window at this layout "
                 "(--check says why)", len(start.skipped), index_path(caches.cache_dir))
        if not start.served:
            print(f"v2v-serve: --videos {source.root}: no video gives a window at this layout (the corpus index "
                  f"{index_path(caches.cache_dir)} knows them all; --check says why)", file=sys.stderr)
            return 2
    return _serve_plan(start)


if __name__ == "__main__":
    from v2v_wire.commands import main_of_module

    sys.exit(main_of_module("v2v-serve", main))

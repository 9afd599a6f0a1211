"""A server in a thread of this process, for demos and tests: what ``v2v-serve`` runs
(``PlanServer``, its workers as processes), bound to a free loopback port.
"""
from __future__ import annotations

import contextlib
import threading
from typing import Iterator, Optional

from v2v_server.ops.config import ServeConfig, load_config
from v2v_server.ops.startup import SAMPLE_VIDEOS, start_source
from v2v_server.ops.plan_start import plan_manifest
from v2v_server.service.plan_server import PlanServer
from v2v_server.sources.errors import StoreError

__all__ = ["SAMPLE_VIDEOS", "StoreError", "local_server"]  # what the demo names: the bundled clips, a corpus not there


@contextlib.contextmanager
def local_server(videos: Optional[str], workers: int, batch_size: int, ready_timeout_s: float = 120.0, *,
                 config: Optional[ServeConfig] = None) -> Iterator[str]:
    """Serve ``videos`` (default: ``config.videos``, else the bundled clips) from a thread of this
    process; yields the bound endpoint (``tcp://127.0.0.1:<free port>``) and always stops the
    server and its workers (a ``PlanServer``). ``config``: the other keys (default: every key's default); the
    corpus is opened, checked, listed and sharded (``shard``), and the videos the host's corpus
    index knows to give no window left out, by the start-up path ``v2v-serve`` runs
    (``ops.startup.start_source``), so both serve the same samples.

    Raises:
        ValueError: a bad ``workers``/``batch_size`` (from the config check, naming the field), a
            cache folder that cannot keep the caches that are on (``disk_cache.CacheDirError``), or a
            folder (or shard) with no video to serve.
        StoreError: the folder does not exist, or the store cannot be reached or listed.
        RuntimeError: the server stopped or stayed silent before it served (its error chained).
    """
    keys = {"workers": workers, "batch_size": batch_size, "bind": "tcp://127.0.0.1:*"}
    cfg = load_config(None, {**(config.to_dict() if config is not None else {}), **keys})
    start = start_source(cfg, videos)  # a folder or an object-store URL; the shard of cfg.shard
    server = PlanServer(start.config, start.source, start.caches, plan_manifest(start), start.corpus, start.skipped)
    ready, failure = threading.Event(), []

    def run() -> None:
        try:
            server.run(ready)
        except BaseException as e:  # noqa: BLE001 - handed to the caller below
            failure.append(e)
            ready.set()

    thread = threading.Thread(target=run, name="v2v-demo-server", daemon=True)
    thread.start()
    try:
        if not ready.wait(ready_timeout_s) or failure:
            raise RuntimeError(f"the server did not start within {ready_timeout_s} s") from (failure[0] if failure else None)
        yield server.bound_endpoint
    finally:
        server.stop()
        thread.join(30.0)

"""A server in a thread of this process, for demos and tests: what ``v2v-serve`` runs
(``V2VServer``, its workers as processes), bound to a free loopback port.
"""
from __future__ import annotations

import contextlib
import threading
from typing import Iterator, Optional

from v2v_server.ops.config import load_config
from v2v_server.videos.corpus import SAMPLE_VIDEOS
from v2v_server.service.server import V2VServer
from v2v_server.videos.source_spec import open_source


@contextlib.contextmanager
def local_server(videos: Optional[str], workers: int, batch_size: int, ready_timeout_s: float = 120.0) -> Iterator[str]:
    """Serve ``videos`` (default: the bundled clips) from a thread of this process; yields the
    bound endpoint (``tcp://127.0.0.1:<free port>``) and always stops the server and its workers.

    Raises:
        ValueError: a bad ``workers``/``batch_size`` (from the config check, naming the field), or
            a folder with no video files.
        RuntimeError: the server stopped or stayed silent before it served (its error chained).
    """
    cfg = load_config(None, {"workers": workers, "batch_size": batch_size, "bind": "tcp://127.0.0.1:*"})
    source = open_source(videos or SAMPLE_VIDEOS)  # a folder or an object-store URL
    found, _rejected = source.list_videos(cfg.video_extensions)
    server = V2VServer(cfg, source, found)
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

"""``v2v-demo``: the main job end to end on the bundled clips.

Runs the server (``v2v_server.server.V2VServer``, what ``v2v-serve`` runs) in a thread of this
process on a free loopback port (its workers are processes, as under ``v2v-serve``), reads
batches through ``V2VStreamDataset`` (the same code path as ``v2v-loadtest``), prints
batches/s, writes a preview PNG of one sample, and stops the server.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import sys
import threading
from pathlib import Path
from typing import Iterator, List, Optional

from v2v_server.cli import SAMPLE_VIDEOS
from v2v_server.config import load_config
from v2v_server.server import V2VServer
from v2v_server.video import scan_corpus

from .dataset import V2VStreamDataset
from .loadtest import format_report, run_loadtest
from .preview import write_preview


@contextlib.contextmanager
def local_server(videos: Optional[str], workers: int, batch_size: int, ready_timeout_s: float = 120.0) -> Iterator[str]:
    """Serve ``videos`` (default: the bundled clips) from a thread of this process; yields the
    bound endpoint (``tcp://127.0.0.1:<free port>``) and always stops the server and its workers.

    Raises:
        ValueError: a bad ``workers``/``batch_size`` (from the config check, naming the field), or
            a folder with no video files.
        RuntimeError: the server stopped or stayed silent before it served (its error chained).
    """
    root = Path(videos) if videos else SAMPLE_VIDEOS
    cfg = load_config(None, {"workers": workers, "batch_size": batch_size, "bind": "tcp://127.0.0.1:*"})
    found, _rejected = scan_corpus(root, cfg.video_extensions)
    server = V2VServer(cfg, root, [f.as_posix() for f in found])
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


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="v2v-demo", description=__doc__.splitlines()[0])
    p.add_argument("--videos", help="corpus folder (default: the bundled sample clips)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument("--batches", type=int, default=6, help="batches to measure")
    p.add_argument("--preview", default="preview.png", help="where to write the preview PNG")
    p.add_argument("--timeout", type=float, default=120.0)
    a = p.parse_args(argv)
    with local_server(a.videos, a.workers, a.batch_size) as endpoint:
        print(f"v2v server running on {endpoint} with {a.workers} workers")
        ds = V2VStreamDataset(endpoint, timeout_s=a.timeout)
        it = iter(ds)
        first = next(it)
        it.close()
        path = write_preview(first, a.preview)
        print(f"preview of {first['sample_ids'][0]} written to {path}")
        shapes = {k: (tuple(v.shape), str(v.dtype)) for k, v in first.items() if hasattr(v, "shape")}
        print(f"batch layout: {shapes}")
        r = run_loadtest(endpoint, a.batches, timeout_s=a.timeout)
        print(format_report(r))
        print(json.dumps(r))
    return 0


if __name__ == "__main__":
    sys.exit(main())

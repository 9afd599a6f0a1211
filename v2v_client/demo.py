"""``v2v-demo``: the main job end to end on the bundled clips.

Runs the server (``v2v_server.service.local.local_server``: what ``v2v-serve`` runs) in a thread of this
process on a free loopback port (its workers are processes, as under ``v2v-serve``), reads
batches through ``V2VStreamDataset`` (the same code path as ``v2v-loadtest``), prints
batches/s, writes a preview PNG of one sample, and stops the server. It hosts a server, so
it needs the server's packages (``pip install 'v2v[server,client]'``); a trainer host with
``v2v[client]`` only reads a remote server's stream.
"""
from __future__ import annotations

import argparse
import json
import sys
from typing import List, Optional

from .dataset import V2VStreamDataset
from .loadtest import format_report, run_loadtest


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="v2v-demo", description=__doc__.splitlines()[0])
    p.add_argument("--videos", help="corpus folder (default: the bundled sample clips)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument("--batches", type=int, default=6, help="batches to measure")
    p.add_argument("--preview", default="preview.png", help="where to write the preview PNG")
    p.add_argument("--timeout", type=float, default=120.0)
    a = p.parse_args(argv)
    try:  # the server and the preview (OpenCV) come with the server's packages only
        from v2v_server.service.local import local_server

        from .preview import write_preview
    except ImportError as e:
        print(f"v2v-demo runs a server in this process and needs the server's packages: "
              f"pip install 'v2v[server,client]' ({e})", file=sys.stderr)
        return 2
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

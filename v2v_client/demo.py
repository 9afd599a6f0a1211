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
import contextlib
import json
import sys
from pathlib import Path
from typing import List, Optional

from v2v_wire.commands import input_overwritten, writable_problem

from .loadtest import run_loadtest
from .plan_dataset import V2VStreamDataset


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="v2v-demo", description=__doc__.splitlines()[0])
    p.add_argument("--videos", help="corpus folder (default: the bundled sample clips)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument("--batches", type=int, default=6, help="batches to measure")
    p.add_argument("--preview", default="preview.png", help="where to write the preview PNG")
    p.add_argument("--timeout", type=float, default=120.0)
    p.add_argument("--json", action="store_true", help="print the measurement as one JSON object on the last line "
                   "(as v2v-loadtest --json)")
    a = p.parse_args(argv)
    try:  # the server and the preview (OpenCV) come with the server's packages only
        from v2v_server.service.local import SAMPLE_VIDEOS, StoreError, local_server

        from .preview import write_preview
    except ImportError as e:
        print(f"v2v-demo runs a server in this process and needs the server's packages: "
              f"pip install 'v2v[server,client]' ({e})", file=sys.stderr)
        return 2
    corpus = a.videos or str(SAMPLE_VIDEOS)  # the bundled clips are an input too
    why = (input_overwritten(a.preview, [("the corpus (--videos)", corpus)], [("inside the corpus (--videos)", corpus, None)])
           or ("it must name a .png file" if Path(a.preview).suffix.lower() != ".png" else None)
           or writable_problem(Path(a.preview)))
    if why:
        print(f"v2v-demo: --preview {a.preview}: {why}", file=sys.stderr)
        return 2
    with contextlib.ExitStack() as stack:
        try:
            endpoint = stack.enter_context(local_server(a.videos, a.workers, a.batch_size))
        except (ValueError, StoreError) as e:  # a corpus not there or without videos, a bad setting
            print(f"v2v-demo: {e}", file=sys.stderr)
            return 2
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
        print(demo_report(r, a.workers))
        if a.json:
            print(json.dumps(r))
    return 0


def demo_report(r: dict, workers: int) -> str:
    """What the demo measured (``run_loadtest``'s dict ``r``), in words a newcomer reads: the
    rate of batches and samples, that it is the server's rate (the demo trains nothing, so the
    reader always waits for the next batch), and which epochs the batches came from."""
    epochs = r["epochs_seen"]
    span = f"epoch {epochs[0]}" if len(epochs) == 1 else f"epochs {epochs[0]}-{epochs[-1]}"
    return (f"read {r['batches']} batches ({r['samples']} samples, {r['unique_samples']} different) in "
            f"{r['seconds']:.1f} s: {r['samples_per_s']:.2f} samples/s, {r['mbytes_per_s']:.1f} MB/s from "
            f"{workers} worker(s).\n"
            f"This is how fast the server makes samples: the demo trains nothing, so it waited for each batch "
            f"({100 * r['wait_fraction']:.0f} % of the time); a trainer whose step takes longer than "
            f"{1 / max(r['batches_per_s'], 1e-9):.2f} s per batch would not wait at all.\n"
            f"The batches came from {span}: an epoch is one pass over every window of the corpus (the bundled "
            f"clips' is a few samples), and the preview's batch was read before these.")


if __name__ == "__main__":
    from v2v_wire.commands import main_of_module

    sys.exit(main_of_module("v2v-demo", main))

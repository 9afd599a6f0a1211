"""The server main process's CPU per GB it relays, this tree against an older one, in one run.

Run: ``python -m bench.server_cpu --old DIR [--old DIR2] [--rounds 4] [--batches 12]`` where each
``DIR`` holds an older tree (``git archive 0232d3c | tar -x -C DIR``: the commit before grants).

Each round runs both trees, in alternating order (ABBA...), each with its own server and client
(``PYTHONPATH`` pointing at the tree): ``v2v-serve --workers 1 --batch-size 4`` on one 596x336
clip (``bbb_camera_596x336.mp4``, the default recipe), and ``v2v-loadtest --batches 12`` (one
batch of warm-up first). Measured: the server main process's CPU-seconds (user + system, all its
threads, ZeroMQ's I/O threads included, its worker processes not: ``/proc/PID/stat``) from the
load test's start to its end, divided by the array bytes it sent (``v2v_sent_bytes_total`` of its
``/metrics``); the load test's samples per second. Medians over the rounds, and their ratio.
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

from harness.data import SAMPLE_VIDEOS
from harness.serve import free_port

ROOT = Path(__file__).resolve().parents[1]
CLIP = "bbb_camera_596x336.mp4"


def _cpu_s(pid: int) -> float:
    """CPU-seconds process ``pid`` ran so far: the sum over its threads of the scheduler's own
    count (``/proc/PID/task/*/schedstat``, nanoseconds; ``/proc/PID/stat``'s 10 ms ticks are too
    coarse for the tenths of a second a run takes), not its children."""
    total = 0
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            total += int((task / "schedstat").read_text().split()[0])
        except (OSError, ValueError, IndexError):
            continue  # a thread that just ended
    return total / 1e9


def _sent_bytes(port: int) -> float:
    text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10).read().decode()
    m = re.search(r"^v2v_sent_bytes_total\s+(\S+)", text, re.M)
    return float(m.group(1)) if m else float("nan")


def one_run(tree: Path, corpus: Path, batches: int) -> dict:
    """One server of ``tree`` and one load test of ``tree`` against it: CPU-s/GB and samples/s."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    port, mport = free_port(), free_port()
    endpoint = f"tcp://127.0.0.1:{port}"
    srv = subprocess.Popen([sys.executable, "-m", "v2v_server.cli", "--videos", str(corpus), "--workers", "1",
                            "--batch-size", "4", "--bind", endpoint, "--metrics-port", str(mport)],
                           env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while True:  # ready: its metrics endpoint answers
            try:
                _sent_bytes(mport)
                break
            except OSError:
                if time.monotonic() > deadline or srv.poll() is not None:
                    raise RuntimeError(f"the server of {tree} did not start: {srv.stderr.read()[-2000:]}")
                time.sleep(0.2)
        cpu0, sent0 = _cpu_s(srv.pid), _sent_bytes(mport)
        out = subprocess.run([sys.executable, "-m", "v2v_client.loadtest", "--connect", endpoint, "--batches",
                              str(batches), "--json"], env=env, capture_output=True, text=True, timeout=1200)
        cpu1, sent1 = _cpu_s(srv.pid), _sent_bytes(mport)
        if out.returncode != 0:
            raise RuntimeError(f"v2v-loadtest of {tree} failed: {out.stderr[-2000:]}")
        import json

        r = json.loads(out.stdout.strip().splitlines()[-1])
        gb = (sent1 - sent0) / 1e9
        return {"cpu_s": cpu1 - cpu0, "gb": gb, "cpu_s_per_gb": (cpu1 - cpu0) / gb, "samples_per_s": r["samples_per_s"]}
    finally:
        srv.terminate()
        try:
            srv.wait(30)
        except subprocess.TimeoutExpired:
            srv.kill()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--old", required=True, action="append",
                    help="an older tree (e.g. git archive 0232d3c | tar -x -C DIR); repeat for several")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--batches", type=int, default=12)
    a = ap.parse_args()
    trees = {}
    for d in a.old:
        old = Path(d).resolve()
        if not (old / "v2v_server" / "cli.py").is_file():
            ap.error(f"--old {d}: not a v2v tree (no v2v_server/cli.py)")
        trees[f"older tree ({old.name})"] = old
    trees["this tree"] = ROOT
    runs = {name: [] for name in trees}
    with tempfile.TemporaryDirectory(prefix="v2v-server-cpu-") as d:
        corpus = Path(d) / "clip"
        corpus.mkdir()
        shutil.copy(SAMPLE_VIDEOS / CLIP, corpus / CLIP)
        names = list(trees)
        for r in range(a.rounds):
            for name in (names if r % 2 == 0 else names[::-1]):  # ABBA: no tree always runs first
                runs[name].append(one_run(trees[name], corpus, a.batches))
                print(name, {k: round(v, 4) for k, v in runs[name][-1].items()}, file=sys.stderr)
    base = statistics.median(x["cpu_s_per_gb"] for x in runs[names[0]])
    print(f"| server main process, one worker, {CLIP}, {a.batches} batches of 4 | CPU-s per GB sent "
          f"(median of {a.rounds}) | ratio | GB per run | samples/s |\n|---|---|---|---|---|")
    for name in names:
        cpu = statistics.median(x["cpu_s_per_gb"] for x in runs[name])
        print(f"| {name} | {cpu:.2f} | {cpu / base:.2f} | {statistics.median(x['gb'] for x in runs[name]):.3f} | "
              f"{statistics.median(x['samples_per_s'] for x in runs[name]):.2f} |")


if __name__ == "__main__":
    main()

"""What scraping ``/metrics`` costs a serving ``v2v-serve``.

Run: ``python -m bench.scrape_storm [--seconds 20] [--rate 200]``. Starts a server on the
bundled clips with ``--metrics-port``, reads voxels for ``--seconds`` with one trainer (the
plan's epochs in turn through ``V2VStreamDataset``, 8 fetches in flight), once
alone and once while another process fetches ``/metrics`` ``--rate`` times a second, and prints
batches/s, the server main process's CPU seconds per batch (``/proc/PID/stat``; workers are
other processes), and the ratios against the run without scrapes.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

from harness.serve import ServeProcess, free_port
from v2v_client import PlanEpochs, V2VStreamDataset

SCRAPER = """
import sys, time, urllib.request
url, rate = sys.argv[1], float(sys.argv[2])
n, t0 = 0, time.monotonic()
while True:
    urllib.request.urlopen(url, timeout=5).read()
    n += 1
    time.sleep(max(0.0, t0 + n / rate - time.monotonic()))
"""


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` (Linux)."""
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run(seconds: float, rate: float) -> dict:
    port = free_port()
    with ServeProcess(["--workers", "1", "--outputs", "voxels", "--metrics-port", str(port),
                       "--crop-size", "64", "--sequence-length", "8", "--batch-size", "4"]) as srv:
        it = iter(PlanEpochs(V2VStreamDataset(srv.endpoint, outputs=("voxels",), timeout_s=60, prefetch=8)))
        for _ in range(10):  # warm: workers compiled and producing
            next(it)
        scraper = None
        if rate > 0:
            scraper = subprocess.Popen([sys.executable, "-c", SCRAPER, f"http://127.0.0.1:{port}/metrics", str(rate)])
        c0, t0, n = cpu_s(srv.proc.pid), time.monotonic(), 0
        while time.monotonic() - t0 < seconds:
            next(it)
            n += 1
        wall, cpu = time.monotonic() - t0, cpu_s(srv.proc.pid) - c0
        if scraper is not None:
            scraper.kill()
            scraper.wait()
        it.close()
    return {"batches_per_s": n / wall, "server_cpu_ms_per_batch": 1e3 * cpu / max(1, n)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--rate", type=float, default=200.0)
    a = ap.parse_args()
    base, storm = run(a.seconds, 0.0), run(a.seconds, a.rate)
    print("| scrapes/s | batches/s | ratio | server main process CPU ms per batch | ratio |\n|---|---|---|---|---|")
    for rate, r in ((0, base), (a.rate, storm)):
        print(f"| {rate:.0f} | {r['batches_per_s']:.1f} | {r['batches_per_s'] / base['batches_per_s']:.2f} | "
              f"{r['server_cpu_ms_per_batch']:.2f} | "
              f"{r['server_cpu_ms_per_batch'] / base['server_cpu_ms_per_batch']:.2f} |")


if __name__ == "__main__":
    main()

"""Fault scenarios of the server's own filesystem work (docs/faults.md, "The server's own
filesystem work") against a real ``v2v-serve`` serving by plan on 127.0.0.1: its frame cache's
folder replaced by a file while serving, a corpus index whose lock another process holds, a
``--cache-dir`` it cannot use at start. Same row format as ``harness/faults.py``.
"""
from __future__ import annotations

import sqlite3
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

from harness.faults import (Layout, _clean, _ids, _serve, _stop, dataset, expected_ids, good_corpus, per_epoch,
                            read_all, real_ids, row)
from harness.serve import free_port
from v2v_server.frames.corpus_index import INDEX_FILE


def _metrics(port: int) -> dict:
    """The ``v2v_fs_errors_total`` samples of the server's /metrics page."""
    page = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
    return {ln.split()[0]: float(ln.split()[1]) for ln in page.splitlines() if ln.startswith("v2v_fs_errors_total")}


def replace_with_a_file(folder: Path) -> None:
    """Move ``folder`` away and put a file in its place (what a vanished mount looks like to a
    scan); workers may make it again in between, so repeat until the file is what sits there."""
    for attempt in range(100):
        try:
            folder.rename(folder.with_name(f"{folder.name}.gone{attempt}"))
        except FileNotFoundError:
            pass
        try:
            with open(folder, "xb") as f:
                f.write(b"not a folder")
            return
        except (FileExistsError, IsADirectoryError):
            continue
    raise RuntimeError(f"{folder} kept being made again by the workers")


def scenario_cache_folder_replaced(tmp: Path, layout: Layout, epochs: int = 2) -> dict:
    """The frame cache's folder turned into a file after the first batch: the gauge scan counts
    it (``v2v_fs_errors_total{where="frame_cache"}``) and logs it once, workers serve by decoding,
    and every sample of ``epochs`` epochs is read once."""
    corpus = good_corpus(tmp, 1)
    expected = per_epoch(expected_ids(corpus, layout), range(epochs))
    cache, port = tmp / "cache", free_port()
    key = 'v2v_fs_errors_total{where="frame_cache"}'
    log: list = []
    with _serve(corpus, layout, "--frame-cache-gb", "1", "--cache-dir", str(cache), "--metrics-port", str(port)) as srv:
        ds = dataset(srv.endpoint)
        it = iter(ds)
        log.append((time.monotonic(), real_ids(next(it), tag=True)))
        replace_with_a_file(cache / "frames")
        for b in it:
            log.append((time.monotonic(), real_ids(b, tag=True)))
        for e in range(1, epochs):
            ds.set_epoch(e)
            read_all(ds, log, tag=True)
        deadline, counted = time.monotonic() + 12, 0.0
        while counted < 2 and time.monotonic() < deadline:  # two scans of a server scanning every 5 s
            time.sleep(0.5)
            counted = _metrics(port).get(key, 0.0)
        rc, clean = _stop(srv), _clean(srv)
    told = [ln for ln in srv.lines if "v2v_fs_errors_total" in ln]
    enotdir = bool(told) and all("ENOTDIR" in t for t in told)
    return row(f"frame cache's folder replaced by a file while serving, {epochs} epochs", expected, _ids(log), None,
               f"scan failures counted {counted:.0f}, logged {len(told)}x{' (ENOTDIR)' if enotdir else ''}; "
               f"server exit {rc}", counted=counted, logged=len(told), enotdir=enotdir, server_exit=rc, clean=clean)


def scenario_locked_index(tmp: Path, layout: Layout) -> dict:
    """The corpus index (made by ``--check``) is locked by another process for the server's whole
    run: one warning naming it, the epoch's size unknown at start, every sample read once."""
    corpus = good_corpus(tmp, 1)
    expected = expected_ids(corpus, layout)
    cache = tmp / "cache"
    subprocess.run([sys.executable, "-m", "v2v_server.cli", "--check", "--videos", str(corpus), "--cache-dir",
                    str(cache), *layout.args()], capture_output=True, timeout=300, check=True)
    holder = sqlite3.connect(cache / INDEX_FILE, isolation_level=None)
    log: list = []
    try:
        holder.execute("BEGIN EXCLUSIVE")
        holder.execute("DELETE FROM entries")  # not committed: the server would read the entries, and cannot
        with _serve(corpus, layout, "--cache-dir", str(cache), "--log-level", "info") as srv:
            read_all(dataset(srv.endpoint), log)
            rc, clean = _stop(srv), _clean(srv)
    finally:
        holder.close()
    warned = sum(str(cache / INDEX_FILE) in ln and "locked" in ln for ln in srv.lines)
    return row("corpus index locked by another process", expected, _ids(log), None,
               f"warned {warned}x naming the index; server exit {rc}", warned=warned, server_exit=rc, clean=clean)


def scenario_unusable_cache_dir(tmp: Path, layout: Layout) -> dict:
    """``--cache-dir`` naming a file, with a frame cache on: ``v2v-serve`` exits 2 at once with one
    line naming the path, before any worker starts."""
    corpus = good_corpus(tmp, 1)
    bad = tmp / "not_a_folder"
    bad.write_text("a file")
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--videos", str(corpus), *layout.args(),
                        "--bind", "tcp://127.0.0.1:0", "--cache-dir", str(bad), "--frame-cache-gb", "1"],
                       capture_output=True, text=True, timeout=120)
    lines = r.stderr.strip().splitlines()
    named = len(lines) == 1 and str(bad) in lines[0]
    return row("unusable --cache-dir at start", [], [], None,
               f"exit {r.returncode} after {time.monotonic() - t0:.1f} s; one line naming it {named}",
               exit=r.returncode, lines=len(lines), named=named)


SCENARIOS = {
    "cache_folder_replaced": scenario_cache_folder_replaced,
    "locked_index": scenario_locked_index,
    "unusable_cache_dir": scenario_unusable_cache_dir,
}

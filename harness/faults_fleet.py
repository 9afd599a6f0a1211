"""Fault scenarios of a fleet (``v2v-serve`` hosts of one corpus read as one plan,
``v2v_client.fleet_read``): a host gone for good, one host under two names. Real servers on
127.0.0.1 read by ``V2VStreamDataset``; same row format as ``harness/faults.py``; ``python -m
bench.faults`` runs them, ``tests/test_faults_fleet.py`` runs them short.
"""
from __future__ import annotations

import logging
import os
import signal
import time
from pathlib import Path
from typing import List, Optional

from harness.faults import (Layout, _clean, _ids, _next_after, _serve, _stop, dataset, expected_ids, good_corpus,
                            per_epoch, read_all, real_ids, row)
from v2v_client.fetch import Link


class _Lines(logging.Handler):
    """The lines logged to ``logger`` at WARNING and above while in a ``with`` block."""

    def __init__(self, logger: str):
        super().__init__(logging.WARNING)
        self.logger, self.lines = logging.getLogger(logger), []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())

    def __enter__(self) -> "_Lines":
        self.logger.addHandler(self)
        return self

    def __exit__(self, *exc) -> None:
        self.logger.removeHandler(self)


def scenario_first_host_killed(tmp: Path, layout: Layout, timeout_s: float = 20.0) -> dict:
    """Two hosts read as one fleet, the first listed SIGKILLed after epoch 0's first batch and
    left dead: epoch 0 ends on the other host, and epoch 1 (a new pass, which asks the fleet for
    its manifest again) is read whole from it, its first batch after about ``ASK_NEXT_S``, not
    after ``timeout_s`` (the reader's, its default 20 s) and an error."""
    corpus = good_corpus(tmp, 2)
    expected = per_epoch(expected_ids(corpus, layout), (0, 1))
    log: list = []
    error: Optional[str] = None
    with _serve(corpus, layout, workers=1) as a, _serve(corpus, layout, workers=1) as b:
        ds = dataset(f"{a.endpoint},{b.endpoint}", timeout_s=timeout_s)
        t_kill = None
        for batch in ds:
            log.append((time.monotonic(), real_ids(batch, tag=True)))
            if t_kill is None:
                os.kill(a.proc.pid, signal.SIGKILL)
                t_kill = time.monotonic()
        ds.set_epoch(1)
        t1 = time.monotonic()
        try:
            read_all(ds, log, tag=True)
        except TimeoutError as e:
            error = f"TimeoutError: {e}"
        waited = _next_after(log, t1)
        ended = time.monotonic() - t1
        rc = _stop(b)
        clean = _clean(b)
    epoch1 = sum(1 for s in _ids(log) if s.startswith("1:"))
    first = "none" if waited is None else f"{waited:.1f} s"
    return row("first-listed fleet host SIGKILLed mid-epoch 0 and left dead, epochs 0 and 1", expected, _ids(log),
               _next_after(log, t_kill), f"epoch 1: {epoch1} samples, its first batch after {first} "
               f"(timeout_s {timeout_s:g}); error: {error or 'none'}; other host exit {rc}",
               epoch1_first_s=waited, epoch1_s=ended, epoch1_samples=epoch1, error=error, server_exit=rc, clean=clean)


def scenario_one_host_two_names(tmp: Path, layout: Layout) -> dict:
    """One host listed twice, as ``tcp://localhost:P`` and ``tcp://127.0.0.1:P``: it says one
    instance under both, so the reader reads it once, under the first name, and says so in one
    line; the host makes each sample read once."""
    corpus = good_corpus(tmp, 2)
    expected = expected_ids(corpus, layout)
    log: list = []
    served: List[str] = []
    with _serve(corpus, layout) as srv:
        names = [f"tcp://localhost:{srv.endpoint.rsplit(':', 1)[1]}", srv.endpoint]
        with _Lines("v2v.client") as lines:
            for batch in dataset(",".join(names)):
                log.append((time.monotonic(), real_ids(batch)))
                served += [ep for ep in batch["servers"] if ep not in served]
        with Link(srv.endpoint, 30) as link:
            made = link.ask().stream["feed"]["samples_made"]
        rc = _stop(srv)
        clean = _clean(srv)
    said = [s for s in lines.lines if names[0] in s and names[1] in s]
    read = len(_ids(log))
    return row("one fleet host under two names (localhost and 127.0.0.1)", expected, _ids(log), None,
               f"read as {len(served)} host(s) ({', '.join(served)}); {made} samples made for {read} read; "
               f"said in {len(said)} line(s); server exit {rc}", hosts=served, made=made, read=read, said=said,
               server_exit=rc, clean=clean)


SCENARIOS = {
    "fleet_first_host_killed": scenario_first_host_killed,
    "fleet_one_host_two_names": scenario_one_host_two_names,
}

"""Fault scenarios of a fleet (``v2v-serve`` hosts of one corpus read as one plan,
``v2v_client.fleet_read``): a host gone for good, one host under two names, a file replaced under
the fleet as a deploy does (each host restarted in turn). Real servers on
127.0.0.1 read by ``V2VStreamDataset``; same row format as ``harness/faults.py``; ``python -m
bench.faults`` runs them, ``tests/test_faults_fleet.py`` runs them short.
"""
from __future__ import annotations

import hashlib
import logging
import os
import shutil
import signal
import time
from pathlib import Path
from typing import Callable, Dict, List, Optional

from harness.faults import (GOOD_VIDEOS, Layout, _clean, _ids, _next_after, _serve, _stop, dataset, expected_ids,
                            good_corpus, per_epoch, read_all, real_ids, row)
from v2v_client.fetch import Link
from v2v_wire.plan import PlanMismatch


class _Lines(logging.Handler):
    """The lines logged to ``logger`` at WARNING and above while in a ``with`` block."""

    def __init__(self, logger: str, on_line: Optional[Callable[[str], None]] = None):
        super().__init__(logging.WARNING)
        self.logger, self.lines, self.on_line = logging.getLogger(logger), [], on_line

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())
        if self.on_line is not None:
            self.on_line(self.lines[-1])

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


#: The file a deploy replaces (by another clip under its name, another size and modification time).
REPLACED = "bikes.mp4"


def _deployed(folder: Path, clips: List[str]) -> None:
    """``folder`` holding ``clips`` and a copy of each (``NAME_1.mp4``), every file's modification
    time the same on every host (a deploy's copy keeps it: ``rsync -a``), so hosts list one plan."""
    folder.mkdir(parents=True)
    for c in clips:
        for name in (c, c.replace(".mp4", "_1.mp4")):
            shutil.copy(GOOD_VIDEOS / c, folder / name)
            os.utime(folder / name, (1_500_000_000, 1_500_000_000))


def _replace(folder: Path) -> None:
    """:data:`REPLACED` in ``folder`` replaced by another clip (another size and tag)."""
    shutil.copy(GOOD_VIDEOS / "bigbuckbunny.mp4", folder / REPLACED)
    os.utime(folder / REPLACED, (1_600_000_000, 1_600_000_000))


def _restart(srv, folder: Path) -> None:
    """Host ``srv`` stopped, its copy of :data:`REPLACED` replaced, and started again on its address."""
    srv.stop()
    _replace(folder)
    srv.start()


def _digests(ds, epoch: int) -> Dict[str, str]:
    """Sample id -> SHA-1 of its voxels, of ``epoch`` read whole from ``ds``."""
    ds.set_epoch(epoch)
    return {sid: hashlib.sha1(b["voxels"][j].numpy().tobytes()).hexdigest()
            for b in ds for j, sid in enumerate(b["sample_ids"]) if not b["padding"][j]}


def scenario_file_replaced_under_fleet(tmp: Path, layout: Layout) -> dict:
    """Two hosts, each its own copy of one corpus, read as one fleet while a deploy replaces
    :data:`REPLACED` by another clip under its name and restarts each host in turn: host a after
    epoch 0's first batch, host b as epoch 1's pass leaves a out. Each sample read is compared
    with what one server makes of its id under the old and the new file (a sample's bytes are a
    function of seed, epoch, id and file): no pass may hold both versions. Epoch 0 ends on b
    (old); epoch 1's pass fails in one line naming the file and saying to start the epoch over;
    started over, it reads the new plan whole."""
    clips = [REPLACED, "bbb_camera_596x336.mp4", "webvid_like_596x336.mp4"]
    ha, hb = tmp / "a", tmp / "b"
    _deployed(ha, clips)
    _deployed(hb, clips)
    expected = per_epoch(expected_ids(ha, layout), (0, 1))
    log: list = []
    versions: Dict[str, set] = {}  # pass -> versions of REPLACED its samples come from
    with _serve(ha, layout, workers=1) as a, _serve(hb, layout, workers=1) as b:
        ref = {("old", e): _digests(dataset(b.endpoint), e) for e in (0, 1)}
        ds = dataset(f"{a.endpoint},{b.endpoint}", timeout_s=30)

        def read(name: str, after_first: Optional[Callable[[], None]] = None) -> None:
            for n, batch in enumerate(ds):
                log.append((time.monotonic(), real_ids(batch, tag=True)))
                for j, sid in enumerate(batch["sample_ids"]):
                    if sid.startswith(REPLACED + "#") and not batch["padding"][j]:
                        d = hashlib.sha1(batch["voxels"][j].numpy().tobytes()).hexdigest()
                        got = [v for v in ("old", "new") if ref.get((v, batch["epoch"]), {}).get(sid) == d]
                        versions.setdefault(name, set()).update(got or ["neither"])
                if n == 0 and after_first is not None:
                    after_first()

        def b_restarts(line: str) -> None:  # b's turn of the deploy, as epoch 1's pass leaves a out
            if armed and line.startswith(a.endpoint) and "left out of the fleet for this pass" in line and not said:
                said.append(line)
                _restart(b, hb)

        said: List[str] = []
        armed: List[bool] = []
        error: Optional[str] = None
        with _Lines("v2v.client", b_restarts) as lines:
            read("epoch 0", lambda: _restart(a, ha))  # a's turn of the deploy, after epoch 0's first batch
            t_b = time.monotonic()
            ds.set_epoch(1)
            armed.append(True)
            try:
                read("epoch 1, first pass")
            except PlanMismatch as e:
                error = str(e)
            first_pass = [s for _, ids in log for s in ids if s.startswith("1:")]
            log = [(t, ids) for t, ids in log if not any(s.startswith("1:") for s in ids)]
            ref[("new", 1)] = _digests(dataset(b.endpoint), 1)
            t_over = time.monotonic()
            ds.set_epoch(1)
            read("epoch 1, started over")
        rc = (_stop(a), _stop(b))
        clean = _clean(a) and _clean(b)
    switched = [ln for ln in lines.lines if "no host serves the plan read last" in ln]
    mixed = sorted(name for name, v in versions.items() if len(v) != 1)
    return row("a file replaced under a two-host fleet, each host restarted in turn (a deploy), epochs 0 and 1",
               expected, _ids(log), _next_after(log, t_over),
               f"{REPLACED}'s samples by pass: " + "; ".join(f"{k}: {'/'.join(sorted(v))}" for k, v in versions.items())
               + f"; passes mixing two versions: {len(mixed)}; epoch 1's first pass read {len(first_pass)} sample(s) "
               f"and failed: {error or 'no error'}; started over, it read the new plan whole; server exits {rc}",
               versions={k: sorted(v) for k, v in versions.items()}, mixed=mixed, error=error, said=said,
               switched=switched, first_pass=first_pass, t_b=t_b, server_exit=rc, clean=clean)


SCENARIOS = {
    "fleet_first_host_killed": scenario_first_host_killed,
    "fleet_one_host_two_names": scenario_one_host_two_names,
    "fleet_file_replaced": scenario_file_replaced_under_fleet,
}

"""The training loop both engines run (``v2v-train`` on a stream, and on each Ray Train rank):
steps until ``max_steps`` or the end of the batches, one CSV row per step, previews and
checkpoints on their schedule, a summary at the end.

Outputs in the run's folder (the process with ``files=True`` writes them: rank 0 under Ray):
``train_log.csv`` (one row per step, on the disk at every checkpoint; on resume, rows after
the resumed step are dropped), ``samples/step_NNNNNNN.png``, ``summary.json``, TensorBoard
event files (``events.out.tfevents.*``, ``trainer.tensorboard_log``: the CSV's columns, the
data-wait fraction of each logging interval, the previews; on resume, events after the resumed
step are purged); checkpoints are whatever ``checkpoint`` saves.
"""
from __future__ import annotations

import csv
import json
import logging
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, List, Optional

import numpy as np
import torch

from v2v_wire.commands import write_whole

from .tensorboard_log import WAIT_FRACTION_TAG

__all__ = ["Schedule", "RunHooks", "RunLog", "train_loop", "INTERRUPTED_ASK_S", "stream_columns"]

log = logging.getLogger("trainer")

#: Seconds an interrupted run waits for the server's feed figures (``RunHooks.server_feed``): a
#: live server answers in milliseconds, so its figures still reach the ``feed`` line; a silent
#: one (stopped, gone, cut off) costs this, not the stream's ``timeout_s``, before the command's
#: one line (Ctrl-C means now).
INTERRUPTED_ASK_S = 0.5


def stream_columns(batch: dict) -> dict:
    """The ``train_log.csv`` columns of where a batch lies in the stream: ``epoch``, and
    ``sample_in_epoch``, its ``position``'s: the epoch's samples read by every rank up to and
    including this step, where a resume from it goes on (the same on every rank). "" where the
    batch does not say (the Ray engine's batches carry their epoch only). Not a plan batch's
    ``step``: that counts from where its pass began (0 again after a resume, and at another world
    or batch size no step of the epoch), which the position says exactly."""
    position = batch.get("position")
    return {"epoch": batch.get("epoch", ""),
            "sample_in_epoch": position.get("sample_in_epoch", "") if isinstance(position, dict) else ""}


@dataclass
class Schedule:
    """When the loop writes: a preview every ``image_every`` steps and a checkpoint every
    ``checkpoint_every`` steps (0: only at the end); a progress bar on stderr; the losses are
    read from the device every ``log_every`` steps (the rows of the steps between are written
    then, so no other step waits for the device; a preview's or a checkpoint's step reads them
    too); with ``tensorboard``, TensorBoard event files beside the CSV log
    (``trainer.tensorboard_log``)."""

    image_every: int = 500
    checkpoint_every: int = 1000
    progress: bool = True
    log_every: int = 10
    tensorboard: bool = True


@dataclass
class RunHooks:
    """What an engine adds to the loop.

    Attributes:
        on_batch: called with (batch, stats) after each step (the Ray engine records the ids).
        files: this process writes the CSV log, previews and summary (rank 0).
        csv_extra: columns logged besides the task's.
        summary_extra: called after the final checkpoint on every process (it may be a
            collective); returns keys added to the summary.
        final_checkpoint: "if_new" (after the last step unless one was just written) or
            "always" (a collective checkpoint every rank must take part in).
        recipe: called once after the first step: the sample recipe the batches were made
            under (a dict, TensorBoard's ``recipe`` text), or None when the source does not say.
        server_feed: called once at the end (rank 0's files) with the seconds it may wait
            (None: the source's own timeout; :data:`INTERRUPTED_ASK_S` after Ctrl-C or SIGTERM):
            the server's ``feed`` figures (``v2v_client.PlanEpochs.server_feed``) for the
            summary's ``feed`` line (``trainer.feed_report``), or None when the source does not
            report them.
    """

    on_batch: Optional[Callable[[dict, dict], None]] = None
    files: bool = True
    csv_extra: tuple = ()
    summary_extra: Callable[[], dict] = dict
    final_checkpoint: str = "if_new"
    recipe: Callable[[], Optional[dict]] = lambda: None
    server_feed: Callable[[Optional[float]], Optional[dict]] = lambda timeout_s=None: None


class RunLog:
    """``train_log.csv`` of a run: opened at ``step`` (0: a new log; else the rows up to
    ``step`` are kept and later ones dropped, as after a resume), line-buffered so that
    ``tail -f`` works. The kept rows are written to a temporary file, synced and renamed over
    the log before any new row is appended, so a crash while reopening loses none of them;
    :meth:`sync` puts the rows written so far on the disk (the loop calls it with every
    checkpoint, so a resume finds every row up to its checkpoint's step)."""

    def __init__(self, out: Path, columns: List[str], step: int):
        path = Path(out) / "train_log.csv"
        kept = []
        if step and path.exists():
            with open(path, newline="") as f:
                kept = [r for r in csv.DictReader(f) if r.get("step", "").isdigit() and int(r["step"]) <= step]
        tmp = path.with_suffix(".csv.tmp")
        with open(tmp, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=columns, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(kept)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        self.fh = open(path, "a", newline="", buffering=1)
        self.writer = csv.DictWriter(self.fh, fieldnames=columns, extrasaction="ignore")

    def write(self, row: dict) -> None:
        self.writer.writerow(row)

    def sync(self) -> None:
        """Flush the rows written so far and wait until the disk holds them (``os.fsync``)."""
        self.fh.flush()
        os.fsync(self.fh.fileno())

    def close(self) -> None:
        self.sync()
        self.fh.close()


class _RunFiles:
    """What one process writes of a run while it trains: the rows of the steps since the last
    logging step (their losses and terms still on the device) and, with ``files``, the CSV log,
    the previews and the TensorBoard events (``trainer.tensorboard_log``); the progress bar.

    :meth:`flush` reads the pending rows, checks the losses, adds each row's ``samples_per_s``
    (the interval's samples / its wall time) and writes them; the interval's data-wait fraction
    goes to TensorBoard at its last step."""

    def __init__(self, trainer, schedule: Schedule, hooks: RunHooks, max_steps: int):
        columns = trainer.spec.csv_columns() + list(hooks.csv_extra)
        self.columns = columns
        self.run_log = RunLog(trainer.out, columns, trainer.step) if hooks.files else None
        self.board = _open_board(trainer, schedule, hooks)
        self.bar = _progress_bar(max_steps, trainer.step) if schedule.progress else None
        self.recipe = hooks.recipe if self.board is not None else None  # its text is written once
        self.pending: List[dict] = []
        self.losses: List[float] = []  # every finite loss so far, for the summary
        self.t_last = time.perf_counter()  # the end of the last logging interval

    def add(self, trainer, stats: dict) -> None:
        """One step's row; the run's config and recipe go to TensorBoard after the first step
        (a stream's recipe is known once its first batch has come)."""
        self.pending.append(stats)
        if self.recipe is not None:
            self.board.texts(trainer.cfg, self.recipe())
            self.recipe = None

    def flush(self, wait_fraction: float) -> None:
        """Read the pending rows' values from the device (one wait), check and log them.

        Raises:
            FloatingPointError: a non-finite loss of a step that had samples.
        """
        rows = _read_rows(self.pending)
        self.pending.clear()
        if not rows:
            return
        now = time.perf_counter()
        interval, self.t_last = max(now - self.t_last, 1e-9), now
        per_s = sum(int(r.get("samples", 0)) for r in rows) / interval
        for row in rows:
            row["samples_per_s"] = round(per_s, 3)
            if np.isfinite(row["loss"]):
                self.losses.append(row["loss"])
            elif row.get("samples", 1):
                raise FloatingPointError(f"non-finite loss {row['loss']} at step {row['step'] - 1}")
            if self.run_log is not None:
                self.run_log.write(row)
        if self.board is not None:
            self.board.rows(rows, self.columns)
            waited = sum(float(r.get("data_wait_s") or 0.0) for r in rows)
            self.board.scalar(WAIT_FRACTION_TAG, min(1.0, waited / interval), rows[-1]["step"])
        if self.bar is not None:
            self.bar.set_postfix(loss=f"{rows[-1]['loss']:.4f}", wait=f"{wait_fraction:.0%}", refresh=False)
            self.bar.update(len(rows))

    def preview(self, trainer) -> None:
        """The last step's preview: ``samples/step_NNNNNNN.png`` and the TensorBoard image."""
        grid = trainer.preview()
        trainer.save_samples(grid=grid)
        if self.board is not None:
            self.board.preview(grid, trainer.step)

    def sync(self) -> None:
        """The rows and events so far on the disk (before a checkpoint that a resume starts from)."""
        if self.run_log is not None:
            self.run_log.sync()
        if self.board is not None:
            self.board.flush()

    def close_log(self) -> None:
        """Close the CSV log and the bar (the events stay open for the final preview)."""
        try:
            if self.run_log is not None:
                self.run_log.close()
        finally:
            if self.bar is not None:
                self.bar.close()

    def close_board(self) -> None:
        if self.board is not None:
            self.board.close()


def _open_board(trainer, schedule: Schedule, hooks: RunHooks):
    """The run's TensorBoard writer (``trainer.tensorboard_log.RunBoard``), or None: off
    (``schedule.tensorboard``), or this process writes no files, or it is not rank 0 of an
    initialised ``torch.distributed`` group. A resumed trainer's step purges the later events."""
    import torch.distributed as dist

    if not (schedule.tensorboard and hooks.files):
        return None
    if dist.is_available() and dist.is_initialized() and dist.get_rank() != 0:
        return None
    from .tensorboard_log import RunBoard

    return RunBoard(trainer.out, trainer.step)


def _read_rows(rows: List[dict]) -> List[dict]:
    """``rows`` with their tensor values read as floats, all in one copy from the device."""
    keys = [(i, k) for i, r in enumerate(rows) for k, v in r.items() if isinstance(v, torch.Tensor)]
    if not keys:
        return [dict(r) for r in rows]
    values = torch.stack([rows[i][k].float().reshape(()) for i, k in keys]).tolist()
    out = [dict(r) for r in rows]
    for (i, k), v in zip(keys, values):
        out[i][k] = v
    return out


class _Pace:
    """What the loop measures of its feed: the first step (its wait for the batch, its own time:
    start-up) apart from the steps after it (the steady figures of the summary)."""

    def __init__(self):
        self.t_start = time.perf_counter()
        self.first: Optional[dict] = None  # {"first_batch_wait": s, "first_step": s}
        self.t_steady = self.t_start  # the end of the first step
        self.steps = self.samples = self.total = 0  # after the first step; all
        self.wait = self.wait_all = 0.0  # seconds waited for batches after the first step; all

    def step(self, t0: float, t1: float, t2: float, samples: int) -> None:
        self.total += samples
        self.wait_all += t1 - t0
        if self.first is None:
            self.first = {"first_batch_wait": round(t1 - t0, 4), "first_step": round(t2 - t1, 4)}
            self.t_steady = t2
            return
        self.steps += 1
        self.samples += samples
        self.wait += t1 - t0

    def waited(self) -> float:
        """The share of the loop's wall time so far spent waiting for batches (the progress bar's)."""
        return self.wait_all / max(time.perf_counter() - self.t_start, 1e-9)

    def figures(self, t_end: float) -> dict:
        """``steps_per_s``, ``samples_per_s``, ``data_wait_fraction`` and ``model_samples_per_s``
        (the samples over the time the loop did not wait) after the first step (None with fewer
        than two steps), ``samples`` (all), and ``startup_s`` (the first step's wait and time)."""
        el = t_end - self.t_steady
        ok = self.steps > 0 and el > 0
        return {"samples": self.total, "steps_per_s": self.steps / el if ok else None, "samples_per_s": self.samples / el if ok else None,
                "data_wait_fraction": min(1.0, self.wait / el) if ok else None,
                "model_samples_per_s": self.samples / (el - self.wait) if ok and el > self.wait else None,
                "startup_s": dict(self.first or {})}


def _summary(trainer, losses: List[float], n: int, pace: dict, extra: dict) -> dict:
    """task, perceptual_term (the trainer's: an LPIPS backbone, ``trainer.models.lpips.STAND_IN``,
    or None), steps, final_step, first/last loss and the means of the first and last 10 (finite
    losses: a step of padding only has none); ``pace`` (:meth:`_Pace.figures`: samples, and from
    the end of the first step on steps_per_s, samples_per_s, data_wait_fraction, the time blocked
    on the batches over the wall time, and model_samples_per_s, the samples over the time not
    blocked: the model's own rate); startup_s (the loop's ``first_batch_wait`` and ``first_step``,
    compile included, with the engine's phases from ``extra`` and, given ``to_loop``,
    ``to_first_step`` from the command's start); plus the rest of ``extra``
    (``hooks.summary_extra()``)."""
    extra = dict(extra)
    startup = {**pace.pop("startup_s"), **extra.pop("startup_s", {})}  # the engine's phases beside the loop's
    if "to_loop" in startup and "first_step" in startup:
        startup["to_first_step"] = round(startup["to_loop"] + startup["first_batch_wait"] + startup["first_step"], 4)
    pace["startup_s"] = startup
    return {"task": trainer.task, "perceptual_term": getattr(trainer, "perceptual_term", None), "steps": n,
            "final_step": trainer.step,
            "first_loss": losses[0] if losses else None, "last_loss": losses[-1] if losses else None,
            "mean_loss_first10": float(np.mean(losses[:10])) if losses else None,
            "mean_loss_last10": float(np.mean(losses[-10:])) if losses else None, **pace, **extra}


def train_loop(trainer, batches: Iterable, max_steps: int, schedule: Schedule, checkpoint: Callable[[], None],
               hooks: Optional[RunHooks] = None) -> dict:
    """Train ``trainer`` (``trainer.core.Trainer``) on ``batches`` until ``max_steps`` total
    steps, the batches end, or Ctrl-C or SIGTERM (which still checkpoint, then stop the run).

    Returns (and, with ``hooks.files``, writes to ``summary.json``) the summary (:func:`_summary`:
    the losses, the feed figures after the first step, the start-up by phase) and, with
    ``hooks.files``, ``feed``: whether the run was fed and what would feed it (:func:`_feed`).

    Steps run with ``train_step(batch, sync=False)``: their losses stay on the device until
    the next multiple of ``schedule.log_every``, a preview, a checkpoint or the end, where they
    are read at once, checked and written (CSV log; with ``schedule.tensorboard``, TensorBoard
    events: rank 0 only under ``torch.distributed``), synced to the disk before each checkpoint.
    ``step_s`` is the host's time for the step (on CUDA the device's work finishes later, and the
    wait for it shows at the logging steps).

    Raises:
        FloatingPointError: a non-finite loss, found at the logging step after it.
        KeyboardInterrupt: Ctrl-C or SIGTERM (``v2v_wire.commands.Terminated``), raised again
            once the checkpoint and the summary are written, naming the step.
    """
    hooks = hooks or RunHooks()
    files = _RunFiles(trainer, schedule, hooks, max_steps)
    pace = _Pace()
    start_step, every = trainer.step, schedule.checkpoint_every
    it = iter(batches)
    interrupted: Optional[KeyboardInterrupt] = None
    try:
        try:
            while trainer.step < max_steps:
                t0 = time.perf_counter()
                try:
                    batch = next(it)
                except StopIteration:
                    log.info("batches ended at step %d", trainer.step)
                    break
                t1 = time.perf_counter()
                stats = trainer.train_step(batch, sync=False)
                t2 = time.perf_counter()
                pace.step(t0, t1, t2, int(stats.get("samples", 0)))
                if hooks.on_batch is not None:
                    hooks.on_batch(batch, stats)
                stats.update(step=trainer.step, **stream_columns(batch), data_wait_s=round(t1 - t0, 5),
                             step_s=round(t2 - t0, 5))
                files.add(trainer, stats)
                preview = hooks.files and schedule.image_every and trainer.step % schedule.image_every == 0
                # a preview's or checkpoint's step: its rows first (events in step order; the rows up
                # to a checkpoint reach the disk before the checkpoint that a resume starts from)
                if trainer.step % max(1, schedule.log_every) == 0 or preview or (every and trainer.step % every == 0):
                    files.flush(pace.waited())
                if preview:
                    files.preview(trainer)
                if every and trainer.step % every == 0:
                    files.sync()
                    checkpoint()
        except KeyboardInterrupt as e:  # Ctrl-C or SIGTERM (v2v_wire.commands.Terminated): checkpoint, then stop
            interrupted = e
        finally:
            try:
                files.flush(pace.waited())
            finally:
                files.close_log()
        t_end = time.perf_counter()
        n = trainer.step - start_step
        previewed = schedule.image_every and trainer.step % schedule.image_every == 0  # in the loop
        if n and hooks.files and getattr(trainer, "_last", None) is not None and not previewed:
            files.preview(trainer)
        if hooks.final_checkpoint == "always" or (n and (not every or trainer.step % every)):
            checkpoint()
        summary = _summary(trainer, files.losses, n, pace.figures(t_end), hooks.summary_extra())
        if hooks.files:
            _feed(summary, hooks, files.board if n else None, trainer.step, interrupted is not None)
    finally:
        files.close_board()
    if hooks.files:
        write_whole(trainer.out / "summary.json", json.dumps(summary, indent=2))
        log.info("done: %s", json.dumps(summary))
    if interrupted is not None:  # the command says it in one line (v2v_wire.commands), with where it stopped
        raise type(interrupted)(f"stopped at step {trainer.step}" + (f"; checkpoint in {trainer.out}" * hooks.files))
    return summary


def _feed(summary: dict, hooks: RunHooks, board, step: int, interrupted: bool = False) -> None:
    """The summary's ``feed`` line, with the server's figures when it reports them (a server
    that does not answer now is left out: the line then says less, the run is not failed; an
    ``interrupted`` run waits :data:`INTERRUPTED_ASK_S` for them at most): logged, and with the
    feed figures on ``board`` (when not None) at ``step``."""
    from .feed_report import feed_line

    try:
        wait = INTERRUPTED_ASK_S if interrupted else None
        server = hooks.server_feed(wait) if summary.get("data_wait_fraction") else None
    except (TimeoutError, RuntimeError, ValueError) as e:
        log.warning("the server's feed figures: %s", e)
        server = None
    summary["feed"] = feed_line(summary, server)
    log.info("feed: %s", summary["feed"])
    if board is not None:
        board.feed(summary, step)


def _progress_bar(max_steps: int, step: int):
    """The run's tqdm bar on stderr, from ``step`` to ``max_steps``."""
    from tqdm import tqdm

    return tqdm(total=max_steps, initial=step, unit="step", dynamic_ncols=True, file=sys.stderr)

"""A run's TensorBoard event files (``tensorboard --logdir runs/``): the one place that names
their tags, used by ``v2v-train`` on both engines (``trainer.loop``) and by ``v2v-eval``.

Tags (x axis: the optimiser step of ``train_log.csv``'s ``step`` column):

==================================  ===============================================================
tag                                 value
==================================  ===============================================================
``loss/total``                      ``loss`` (the step's total loss)
``loss/<term>``                     each loss term of the task, by its column name (E2VID:
                                    ``l1``, ``perceptual``, ``tc``; EvFlow: ``flow_l1``, ``aee``)
``optim/lr``                        ``lr``, the learning rate of the step
``optim/grad_norm``                 ``grad_norm``, the gradient's total L2 norm before clipping (the
                                    Ray engine: rank 0's, before the ranks' are averaged)
``speed/samples_per_s``             ``samples_per_s``, samples trained per second of wall time over
                                    the logging interval the step belongs to
``speed/data_wait_s``               ``data_wait_s``, seconds the step waited for its batch
``speed/step_s``                    ``step_s``, the host's seconds for the step
``speed/data_wait_fraction``        time waited for batches / wall time over each logging interval
                                    (``log.every`` steps), at the interval's last step: near 0 the
                                    decode hosts keep up, near 1 the GPU waits for them
``feed/samples_per_s``,             at the session's last step: the summary's ``samples_per_s``,
``feed/model_samples_per_s``,       ``model_samples_per_s`` and ``data_wait_fraction`` (from the
``feed/data_wait_fraction``         end of the first step on: ``trainer.loop``)
``feed``                            text, at the session's last step: the summary's ``feed`` line
                                    (fed, or what would feed it: ``trainer.feed_report``)
``stream/epoch``                    ``epoch``
``stream/sample_in_epoch``          ``sample_in_epoch``: the batch's position in its epoch
                                    (``trainer.loop.stream_columns``; the stream engine's)
``stream/samples``                  ``samples`` (the Ray engine's real samples of the step)
``preview``                         the preview image (``samples/step_NNNNNNN.png``): per sample
                                    voxel | prediction | ground truth (flow in the colour wheel)
``config``, ``recipe``              text, once per session at its first step: the run's config
                                    (``config.json``) and the sample recipe (a plan's identity and
                                    the server's stream info, ``v2v_client.PlanEpochs.recipe``, or
                                    the Ray engine's serve config)
``eval/<metric>``                   ``v2v-eval --tensorboard RUN``: the mean of each metric, at the
                                    checkpoint's step; ``eval/<dataset>/<metric>`` per dataset of
                                    ``--protocol v2v-paper``
==================================  ===============================================================

A resumed run opens its writer with ``purge_step`` one past the checkpoint's step: TensorBoard
drops the events of the earlier session after the checkpoint, as ``train_log.csv`` drops its
rows, so no step is shown twice. Only the process that writes the run's files writes events
(rank 0 under DDP and under the Ray engine).
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Dict, Iterable, Optional

import numpy as np

__all__ = ["COLUMN_TAGS", "WAIT_FRACTION_TAG", "PREVIEW_TAG", "column_tag", "eval_scalars", "RunBoard",
           "tensorboard_problem"]

#: ``train_log.csv`` column -> tag; every other column is a loss term, ``loss/<column>``.
COLUMN_TAGS: Dict[str, str] = {
    "loss": "loss/total", "lr": "optim/lr", "grad_norm": "optim/grad_norm",
    "samples_per_s": "speed/samples_per_s", "data_wait_s": "speed/data_wait_s", "step_s": "speed/step_s",
    "epoch": "stream/epoch", "sample_in_epoch": "stream/sample_in_epoch", "samples": "stream/samples",
}
#: Time blocked on the batches / wall time over each logging interval.
WAIT_FRACTION_TAG = "speed/data_wait_fraction"
#: The preview grid of :meth:`trainer.core.Trainer.preview`.
PREVIEW_TAG = "preview"


def column_tag(column: str) -> Optional[str]:
    """The tag of a ``train_log.csv`` column; None for ``step`` (the x axis)."""
    if column == "step":
        return None
    return COLUMN_TAGS.get(column, f"loss/{column}")


def eval_scalars(summary: dict) -> Dict[str, float]:
    """``v2v-eval``'s summary -> ``{tag: value}``: ``eval/<metric>`` for each finite mean in
    ``summary["mean"]`` and ``eval/<dataset>/<metric>`` for each of ``summary["datasets"]`` (the
    paper protocol's table; its ``sequences`` count left out)."""
    out = {f"eval/{k}": v for k, v in (summary.get("mean") or {}).items()}
    for ds, row in (summary.get("datasets") or {}).items():
        out.update({f"eval/{ds}/{k}": v for k, v in row.items() if k != "sequences"})
    return {k: float(v) for k, v in out.items() if isinstance(v, (int, float)) and math.isfinite(v)}


def tensorboard_problem() -> str:
    """Why event files cannot be written here ("" when they can): the ``tensorboard`` package
    that ``torch.utils.tensorboard`` needs is missing."""
    try:
        import torch.utils.tensorboard  # noqa: F401
    except ImportError as e:
        return f"the tensorboard package is missing (pip install 'v2v[trainer]'): {e}"
    return ""


def _number(v) -> Optional[float]:
    """``v`` as a float when it is a number (a CSV cell may be "": no position in an epoch), else None."""
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        return None
    return float(v)


class RunBoard:
    """The event files of one session of a run in ``out`` (``torch.utils.tensorboard``).

    Args:
        out: the run's folder (``v2v-train --out``); its event files go there.
        step: the step the session starts from (0: a new run; the events at and after step 1
            are purged, those of an earlier run in the same folder included; k > 0: a resume
            from a checkpoint at step k, the events after k are purged).
        purge: False for a writer that adds to the run without dropping anything
            (``v2v-eval``).

    Raises:
        ImportError: the tensorboard package is missing (:func:`tensorboard_problem`).
    """

    def __init__(self, out: Path, step: int = 0, purge: bool = True):
        from torch.utils.tensorboard import SummaryWriter

        self.writer = SummaryWriter(log_dir=str(out), purge_step=int(step) + 1 if purge else None)
        self.texts_at = int(step) + 1  # the session's first step

    def rows(self, rows: Iterable[dict], columns: Iterable[str]) -> None:
        """One scalar per column of ``train_log.csv`` (``columns``) of each row, at its
        ``step``; a cell that is not a number (no position in an epoch, a padding-only step's lr) is left out."""
        columns = list(columns)
        for row in rows:
            step = int(row["step"])
            for column in columns:
                tag, v = column_tag(column), _number(row.get(column))
                if tag is not None and v is not None:
                    self.writer.add_scalar(tag, v, step)

    def scalar(self, tag: str, value: float, step: int) -> None:
        """One scalar (a tag of this module's table)."""
        self.writer.add_scalar(tag, float(value), int(step))

    def preview(self, grid_bgr: np.ndarray, step: int) -> None:
        """The preview grid, (H, W, 3) uint8 BGR as ``cv2`` writes it, as the ``preview`` image."""
        self.writer.add_image(PREVIEW_TAG, np.ascontiguousarray(grid_bgr[..., ::-1]), int(step), dataformats="HWC")

    def texts(self, config: dict, recipe: Optional[dict]) -> None:
        """The run's config and sample recipe as text (JSON), at the session's first step."""
        self.writer.add_text("config", _json_block(config), self.texts_at)
        self.writer.add_text("recipe", _json_block(recipe) if recipe else "not reported by the batches' source",
                             self.texts_at)

    def feed(self, summary: dict, step: int) -> None:
        """The run's feed figures and its ``feed`` line (``trainer.loop``'s summary) at ``step``."""
        for key in ("samples_per_s", "model_samples_per_s", "data_wait_fraction"):
            v = _number(summary.get(key))
            if v is not None:
                self.writer.add_scalar(f"feed/{key}", v, int(step))
        self.writer.add_text("feed", str(summary.get("feed", "")), int(step))

    def flush(self) -> None:
        """Put the events written so far into the files (the loop calls it with every checkpoint)."""
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()


def _json_block(d: dict) -> str:
    """``d`` as indented JSON in a markdown code block (TensorBoard renders text as markdown)."""
    text = json.dumps(d, indent=2, default=str)
    return "\n".join("    " + line for line in text.splitlines())

"""The V2V authors' batch layout for stream batches: a drop-in for their training code.

The authors' training loop (HYLZ-2019/V2V ``train.py`` / ``model/train_utils.py``) reads
batches of their ``WebvidDatasetV2`` through torch's ``default_collate``:

* ``frame``: float32 in [0, 1], (B, T, 1, H, W), frame t taken at voxel t's end; with
  ``output_additional_frame`` (their flow-training configs) (B, T + 1, 1, H, W) starting with
  the frame at voxel 0's start.
* ``events``: float32 (B, T, num_bins, H, W) voxel grids (signed event counts per bin).
* ``data_source_idx``: int64 (B,), the index of the source's name in their ``data_sources``.
* ``v2e_params``: dict of float64 (B,) tensors ``pos_thres``, ``neg_thres``, ``base_noise_std``,
  ``hot_pixel_fraction``, ``hot_pixel_std``.
* ``flow`` (their code adds it from RAFT, or from ground truth): float32 (B, T, 2, H, W), flow t
  moving frame t-1 to frame t in pixels (x, y), the stream's ``flow`` with the same index.

:func:`to_reference_layout` maps a ``V2VStreamDataset`` batch (``voxels`` (B, L, nb, H, W),
``frames`` (B, L + 1, 1, H, W) uint8 or float, ``flow``, ``sample_ids``, ``params``,
``padding``, ``epoch``, ``step``, ``position``) onto those keys; the stream's own extras stay
under their names.
"""
from __future__ import annotations

from typing import Optional

import torch

__all__ = ["DATA_SOURCES", "to_reference_layout"]

#: The authors' data source names (``utils/data.py`` ``data_sources``); the index of a name is
#: the ``data_source_idx`` their code logs losses by.
DATA_SOURCES = ("esim", "ijrr", "mvsec", "eccd", "hqf", "unknown", "reds", "sportsslomo", "adobe", "youcook",
                "vimeo", "webvid", "evbird", "evaid", "hs-ergb", "openvid")

_EXTRAS = ("sample_ids", "params", "padding", "epoch", "step", "position")


def _float_frames(frames: torch.Tensor) -> torch.Tensor:
    if frames.dtype == torch.uint8:
        return frames.to(torch.float32) / 255.0
    return frames.to(torch.float32)


def to_reference_layout(batch: dict, additional_frame: bool = False, data_source: str = "webvid") -> dict:
    """A stream batch in the authors' layout (see the module doc).

    Args:
        batch: a ``V2VStreamDataset`` batch (raw or float arrays) with ``voxels`` and, when
            present, ``frames`` and ``flow``.
        additional_frame: keep all L + 1 frames (their ``output_additional_frame``, used to
            train flow); otherwise the L frames at the voxels' ends.
        data_source: name in :data:`DATA_SOURCES` reported as ``data_source_idx`` ("webvid":
            the stream's training videos play the role of their WebVid data).

    Returns:
        New dict: ``events``, ``frame`` (if the batch has frames), ``flow`` (if it has flow),
        ``data_source_idx``, ``v2e_params`` (from each sample's ``params``: thresholds,
        ``noise_std`` as ``base_noise_std``, ``hot_pixel_count / (H * W)`` as
        ``hot_pixel_fraction``, ``hot_pixel_std``), and the extras under their own names.

    Raises:
        ValueError: an unknown ``data_source``, a batch without ``voxels``, or frames that
            are not (B, L + 1, 1, H, W) for voxels (B, L, nb, H, W).
    """
    if data_source not in DATA_SOURCES:
        raise ValueError(f"data_source must be one of {DATA_SOURCES}, got {data_source!r}")
    if "voxels" not in batch:
        raise ValueError("batch has no 'voxels' (ask the stream for outputs including 'voxels')")
    vox = batch["voxels"]
    B, L, _, H, W = vox.shape
    out = {"events": vox.to(torch.float32)}
    frames: Optional[torch.Tensor] = batch.get("frames")
    if frames is not None:
        if tuple(frames.shape) != (B, L + 1, 1, H, W):
            raise ValueError(f"batch 'frames' must be {(B, L + 1, 1, H, W)} for voxels {tuple(vox.shape)}, "
                             f"got {tuple(frames.shape)}")
        f = _float_frames(frames)
        out["frame"] = f if additional_frame else f[:, 1:]
    if batch.get("flow") is not None:
        out["flow"] = batch["flow"].to(torch.float32)
    out["data_source_idx"] = torch.full((B,), DATA_SOURCES.index(data_source), dtype=torch.int64)
    params = list(batch.get("params") or [{}] * B)
    get = lambda key, scale=1.0: torch.tensor([float(p.get(key, float("nan"))) * scale for p in params],  # noqa: E731
                                               dtype=torch.float64)
    out["v2e_params"] = {"pos_thres": get("pos_threshold"), "neg_thres": get("neg_threshold"),
                         "base_noise_std": get("noise_std"), "hot_pixel_fraction": get("hot_pixel_count", 1.0 / (H * W)),
                         "hot_pixel_std": get("hot_pixel_std")}
    for k in _EXTRAS:
        if k in batch:
            out[k] = batch[k]
    return out

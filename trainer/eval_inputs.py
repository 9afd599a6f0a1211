"""``v2v-eval``'s inputs: a video's simulated voxels and frames, an H5 sequence's voxels
with their frames or flows, a real recording's grid edges and frames (the layouts and the flow
convention: ``trainer/evaluate.py``'s docstring), and the network a checkpoint holds."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Tuple

import numpy as np
import torch

from .config import ConfigError
from .recordings import H5Sequence, Recording

__all__ = ["video_sequence", "input_sequence", "RecordingInput", "recording_input", "load_model"]

log = logging.getLogger("trainer.evaluate")


def video_sequence(path: str, num_bins: int, contrast_threshold: float = 0.2, max_frames: int = 0,
                   size: Optional[Tuple[int, int]] = None, seed: int = 0) -> Tuple[np.ndarray, np.ndarray]:
    """Voxels and ground-truth frames of a video, simulated with the V2V core.

    Every voxel spans ``num_bins`` frame pairs (one per bin, as in the stream); the ground
    truth of voxel l is the frame at its end.

    Args:
        path: video file, read like the stream reads it (``v2v_server.frames.decode.iter_luma``:
            full-range, display-oriented luma; uint16 for sources deeper than 8 bits).
        num_bins: B.
        contrast_threshold: c+ = c- (log-intensity units); no noise or hot pixels.
        max_frames: use at most this many frames (0 = all).
        size: (H, W) to resize to with INTER_AREA, or None.
        seed: seed of the initial potential.

    Returns:
        ``(voxels int32 (L, B, H, W), frames uint8 (L+1, H, W))``.
    """
    import cv2

    from v2v_server.simulation.simulate import SensorParams, simulate_voxels
    from v2v_server.luma import to_uint8
    from v2v_server.frames.decode import iter_luma

    out = []
    frames_it = iter_luma(path)  # the stream's reader: full-range, display-oriented luma
    for g in frames_it:
        g = cv2.resize(g, (size[1], size[0]), interpolation=cv2.INTER_AREA) if size is not None else g.copy()
        out.append(g)
        if max_frames and len(out) >= max_frames:
            break
    frames_it.close()
    n = (len(out) - 1) // num_bins * num_bins + 1
    if n < num_bins + 1:
        raise ValueError(f"{path}: too few frames ({len(out)}) for one voxel of {num_bins} bins")
    frames = np.stack(out[:n])
    vox, _ = simulate_voxels(frames, SensorParams(contrast_threshold, contrast_threshold), num_bins,
                             rng=np.random.default_rng(seed))
    return vox, to_uint8(frames[::num_bins])


def input_sequence(kind: str, path: str, recon: bool, nb: int, contrast_threshold: float = 0.2, max_frames: int = 0,
                   size: Optional[Tuple[int, int]] = None):
    """``(voxels, counts or None, frames or None, flows or None)`` of one ``--h5`` / ``--video``
    input: an H5 file's voxels between images (reconstruction) or between flow timestamps
    (flow), a video's simulated voxels and frames (``contrast_threshold``, ``max_frames``, ``size``:
    :func:`video_sequence`'s)."""
    if kind == "h5":
        seq = H5Sequence(path)
        if recon:
            vox, counts = seq.voxels(nb)
            return vox, counts, seq.images, None
        vox, counts, flows = seq.flow_voxels(nb)  # between flow timestamps when present
        return vox, counts, None, flows
    vox, frames = video_sequence(path, nb, contrast_threshold, max_frames, size)
    return vox, None, frames, None


@dataclass(frozen=True)
class RecordingInput:
    """A real recording cut into voxel-grid intervals (``recording_input``).

    Attributes:
        recording: the opened :class:`~trainer.recordings.Recording`.
        edges: int64 (K+1,) grid boundaries, microseconds (absolute, like the events' t).
        frames: uint8 (K+1, H, W) frames at the edges (resized to the sensor), or None.
        binning: how the edges were chosen, in words.
        fps: the grids' rate, per second (an MP4's frame rate).
    """
    recording: Recording
    edges: np.ndarray
    frames: Optional[np.ndarray]
    binning: str
    fps: float


def recording_input(path: str, sensor_size: Optional[Tuple[int, int]] = None, start_s: float = 0.0,
                    end_s: Optional[float] = None, window_ms: float = 50.0, events_per_grid: int = 0) -> RecordingInput:
    """Open a real recording and choose its grid edges: between consecutive frame timestamps
    when it has >= 2 frames in the cut (the paper's HQF/EVAID convention), else grids of
    ``events_per_grid`` events, else fixed ``window_ms`` windows. ``start_s`` / ``end_s``: the
    cut, seconds from the first event.

    Raises:
        RecordingError: the recording cannot be read (``trainer.recordings``).
    """
    from .event_grids import count_edges, window_edges
    from .recordings import open_recording

    rec = open_recording(path, sensor_size)
    t_first = rec.first_t_us()
    start_us = t_first + int(round(start_s * 1e6))
    end_us = None if end_s is None else t_first + int(round(end_s * 1e6))
    fr = rec.frames()
    frames = None
    if fr is not None:
        keep = (fr.t_us >= start_us) & ((fr.t_us <= end_us) if end_us is not None else True)
        if keep.sum() >= 2:
            edges, frames = fr.t_us[keep], fr.images[keep]
            if frames.shape[1:] != (rec.height, rec.width):
                import cv2

                frames = np.stack([cv2.resize(f, (rec.width, rec.height), interpolation=cv2.INTER_AREA)
                                   for f in frames])
            binning = "between consecutive frame timestamps"
            fps = 1e6 / float(np.median(np.diff(edges)))
    if frames is None and events_per_grid:
        edges = count_edges(rec.chunks(start_us, end_us), events_per_grid)
        binning = f"{events_per_grid} events per grid"
        fps = 1e6 / float(np.median(np.diff(edges)))  # >= 2 strictly increasing integer edges
    elif frames is None:
        last = start_us
        for ev in rec.chunks(start_us, end_us):
            last = int(ev["t"][-1])
        window_us = max(1, int(round(window_ms * 1e3)))
        edges = window_edges(start_us, last, window_us)
        binning = f"fixed windows of {window_ms:g} ms"
        fps = 1e3 / window_ms
    return RecordingInput(rec, edges, frames, binning, fps)


def load_model(checkpoint: str, device: torch.device, fmt: Optional[str] = None):
    """Rebuild the network stored in ``checkpoint``: one written by ``v2v-train``, or one of the
    V2V authors' released formats (``trainer.checkpoints``; ``fmt`` names it, e.g. ``"e2vid++"``,
    None detects it from the keys).

    Returns:
        ``(task, model in eval mode, cfg, record)``: ``task`` the trainer task whose metrics
        score the network, ``cfg`` the run's config (the paper's for an authors' checkpoint),
        ``record`` what results record about the weights: ``format`` (``"v2v-train"`` or
        ``"authors:<fmt>"``), ``step`` (the optimiser step of a ``v2v-train`` checkpoint) and
        ``trained_perceptual_term`` (the run's
        ``Trainer.perceptual_term``, ``trainer.models.lpips.STAND_IN`` for a run trained with the
        1 - SSIM stand-in; ``"unrecorded"`` when the checkpoint predates the record, ``"authors'
        release"`` for theirs).

    Raises:
        ConfigError: naming ``checkpoint``, when it is missing or its stored configuration
            does not build a network (an unknown model key, with the allowed ones).
        ValueError: an authors' checkpoint that does not fit its format (naming it).
    """
    from .checkpoints import AUTHORS_FORMATS, is_authors_checkpoint, load_authors_checkpoint
    from .config import default_config
    from .zoo import build_model

    if not Path(checkpoint).is_file():
        raise ConfigError(f"checkpoint not found: {checkpoint}")
    ck = torch.load(checkpoint, map_location=device, weights_only=False)
    if is_authors_checkpoint(ck):
        name, model = load_authors_checkpoint(checkpoint, fmt, device)
        task = AUTHORS_FORMATS[name][3]
        return task, model, default_config(task), {"format": f"authors:{name}",
                                                  "trained_perceptual_term": "authors' release"}
    if fmt is not None:
        raise ValueError(f"{checkpoint}: --model {fmt} names an authors' checkpoint format, but this is a "
                         "v2v-train checkpoint (it names its own network)")
    cfg = ck["config"]
    try:
        model = build_model(ck["task"], dict(cfg["model"]))
    except ConfigError as e:
        raise ConfigError(f"{checkpoint}: {e}") from None
    model = model.to(device)
    model.load_state_dict(ck["model"])
    model.eval()
    return ck["task"], model, cfg, {"format": "v2v-train", "step": int(ck.get("step", 0)),
                                    "trained_perceptual_term": ck.get("perceptual_term", "unrecorded")}

"""``v2v-eval``: evaluate E2VID / EvFlow checkpoints with the metrics the V2V paper reports.

Checkpoints: those ``v2v-train`` writes, or the V2V authors' released ones (``--model`` names
the format, e.g. ``e2vid++`` for their original E2VID++; ``trainer/checkpoints.py``). Every
network sees its input padded to multiples of 16 as the authors' driver pads it
(``trainer.models.pad_input``). Results (JSON and the protocol's markdown table) record the
weights' ``format``, the perceptual term the run trained with (``trained_perceptual_term``:
``trainer.models.lpips.STAND_IN`` when 1 - SSIM stood in for LPIPS) and whether LPIPS was scored
(``lpips_metric``); ``--require-lpips`` refuses to score without LPIPS weights (exit 2).

Inputs:

* H5 sequences in the layout of the V2V reference repo and event_cnn_minimal:
  ``events/xs, ys, ts, ps`` (pixels, seconds, polarity in {0, 1} or {-1, 1}, ``ts``
  non-decreasing), ``images/imageNNNNNNNNN`` (H, W) uint8 with a ``timestamp`` attribute
  (seconds), optional ``flow/flowNNNNNNNNN`` (2, H, W) float32 ground-truth flow in pixels
  with a ``timestamp`` attribute (``flow_ts``); root attribute ``sensor_resolution`` = (H, W)
  if present. MVSEC files converted by the reference's ``scripts/mvsec_to_h5.py`` have
  this layout, with flows at the depth camera's timestamps (not the images') and NaN where
  depth is missing.
* Flow convention (the V2V reference's ``data/testh5.py`` ``TestH5Dataset`` and
  ``model/train_flow_utils.py``): when every flow has a timestamp, the events are binned
  between consecutive *flow* timestamps, and the voxel of ``[flow_ts[k], flow_ts[k+1])`` is
  scored against ``flow[k+1]``, the flow stored at the interval's end (the first flow has
  no interval and is not scored). Without flow timestamps, ``flow[N]`` is read as the
  forward flow from image N to image N+1 and scored against the voxel between them.
  Ground-truth pixels that are NaN in either component or zero in both (no depth) are not
  scored; a flow with no valid pixel gives NaN metrics, which the means skip.
* Real recordings (``--recording``; trainer/recordings.py reads AEDAT4, Prophesee RAW/DAT,
  Event Stream, CSV, this H5 layout and the IJRR/ECD text layout, docs/recordings.md): the
  discrete voxel grids between consecutive frame timestamps when the recording has frames
  (the paper's convention for HQF/EVAID), each reconstruction scored against the frame at its
  interval's end (resized to the sensor size where they differ); else grids over fixed
  ``--window-ms`` windows or of ``--events-per-grid`` events, with no scores. ``--start`` /
  ``--end`` cut in seconds from the first event. ``--write-video DIR`` (always, for recordings
  without frames, under ``--out``) writes the reconstructions as PNGs and an MP4, or a flow
  network's flow colour-coded as an MP4.
* Videos (``--video``), whose voxels are simulated with the V2V core
  (``v2v_server.simulation.simulate.simulate_voxels``), for held-out clips without an event file.

Voxels follow the paper's discrete voxel definition: between consecutive frames at t_i and
t_{i+1}, event k falls in bin ``floor(B * (t_k - t_i) / (t_{i+1} - t_i))`` and the bin
value is N+ - N- (signed event count).

Metrics (per frame, then averaged over all frames of all inputs):

* reconstruction: MSE on [0, 1] images (prediction clipped to [0, 1]); SSIM with
  ``skimage.metrics.structural_similarity(win_size=7, data_range=R)`` where R = 1 by
  default and ``--ssim-data-range 2`` reproduces the convention behind the paper's tables;
  LPIPS (AlexNet, v0.1) when weights are available. The constant-mean-image baseline (every
  prediction = the mean intensity of the sequence's ground-truth frames) is reported alongside.
* flow: AEE (mean end-point error, pixels) and the percentage of pixels with error > 3 px,
  dense (all valid ground-truth pixels) and sparse (valid pixels with at least one event
  in the voxel).
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch

from .config import ConfigError, exit_on_config_error
from .event_grids import events_to_voxels
from .recordings import H5Sequence, RecordingError  # readers live in trainer/recordings.py

__all__ = ["H5Sequence", "events_to_voxels", "video_sequence", "reconstruction_metrics", "flow_metrics",
           "evaluate_e2vid", "evaluate_evflow", "evaluate_eraft", "evaluate_recording", "load_model",
           "build_arg_parser", "main", "LPIPS_NOT_REPORTED"]

log = logging.getLogger("trainer.evaluate")


def video_sequence(path: str, num_bins: int, contrast_threshold: float = 0.2, max_frames: int = 0,
                   size: Optional[Tuple[int, int]] = None, seed: int = 0) -> Tuple[np.ndarray, np.ndarray]:
    """Voxels and ground-truth frames of a video, simulated with the V2V core.

    Every voxel spans ``num_bins`` frame pairs (one per bin, as in the stream); the ground
    truth of voxel l is the frame at its end.

    Args:
        path: video file, read like the stream reads it (``v2v_server.videos.decode.iter_luma``:
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
    from v2v_server.videos.decode import iter_luma, to_uint8

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


def reconstruction_metrics(pred: np.ndarray, gt: np.ndarray, ssim_data_range: float = 1.0) -> Dict[str, float]:
    """MSE and SSIM of one frame. ``pred``, ``gt``: float (H, W) in [0, 1] (pred is
    clipped). SSIM: ``skimage.metrics.structural_similarity(win_size=7, data_range=R)``."""
    from skimage.metrics import structural_similarity

    pred = np.clip(np.asarray(pred, np.float64), 0.0, 1.0)
    gt = np.asarray(gt, np.float64)
    return {"mse": float(np.mean((pred - gt) ** 2)),
            "ssim": float(structural_similarity(pred, gt, win_size=7, data_range=ssim_data_range))}


def flow_metrics(pred: np.ndarray, gt: np.ndarray, event_mask: Optional[np.ndarray] = None,
                 threshold_px: float = 3.0) -> Dict[str, float]:
    """Flow errors of one frame pair.

    Ground-truth pixels that are NaN in either component or zero in both (MVSEC: no depth)
    are not scored, as in the V2V reference (``model/train_flow_utils.py``, mean over valid
    pixels).

    Args:
        pred, gt: float (2, H, W) flow in pixels.
        event_mask: bool (H, W), pixels with at least one event (sparse metrics), or None.
        threshold_px: outlier threshold on the end-point error, pixels.

    Returns:
        ``aee`` (mean end-point error, px) and ``outlier_pct`` (% of pixels with EPE >
        threshold) over the valid pixels (NaN when there is none), ``aee_sparse`` /
        ``outlier_pct_sparse`` over the valid event pixels (NaN when none or no mask), and
        ``valid_pct``, the % of pixels with valid ground truth.
    """
    gt = np.asarray(gt, np.float64)
    valid = ~(np.isnan(gt).any(axis=0) | ((gt[0] == 0) & (gt[1] == 0)))
    epe = np.sqrt(((np.asarray(pred, np.float64) - gt) ** 2).sum(0))
    nan = float("nan")
    out = {"aee": nan, "outlier_pct": nan, "aee_sparse": nan, "outlier_pct_sparse": nan,
           "valid_pct": float(100.0 * valid.mean())}
    if valid.any():
        e = epe[valid]
        out["aee"] = float(e.mean())
        out["outlier_pct"] = float(100.0 * (e > threshold_px).mean())
    if event_mask is not None:
        sparse = valid & np.asarray(event_mask, bool)
        if sparse.any():
            e = epe[sparse]
            out["aee_sparse"] = float(e.mean())
            out["outlier_pct_sparse"] = float(100.0 * (e > threshold_px).mean())
    return out


def load_model(checkpoint: str, device: torch.device, fmt: Optional[str] = None):
    """Rebuild the network stored in ``checkpoint``: one written by ``v2v-train``, or one of the
    V2V authors' released formats (``trainer.checkpoints``; ``fmt`` names it, e.g. ``"e2vid++"``,
    None detects it from the keys).

    Returns:
        ``(task, model in eval mode, cfg, record)``: ``task`` the trainer task whose metrics
        score the network, ``cfg`` the run's config (the paper's for an authors' checkpoint),
        ``record`` what results record about the weights: ``format`` (``"v2v-train"`` or
        ``"authors:<fmt>"``) and ``trained_perceptual_term`` (the run's
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
    return ck["task"], model, cfg, {"format": "v2v-train",
                                    "trained_perceptual_term": ck.get("perceptual_term", "unrecorded")}


def _score(res: Dict[str, List[float]], p: np.ndarray, gt: np.ndarray, mean_img: np.ndarray,
           ssim_data_range: float, lpips_model, device) -> None:
    """Append one reconstruction's scores to ``res``: MSE and SSIM of ``p`` and of the
    constant-mean-image baseline ``mean_img`` against ``gt`` (float32 (H, W) in [0, 1]), and
    their LPIPS when ``lpips_model`` is given."""
    m = reconstruction_metrics(p, gt, ssim_data_range)
    b = reconstruction_metrics(mean_img, gt, ssim_data_range)
    res["mse"].append(m["mse"]); res["ssim"].append(m["ssim"])
    res["base_mse"].append(b["mse"]); res["base_ssim"].append(b["ssim"])
    if lpips_model is not None:
        g = torch.from_numpy(gt)[None, None].to(device)
        res["lpips"].append(float(lpips_model(torch.from_numpy(np.clip(p, 0, 1))[None, None].to(device), g)[0]))
        res["base_lpips"].append(float(lpips_model(torch.from_numpy(mean_img)[None, None].to(device), g)[0]))


@torch.no_grad()
def evaluate_e2vid(model, voxels: np.ndarray, frames: np.ndarray, device: torch.device, ssim_data_range: float = 1.0,
                   lpips_model=None, skip_first: int = 0) -> Dict[str, List[float]]:
    """Run the recurrent model over one sequence (state reset at its start) and score
    voxel l's reconstruction against frame l+1.

    Args:
        voxels: (L, B, H, W) signed counts; frames: uint8 (L+1, H, W).
        skip_first: frames at the start left out of the scores (recurrent warm-up).

    Returns:
        Per-frame lists: ``mse``, ``ssim``, ``lpips`` (if a model is given) and the
        constant-mean-image baseline's ``base_mse``, ``base_ssim``, ``base_lpips``.
    """
    gt_all = frames.astype(np.float32) / 255.0
    mean_img = np.full(gt_all.shape[1:], gt_all[1:].mean(), np.float32)
    res: Dict[str, List[float]] = {k: [] for k in ("mse", "ssim", "base_mse", "base_ssim")}
    if lpips_model is not None:
        res["lpips"], res["base_lpips"] = [], []
    states = None
    preds = []
    for l in range(voxels.shape[0]):
        v = torch.from_numpy(np.ascontiguousarray(voxels[l], dtype=np.float32))[None].to(device)
        pred, states = model(v, states)
        p = pred[0, 0].float().cpu().numpy()
        preds.append(p)
        if l < skip_first:
            continue
        _score(res, p, gt_all[l + 1], mean_img, ssim_data_range, lpips_model, device)
    res["_preds"] = preds  # not a metric; for saving images
    return res


@torch.no_grad()
def evaluate_evflow(model, voxels: np.ndarray, flows: np.ndarray, counts: Optional[np.ndarray],
                    device: torch.device) -> Dict[str, List[float]]:
    """Score flow predictions of each voxel against ``flows`` (L, 2, H, W) pixels;
    ``counts`` (L, H, W) event counts for the sparse metrics (None: the voxel's non-zero
    pixels are used). Returns per-frame lists of :func:`flow_metrics`' keys."""
    res: Dict[str, List[float]] = {}
    for l in range(min(voxels.shape[0], flows.shape[0])):
        v = torch.from_numpy(np.ascontiguousarray(voxels[l], dtype=np.float32))[None].to(device)
        p = model(v)[0].float().cpu().numpy()
        mask = counts[l] > 0 if counts is not None else np.any(voxels[l] != 0, axis=0)
        for k, val in flow_metrics(p, flows[l], mask).items():
            res.setdefault(k, []).append(val)
    return res


@torch.no_grad()
def evaluate_eraft(model, voxels: np.ndarray, flows: np.ndarray, counts: Optional[np.ndarray],
                   device: torch.device, sequence_length: int = 80) -> Dict[str, List[float]]:
    """Score E-RAFT's flow of each voxel against ``flows`` (K, 2, H, W) pixels, as the V2V
    authors' MVSEC test does (``data/testh5.py`` ``TestH5FlowDataset`` with
    ``output_additional_evs``, ``model/train_flow_utils.py`` ``forward_sequence_eraft``):

    * the voxels are cut into chunks of ``sequence_length`` (80); the warm-start flow is reset
      at each chunk's start;
    * voxel k is paired with voxel k-1 (the voxel before the chunk for its first pair; a zero
      grid before voxel 0, their empty event slice) and its flow scored against ``flows[k]``;
    * the sparse metrics' event mask is that of the pair's first voxel: their
      ``compute_metrics`` takes ``events[t]``, which for E-RAFT's L+1 grids is the grid before
      the scored interval (dense metrics do not use it).

    Args:
        voxels: (K, B, H, W) signed counts; counts: (K, H, W) event counts or None (then the
            voxels' non-zero pixels).
        sequence_length: pairs per chunk (their test configs: 80).

    Returns:
        Per-frame lists of :func:`flow_metrics`' keys.
    """
    res: Dict[str, List[float]] = {}
    k_all = min(voxels.shape[0], flows.shape[0])

    def grid(k):
        if k < 0:
            return torch.zeros((1, *voxels.shape[1:]), dtype=torch.float32, device=device)
        return torch.from_numpy(np.ascontiguousarray(voxels[k], dtype=np.float32))[None].to(device)

    for k in range(k_all):
        if k % int(sequence_length) == 0:
            model.reset_states()
        p = model(grid(k - 1), grid(k))[0].float().cpu().numpy()
        if k == 0:
            mask = np.zeros(voxels.shape[2:], bool)
        else:
            mask = counts[k - 1] > 0 if counts is not None else np.any(voxels[k - 1] != 0, axis=0)
        for key, val in flow_metrics(p, flows[k], mask).items():
            res.setdefault(key, []).append(val)
    return res


def _summarise(per_input: Dict[str, Dict[str, List[float]]]) -> dict:
    keys = sorted({k for r in per_input.values() for k in r if not k.startswith("_")})
    allv = {k: [v for r in per_input.values() for v in r.get(k, [])] for k in keys}
    return {
        "mean": {k: float(np.nanmean(v)) if len(v) else None for k, v in allv.items()},
        "frames": max((len(v) for v in allv.values()), default=0),
        "per_input": {name: {k: float(np.nanmean(v)) for k, v in r.items() if not k.startswith("_") and len(v)}
                      for name, r in per_input.items()},
    }


def build_arg_parser() -> argparse.ArgumentParser:
    """The ``v2v-eval`` command line."""
    from .checkpoints import AUTHORS_FORMATS

    p = argparse.ArgumentParser(prog="v2v-eval", description="Evaluate a v2v-train checkpoint (paper metrics).")
    p.add_argument("--checkpoint", help="checkpoint_*.pt written by v2v-train, or an authors' released .pth")
    p.add_argument("--model", choices=list(AUTHORS_FORMATS), help="the network of an authors' checkpoint "
                   "(trainer/checkpoints.py; detected from its keys when left out); e2vid++ is their original "
                   "E2VID++ (FlowNet)")
    p.add_argument("--protocol", choices=["v2v-paper"], help="v2v-paper: the paper's sequences and cuts of IJRR, "
                   "MVSEC, HQF, EVAID under --data-root, SSIM data_range 2, LPIPS-Alex; table per dataset + mean")
    p.add_argument("--data-root", help="--protocol / --select-checkpoint: folder with ijrr/, mvsec/, hqf/, evaid/ "
                   "holding <sequence>.h5 (missing files are named and skipped)")
    p.add_argument("--select-checkpoint", metavar="DIR", help="pick the run's checkpoint with the lowest mean LPIPS "
                   "over HQF and EVAID (the paper's rule); needs --data-root and --lpips-weights")
    p.add_argument("--h5", nargs="*", default=[], help="H5 files in the event_cnn_minimal layout")
    p.add_argument("--video", nargs="*", default=[], help="videos: voxels simulated with the V2V core (E2VID only)")
    p.add_argument("--recording", nargs="*", default=[], help="real recordings, format by extension: .aedat4, "
                   ".raw (EVT 2/2.1/3), .dat, .es, .csv, .h5, or an IJRR/ECD folder (docs/recordings.md)")
    p.add_argument("--sensor-size", type=int, nargs=2, metavar=("W", "H"), help="--recording: sensor size, for "
                   "files whose header does not state it (CSV, some RAW) or to override it")
    p.add_argument("--start", type=float, default=0.0, help="--recording: first second to use, from the first event")
    p.add_argument("--end", type=float, default=None, help="--recording: end of the cut, seconds from the first event")
    p.add_argument("--window-ms", type=float, default=50.0, help="--recording without frames: one voxel grid per "
                   "window of this many milliseconds")
    p.add_argument("--events-per-grid", type=int, default=0, help="--recording without frames: one voxel grid "
                   "per this many events instead of --window-ms windows")
    p.add_argument("--write-video", metavar="DIR", help="--recording: write reconstruction PNGs + MP4 (or a flow "
                   "network's colour-coded flow MP4) under DIR; recordings without frames write them under --out")
    p.add_argument("--contrast-threshold", type=float, default=0.2, help="--video: c+ = c- (log units)")
    p.add_argument("--max-frames", type=int, default=0, help="--video: frames to use (0 = all)")
    p.add_argument("--size", type=int, nargs=2, metavar=("H", "W"), help="--video: resize frames to H W")
    p.add_argument("--ssim-data-range", type=float, default=1.0,
                   help="skimage data_range for SSIM; 2 reproduces the paper tables' convention")
    p.add_argument("--lpips-weights", nargs="*", default=None, help="LPIPS AlexNet weight file(s)")
    p.add_argument("--require-lpips", action="store_true", help="refuse to start (exit 2) when no LPIPS (Alex) "
                   "weights are found, instead of scoring without LPIPS")
    p.add_argument("--skip-first", type=int, default=0, help="E2VID: leave the first N frames out (warm-up)")
    p.add_argument("--device", default="auto")
    p.add_argument("--out", help="write the metrics JSON (and sample PNGs) here")
    p.add_argument("--save-images", type=int, default=0, help="E2VID: save every Nth reconstruction as PNG (beside "
                   "its voxel grid and frame)")
    return p


#: What results record as the LPIPS metric when no LPIPS weights were found.
LPIPS_NOT_REPORTED = "not reported: no LPIPS weights"


def _lpips_metric(args, device):
    """``(LPIPS-Alex module or None, what results record as the LPIPS metric)``.

    Raises:
        LPIPSUnavailable: ``--require-lpips`` and no weights.
    """
    from .models.lpips import LPIPSUnavailable, load_lpips

    lp = load_lpips("alex", args.lpips_weights)
    if lp is None:
        if args.require_lpips:
            raise LPIPSUnavailable("--require-lpips: no LPIPS (Alex) weights found (give --lpips-weights or install "
                                   "the lpips package); not scoring without LPIPS")
        log.warning("LPIPS (Alex) weights not found: LPIPS is not reported")
        return None, LPIPS_NOT_REPORTED
    return lp.to(device), "lpips-alex"


def _provenance(record: dict, lpips_metric: str) -> str:
    """The line a markdown result carries about how it was scored and what was trained with."""
    return (f"LPIPS metric: {lpips_metric}; weights: {record['format']}, perceptual term in training: "
            f"{record['trained_perceptual_term']}")


@exit_on_config_error("v2v-eval")
def main(argv=None) -> int:
    p = build_arg_parser()
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    from .core import resolve_device
    from .models.lpips import LPIPSUnavailable

    device = resolve_device(args.device)
    try:
        lp, lpips_metric = _lpips_metric(args, device)
    except LPIPSUnavailable as e:
        log.error("%s", e)
        return 2
    if args.select_checkpoint or args.protocol:
        return _paper_main(p, args, device, lp, lpips_metric)
    if not args.checkpoint:
        p.error("give --checkpoint (or --select-checkpoint DIR)")
    if not args.h5 and not args.video and not args.recording:
        p.error("give --h5, --video and/or --recording inputs")
    if args.recording and not (args.out or args.write_video):
        p.error("--recording needs --out or --write-video (recordings without frames are written as video)")
    try:
        task, model, cfg, record = load_model(args.checkpoint, device, args.model)
    except ConfigError:
        raise  # exit_on_config_error: the file and the key, exit 2
    except ValueError as e:
        p.error(str(e))
    from .tasks import get_task

    recon = "frames" in get_task(task).outputs  # e2vid, hypere2vid, etnet: reconstruction metrics
    if not recon and args.video:
        p.error("--video inputs have no ground-truth flow; EvFlow needs --h5 files with a flow group")
    out = Path(args.out) if args.out else None
    if out:
        out.mkdir(parents=True, exist_ok=True)
    nb = int(cfg["model"]["num_bins"])
    per_input = _score_inputs(args, task, model, nb, recon, lp if recon else None, device, out)
    recordings = {}
    for path in args.recording:
        try:
            r, info = _recording_input(args, path, task, model, nb, lp if recon else None, device, out)
        except RecordingError as e:
            log.error("%s", e)
            return 2
        recordings[path] = info
        if info["frames_scored"]:
            per_input[path] = r
    summary = {"checkpoint": args.checkpoint, "task": task, **record,
               "lpips_metric": lpips_metric if recon else None, "ssim_data_range": args.ssim_data_range,
               "skip_first": args.skip_first, **_summarise(per_input)}
    if recordings:
        summary["recordings"] = recordings
    _write_summary(summary, out)
    return 0


def _input_sequence(kind: str, path: str, recon: bool, nb: int, args):
    """``(voxels, counts or None, frames or None, flows or None)`` of one ``--h5`` / ``--video``
    input: an H5 file's voxels between images (reconstruction) or between flow timestamps
    (flow), a video's simulated voxels and frames."""
    if kind == "h5":
        seq = H5Sequence(path)
        if recon:
            vox, counts = seq.voxels(nb)
            return vox, counts, seq.images, None
        vox, counts, flows = seq.flow_voxels(nb)  # between flow timestamps when present
        return vox, counts, None, flows
    vox, frames = video_sequence(path, nb, args.contrast_threshold, args.max_frames,
                                 tuple(args.size) if args.size else None)
    return vox, None, frames, None


def _score_inputs(args, task: str, model, nb: int, recon: bool, lp, device, out: Optional[Path]) -> Dict[str, dict]:
    """Per-frame metrics of every ``--h5`` and ``--video`` input, by path; reconstructions
    saved as PNG every ``--save-images`` frames under ``out``."""
    per_input = {}
    for kind, path in [("h5", x) for x in args.h5] + [("video", x) for x in args.video]:
        vox, counts, frames, flows = _input_sequence(kind, path, recon, nb, args)
        if recon:
            r = evaluate_e2vid(model, vox, frames, device, args.ssim_data_range, lp, args.skip_first)
            if out and args.save_images:
                from .viz import gray_to_u8, save_grid, voxel_to_u8

                preds = r["_preds"]
                for l in range(0, len(preds), args.save_images):
                    save_grid(str(out / f"{Path(path).stem}_{l:05d}.png"),
                              [[voxel_to_u8(vox[l]), gray_to_u8(preds[l]), gray_to_u8(frames[l + 1] / 255.0)]])
        else:
            flow_eval = evaluate_eraft if task == "eraft" else evaluate_evflow
            r = flow_eval(model, vox, flows, counts, device)
        per_input[path] = r
        log.info("%s: %s", path, {k: round(float(np.nanmean(v)), 5) for k, v in r.items() if not k.startswith("_") and len(v)})
    return per_input


class _Mp4Writer:
    """Encode (H, W) uint8 grey or (H, W, 3) uint8 BGR frames as an H.264 MP4 with PyAV, one at a
    time (odd sizes are padded by one pixel: yuv420p needs even ones)."""

    def __init__(self, path: Path, fps: float):
        import av

        self.path, self.fps = path, fps
        self._av, self._c, self._s = av, None, None

    def write(self, img: np.ndarray) -> None:
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        h, w = img.shape[:2]
        img = np.pad(img, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
        if self._c is None:
            from fractions import Fraction

            self._c = self._av.open(str(self.path), "w")
            self._s = self._c.add_stream("libx264", rate=Fraction(self.fps).limit_denominator(1000))
            self._s.width, self._s.height, self._s.pix_fmt = img.shape[1], img.shape[0], "yuv420p"
            self._s.options = {"crf": "18", "preset": "fast"}
        vf = self._av.VideoFrame.from_ndarray(np.ascontiguousarray(img), format="bgr24").reformat(format="yuv420p")
        for pkt in self._s.encode(vf):
            self._c.mux(pkt)

    def close(self) -> None:
        if self._c is not None:
            for pkt in self._s.encode():
                self._c.mux(pkt)
            self._c.close()


@torch.no_grad()
def evaluate_recording(model, task: str, grids, device: torch.device, frames: Optional[np.ndarray] = None,
                       ssim_data_range: float = 1.0, lpips_model=None, skip_first: int = 0,
                       video_dir: Optional[Path] = None, fps: float = 20.0, name: str = "recording",
                       save_every: int = 0, save_dir: Optional[Path] = None) -> Dict[str, List[float]]:
    """Run a network over voxel grids streamed from a real recording, one grid at a time.

    Args:
        model: a reconstruction network (``model(voxel, states) -> (image, states)``), a flow
            network (``model(voxel) -> flow``) or E-RAFT (``task == "eraft"``: pairs of
            consecutive grids, the first paired with a zero grid).
        task: the trainer task name of ``model``.
        grids: iterable of ``(k, voxel int32 (B, H, W), counts)`` (``trainer.event_grids.voxel_grids``).
        frames: uint8 (K+1, H, W) ground truth, frame k+1 ending grid k (reconstruction only),
            or None: nothing scored.
        ssim_data_range, lpips_model, skip_first: as :func:`evaluate_e2vid`.
        video_dir: where to write ``<name>_NNNNN.png`` reconstructions and ``<name>.mp4`` (or
            ``<name>_flow.mp4``, the flow colour-coded by ``trainer.viz.flow_to_bgr``), or None.
        fps: frame rate of the MP4.
        save_every, save_dir: with frames, every ``save_every``-th grid as ``<name>_cmp_NNNNN.png``
            in ``save_dir``: the voxel grid, the reconstruction and the frame side by side.

    Returns:
        Per-frame lists as :func:`evaluate_e2vid` (empty without frames or for flow), plus
        ``_grids``, the number of grids run.
    """
    from .viz import flow_to_bgr

    recon = task not in ("evflow", "eraft")
    res: Dict[str, List[float]] = {k: [] for k in ("mse", "ssim", "base_mse", "base_ssim")}
    if lpips_model is not None and frames is not None:
        res["lpips"], res["base_lpips"] = [], []
    if frames is not None:
        gt_all = frames.astype(np.float32) / 255.0
        mean_img = np.full(gt_all.shape[1:], gt_all[1:].mean(), np.float32)
    writer = None
    if video_dir is not None:
        video_dir.mkdir(parents=True, exist_ok=True)
        writer = _Mp4Writer(video_dir / (f"{name}.mp4" if recon else f"{name}_flow.mp4"), fps)
    if task == "eraft":
        model.reset_states()
    states, prev, n = None, None, 0
    for k, vox, _ in grids:
        v = torch.from_numpy(vox.astype(np.float32))[None].to(device)
        n += 1
        if not recon:
            flow = (model(prev if prev is not None else torch.zeros_like(v), v) if task == "eraft" else model(v))
            prev = v
            if writer is not None:
                writer.write(flow_to_bgr(flow[0].float().cpu().numpy()))
            continue
        pred, states = model(v, states)
        p = pred[0, 0].float().cpu().numpy()
        if writer is not None:
            img = (np.clip(p, 0, 1) * 255 + 0.5).astype(np.uint8)
            import cv2

            cv2.imwrite(str(video_dir / f"{name}_{k:05d}.png"), img)
            writer.write(img)
        if frames is None or k < skip_first or k + 1 >= len(frames):
            continue
        gt = gt_all[k + 1]
        if save_every and save_dir is not None and k % save_every == 0:
            from .viz import gray_to_u8, save_grid, voxel_to_u8

            save_grid(str(save_dir / f"{name}_cmp_{k:05d}.png"), [[voxel_to_u8(vox), gray_to_u8(p), gray_to_u8(gt)]])
        _score(res, p, gt, mean_img, ssim_data_range, lpips_model if "lpips" in res else None, device)
    if writer is not None:
        writer.close()
    res["_grids"] = n
    return res


def _recording_input(args, path: str, task: str, model, nb: int, lp, device, out: Optional[Path]):
    """Score (with frames) and/or write the video of one ``--recording``: ``(per-frame
    results, info)``; info records how the grids were binned. Raises ``RecordingError``."""
    from .event_grids import count_edges, voxel_grids, window_edges
    from .recordings import open_recording

    rec = open_recording(path, tuple(args.sensor_size) if args.sensor_size else None)
    t_first = rec.first_t_us()
    start_us = t_first + int(round(args.start * 1e6))
    end_us = None if args.end is None else t_first + int(round(args.end * 1e6))
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
    if frames is None and args.events_per_grid:
        edges = count_edges(rec.chunks(start_us, end_us), args.events_per_grid)
        binning = f"{args.events_per_grid} events per grid"
        fps = 1e6 / float(np.median(np.diff(edges)))  # >= 2 strictly increasing integer edges
    elif frames is None:
        last = start_us
        for ev in rec.chunks(start_us, end_us):
            last = int(ev["t"][-1])
        window_us = max(1, int(round(args.window_ms * 1e3)))
        edges = window_edges(start_us, last, window_us)
        binning = f"fixed windows of {args.window_ms:g} ms"
        fps = 1e3 / args.window_ms
    recon = task not in ("evflow", "eraft")
    # nothing to score (no frames, or a flow network without ground truth): the video is the output
    video_dir = Path(args.write_video) if args.write_video else (out if frames is None or not recon else None)
    name = Path(path).stem or Path(path).name
    r = evaluate_recording(model, task, voxel_grids(rec.chunks(int(edges[0]), int(edges[-1])), edges, nb,
                                                    rec.height, rec.width),
                           device, frames if recon else None, args.ssim_data_range, lp, args.skip_first,
                           video_dir, fps, name, args.save_images, out)
    info = {"format": rec.format, "sensor_size": [rec.width, rec.height], "size_source": rec.size_source,
            "binning": binning, "grids": r.pop("_grids"), "num_bins": nb, "start_us": int(edges[0]),
            "end_us": int(edges[-1]), "frames_scored": len(r["mse"]), "dropped_backward": rec.dropped_backward,
            "truncated": rec.truncated, "video_dir": str(video_dir) if video_dir else None}
    log.info("%s: %s", path, info)
    return r, info


def _write_summary(summary: dict, out: Optional[Path]) -> None:
    """Print the summary as JSON and write it to ``out/metrics.json`` when ``out`` is given."""
    text = json.dumps(summary, indent=2)
    print(text)
    if out:
        (out / "metrics.json").write_text(text)


def paper_scorer(model, num_bins: int, device: torch.device, lpips_model=None):
    """``score_sequence`` for ``trainer.protocol.evaluate_paper``: loads an H5 file, applies the
    protocol's cut, and scores ``model`` with the paper's conventions (SSIM data_range 2)."""
    from .protocol import cut_sequence

    def score(path, cut, inclusive_end):
        seq = H5Sequence(str(path))
        if cut is not None:
            cut_sequence(seq, cut[0], cut[1], inclusive_end)
        vox, _ = seq.voxels(num_bins)
        return evaluate_e2vid(model, vox, seq.images, device, ssim_data_range=2.0, lpips_model=lpips_model)

    return score


def _paper_main(p: argparse.ArgumentParser, args, device, lp, lpips_metric: str) -> int:
    """``--select-checkpoint`` and ``--protocol v2v-paper`` (trainer/protocol.py); ``lp`` the
    LPIPS-Alex module (None: not reported, ``lpips_metric`` says so in the results)."""
    from .protocol import evaluate_paper, paper_markdown, select_checkpoint
    from .tasks import get_task

    if not args.data_root:
        p.error("--protocol and --select-checkpoint need --data-root")

    def evaluate_checkpoint(ck, datasets):
        try:
            task, model, cfg, record = load_model(str(ck), device, args.model)
        except ValueError as e:
            p.error(str(e))
        if "frames" not in get_task(task).outputs:
            p.error(f"the v2v-paper protocol scores reconstruction; {ck} is a {task!r} checkpoint")
        scorer = paper_scorer(model, int(cfg["model"]["num_bins"]), device, lp)
        return {"task": task, **record, "lpips_metric": lpips_metric, **evaluate_paper(scorer, args.data_root, datasets)}

    out = Path(args.out) if args.out else None
    if out:
        out.mkdir(parents=True, exist_ok=True)
    summary = {}
    ck = args.checkpoint
    if args.select_checkpoint:
        try:
            sel = select_checkpoint(args.select_checkpoint, evaluate_checkpoint)
        except ValueError as e:
            p.error(str(e))
        summary["selection"] = sel
        ck = sel["selected"]
        print(f"selected checkpoint: {ck}")
    if args.protocol:
        if not ck:
            p.error("--protocol needs --checkpoint (or --select-checkpoint DIR)")
        from .protocol import PAPER_DATASETS

        r = evaluate_checkpoint(ck, PAPER_DATASETS)
        summary.update({"checkpoint": ck, "protocol": "v2v-paper", **r})
        name = r["format"].split(":", 1)[1] if r["format"].startswith("authors:") else r["task"]
        table = paper_markdown(r, f"{name} {Path(ck).name}") + "\n\n" + _provenance(r, lpips_metric)
        print(table)
        if out:
            (out / "paper_table.md").write_text(table + "\n")
    _write_summary(summary, out)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

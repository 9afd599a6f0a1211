"""``v2v-eval``: evaluate E2VID / EvFlow checkpoints with the metrics the V2V paper reports.

The command line; the inputs (H5 sequences, videos, recordings, checkpoints) are read by
``trainer/eval_inputs.py`` and scored by ``trainer/eval_metrics.py``.

Checkpoints: those ``v2v-train`` writes, or the V2V authors' released ones (``--model`` names
the format, e.g. ``e2vid++`` for their original E2VID++; ``trainer/checkpoints.py``). Every
network sees its input padded to multiples of 16 as the authors' driver pads it
(``trainer.models.pad_input``). Results (JSON and the protocol's markdown table) record the
weights' ``format``, the perceptual term the run trained with (``trained_perceptual_term``:
``trainer.models.lpips.STAND_IN`` when 1 - SSIM stood in for LPIPS) and whether LPIPS was scored
(``lpips_metric``); ``--require-lpips`` refuses to score without LPIPS weights (exit 2).
``--tensorboard RUN`` adds the means to a training run's TensorBoard event files as
``eval/<metric>`` at the checkpoint's step (``trainer/tensorboard_log.py``).

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
from typing import Dict, Optional

import numpy as np
import torch

from v2v_wire.commands import input_overwritten, writable_problem, write_whole

from .config import ConfigError, exit_on_config_error
from .eval_inputs import input_sequence, load_model, recording_input, video_sequence
from .eval_metrics import (evaluate_e2vid, evaluate_eraft, evaluate_evflow, evaluate_recording, flow_metrics,
                           reconstruction_metrics, summarise)
from .event_grids import events_to_voxels
from .recordings import H5Sequence, RecordingError
from .tensorboard_log import RunBoard, eval_scalars, tensorboard_problem

# the names scripts import from here; each is defined in the module named above
__all__ = ["H5Sequence", "events_to_voxels", "video_sequence", "reconstruction_metrics", "flow_metrics",
           "evaluate_e2vid", "evaluate_evflow", "evaluate_eraft", "evaluate_recording", "load_model",
           "build_arg_parser", "main", "LPIPS_NOT_REPORTED"]

log = logging.getLogger("trainer.evaluate")


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
    p.add_argument("--tensorboard", metavar="RUN", help="a v2v-train run folder (its --out): the metrics' means go "
                   "into its TensorBoard event files as eval/<metric> at the checkpoint's step (0 for an authors' "
                   "checkpoint); tags: trainer/tensorboard_log.py")
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


def output_problem(args) -> str:
    """Why ``--out`` or ``--write-video`` cannot take what ``v2v-eval`` writes, or "": either
    folder, ``metrics.json``, ``paper_table.md`` or a recording's MP4 (``<stem>.mp4``,
    ``<stem>_flow.mp4``) would be one of its inputs, or a folder cannot be made or written.
    Checked before any model is loaded."""
    inputs = [("the checkpoint (--checkpoint)", args.checkpoint), ("--data-root", args.data_root),
              ("--select-checkpoint", args.select_checkpoint),
              *((f"an input (--{kind} {x})", x) for kind in ("h5", "video", "recording") for x in getattr(args, kind)),
              *((f"LPIPS weights (--lpips-weights {x})", x) for x in args.lpips_weights or ())]
    folders = [(flag, Path(d)) for flag, d in (("--out", args.out), ("--write-video", args.write_video)) if d]
    for flag, d in folders:
        written = [d, d / "metrics.json", d / "paper_table.md"]
        written += [d / f"{Path(r).stem or Path(r).name}{tail}.mp4" for r in args.recording for tail in ("", "_flow")]
        for target in written:
            why = input_overwritten(target, inputs)
            if why:
                return f"{flag} {d}: " + (why if target == d else f"its {target.name} {why}")
    for flag, d in folders:
        why = writable_problem(d, folder=True)
        if why:
            return f"{flag} {d}: {why}"
    if args.tensorboard:
        run = Path(args.tensorboard)
        why = ("not a folder (give a v2v-train run's --out)" if not run.is_dir() else writable_problem(run, folder=True)
               or tensorboard_problem())
        if why:
            return f"--tensorboard {run}: {why}"
    return ""


@exit_on_config_error("v2v-eval")
def main(argv=None) -> int:
    p = build_arg_parser()
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    why = output_problem(args)
    if why:
        print(f"v2v-eval: {why}", file=sys.stderr)
        return 2
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
               "skip_first": args.skip_first, **summarise(per_input)}
    if recordings:
        summary["recordings"] = recordings
    _write_summary(summary, out)
    _write_board(args, summary)
    return 0


def _score_inputs(args, task: str, model, nb: int, recon: bool, lp, device, out: Optional[Path]) -> Dict[str, dict]:
    """Per-frame metrics of every ``--h5`` and ``--video`` input, by path; reconstructions
    saved as PNG every ``--save-images`` frames under ``out``."""
    per_input = {}
    for kind, path in [("h5", x) for x in args.h5] + [("video", x) for x in args.video]:
        vox, counts, frames, flows = input_sequence(kind, path, recon, nb, args.contrast_threshold, args.max_frames,
                                                    tuple(args.size) if args.size else None)
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


def _recording_input(args, path: str, task: str, model, nb: int, lp, device, out: Optional[Path]):
    """Score (with frames) and/or write the video of one ``--recording``: ``(per-frame
    results, info)``; info records how the grids were binned. Raises ``RecordingError``."""
    from .event_grids import voxel_grids

    ri = recording_input(path, tuple(args.sensor_size) if args.sensor_size else None, args.start, args.end,
                         args.window_ms, args.events_per_grid)
    rec, edges, frames = ri.recording, ri.edges, ri.frames
    recon = task not in ("evflow", "eraft")
    # nothing to score (no frames, or a flow network without ground truth): the video is the output
    video_dir = Path(args.write_video) if args.write_video else (out if frames is None or not recon else None)
    name = Path(path).stem or Path(path).name
    r = evaluate_recording(model, task, voxel_grids(rec.chunks(int(edges[0]), int(edges[-1])), edges, nb,
                                                    rec.height, rec.width),
                           device, frames if recon else None, args.ssim_data_range, lp, args.skip_first,
                           video_dir, ri.fps, name, args.save_images, out)
    info = {"format": rec.format, "sensor_size": [rec.width, rec.height], "size_source": rec.size_source,
            "binning": ri.binning, "grids": r.pop("_grids"), "num_bins": nb, "start_us": int(edges[0]),
            "end_us": int(edges[-1]), "frames_scored": len(r["mse"]), "dropped_backward": rec.dropped_backward,
            "truncated": rec.truncated, "video_dir": str(video_dir) if video_dir else None}
    log.info("%s: %s", path, info)
    return r, info


def _write_board(args, summary: dict) -> None:
    """With ``--tensorboard RUN``: the summary's metrics (``trainer.tensorboard_log.eval_scalars``)
    into the run's event files at the checkpoint's step (``summary["step"]``; 0 when unknown)."""
    if not args.tensorboard:
        return
    board = RunBoard(Path(args.tensorboard), purge=False)
    try:
        step = int(summary.get("step") or 0)
        for tag, value in eval_scalars(summary).items():
            board.scalar(tag, value, step)
    finally:
        board.close()
    log.info("metrics written to the TensorBoard events of %s at step %d", args.tensorboard, step)


def _write_summary(summary: dict, out: Optional[Path]) -> None:
    """Print the summary as JSON and write it to ``out/metrics.json`` when ``out`` is given."""
    text = json.dumps(summary, indent=2)
    print(text)
    if out:
        write_whole(out / "metrics.json", text)


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
            write_whole(out / "paper_table.md", table + "\n")
    _write_summary(summary, out)
    if args.protocol:
        _write_board(args, summary)
    return 0


if __name__ == "__main__":  # pragma: no cover
    from v2v_wire.commands import main_of_module

    sys.exit(main_of_module("v2v-eval", main))

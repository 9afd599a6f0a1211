"""``v2v-calibrate``: a recipe whose sensor ranges make the stream's statistics match a recording.

    v2v-calibrate --recording tests/data/events/davis346_road.aedat4 --out fitted.yaml
    v2v-calibrate --recording evk4.raw --videos my_clips/ --recipe serve.yaml --out fitted.yaml

A recording with intensity frames (a DAVIS's APS) is fitted from its frames: V2V simulates them
and its events between the same frames are matched (N+, N-, active fraction, per-pixel
correlation). A recording without frames (Prophesee EVT2/EVT3, or ``--fit statistics``) is
fitted by statistics: the corpus's windows (``--videos``, the bundled clips by default), cut as
the recipe cuts them, against the recording on the same grid (one voxel grid's duration): the
net event rate, the active fraction and the rate in still regions (``trainer.grid_stats``).
``trainer.calibrate_fit`` holds both fits and their limits.

Writes ``--out``: the base recipe (``--recipe``, a ``v2v-serve`` YAML; the defaults without it)
with the fitted ``ranges`` and ``nonidealities``, and prints the before and after table. A
fitted recipe matches statistics of the recording; it does not promise a trained model's
accuracy on the camera (docs/calibrate.md). Bad input (an unreadable or unusable recording, a
recording too short, too quiet or without motion, an empty corpus, an ``--out`` that cannot be
written) is one line naming it, and exit status 2, checked before the fit where it can be.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import List, Optional

import numpy as np

from v2v_wire.commands import input_overwritten, writable_problem, write_whole

from trainer.calibrate_fit import (CORPUS_STATS, FRAME_STATS, CalibrationError, FitResult, corpus_windows,
                                   fit_corpus, fit_frames, frame_target, recording_target)

#: Statistic -> (label, format) in the printed table.
LABELS = {"rate_net": ("events / pixel / s, net", ".4g"), "rate_signal": ("events / pixel / s, signal", ".4g"),
          "active_fraction": ("active-pixel fraction", ".4g"), "events_per_active": ("events per active pixel", ".3g"),
          "still_rate": ("isolated events / pixel / s", ".3g"), "polarity_balance": ("polarity balance N+/N", ".3f"),
          "events": ("events", "d"), "n_pos": ("N+", "d"), "n_neg": ("N-", "d"),
          "corr": ("per-pixel correlation", ".3f")}


def table(res: FitResult) -> str:
    """The before and after table of a fit: each statistic, the recording's value, the base
    recipe's and the fitted one's, with the fitted one's ratio to the recording's."""
    keys = FRAME_STATS if res.mode == "frames" else CORPUS_STATS
    head = f"{'statistic':32s} {'recording':>11s} {'base recipe':>12s} {'fitted':>11s} {'fitted/rec':>10s}"
    lines = [head, "-" * len(head)]

    def fmt(v, f):
        if v is None or (isinstance(v, float) and not np.isfinite(v)):
            return "n/a"
        return format(int(v), f) if f == "d" else format(v, f)

    for k in keys:
        label, f = LABELS[k]
        t, b, a = res.target.get(k), res.before.get(k), res.after.get(k)
        ratio = a / t if k != "corr" and t and a is not None and np.isfinite(a) else None
        lines.append(f"{label:32s} {fmt(t, f):>11s} {fmt(b, f):>12s} {fmt(a, f):>11s} "
                     f"{fmt(ratio, '.2f') if ratio is not None else '':>10s}")
    return "\n".join(lines)


def _round(d: dict) -> dict:
    def r(v):
        if isinstance(v, float):
            return float(f"{v:.4g}")
        if isinstance(v, list):
            return [r(x) for x in v]
        return v
    return {k: r(v) for k, v in d.items()}


def fitted_yaml(base: dict, res: FitResult, recording: str, seed: int) -> str:
    """The fitted recipe's YAML: ``base`` (the base file's mapping) with the fit's ``ranges``
    and ``nonidealities`` (4 significant digits), headed by comment lines naming the recording,
    the fit and what it promises."""
    import yaml

    data = dict(base)
    data["ranges"] = _round(res.ranges)
    ni = {k: v for k, v in _round(res.nonidealities).items() if not (k == "threshold_sigma" and v < 1e-3)}
    if ni:
        data["nonidealities"] = ni
    else:
        data.pop("nonidealities", None)
    fitted = ", ".join(f"{k} {v:.4g}" for k, v in res.params.items())
    head = [f"# v2v-calibrate: fitted to {recording} ({'its frames' if res.mode == 'frames' else 'statistics over the corpus'}, "
            f"seed {seed}, {res.evaluations} simulations)", f"# fitted: {fitted}",
            "# matches the recording's event statistics (docs/calibrate.md); it does not promise a trained "
            "model's accuracy on this camera"]
    return "\n".join(head) + "\n" + yaml.safe_dump(data, sort_keys=False)


def check_out(out: Path, recording: str, recipe: Optional[str], videos: str, cfg) -> None:
    """Refuse an ``--out`` before any work: one that is an input (the recording, or a file of a
    recording folder; the base recipe; the corpus, its video list or one of its videos) or that
    cannot be written (a folder, a read-only file, a folder that cannot be made or written).

    Raises:
        CalibrationError: naming ``--out`` and why.
    """
    from v2v_server.sources.shards import ARCHIVES

    if out.is_dir():
        raise CalibrationError(f"--out {out}: is a folder; give the fitted recipe's file name")
    why = input_overwritten(out, [("the recording (--recording)", recording), ("the base recipe (--recipe)", recipe),
                                  ("the corpus (--videos)", videos), ("the corpus's video list", cfg.video_list)],
                            [("inside the recording (--recording)", recording, None),
                             ("a video of the corpus (--videos)", videos, tuple(cfg.video_extensions) + ARCHIVES)])
    why = why or writable_problem(out)
    if why:
        raise CalibrationError(f"--out {out}: {why}")


def _has_frames(path: str) -> bool:
    from trainer.recordings import RecordingError, open_recording

    try:
        return open_recording(path).frames() is not None
    except RecordingError as e:
        raise CalibrationError(f"recording {e}") from None


def run_fit(a, cfg, bar) -> FitResult:
    """The fit ``a`` (parsed arguments) asks for, with ``cfg`` (the base ``ServeConfig``);
    ``bar`` a tqdm bar counting simulations."""
    mode = a.fit
    if mode == "auto":
        mode = "frames" if _has_frames(a.recording) else "statistics"
    if mode == "frames":
        bar.set_description("aligning frames and events")
        target = frame_target(a.recording)
        bar.set_description("fitting from frames")
        return fit_frames(target, cfg.recipe, a.seed, a.evaluations, bar.update)
    _has_frames(a.recording)  # readable, before the corpus is decoded
    bar.set_description("cutting the corpus's windows")
    win = corpus_windows(cfg, a.videos, a.windows, a.seed)
    r = cfg.recipe
    cell_s = r.num_bins * r.frames_per_bin / float(np.median(win.fps))
    bar.set_description("measuring the recording")
    target = recording_target(a.recording, cell_s, r.num_bins)
    bar.set_description("fitting by statistics")
    res = fit_corpus(win, target, r, a.evaluations, bar.update)
    res.notes.append(f"grid: cells of {r.num_bins} bins x {r.frames_per_bin} frame interval(s) = {cell_s:.3g} s; "
                     f"{len(win.seqs)} corpus window(s), {target.cells} recording cells")
    return res


def main(argv: Optional[List[str]] = None) -> int:
    from v2v_server.ops.startup import SAMPLE_VIDEOS

    ap = argparse.ArgumentParser(prog="v2v-calibrate", description=__doc__.splitlines()[0])
    ap.add_argument("--recording", required=True, help="a real recording (any format v2v-eval reads)")
    ap.add_argument("--videos", help="corpus for a fit by statistics (folder, list file or bucket URL; default: --recipe's "
                    "videos, else the bundled clips); its config keys (video_list...) come from --recipe")
    ap.add_argument("--recipe", help="base v2v-serve YAML: kept, with its ranges and nonidealities fitted "
                    "(default: the paper's recipe)")
    ap.add_argument("--out", required=True, help="the fitted recipe's YAML file")
    ap.add_argument("--fit", choices=("auto", "frames", "statistics"), default="auto",
                    help="auto: from frames when the recording has them, else by statistics")
    ap.add_argument("--seed", type=int, default=0, help="seed of the fit's fixed draws (same seed, same fit)")
    ap.add_argument("--evaluations", type=int, default=100, help="most simulations the search makes")
    ap.add_argument("--windows", type=int, default=48, help="fit by statistics: most corpus windows simulated "
                    "(each video's windows as cut in epochs 0 and 1, video by video)")
    a = ap.parse_args(argv)
    if a.evaluations < 10 or a.windows < 1 or a.seed < 0:
        ap.error("--evaluations must be >= 10, --windows >= 1, --seed >= 0")
    from tqdm import tqdm

    from v2v_server.ops.config import load_config
    from v2v_server.settings import load_yaml

    out = Path(a.out)
    try:
        base = load_yaml(a.recipe) if a.recipe else {}
        cfg = load_config(a.recipe)
        a.videos = a.videos or cfg.videos or str(SAMPLE_VIDEOS)
        check_out(out, a.recording, a.recipe, a.videos, cfg)
    except (OSError, ValueError) as e:  # CalibrationError is a ValueError
        print(f"v2v-calibrate: {'' if isinstance(e, CalibrationError) else f'--recipe {a.recipe}: '}{e}",
              file=sys.stderr)
        return 2
    try:
        with tqdm(total=a.evaluations, unit="simulation", leave=False) as bar:
            res = run_fit(a, cfg, bar)
        text = fitted_yaml(base, res, a.recording, a.seed)
        load_config(None, {k: v for k, v in text_mapping(text).items()})  # the fitted recipe validates
        write_whole(out, text)
    except CalibrationError as e:
        print(f"v2v-calibrate: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"v2v-calibrate: --out {out}: cannot be written ({e.strerror or e})", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:  # v2v_wire.commands says it, with this
        raise type(e)(f"nothing written to {out}") from None
    print(table(res))
    for n in res.notes:
        print(n)
    print(f"fitted: {', '.join(f'{k} {v:.4g}' for k, v in res.params.items())}")
    print(f"{res.evaluations} simulations in {res.seconds:.1f} s; wrote {out}")
    return 0


def text_mapping(text: str) -> dict:
    """The mapping of a YAML text (the fitted recipe, before it is written)."""
    import yaml

    return yaml.safe_load(text) or {}


if __name__ == "__main__":
    from v2v_wire.commands import main_of_module

    sys.exit(main_of_module("v2v-calibrate", main))

"""``v2v-calibrate``: a recipe whose sensor ranges make the stream's statistics match a recording.

    v2v-calibrate --recording tests/data/events/davis346_road.aedat4 --out fitted.yaml
    v2v-calibrate --recording evk4.raw --videos my_clips/ --recipe serve.yaml --out fitted.yaml

Two fits (``trainer.calibrate_fit`` holds both and their limits), chosen by :func:`route`:

* **by statistics**, the default when a corpus is named (``--videos``, or the recipe's
  ``videos``) or the recording has no frames: the corpus's windows, cut as the recipe cuts them,
  against the recording on the same grid (one voxel grid's duration): the net event rate, the
  active fraction and the rate in still regions (``trainer.grid_stats``). A recording with
  frames seeds it with the camera fitted from them, printed beside;
* **from frames**, the default without a corpus for a recording with intensity frames (a
  DAVIS's APS): V2V simulates them and its events between the same frames are matched (N+, N-,
  active fraction, per-pixel correlation).

After either, the written recipe is served over the corpus (the bundled clips without one) as
``v2v-serve`` serves it, and the base recipe too, and their same-grid statistics are printed
next to the recording's: what the user will get. After a fit by statistics that stream's net
rate is first brought within 10 % of the recording's (``calibrate_fit.match_served_rate``).

Writes ``--out``: the base recipe (``--recipe``, a ``v2v-serve`` YAML; the defaults without it)
with the fitted ``ranges`` and ``nonidealities``. A fitted recipe matches statistics of the
recording; it does not promise a trained model's accuracy on the camera (docs/calibrate.md). Bad
input (an unreadable or unusable recording: too short, too quiet, without motion, of one
polarity, or one whose fit runs into a bound; an empty corpus; an ``--out`` that is an input or
cannot be written) is one line naming it, and exit status 2, checked before the fit where it can be.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import List, Optional, Tuple

import numpy as np

from v2v_wire.commands import input_overwritten, writable_problem, write_whole

from trainer.calibrate_fit import (CORPUS_STATS, FRAME_STATS, RATE_ROUNDS, SERVED_SAMPLES,
                                   CalibrationError, FitResult, Served, check_bounds, corpus_windows, fit_corpus,
                                   fit_frames, frame_target, match_served_rate, recording_target, served_stream)

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


def route(fit: str, corpus_named: bool, has_frames: bool) -> str:
    """The fit ``--fit`` (``auto``, ``frames``, ``statistics``) runs: ``auto`` fits by statistics
    when a corpus is named (``--videos`` or the recipe's: the stream over it is what the recipe
    is for), else from the recording's frames when it has them, else by statistics over the
    bundled clips."""
    if fit != "auto":
        return fit
    return "statistics" if corpus_named or not has_frames else "frames"


def run_fit(a, cfg, bar, mode: str, has_frames: bool) -> Tuple[FitResult, Optional[FitResult]]:
    """The fit ``mode`` with ``a`` (parsed arguments) and ``cfg`` (the base ``ServeConfig``);
    ``bar`` a tqdm bar counting simulations. Returns ``(fit, sensor)``: by statistics over a
    recording that has frames, ``sensor`` is the camera fitted from them first, which seeds the
    fit and is reported beside it (else None)."""
    sensor = None
    if mode == "frames" or has_frames:
        bar.set_description("aligning frames and events")
        target = frame_target(a.recording)
        bar.set_description("fitting from frames")
        sensor = fit_frames(target, cfg.recipe, a.seed, a.evaluations, bar.update)
        check_bounds(a.recording, sensor.params, ("c_pos", "c_neg"))
        if mode == "frames":
            return sensor, None
    bar.set_description("cutting the corpus's windows")
    win = corpus_windows(cfg, a.videos, a.windows, a.seed)
    r = cfg.recipe
    cell_s = r.num_bins * r.frames_per_bin / float(np.median(win.fps))
    bar.set_description("measuring the recording")
    target = recording_target(a.recording, cell_s, r.num_bins)
    bar.set_description("fitting by statistics")
    res = fit_corpus(win, target, r, a.evaluations, bar.update, sensor.params if sensor else None)
    check_bounds(a.recording, res.params, ("threshold_centre",))
    res.notes.append(f"grid: cells of {r.num_bins} bins x {r.frames_per_bin} frame interval(s) = {cell_s:.3g} s; "
                     f"{len(win.seqs)} corpus window(s), {target.cells} recording cells")
    return res, sensor


def served_check(a, base: dict, cfg, res: FitResult, bar, correct: bool):
    """Serve the written recipe (``base`` with ``res``'s ranges) over the corpus ``a.videos``
    as ``v2v-serve`` would (``calibrate_fit.served_stream``), and the base recipe too; with
    ``correct`` (a fit by statistics) first bring the served net rate to the recording's
    (``calibrate_fit.match_served_rate``), ``res`` updated. Returns ``(text, base stream,
    written stream, recording's grid statistics, factors)``: the recipe's YAML and what each
    stream and the recording give on one grid."""
    from v2v_server.ops.config import load_config

    def config(ranges, ni):
        res.ranges, res.nonidealities = ranges, ni
        text = fitted_yaml(base, res, a.recording, a.seed)
        try:  # the recipe v2v-serve --config would serve, checked by its rules (the kernel's tested ranges)
            return text, load_config(None, text_mapping(text))
        except ValueError as e:
            raise CalibrationError(f"recording {a.recording}: the fitted recipe is refused: {e}") from None

    def serve(ranges, ni):
        bar.set_description("serving the written recipe")
        return served_stream(config(ranges, ni)[1], a.videos, progress=bar.update)

    from trainer.grid_stats import summarise
    from trainer.stream_stats import recording_grid

    bar.reset(total=SERVED_SAMPLES * (2 + (RATE_ROUNDS if correct else 0)))
    bar.set_description("serving the base recipe")
    before = served_stream(cfg, a.videos, progress=bar.update)
    rec = summarise(recording_grid(a.recording, before.cell_s, cfg.recipe.num_bins)["cells"])  # on the same grid
    factors: List[float] = []
    if correct:
        target = rec["rate_net"]["median"]
        res.ranges, res.nonidealities, after, factors = match_served_rate(serve, res.ranges, res.nonidealities, target)
        if factors:
            total = float(np.prod(factors))
            for k in ("threshold_centre", "threshold_sigma"):  # as the range and the spread were scaled
                res.params[k] = res.params[k] * total
            res.notes.append(f"served check: the threshold range x {total:.3g} ({len(factors)} round(s)) brings the "
                             f"served stream's net rate to {after.median('rate_net') / target:.2f} x the recording's")
    else:
        after = serve(res.ranges, res.nonidealities)
    text, _ = config(res.ranges, res.nonidealities)
    return text, before, after, rec, factors


def served_table(rec: dict, before: Served, after: Served) -> str:
    """The same-grid table of what the user gets: each ``grid_stats`` statistic (median over
    the cells) of the recording, of the base recipe's stream and of the written recipe's, with
    each stream's ratio to the recording."""
    head = (f"{'statistic':32s} {'recording':>11s} {'base recipe':>12s} {'written':>11s} {'base/rec':>9s} "
            f"{'written/rec':>11s}")
    lines = [head, "-" * len(head)]
    for k in CORPUS_STATS:
        label, f = LABELS[k]
        t = rec[k].get("median")
        b, w = before.median(k), after.median(k)
        cells = [format(v, f) if v is not None and np.isfinite(v) else "n/a" for v in (t, b, w)]
        ratios = [format(v / t, ".2f") if t and np.isfinite(v) else "" for v in (b, w)]
        lines.append(f"{label:32s} {cells[0]:>11s} {cells[1]:>12s} {cells[2]:>11s} {ratios[0]:>9s} {ratios[1]:>11s}")
    return "\n".join(lines)


def main(argv: Optional[List[str]] = None) -> int:
    from v2v_server.ops.startup import SAMPLE_VIDEOS

    ap = argparse.ArgumentParser(prog="v2v-calibrate", description=__doc__.splitlines()[0])
    ap.add_argument("--recording", required=True, help="a real recording (any format v2v-eval reads)")
    ap.add_argument("--videos", help="the corpus the recipe is for (folder, list file or bucket URL; default: "
                    "--recipe's videos, else the bundled clips); its config keys (video_list...) come from --recipe")
    ap.add_argument("--recipe", help="base v2v-serve YAML: kept, with its ranges and nonidealities fitted "
                    "(default: the paper's recipe)")
    ap.add_argument("--out", required=True, help="the fitted recipe's YAML file")
    ap.add_argument("--fit", choices=("auto", "frames", "statistics"), default="auto",
                    help="auto: by statistics over the corpus when one is named (--videos or the recipe's; a "
                         "recording's frames then seed the fit), else from the recording's frames when it has them, "
                         "else by statistics over the bundled clips")
    ap.add_argument("--seed", type=int, default=0, help="seed of the fit's fixed draws (same seed, same fit)")
    ap.add_argument("--evaluations", type=int, default=100, help="most simulations each search makes")
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
        corpus_named = bool(a.videos or cfg.videos)
        a.videos = a.videos or cfg.videos or str(SAMPLE_VIDEOS)
        check_out(out, a.recording, a.recipe, a.videos, cfg)
    except (OSError, ValueError) as e:  # CalibrationError is a ValueError
        print(f"v2v-calibrate: {'' if isinstance(e, CalibrationError) else f'--recipe {a.recipe}: '}{e}",
              file=sys.stderr)
        return 2
    try:
        has_frames = _has_frames(a.recording)  # readable, before the corpus is decoded
        mode = route(a.fit, corpus_named, has_frames)
        with tqdm(total=a.evaluations * (1 + (mode == "statistics" and has_frames)), unit="simulation",
                  leave=False) as bar:
            res, sensor = run_fit(a, cfg, bar, mode, has_frames)
            text, before, after, rec, _ = served_check(a, base, cfg, res, bar, correct=mode == "statistics")
        write_whole(out, text)
    except CalibrationError as e:
        print(f"v2v-calibrate: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"v2v-calibrate: --out {out}: cannot be written ({e.strerror or e})", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:  # v2v_wire.commands says it, with this
        raise type(e)(f"nothing written to {out}") from None
    _report(a, res, sensor, before, after, rec, corpus_named, out)
    return 0


def _report(a, res: FitResult, sensor: Optional[FitResult], before: Served, after: Served, rec: dict,
            corpus_named: bool, out: Path) -> None:
    """Print the fit's own table, the sensor fitted from frames beside a fit by statistics, and
    the same-grid table of the streams the base and the written recipe serve over the corpus."""
    if sensor is not None:
        print("The camera fitted from the recording's frames (it seeds the fit by statistics below):")
        print(table(sensor))
        print(f"sensor: {', '.join(f'{k} {v:.4g}' for k, v in sensor.params.items())}\n")
    how = "from the recording's frames" if res.mode == "frames" else f"by statistics over {a.videos}"
    print(f"The fit ({how}), as it saw it:")
    print(table(res))
    for n in res.notes:
        print(n)
    print(f"fitted: {', '.join(f'{k} {v:.4g}' for k, v in res.params.items())}\n")
    corpus = a.videos if corpus_named else f"{a.videos} (the bundled clips: no corpus named)"
    print(f"What the stream gets: each recipe served over {corpus} as v2v-serve serves it ({after.samples} samples of "
          f"epochs 0-{after.epochs - 1}, {after.grids} voxel grids of {after.cell_s:.3g} s), medians over one grid "
          f"(trainer/grid_stats.py):")
    print(served_table(rec, before, after))
    if res.mode == "frames":
        print("The recipe is fitted to the camera's own frames" + (
            "; name the corpus it will serve (--videos) for a recipe whose stream over it matches the recording's "
            "statistics." if not corpus_named else " (--fit frames); --fit auto fits it to the stream over the corpus."))
    print(f"{res.evaluations + (sensor.evaluations if sensor else 0)} simulations in "
          f"{res.seconds + (sensor.seconds if sensor else 0):.1f} s; wrote {out}")


def text_mapping(text: str) -> dict:
    """The mapping of a YAML text (the fitted recipe, before it is written)."""
    import yaml

    return yaml.safe_load(text) or {}


if __name__ == "__main__":
    from v2v_wire.commands import main_of_module

    sys.exit(main_of_module("v2v-calibrate", main))

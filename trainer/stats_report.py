"""``v2v-stats``: what a stream's samples look like, next to a real camera, as an HTML page.

    v2v-stats --videos v2v_server/sample_videos --recording tests/data/events/davis346_road.aedat4 --out report/
    v2v-stats --server tcp://host:5555 --samples 500 --out report/

Reads ``--samples`` N samples' params from a running server (``--server``), or simulates them
from a corpus (``--videos``: folder, list or bucket, with ``--config``'s recipe, as ``v2v-serve``
would make them in epoch 0), with a progress bar, and writes ``OUT/index.html`` with PNG figures
beside it and ``OUT/stats.json`` (every row and summary): distributions of events per pixel per
second (per sample and per voxel grid), active-pixel fraction, thresholds, noise and flow
magnitude; windows per video and shot lengths; a table of the videos' resolutions and codecs
(corpus only: a server's params name the video, not its format). ``--recording FILE`` (any
format ``v2v-eval`` reads) overlays the same statistics measured on the recording in windows of
the samples' duration and of one voxel grid's; a recording shorter than a window is named and
left out of that overlay. The page opens with every event statistic on one grid for both sides
(``trainer.grid_stats``: the stream's voxel grids, the recording in cells of one voxel grid's
duration and bins; the grid is stated). Bad input (an unreachable server, an empty corpus, an
unreadable recording, an ``--out`` that is a file or cannot be made, checked before any sampling)
is one line naming it, and exit status 2.
"""
from __future__ import annotations

import argparse
import html
import io
import json
import sys
from pathlib import Path
from typing import List, Optional

import numpy as np

from v2v_server.frames.motion import STATIC_MOTION
from v2v_wire.commands import input_overwritten, writable_problem, write_whole

from trainer.grid_stats import GRID_STATS, summarise
from trainer.stream_stats import (Collected, StatsInputError, check_recording, from_corpus, from_server, grid_seconds,
                                  recording_grid, recording_windows, summary)

#: (row key, label) of the per-sample statistics shown and summarised.
STATS = (("rate", "events / pixel / s (both polarities)"), ("rate_pos", "positive events / pixel / s"),
         ("rate_neg", "negative events / pixel / s"), ("active_fraction", "fraction of pixels with an event"),
         ("flow_mag", "mean flow magnitude, px / frame"), ("pos_threshold", "c+ (log intensity)"),
         ("neg_threshold", "c- (log intensity)"), ("noise_std", "noise sigma (log intensity / frame pair)"),
         ("motion", "window motion (log intensity change / frame pair)"))


def _values(rows: List[dict], key: str) -> List[float]:
    if key == "rate":
        return [r["rate_pos"] + r["rate_neg"] for r in rows if "rate_pos" in r]
    return [float(r[key]) for r in rows if isinstance(r.get(key), (int, float))]


def _hist(ax, series, log=False) -> None:
    """Density histograms of each ``(values, label)`` in ``series`` on shared bins (log-spaced
    with ``log``, zeros left out there)."""
    arrays = [np.asarray(v, dtype=np.float64) for v, _ in series]
    arrays = [a[np.isfinite(a)] for a in arrays]
    if log:
        arrays = [a[a > 0] for a in arrays]
        ax.set_xscale("log")
    allv = np.concatenate(arrays) if arrays else np.empty(0)
    if not allv.size:
        return
    lo, hi = allv.min(), allv.max()
    if log:
        bins = np.logspace(np.log10(lo) - 0.05, np.log10(hi) + 0.05, 40)
    else:
        bins = np.linspace(lo, hi if hi > lo else lo + 1e-3, 40)
    for a, (_, label) in zip(arrays, series):
        if a.size:
            ax.hist(a, bins=bins, label=label, density=True, alpha=0.6)
    ax.legend(fontsize=8)


def name_label(name: str) -> str:
    """A corpus name as a figure label, drawn as written: ``$`` escaped (matplotlib reads text
    between two ``$`` as mathtext: ``price_$5_$10.mp4`` would be parsed as a formula and fail)
    and control characters (a newline, a tab) shown as their escapes, so one name stays one line."""
    text = "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in name)
    return text.replace("$", r"\$")


def figures(col: Collected, rec: Optional[dict], out: Path) -> List[str]:
    """Write the report's PNG figures into ``out``; returns their file names. Names are drawn
    through :func:`name_label`; a glyph the font lacks (a name in a script DejaVu does not
    cover) is drawn as a box without a warning."""
    import warnings

    import matplotlib

    matplotlib.use("Agg")
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"Glyph \d+ .* missing from", category=UserWarning)
        return _figures(col, rec, out)


def _grid_figure(plt, col: Collected, rec: Optional[dict], save) -> None:
    """One panel per statistic of ``grid_stats.GRID_STATS``: the stream's voxel grids against
    the recording's cells of the same duration."""
    cells = [c for r in col.rows for c in r.get("cells", [])]
    rcells = (rec or {}).get("cells", {}).get("cells", [])
    if not cells:
        return
    fig, axes = plt.subplots(2, 3, figsize=(15, 7))
    for ax, (key, label, _) in zip(axes.ravel(), GRID_STATS):
        log = key in ("rate_signal", "rate_net", "still_rate", "events_per_active", "active_fraction")
        _hist(ax, [([c[key] for c in cells], "stream, per voxel grid"),
                   ([c[key] for c in rcells], "recording, per cell of the same duration")], log=log)
        ax.set_title(label, fontsize=9)
    save(fig, "grid.png")


def _figures(col: Collected, rec: Optional[dict], out: Path) -> List[str]:
    import matplotlib.pyplot as plt

    names = []

    def save(fig, name):
        fig.tight_layout()
        png = io.BytesIO()
        fig.savefig(png, format="png", dpi=90)
        plt.close(fig)
        write_whole(out / name, png.getvalue())
        names.append(name)

    _grid_figure(plt, col, rec, save)
    rows = col.rows
    wins = (rec or {}).get("sample", {}).get("windows", [])
    gwins = (rec or {}).get("grid", {}).get("windows", [])
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    rate = lambda ws: [w["rate_pos"] + w["rate_neg"] for w in ws]  # noqa: E731
    _hist(axes[0], [(_values(rows, "rate"), "simulated samples"), (rate(wins), "recording, same duration")], log=True)
    axes[0].set_title("events / pixel / s per sample")
    _hist(axes[1], [([g for r in rows for g in r.get("grid_rates", [])], "simulated voxel grids"),
                    (rate(gwins), "recording, one grid's duration")], log=True)
    axes[1].set_title("events / pixel / s per voxel grid")
    _hist(axes[2], [(_values(rows, "active_fraction"), "simulated samples"),
                    ([w["active_fraction"] for w in wins], "recording, same duration")])
    axes[2].set_title("fraction of pixels with at least one event")
    save(fig, "events.png")
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    _hist(axes[0], [(_values(rows, "pos_threshold"), "c+"), (_values(rows, "neg_threshold"), "c-")])
    axes[0].set_title("contrast thresholds drawn (log intensity)")
    _hist(axes[1], [(_values(rows, "noise_std"), "noise sigma")])
    axes[1].set_title("background-noise sigma drawn")
    _hist(axes[2], [(_values(rows, "flow_mag"), "flow")])
    axes[2].set_title("mean optical-flow magnitude, px / frame")
    save(fig, "params.png")
    if col.videos:
        fig, axes = plt.subplots(1, 2, figsize=(12, 4))
        vids = col.videos
        axes[0].barh(range(len(vids)), [v["windows"] for v in vids], color="tab:blue")
        axes[0].set_yticks(range(len(vids)), [name_label(v["path"]) for v in vids], fontsize=7)
        axes[0].set_title("windows per video")
        axes[1].hist([s for v in vids for s in _whole_shots(v)], bins=30, color="tab:green")
        axes[1].set_title("shot lengths, frames (shots read whole)")
        save(fig, "videos.png")
    return names


def _whole_shots(video: dict) -> List[int]:
    """The lengths of ``video``'s shots read whole: the last one is left out when the check
    stopped decoding before the end (``lower_bound``), its length being only a lower bound."""
    lengths = video["shot_lengths"]
    return lengths[:-1] if video.get("lower_bound") else lengths


def _table(header, rows) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _grid_section(grid: Optional[dict]) -> str:
    """The page's same-grid table: each ``grid_stats`` statistic of the stream's voxel grids and
    of the recording's cells, median and p10 - p90, under a line stating the grid."""
    if not grid:
        return ""
    def cell(s):
        if not s.get("n"):
            return "n/a"
        return f"{s['median']:.4g} ({s['p10']:.3g} - {s['p90']:.3g})"

    rec = grid.get("recording")
    head = ("statistic", "stream: median (p10 - p90)") + (("recording: median (p10 - p90)",) if rec else ())
    rows = [(label, cell(grid["stream"][k]), *((cell(rec[k]),) if rec else ())) for k, label, _ in GRID_STATS]
    stated = (f"Grid: one voxel grid, {grid['bins']} bins x {grid['frames_per_bin']} frame interval(s) = "
              f"{grid['cell_s']:.3g} s at the samples' median {grid['fps']:.3g} fps; {grid['stream']['rate_net'].get('n', 0)} "
              "voxel grids of the stream")
    if rec:
        stated += (f", {rec['rate_net'].get('n', 0)} cells of {grid['cell_s']:.3g} s ({grid['bins']} bins each) of the "
                   "recording from its first event")
    return (f"<h2>Same grid: stream and recording</h2><p class='grid'>{html.escape(stated)}. Isolated events: an event "
            "whose pixel has no firing neighbour in the cell (noise in still regions).</p>"
            + _table(head, rows))


def page(col: Collected, rec: Optional[dict], notes: List[str], pngs: List[str], summ: dict) -> str:
    """The report's HTML (figures by file name, a summary table, the videos' table, notes)."""
    fmt = lambda v: f"{v:.4g}" if isinstance(v, float) else v  # noqa: E731
    more = lambda v: "+" if v.get("lower_bound") else ""  # noqa: E731
    parts = [f"<h1>v2v-stats</h1><p>{len(col.rows)} samples from {html.escape(col.source)}</p>"]
    parts += [f'<p class="note">{html.escape(n)}</p>' for n in notes]
    srows = [(label, *(fmt(summ["samples"][k].get(q, "")) for q in ("n", "mean", "p10", "p50", "p90")))
             for k, label in STATS]
    for scope in ("sample", "grid"):
        for k in ("rate", "active_fraction"):
            s = summ.get("recording", {}).get(scope, {}).get(k)
            if s and s.get("n"):
                srows.append((f"recording, {scope} windows: {dict(STATS)[k]}",
                              *(fmt(s.get(q, "")) for q in ("n", "mean", "p10", "p50", "p90"))))
    parts.append(_grid_section(summ.get("grid")))
    parts.append("<h2>Per sample</h2>" + _table(("statistic", "n", "mean", "p10", "median", "p90"), srows))
    st = summ["static_windows"]
    parts.append(f"<p>Static windows (motion below {st['threshold']} log intensity a frame pair; "
                 f"<code>static_windows: skip</code> serves none): {st['count']} of {st['of']} samples</p>")
    parts += [f'<h2>{html.escape(p[:-4])}</h2><img src="{p}" alt="{p[:-4]}">' for p in pngs]
    if col.videos:
        parts.append("<h2>Videos</h2>" + _table(
            ("video", "resolution", "codec", "fps", "frames", "windows", "shots", "not usable because"),
            [(v["path"], f"{v['width']}x{v['height']}" if v["width"] else "?", v["codec"], f"{v['fps']:.3g}",
              f"{v['frames']}{more(v)}", v["windows"], f"{len(v['shot_lengths'])}{more(v)}", v["reason"])
             for v in col.videos]))
        if any(v.get("lower_bound") for v in col.videos):
            parts.append("<p>N+: the check stops decoding a video once the recipe's windows are complete "
                         "(max_samples_per_video), so it read N frames and shots and the video may hold more.</p>")
    style = ("body{font-family:sans-serif;margin:2em;max-width:1400px}table{border-collapse:collapse}"
             "td,th{border:1px solid #aaa;padding:2px 8px;text-align:right}img{max-width:100%}.note{color:#a40}")
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>v2v-stats</title><style>{style}</style>"
            f"</head><body>{''.join(parts)}<p>Numbers: <a href='stats.json'>stats.json</a></p></body></html>")


def _recording(path: str, rows: List[dict], cfg_recipe, notes: List[str]) -> Optional[dict]:
    """The recording measured in windows of one sample's and one voxel grid's duration (at the
    samples' median frame rate), and on the grid (``cells``: ``stream_stats.recording_grid``,
    cells of one voxel grid's duration and bins); notes say which durations it is shorter than."""
    fps = float(np.median(_values(rows, "video_fps"))) if rows else 25.0
    grid_s = cfg_recipe.num_bins * cfg_recipe.frames_per_bin / fps
    out: dict = {}
    for scope, seconds in (("sample", grid_s * cfg_recipe.sequence_length), ("grid", grid_s)):
        r = recording_windows(path, seconds)
        if not r["windows"]:
            notes.append(f"recording {path} ({r['duration_s']:.3g} s) is shorter than one {scope} window "
                         f"({seconds:.3g} s): no {scope}-level overlay")
        out[scope] = r
    if out["sample"]["truncated"]:
        notes.append(f"recording {path} is truncated (it ends inside a packet or word): the events before the cut "
                     "are measured")
    out["cells"] = recording_grid(path, grid_s, cfg_recipe.num_bins)
    return out


#: The files the report writes in ``--out`` (its figures are among PNG_NAMES).
REPORT_FILES = ("index.html", "stats.json")
PNG_NAMES = ("grid.png", "events.png", "params.png", "videos.png")


def out_problem(out: Path, inputs) -> str:
    """Why ``--out`` cannot take the report (made here when missing), or "" when it can:
    checked before any sampling. ``inputs``: ``(what, path)`` of what the command reads (the
    recording, the recipe, the corpus); neither ``--out`` nor a file the report writes there
    may be one of them."""
    for target in (out, *(out / name for name in REPORT_FILES + PNG_NAMES)):
        why = input_overwritten(target, inputs)
        if why:
            return why if target == out else f"its {target.name} {why}"
    return writable_problem(out, folder=True)


def grid_summary(rows: List[dict], rec: Optional[dict], recipe) -> dict:
    """The same-grid summary: ``grid_stats.summarise`` of the stream's voxel grids
    (``stream``) and of the recording's cells (``recording``, when one is given), with the grid
    (``bins``, ``frames_per_bin``, ``fps``: the samples' median, ``cell_s``)."""
    fps = float(np.median(_values(rows, "video_fps"))) if rows else 25.0
    out = {"bins": recipe.num_bins, "frames_per_bin": recipe.frames_per_bin, "fps": fps,
           "cell_s": grid_seconds(recipe, fps), "stream": summarise([c for r in rows for c in r.get("cells", [])])}
    if rec and "cells" in rec:
        out["recording"] = summarise(rec["cells"]["cells"])
    return out


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="v2v-stats", description=__doc__.splitlines()[0])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--server", help="read samples from the server at this endpoint (tcp://host:port)")
    src.add_argument("--videos", help="simulate samples from this corpus (folder, list file or bucket URL)")
    ap.add_argument("--config", help="v2v-serve YAML: the recipe used with --videos (default: the paper's)")
    ap.add_argument("--samples", type=int, default=200, help="samples to read or simulate (N)")
    ap.add_argument("--epochs", type=int, default=1, help="--videos: epochs to simulate (each draws new sensor "
                    "parameters for the same windows) until --samples are made")
    ap.add_argument("--recording", help="a real recording to overlay (any format v2v-eval reads)")
    ap.add_argument("--timeout", type=float, default=30.0, help="--server: seconds without a batch before giving up")
    ap.add_argument("--out", required=True, help="folder for index.html, its PNGs and stats.json")
    a = ap.parse_args(argv)
    if a.samples < 1 or a.epochs < 1:
        ap.error("--samples and --epochs must be >= 1")
    from tqdm import tqdm

    from v2v_server.ops.config import load_config

    try:
        cfg = load_config(a.config)
    except (OSError, ValueError) as e:
        print(f"v2v-stats: config {a.config}: {e}", file=sys.stderr)
        return 2
    out = Path(a.out)
    why = out_problem(out, [("the recording (--recording)", a.recording), ("the recipe (--config)", a.config),
                            ("the corpus (--videos)", a.videos), ("the corpus's video list", cfg.video_list)])
    if why:
        print(f"v2v-stats: --out {out}: {why}", file=sys.stderr)
        return 2
    notes: List[str] = []
    try:
        if a.recording:
            check_recording(a.recording)
        with tqdm(total=a.samples, unit="sample", desc="sampling", leave=False) as bar:
            col = (from_server(a.server, a.samples, a.timeout, bar.update, cfg.recipe) if a.server
                   else from_corpus(cfg, a.videos, a.samples, bar.update, a.epochs))
        if not col.rows:
            raise StatsInputError(f"{col.source}: gave no sample")
        rec = _recording(a.recording, col.rows, cfg.recipe, notes) if a.recording else None
    except StatsInputError as e:
        print(f"v2v-stats: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:  # v2v_wire.commands says it, with this
        raise type(e)(f"nothing written to {out}") from None
    if len(col.rows) < a.samples:
        notes.append(f"{col.source} gave {len(col.rows)} of the {a.samples} samples asked for")
    summ = {"samples": {k: summary(_values(col.rows, k)) for k, _ in STATS}}
    summ["samples"]["grid_rate"] = summary(g for r in col.rows for g in r.get("grid_rates", []))
    motions = _values(col.rows, "motion")
    summ["static_windows"] = {"threshold": STATIC_MOTION, "count": sum(m < STATIC_MOTION for m in motions),
                              "of": len(motions)}
    if rec:
        summ["recording"] = {s: {"rate": summary(w["rate_pos"] + w["rate_neg"] for w in rec[s]["windows"]),
                                 "active_fraction": summary(w["active_fraction"] for w in rec[s]["windows"])}
                             for s in ("sample", "grid")}
    summ["grid"] = grid_summary(col.rows, rec, cfg.recipe)
    pngs = figures(col, rec, out)
    write_whole(out / "stats.json", json.dumps({"source": col.source, "notes": notes, "summary": summ,
                                                "samples": col.rows, "videos": col.videos, "recording": rec},
                                               indent=1))
    write_whole(out / "index.html", page(col, rec, notes, pngs, summ))
    for n in notes:
        print(f"v2v-stats: {n}", file=sys.stderr)
    print(f"v2v-stats: wrote {out / 'index.html'} ({len(col.rows)} samples)")
    return 0


if __name__ == "__main__":
    from v2v_wire.commands import main_of_module

    sys.exit(main_of_module("v2v-stats", main))

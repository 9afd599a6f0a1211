"""Fitting a recipe's sensor parameters to a real recording (the core of ``v2v-calibrate``).

Two fits, both with ``scipy.optimize.minimize`` (Nelder-Mead, bounded) on an objective made
deterministic by common random numbers: every draw a simulation needs (initial potentials,
noise seeds, pixel mismatch, the uniform variates that pick parameters inside the ranges) is
fixed by ``seed`` before the search, so a parameter vector always scores the same and a fit is
repeatable (same inputs, same seed, same recipe: the same fitted values).

* :func:`fit_frames`, for a recording with intensity frames (a DAVIS's APS): V2V simulates the
  recording's own frames and is compared with its events between the same frame timestamps
  (:func:`frame_target`, one frame interval per cell): total N+ and N-, the active fraction of
  the cells and the per-pixel Pearson correlation of the signed counts (the measures of
  ``bench/real_sensor.py``). Parameters: c+, c-, the per-pixel threshold spread
  (``nonidealities.threshold_sigma``), the background noise sigma and the spread of the initial
  potential (a fraction of the paper's U[-c-, c+]; the recorded pixels start at their own
  reference levels, the stream's windows mid-scene as in the paper).
* :func:`fit_corpus`, for a recording without frames (Prophesee EVT2/EVT3, or any): the
  statistics of ``trainer.grid_stats`` on the same grid (one voxel grid's duration), the
  corpus's windows simulated with candidate ranges against the recording's cells: the median
  net rate, the median active fraction and the median rate in still regions. Parameters: the
  threshold range's centre (the range is +-25 % around it, the ratio range the base recipe's),
  the noise sigma's upper bound, the threshold spread and the shot-noise rate.

Every fitted value lies inside :data:`BOUNDS`, the ranges the kernel is tested at
(``tests/test_stability.py``: thresholds 1e-3 .. 10 log units, noise sigma 0 .. 10; the
non-idealities' tests in ``tests/test_nonideal.py``), narrowed where a wider value would be no
camera (a threshold spread above a quarter of the threshold, shot noise above 10 Hz per pixel); a
threshold range's centre stays <= 8 so its upper end (+25 %) stays inside the tested 10.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np

from trainer.grid_stats import cell_stats, recording_cells, summarise, voxel_cell_stats

log = logging.getLogger("v2v.calibrate")

#: (lo, hi) of every fitted value (log-intensity units, Hz): inside the kernel's tested ranges.
BOUNDS = {"threshold": (0.02, 8.0), "noise_std": (0.0, 0.5), "threshold_sigma_rel": (0.0, 0.25),
          "shot_noise_hz": (0.0, 10.0), "potential_spread": (0.0, 1.0)}

#: Multiplicative steps on the threshold alone before a search starts (the event count is about
#: proportional to 1 / threshold): the search starts near the recording's rate.
START_STEPS = 4
#: Fewest grid cells (corpus fit) or frame intervals (frames fit) a recording must hold.
MIN_CELLS = 3
#: Quietest recording fitted: median events per pixel per second over its cells.
MIN_RATE = 1e-3
#: Share of isolated events (``grid_stats.still_rate`` over the signal rate) above which a
#: recording holds no motion, only noise.
MAX_ISOLATED = 0.9
#: Largest share of one polarity (median N+ / (N+ + N-) over the cells, or 1 minus it) a fitted
#: recording may have: a camera's moving edges fire both polarities (the shared recordings:
#: 0.44-0.52); one polarity alone is a recording whose polarity field or biases are wrong, and a
#: fit would drive the other threshold to its bound.
MAX_POLARITY_SHARE = 0.95
#: Half-width of a fitted threshold range, relative to its centre (the paper draws each
#: sample's thresholds from a range; a fit keeps a range, narrowed around the camera's value).
THRESHOLD_SPREAD = 0.25


class CalibrationError(ValueError):
    """A recording or corpus that cannot be fitted; the message names it and what is missing."""


@dataclass
class FitResult:
    """A finished fit.

    Attributes:
        mode: ``"frames"`` or ``"corpus"``.
        params: the fitted values by name (log-intensity units, Hz).
        ranges, nonidealities: what the fitted recipe writes (``ParamRanges`` and
            ``NonIdealities`` fields).
        before, after: the compared statistics of the base recipe and of the fitted one,
            ``{name: simulated value}``; ``target``: the recording's, same names.
        evaluations: objective evaluations; seconds: wall time of the search.
    """
    mode: str
    params: Dict[str, float]
    ranges: Dict[str, list]
    nonidealities: Dict[str, float]
    before: Dict[str, float]
    after: Dict[str, float]
    target: Dict[str, float]
    evaluations: int = 0
    seconds: float = 0.0
    notes: List[str] = field(default_factory=list)


def _minimize(loss: Callable[[np.ndarray], float], x0, steps, bounds, max_evals: int, progress
              ) -> Tuple[np.ndarray, int]:
    """Bounded Nelder-Mead (scipy) from ``x0``, its first simplex ``x0`` plus each of ``steps``
    along its axis (towards the inside of ``bounds``); ``progress(1)`` after each evaluation.
    Returns the best point and the evaluations made."""
    from scipy.optimize import minimize

    lo, hi = np.array([b[0] for b in bounds]), np.array([b[1] for b in bounds])
    count = [0]

    def f(x):
        count[0] += 1
        progress(1)
        return loss(np.clip(x, lo, hi))

    x0 = np.clip(np.asarray(x0, np.float64), lo, hi)
    simplex = [x0]
    for i, st in enumerate(steps):
        x = x0.copy()
        x[i] = x0[i] + st if x0[i] + st <= hi[i] else x0[i] - st
        simplex.append(x)
    res = minimize(f, x0, method="Nelder-Mead", bounds=bounds,
                   options={"maxfev": max_evals, "xatol": 1e-3, "fatol": 1e-5, "initial_simplex": np.array(simplex)})
    return np.clip(res.x, lo, hi), count[0]


def check_cells(path: str, target: Dict[str, Dict[str, float]], n_cells: int, cell_s: float) -> None:
    """Refuse a recording too short, too quiet, without motion or of one polarity for a fit
    (both fits: a fit by statistics on its grid cells, a fit from frames on its frame
    intervals).

    Args:
        target: ``grid_stats.summarise`` of its cells; n_cells: how many; cell_s: a cell's seconds.

    Raises:
        CalibrationError: naming ``path`` and what is missing.
    """
    if n_cells < MIN_CELLS:
        raise CalibrationError(f"recording {path}: too short: {n_cells} whole grid cell(s) of {cell_s:.3g} s, "
                               f"a fit needs at least {MIN_CELLS} ({MIN_CELLS * cell_s:.3g} s of events)")
    rate = target["rate_signal"].get("median", 0.0)
    if rate < MIN_RATE:
        raise CalibrationError(f"recording {path}: too quiet: median {rate:.3g} events / pixel / s over its "
                               f"{n_cells} cells, below the {MIN_RATE:g} a fit needs")
    iso = target["still_rate"].get("median", 0.0) / rate
    if iso > MAX_ISOLATED:
        raise CalibrationError(f"recording {path}: no motion: {100 * iso:.0f} % of its events are isolated "
                               f"(noise, no moving edge); a fit needs a scene that moves")
    on = target["polarity_balance"].get("median", 0.5)
    if max(on, 1 - on) > MAX_POLARITY_SHARE:
        raise CalibrationError(f"recording {path}: one polarity: {100 * max(on, 1 - on):.0f} % of its events are "
                               f"{'ON' if on > 0.5 else 'OFF'} (median over its {n_cells} cells); a camera's moving "
                               f"edges fire both, so its polarity field or biases are wrong, and a fit would drive the "
                               f"{'OFF' if on > 0.5 else 'ON'} threshold to its bound")


def check_bounds(path: str, params: Dict[str, float], names: Tuple[str, ...]) -> None:
    """Refuse a fit whose ``names`` (thresholds of ``params``) ended at a bound of
    :data:`BOUNDS`: the recording's events could not be matched inside the tested range, and the
    written recipe would say so only by its numbers.

    Raises:
        CalibrationError: naming the recording, the value and the bound.
    """
    lo, hi = BOUNDS["threshold"]
    for name in names:
        v = params[name]
        if v <= lo * 1.001 or v >= hi * 0.999:
            raise CalibrationError(f"recording {path}: the fit ran into a bound: {name} {v:.4g} at the tested "
                                   f"{'lower' if v <= lo * 1.001 else 'upper'} limit ({lo:g} - {hi:g}): its events "
                                   f"cannot be matched (a degenerate recording: too few events of one polarity, "
                                   f"or events that do not follow its frames)")


@dataclass
class RecordingTarget:
    """A recording on the grid: ``stats`` (``grid_stats.summarise`` of its cells), ``cells``
    (how many), ``hot_fraction`` (the share of pixels firing in at least 90 % of the cells: hot
    pixels, which fire whatever the scene), ``sensor`` ("WxH")."""
    stats: Dict[str, Dict[str, float]]
    cells: int
    hot_fraction: float
    sensor: str


def recording_target(path: str, cell_s: float, bins: int) -> RecordingTarget:
    """The recording at ``path`` on the grid (cells of ``cell_s`` seconds, ``bins`` bins),
    refused by :func:`check_cells`.

    Raises:
        CalibrationError: the file cannot be read, or :func:`check_cells` refuses it.
    """
    from trainer.recordings import RecordingError, open_recording

    cells: List[dict] = []
    try:
        rec = open_recording(path)
        fired = np.zeros((rec.height, rec.width), np.int32)
        for pos, neg in recording_cells(rec.chunks(), rec.width, rec.height, max(bins, int(round(cell_s * 1e6))), bins):
            cells += cell_stats(pos, neg, cell_s)
            fired += (pos + neg).sum(axis=(0, 1)) > 0
    except RecordingError as e:
        raise CalibrationError(f"recording {e}") from None
    target = summarise(cells)
    check_cells(str(path), target, len(cells), cell_s)
    hot = float(np.mean(fired >= 0.9 * len(cells)))
    return RecordingTarget(target, len(cells), hot, f"{rec.width}x{rec.height}")


@dataclass
class CorpusWindows:
    """The corpus's windows as the stream cuts them (crop, flip and pauses applied), with the
    fixed draws the fit simulates them with.

    Attributes:
        seqs: uint8 (N, S, S) frames of each window; fps: each window's source frame rate, Hz.
        draws: per window, the uniform variates and seeds (``_draw``).
    """
    seqs: List[np.ndarray]
    fps: List[float]
    draws: List[dict]


def corpus_windows(cfg, videos: str, max_windows: int, seed: int, progress=lambda n: None,
                   epochs: int = 2) -> CorpusWindows:
    """Up to ``max_windows`` windows of the corpus at ``videos`` cut as ``cfg``'s recipe (a
    ``ServeConfig``) cuts them in epochs 0 .. ``epochs`` - 1, video by video (each epoch crops,
    flips and pauses a window anew, so several epochs show the fit what a stream's crops hold,
    not one draw of them): the same recipe with one frame pair per voxel grid gives every frame
    of the window (crop, flip and pause offsets are drawn before the sensor parameters, so they
    are the served samples').

    Raises:
        CalibrationError: the corpus cannot be listed or gives no window.
    """
    import dataclasses

    r = cfg.recipe
    frames_recipe = dataclasses.replace(r, sequence_length=r.sequence_length * r.num_bins * r.frames_per_bin,
                                        num_bins=1, frames_per_bin=1, outputs=("frames",), nonidealities={},
                                        refine="off")
    out = CorpusWindows([], [], [])
    rng = np.random.default_rng(seed)
    skipped: set = set()
    for _epoch, arrays, meta in corpus_samples(cfg, videos, frames_recipe, ("frames",),
                                               lambda names: ((rel, e) for rel in names for e in range(epochs)),
                                               skipped):
        shape = arrays["frames"].shape[1:]
        out.seqs.append(arrays["frames"])
        out.fps.append(float(meta["video_fps"]))
        out.draws.append({"pot": rng.random(shape), "hot_u": rng.random(shape),
                          "hot_n": rng.standard_normal(shape), "noise_seed": int(rng.integers(2**62)),
                          "pixel_seed": int(rng.integers(2**62))})
        progress(1)
        if len(out.seqs) >= max_windows:
            break
    if not out.seqs:
        raise CalibrationError(f"corpus {videos}: no window to simulate (no usable video for the recipe's "
                               f"{r.frames_per_sample}-frame windows"
                               + (f"; {len(skipped)} file(s) could not be read" if skipped else "") + ")")
    # the variates that pick each window's parameters inside the ranges: a Latin hypercube over the
    # windows, so a few windows cover each range evenly (as many served samples would)
    from scipy.stats import qmc

    for d, u in zip(out.draws, qmc.LatinHypercube(d=6, seed=rng).random(len(out.draws))):
        d["u"] = u
    return out


def corpus_samples(cfg, videos: str, recipe, outputs, passes, skipped: set):
    """``(epoch, arrays, meta)`` of each sample ``recipe`` (a ``SampleRecipe``) makes from the corpus at
    ``videos`` (opened as ``v2v-serve`` opens it, with ``cfg``'s source and caches), for each
    ``(video, epoch)`` that ``passes(names)`` gives, in its order (the worker's sample pass,
    ``samples.make.video_samples``). A file that cannot be read is skipped with one line naming
    it, as ``v2v-serve`` skips it, and added to ``skipped`` (its samples before stay).

    Raises:
        CalibrationError: the corpus cannot be listed.
    """
    from v2v_server.ops.startup import start_source
    from v2v_server.samples.make import video_samples
    from v2v_server.sources.errors import StoreError, VideoError

    try:
        start = start_source(cfg, videos)  # the start-up path v2v-serve runs: the same source and caches
    except (OSError, ValueError, StoreError) as e:
        raise CalibrationError(f"corpus {videos}: {e}") from None
    source, caches = start.source, start.caches
    for rel, epoch in passes(start.videos):
        if rel in skipped:
            continue
        try:
            for _key, arrays, meta in video_samples(recipe, source, rel, epoch, outputs, caches=caches):
                yield epoch, arrays, meta
        except VideoError as e:  # one bad file is skipped, as v2v-serve skips it; its windows before stay
            skipped.add(rel)
            log.warning("skipped %s: %s", source.where(rel), e)


def simulate_windows(win: CorpusWindows, ranges, nonideal, num_bins: int, frames_per_bin: int) -> List[dict]:
    """``grid_stats`` cells of every window of ``win`` simulated as the stream would with
    ``ranges`` (a ``ParamRanges``) and ``nonideal`` (a ``NonIdealities``), each window's
    parameters picked inside the ranges by its fixed uniform variates (as ``sample_params``
    draws them: t1, the ratio, the coin for c+, sigma, the hot-pixel fraction and scale)."""
    from v2v_server.simulation.nonideal import simulate_voxels_nonideal
    from v2v_server.simulation.simulate import SensorParams

    def pick(rng_pair, u):
        return rng_pair[0] + u * (rng_pair[1] - rng_pair[0])

    cells: List[dict] = []
    for seq, fps, d in zip(win.seqs, win.fps, win.draws):
        u = d["u"]
        t1 = pick(ranges.threshold, u[0])
        t2 = t1 * pick(ranges.ratio, u[1])
        cp, cn = (t1, t2) if u[2] < 0.5 else (t2, t1)
        sigma = pick(ranges.noise_std, u[3])
        frac, scale = pick(ranges.hot_pixel_fraction, u[4]), pick(ranges.hot_pixel_std, u[5])
        mask = d["hot_u"] < frac
        hot = np.where(mask, d["hot_n"] * scale, 0.0).astype(np.float32) if mask.any() and scale > 0 else None
        pot = -cn + d["pot"] * (cp + cn)
        vox, _, _ = simulate_voxels_nonideal(seq, SensorParams(cp, cn, sigma, hot), num_bins * frames_per_bin,
                                             nonideal, fps=fps, initial_potential=pot,
                                             rng=np.random.default_rng(d["pixel_seed"]))
        if frames_per_bin > 1:
            L, _, h, w = vox.shape
            vox = vox.reshape(L, num_bins, frames_per_bin, h, w).sum(axis=2)
        cells += voxel_cell_stats(vox, num_bins * frames_per_bin / fps)
    return cells


#: The statistics compared by a corpus fit (medians over the grid cells), in table order.
CORPUS_STATS = ("rate_net", "rate_signal", "active_fraction", "events_per_active", "still_rate", "polarity_balance")


def corpus_parts(x: np.ndarray, base_ranges, base_nonideal, hot_fraction: float):
    """The ranges and non-idealities of a corpus fit's vector ``x`` = (log threshold centre,
    noise sigma's upper bound, threshold spread relative to the range's low end, shot-noise
    Hz): ``(ParamRanges, NonIdealities)``. Ratio from ``base_ranges``; hot pixels: a fraction
    up to twice the recording's ``hot_fraction`` (mean: the recording's), none when it has none."""
    import dataclasses

    from v2v_server.simulation.simulate import ParamRanges

    c = float(np.exp(x[0]))
    lo = c * (1 - THRESHOLD_SPREAD)
    ranges = ParamRanges(threshold=(lo, c * (1 + THRESHOLD_SPREAD)), ratio=base_ranges.ratio,
                         noise_std=(0.0, float(x[1])), hot_pixel_fraction=(0.0, min(1.0, 2 * hot_fraction)),
                         hot_pixel_std=base_ranges.hot_pixel_std if hot_fraction > 0 else (0.0, 0.0))
    ni = dataclasses.replace(base_nonideal, threshold_sigma=float(x[2]) * lo, shot_noise_hz=float(x[3]))
    return ranges, ni


def medians(cells: List[dict], keys=CORPUS_STATS) -> Dict[str, float]:
    """The median over ``cells`` of each of ``keys`` (NaN-free; NaN when none has a value)."""
    s = summarise(cells)
    return {k: s[k].get("median", float("nan")) for k in keys}


def fit_corpus(win: CorpusWindows, target: RecordingTarget, recipe, max_evals: int = 80,
               progress=lambda n: None, sensor: Optional[Dict[str, float]] = None) -> FitResult:
    """Fit ``recipe``'s (a ``SampleRecipe``) sensor ranges so that ``win`` simulated with them
    matches ``target`` on the grid (module docstring): the loss is
    ``100 e_rate^2 + e_active^2 + 0.5 e_still^2``, each ``e`` the log ratio of the simulated
    median to the recording's (the rate first: a rate within 25 % is the promise; the active
    fraction depends on the scenes, which differ between corpus and recording).

    ``sensor``: the camera fitted from the recording's frames (:func:`fit_frames`' params), which
    seeds the fit: the ratio range up to its max(c+, c-) / min, the search's start at its
    threshold spread (relative) and noise sigma; the threshold's level is the corpus's to find."""
    import time

    B, fpb = recipe.num_bins, recipe.frames_per_bin
    tgt = {k: target.stats[k].get("median", float("nan")) for k in CORPUS_STATS}
    eps = 1e-4

    def stats_of(ranges, ni):
        return medians(simulate_windows(win, ranges, ni, B, fpb))

    def loss(x):
        m = stats_of(*corpus_parts(x, recipe.ranges, recipe.nonideal_spec, target.hot_fraction))
        e_rate = np.log(max(m["rate_net"], 1e-9) / tgt["rate_net"])
        e_act = np.log(max(m["active_fraction"], 1e-9) / tgt["active_fraction"])
        e_still = np.log((m["still_rate"] + eps) / (tgt["still_rate"] + eps))
        return float(100 * e_rate ** 2 + e_act ** 2 + 0.5 * e_still ** 2)

    t0 = time.perf_counter()
    base, (lo, hi) = recipe, recipe.ranges.threshold
    b = BOUNDS
    bounds = [tuple(np.log(b["threshold"])), b["noise_std"], b["threshold_sigma_rel"], b["shot_noise_hz"]]
    x0 = np.array([np.log(np.clip((lo + hi) / 2, *b["threshold"])), min(recipe.ranges.noise_std[1], b["noise_std"][1]),
                   0.0, min(recipe.nonideal_spec.shot_noise_hz, b["shot_noise_hz"][1])])
    if sensor is not None:
        import dataclasses

        c = min(sensor["c_pos"], sensor["c_neg"])
        recipe = dataclasses.replace(recipe, ranges=dataclasses.replace(
            recipe.ranges, ratio=(1.0, max(sensor["c_pos"], sensor["c_neg"]) / c)))
        x0[1] = min(2 * sensor["noise_std"], b["noise_std"][1])  # the frames fit's sigma is the range's mean
        x0[2] = min(sensor["threshold_sigma"] / c, b["threshold_sigma_rel"][1])
    for _ in range(START_STEPS):  # the rate is about proportional to 1 / threshold: a few steps to the start
        m = stats_of(*corpus_parts(x0, recipe.ranges, recipe.nonideal_spec, target.hot_fraction))
        progress(1)
        x0[0] = np.clip(x0[0] + np.log(max(m["rate_net"], 1e-9) / tgt["rate_net"]), *bounds[0])
    x, n = _minimize(loss, x0, [0.3, 0.02, 0.1, 0.05], bounds, max_evals - START_STEPS, progress)
    n += START_STEPS
    ranges, ni = corpus_parts(x, recipe.ranges, recipe.nonideal_spec, target.hot_fraction)
    before = stats_of(base.ranges, base.nonideal_spec)
    after = stats_of(ranges, ni)
    fitted = {"threshold_centre": float(np.exp(x[0])), "noise_std_max": float(x[1]),
              "threshold_sigma": ni.threshold_sigma, "shot_noise_hz": ni.shot_noise_hz,
              "hot_pixel_fraction_mean": ranges.hot_pixel_fraction[1] / 2}
    return FitResult("corpus", fitted, ranges.to_dict(), _changed(ni), before, after, tgt, n,
                     time.perf_counter() - t0)


def _changed(ni) -> Dict[str, float]:
    """The non-idealities that are switched on, as the recipe's ``nonidealities`` writes them."""
    from v2v_server.simulation.nonideal import NonIdealities

    base = NonIdealities().to_dict()
    return {k: v for k, v in ni.to_dict().items() if v != base[k]}


@dataclass
class FrameTarget:
    """A recording with frames, aligned: ``frames`` uint8 (K + 1, H, W) (the first frame after
    the first event and those after it), ``real`` int32 (K, H, W) its signed counts N+ - N- per
    frame interval and pixel, ``counts`` int32 (K, H, W) its events per interval and pixel,
    ``n_pos`` and ``n_neg`` (events), ``fps`` (Hz, the frames' median rate)."""
    frames: np.ndarray
    real: np.ndarray
    counts: np.ndarray
    n_pos: int
    n_neg: int
    fps: float


def frame_target(path: str) -> FrameTarget:
    """The recording at ``path`` with its frames and the events between them (one frame
    interval per cell, ``trainer.event_grids.voxel_grids`` with one bin), refused when it has
    no frames or fewer than :data:`MIN_CELLS` intervals, by :func:`check_cells` on its intervals
    (the rules of a fit by statistics: too quiet, events that are noise alone, one polarity), or
    when its frames do not change (no motion).

    Raises:
        CalibrationError: naming ``path`` and what is missing.
    """
    from trainer.event_grids import voxel_grids
    from trainer.recordings import RecordingError, open_recording
    from v2v_server.simulation.simulate import log_intensity_lut

    try:
        rec = open_recording(path)
        fr = rec.frames()
        if fr is None or len(fr.t_us) < 2:
            raise CalibrationError(f"recording {path}: no intensity frames to simulate from (fit it by statistics: "
                                   "--fit statistics)")
        first = int(np.searchsorted(fr.t_us, rec.first_t_us(), "left"))
        ts, frames = fr.t_us[first:], fr.images[first:]
        k = len(ts) - 1
        if k < MIN_CELLS:
            raise CalibrationError(f"recording {path}: too short: {max(k, 0)} frame interval(s) after the first "
                                   f"event, a fit needs at least {MIN_CELLS}")
        real = np.zeros((k, rec.height, rec.width), np.int32)
        counts = np.zeros_like(real)
        for i, vox, cnt in voxel_grids(rec.chunks(int(ts[0]), int(ts[-1])), ts, 1, rec.height, rec.width):
            real[i], counts[i] = vox[0], cnt
    except RecordingError as e:
        raise CalibrationError(f"recording {e}") from None
    fps = 1e6 / float(np.median(np.diff(ts)))
    events, net = int(counts.sum()), int(real.sum(dtype=np.int64))
    pos, neg = (counts + real) // 2, (counts - real) // 2  # one bin per interval: N+ and N- of each pixel
    check_cells(str(path), summarise(cell_stats(pos[:, None], neg[:, None], 1.0 / fps)), k, 1.0 / fps)
    lut = log_intensity_lut(255, np.float64)
    moving = float(np.mean(np.abs(np.diff(lut[frames], axis=0)) > 0.1))
    if moving < 1e-4:
        raise CalibrationError(f"recording {path}: no motion: its frames barely change ({100 * moving:.3g} % of the "
                               "pixels change by 0.1 log intensity in a frame interval)")
    return FrameTarget(frames, real, counts, (events + net) // 2, (events - net) // 2, fps)


#: The statistics compared by a frames fit, in table order.
FRAME_STATS = ("events", "n_pos", "n_neg", "active_fraction", "corr")


def frame_stats(sim: np.ndarray, target: FrameTarget) -> Dict[str, float]:
    """``sim`` (int (K, H, W) signed counts per frame interval, one polarity per pixel and
    interval) against ``target``: N+, N-, events, the active fraction of the (interval, pixel)
    cells and the Pearson correlation of the signed counts over all cells."""
    s = sim.astype(np.float64).ravel()
    r = target.real.astype(np.float64).ravel()
    corr = float(np.corrcoef(s, r)[0, 1]) if s.std() > 0 else float("nan")
    pos, neg = int(np.maximum(sim, 0).sum(dtype=np.int64)), int(np.maximum(-sim, 0).sum(dtype=np.int64))
    return {"events": pos + neg, "n_pos": pos, "n_neg": neg, "active_fraction": float(np.mean(sim != 0)),
            "corr": corr}


def target_frame_stats(target: FrameTarget) -> Dict[str, float]:
    """The recording's own values of :data:`FRAME_STATS` (its correlation with itself: 1)."""
    return {"events": target.n_pos + target.n_neg, "n_pos": target.n_pos, "n_neg": target.n_neg,
            "active_fraction": float(np.mean(target.counts > 0)), "corr": 1.0}


def simulate_frames(target: FrameTarget, params: Dict[str, float], seed: int) -> np.ndarray:
    """V2V (with the threshold spread) on ``target``'s frames for a frames fit's ``params`` as
    :func:`fit_frames` returns them (``c_pos``, ``c_neg``, ``threshold_sigma``, ``noise_std``
    in log intensity; ``potential_spread``: the initial potential drawn in that fraction of
    (-c-, c+)); the draws fixed by ``seed``: the fit's own simulations, and its check with
    other draws. Returns int32 (K, H, W) signed counts."""
    from v2v_server.simulation.nonideal import NonIdealities, simulate_voxels_nonideal
    from v2v_server.simulation.simulate import SensorParams

    cp, cn = params["c_pos"], params["c_neg"]
    rng = np.random.default_rng(seed)
    pot = rng.uniform(-cn, cp, target.frames.shape[1:]) * params["potential_spread"]
    ni = NonIdealities(threshold_sigma=params["threshold_sigma"])
    vox, _, _ = simulate_voxels_nonideal(target.frames, SensorParams(cp, cn, params["noise_std"]), 1, ni,
                                         fps=target.fps, initial_potential=pot, rng=rng)
    return vox[:, 0]


def _frame_params(x) -> Dict[str, float]:
    """A frames fit's vector ``x`` = (log c+, log c-, threshold spread relative to min(c+, c-),
    noise sigma, initial-potential spread) as :func:`simulate_frames`'s ``params``."""
    cp, cn = float(np.exp(x[0])), float(np.exp(x[1]))
    return {"c_pos": cp, "c_neg": cn, "threshold_sigma": float(x[2]) * min(cp, cn), "noise_std": float(x[3]),
            "potential_spread": float(x[4])}


def fit_frames(target: FrameTarget, recipe, seed: int = 0, max_evals: int = 120, progress=lambda n: None) -> FitResult:
    """Fit c+, c-, the threshold spread, the noise sigma and the initial-potential spread so
    that V2V on ``target``'s frames matches its events (module docstring). The loss is
    ``e_pos^2 + e_neg^2 + e_active^2 + 2 (1 - corr)``, each ``e`` a log ratio to the
    recording's; the start: c+ and c- matching N+ and N- with the rest off
    (``bench/real_sensor.py``'s fit). ``before``: the recipe's thresholds' centre, its
    noise's centre, full potential spread."""
    import time

    tgt = target_frame_stats(target)

    def stats(x):
        return frame_stats(simulate_frames(target, _frame_params(x), seed), target)

    def loss(x):
        m = stats(x)
        e = [np.log(max(m[k], 1) / max(tgt[k], 1)) for k in ("n_pos", "n_neg")]
        e.append(np.log(max(m["active_fraction"], 1e-9) / tgt["active_fraction"]))
        return float(sum(v * v for v in e) + 2 * (1 - np.nan_to_num(m["corr"])))

    t0 = time.perf_counter()
    cp = cn = 0.3
    for _ in range(START_STEPS):  # N is about proportional to 1 / c: a few multiplicative steps to the start
        m = stats([np.log(cp), np.log(cn), 0.0, 0.0, 1.0])
        progress(1)
        cp *= max(m["n_pos"], 1) / max(tgt["n_pos"], 1)
        cn *= max(m["n_neg"], 1) / max(tgt["n_neg"], 1)
        cp, cn = (float(np.clip(c, *BOUNDS["threshold"])) for c in (cp, cn))
    b = BOUNDS
    bounds = [tuple(np.log(b["threshold"]))] * 2 + [b["threshold_sigma_rel"], b["noise_std"], b["potential_spread"]]
    x, n = _minimize(loss, [np.log(cp), np.log(cn), 0.0, 0.0, 1.0], [0.1, 0.1, 0.05, 0.02, 0.3], bounds,
                     max_evals - START_STEPS, progress)
    lo, hi = recipe.ranges.threshold
    before = stats([np.log((lo + hi) / 2)] * 2 + [0.0, float(np.mean(recipe.ranges.noise_std)), 1.0])
    after = stats(x)
    params = _frame_params(x)
    ranges, ni = frame_parts(params, recipe)
    return FitResult("frames", params, ranges.to_dict(), _changed(ni), before, after, tgt, n + START_STEPS,
                     time.perf_counter() - t0)


def frame_parts(params: Dict[str, float], recipe):
    """The recipe's ranges and non-idealities for a frames fit's ``params``: thresholds
    +-:data:`THRESHOLD_SPREAD` around min(c+, c-), the ratio up to max / min (the stream's
    coin decides which polarity gets which), noise sigma up to twice the fitted (mean: the
    fitted), no hot pixels (the camera's events between its frames need none), the spread."""
    import dataclasses

    from v2v_server.simulation.simulate import ParamRanges

    t = min(params["c_pos"], params["c_neg"])
    r = max(params["c_pos"], params["c_neg"]) / t
    ranges = ParamRanges(threshold=(t * (1 - THRESHOLD_SPREAD), t * (1 + THRESHOLD_SPREAD)), ratio=(1.0, r),
                         noise_std=(0.0, 2 * params["noise_std"]), hot_pixel_fraction=(0.0, 0.0),
                         hot_pixel_std=(0.0, 0.0))
    ni = dataclasses.replace(recipe.nonideal_spec, threshold_sigma=params["threshold_sigma"])
    return ranges, ni


# -- the written recipe's stream --------------------------------------------------------------

#: Samples the served check makes: the written recipe's stream over the corpus, as ``v2v-serve``
#: makes it (its epochs' own crops and sensor draws, not the fit's fixed ones).
SERVED_SAMPLES = 24
#: Most epochs the served check reads to make them (a small corpus has few windows an epoch).
SERVED_EPOCHS = 8
#: A served net rate further than this (relative) from the recording's moves the thresholds
#: (:func:`match_served_rate`): inside the promised 25 % with room for another epoch's draws.
RATE_TOLERANCE = 0.10
#: Most rounds of that correction.
RATE_ROUNDS = 3


@dataclass
class Served:
    """The stream a recipe serves over a corpus, on the grid: ``stats`` (``grid_stats.summarise``
    of its voxel grids), ``samples`` and ``epochs`` read, ``grids`` (voxel grids), ``cell_s``
    (one voxel grid's duration, s, at the samples' median frame rate)."""
    stats: Dict[str, Dict[str, float]]
    samples: int
    epochs: int
    grids: int
    cell_s: float

    def median(self, key: str) -> float:
        return self.stats[key].get("median", float("nan"))


def served_stream(cfg, videos: str, n: int = SERVED_SAMPLES, progress=lambda n: None) -> Served:
    """The first ``n`` samples that ``cfg``'s recipe (a ``ServeConfig``: what ``v2v-serve
    --config`` takes) serves over the corpus at ``videos``, epoch by epoch (0, 1, ... at most
    :data:`SERVED_EPOCHS`) and video by video, made by the worker's sample pass with each
    epoch's own crops and sensor draws, each voxel grid a cell of ``grid_stats``.

    Raises:
        CalibrationError: the corpus cannot be listed or gives no sample.
    """
    from trainer.stream_stats import sample_row

    cells: List[dict] = []
    fps: List[float] = []
    last_epoch, skipped = 0, set()
    passes = lambda names: ((rel, e) for e in range(SERVED_EPOCHS) for rel in names)  # noqa: E731
    for epoch, arrays, meta in corpus_samples(cfg, videos, cfg.recipe, ("voxels",), passes, skipped):
        cells += sample_row(meta, arrays["voxels"], cfg.recipe)["cells"]
        fps.append(float(meta["video_fps"]))
        last_epoch = epoch
        progress(1)
        if len(fps) >= n:
            break
    if not fps:
        raise CalibrationError(f"corpus {videos}: gives no sample with the recipe")
    r = cfg.recipe
    return Served(summarise(cells), len(fps), last_epoch + 1, len(cells),
                  r.num_bins * r.frames_per_bin / float(np.median(fps)))


def scaled_thresholds(ranges: Dict[str, list], nonideal: Dict[str, float], factor: float):
    """``(ranges, nonidealities)`` (as a recipe writes them) with the threshold range and the
    threshold spread times ``factor``, the range's centre kept inside :data:`BOUNDS` and its
    upper end at or under the kernel's tested 10."""
    lo, hi = ranges["threshold"]
    centre = (lo + hi) / 2
    factor = float(np.clip(centre * factor, *BOUNDS["threshold"]) / centre)
    factor = min(factor, 10.0 / hi)
    out = dict(ranges, threshold=[lo * factor, hi * factor])
    ni = dict(nonideal)
    if ni.get("threshold_sigma"):
        ni["threshold_sigma"] = ni["threshold_sigma"] * factor
    return out, ni


def match_served_rate(serve: Callable[[Dict[str, list], Dict[str, float]], Served], ranges: Dict[str, list],
                      nonideal: Dict[str, float], target_rate: float):
    """Bring the served stream's median net rate to ``target_rate`` (events / pixel / s), as
    Stoffregen et al. (ECCV 2020) matched their training data's event rate to the camera's: the
    threshold range is scaled until the stream ``serve(ranges, nonidealities)`` gives is within
    :data:`RATE_TOLERANCE` of it (at most :data:`RATE_ROUNDS` rounds; the rate goes about as one
    over the threshold, a secant in log-log after the first step).

    Returns:
        ``(ranges, nonidealities, served, factors)``: the last recipe's parts and stream, and
        the threshold factor of each round.
    """
    served = serve(ranges, nonideal)
    factors: List[float] = []
    slope, last = -1.0, None
    for _ in range(RATE_ROUNDS):
        rate = served.median("rate_net")
        err = np.log(max(rate, 1e-12) / target_rate)
        if abs(err) <= np.log1p(RATE_TOLERANCE):
            break
        centre = float(np.mean(ranges["threshold"]))
        if last is not None and abs(np.log(centre) - last[0]) > 1e-6:
            slope = float(np.clip((err - last[1]) / (np.log(centre) - last[0]), -3.0, -0.3))
        last = (np.log(centre), err)
        new_ranges, new_ni = scaled_thresholds(ranges, nonideal, float(np.exp(-err / slope)))
        if np.isclose(np.mean(new_ranges["threshold"]), centre):
            break  # at a bound: no further
        ranges, nonideal = new_ranges, new_ni
        factors.append(float(np.mean(ranges["threshold"]) / centre))
        served = serve(ranges, nonideal)
    return ranges, nonideal, served, factors

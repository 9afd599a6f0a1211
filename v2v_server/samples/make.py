"""Training samples from one sequential decode of a video.

A video is cut into windows of ``frames_per_sample`` (201) source frames that follow each other
``window_stride`` (200) apart (a window's last frame is the next one's first, as in the authors'
loader), placed by ``frames.shots.WindowLayout``: with ``shot_cuts: avoid`` inside the video's
shots (each shot's first frame + k x 200, the cuts found by the same pass), with ``off`` at
k x 200 from frame 0; at most ``max_samples_per_video`` windows, numbered 0.. in frame order.
Everything random in a sample (pauses, crop, flip, sensor parameters, initial potential, noise)
comes from a generator seeded by ``(seed, epoch, sample_id)``, so its content never depends on
which worker made it or in which order. With ``crops_per_window`` K > 1 a window gives K samples
(ids ``path#window.crop``), K crops of the same decoded frames.
"""
from __future__ import annotations

import hashlib
import math
import time
from dataclasses import dataclass
from typing import Callable, Dict, FrozenSet, Iterable, Iterator, List, Mapping, Optional, Tuple

import cv2
import numpy as np

from v2v_server.samples.augment import augment_plan, degrade_window
from v2v_server.samples.recipe import SampleRecipe
from v2v_server.samples.stats import add_stats
from v2v_server.sources.source import VideoSource
from v2v_wire.ids import SampleKey, window_keys
from v2v_server.flow.estimate import FlowEstimator
from v2v_server.simulation.simulate import SensorParams, polarity_counts, sample_params, simulate_voxels
from v2v_server.luma import to_uint8
from v2v_server.frames.host_caches import HostCaches
from v2v_server.frames.video_read import read_video, reraise
from v2v_server.frames.window_pass import VideoPass, WindowFrame, WindowPass


def sample_rng(seed: int, epoch: int, sample_id: str) -> np.random.Generator:
    """The generator for one sample, a pure function of (seed, epoch, sample_id)."""
    digest = hashlib.blake2b(sample_id.encode("utf-8"), digest_size=8).digest()
    key = int.from_bytes(digest, "little")
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), int(epoch), key])))


def pause_offsets(rng: np.random.Generator, n_out: int, p_run: float, p_paused: float) -> np.ndarray:
    """Source-frame offset of each of ``n_out`` output frames under the pause Markov chain.

    At each step the chain is paused with probability ``p_paused`` if it was paused, else
    ``p_run``; a paused step repeats the previous frame. Returns int64 (n_out,), starting at
    0, non-decreasing, steps of 0 or 1.
    """
    u = rng.random(n_out - 1)
    adv = np.empty(n_out - 1, dtype=np.int64)
    paused = False
    for i in range(n_out - 1):
        paused = bool(u[i] < (p_paused if paused else p_run))
        adv[i] = 0 if paused else 1
    return np.concatenate([[0], np.cumsum(adv)])


@dataclass(frozen=True, eq=False)  # eq=False: identity, as SensorParams (arrays have no truth value)
class WindowPlan:
    """The random choices of one sample, made before its frames are decoded: a frozen record,
    built whole by :func:`plan_window` (a step that derives another plan returns a new one,
    ``dataclasses.replace``).

    ``offsets``: int64 (frames_per_sample,) source offsets inside the window (pauses);
    ``scale``: resize factor of the kept region (>= 1, only when it is smaller than the crop);
    ``crop_y``, ``crop_x``: top-left corner of the crop in the scaled kept region, pixels;
    ``flip``: horizontal flip; ``params``: sensor parameters; ``rng``: the sample's generator
    (``sample_rng``), which the simulation draws from after the plan's choices;
    ``fixed_sensor_params``: ``params`` hold the video's fixed c+ / c-, and
    ``dynamic_range_scale``: the degradation scale drawn, None when off (``augment.augment_plan``).
    """

    sample_id: str
    window: int
    offsets: np.ndarray
    scale: float
    crop_y: int
    crop_x: int
    flip: bool
    params: SensorParams
    rng: np.random.Generator
    fixed_sensor_params: bool = False
    dynamic_range_scale: Optional[float] = None

    @property
    def consumed(self) -> int:
        """Source frames this window reads (<= frames_per_sample because of pauses)."""
        return int(self.offsets[-1]) + 1

    @property
    def info(self) -> dict:
        """The ablations applied, as the sample's params name them (a new dict, empty when both
        are off): ``fixed_sensor_params`` (True) and ``dynamic_range_scale`` (float)."""
        out: dict = {}
        if self.fixed_sensor_params:
            out["fixed_sensor_params"] = True
        if self.dynamic_range_scale is not None:
            out["dynamic_range_scale"] = self.dynamic_range_scale
        return out


@dataclass(frozen=True)
class StageSeconds:
    """Seconds spent per stage of making samples, for the server's metrics
    (``v2v_worker_busy_seconds_total``): ``simulate`` (voxels, polarity counts) and ``flow``
    (optical flow) by the wall clock; ``stats`` (``stats.add_stats``) in this thread's CPU time,
    so a loaded host does not inflate it. ``a + b`` sums two records, ``a - b`` gives what was
    spent between two readings of a running total."""

    simulate: float = 0.0
    flow: float = 0.0
    stats: float = 0.0

    def __add__(self, other: "StageSeconds") -> "StageSeconds":
        return StageSeconds(self.simulate + other.simulate, self.flow + other.flow, self.stats + other.stats)

    def __sub__(self, other: "StageSeconds") -> "StageSeconds":
        return StageSeconds(self.simulate - other.simulate, self.flow - other.flow, self.stats - other.stats)


@dataclass(frozen=True)
class MadeSample:
    """What :func:`make_sample` made of one sample.

    Attributes:
        arrays: the requested outputs by name (shapes and dtypes: :func:`make_sample`).
        simulation: what the V2V core used, for the sample's params (:func:`sample_meta`):
            ``refine`` ("off" or the refinement's name), with non-idealities also
            ``nonidealities``, with refinement ``subframes_mean``; empty when nothing was simulated.
        seconds: the time this sample took per stage (``stats`` 0: statistics come after).
    """

    arrays: Dict[str, np.ndarray]
    simulation: Mapping[str, object]
    seconds: StageSeconds


def plan_window(recipe: SampleRecipe, epoch: int, sample_id: str, window: int, kept_hw: Tuple[int, int]) -> WindowPlan:
    """Draw the random choices of one window from its own generator (see ``sample_rng``)."""
    rng = sample_rng(recipe.seed, epoch, sample_id)
    n = recipe.frames_per_sample
    if recipe.pause_enabled:
        offsets = pause_offsets(rng, n, recipe.p_pause_when_running, recipe.p_pause_when_paused)
    else:
        offsets = np.arange(n, dtype=np.int64)
    h, w = kept_hw
    s = recipe.crop_size
    scale = max(1.0, s / h, s / w)
    sh, sw = max(s, int(math.ceil(h * scale))), max(s, int(math.ceil(w * scale)))
    crop_y = int(rng.integers(0, sh - s + 1))
    crop_x = int(rng.integers(0, sw - s + 1))
    flip = bool(rng.random() < recipe.hflip_prob)
    params = sample_params(rng, recipe.ranges, (s, s))
    # ablations (off by default), from their own generators
    return augment_plan(recipe, epoch, WindowPlan(sample_id, window, offsets, scale, crop_y, crop_x, flip, params, rng))


def crop_frame(recipe: SampleRecipe, plan: WindowPlan, luma: np.ndarray) -> np.ndarray:
    """Scale (if needed), crop and flip one kept-region luma frame -> (S, S) of the same dtype
    (uint8, or uint16 for deeper sources), a copy."""
    s = recipe.crop_size
    if plan.scale > 1.0:
        h, w = luma.shape
        sh, sw = max(s, int(math.ceil(h * plan.scale))), max(s, int(math.ceil(w * plan.scale)))
        luma = cv2.resize(luma, (sw, sh), interpolation=cv2.INTER_LINEAR)
    c = luma[plan.crop_y:plan.crop_y + s, plan.crop_x:plan.crop_x + s]
    if plan.flip:
        c = c[:, ::-1]
    return np.ascontiguousarray(c)


def make_sample(
    recipe: SampleRecipe,
    plan: WindowPlan,
    window_frames: np.ndarray,
    outputs: Iterable[str],
    flow: Optional[FlowEstimator] = None,
    fps: float = 0.0,
    flow_grid: bool = False,
) -> MadeSample:
    """Compute the requested outputs of one sample.

    Args:
        window_frames: uint8 or uint16 (plan.consumed, S, S) full-range cropped source frames
            of the window (uint16 sources feed the V2V core at full precision; frames and flow
            use their 8-bit rounding).
        outputs: any of ``OUTPUTS`` ("voxels", "frames", "flow", "polarity_counts"); only
            these are computed.
        fps: source frame rate, Hz (for non-idealities given as rates).
        flow_grid: with a tracked flow option, give the flow as ``flow_grid`` float32
            (L, 2, n, n), its values at the tracking grid's points
            (``FlowEstimator.voxel_flow_grids``; what a worker sends), instead of the dense
            ``flow``; other options give dense ``flow`` either way.

    Returns:
        a :class:`MadeSample`: what the simulation used, the seconds spent simulating and
        estimating flow, and its ``arrays``, a dict with ``voxels`` (L, B, S, S) signed event counts (int8/int16/int32, the narrowest
        that holds them, for plain V2V with one frame per bin; else int32), ``frames`` uint8
        (L + 1, S, S) at voxel boundaries, ``flow`` (L, 2, S, S) in pixels from frame l to
        l + 1 (``recipe.flow_preset``, see ``flow.py``; tracked options use every source frame
        between the boundaries), in ``recipe.flow_dtype``, ``polarity_counts`` uint8
        (L, 2, B, S, S) N+ and N- per bin saturating at 255 (plain V2V only) — each present
        only if asked for (dtypes and shapes: ``v2v_wire.outputs``).
    """
    outputs = set(outputs)
    seq = window_frames[plan.offsets]  # pauses repeat frames
    step = recipe.num_bins * recipe.frames_per_bin
    out: Dict[str, np.ndarray] = {}
    simulation: Mapping[str, object] = {}
    t0 = time.perf_counter()
    simulated = "voxels" in outputs or "polarity_counts" in outputs
    if simulated:
        vox, counts, simulation = _simulate(recipe, plan, seq, fps, "polarity_counts" in outputs)
        if "voxels" in outputs:
            if recipe.frames_per_bin > 1:
                L, _, h, w = vox.shape
                vox = vox.reshape(L, recipe.num_bins, recipe.frames_per_bin, h, w).sum(axis=2, dtype=np.int32)
            out["voxels"] = vox
        if counts is not None:
            out["polarity_counts"] = counts
    if "frames" in outputs:
        out["frames"] = np.ascontiguousarray(to_uint8(seq[::step]))
    t1 = time.perf_counter()
    if "flow" in outputs:
        flow = flow or FlowEstimator(recipe.flow_preset)
        # pauses repeat frames: the pairs between repeats cost no tracking
        repeats = np.concatenate([[False], np.diff(plan.offsets) == 0])
        if flow_grid and flow.option.method == "tracked":
            out["flow_grid"] = flow.voxel_flow_grids(seq, step, repeats)
        else:
            out["flow"] = flow.voxel_flows(seq, step, repeats, dtype=recipe.flow_dtype)
    seconds = StageSeconds(simulate=t1 - t0 if simulated else 0.0,
                           flow=time.perf_counter() - t1 if "flow" in outputs else 0.0)
    return MadeSample(out, simulation, seconds)


def _simulate(recipe: SampleRecipe, plan: WindowPlan, seq: np.ndarray, fps: float,
              polarity: bool = False) -> Tuple[np.ndarray, Optional[np.ndarray], Dict[str, object]]:
    """Voxels of one window: plain V2V, V2V with refinement, V2V with non-idealities, or
    both composed (one kernel call either way), as configured, and what was used (for the
    sample's params: :attr:`MadeSample.simulation`). With ``polarity``, also the
    ``polarity_counts`` of the same kernel call (plain V2V only), else None.

    Raises:
        ValueError: ``polarity`` with refinement or non-idealities configured."""
    bins = recipe.num_bins * recipe.frames_per_bin
    if polarity and (recipe.nonidealities or recipe.refine != "off"):
        raise ValueError("polarity_counts is made by plain V2V only: serve it with refine: off and no nonidealities")
    if polarity:
        # same kernel, same draws and the same voxels; N+ and N- kept (the kernel's slower split path)
        vox, _, (n_pos, n_neg) = simulate_voxels(seq, plan.params, bins, rng=plan.rng, narrow=recipe.frames_per_bin == 1,
                                                 split=True)
        return vox, polarity_counts(n_pos, n_neg, recipe.sequence_length, recipe.num_bins), {"refine": "off"}
    if recipe.nonidealities:
        from v2v_server.simulation.nonideal import simulate_voxels_nonideal

        vox, _, info = simulate_voxels_nonideal(seq, plan.params, bins, recipe.nonideal_spec, fps=fps or 25.0,
                                                rng=plan.rng, refine=recipe.refine_spec)
        return vox, None, {"nonidealities": info["nonidealities"], "refine": info.get("refine", "off")}
    if recipe.refine != "off":
        from v2v_server.simulation.refine import simulate_voxels_refined

        vox, _, info = simulate_voxels_refined(seq, plan.params, bins, recipe.refine_spec, rng=plan.rng)
        return vox, None, {"refine": info["refine"], "subframes_mean": float(info["subframes_mean"])}
    # the wire's narrow dtype straight from the kernel, unless bins are summed below
    vox, _ = simulate_voxels(seq, plan.params, bins, rng=plan.rng, narrow=recipe.frames_per_bin == 1)
    return vox, None, {"refine": "off"}


def sample_meta(plan: WindowPlan, video_fps: float, src_start: int, simulation: Optional[Mapping[str, object]] = None) -> dict:
    """msgpack-safe description of a sample's random choices and sensor parameters: a new dict
    of the plan's choices, the ablations applied (``WindowPlan.info``) and what the simulation
    used (``simulation``, :attr:`MadeSample.simulation`)."""
    d = plan.params.summary()
    d.update(
        sample_id=plan.sample_id,
        crop_y=plan.crop_y, crop_x=plan.crop_x, scale=float(plan.scale), flip=plan.flip,
        pauses=int(len(plan.offsets) - plan.consumed), src_start_frame=int(src_start),
        src_frames=plan.consumed, video_fps=float(video_fps),
    )
    d.update(plan.info)
    d.update(simulation or {})
    return d


class _CropFrames:
    """One crop of the window being decoded: its plan and its frames so far, (consumed, S, S).

    Full range is applied per pixel on the crop (exact, and far cheaper than on the frame),
    before any resampling. An unscaled crop keeps the codes of every frame that shares the
    window's first code -> full-range map and maps them once, whole, when the window is
    complete (one call instead of one per frame); any other frame (another map, or a crop
    that is resampled from the full-range frame) is stored at full range as it arrives.
    """

    def __init__(self, recipe: SampleRecipe, key: SampleKey, plan: WindowPlan):
        self.recipe, self.key, self.plan = recipe, key, plan
        self.buf: Optional[np.ndarray] = None
        self.coded: List[int] = []  # rows of buf still holding codes
        # an unscaled crop is one slice of the frame: what crop_frame cuts, without its
        # per-call overhead on each of the window's frames; rows kept as codes are flipped
        # once, all together, when the window is complete (a reversed copy per frame is 3x
        # slower than a plain one)
        y, x, sz = plan.crop_y, plan.crop_x, recipe.crop_size
        self.view = (slice(y, y + sz), slice(x, x + sz))
        self.consumed = plan.consumed  # source frames it takes (read for every decoded frame)

    def add(self, off: int, codes: np.ndarray, window_map: bool, expand, full: Optional[np.ndarray]) -> None:
        """Frame ``off`` of the window: its codes (``window_map``: they share the window's
        first map ``expand``), and ``full``, the frame at full range (needed only by a crop
        that is resampled)."""
        recipe, plan = self.recipe, self.plan
        if plan.scale == 1.0:
            if self.buf is None:
                self.buf = np.empty((plan.consumed, recipe.crop_size, recipe.crop_size), codes.dtype)
            if window_map:
                np.copyto(self.buf[off], codes[self.view])
                self.coded.append(off)
            else:
                self.buf[off] = expand(crop_frame(recipe, plan, codes))
            return
        crop = crop_frame(recipe, plan, full)
        if self.buf is None:
            self.buf = np.empty((plan.consumed, recipe.crop_size, recipe.crop_size), crop.dtype)
        self.buf[off] = crop

    def frames(self, window_expand) -> np.ndarray:
        """The crop's full-range frames once the window is complete (maps the rows still
        holding codes with the window's map)."""
        buf = self.buf
        flip = self.plan.flip
        if len(self.coded) == len(buf):
            full = window_expand(buf.reshape(-1, buf.shape[-1]))
            return (cv2.flip(full, 1) if flip else full).reshape(buf.shape)
        for j in self.coded:
            buf[j] = window_expand(buf[j][:, ::-1] if flip else buf[j])
        return buf



class _Window:
    """The window being decoded: its first frame, the code -> full-range map of that frame and
    its crops (:class:`_CropFrames`)."""

    def __init__(self, start: int, expand, crops: List[_CropFrames]):
        self.start, self.expand, self.crops = start, expand, crops

    def add(self, off: int, codes: np.ndarray, expand, full: list) -> None:
        """Frame ``off`` of the window; ``full`` caches the frame at full range (made at most
        once per frame, shared by the windows the frame belongs to)."""
        for crop in self.crops:
            if off < crop.consumed:
                if crop.plan.scale != 1.0 and not full:
                    full.append(np.ascontiguousarray(expand(codes)))
                crop.add(off, codes, expand is self.expand, expand, full[0] if full else None)

    def finish(self) -> Iterator[Tuple[SampleKey, "WindowPlan", np.ndarray]]:
        """Each crop's key, plan and full-range frames, once the window is complete."""
        for crop in self.crops:
            yield crop.key, crop.plan, crop.frames(self.expand)


class SamplePass:
    """The samples of one sequential pass over the video at ``rel_path`` of ``source`` (the
    corpus, a ``sources.source.VideoSource``): an iterator of ``(key, arrays, meta)``, and a
    context manager around the reader's work on them.

    With ``recipe.crops_per_window`` = K, each window gives K samples: K crops, each with its own
    plan (crop, flip, pauses, sensor parameters) from its own id, cut from the same decoded
    frames as they pass (the window is never held at full size).

    Yields ``(key, arrays, meta)`` (``key`` an ``ids.SampleKey``; ``arrays``: ``make_sample``'s)
    for each sample of a complete window whose key is not in ``skip``, in window then crop
    order; a sample's random choices come from its sample id (``SampleKey.sample_id``). The
    video is read the one way every reader reads one (``frames.video_read.read_video``, part
    ``"frames"``): from the host's frame cache or decoded and stored, through the window pass
    (``frames.window_pass.WindowPass``), so a window that a cut drops or a frame of another size
    fails gives no sample (the following ones are planned on the new size); decoding stops after
    the last window that can be used (known from the container's declared frame count when it
    has one); a whole pass is recorded in the host's corpus index. ``flow_grid``: see
    ``make_sample``.

    A failure (decoding, or making a sample; inside the ``with`` block, the reader's own work
    too) goes to ``handler`` (``video_read.as_verdict``: it ends the pass and is its
    :attr:`error`; ``video_read.reraise``: it propagates); samples already yielded are good.
    """

    def __init__(self, recipe: SampleRecipe, source: VideoSource, rel_path: str, epoch: int, outputs: Iterable[str],
                 skip: Iterable[SampleKey] = (), flow: Optional[FlowEstimator] = None, flow_grid: bool = False,
                 caches: Optional[HostCaches] = None, handler: Callable[[Exception], None] = reraise):
        #: The read of the video (``video_read.VideoRead``): its record, verdict and frame pass.
        self.read = read_video(source, rel_path, recipe.reads, caches, handler=handler)
        self._samples = _WindowSamples(recipe, rel_path, epoch, tuple(outputs), frozenset(skip), flow, flow_grid,
                                       self.read.window_pass)
        # opens the video on the first sample asked for; holds the cutter, not this object, so
        # dropping the pass closes it at once (a frame-cache entry being stored is dropped)
        self._run = self.read.run(self._samples.cut(self.read.frames))

    @property
    def seconds(self) -> StageSeconds:
        """The seconds spent so far per stage (simulate, flow, stats), summed over the samples
        made: a record, read between samples (a reader takes the difference of two readings)."""
        return self._samples.seconds

    @property
    def storing(self) -> bool:
        """Whether the pass is still storing the video in the frame cache (``VideoRead.storing``):
        a consumer that stops early then drops the entry."""
        return self.read.storing

    @property
    def error(self) -> Optional[Exception]:
        """What ended the pass, kept by the handler (``VideoRead.error``), or None."""
        return self.read.error

    def record(self) -> VideoPass:
        """What the pass found so far: frames, cuts, complete and failed windows, what ended it
        (``frames.window_pass.VideoPass``, ``VideoRead.record``)."""
        return self.read.record()

    def __iter__(self) -> "SamplePass":
        return self

    def __next__(self) -> Tuple[SampleKey, Dict[str, np.ndarray], dict]:
        return next(self._run)

    def __enter__(self) -> "SamplePass":
        return self

    def __exit__(self, kind, error, tb) -> bool:
        """The end of the reader's block: the pass ends there (``VideoRead.__exit__``), an
        exception of the block handled as one of the pass."""
        self._run.close()
        return self.read.__exit__(kind, error, tb)

    def close(self) -> None:
        """Stop the pass here: the video is closed (a frame-cache entry being stored is dropped)."""
        self._run.close()


@dataclass
class _WindowSamples:
    """What a :class:`SamplePass` makes, the window pass it cuts from, and the seconds spent so
    far per stage (the one writer of ``seconds``: a new record after each sample)."""

    recipe: SampleRecipe
    rel_path: str
    epoch: int
    outputs: Tuple[str, ...]
    skip: FrozenSet[SampleKey]
    flow: Optional[FlowEstimator]
    flow_grid: bool
    window_pass: WindowPass
    seconds: StageSeconds = StageSeconds()

    def _sample(self, key: SampleKey, plan: WindowPlan, frames: np.ndarray, fps: float, start: int
                ) -> Tuple[SampleKey, Dict[str, np.ndarray], dict]:
        """One sample of a complete window: ``(key, arrays, meta)``; its seconds are added to
        :attr:`seconds`."""
        recipe = self.recipe
        made = make_sample(recipe, plan, degrade_window(plan, frames), self.outputs, self.flow, fps, self.flow_grid)
        meta = sample_meta(plan, fps, start, made.simulation)
        t = time.thread_time()  # statistics: this thread's CPU time, so a loaded host does not inflate it
        meta = add_stats(meta, made.arrays, recipe, self.window_pass.shot if recipe.windows.avoid_cuts else None,
                         self.window_pass.motions[-1])
        self.seconds = self.seconds + made.seconds + StageSeconds(stats=time.thread_time() - t)
        return key, made.arrays, meta

    def cut(self, frames: Iterator[WindowFrame]) -> Iterator[Tuple[SampleKey, Dict[str, np.ndarray], dict]]:
        """The samples of the window pass's ``frames`` (``VideoRead.frames``), as they pass."""
        recipe, kpw = self.recipe, self.recipe.crops_per_window
        last = recipe.frames_per_sample - 1  # a window's last frame, from its first
        win: Optional[_Window] = None  # the window being cut (frames are added as they pass)
        for f in frames:  # the frames of the layout's windows at most
            full: list = []  # the whole kept region at full range, made once per frame when a crop is resampled
            if f.drops is not None or f.fails is not None or f.skips is not None:
                win = None  # it would show two scenes, frames of two sizes, or (skipped) almost no change
            if f.ends is not None and win is not None:  # this frame ends the window in progress ...
                win.add(last, f.codes, f.expand, full)
                for key, plan, window in win.finish():
                    yield self._sample(key, plan, window, self.window_pass.info.fps, win.start)
                win = None
            if f.starts is not None:  # ... and starts the next one
                k = f.starts
                win = _Window(f.index, f.expand,
                              [_CropFrames(recipe, key, plan_window(recipe, self.epoch, key.sample_id(kpw), k, f.codes.shape))
                               for key in window_keys(self.rel_path, k, kpw) if key not in self.skip])
            if win is not None and f.offset is not None:
                win.add(f.offset, f.codes, f.expand, full)


def video_samples(recipe: SampleRecipe, source: VideoSource, rel_path: str, epoch: int, outputs: Iterable[str],
                  skip: Iterable[SampleKey] = (), flow: Optional[FlowEstimator] = None, flow_grid: bool = False,
                  caches: Optional[HostCaches] = None, handler: Callable[[Exception], None] = reraise) -> SamplePass:
    """Decode the video at ``rel_path`` of ``source`` once, sequentially (or replay it from the
    frame cache of the host's ``caches``, None: none), and give its samples: a
    :class:`SamplePass` (iterate it for ``(key, arrays, meta)``; its ``record`` says what the
    pass found). ``handler``: the error policy (``video_read.reraise``, the default here: a
    failure propagates; ``video_read.as_verdict``: it ends the pass as its ``error``).

    Raises:
        VideoError: while iterating, with ``reraise``: the file cannot be opened or decoded
            (samples already yielded are good).
    """
    return SamplePass(recipe, source, rel_path, epoch, outputs, skip, flow, flow_grid, caches, handler)

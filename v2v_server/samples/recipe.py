"""The sample recipe: everything that decides a sample's content, the samples stage's settings.

Defaults follow the paper's WebVid recipe (Lou et al. 2025, Sec. 4). The recipe declares the keys
it owns (default, help text, checks; ``docs/config.md`` is generated from them) and composes the
frames stage's settings, which declare theirs: where windows lie (``frames.windows.WindowSettings``,
:attr:`SampleRecipe.windows`) and how frames are decoded (``frames.frame_pass.DecodeSettings``,
:attr:`SampleRecipe.decode`). Users write every key flat (``shot_cuts: off``, ``--crop-size 64``)
and the recipe reads them flat (``recipe.shot_cuts``). The simulation gets the sensor ranges
(``simulation.simulate.ParamRanges``), the flow the option's name.
``v2v_server.ops.config.ServeConfig`` composes the recipe with the serving settings; a worker
process is given the recipe itself (``service.worker.WorkerSetup``).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass
from functools import cached_property
from typing import Tuple

from v2v_server.checks import check_bool, check_choice, check_int, check_prob
from v2v_server.flow.options import DEFAULT_FLOW, FLOW_OPTIONS, check_option, unavailable_reason
from v2v_server.settings import documented, owners, setting, split_keys
from v2v_server.simulation.simulate import ParamRanges
from v2v_server.frames.frame_pass import DecodeSettings
from v2v_server.frames.pass_record import PassRecord
from v2v_server.frames.windows import WindowSettings
from v2v_wire.outputs import ARRAYS
from v2v_wire.protocol import OUTPUTS, check_outputs

#: Wire dtypes of dense flow (``v2v_wire.outputs``).
FLOW_DTYPES = ARRAYS["flow"].dtypes


@dataclass(frozen=True, init=False)
class SampleRecipe:
    """The sample recipe: everything that decides a sample's content.

    Defaults follow the paper's WebVid recipe: ``sequence_length`` L voxel grids of
    ``num_bins`` B bins, ``frames_per_bin`` frame pairs per bin, so a sample spans
    ``L * B * frames_per_bin + 1`` frame indices (201 by default). Spatial: the top
    ``keep_top_fraction`` of each frame is kept (WebVid watermark), a random ``crop_size`` x
    ``crop_size`` crop (pixels) is taken, flipped horizontally with probability ``hflip_prob``.
    Pauses: a per-frame Markov chain repeats the previous frame.

    Built from flat keys (``SampleRecipe(seed=3, shot_cuts="off")``): its own, and those of the
    parts it composes (:attr:`PARTS`), which build them; a part's key reads through the recipe
    too (``recipe.shot_cuts`` is ``recipe.windows.shot_cuts``). A part given whole
    (``windows=WindowSettings(...)``, as ``dataclasses.replace`` gives it) stands for its keys.

    Attributes:
        windows: where this recipe's windows lie (``frames.windows.WindowSettings``), with the
            window span the recipe's keys decide (:attr:`frames_per_sample`).
        decode: how its frames are decoded (``frames.frame_pass.DecodeSettings``).

    Raises:
        ValueError: naming the key, for an unknown key or a bad value.
    """

    #: The frames stage's settings the recipe composes: (attribute, class).
    PARTS = (("windows", WindowSettings), ("decode", DecodeSettings))

    seed: int = setting(0, help="base seed: sample content depends only on (seed, epoch, sample id)")
    sequence_length: int = setting(40, help="voxel grids per sample, L")
    num_bins: int = setting(5, help="temporal bins per voxel grid, B")
    frames_per_bin: int = setting(1, help="frame pairs summed into one bin; a sample spans L x B x this + 1 frames")
    crop_size: int = setting(128, help="square crop side, pixels")
    hflip_prob: float = setting(0.5, help="probability of a horizontal flip")
    crops_per_window: int = setting(1, help="random crops per decoded window, each its own sample (own crop, flip, "
                                            "pauses, sensor parameters; ids path#window.crop when > 1)")
    pause_enabled: bool = setting(True, help="pause augmentation (a Markov chain repeating the previous frame)")
    p_pause_when_running: float = setting(0.0102, help="probability that a pause starts at a frame")
    p_pause_when_paused: float = setting(0.9791, help="probability that a pause goes on at a frame")
    outputs: Tuple[str, ...] = setting(OUTPUTS, help="what clients may ask for (comma list)", cli=str)
    flow_preset: str = setting(DEFAULT_FLOW, help="optical flow option (docs/flow.md)", choices=tuple(FLOW_OPTIONS))
    flow_dtype: str = setting("float16", help="wire dtype of flow", choices=FLOW_DTYPES)
    ranges: ParamRanges = setting(help="sensor parameter ranges: threshold, ratio, noise_std, hot_pixel_fraction, "
                                       "hot_pixel_std as [lo, hi] (WebVid ranges)", flag="", factory=ParamRanges)
    refine: str = setting("off", help="off | uniform:K | adaptive:PX | adaptive-dl:L: sub-frames where motion needs "
                                      "them (docs/fidelity.md)")
    nonidealities: dict = setting(help="sensor non-idealities, all off by default (v2v_server/simulation/nonideal.py)", flag="",
                                  factory=dict)
    degrade_dynamic_range: dict = setting(help="{probability, scale: [lo, hi]}: dynamic-range degradation before V2V "
                                               "(paper appendix 'Dataset quality'; true = 0.8, [1, 3])", flag="",
                                          factory=dict)
    fixed_sensor_params: bool = setting(False, help="each video keeps one (c+, c-) drawn from (seed, video) for every "
                                                    "window and epoch (the paper's '-F' datasets)")
    windows: WindowSettings = dataclasses.field(default=None)
    decode: DecodeSettings = dataclasses.field(default=None)

    def __init__(self, **keys):
        for attr, part in self.PARTS:  # a part given whole stands for its keys
            given = keys.pop(attr, None)
            if given is not None:
                keys = {**{f.name: getattr(given, f.name) for f in documented(part)}, **keys}
        groups = split_keys(SampleRecipe, keys)
        for f in dataclasses.fields(self):
            if f.name in groups[""]:
                object.__setattr__(self, f.name, groups[""][f.name])
            elif f.name not in groups:
                object.__setattr__(self, f.name, f.default_factory() if f.default is dataclasses.MISSING
                                   else f.default)
        self._build(groups)

    def __getattr__(self, name: str):
        """A part's key, read through the recipe (``recipe.shot_cuts``)."""
        part = _PART_KEYS.get(name)
        if part is None or part not in self.__dict__:  # not a key, or the recipe is not built yet
            raise AttributeError(f"SampleRecipe has no key {name!r}")
        return getattr(self.__dict__[part], name)

    @property
    def frames_per_sample(self) -> int:
        """Frame indices one sample spans: L * B * frames_per_bin + 1."""
        return self.sequence_length * self.num_bins * self.frames_per_bin + 1

    def epoch_samples(self, windows: int) -> int:
        """Samples an epoch holds of ``windows`` windows: each window gives ``crops_per_window``
        samples (ids ``path#window.crop``, ``v2v_wire.ids``). What ``--check``, the server's
        start, the Ray engine's count and their progress bars report."""
        return windows * self.crops_per_window

    @cached_property
    def refine_spec(self):
        """``refine`` parsed (``simulation.refine.RefineSpec``), once per recipe: what each window's
        simulation is given."""
        from v2v_server.simulation.refine import parse_refine

        return parse_refine(self.refine)

    @cached_property
    def nonideal_spec(self):
        """``nonidealities`` parsed (``simulation.nonideal.NonIdealities``), once per recipe."""
        from v2v_server.simulation.nonideal import NonIdealities

        return NonIdealities.from_dict(self.nonidealities or None)

    @cached_property
    def reads(self) -> PassRecord:
        """What a pass over a video reads under this recipe (``frames.pass_record.PassRecord``):
        the frame cache's, the corpus index's and the window pass's one key."""
        return PassRecord.of(self.decode, self.windows)

    def fingerprint(self) -> str:
        """A short hash of what decides a sample's content: the recipe less the outputs each
        client asks for and the decoding threads, its pass settings as the pass record gives
        them (:attr:`reads`, ``PassRecord.content``: the shot detector's version with
        ``shot_cuts: avoid``, the motion measure's with ``static_windows: skip``, a setting at
        its neutral value left out): sample ids name the same samples only under the same
        fingerprint."""
        reads = self.reads.content()
        del reads["frames_per_sample"]  # sequence_length, num_bins and frames_per_bin, beside it, name it
        content = {k: v for k, v in self.recipe_dict().items() if k != "outputs" and _PART_KEYS.get(k) is None}
        content.update(reads)
        return hashlib.sha256(json.dumps(content, sort_keys=True, default=str).encode()).hexdigest()[:16]

    def recipe_dict(self) -> dict:
        """Every key of the recipe, its parts' included, flat, as a plain, msgpack/YAML-safe dict
        (ranges as lists): what a fitted recipe file or a fingerprint is made of."""
        d = {f.name: getattr(self, f.name) for f in documented(SampleRecipe)}
        d.update(ranges=self.ranges.to_dict(), outputs=list(self.outputs))
        return d

    def _build(self, parts: dict):
        """Check the recipe's fields (``ValueError`` names the first bad one) and normalise them;
        builds :attr:`windows` and :attr:`decode` from their keys in ``parts`` (``split_keys``),
        which check them."""
        _set = object.__setattr__  # a frozen recipe normalises its own fields once, here
        for name in ("sequence_length", "num_bins", "frames_per_bin", "crops_per_window"):
            check_int(name, getattr(self, name), 1)
        check_int("seed", self.seed, 0)
        for name in ("hflip_prob", "p_pause_when_running", "p_pause_when_paused"):
            _set(self, name, check_prob(name, getattr(self, name)))
        _set(self, "windows", WindowSettings(**parts["windows"], frames_per_sample=self.frames_per_sample))
        _set(self, "decode", DecodeSettings(**parts["decode"]))
        check_int("crop_size", self.crop_size, 8, 4096, "pixels")
        if self.frame_height and math.floor(self.frame_height * self.keep_top_fraction) < self.crop_size:
            raise ValueError(f"frame_height {self.frame_height} keeps {math.floor(self.frame_height * self.keep_top_fraction)}"
                             f" rows (keep_top_fraction {self.keep_top_fraction}), fewer than crop_size "
                             f"{self.crop_size}: every crop would be enlarged again; use frame_height >= "
                             f"{math.ceil(self.crop_size / self.keep_top_fraction)} or 0 (no scaling)")
        _set(self, "outputs", check_outputs(self.outputs))
        _set(self, "flow_preset", check_option(self.flow_preset).name)  # ValueError naming flow_preset
        why = unavailable_reason(self.flow_preset)
        if why:
            raise ValueError(f"flow_preset {self.flow_preset!r} cannot run here: {why}")
        check_choice("flow_dtype", self.flow_dtype, FLOW_DTYPES)
        if not isinstance(self.ranges, ParamRanges):
            _set(self, "ranges", ParamRanges.from_dict(self.ranges))
        from v2v_server.samples.augment import parse_degrade
        from v2v_server.simulation.nonideal import NonIdealities
        from v2v_server.simulation.refine import parse_refine

        _set(self, "refine", str(parse_refine(self.refine)))
        ni = NonIdealities.from_dict(self.nonidealities or None)  # ValueError naming nonidealities.<field>
        _set(self, "nonidealities", ni.to_dict() if ni.enabled else {})
        if "polarity_counts" in self.outputs and (self.nonidealities or self.refine != "off"):
            # N+ and N- come from plain V2V's kernel call only: not offered under refinement or
            # non-idealities (the stream info lists the outputs served; a fetch naming another is
            # refused in one line)
            if self.outputs != OUTPUTS:
                raise ValueError("outputs: polarity_counts is made by plain V2V only (refine: off, no "
                                 f"nonidealities); got refine {self.refine!r}, nonidealities {self.nonidealities}")
            _set(self, "outputs", tuple(o for o in self.outputs if o != "polarity_counts"))
        _set(self, "degrade_dynamic_range", parse_degrade(self.degrade_dynamic_range))
        check_bool("pause_enabled", self.pause_enabled)
        check_bool("fixed_sensor_params", self.fixed_sensor_params)


#: A part's key -> the recipe's attribute holding that part.
_PART_KEYS = {k: part for k, part in owners(SampleRecipe).items() if part}

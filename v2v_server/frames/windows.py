"""The frames stage's window settings: where a video's windows lie.

A window is ``frames_per_sample`` source frames (201 at the paper's recipe); windows follow each
other ``window_stride`` (200) apart, so a window's last frame is the next one's first, as in the
authors' loader (HYLZ-2019/V2V ``data/v2v_datasets.py``, ``step_size = frames_per_seq``).
``shot_cuts`` decides whether they start at each shot's first frame (``avoid``) or at k x stride
from frame 0 (``off``): ``shots.WindowLayout``. The defaults of these values have one owner, the
sample recipe (``v2v_server.samples.recipe.SampleRecipe``), which builds a :class:`WindowSettings`
for this stage (and a ``frame_pass.DecodeSettings`` for how frames are decoded); the checks of the
values this class holds are here.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from v2v_server.checks import check_choice, check_int
from v2v_server.frames.motion import STATIC_MOTION
from v2v_server.frames.shots import SHOT_CUTS, WindowLayout
from v2v_server.settings import setting

#: What ``static_windows`` takes: keep static windows (the paper's) or skip them (docs/fidelity.md).
STATIC_WINDOWS = ("keep", "skip")


@dataclass(frozen=True)
class WindowSettings:
    """Where a video's windows lie, and so how many of its frames a pass reads.

    Attributes:
        max_samples_per_video: windows a video gives at most per epoch (>= 1).
        shot_cuts: ``"avoid"`` (windows inside one shot) or ``"off"`` (k x stride), ``shots.SHOT_CUTS``.
        static_windows: ``"keep"`` or ``"skip"`` windows whose motion is below
            ``motion.STATIC_MOTION`` (decided from the frames, before simulation).
        frames_per_sample: source frames one window spans (>= 2; ``L x B x frames_per_bin + 1``,
            given by the recipe, whose keys decide it: not a key of its own).

    Raises:
        ValueError: naming the field, for a value out of its range.
    """

    max_samples_per_video: int = setting(10, help="windows (samples with crops_per_window 1) per video per epoch")
    shot_cuts: str = setting("avoid", help="avoid: windows lie inside one shot (they start at each shot's first "
                                           "frame + k x stride; shot cuts found while decoding, docs/corpora.md); "
                                           "off: windows at k x stride whatever they hold (the authors' loader)",
                             choices=SHOT_CUTS)
    static_windows: str = setting("keep", help="keep: every window (the paper's pauses and still shots included); skip: "
                                                "windows whose frames barely change (motion below "
                                                f"{STATIC_MOTION} log intensity a frame pair) give no sample, decided "
                                                "before simulation (docs/fidelity.md)", choices=STATIC_WINDOWS)
    frames_per_sample: int = field(kw_only=True)

    def __post_init__(self):
        check_int("frames_per_sample", self.frames_per_sample, 2)
        check_int("max_samples_per_video", self.max_samples_per_video, 1)
        check_choice("shot_cuts", self.shot_cuts, SHOT_CUTS)
        check_choice("static_windows", self.static_windows, STATIC_WINDOWS)

    @property
    def window_stride(self) -> int:
        """Source frames from one window's start to the next: ``frames_per_sample - 1``, so every
        frame pair of a video is in exactly one window."""
        return self.frames_per_sample - 1

    @property
    def avoid_cuts(self) -> bool:
        """Whether windows lie inside one shot (``shot_cuts: avoid``)."""
        return self.shot_cuts == "avoid"

    @property
    def skip_static(self) -> bool:
        """Whether static windows are skipped (``static_windows: skip``)."""
        return self.static_windows == "skip"

    @property
    def reads_frames(self) -> bool:
        """Whether where windows lie depends on the frames (their cuts, or which are static), so
        a count of windows must decode them."""
        return self.avoid_cuts or self.skip_static

    def short_of(self, listed_frames: float) -> Optional[str]:
        """Why a video a list counts ``listed_frames`` frames for holds no window (fewer than
        ``frames_per_sample``, less half a frame: a table's numbers are rounded, OpenVid's
        seconds to 1/100 s), or None when it may hold one. The rule a source's table reader is
        given for the rows it leaves unopened (``video_tables.TableSettings.unopened``)."""
        if listed_frames < self.frames_per_sample - 0.5:
            return f"below one window's {self.frames_per_sample} frames"
        return None

    def windows_in(self, frames: int) -> int:
        """Windows a video of ``frames`` frames holds laid out from frame 0, at most ``max_samples_per_video``."""
        return max(0, min(self.max_samples_per_video, (frames - 1) // self.window_stride))

    def slots_at_most(self, frames: int, crops_per_window: int = 1) -> int:
        """Samples a video of ``frames`` frames can give per epoch at most, whatever ``shot_cuts``
        and ``static_windows`` say: :meth:`windows_in` ``(frames)`` x ``crops_per_window``. Known
        before a decode from a packet count (``video_read.read_video(..., part="packets")``), it
        is how many slots a plan can hold for the video; those its decode leaves empty are padding.

        Why a bound: a window takes ``window_stride`` frame pairs of its own (consecutive windows
        share one frame, never a pair), so ``frames`` frames hold at most ``(frames - 1) //
        window_stride`` windows; laying them out inside shots (each starts at its shot's first
        frame + k x stride) or skipping static ones only leaves pairs unused. It bounds the decode's
        windows only while the decode gives no more frames than were counted (the video's packets:
        one frame each in the containers served; ``bench/plan_slots.py`` measures it).

        Raises:
            ValueError: ``frames`` < 0 or ``crops_per_window`` < 1.
        """
        check_int("frames", frames, 0)
        check_int("crops_per_window", crops_per_window, 1)
        return self.windows_in(frames) * crops_per_window

    def frames_for(self, windows: int) -> int:
        """Frames to decode for the first ``windows`` windows: ``windows * window_stride + 1``."""
        return windows * self.window_stride + 1 if windows > 0 else 0

    def worth_decoding(self, declared: int) -> int:
        """Windows worth decoding: whole windows only. When the container declares its frame
        count (``declared``, 0 when it does not) the trailing partial window is not decoded
        (decoding is the cost that matters)."""
        n = self.max_samples_per_video
        return min(n, self.windows_in(declared)) if declared >= self.frames_per_sample else n

    def frame_limit(self, declared: int) -> int:
        """Frames a pass may read: those of the windows the declared frame count allows; with
        ``shot_cuts: avoid`` every declared frame (where windows lie depends on the cuts; the
        pass ends once the last window is complete, ``WindowLayout.done``); so with
        ``static_windows: skip``, whose skipped windows are replaced by later ones."""
        if self.reads_frames:
            return declared if declared >= self.frames_per_sample else (1 << 62)
        return self.frames_for(self.worth_decoding(declared))

    def layout(self, declared: int = 0) -> WindowLayout:
        """The windows of a video whose container declares ``declared`` frames (0: unknown)."""
        return WindowLayout(self.frames_per_sample, self.worth_decoding(declared), self.avoid_cuts, self.skip_static)

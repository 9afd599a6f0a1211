"""The videos stage's settings: where a video's windows lie and which frames a pass reads.

A window is ``frames_per_sample`` source frames (201 at the paper's recipe); windows follow each
other ``window_stride`` (200) apart, so a window's last frame is the next one's first, as in the
authors' loader (HYLZ-2019/V2V ``data/v2v_datasets.py``, ``step_size = frames_per_seq``).
``shot_cuts`` decides whether they start at each shot's first frame (``avoid``) or at k x stride
from frame 0 (``off``): ``shots.WindowLayout``. The defaults of these values have one owner, the
sample recipe (``v2v_server.samples.recipe.SampleRecipe``), which builds a :class:`WindowSettings`
for this stage; the checks of the values this stage reads are here.
"""
from __future__ import annotations

from dataclasses import dataclass

from v2v_server.checks import check_choice, check_int
from v2v_server.videos.decode import DECODE_FAST
from v2v_server.videos.frame_cache import decode_settings
from v2v_server.videos.frames import kept_rows
from v2v_server.videos.motion import MOTION_VERSION, STATIC_MOTION
from v2v_server.videos.shots import DETECTOR_VERSION, SHOT_CUTS, WindowLayout

#: What ``static_windows`` takes: keep static windows (the paper's) or skip them (docs/fidelity.md).
STATIC_WINDOWS = ("keep", "skip")
#: Largest frame_height (8K UHD).
MAX_FRAME_HEIGHT = 4320


@dataclass(frozen=True)
class WindowSettings:
    """What decides the frames a pass over a video reads and where its windows lie.

    Attributes:
        frames_per_sample: source frames one window spans (>= 2; ``L x B x frames_per_bin + 1``).
        max_windows: windows a video gives at most per epoch (>= 1).
        shot_cuts: ``"avoid"`` (windows inside one shot) or ``"off"`` (k x stride), ``shots.SHOT_CUTS``.
        keep_top_fraction: share of a displayed frame's height kept from the top, in (0, 1].
        crop_size: square crop side, pixels (a file must give a kept region to crop from).
        frame_height: scale decoded frames to this height, pixels (0 = as decoded).
        decode_threads: FFmpeg threads per pass (>= 1).
        decode_fast: the decoder shortcut, ``decode.DECODE_FAST``.
        static_windows: ``"keep"`` or ``"skip"`` windows whose motion is below
            ``motion.STATIC_MOTION`` (decided from the frames, before simulation).

    Raises:
        ValueError: naming the field, for a value out of its range.
    """

    frames_per_sample: int
    max_windows: int
    shot_cuts: str
    keep_top_fraction: float
    crop_size: int
    frame_height: int = 0
    decode_threads: int = 1
    decode_fast: str = "off"
    static_windows: str = "keep"

    def __post_init__(self):
        check_int("frames_per_sample", self.frames_per_sample, 2)
        check_int("max_samples_per_video", self.max_windows, 1)
        check_choice("shot_cuts", self.shot_cuts, SHOT_CUTS)
        if not isinstance(self.keep_top_fraction, (int, float)) or isinstance(self.keep_top_fraction, bool) \
                or not (0 < self.keep_top_fraction <= 1):
            raise ValueError(f"keep_top_fraction must be in (0, 1], got {self.keep_top_fraction!r}")
        check_int("crop_size", self.crop_size, 8, 4096, "pixels")
        check_int("frame_height", self.frame_height, 0, MAX_FRAME_HEIGHT, "pixels; 0 = no scaling")
        check_int("decode_threads", self.decode_threads, 1)
        check_choice("decode_fast", self.decode_fast, tuple(DECODE_FAST))
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

    def windows_in(self, frames: int) -> int:
        """Windows a video of ``frames`` frames holds laid out from frame 0, at most ``max_windows``."""
        return max(0, min(self.max_windows, (frames - 1) // self.window_stride))

    def frames_for(self, windows: int) -> int:
        """Frames to decode for the first ``windows`` windows: ``windows * window_stride + 1``."""
        return windows * self.window_stride + 1 if windows > 0 else 0

    def kept_rows(self, height: int) -> int:
        """Rows kept from the top of a displayed frame of ``height`` pixels (``frames.kept_rows``)."""
        return kept_rows(self.keep_top_fraction, height)

    def worth_decoding(self, declared: int) -> int:
        """Windows worth decoding: whole windows only. When the container declares its frame
        count (``declared``, 0 when it does not) the trailing partial window is not decoded
        (decoding is the cost that matters)."""
        n = self.max_windows
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

    def frame_settings(self) -> dict:
        """The settings that change the frames a pass reads (``frame_cache.decode_settings``):
        what, with the corpus and the video, names a frame-cache entry."""
        settings = decode_settings(self.decode_fast, self.keep_top_fraction, self.frames_per_sample,
                                   self.max_windows, self.frame_height)
        if self.avoid_cuts:  # the entry holds the frames up to the last window, and the cuts this detector found
            settings["shots"] = DETECTOR_VERSION
        if self.skip_static:  # and the frames of the windows that replace static ones
            settings["static"] = f"{MOTION_VERSION}<{STATIC_MOTION}"
        return settings

"""What a pass over a video reads, as one frozen record, and the one key derived from it.

Every setting that changes the frames a pass gives or where its windows lie is a field of
:class:`PassRecord`: the decoder shortcut, the frame scale, the rows kept, the window layout
(span, window count, shot cuts, static windows) and the versions of the shot detector and of the
motion measure that place windows. Its :attr:`PassRecord.key` is the one key of those settings:

* the frame cache names an entry by it (``frame_pass.entry_settings``, with the corpus and the video);
* the corpus index keys a row's window layout by it (``corpus_index.layout_key``: the record of
  ``--check``'s pass, which scores shot cuts whatever ``shot_cuts`` says; the sample pass's
  under ``shot_cuts: avoid``);
* the window pass records it as the layout of a video's verdict (``window_pass.VideoPass.layout``);
* the sample recipe's fingerprint takes the record's :meth:`PassRecord.content`
  (``samples.recipe.SampleRecipe.fingerprint``).

The video's own identity (the corpus, its id path, ``VideoSource.identity``) is not a field:
the cache and the index pair the key with it per video (an entry's name and trailer, a row's
location and identity), while the fingerprint is the same for every video.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from typing import Optional

from v2v_server.frames.motion import MOTION_VERSION, STATIC_MOTION
from v2v_server.frames.shots import DETECTOR_VERSION

#: Version of the key's content: a change makes every frame-cache entry and index row a miss.
PASS_VERSION = 1


@dataclass(frozen=True)
class PassRecord:
    """What a pass over a video reads, beside the video (module docstring); built by :meth:`of`.

    Attributes:
        decode_fast: the decoder shortcut (``decode.DECODE_FAST``).
        keep_top_fraction: share of a displayed frame's height kept from the top, in (0, 1].
        frame_height: decoded frames scaled to this height, pixels (0 = as decoded).
        frames_per_sample: source frames one window spans.
        max_samples_per_video: windows a pass reads at most.
        shot_cuts: ``"avoid"`` or ``"off"`` (``shots.SHOT_CUTS``).
        static_windows: ``"keep"`` or ``"skip"`` (``windows.STATIC_WINDOWS``).
        shot_detector: the version of the shot detector whose cuts the pass finds (with
            ``shot_cuts: avoid`` they place windows; ``--check`` reports them), else ``""``.
        static_motion: ``"MOTION_VERSION<STATIC_MOTION"`` with ``static_windows: skip`` (the
            measure and threshold decide which windows are static), else ``""``.
    """

    decode_fast: str
    keep_top_fraction: float
    frame_height: int
    frames_per_sample: int
    max_samples_per_video: int
    shot_cuts: str
    static_windows: str
    shot_detector: str = ""
    static_motion: str = ""

    @classmethod
    def of(cls, decode, windows, scores_cuts: Optional[bool] = None) -> "PassRecord":
        """The record of a pass decoding as ``decode`` says (``frame_pass.DecodeSettings``) over the
        windows of ``windows`` (``windows.WindowSettings``), with this build's detector and
        motion versions where they decide what the pass gives. ``scores_cuts``: the pass scores
        shot cuts (None: where windows follow them, ``shot_cuts: avoid``, as a sample pass
        does; True for ``--check``'s pass, which reports the cuts whatever ``shot_cuts`` says)."""
        detects = windows.avoid_cuts if scores_cuts is None else bool(scores_cuts)
        return cls(decode.decode_fast, decode.keep_top_fraction, int(decode.frame_height),
                   int(windows.frames_per_sample), int(windows.max_samples_per_video), windows.shot_cuts,
                   windows.static_windows, DETECTOR_VERSION if detects else "",
                   f"{MOTION_VERSION}<{STATIC_MOTION}" if windows.skip_static else "")

    def content(self) -> dict:
        """The record as a plain dict under the recipe's key names, a key left out at its
        neutral value (``frame_height`` 0: no scaling; ``static_windows`` keep; a version not
        in use), so that a setting added at its neutral value keeps every key as it is."""
        d = {"decode_fast": self.decode_fast, "keep_top_fraction": self.keep_top_fraction,
             "frames_per_sample": int(self.frames_per_sample), "max_samples_per_video": int(self.max_samples_per_video),
             "shot_cuts": self.shot_cuts}
        if self.frame_height:
            d["frame_height"] = int(self.frame_height)
        if self.static_windows != "keep":
            d["static_windows"] = self.static_windows
        if self.shot_detector:
            d["shot_detector"] = self.shot_detector
        if self.static_motion:
            d["static_motion"] = self.static_motion
        return d

    @property
    def key(self) -> str:
        """The one key of what a pass reads: 16 hex digits of the SHA-256 of :meth:`content`
        with :data:`PASS_VERSION`."""
        text = json.dumps({"v": PASS_VERSION, **self.content()}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

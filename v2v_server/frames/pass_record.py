"""What a pass over a video reads, as one frozen record, and the one key derived from it.

Every setting that changes the frames a pass gives or where its windows lie is in
:class:`PassRecord`, which holds the stage's own settings rather than copies of their keys: the
``DecodeSettings`` (decoder shortcut, frame scale, rows kept) and the ``WindowSettings`` (span,
window count, shot cuts, static windows), with the versions of the shot detector and of the
motion measure that place windows. A new field of either part is in the key by itself. Its :attr:`PassRecord.key` is the one key of those settings:

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
from dataclasses import dataclass, fields
from typing import Optional

from v2v_server.frames.motion import MOTION_VERSION, STATIC_MOTION
from v2v_server.frames.shots import DETECTOR_VERSION

#: Version of the key's content: a change makes every frame-cache entry and index row a miss.
PASS_VERSION = 1


#: Settings of the parts that do not change what a pass reads: how many threads decode it.
UNREAD = frozenset({"decode_threads"})

#: Settings added after the key's first version, left out of it at the value that reads as before
#: (``frame_height`` 0: no scaling; ``static_windows`` keep), so that the keys made before them stay.
NEUTRAL = {"frame_height": 0, "static_windows": "keep"}


@dataclass(frozen=True, eq=False)
class PassRecord:
    """What a pass over a video reads, beside the video (module docstring); built by :meth:`of`.
    Two records are equal when they read the same (:meth:`content`): a setting outside it
    (``decode_threads``) makes no other record.

    Attributes:
        decode: how frames are decoded (``frame_pass.DecodeSettings``: decoder shortcut, frame
            scale, rows kept; its threads are not read, :data:`UNREAD`).
        windows: where windows lie (``windows.WindowSettings``: span, window count, shot cuts,
            static windows).
        shot_detector: the version of the shot detector whose cuts the pass finds (with
            ``shot_cuts: avoid`` they place windows; ``--check`` reports them), else ``""``.
        static_motion: ``"MOTION_VERSION<STATIC_MOTION"`` with ``static_windows: skip`` (the
            measure and threshold decide which windows are static), else ``""``.
    """

    decode: object  # frame_pass.DecodeSettings (frame_pass names this module's record: no import back)
    windows: object  # windows.WindowSettings
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
        return cls(decode, windows, DETECTOR_VERSION if detects else "",
                   f"{MOTION_VERSION}<{STATIC_MOTION}" if windows.skip_static else "")

    @property
    def scores_cuts(self) -> bool:
        """Whether the pass scores shot cuts (``shots.ShotDetector``)."""
        return bool(self.shot_detector)

    def values(self) -> dict:
        """Every value the record holds, under the recipe's key names: each field of its parts
        but :data:`UNREAD`, then the versions."""
        d = {f.name: getattr(part, f.name) for part in (self.decode, self.windows) for f in fields(part)
             if f.name not in UNREAD}
        d.update(shot_detector=self.shot_detector, static_motion=self.static_motion)
        return d

    def content(self) -> dict:
        """:meth:`values` less a setting at its neutral value (:data:`NEUTRAL`) and a version not
        in use, so that a setting added at its neutral value keeps every key as it is."""
        return {k: v for k, v in self.values().items() if v != NEUTRAL.get(k, "")}

    def __eq__(self, other) -> bool:
        return isinstance(other, PassRecord) and self.content() == other.content()

    def __hash__(self) -> int:
        return hash(self.key)

    @property
    def key(self) -> str:
        """The one key of what a pass reads: 16 hex digits of the SHA-256 of :meth:`content`
        with :data:`PASS_VERSION`."""
        text = json.dumps({"v": PASS_VERSION, **self.content()}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

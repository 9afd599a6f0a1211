"""Sample keys and sample ids: the one place a sample's identity is made, numbered and written.

A sample is named by its :class:`SampleKey` ``(video, window, crop)``: the video's path relative
to the corpus root (POSIX), the window index and the crop index inside the window (0 .. K - 1
with K = ``crops_per_window``). The plan, the server's scheduler and the workers' messages carry
keys. The string form, the *sample id*, is made and read only at the edges (logs,
the ``sample_ids`` of a batch): the path, ``#``, the window index and, when K > 1,
``.`` and the crop index: ``clips/a.mp4#3`` or ``clips/a.mp4#3.1``. The *ordinal*
``window * K + crop`` (``SampleKey.ordinal``) numbers a video's samples in the order they are
made: how many samples a file gave, where a pass over it stopped.
Pure: no I/O, no numpy.
"""
from __future__ import annotations

from typing import List, NamedTuple


class SampleKey(NamedTuple):
    """The identity of one sample: ``video`` (corpus-relative POSIX path), ``window`` (index of
    the window in the video, >= 0), ``crop`` (index of the crop in the window, 0 .. K - 1).
    Immutable, hashable, ordered as the samples of a video are made (window, then crop). A
    named tuple: hashing and comparing cost what a tuple's do (the scheduler keeps sets of
    keys), and a plain tuple is still not a ``SampleKey`` (``isinstance``)."""

    video: str
    window: int
    crop: int = 0

    def ordinal(self, crops_per_window: int = 1) -> int:
        """The sample's number in its video, ``window * crops_per_window + crop``."""
        return self.window * crops_per_window + self.crop

    @classmethod
    def at(cls, video: str, index: int, crops_per_window: int = 1) -> "SampleKey":
        """The key of sample number ``index`` of ``video`` (the inverse of :meth:`ordinal`)."""
        window, crop = divmod(index, crops_per_window)
        return cls(video, window, crop)

    def sample_id(self, crops_per_window: int = 1) -> str:
        """The string form (see :func:`make_sample_id`)."""
        return make_sample_id(self.video, self.window, self.crop, crops_per_window)

    def wire(self) -> List:
        """``[video, window, crop]``: the key in a msgpack message (:meth:`from_wire` reads it)."""
        return [self.video, self.window, self.crop]

    @classmethod
    def from_wire(cls, value, crops_per_window: int = 1) -> "SampleKey":
        """The key of a message's ``[video, window, crop]``.

        Raises:
            ValueError: for anything else (a non-string or overlong video, a negative or
                non-integer window, a crop outside 0 .. ``crops_per_window`` - 1), naming it.
        """
        ok = isinstance(value, (list, tuple)) and len(value) == 3
        if ok:
            video, window, crop = value
            ok = (isinstance(video, str) and 0 < len(video) <= 4096 and _small_int(window)
                  and _small_int(crop) and crop < crops_per_window)
        if not ok:
            raise ValueError(f"sample key must be [video, window, crop] with crop < {crops_per_window}, "
                             f"got {value!r:.80}")
        return cls(video, window, crop)


def _small_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 10 ** 9


def window_keys(video: str, window: int, crops_per_window: int = 1) -> List[SampleKey]:
    """The ``crops_per_window`` keys of one window, in crop order."""
    return [SampleKey(video, window, c) for c in range(crops_per_window)]


def make_sample_id(rel_path: str, window: int, crop: int = 0, crops_per_window: int = 1) -> str:
    """Stable sample id: the video's path relative to the corpus root (POSIX), ``#``, the
    window index and, when ``crops_per_window`` > 1, ``.`` and the crop index:
    ``clips/a.mp4#3`` (one crop per window: the ids of a run without crops) or
    ``clips/a.mp4#3.1``. The inverse is :func:`parse_sample_id`."""
    if crops_per_window == 1:
        return f"{rel_path}#{window}"
    return f"{rel_path}#{window}.{crop}"


def parse_sample_id(sample_id: str, crops_per_window: int = 1) -> SampleKey:
    """The :class:`SampleKey` of a sample id made by :func:`make_sample_id`.

    Raises:
        ValueError: for an id that is not ``path#window`` (K = 1) or ``path#window.crop``
            (K > 1, crop < K), naming the id.
    """
    if not isinstance(sample_id, str) or len(sample_id) > 4096:
        raise ValueError(f"sample id must be a string of at most 4096 characters, got {sample_id!r:.80}")
    video, sep, tail = sample_id.rpartition("#")
    window, dot, crop = tail.partition(".")
    ok = bool(sep and video and window.isdigit() and window.isascii() and len(window) <= 9 and len(crop) <= 9)
    if crops_per_window == 1:
        ok = ok and not dot
        c = 0
    else:
        ok = ok and bool(dot) and crop.isdigit() and crop.isascii() and int(crop) < crops_per_window
        c = int(crop) if ok else 0
    if not ok:
        form = "path#window" if crops_per_window == 1 else f"path#window.crop (crop < {crops_per_window})"
        raise ValueError(f"sample id {sample_id!r} is not of the form {form}")
    return SampleKey(video, int(window), c)

"""``v2v-serve --check``: decode every file of a corpus and say what it is worth, before
training; and what the host's corpus index knows of a listing at a server's start."""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Dict, Iterator, List, NamedTuple, Optional, Sequence, Tuple

from v2v_server.frames.corpus_index import Verdict, check_record, layout_key
from v2v_server.sources.names import VideoError
from v2v_server.frames.decode import DecodedFrame, decode_frames, frame_intervals, open_video
from v2v_server.frames.frame_pass import DecodeSettings, FramePass, PassFrame
from v2v_server.sources.local import LocalSource
from v2v_server.sources.segments import split_segment
from v2v_server.frames.shots import ShotDetector
from v2v_server.sources.source import VideoSource
from v2v_server.frames.host_caches import HostCaches
from v2v_server.frames.video_pool import map_videos
from v2v_server.frames.window_pass import VideoPass, WindowPass
from v2v_server.frames.windows import WindowSettings


#: Spread of a file's frame intervals (longest less shortest), as a share of the median one, above
#: which ``--check`` reports a variable frame rate (timestamp rounding stays far below it).
VFR_SPREAD = 0.1


def check_video(windows: WindowSettings, decode: DecodeSettings, source: VideoSource, rel: str,
                caches: Optional[HostCaches] = None) -> Verdict:
    """The :class:`~v2v_server.frames.corpus_index.Verdict` of one file of ``source`` (the
    corpus), never raising for a bad file (its failure is the verdict's reason): the window
    pass's record (``window_pass.VideoPass``, windows laid out by ``windows``) of the frames the
    workers cut (scaled and kept rows as ``decode`` says), scored by the same detector; a
    frame's size in a message is the whole displayed frame's.

    Answered from the host's corpus index (``caches.corpus_index()``; none without ``caches``)
    while the file's identity holds, else by decoding it; a verdict that decoding reached without
    an error (a read failure may be passing) is recorded there for the next pass."""
    index = caches.corpus_index() if caches is not None else None
    identity = _identity(source, rel) if index is not None else None  # before decoding: what the verdict is of
    known = indexed_verdict(windows, decode, source, rel, caches)
    if known is not None:
        return known
    variable_rate = ""  # what only this pass measures (frame timing), beside the window pass's verdict
    found = WindowPass(windows, check_record(windows, decode))
    times: list = []  # presentation times, for a variable frame rate
    error = None
    try:
        with source.open(rel) as path:
            container, stream, info = open_video(path)
            detector = ShotDetector()
            # the rows the sample pass scores and cuts; a size change is named by the displayed frame's
            decoded = decode_frames(container, stream, decode.kept_rows, decode.frame_height, split_segment(rel)[1])
            for _ in found.over(FramePass(info, 0, _timed(decoded, detector, times), False)):
                pass
        gaps = frame_intervals(times)
        if gaps and gaps[2] - gaps[0] > VFR_SPREAD * gaps[1]:
            variable_rate = (f"variable frame rate: frame intervals {gaps[0] * 1e3:.3g}-{gaps[2] * 1e3:.3g} "
                             f"ms, taken as if evenly spaced at the average {info.fps:.3g} fps")
    except Exception as e:  # report every failure as a verdict; one bad file never stops the check
        error = e
    out = dataclasses.replace(pass_verdict(windows, rel, found.record(error)), variable_rate=variable_rate)
    if index is not None and error is None:
        index.record(source.where(rel), identity, layout_key(windows, decode), out)
    return out


def _timed(decoded: Iterator[DecodedFrame], detector: ShotDetector, times: list) -> Iterator[PassFrame]:
    """The pass frames of ``decoded`` scored by ``detector``, each named by its displayed size;
    each frame's presentation time is appended to ``times``."""
    for d in decoded:
        times.append(d.time)
        yield PassFrame(d.codes, d.expand, detector.score(d.codes, d.expand), (d.shown_height, d.codes.shape[1]))


def _identity(source: VideoSource, rel: str):
    """The identity of the video at ``rel`` now (``VideoSource.identity``), None when it is
    missing or unreadable (decoding says why)."""
    try:
        return source.identity(rel)
    except VideoError:
        return None


def indexed_verdict(windows: WindowSettings, decode: DecodeSettings, source: VideoSource, rel: str,
                    caches: Optional[HostCaches]):
    """``check_video``'s verdict of the video at ``rel`` as the host's corpus index
    (``caches.corpus_index()``) holds it (the video's identity unchanged, the entry made by a
    pass that timed frames), or None."""
    index = caches.corpus_index() if caches is not None else None
    if index is None:
        return None
    known = index.lookup(source.where(rel), _identity(source, rel), layout_key(windows, decode))
    if known is not None and known.frame_timing:  # a sample pass's entry lacks --check's timing
        return dataclasses.replace(known, path=rel)
    return None


def pass_verdict(windows: WindowSettings, rel: str, record: VideoPass) -> Verdict:
    """``check_video``'s verdict of the video at ``rel`` from a window pass's ``record``
    (``window_pass.VideoPass``), frame timing aside (``cause``: the reason's code,
    ``window_pass.judged``; windows before a failure still count)."""
    count, failed, cause, reason = record.judged(windows)
    return Verdict(path=rel, usable=count > 0, windows=count, frames=record.frames, reason=reason or "", cause=cause,
                   cuts=tuple(record.cuts), dropped=record.dropped, stream=record.stream(),
                   failed_windows=tuple(failed), static=record.static, more=record.complete)


def record_pass(windows: WindowSettings, decode: DecodeSettings, source: VideoSource, rel: str,
                record: VideoPass, caches: Optional[HostCaches]) -> bool:
    """Keep what a sample pass or ``--warm-cache`` found of the video at ``rel`` in the host's
    corpus index, so that the server's next start knows its windows without ``--check``: when
    the pass ran whole (no error), with shot detection (``shot_cuts: avoid``: an entry holds
    the cuts found, as ``--check``'s do), and no entry holds for the video yet. These passes
    do not time frames, so the entry says ``frame_timing: False`` and ``--check`` decodes the
    video again for its own line. An index that cannot be written is one warning; the pass's
    samples are unaffected. Returns whether an entry was written (never without ``caches``)."""
    if record.error is not None or not windows.avoid_cuts:
        return False
    index = caches.corpus_index() if caches is not None else None
    if index is None:
        return False
    where, key, identity = source.where(rel), layout_key(windows, decode), source.listed_identity(rel)
    if identity is None or index.lookup(where, identity, key) is not None:
        return False
    verdict = dataclasses.replace(pass_verdict(windows, rel, record), frame_timing=False)
    return index.record(where, identity, key, verdict)


class KnownWindows(NamedTuple):
    """What the corpus index says of a listing at a server's start (:func:`known_windows`):
    ``known``, how many of its videos it knows; ``samples``, their samples per epoch together;
    ``empty``, those known to give no window -> ``(cause, reason)``, the verdict's reason and
    its code (``window_pass.judged``)."""

    known: int
    samples: int
    empty: Dict[str, Tuple[str, str]]


def known_windows(windows: WindowSettings, decode: DecodeSettings, source: VideoSource,
                  videos: Sequence[str], caches: Optional[HostCaches]) -> KnownWindows:
    """What the host's corpus index knows of ``videos`` under the layout of ``windows`` and
    ``decode`` (``corpus_index.layout_key``), each video's identity unchanged
    (``source.listed_identity``: a file's status, a store's listing, no request per object).
    The server reads it at start: an epoch's size when every video is known, and the videos not
    worth opening. Nothing is known without an index (``caches.corpus_index()``)."""
    index = caches.corpus_index() if caches is not None else None
    known, samples, empty = 0, 0, {}
    if index is None:
        return KnownWindows(0, 0, empty)
    for rel, n, cause, reason in index.windows(((rel, source.where(rel), source.listed_identity(rel))
                                                for rel in videos), layout_key(windows, decode)):
        known, samples = known + 1, samples + n
        if n == 0:
            empty[rel] = (cause, reason)
    if index.fault is not None:  # a fault on the way: nothing it answered is trusted
        return KnownWindows(0, 0, {})
    return KnownWindows(known, samples, empty)


def check_corpus(windows: WindowSettings, decode: DecodeSettings, source: VideoSource, videos: List[str],
                 processes: int = 1, caches: Optional[HostCaches] = None) -> List[Verdict]:
    """``check_video`` for every file of ``source``, in ``processes`` processes (``source`` and
    ``caches`` themselves in this one, or built once in each of them from their ``spec()``,
    ``video_pool.map_videos``). The corpus index (``caches.corpus_index()``) is
    opened here first, and for a folder (a video's identity is a ``stat``) its answers are read
    here: a fault of the index is then found (and named) once, in this process, the processes
    leave it off, and only the videos it does not know are decoded. A store's identities cost
    a request each, made by the processes in parallel, which read its answers themselves."""
    local = isinstance(source, LocalSource)
    index = caches.corpus_index() if caches is not None else None
    known = {rel: indexed_verdict(windows, decode, source, rel, caches) if local and index is not None else None
             for rel in videos}
    todo = [rel for rel in videos if known[rel] is None]
    made = dict(zip(todo, map_videos(check_video, (windows, decode), source, caches, todo, processes)))
    return [known[rel] or made[rel] for rel in videos]


def format_check(results: List[Verdict], rejected: List[Tuple[str, str]], crops_per_window: int = 1) -> str:
    """A table: one line per file with its verdict (its windows), then a summary line: the
    samples an epoch holds, ``crops_per_window`` per window (``SampleRecipe.epoch_samples``)."""
    lines = [f"{'file':<48} {'verdict':<12} detail"]
    for r in results:
        verdict = f"{r.windows} window(s)" if r.usable else "unusable"
        cuts = r.cuts
        shots = (f"; {len(cuts)} cut(s) at frame(s) {', '.join(map(str, cuts[:12]))}{' ...' if len(cuts) > 12 else ''}"
                 if cuts else "; no cut in the frames read" if r.more else "; one shot")
        if r.dropped:
            shots += f", {r.dropped} window(s) removed by cuts"
        if r.static:
            shots += f", {r.static} static window(s) skipped"
        size = r.stream.text() if r.stream is not None else ""
        detail = (f"{r.frames}{'+' if r.more else ''} frames, {size}" if r.usable else r.reason) + \
            (shots if r.frames else "")
        if r.usable and r.failed_windows:
            detail += f"; {r.reason}"
        if r.usable and r.variable_rate:
            detail += f"; {r.variable_rate}"
        lines.append(f"{r.path:<48} {verdict:<12} {detail}")
    for rel, reason in rejected:
        lines.append(f"{Path(rel).as_posix():<48} {'ignored':<12} {reason}")
    usable = [r for r in results if r.usable]
    windows = sum(r.windows for r in usable)
    crops = f" ({windows} window(s) x {crops_per_window} crops)" if crops_per_window > 1 else ""
    lines.append(f"{len(usable)} usable video(s) of {len(results)}, {windows * crops_per_window} sample(s) "
                 f"per epoch{crops}; {sum(len(r.cuts) for r in results)} shot cut(s) found, "
                 f"{sum(r.dropped for r in results)} window(s) removed by cuts; "
                 f"{len(rejected)} other entr{'y' if len(rejected) == 1 else 'ies'} ignored")
    return "\n".join(lines)

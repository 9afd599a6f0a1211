"""``v2v-serve --check``: decode every file of a corpus and say what it is worth, before
training."""
from __future__ import annotations

from pathlib import Path
from typing import List, Optional, Tuple

from v2v_server.frames.corpus_index import Verdict, check_record
from v2v_server.frames.frame_pass import DecodeSettings
from v2v_server.sources.segments import split_segment
from v2v_server.sources.source import VideoSource
from v2v_server.frames.host_caches import HostCaches
from v2v_server.frames.pass_record import PassRecord
from v2v_server.frames.video_pool import map_videos
from v2v_server.frames.video_read import read_video
from v2v_server.frames.windows import WindowSettings


def check_video(windows: WindowSettings, decode: DecodeSettings, source: VideoSource, rel: str,
                caches: Optional[HostCaches] = None) -> Verdict:
    """The :class:`~v2v_server.frames.corpus_index.Verdict` of one file of ``source`` (the
    corpus), never raising for a bad file (its failure is the verdict's reason): the timed read
    (``video_read.read_video``, part ``"timed"``) of the frames the workers cut (scaled and kept
    rows as ``decode`` says), windows laid out by ``windows`` and shot cuts scored whatever
    ``shot_cuts`` says (``corpus_index.check_record``); a frame's size in a message is the whole
    displayed frame's. Answered from the host's corpus index (``caches.corpus_index()``; none
    without ``caches``) while the file's identity holds, else recorded there once read."""
    with read_video(source, rel, check_record(windows, decode), caches, part="timed") as read:
        for _ in read.frames:
            pass
    return read.verdict()


#: The corpus index's layout prefix of a packet count's bound (``count_windows``), kept apart from
#: the windows a decode found: a server serving by plan counts each video by one rule, whatever
#: else the host read of it, so a server started again gives the same manifest.
PACKETS_LAYOUT = "packets:"


def count_windows(windows: WindowSettings, decode: DecodeSettings, reads: PassRecord, source: VideoSource, rel: str,
                  caches: Optional[HostCaches] = None) -> Tuple[int, Optional[str]]:
    """Windows the video at ``rel`` of ``source`` gives per epoch, read the one way every reader
    reads a video (``video_read.read_video``) for the part the count needs: its video packets
    (demuxed, not decoded), the packet count bounding the windows (``WindowSettings.slots_at_most``;
    exact while a decode gives a frame per packet, docs/plan_slots.md); with ``shot_cuts: avoid``
    or ``static_windows: skip``, or for a segment, its decoded frames as :func:`check_video` reads
    them (the windows depend on the cuts, the motion or the range's frames; answered from the
    corpus index of ``caches`` while the video's identity holds; a packet count is kept there
    too, under :data:`PACKETS_LAYOUT`, so a server started again reads no packet). ``reads``:
    the sample pass's record (``SampleRecipe.reads``).

    Returns ``(windows, reason)``: ``reason`` is ``None`` for a usable file, else the text
    ``v2v-serve`` logs for it. A file whose packets demux but whose frames do not decode is found
    out later, while decoding, with the decoder's reason.
    """
    if windows.reads_frames or split_segment(rel)[1]:
        v = check_video(windows, decode, source, rel, caches)
        return v.windows, (None if v.usable else v.reason)
    index = caches.corpus_index() if caches is not None else None
    where, layout = source.where(rel), PACKETS_LAYOUT + reads.key
    identity = source.listed_identity(rel) if index is not None else None
    v = index.lookup(where, identity, layout) if identity is not None else None
    if v is None:
        with read_video(source, rel, reads, part="packets") as read:
            for _ in read.frames:
                pass
        v = read.verdict()
        if identity is not None and read.error is None:
            index.record(where, identity, layout, v)
    return v.windows, (None if v.usable else v.reason)


def check_corpus(windows: WindowSettings, decode: DecodeSettings, source: VideoSource, videos: List[str],
                 processes: int = 1, caches: Optional[HostCaches] = None) -> List[Verdict]:
    """``check_video`` for every file of ``source``, in ``processes`` processes (``source`` and
    ``caches`` themselves in this one, or built once in each of them from their ``spec()``,
    ``video_pool.map_videos``). The corpus index (``caches.corpus_index()``) is
    opened here first, and for a folder (a video's identity is a ``stat``) its answers are read
    here: a fault of the index is then found (and named) once, in this process, the processes
    leave it off, and only the videos it does not know are decoded. A store's identities cost
    a request each, made by the processes in parallel, which read its answers themselves."""
    here = not source.identity_costs_request and caches is not None and caches.corpus_index() is not None
    reads = check_record(windows, decode)
    known = {rel: read_video(source, rel, reads, caches, part="timed").known if here else None for rel in videos}
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

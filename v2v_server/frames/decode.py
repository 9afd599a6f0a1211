"""Video decoding with PyAV (FFmpeg): display-oriented, full-range luma, one function for
every reader (serving, ``--check``, evaluation, benchmarks).

The paper's reference loader reads frames with OpenCV and converts BGR to grey, so its frames
span the full 0..255 range. Most videos store *limited-range* luma (Y in 16..235 for 8 bits,
64..940 for 10 bits; ITU-R BT.601/709). :func:`decode_luma` reads plane 0 of YUV frames as is
(no colour conversion, no chroma) and expands it to full range with one lookup table per
stream, unless the stream is already full range (``yuvj*`` pixel formats or
``color_range`` = JPEG/pc; grey formats unless they say MPEG/tv). Sources deeper than 8 bits
come out as uint16 spanning 0..65535 (the V2V core's uint16 input); 8-bit sources as uint8.
Frames carrying a display matrix (phone videos) are rotated as a player would show them.
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, Iterator, NamedTuple, Optional, Sequence, Tuple, Union

import numpy as np

from v2v_server.sources.errors import VideoError

#: Pixel formats whose plane 0 is 8-bit luma: read directly, no colour conversion.
_Y8_FORMATS = {"yuv420p", "yuvj420p", "yuv422p", "yuvj422p", "yuv444p", "yuvj444p", "nv12", "nv21", "gray",
               "yuv410p", "yuv411p", "yuv440p", "yuvj440p", "yuva420p", "yuva422p", "yuva444p"}
#: Rows kept from the top of each displayed frame: all (None), a count, or a function of the height.
Rows = Union[None, int, Callable[[int], int]]
#: FFmpeg ``AVColorRange`` values (``frame.color_range``).
COLOR_RANGE_MPEG, COLOR_RANGE_JPEG = 1, 2


@dataclass
class VideoInfo:
    """Container facts of the chosen video stream: coded frame size in pixels (before the
    display rotation), average frame rate in Hz, codec and pixel format names, stream index."""

    width: int
    height: int
    fps: float
    codec: str
    pix_fmt: str
    stream_index: int = 0


def range_table(bits: int, full_range: bool) -> Optional[np.ndarray]:
    """Lookup table from ``bits``-bit luma codes to full-range output.

    Limited range maps ``16 << (bits - 8)`` to 0 and ``235 << (bits - 8)`` to the output's
    full scale, rounding and clipping (codes below/above the nominal range, footroom and
    headroom, clip to 0 / full scale). Full range only rescales. The output is uint8 (full
    scale 255) for 8-bit sources and uint16 (full scale 65535) for deeper ones.

    Returns:
        uint8 or uint16 (2**bits,) table, or ``None`` for 8-bit full range (identity).

    Raises:
        ValueError: ``bits`` outside 8..16.
    """
    if not 8 <= bits <= 16:
        raise ValueError(f"luma bit depth must be 8..16, got {bits}")
    if bits == 8 and full_range:
        return None
    top, dtype = (255, np.uint8) if bits == 8 else (65535, np.uint16)
    codes = np.arange(1 << bits, dtype=np.float64)
    if full_range:
        out = codes * (top / ((1 << bits) - 1))
    else:
        lo, hi = 16 << (bits - 8), 235 << (bits - 8)
        out = (codes - lo) * (top / (hi - lo))
    return np.clip(np.rint(out), 0, top).astype(dtype)


def is_full_range(pix_fmt: str, color_range: int) -> bool:
    """True when luma codes already span the full range: ``yuvj*`` formats, frames tagged
    JPEG/pc range, and grey formats not tagged MPEG/tv range; everything else (untagged YUV
    included, as FFmpeg assumes) is limited range."""
    if pix_fmt.startswith("yuvj") or int(color_range) == COLOR_RANGE_JPEG:
        return True
    return pix_fmt.startswith("gray") and int(color_range) != COLOR_RANGE_MPEG


def full_range(a: np.ndarray) -> np.ndarray:
    """The ``expand`` of codes already at full range (8-bit full-range streams, cached frames): ``a`` itself."""
    return a


def _unit_stride(a: np.ndarray) -> np.ndarray:
    """``a`` itself when its rows are unit-stride and go forward (what OpenCV reads without a
    copy), else a C-contiguous copy (rotated views)."""
    return a if a.strides[1] == a.itemsize and a.strides[0] > 0 else np.ascontiguousarray(a)


def _converter(frame) -> Tuple[Callable[[object], np.ndarray], Callable[[np.ndarray], np.ndarray]]:
    """``(codes, expand)`` for frames of this frame's layout: ``codes(frame)`` is a view of
    plane 0 (coded orientation) and ``expand(codes)`` maps it to full range through
    :func:`range_table` (planar YUV / grey layouts). Every other layout (RGB, paletted,
    semi-planar high bit depth...) goes through swscale's grey conversion, which is already
    full range, and ``expand`` is the identity."""
    import cv2

    fmt = frame.format
    name = fmt.name
    bits = int(fmt.components[0].bits) if fmt.components else 8
    full = is_full_range(name, frame.color_range)
    if name in _Y8_FORMATS:
        table = range_table(8, full)

        def y8(fr):
            plane = fr.planes[0]
            return np.frombuffer(plane, dtype=np.uint8).reshape(fr.height, plane.line_size)[:, :fr.width]
        return y8, (full_range if table is None else (lambda a: cv2.LUT(_unit_stride(a), table)))
    if 8 < bits <= 16 and name.endswith("le") and name.startswith(("yuv", "gray")):
        table = range_table(bits, full)  # LSB-aligned little-endian codes

        def y16(fr):
            plane = fr.planes[0]
            return np.frombuffer(plane, dtype="<u2").reshape(fr.height, plane.line_size // 2)[:, :fr.width]
        return y16, (lambda a: np.take(table, a, mode="clip"))
    if bits > 8:
        return (lambda fr: fr.to_ndarray(format="gray16le")), full_range
    return (lambda fr: fr.to_ndarray(format="gray")), full_range


def frame_intervals(times: Sequence[Optional[float]]) -> Optional[Tuple[float, float, float]]:
    """``(shortest, median, longest)`` interval in seconds between consecutive presentation
    times ``times`` (frames without one left out; a time that goes back, as where a stream's
    timestamps restart, bounds no interval); None with fewer than two intervals."""
    t = np.array([x for x in times if x is not None], dtype=np.float64)
    d = np.diff(t)
    d = d[d > 0]
    if len(d) < 2:
        return None
    return float(d.min()), float(np.median(d)), float(d.max())


def display_rotation(frame) -> int:
    """Counter-clockwise rotation in quarter turns (0..3) that the frame's display matrix asks
    for (``VideoFrame.rotation``, rounded to a multiple of 90 degrees); 0 without one. Flips
    in the matrix are not applied."""
    try:
        deg = frame.rotation
    except Exception:  # no side data, or a PyAV without it
        return 0
    return int(round(float(deg or 0) / 90.0)) % 4


def _codes(frame, conv) -> np.ndarray:
    """Plane-0 codes of ``frame`` (a view where possible), display-oriented."""
    y = conv[0](frame)
    k = display_rotation(frame)
    if k:
        y = np.rot90(y, k)
    return y


def choose_video_stream(streams: Sequence):
    """The stream to decode among a container's video streams: attached pictures (cover art)
    are never chosen; among the rest, the one with the most frames (the container's count,
    else duration x frame rate), then the one marked default, then the first.

    Returns the stream or ``None`` when there is none but attached pictures."""
    import av

    def disp(s) -> int:
        try:
            return int(s.disposition)
        except Exception:
            return 0

    cand = [s for s in streams if not disp(s) & int(av.stream.Disposition.attached_pic)]
    if not cand:
        return None

    def est_frames(s) -> float:
        if s.frames:
            return float(s.frames)
        rate = s.average_rate or s.guessed_rate
        if s.duration and s.time_base and rate:
            return float(s.duration * s.time_base * rate)
        dur = (s.metadata or {}).get("DURATION")  # Matroska keeps it as a tag
        if dur and rate:
            try:
                h, m, sec = dur.split(":")
                return (int(h) * 3600 + int(m) * 60 + float(sec)) * float(rate)
            except ValueError:
                pass
        return 0.0

    default = int(av.stream.Disposition.default)
    return max(cand, key=lambda s: (s.codec_context is not None, est_frames(s), bool(disp(s) & default), -s.index))


#: Decoder shortcuts by ``decode_fast`` name: FFmpeg codec options (``AVCodecContext``) that
#: skip H.264's deblocking (loop) filter on some frames, a speed/accuracy trade measured in
#: docs/decode_fast.md (``python -m bench.decode_fast``). The frame count and timing never
#: change (no frame is skipped), only the pixels of the frames whose filter is skipped.
DECODE_FAST = {
    "off": {},
    "noref": {"skip_loop_filter": "noref"},  # frames no other frame references: errors do not propagate
    "bidir": {"skip_loop_filter": "bidir"},  # B-frames
    "all": {"skip_loop_filter": "all"},  # every frame: errors propagate through prediction
}


def open_video(path, threads: int = 1, fast: str = "off"):
    """Open ``path`` with PyAV and return ``(container, stream, info)``; ``fast`` names a
    ``DECODE_FAST`` setting (decoder options applied when the decoder opens). ``path`` is a
    file path or a readable, seekable binary file object (an object-store file from
    ``store.StoreSource.open``: FFmpeg reads and seeks through it); the caller closes a file
    object after the container.

    Raises:
        VideoError: the file cannot be opened or holds no video stream.
        ValueError: for an unknown ``fast``.
    """
    if fast not in DECODE_FAST:
        raise ValueError(f"decode_fast must be one of {list(DECODE_FAST)}, got {fast!r}")
    import av

    is_file = hasattr(path, "read")
    try:
        if (getattr(path, "size", None) if is_file else Path(path).stat().st_size) == 0:
            raise VideoError("empty file (0 bytes)")
    except OSError as e:
        raise VideoError(f"cannot read: {e.strerror or e}") from None
    try:
        container = av.open(path if is_file else str(path), mode="r")
    except Exception as e:  # av raises many error types (InvalidDataError, OSError...)
        raise VideoError(f"cannot open: {type(e).__name__}: {e}") from None
    stream = choose_video_stream(list(container.streams.video))
    if stream is None:
        n = len(container.streams.video)
        container.close()
        raise VideoError("no video stream" + (f" (only {n} attached picture(s))" if n else ""))
    if stream.codec_context is None:
        tag = getattr(stream, "codec_tag", "") or "?"
        container.close()
        raise VideoError(f"unsupported codec (tag {tag!r}): no decoder")
    stream.thread_type = "AUTO" if threads > 1 else "SLICE"
    stream.codec_context.thread_count = threads
    if DECODE_FAST[fast]:
        stream.codec_context.options = dict(DECODE_FAST[fast])
    cc = stream.codec_context
    rate = stream.average_rate or stream.guessed_rate
    info = VideoInfo(
        width=int(cc.width or 0), height=int(cc.height or 0), fps=float(rate) if rate else 0.0,
        codec=str(cc.name), pix_fmt=str(cc.pix_fmt), stream_index=int(stream.index),
    )
    if info.width <= 0 or info.height <= 0:
        container.close()
        raise VideoError("video stream has no frame size")
    return container, stream, info


def iter_luma(path: Path, threads: int = 1, rows: Rows = None, height: int = 0) -> Iterator[np.ndarray]:
    """Decode ``path`` sequentially and yield each frame's full-range, display-oriented luma
    (see :func:`decode_luma`), scaled to ``height`` rows when it is not 0.

    Raises:
        VideoError: as ``open_video`` and ``decode_luma``.
    """
    container, stream, _ = open_video(path, threads)
    return decode_luma(container, stream, rows, height)


def scaled_size(height: int, width: int, frame_height: int) -> Tuple[int, int]:
    """``(rows, columns)`` of a displayed ``height`` x ``width`` frame scaled to ``frame_height``
    rows, its aspect ratio kept (columns rounded, at least 1); ``(height, width)`` when
    ``frame_height`` is 0 (no scaling)."""
    if not frame_height:
        return height, width
    return frame_height, max(1, int(round(width * frame_height / height)))


def feeding_rows(height: int, frame_height: int, kept: int) -> int:
    """Rows from the top of a displayed ``height``-row frame that the top ``kept`` rows of it
    scaled to ``frame_height`` rows (:func:`scale_frame`) are made from.

    INTER_AREA gives output row ``y`` the source rows its area ``[y s, (y + 1) s)`` overlaps,
    ``s = height / frame_height`` (averaged when shrinking; when enlarging, the one or two rows
    it lies over, the second weighted 0 unless the area crosses into it). The kept rows therefore
    read source rows ``0 .. ceil(kept s) - 1``; one more row is fed so that OpenCV's
    floating-point cell at that edge is never cut by the frame's end. All ``height`` rows when
    that reaches the end."""
    return min(height, -(-kept * height // frame_height) + 1)


def scale_frame(luma: np.ndarray, frame_height: int, rows: Rows = None,
                expand: Callable[[np.ndarray], np.ndarray] = full_range) -> np.ndarray:
    """The top ``rows`` of a displayed frame scaled to ``frame_height`` rows (width per
    :func:`scaled_size`) with OpenCV's ``INTER_AREA`` (pixel-area averaging when shrinking,
    bilinear when enlarging), as uint8 or uint16 (rows', W') full-range luma.

    ``luma``: (H, W) uint8 or uint16, full-range luma, or codes that ``expand`` maps to full
    range (:func:`decode_codes`' pairs): scaling averages intensities, so it acts on full-range
    luma, never on codes. ``rows``: as :data:`Rows`, of the *scaled* height (``None``: all).
    Only the source rows that feed the kept rows are expanded and resized
    (:func:`feeding_rows`), with the scale factor of the whole frame, so the result equals
    ``cv2.resize(expand(luma), (W', frame_height), INTER_AREA)[:rows]`` value for value
    (``tests/test_frame_scale.py`` checks this over random sizes, scale factors and row counts).
    ``expand(luma)[:rows]`` (no resize) when H already is ``frame_height``."""
    import cv2

    h, w = scaled_size(luma.shape[0], luma.shape[1], frame_height)
    kept = h if rows is None else min(h, rows(h) if callable(rows) else rows)
    if (h, w) == luma.shape:
        return _unit_stride(expand(luma[:kept]))
    height, width = luma.shape
    n = feeding_rows(height, h, max(kept, 1))
    fx, fy = w / width, h / height  # the whole frame's factors, as cv2.resize(luma, (w, h)) takes them
    if (int(round(n * fy)), w) == (n, width):
        n = height  # the cut would scale 1:1, which OpenCV answers with a copy instead of INTER_AREA
    src = _unit_stride(expand(luma[:n]))
    out = cv2.resize(src, None, fx=fx, fy=fy, interpolation=cv2.INTER_AREA)
    return out[:kept]


class DecodedFrame(NamedTuple):
    """One frame as :func:`decode_frames` yields it.

    Attributes:
        codes: the display-oriented, row-cut plane-0 array as stored (a view, possibly
            strided), or with a frame height the full-range scaled rows (:func:`decode_codes`).
        expand: maps ``codes`` or any crop or flip of it to full-range luma.
        shown_height: rows of the displayed frame (rotated, and scaled to the frame height
            when one is set) before the kept rows are cut from it, pixels.
        time: presentation time in seconds from the stream's start, None when the frame has none.
    """

    codes: np.ndarray
    expand: Callable[[np.ndarray], np.ndarray]
    shown_height: int
    time: Optional[float]


def decode_codes(container, stream, rows: Rows = None, height: int = 0,
                 segment: Optional[Tuple[float, float]] = None) -> Iterator[Tuple[np.ndarray, Callable[[np.ndarray], np.ndarray]]]:
    """``(codes, expand)`` of each frame :func:`decode_frames` yields (its arguments and errors):
    what a pass cuts windows from. Closes the container when done."""
    with contextlib.closing(decode_frames(container, stream, rows, height, segment)) as frames:
        for f in frames:
            yield f.codes, f.expand


def decode_frames(container, stream, rows: Rows = None, height: int = 0,
                  segment: Optional[Tuple[float, float]] = None) -> Iterator[DecodedFrame]:
    """Like :func:`decode_luma`, but yield a :class:`DecodedFrame` per frame: its ``codes``
    (display-oriented, row-cut plane-0 array as stored) and ``expand``, which maps ``codes`` or
    any crop or flip of it to full-range luma. Expansion is per pixel, so expanding a crop
    equals cropping the expanded frame, at a fraction of the cost; resampling must expand first.
    ``segment``: a time range ``(start, end)`` in seconds from the stream's start
    (``sources.segments``): the container seeks to the key frame before ``start`` and only
    frames whose presentation time lies in ``[start, end)`` are yielded. Closes the container
    when done.

    With ``height`` > 0 every displayed frame is expanded to full range and scaled to
    ``height`` rows, and ``rows`` cut from the scaled frame (a function ``rows`` gets the
    scaled height): :func:`scale_frame`, which expands and scales only the source rows that
    feed the kept rows. ``codes`` is then that full-range frame and ``expand`` is
    :func:`full_range`. Frames come in presentation order; their times are facts only
    (windows count frames, whatever their spacing).

    Raises:
        VideoError: when decoding fails part-way (the frames yielded before were good), or a
            segment holds no frame (it starts after the video ends, or the frames carry no
            timestamps).
    """
    import av

    convs: Dict[tuple, tuple] = {}
    kept = 0
    try:
        frames = container.decode(stream)
        if segment is not None:
            frames = _in_range(container, stream, frames, *segment)
        for frame in frames:
            key = (frame.format.name, int(frame.color_range))
            conv = convs.get(key)
            if conv is None:
                conv = convs[key] = _converter(frame)
            kept += 1
            shown = _codes(frame, conv)
            if not height:
                cut = shown[: (rows(shown.shape[0]) if callable(rows) else rows)] if rows is not None else shown
                yield DecodedFrame(cut, conv[1], shown.shape[0], frame.time)
                continue
            yield DecodedFrame(scale_frame(shown, height, rows, conv[1]), full_range,
                               scaled_size(shown.shape[0], shown.shape[1], height)[0], frame.time)
        if segment is not None and kept == 0:
            length = float(stream.duration * stream.time_base) if stream.duration and stream.time_base else \
                (container.duration or 0) / 1e6
            raise VideoError(f"no frame in the time range {segment[0]:g}-{segment[1]:g} s (the video lasts {length:.3g} s)")
    except av.error.FFmpegError as e:
        raise VideoError(f"decoding failed: {type(e).__name__}: {e}") from None
    finally:
        container.close()


def _in_range(container, stream, frames, start: float, end: float):
    """The frames of ``frames`` whose time from the stream's start lies in ``[start, end)``,
    after seeking ``container`` to the key frame at or before ``start``.

    Raises:
        VideoError: a frame has no timestamp (a range cannot be cut from it)."""
    tb = stream.time_base
    first = stream.start_time or 0
    if start > 0 and tb:
        container.seek(first + int(start / tb), stream=stream, backward=True, any_frame=False)
        frames = container.decode(stream)
    for frame in frames:
        pts = frame.pts
        if pts is None or not tb:
            raise VideoError("frames carry no timestamps: a time range cannot be cut from this video")
        t = float((pts - first) * tb)
        if t >= end:
            return
        if t >= start - 1e-6:
            yield frame


def decode_luma(container, stream, rows: Rows = None, height: int = 0) -> Iterator[np.ndarray]:
    """Yield the luma of each frame of an ``open_video`` result; closes the container when
    done (or when the generator is closed). With :func:`decode_codes` (its lazy form), this
    is the one place frames are read.

    Each frame is uint8 (H', W) spanning 0..255 for 8-bit sources, uint16 (H', W) spanning
    0..65535 for 9- to 16-bit sources: limited-range luma is expanded to full range, as the
    reference loader's BGR -> grey conversion does (module docstring), and a display matrix
    rotates the frame as a player shows it (H, W are then the displayed height and width).
    ``rows`` keeps only the top rows of each displayed frame: ``None`` all, an int, or a
    function of the displayed height. ``height`` > 0 scales each displayed frame to that many
    rows before ``rows`` are cut (see :func:`decode_codes`). The yielded array may be a view
    into the decoder's buffer, valid until the next frame: copy what you keep.

    Raises:
        VideoError: when decoding fails part-way (the frames yielded before were good).
    """
    gen = decode_codes(container, stream, rows, height)
    try:
        for codes, expand in gen:
            yield _unit_stride(expand(codes))
    finally:
        gen.close()

"""Video decoding with PyAV (FFmpeg), luma only where the decoder allows it."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, List, Optional, Sequence, Tuple

import numpy as np

#: Pixel formats whose plane 0 is 8-bit luma: read directly, no colour conversion.
_Y8_FORMATS = {"yuv420p", "yuvj420p", "yuv422p", "yuvj422p", "yuv444p", "yuvj444p", "nv12", "nv21", "gray",
               "yuv410p", "yuv411p", "yuv440p", "yuvj440p", "yuva420p"}


class VideoError(RuntimeError):
    """A file that cannot be used as a video (the message says why)."""


@dataclass
class VideoInfo:
    """Container facts: frame size in pixels, average frame rate in Hz, codec name."""

    width: int
    height: int
    fps: float
    codec: str
    pix_fmt: str


def _luma(frame) -> np.ndarray:
    """(H, W) uint8 luma of a decoded ``av.VideoFrame``."""
    fmt = frame.format.name
    if fmt in _Y8_FORMATS:
        plane = frame.planes[0]
        h, w = frame.height, frame.width
        a = np.frombuffer(plane, dtype=np.uint8).reshape(h, plane.line_size)
        return a[:, :w]
    # other layouts (RGB, 10-bit YUV, paletted...): let swscale produce 8-bit gray
    return frame.to_ndarray(format="gray")


def open_video(path: Path, threads: int = 1):
    """Open ``path`` with PyAV and return ``(container, stream, info)``.

    Raises:
        VideoError: the file cannot be opened or holds no video stream.
    """
    import av

    try:
        if Path(path).stat().st_size == 0:
            raise VideoError("empty file (0 bytes)")
    except OSError as e:
        raise VideoError(f"cannot read: {e.strerror or e}") from None
    try:
        container = av.open(str(path), mode="r")
    except Exception as e:  # av raises many error types (InvalidDataError, OSError...)
        raise VideoError(f"cannot open: {type(e).__name__}: {e}") from None
    if not container.streams.video:
        container.close()
        raise VideoError("no video stream")
    stream = container.streams.video[0]
    if stream.codec_context is None:
        tag = getattr(stream, "codec_tag", "") or "?"
        container.close()
        raise VideoError(f"unsupported codec (tag {tag!r}): no decoder")
    stream.thread_type = "AUTO" if threads > 1 else "SLICE"
    stream.codec_context.thread_count = threads
    cc = stream.codec_context
    rate = stream.average_rate or stream.guessed_rate
    info = VideoInfo(
        width=int(cc.width or 0), height=int(cc.height or 0), fps=float(rate) if rate else 0.0,
        codec=str(cc.name), pix_fmt=str(cc.pix_fmt),
    )
    if info.width <= 0 or info.height <= 0:
        container.close()
        raise VideoError("video stream has no frame size")
    return container, stream, info


def iter_luma(path: Path, threads: int = 1, rows: Optional[int] = None) -> Iterator[np.ndarray]:
    """Decode ``path`` sequentially and yield each frame's luma, uint8 (H', W).

    Args:
        path: video file.
        threads: decoder threads.
        rows: keep only the top ``rows`` rows of each frame (``None``: all).

    Raises:
        VideoError: as ``open_video`` and ``decode_luma``.
    """
    container, stream, _ = open_video(path, threads)
    return decode_luma(container, stream, rows)


def decode_luma(container, stream, rows: Optional[int] = None) -> Iterator[np.ndarray]:
    """Yield the luma of each frame of an ``open_video`` result, uint8 (H', W); closes the
    container when done (or when the generator is closed).

    ``rows`` keeps only the top rows of each frame (``None``: all). The yielded array is a
    view into the decoder's buffer, valid until the next frame: copy what you keep.

    Raises:
        VideoError: when decoding fails part-way (the frames yielded before were good).
    """
    import av

    try:
        for frame in container.decode(stream):
            y = _luma(frame)
            yield y if rows is None else y[:rows]
    except av.error.FFmpegError as e:
        raise VideoError(f"decoding failed: {type(e).__name__}: {e}") from None
    finally:
        container.close()


def inside(root: Path, path: Path) -> bool:
    """True when ``path`` resolves (symlinks followed) to a file under ``root``."""
    try:
        return path.resolve(strict=True).is_relative_to(Path(root).resolve(strict=True))
    except (OSError, RuntimeError):
        return False


def scan_corpus(root: Path, extensions: Sequence[str]) -> Tuple[List[Path], List[Tuple[Path, str]]]:
    """Walk ``root`` recursively (sorted, symlink loops cut) for video files.

    Returns ``(videos, rejected)``: video paths relative to ``root`` with an accepted
    extension, and ``(relative path, reason)`` for every other entry met: other extensions,
    symlink loops, dangling links, links that leave the corpus root, unreadable folders.
    """
    root = Path(root)
    videos: List[Path] = []
    rejected: List[Tuple[Path, str]] = []
    seen_dirs = set()
    stack = [root]
    while stack:
        d = stack.pop()
        try:
            real = d.resolve(strict=True)
        except (OSError, RuntimeError) as e:
            rejected.append((d.relative_to(root), f"folder cannot be resolved: {e}"))
            continue
        if real in seen_dirs:
            continue
        seen_dirs.add(real)
        try:
            entries = sorted(d.iterdir())
        except OSError as e:
            rejected.append((d.relative_to(root), f"folder cannot be read: {e.strerror or e}"))
            continue
        for p in entries:
            rel = p.relative_to(root)
            try:
                target = p.resolve(strict=True)
            except RuntimeError:
                rejected.append((rel, "symlink loop"))
                continue
            except OSError as e:
                reason = "symlink loop" if e.errno == 40 else "dangling symlink" if p.is_symlink() else str(e)
                rejected.append((rel, reason))
                continue
            if not inside(root, p):
                rejected.append((rel, "points outside the corpus root"))
                continue
            if target.is_dir():
                stack.append(p)
            elif p.suffix.lower() in extensions and target.is_file():
                videos.append(rel)
            else:
                rejected.append((rel, f"not a video file (extension {p.suffix or 'none'!r})"))
    key = lambda p: p.as_posix()  # noqa: E731
    return sorted(videos, key=key), sorted(rejected, key=lambda r: key(r[0]))


def find_videos(root: Path, extensions: Sequence[str]) -> List[Path]:
    """Video files under ``root`` (see ``scan_corpus``), relative to ``root``."""
    return scan_corpus(root, extensions)[0]

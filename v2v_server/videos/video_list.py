"""Video lists: a file of the V2V authors' format that selects and orders the videos of a corpus
(a local file, or an object beside the corpus in the store), read by every ``VideoSource``."""
from __future__ import annotations

from pathlib import Path
from typing import List, Union

from v2v_server.videos.segments import is_time, parse_time, segment_name


def is_url(videos: Union[str, Path, None]) -> bool:
    """True for a corpus given as a URL (``s3://``, ``gs://``...), False for a local folder
    (``file://`` URLs included: they are folders)."""
    return isinstance(videos, str) and "://" in videos and not videos.startswith("file://")


def read_video_list(path: str) -> List[str]:
    """The videos a list file names, in its order, duplicates dropped: the V2V authors' format
    (HYLZ-2019/V2V ``config/webvid10000_unfiltered.txt``): one video per line, its first
    whitespace-separated field a path relative to the corpus root (later fields, such as
    frame counts, are ignored); ``#`` starts a comment line; blank lines are skipped. Leading
    ``./`` is dropped so ids match a folder's listing. A line of exactly three fields ``path start
    end`` whose second and third are times (seconds, or ``H:MM:SS.sss``: Panda-70M's clip
    timestamps) names the segment ``path#t=start,end`` (``videos.segments``); a video may have
    several. The authors' lines carry one or three numbers after the path and stay whole videos.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: naming the file, when it lists nothing.
    """
    if is_url(path):  # a list kept beside the corpus in the store
        import fsspec

        with fsspec.open(path, "rt", encoding="utf-8") as f:
            lines = f.read().splitlines()
    else:
        try:
            lines = Path(path).read_text(encoding="utf-8").splitlines()
        except FileNotFoundError:
            raise FileNotFoundError(f"video_list {path}: no such file") from None
    out, seen = [], set()
    for line in lines:
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        fields = s.split()
        rel = fields[0]
        while rel.startswith("./"):
            rel = rel[2:]
        rel = rel.lstrip("/")
        if rel and len(fields) == 3 and is_time(fields[1]) and is_time(fields[2]):
            rel = segment_name(rel, parse_time(fields[1]), parse_time(fields[2]))
        if rel and rel not in seen:
            seen.add(rel)
            out.append(rel)
    if not out:
        raise ValueError(f"video_list {path}: lists no video")
    return out

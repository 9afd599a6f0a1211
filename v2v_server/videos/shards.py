"""Tar shards (the WebDataset convention): their members read in place by offset, and brace
patterns of shard names (``webvid-{000000..000999}.tar``)."""
from __future__ import annotations

import io
from typing import Dict, List, Optional, Tuple


def tar_members(f) -> Dict[str, Tuple[int, int]]:
    """Member name -> (offset of its data, size) in bytes of every regular file of the tar
    read from the binary file object ``f``, in one pass over the headers (the data between
    them is skipped by seeking; an object-store file fetches the blocks that hold headers).

    Raises:
        tarfile.TarError: not a tar archive.
    """
    import tarfile

    out = {}
    with tarfile.open(fileobj=f, mode="r:") as tar:
        for m in tar:
            if m.isfile():
                out[m.name] = (m.offset_data, m.size)
    return out


class TarMember(io.RawIOBase):
    """A read-only, seekable window ``[offset, offset + size)`` of the binary file ``f``: one
    member of a tar shard, read in place (FFmpeg decodes it like a file of its own)."""

    def __init__(self, f, offset: int, size: int):
        super().__init__()
        self.f, self.offset, self.size, self.pos = f, offset, size, 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self.pos

    def seek(self, pos: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self.pos, io.SEEK_END: self.size}[whence]
        self.pos = min(max(0, base + pos), self.size)
        return self.pos

    def readinto(self, b) -> int:
        n = min(len(b), self.size - self.pos)
        if n <= 0:
            return 0
        self.f.seek(self.offset + self.pos)
        data = self.f.read(n)
        b[:len(data)] = data
        self.pos += len(data)
        return len(data)


def expand_braces(pattern: str) -> List[str]:
    """The names a brace pattern stands for, in order: ``{000..003}`` is a zero-padded numeric
    range (as the WebDataset tools write shard names), ``{a,b}`` a list; several braces
    multiply. ``shards-{0..1}-{a,b}.tar`` -> ``shards-0-a.tar, shards-0-b.tar, shards-1-a.tar...``

    Raises:
        ValueError: a brace that is neither form.
    """
    import re

    m = re.search(r"\{([^{}]*)\}", pattern)
    if m is None:
        return [pattern]
    body = m.group(1)
    r = re.fullmatch(r"(\d+)\.\.(\d+)", body)
    if r:
        lo, hi = int(r.group(1)), int(r.group(2))
        width = len(r.group(1)) if r.group(1).startswith("0") else 0
        items = [str(i).zfill(width) for i in range(lo, hi + 1)]
    elif "," in body:
        items = body.split(",")
    else:
        raise ValueError(f"{pattern}: brace {{{body}}} is neither a range {{000..009}} nor a list {{a,b}}")
    head, tail = pattern[:m.start()], pattern[m.end():]
    return [x for item in items for x in expand_braces(head + item + tail)]


def split_pattern(videos: str) -> Tuple[str, Optional[List[str]]]:
    """``(root, names)`` of a corpus given as a brace pattern of tar shards
    (``s3://b/webvid-{000000..000009}.tar``: root ``s3://b/``, names ``webvid-000000.tar``...;
    the root is the pattern up to the last ``/`` before the first brace), or ``(videos, None)``
    for a folder or prefix; a single ``.tar`` is a pattern of one."""
    brace = videos.find("{")
    if brace < 0 and not videos.lower().endswith(".tar"):
        return videos, None
    cut = videos.rfind("/", 0, brace if brace >= 0 else len(videos)) + 1
    return videos[:cut] or ".", expand_braces(videos[cut:])



def split_member(rel: str) -> Optional[Tuple[str, str]]:
    """``("shard.tar", "member.mp4")`` for a tar member's id path, else None."""
    i = rel.lower().find(".tar/")
    return (rel[:i + 4], rel[i + 5:]) if i >= 0 else None


class ShardIndex:
    """The member indexes of one source's tar shards: shard -> member name -> (offset of its
    data, size) in bytes, each read from the shard's headers (:func:`tar_members`) once per
    process and version of the shard, or given by a listing that holds them (a store's
    manifest)."""

    def __init__(self):
        self.members: Dict[str, Dict[str, Tuple[int, int]]] = {}
        self._versions: Dict[str, Optional[str]] = {}

    def of(self, tar: str, version: Optional[str], open_raw) -> Dict[str, Tuple[int, int]]:
        """The index of the shard ``tar``, read (``open_raw(tar)``: a context manager giving the
        shard as a binary file) when it is not held or when ``version``, what stands for the
        shard's content, differs from the one it was read at; None: always read it.

        Raises:
            tarfile.TarError, OSError, VideoError: the shard cannot be read (as ``open_raw``)."""
        if tar not in self.members or version is None or self._versions.get(tar, "") != version:
            with open_raw(tar) as f:
                self.members[tar] = tar_members(f)
            self._versions[tar] = version
        return self.members[tar]

    def add(self, rel: str, offset: int, size: int) -> None:
        """Hold the member ``rel`` (``shard.tar/member.mp4``) found by a listing."""
        tar, name = split_member(rel)
        self.members.setdefault(tar, {})[name] = (offset, size)

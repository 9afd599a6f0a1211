"""A corpus in a local folder (``LocalSource``), and what stands for a local file's content in
the frame cache: its identity (size, mtime, ctime, inode) and git's racy rule."""
from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path, PurePosixPath
from typing import Iterator, List, Optional, Sequence, Tuple, Union

from v2v_server.sources.errors import VideoError
from v2v_server.sources.names import inside
from v2v_server.sources.folder_scan import scan_corpus_names
from v2v_server.sources.manifest import ListedObject
from v2v_server.sources.segments import base_path
from v2v_server.sources.shards import ARCHIVES, PIECE, gather_pieces, split_member
from v2v_server.sources.source import VideoSource
from v2v_server.sources.errors import StoreError
from v2v_server.sources.video_tables import TableSettings


def corpus_file(root, rel: str) -> Path:
    """``root / rel``, a file inside the local corpus folder ``root``.

    Raises:
        VideoError: it is missing or a link leads outside the root (the one wording every
            verdict uses).
    """
    path = Path(root) / rel
    if not inside(Path(root), path):
        raise VideoError("missing, or points outside the corpus root")
    return path


#: Nanoseconds within which a change to a file may leave its change time (ctime) where it was:
#: the kernel stamps files from a clock that advances once per tick (1 to 10 ms), and some
#: file systems keep coarser times (exFAT 10 ms). A margin over both.
RACY_NS = 50_000_000
#: The same for a file system that keeps whole seconds (ext3, HFS+; FAT's 2 s): a change time
#: that is a whole second is taken to come from one.
RACY_COARSE_NS = 3_000_000_000


def file_identity(st: os.stat_result) -> str:
    """What stands for a file's content (``st``: its status, links followed): size in bytes,
    modification time (ns), change time (ns) and inode. Size, mtime and inode are what a user
    can keep by accident while rewriting the bytes (``rsync --inplace -t``, ``cp -p`` onto an
    existing file, a tool that restores mtimes); the change time is set by the kernel on every
    write and by no user tool, as git's index records it."""
    return f"{st.st_size} {st.st_mtime_ns} {st.st_ctime_ns} {st.st_ino}"


def racy(st: os.stat_result, now_ns: Optional[int] = None) -> bool:
    """git's racy rule: whether the file of status ``st`` changed within its file system's
    timestamp resolution of ``now_ns`` (default: the clock now), so that a write after this
    stat could leave its identity (:func:`file_identity`) unchanged. Only a file whose change
    time is older than ``RACY_NS`` (``RACY_COARSE_NS`` for whole-second times) is trusted."""
    now_ns = time.time_ns() if now_ns is None else now_ns
    bound = RACY_COARSE_NS if st.st_ctime_ns % 1_000_000_000 == 0 else RACY_NS
    return st.st_ctime_ns >= now_ns - bound


def _portable(st: os.stat_result) -> str:
    """A file's size and whole-second modification time: what a copy to another host keeps."""
    return f"{st.st_size} {st.st_mtime_ns // 1_000_000_000}"


def _plain_identity(st: os.stat_result) -> Optional[str]:
    """The identity of a plain file of status ``st``; None while it is racy."""
    return None if racy(st) else f"file {file_identity(st)}"


class LocalSource(VideoSource):
    """A corpus folder (searched recursively, symlinks that stay inside it followed); ``root``
    a path or a ``file://`` URL, the other arguments as :class:`~v2v_server.sources.source.VideoSource`'s."""

    def __init__(self, root: Union[str, Path], video_list: Optional[str] = None, names: Optional[List[str]] = None,
                 cache_dir: Optional[str] = None, table: TableSettings = TableSettings()):
        root = str(root)
        super().__init__(root[len("file://"):] if root.startswith("file://") else root, video_list, names, cache_dir,
                         table)
        self._abs_root = os.path.abspath(self.root)
        self._members: Optional[Tuple[List[str], List[Tuple[str, str]]]] = None  # _corpus_archives' answer

    @property
    def location(self) -> str:
        """The folder's absolute path: the same corpus whatever folder a process started in."""
        return self._abs_root

    def check(self) -> None:
        """Raises StoreError: the folder does not exist."""
        if not Path(self.root).is_dir():
            raise StoreError(f"--videos {self.root}: not a folder")

    def list_videos(self, extensions):
        names = self._names(extensions)
        if names is not None:
            root = Path(self.root)
            return self._listed(names, lambda rel: inside(root, root / rel), extensions)
        names, others, problems = self._scan(tuple(extensions) + ARCHIVES)
        return self.archives.expand(names, others + problems, extensions)

    def _scan(self, kinds: Sequence[str]) -> Tuple[List[str], List[Tuple[str, str]], List[Tuple[str, str]]]:
        """``(names, others, problems)``: the files of the folder with an extension of
        ``kinds``, and its split zip parts whose pieces are all present (kept in the archives'
        index), sorted; the other files, why; the pieces of parts that cannot be joined, why."""
        names, others = scan_corpus_names(self.root, kinds)
        is_piece = lambda r: r[1].startswith("not a video file") and PIECE.match(r[0])  # noqa: E731
        parts, problems = gather_pieces([rel for rel, why in others if is_piece((rel, why))], set(names))
        self.archives.index.pieces.update(parts)
        return sorted(names + list(parts)), [r for r in others if not is_piece(r)], problems

    def _corpus_archives(self, extensions):
        """The video members of the folder's archives (tar shards, zip parts whole or in pieces,
        at any depth), listed once per source."""
        if self._members is None:
            archives, _, problems = self._scan(ARCHIVES)
            self._members = self.archives.expand(archives, problems, extensions)
        return self._members

    def _exists(self, rel: str) -> bool:
        return Path(self.root, rel).is_file()

    def _siblings(self, part: str) -> List[str]:
        folder = PurePosixPath(part).parent
        try:
            return [(folder / n).as_posix() for n in os.listdir(Path(self.root, folder))]
        except OSError:
            return []

    @contextlib.contextmanager
    def _open_raw(self, rel: str, expected: Optional[ListedObject] = None):
        with open(corpus_file(self.root, rel), "rb") as f:
            yield f

    def _in_archive(self, rel: str) -> bool:
        """Whether ``rel`` names a member of an archive of the corpus (not a file under a folder
        named like one)."""
        member = split_member(rel)
        if member is None:
            return False
        try:
            return bool(self.archives.pieces(member.archive))
        except VideoError:
            return False

    @contextlib.contextmanager
    def open(self, rel: str) -> Iterator[Path]:
        rel = base_path(rel)  # a segment reads its video (the pass keeps its time range)
        if not self._in_archive(rel):
            yield corpus_file(self.root, rel)
            return
        with self.archives.open_member(rel) as f:
            yield f

    def where(self, rel: str) -> str:
        """The file's absolute path (the corpus index's location: the same file whatever
        working folder or spelling of the root it was served from)."""
        return os.path.join(self._abs_root, rel)

    def identity(self, rel: str) -> Optional[str]:
        rel = base_path(rel)
        try:
            if self._in_archive(rel):
                archive = split_member(rel).archive
                stats = self._archive_stats(archive)
                where = " ".join(map(str, self.archives.member_at(rel, None).numbers()))
                held = " + ".join(file_identity(st) for st in stats)
                return None if any(racy(st) for st in stats) else f"{archive[-3:].lower()} {held} member {where}"
            st = os.stat(corpus_file(self.root, rel))
        except OSError as e:
            raise VideoError(f"cannot read: {e.strerror or e}") from None
        return _plain_identity(st)

    def listed_identity(self, rel: str) -> Optional[str]:
        """:meth:`identity` without resolving the path (a listed file lies inside the folder;
        a link out of it has no entry to match, since :meth:`identity` refuses it): the
        start's question asked of every video costs one ``stat``."""
        rel = base_path(rel)
        if split_member(rel) is not None:
            return super().listed_identity(rel)
        try:
            return _plain_identity(os.stat(os.path.join(self.root, rel)))
        except OSError:
            return None

    def listed_tag(self, rel: str) -> Optional[str]:
        """``VideoSource.listed_tag``: a file's size and modification time in whole seconds
        (``file SIZE MTIME``), which ``cp -p``, ``rsync -a`` and ``tar`` keep on another host; an
        archive member's archive's (each piece's) with the member's place in it. One ``stat``
        per file, nothing read. A file rewritten within the same second at the same size keeps
        its tag (docs/delivery.md, "A corpus that changed")."""
        rel = base_path(rel)
        member = split_member(rel)
        try:
            if member is None:
                return f"file {_portable(os.stat(os.path.join(self.root, rel)))}"
            archive = member.archive
            held = " + ".join(_portable(st) for st in self._archive_stats(archive))
            where = " ".join(map(str, self.archives.member_at(rel, None).numbers()))
            return f"{archive[-3:].lower()} {held} member {where}"
        except (OSError, VideoError):
            return None

    def _archive_stats(self, archive: str) -> List[os.stat_result]:
        """The status of the archive's file, or of each piece of a split zip part (links
        followed; one out of the root is refused).

        Raises:
            VideoError, OSError: one is missing."""
        return [os.stat(corpus_file(self.root, p)) for p in self.archives.pieces(archive)]

    def _shard_version(self, tar: str) -> Optional[str]:
        """The archive's identity (:func:`file_identity`, of each piece of a split zip part); None
        while it is racy or cannot be read."""
        try:
            stats = self._archive_stats(tar)
        except (OSError, VideoError):
            return None
        return None if any(racy(st) for st in stats) else " + ".join(file_identity(st) for st in stats)

    def spec(self) -> dict:
        return {"root": self.root, "video_list": self.video_list, "names": self.names, "cache_dir": self.cache_dir,
                "table": self.table}

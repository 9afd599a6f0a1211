"""Where the videos live: a corpus as a local folder or an object-store prefix (any URL fsspec
understands: ``s3://`` through s3fs, ``gs://`` through gcsfs, ``az://`` through adlfs), optionally
narrowed and ordered by a video list in the V2V authors' format.

Every reader of the corpus goes through a :class:`VideoSource`, the seam this module defines
(``sources.local.LocalSource`` for a folder, ``sources.store.StoreSource`` for a store prefix,
both built by ``sources.source_spec``): ``v2v-serve`` (listing, shards, the corpus fingerprint,
``--check``), its worker processes (``source.open(rel)`` per task), and the Ray engine
(``ray_data``). Each process builds its source once (at its start) and hands the built source
to the stages that read videos. A source knows where bytes come from, nothing of what is made of
them: the host's frame cache and corpus index (``frames.host_caches.HostCaches``) are passed
beside it to the frames side. A source lists the corpus as **sample-id paths**: POSIX paths
relative to the folder or key prefix, so the same files in a folder and under a bucket prefix
give the same ids and, for the same seed, bit-identical samples. ``open(rel)`` yields what
``decode.open_video`` reads: a local path, or a file object on the stored object that fetches
it in ``read_block_mb`` blocks (PyAV reads straight from it, no local copy; ``cache_max_gb``
keeps whole objects on local disk instead). Archives given as ``.tar`` or ``.zip`` files or
objects, a brace pattern or list entries stand for their video members, ids
``shard.tar/member.mp4`` or ``part.zip/member.mp4``, read in place by offset (``sources.shards``):
tar shards in the WebDataset convention, zip parts (stored or compressed members, ZIP64, a part
split into ``part_partaa``, ``part_partab``... pieces read as one).

An object store is listed once and the listing is kept as a **manifest** (one JSON line per
object: key relative to the prefix, size in bytes, ETag), so a restart and every shard of the
corpus read the same listing without walking the bucket again (``manifest.Manifest``;
``manifest.manifest_path`` says where it is kept). A worker compares the ETag the store
reports when it opens an object with the manifest's: an object overwritten since it was listed is skipped with the key named.

Transient store errors are retried by the storage library (botocore's ``standard`` retry mode
for S3: ``max_attempts`` attempts with exponential backoff, for throttling, 5xx and
connection errors); a read that still fails, or a store that stops answering for
``read_timeout_s`` (``sources.store.StoreSettings``), fails that video's task, whose windows
the server skips and logs once; the server stays up.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

from v2v_server.sources.archive_members import Archives, pair_members
from v2v_server.sources.errors import VideoError
from v2v_server.sources.manifest import ListedObject
from v2v_server.disk_cache import cache_folder, check_cache_folders
from v2v_server.sources.segments import (RANGE_FORM, base_path, looks_like_segment, printable_name, range_problem,
                                         split_segment)
from v2v_server.sources.shards import ARCHIVES, split_member
from v2v_server.sources.video_list import VideoList, read_video_list
from v2v_server.sources.video_tables import TableSettings


log = logging.getLogger("v2v")


class VideoSource:
    """A corpus: lists videos as sample-id paths and opens them for decoding. See the module
    docstring; ``source_spec.open_source`` builds one.

    What a source can do, for the readers that ask (rather than testing its class):
    :attr:`identity_costs_request` and :attr:`location`.

    Args:
        root: the corpus as given (a folder path or a URL), for logs and errors.
        video_list: the video list file that selects and orders the videos, if any.
        names: entries given with the corpus itself (a brace pattern's shard names), listed
            instead of the store.
        cache_dir: the folder of the host's caches (None: the host's default,
            ``disk_cache.cache_folder``): a store's manifests and object cache.
        table: how a table video list is read (its path column, its filter, the reader's rule
            for rows not worth opening).
    """

    def __init__(self, root: str, video_list: Optional[str] = None, names: Optional[List[str]] = None,
                 cache_dir: Optional[str] = None, table: TableSettings = TableSettings()):
        self.root, self.video_list, self.names, self.table = root, video_list, names, table
        self.cache_dir = cache_folder(cache_dir)  # resolved here once: the store's caches and spec() take it
        #: The corpus's archives: their member indexes, split parts' pieces, their members opened.
        self.archives = Archives(self.root, self._open_raw, self._exists, self._siblings, self._shard_version)


    #: Whether :meth:`identity` costs a request to a store (an object's ETag), so that questions
    #: asked of every video at once are asked where they can run in parallel; False where it is
    #: a ``stat`` of this host's file system (a folder's file, or a member of its archive).
    identity_costs_request = False

    @property
    def location(self) -> str:
        """The corpus as one name for what this host keeps of it (the frame cache's entries):
        :attr:`root` as given (a URL); a folder's absolute path (``LocalSource``)."""
        return self.root

    def _cache_folders(self) -> List[Path]:
        """The folders of this source's caches that are on (a store's object cache)."""
        return []

    def check_cache_dir(self) -> None:
        """At start: this source's caches that are on (``cache_dir/objects`` with
        ``cache_max_gb`` > 0) can be kept (``disk_cache.check_cache_folders``).

        Raises:
            CacheDirError: naming ``cache_dir`` and the folder, with the system's reason.
        """
        check_cache_folders(self.cache_dir, self._cache_folders())

    def identity(self, rel: str) -> Optional[str]:
        """The identity of the video at ``rel`` as it is now, without reading its content:
        what a frame-cache entry made from it records (size, modification time, change time
        and inode of a file, ``local.file_identity``; the ETag or generation of an object; for
        an archive member, its archive's identity (a split part's: its pieces') with the
        member's index entry: offset and size, and a zip member's compressed size, CRC-32,
        method and flags). A source
        rewritten in place gets a new identity, whatever it keeps of size, mtime and inode.

        None when the identity cannot vouch for the content: a file changed within the file
        system's timestamp resolution of now (``local.racy``), an object whose store gives no
        version tag. Such a video is decoded and not stored.

        Raises:
            VideoError: it is missing, or (a store) changed since it was listed.
        """
        raise NotImplementedError

    def listed_identity(self, rel: str) -> Optional[str]:
        """:meth:`identity` of ``rel`` where it costs no request to a store (a folder's file:
        its status; a store's object or member: its listing entry, else None), for questions
        asked of every video at once, such as the server's start; None also when it cannot be
        read (decoding then says why)."""
        try:
            return self.identity(rel)
        except VideoError:
            return None

    def listed_tag(self, rel: str) -> Optional[str]:
        """What stands for the content of the video at ``rel`` in a plan's identity
        (``v2v_wire.plan.Manifest.tags``), costing no request to a store: the same on every host
        that holds the same corpus, so it leaves out what a copy changes (a file's inode and
        change time). A store's object or member: its listing's identity (size and ETag, which
        a copy within the store keeps). None when it cannot be read (decoding then says why)."""
        return self.listed_identity(rel)

    def _names(self, extensions: Sequence[str]) -> Optional[VideoList]:
        """The entries that replace a listing: the video list's (with the list lines it
        refuses), the archives a brace pattern (or one archive) names, or, with both, the list's
        entries paired with those archives' video members (:func:`archive_members.pair_members`)."""
        if self.names and self.video_list:
            listed = read_video_list(self.video_list, self.table)
            members, rejected = self.archives.expand(list(self.names), [], extensions)
            where = f"the {len(self.names)} archive(s) given in {self.root}" if len(self.names) > 1 else self.names[0]
            paired, refused = pair_members(listed.videos, members, self.video_list, where)
            return VideoList(paired, listed.refused + rejected + refused)
        if self.names:
            return VideoList(list(self.names), [])
        return read_video_list(self.video_list, self.table) if self.video_list else None

    def list_videos(self, extensions: Sequence[str]) -> Tuple[List[str], List[Tuple[str, str]]]:
        """``(videos, rejected)``: sample-id paths of the videos (the list's order with a video
        list, else sorted), and ``(path, reason)`` for every entry not served."""
        raise NotImplementedError

    def open(self, rel: str):
        """A context manager giving what ``open_video`` reads for the video at ``rel`` (for a
        segment, ``sources.segments``, its whole video).

        Raises:
            VideoError: it is missing, or changed since it was listed.
        """
        raise NotImplementedError

    def where(self, rel: str) -> str:
        """Where ``rel`` lives, for a log line."""
        return f"{self.root.rstrip('/')}/{rel}"

    def spec(self) -> dict:
        """What a worker process needs to build the same source (``source_spec.source_from_spec``):
        plain values that pickle."""
        raise NotImplementedError

    def take_stats(self) -> dict:
        """Reads since the last call: for a store, ``bytes`` fetched, ``reads`` (range
        requests), ``read_s`` (seconds waiting for the store), ``retries`` (botocore's),
        ``skipped`` (objects missing or changed since listed); empty for a local folder."""
        return {}

    def _listed(self, names: VideoList, exists, extensions: Sequence[str]) -> Tuple[List[str], List[Tuple[str, str]]]:
        """Keep the names of a video list that ``exists(name)`` and have a video extension; a
        ``.tar`` or ``.zip`` name stands for its video members (``Archives.expand``), and a name
        inside an archive (``shard.tar/member.mp4``, with or without a time range) for that member.
        Names that are no file of the corpus are first paired with the members of the archives
        it holds (:meth:`_paired`). The lines the list refused come first among the rejected."""
        names = self._paired(names, exists, extensions)
        videos, rejected = [], list(names.refused)
        for rel in names.videos:
            base, times = split_segment(rel)
            problem = range_problem(*times) if times else None
            if problem:
                rejected.append((rel, f"listed in {self.video_list}: {problem}"))
            elif rel.lower().endswith(ARCHIVES):
                videos.append(rel)
            elif not base.lower().endswith(tuple(extensions)):
                rejected.append((rel, f"listed in {self.video_list} but not a video file (extensions "
                                      f"{', '.join(extensions)})" + (f" ({RANGE_FORM})" if looks_like_segment(rel)
                                                                    else "")))
            elif not (self.archives.has_member(base, exists) if split_member(base) else exists(base)):
                rejected.append((rel, f"listed in {self.video_list} but missing from {self.root}"
                                      + (f" ({RANGE_FORM})" if looks_like_segment(rel) else "")))
            else:
                videos.append(rel)
        videos, rejected = self.archives.expand(videos, rejected, extensions)
        return videos, [(printable_name(rel), why) for rel, why in rejected]  # a cell's newline stays on its line

    def _paired(self, names: VideoList, exists, extensions: Sequence[str]) -> VideoList:
        """A list's video names that are no file of the corpus paired with the video members of
        the archives the corpus holds (:meth:`_corpus_archives`), as with a brace range of them
        (``archive_members.pair_members``: OpenVid-1M's table names ``clip.mp4``, served from
        ``OpenVid_part3.zip/clip.mp4`` in the folder of parts); the names that are files are
        kept in their place. ``names`` as it is when every name is a file, or the corpus holds
        no archive."""
        def lost(rel: str) -> bool:
            base = base_path(rel)
            return base.lower().endswith(tuple(extensions)) and not split_member(base) and not exists(base)

        missing = {rel for rel in names.videos if lost(rel)}
        found = self._corpus_archives(extensions) if missing else None
        if not found or not (found[0] or found[1]):
            return names
        members, problems = found
        paired, refused = pair_members(names.videos, members, self.video_list, f"the archives in {self.root}",
                                       present=lambda rel: rel not in missing)
        return VideoList(paired, names.refused + problems + refused)

    def _corpus_archives(self, extensions: Sequence[str]) -> Optional[Tuple[List[str], List[Tuple[str, str]]]]:
        """``(members, rejected)``: the ids of the video members of the archives the corpus
        holds, and the archives (or members) that give none, why; None when the corpus is not
        searched for them (a store, read name by name with a list)."""
        return None

    def where_ignored(self, rel: str) -> str:
        """Where an entry not served lives, for a log line: :meth:`where` of a corpus path; the
        video list itself, or what names a group of its lines (``(3 entries)``, ``(line 7)``,
        ``(no path)``), as it is."""
        return rel if rel == self.video_list or (rel.startswith("(") and rel.endswith(")")) else self.where(rel)

    # ------------------------------------------------------------------ what the archives read
    def _exists(self, rel: str) -> bool:
        """Whether the file or object ``rel`` exists."""
        raise NotImplementedError

    def _siblings(self, part: str) -> List[str]:
        """Names beside the zip part ``part`` that may be its pieces (``stem_part*``)."""
        raise NotImplementedError

    def _shard_version(self, archive: str) -> Optional[str]:
        """What stands for the content of ``archive`` when its index is reused; None: read the
        index again. A store's archive is held to its listed ETag when it is opened
        (``StoreSource._check_unchanged``), so its index stands."""
        return ""

    def _open_raw(self, rel: str, expected: Optional[ListedObject] = None):
        """A context manager giving the file or object at ``rel`` as a binary file (an object
        checked against ``expected``, its listing entry)."""
        raise NotImplementedError

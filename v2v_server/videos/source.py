"""Where the videos live: a corpus as a local folder or an object-store prefix (any URL fsspec
understands: ``s3://`` through s3fs, ``gs://`` through gcsfs, ``az://`` through adlfs), optionally
narrowed and ordered by a video list in the V2V authors' format.

Every reader of the corpus goes through a :class:`VideoSource`: ``v2v-serve`` (listing, shards,
the corpus fingerprint, ``--check``), its worker processes (``source.open(rel)`` per task), and
the Ray engine (``ray_data``). A source lists the corpus as **sample-id paths**: POSIX paths
relative to the folder or key prefix, so the same files in a folder and under a bucket prefix
give the same ids and, for the same seed, bit-identical samples. ``open(rel)`` yields what
``decode.open_video`` reads: a local path, or a file object on the stored object that fetches
it in ``read_block_mb`` blocks (PyAV reads straight from it, no local copy; ``cache_max_gb``
keeps whole objects on local disk instead). Tar shards (WebDataset convention) given as
``.tar`` files or objects, a brace pattern or list entries stand for their video members, ids
``shard.tar/member.mp4``, read in place by offset (``videos.shards``).

An object store is listed once and the listing is kept as a **manifest** (one JSON line per
object: key relative to the prefix, size in bytes, ETag), so a restart and every shard of the
corpus read the same listing without walking the bucket again; see :func:`manifest_path` for
where it is kept (``videos.manifest``). A worker compares the ETag the store reports when it opens an object with
the manifest's: an object overwritten since it was listed is skipped with the key named.

Transient store errors are retried by the storage library (botocore's ``standard`` retry mode
for S3: ``store_max_attempts`` attempts with exponential backoff, for throttling, 5xx and
connection errors); a read that still fails, or a store that stops answering for
``store_read_timeout_s``, fails that video's task, whose windows the server skips and logs
once; the server stays up.
"""
from __future__ import annotations

import contextlib
import errno
import logging
import os
import stat
import tempfile
import time
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Sequence, Tuple, Union

from v2v_server.videos.frame_cache import FrameCache
from v2v_server.videos.decode import VideoError, inside, printable, scan_corpus, utf8_name
from v2v_server.videos.manifest import (ManifestIndex, default_cache_dir, etag_of, manifest_path, read_manifest,
                                        write_manifest)
from v2v_server.videos.segments import base_path, is_time, parse_time, range_problem, segment_name, split_segment
from v2v_server.videos.shards import TarMember, split_pattern, tar_members
from v2v_server.videos.store_io import ObjectCache, ReadStats, StoreError, make_filesystem, time_fetches

log = logging.getLogger("v2v.source")



class CacheDirError(ValueError):
    """A cache that is on cannot be kept in ``cache_dir`` (the message names the folder)."""


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


class VideoSource:
    """A corpus: lists videos as sample-id paths and opens them for decoding. See the module
    docstring; :func:`open_source` builds one."""

    #: The corpus as given (a folder path or a URL), for logs and errors.
    root: str = ""
    #: The video list file that selects and orders the videos, if any.
    video_list: Optional[str] = None
    #: Entries given with the corpus itself (a brace pattern's shard names), listed instead of the store.
    names: Optional[List[str]] = None
    #: The host's decoded-frame cache (``frame_cache.FrameCache``), None when off.
    frame_cache: Optional[FrameCache] = None

    def _setup_frame_cache(self, cache_dir: Optional[str], frame_cache_gb: float, frame_cache_format: str) -> None:
        """``frame_cache`` under ``cache_dir/frames`` within ``frame_cache_gb`` GiB (0: off)."""
        self.cache_dir = cache_dir or str(default_cache_dir())
        self.frame_cache_gb, self.frame_cache_format = float(frame_cache_gb), frame_cache_format
        if self.frame_cache_gb > 0:
            self.frame_cache = FrameCache(Path(self.cache_dir) / "frames", int(self.frame_cache_gb * (1 << 30)),
                                          frame_cache_format)

    def check_cache_dir(self) -> None:
        """At start: the folders of the caches that are on (``cache_dir/frames`` with
        ``frame_cache_gb`` > 0, ``cache_dir/objects`` with ``cache_max_gb`` > 0) can be made
        and written. A cache asked for and unusable is a setting to fix, not a run to make at a
        fraction of the speed: ``v2v-serve`` exits with this one line. (While serving, the same
        faults are served by decoding: docs/faults.md.)

        Raises:
            CacheDirError: naming ``cache_dir`` and the folder, with the system's reason.
        """
        folders = [self.frame_cache.disk.folder] if self.frame_cache is not None else []
        if getattr(self, "cache_max_gb", 0) > 0:
            folders.append(self.cache.disk.folder)
        for folder in folders:
            try:
                folder.mkdir(parents=True, exist_ok=True)
                with tempfile.TemporaryFile(dir=folder):
                    pass
            except OSError as e:
                raise CacheDirError(f"--cache-dir {self.cache_dir}: cannot keep a cache in {folder}: "
                                    f"{e.strerror or e}") from None

    def _cache_spec(self) -> dict:
        return {"cache_dir": self.cache_dir, "frame_cache_gb": self.frame_cache_gb,
                "frame_cache_format": self.frame_cache_format}

    def identity(self, rel: str) -> Optional[str]:
        """The identity of the video at ``rel`` as it is now, without reading its content:
        what a frame-cache entry made from it records (size, modification time, change time
        and inode of a file, :func:`file_identity`; the ETag or generation of an object; for a
        tar member, its shard's identity with the member's offset and size). A source
        rewritten in place gets a new identity, whatever it keeps of size, mtime and inode.

        None when the identity cannot vouch for the content: a file changed within the file
        system's timestamp resolution of now (:func:`racy`), an object whose store gives no
        version tag. Such a video is decoded and not stored.

        Raises:
            VideoError: it is missing, or (a store) changed since it was listed.
        """
        raise NotImplementedError

    def _names(self) -> Optional[List[str]]:
        """The entries that replace a listing: the brace pattern's, else the video list's.

        Raises:
            ValueError: both a brace pattern and a video list are given.
        """
        if self.names:
            if self.video_list:
                raise ValueError(f"--videos {self.root}: a brace pattern of tar shards names the shards itself; "
                                 f"give it or --video-list {self.video_list}, not both")
            return list(self.names)
        return read_video_list(self.video_list) if self.video_list else None

    def list_videos(self, extensions: Sequence[str]) -> Tuple[List[str], List[Tuple[str, str]]]:
        """``(videos, rejected)``: sample-id paths of the videos (the list's order with a video
        list, else sorted), and ``(path, reason)`` for every entry not served."""
        raise NotImplementedError

    def open(self, rel: str):
        """A context manager giving what ``open_video`` reads for the video at ``rel`` (for a
        segment, ``videos.segments``, its whole video).

        Raises:
            VideoError: it is missing, or changed since it was listed.
        """
        raise NotImplementedError

    def where(self, rel: str) -> str:
        """Where ``rel`` lives, for a log line."""
        return f"{self.root.rstrip('/')}/{rel}"

    def spec(self) -> dict:
        """What a worker process needs to build the same source (:func:`source_from_spec`)."""
        raise NotImplementedError

    def take_stats(self) -> dict:
        """Store reads since the last call: ``bytes`` fetched, ``reads`` (range requests),
        ``read_s`` (seconds waiting for the store), ``retries`` (botocore's), ``skipped``
        (objects missing or changed since listed); empty for a local folder."""
        return {}

    def _listed(self, names: Sequence[str], exists, extensions: Sequence[str]) -> Tuple[List[str], List[Tuple[str, str]]]:
        """Keep the names of a video list that ``exists(name)`` and have a video extension; a
        ``.tar`` name stands for its video members (:meth:`_with_members`), and a name inside a
        shard (``shard.tar/member.mp4``, with or without a time range) for that member."""
        videos, rejected = [], []
        for rel in names:
            base, times = split_segment(rel)
            problem = range_problem(*times) if times else None
            if problem:
                rejected.append((rel, f"listed in {self.video_list}: {problem}"))
            elif rel.lower().endswith(".tar"):
                videos.append(rel)
            elif not base.lower().endswith(tuple(extensions)):
                rejected.append((rel, f"listed in {self.video_list} but not a video file (extensions "
                                      f"{', '.join(extensions)})"))
            elif not (self._has_member(base, exists) if self.split_member(base) else exists(base)):
                rejected.append((rel, f"listed in {self.video_list} but missing from {self.root}"))
            else:
                videos.append(rel)
        return self._with_members(videos, rejected, extensions)

    def _has_member(self, rel: str, exists) -> bool:
        """Whether the tar member ``rel`` (``shard.tar/member.mp4``, a list entry such as a
        segment's video) is in its shard, which ``exists``."""
        tar, name = self.split_member(rel)
        try:
            return exists(tar) and name in self.tar_index(tar)
        except Exception:  # an unreadable shard: the member is missing
            return False

    # ------------------------------------------------------------------ tar shards
    def tar_index(self, tar: str) -> Dict[str, Tuple[int, int]]:
        """Member name -> (offset of its data in bytes, size in bytes) of the tar shard at
        ``tar`` (relative path), read from the tar's headers once per process and version of
        the shard (:meth:`_shard_version`): a shard rewritten in place is read again."""
        cache = self.__dict__.setdefault("_tar_cache", {})
        versions = self.__dict__.setdefault("_tar_versions", {})
        version = self._shard_version(tar)
        if tar not in cache or version is None or versions.get(tar, "") != version:
            with self._open_raw(tar) as f:
                cache[tar] = tar_members(f)
            versions[tar] = version
        return cache[tar]

    def _shard_version(self, tar: str) -> Optional[str]:
        """What stands for the content of shard ``tar`` when its index is reused; None: read
        the index again. A store's shard is held to its listed ETag when it is opened
        (``StoreSource._check_unchanged``), so its index stands."""
        return ""

    def _open_raw(self, rel: str):
        raise NotImplementedError

    def _member_at(self, rel: str, entry: Optional[tuple]) -> Tuple[int, int]:
        """(offset, size) of the tar member ``rel``: from its manifest ``entry`` (a store's), else
        the shard's index.

        Raises:
            VideoError: the shard has no such member."""
        if entry is not None and len(entry) == 3:
            return entry[2], entry[0]
        tar, name = self.split_member(rel)
        where = self.tar_index(tar).get(name)
        if where is None:
            raise VideoError(f"no member {name!r} in the tar shard {tar}")
        return where

    def _with_members(self, names: List[str], rejected: List[Tuple[str, str]], extensions: Sequence[str]
                      ) -> Tuple[List[str], List[Tuple[str, str]]]:
        """``names`` with each ``.tar`` shard replaced by its video members, ``shard.tar/member.mp4``
        (the WebDataset convention: a sample's files share a key, the video is the member with
        a video extension; the other members, such as ``.json`` or ``.txt``, are not served)."""
        out = []
        for rel in names:
            if not rel.lower().endswith(".tar"):
                out.append(rel)
                continue
            try:
                members = self.tar_index(rel)
            except Exception as e:  # one unreadable shard never stops the listing
                rejected.append((rel, f"tar shard cannot be read: {type(e).__name__}: {e}"))
                continue
            vids = [m for m in members if m.lower().endswith(tuple(extensions))]
            out += [f"{rel}/{m}" for m in vids]
            if not vids:
                rejected.append((rel, "tar shard holds no video member"))
        return out, rejected

    @staticmethod
    def split_member(rel: str) -> Optional[Tuple[str, str]]:
        """``("shard.tar", "member.mp4")`` for a tar member's id path, else None."""
        i = rel.lower().find(".tar/")
        return (rel[:i + 4], rel[i + 5:]) if i >= 0 else None


class LocalSource(VideoSource):
    """A corpus folder (searched recursively, symlinks that stay inside it followed)."""

    def __init__(self, root: Union[str, Path], video_list: Optional[str] = None, names: Optional[List[str]] = None,
                 cache_dir: Optional[str] = None, frame_cache_gb: float = 0.0, frame_cache_format: str = "raw"):
        root = str(root)
        self.root = root[len("file://"):] if root.startswith("file://") else root
        self.video_list, self.names = video_list, names
        self._setup_frame_cache(cache_dir, frame_cache_gb, frame_cache_format)

    def check(self) -> None:
        """Raises StoreError: the folder does not exist."""
        if not Path(self.root).is_dir():
            raise StoreError(f"--videos {self.root}: not a folder")

    def list_videos(self, extensions):
        names = self._names()
        if names is not None:
            root = Path(self.root)
            return self._listed(names, lambda rel: inside(root, root / rel), extensions)
        found, rejected = scan_corpus(Path(self.root), tuple(extensions) + (".tar",))
        return self._with_members([p.as_posix() for p in found], [(p.as_posix(), why) for p, why in rejected],
                                  extensions)

    @contextlib.contextmanager
    def _open_raw(self, rel: str):
        with open(corpus_file(self.root, rel), "rb") as f:
            yield f

    @contextlib.contextmanager
    def open(self, rel: str) -> Iterator[Path]:
        rel = base_path(rel)  # a segment reads its video (the pass keeps its time range)
        member = self.split_member(rel)
        if member is None or not Path(self.root, member[0]).is_file():
            yield corpus_file(self.root, rel)
            return
        where = self._member_at(rel, None)
        with self._open_raw(member[0]) as f:
            yield TarMember(f, *where)

    def where(self, rel: str) -> str:
        return str(Path(self.root) / rel)

    def identity(self, rel: str) -> Optional[str]:
        rel = base_path(rel)
        member = self.split_member(rel)
        try:
            shard = self._shard_stat(member[0]) if member is not None else None
            if shard is not None:
                corpus_file(self.root, member[0])  # a link out of the root is refused
                offset, size = self._member_at(rel, None)
                return None if racy(shard) else f"tar {file_identity(shard)} member {offset} {size}"
            st = os.stat(corpus_file(self.root, rel))
        except OSError as e:
            raise VideoError(f"cannot read: {e.strerror or e}") from None
        return None if racy(st) else f"file {file_identity(st)}"

    def _shard_version(self, tar: str) -> Optional[str]:
        """The shard file's identity (:func:`file_identity`); None while it is racy or cannot
        be read."""
        try:
            st = os.stat(Path(self.root, tar))
        except OSError:
            return None
        return None if racy(st) else file_identity(st)

    def _shard_stat(self, tar: str) -> Optional[os.stat_result]:
        """The status of ``tar`` (links followed) when it is a file, a tar shard; None when it is
        missing or no file (a folder named like a shard), the errors ``Path.is_file`` takes for
        no; others raise."""
        try:
            st = os.stat(Path(self.root, tar))
        except OSError as e:
            if e.errno in (errno.ENOENT, errno.ENOTDIR, errno.EBADF, errno.ELOOP):
                return None
            raise
        return st if stat.S_ISREG(st.st_mode) else None

    def spec(self) -> dict:
        return {"root": self.root, "video_list": self.video_list, "names": self.names, **self._cache_spec()}

    def take_stats(self) -> dict:
        return {"frame_cache": self.frame_cache.take_stats()} if self.frame_cache is not None else {}


class _StoreManifest:
    """The part of :class:`StoreSource` that keeps its listing: the manifest written and read
    back, and the members of its tar shards within it."""

    def _add_members(self, objects: dict, tar: str) -> None:
        """Add the members of the shard ``tar`` to ``objects`` as ``tar/member`` -> (size, the
        shard's ETag, offset); an unreadable shard gets no member (it is reported when listed)."""
        try:
            with self._open_raw(tar) as f:
                members = tar_members(f)
        except Exception as e:  # noqa: BLE001 - one bad shard never stops the listing
            log.warning("tar shard %s cannot be read: %s: %s", self.where(tar), type(e).__name__, e)
            return
        etag = objects.get(tar, (0, ""))[1]
        for name, (offset, size) in members.items():
            objects[f"{tar}/{name}"] = (size, etag, offset)

    def _load(self, objects: Dict[str, tuple]) -> None:
        """Keep ``objects`` (a listing or manifest) and the tar members it holds."""
        self._objects = objects
        cache = self.__dict__.setdefault("_tar_cache", {})
        for rel, v in objects.items():
            if len(v) == 3:
                tar, member = self.split_member(rel)
                cache.setdefault(tar, {})[member] = (v[2], v[0])

    def _save(self, objects: dict) -> None:
        if self.manifest:
            try:
                write_manifest(Path(self.manifest), self.root, objects)
                log.info("manifest written to %s", self.manifest)
            except OSError as e:
                log.warning("cannot write the manifest %s: %s (the store is listed again at the next start)",
                            self.manifest, e)

    def _save_members(self) -> None:
        """Write the tar members read from shard headers (no listing) as the manifest."""
        objects = {f"{tar}/{m}": (size, "", offset) for tar, ms in self.__dict__.get("_tar_cache", {}).items()
                   for m, (offset, size) in ms.items()}
        self._save(objects)
        self._objects = objects


class StoreSource(_StoreManifest, VideoSource):
    """A corpus under an object-store prefix, read through fsspec.

    Args:
        url: ``s3://bucket/prefix/`` (a trailing ``/`` is implied) or another fsspec URL.
        storage_options: passed to the filesystem (``endpoint_url``, ``key``...), over the
            defaults below; credentials otherwise come from the store's standard configuration
            (for S3: ``AWS_*`` variables incl. ``AWS_ENDPOINT_URL``, shared config files,
            instance roles).
        manifest: the manifest file (see :func:`manifest_path`); None keeps none.
        read_timeout_s: seconds a store request may stay silent before it fails (then retried).
        max_attempts: attempts per request (botocore ``standard`` retry mode for S3).
        read_block_mb: bytes fetched per request while decoding, MiB (one request for a clip
            smaller than this); at most four blocks per open video are kept.
        cache_dir, cache_max_gb: a bounded local cache of whole objects for corpora read every
            epoch (``cache_dir/objects``, least recently used removed beyond ``cache_max_gb``
            GiB); 0 (the default) reads from the store every time.
        frame_cache_gb, frame_cache_format: the host's decoded-frame cache
            (``cache_dir/frames``, ``frame_cache.FrameCache``); 0 GiB (the default) is off.
    """

    def __init__(self, url: str, storage_options: Optional[dict] = None, video_list: Optional[str] = None,
                 manifest: Optional[str] = None, refresh_manifest: bool = False, read_timeout_s: float = 20.0,
                 max_attempts: int = 3, read_block_mb: float = 8.0, names: Optional[List[str]] = None,
                 cache_dir: Optional[str] = None, cache_max_gb: float = 0.0, frame_cache_gb: float = 0.0,
                 frame_cache_format: str = "raw"):
        self.names = names
        self._setup_frame_cache(cache_dir, frame_cache_gb, frame_cache_format)
        self.cache_max_gb = float(cache_max_gb)
        self.protocol = url.split("://", 1)[0].lower()
        self.root = url if url.endswith("/") else url + "/"
        self.prefix = self.root.split("://", 1)[1]
        self.storage_options = dict(storage_options or {})
        self.video_list, self.manifest = video_list, manifest
        self.refresh_manifest = refresh_manifest
        self.read_timeout_s, self.max_attempts, self.read_block_mb = read_timeout_s, max_attempts, read_block_mb
        self._fs = None
        self._objects: Optional[Dict[str, Tuple[int, str]]] = None  # the manifest, loaded on first need
        self.stats = ReadStats()
        self.cache = ObjectCache(Path(self.cache_dir) / "objects", self.cache_max_gb)

    # ------------------------------------------------------------------ the filesystem
    @property
    def fs(self):
        if self._fs is None:
            self._fs = self._make_fs()
        return self._fs

    def _make_fs(self):
        return make_filesystem(self.protocol, self.root, self.storage_options, self.read_timeout_s,
                               self.max_attempts, self.stats)

    def _path(self, rel: str) -> str:
        """The filesystem path of ``rel``: the key for object stores, the whole URL for http(s)."""
        return (self.root if self.protocol in ("http", "https") else self.prefix) + rel

    def _fail(self, what: str, e: BaseException) -> StoreError:
        return StoreError(f"--videos {self.root}: {what}: {type(e).__name__}: {e}")

    def check(self) -> None:
        """Reach the store once (the bucket's metadata, not a listing).

        Raises:
            StoreError: naming the URL: no such bucket, credentials refused or missing, store
                unreachable, no library for the protocol.
        """
        if self.protocol in ("http", "https"):
            return  # no bucket to ask about: a missing shard is named when it is read
        bucket = self.prefix.split("/", 1)[0]
        try:
            self.fs.info(bucket)
        except FileNotFoundError as e:
            raise self._fail(f"no such bucket {bucket!r}", e) from None
        except PermissionError as e:
            raise self._fail("access refused (check the credentials)", e) from None
        except StoreError:
            raise
        except Exception as e:  # NoCredentialsError, EndpointConnectionError, ...: each one a clear line
            raise self._fail("cannot reach the store", e) from None

    # ------------------------------------------------------------------ listing
    def objects(self) -> Dict[str, Tuple[int, str]]:
        """Key relative to the prefix -> (size, ETag) of every object under the prefix: the
        manifest when there is one (and ``refresh_manifest`` is off), else a paginated listing
        of the store, then written as the manifest.

        Raises:
            StoreError: the listing fails (naming the URL).
        """
        if self._objects is not None:
            return self._objects
        if self.manifest and not self.refresh_manifest:
            got = read_manifest(Path(self.manifest), self.root)
            if got is not None:
                log.info("%s: %d object(s) from the manifest %s (--refresh-manifest lists the store again)",
                         self.root, len(got), self.manifest)
                self._load(got)
                return got
        t0 = time.monotonic()
        try:
            found = self.fs.find(self.prefix, detail=True)
        except FileNotFoundError as e:
            raise self._fail("no such bucket or prefix", e) from None
        except PermissionError as e:
            raise self._fail("access refused (check the credentials)", e) from None
        except Exception as e:
            raise self._fail("cannot list", e) from None
        objects = {}
        for key, info in found.items():
            if info.get("type", "file") != "file" or not key.startswith(self.prefix):
                continue
            objects[key[len(self.prefix):]] = (int(info.get("size") or 0), etag_of(info))
        for rel in [k for k in objects if k.lower().endswith(".tar")]:  # shards: their members, once
            self._add_members(objects, rel)
        log.info("%s: listed %d object(s) in %.1f s", self.root, len(objects), time.monotonic() - t0)
        self._save(objects)
        self.refresh_manifest = False
        self._load(objects)
        return objects

    def list_videos(self, extensions):
        names = self._names()
        if names is not None:  # nothing is listed from the store: a missing video is found when it is opened
            known = None
            if self.manifest and not self.refresh_manifest:  # the tar members read at an earlier start
                known = read_manifest(Path(self.manifest), self.root)
            if known is not None:
                self._load(known)
            got = self._listed(names, lambda rel: True, extensions)
            if known is None and self.manifest and any(self.split_member(v) for v in got[0]):
                self._save_members()  # the shards' members, so that workers and restarts need not read headers
            return got
        videos, rejected = [], []
        for rel in sorted(self.objects()):
            if not utf8_name(rel):
                rejected.append((printable(rel), "key is not valid UTF-8 (sample ids are UTF-8): rename it"))
            elif rel.endswith("/") or not rel or rel.lower().endswith(".tar"):
                continue  # a shard stands for its members, listed after it
            elif self.split_member(rel) is not None and not rel.lower().endswith(tuple(extensions)):
                continue  # a shard's metadata member (.json, .txt): not a video, not worth a line
            elif rel.lower().endswith(tuple(extensions)):
                videos.append(rel)
            else:
                rejected.append((rel, f"not a video file (extension {Path(rel).suffix or 'none'!r})"))
        return videos, rejected

    # ------------------------------------------------------------------ reading
    def _expected(self, rel: str) -> Optional[tuple]:
        """The listing's entry for ``rel``: from the listing this process holds (the server),
        else looked up in the manifest file (a worker: one entry, not the whole manifest)."""
        if self._objects is not None:
            return self._objects.get(rel)
        if self.manifest:
            if "_index" not in self.__dict__:
                self._index = ManifestIndex.open(Path(self.manifest), self.root)
            if self._index is not None:
                return self._index.get(rel)
        return None

    @contextlib.contextmanager
    def open(self, rel: str):
        rel = base_path(rel)  # a segment reads its object (the pass keeps its time range)
        member = self.split_member(rel)
        if member is None:
            with self._open_raw(rel) as f:
                yield f
            return
        entry = self._expected(rel)
        with self._open_raw(member[0], entry) as f:
            yield TarMember(f, *self._member_at(rel, entry))


    def identity(self, rel: str) -> Optional[str]:
        rel = base_path(rel)
        member = self.split_member(rel)
        obj = member[0] if member is not None else rel
        with self._request():
            info = self.fs.info(self._path(obj))  # one HEAD request: no content read
        self.stats.reads += 1
        now, size = etag_of(info), int(info.get("size") or 0)
        entry = self._expected(rel)  # the listing's entry: the object's, or the member's (its shard's ETag, its offset)
        self._check_unchanged(entry, now)
        if not now:  # no version tag (an HTTP server without ETag): the size alone cannot vouch for the bytes
            return None
        if member is None:
            return f"object {size} {now}"
        offset, msize = self._member_at(rel, entry)
        return f"tar {size} {now} member {offset} {msize}"

    @contextlib.contextmanager
    def _request(self):
        """A request to the store: its seconds counted; a missing object or any failure (timeouts,
        refused reads) raised as the file's ``VideoError``, never the worker's death."""
        t0 = time.perf_counter()
        try:
            yield
        except FileNotFoundError:
            self.stats.skipped += 1
            raise VideoError("missing from the store") from None
        except Exception as e:
            raise VideoError(f"cannot open: {type(e).__name__}: {e}") from None
        finally:
            self.stats.read_s += time.perf_counter() - t0

    def _check_unchanged(self, expected: Optional[tuple], now: str) -> None:
        """Raises VideoError: the object's ETag ``now`` differs from the listing's (``expected``:
        its manifest entry)."""
        if expected is not None and expected[1] and now and now != expected[1]:
            self.stats.skipped += 1
            raise VideoError(f"changed since it was listed (ETag {expected[1]} -> {now}); skipped until "
                             f"--refresh-manifest")

    @contextlib.contextmanager
    def _open_raw(self, rel: str, expected: Optional[tuple] = None):
        """The object at ``rel`` as a file, checked against the listing's ETag (``expected``:
        its manifest entry, looked up when not given)."""
        block = max(1, int(self.read_block_mb * (1 << 20)))
        with self._request():
            f = self.fs.open(self._path(rel), "rb", block_size=block, cache_type="blockcache",
                             cache_options={"maxblocks": 4})
        try:
            now = etag_of(getattr(f, "details", None) or {})
            self._check_unchanged(self._expected(rel) if expected is None else expected, now)
            time_fetches(f, self.stats)
            if self.cache_max_gb > 0:
                with self.cache.open(f"{self.root}{rel}", now, f) as local:
                    yield local
            else:
                yield f
        finally:
            f.close()

    def take_stats(self) -> dict:
        out = self.stats.take()
        if self.frame_cache is not None:
            out["frame_cache"] = self.frame_cache.take_stats()
        return out

    def spec(self) -> dict:
        return {"root": self.root, "storage_options": self.storage_options, "video_list": self.video_list,
                "manifest": self.manifest, "read_timeout_s": self.read_timeout_s, "max_attempts": self.max_attempts,
                "read_block_mb": self.read_block_mb, "cache_max_gb": self.cache_max_gb, **self._cache_spec()}


def open_source(videos: Union[str, Path, None], *, storage_options: Optional[dict] = None,
                video_list: Optional[str] = None, manifest: Optional[str] = None, refresh_manifest: bool = False,
                read_timeout_s: float = 20.0, max_attempts: int = 3, read_block_mb: float = 8.0,
                names: Optional[List[str]] = None, cache_dir: Optional[str] = None,
                cache_max_gb: float = 0.0, frame_cache_gb: float = 0.0, frame_cache_format: str = "raw") -> VideoSource:
    """The source of a corpus given as a folder, a URL, or a brace pattern / path of tar shards;
    ``frame_cache_gb`` > 0 gives it the host's frame cache under ``cache_dir/frames``."""
    if isinstance(videos, VideoSource):
        return videos
    if names is None:
        videos, names = split_pattern(str(videos))
    if is_url(str(videos)):
        return StoreSource(str(videos), storage_options, video_list, manifest, refresh_manifest, read_timeout_s,
                           max_attempts, read_block_mb, names, cache_dir, cache_max_gb, frame_cache_gb,
                           frame_cache_format)
    return LocalSource(videos, video_list, names, cache_dir, frame_cache_gb, frame_cache_format)


def source_from_config(cfg, videos: Union[str, Path, None] = None) -> VideoSource:
    """The source ``cfg`` (a ``ServeConfig``) describes: ``videos`` or ``cfg.videos``, its
    ``video_list``, ``storage_options``, store timeouts and manifest (:func:`manifest_path`)."""
    videos = cfg.videos if videos is None else videos
    manifest = None
    if videos is not None and is_url(str(videos)):
        # one manifest per listing: of a prefix (all its objects), or of a pattern's or a list's tar members
        key = str(videos) if split_pattern(str(videos))[1] else StoreSource(str(videos)).root
        if cfg.video_list:
            key += f" listed by {Path(cfg.video_list).resolve()}"
        manifest = str(manifest_path(key, cfg.state_dir, cfg.cache_dir))
    return open_source(videos, storage_options=cfg.storage_options, video_list=cfg.video_list, manifest=manifest,
                       refresh_manifest=cfg.refresh_manifest, read_timeout_s=cfg.store_read_timeout_s,
                       max_attempts=cfg.store_max_attempts, read_block_mb=cfg.read_block_mb, cache_dir=cfg.cache_dir,
                       cache_max_gb=cfg.cache_max_gb, frame_cache_gb=cfg.frame_cache_gb,
                       frame_cache_format=cfg.frame_cache_format)


def source_from_spec(spec: Union[str, Path, dict, VideoSource]) -> VideoSource:
    """The source a worker builds from :meth:`VideoSource.spec` (a folder path is accepted as is)."""
    if isinstance(spec, VideoSource):
        return spec
    if isinstance(spec, dict):
        spec = dict(spec)
        return open_source(spec.pop("root"), **spec)
    return open_source(spec)


def take_store_stats(source) -> dict:
    """``source.take_stats()`` for a source, ``{}`` for anything else (a folder path)."""
    return source.take_stats() if isinstance(source, VideoSource) else {}

"""A corpus under an object-store prefix (``StoreSource``), read through fsspec, and the
store's settings (``StoreSettings``: the one owner of their defaults and checks)."""
from __future__ import annotations

import contextlib
import dataclasses
import itertools
import logging
import time
from pathlib import Path
from typing import Dict, List, Optional

from v2v_server.checks import check_float, check_int
from v2v_server.settings import setting
from v2v_server.sources.archive_members import archive_problems
from v2v_server.sources.errors import VideoError
from v2v_server.sources.names import name_problem, printable
from v2v_server.sources.manifest import ListedObject, Manifest, etag_of, object_identity
from v2v_server.sources.segments import base_path
from v2v_server.sources.shards import ARCHIVES, gather_pieces, piece_archive, piece_names, split_member
from v2v_server.sources.source import VideoSource
from v2v_server.sources.video_tables import TableSettings
from v2v_server.sources.errors import StoreError
from v2v_server.sources.store_io import (MAX_ATTEMPTS, READ_TIMEOUT_S, ObjectCache, ReadStats, make_filesystem, retry_policy,
                                         time_fetches)

log = logging.getLogger("v2v.source")


@dataclasses.dataclass(frozen=True)
class StoreSettings:
    """Object store: how a corpus under a store prefix is read.

    The one owner of these keys' defaults, help and checks (``docs/config.md``'s store keys are
    generated from the fields made with ``setting``); ``ops.config.ServeConfig`` composes it,
    and a :class:`StoreSource` reads it.

    Attributes:
        store_read_timeout_s: seconds a store request may wait to connect, or between bytes of
            its answer, before it fails (then retried); honoured by S3, GCS, Azure and http(s)
            (``store_io.make_filesystem``).
        store_max_attempts: attempts per request, 1..20: botocore's ``standard`` retry mode for
            S3, gcsfs's retry loop for GCS, azure-storage-blob's retry policy for Azure; other
            stores make one attempt and refuse another value (``store_io.retry_policy``).
        read_block_mb: MiB fetched per request while decoding (one request for a clip smaller
            than this); at most four blocks per open video are kept.
        cache_max_gb: GiB of a bounded local cache of whole objects for corpora read every
            epoch (``cache_dir/objects``, least recently used removed first); 0 reads from the
            store every time.

    Raises:
        ValueError: naming the key, for a value out of its range.
    """

    store_read_timeout_s: float = setting(READ_TIMEOUT_S, help="seconds a store request may wait to connect, or "
                                                               "between bytes of its answer, before it fails (then "
                                                               "retried); s3://, gs://, az:// and http(s)://",
                                          flag="--store-read-timeout")
    store_max_attempts: int = setting(MAX_ATTEMPTS, help="attempts per store request, with exponential backoff on "
                                                         "throttling, 5xx, connection errors and timeouts: s3:// "
                                                         "(botocore standard retry mode), gs:// (gcsfs's retry loop), "
                                                         "az:// (azure-storage-blob's retry policy); other stores "
                                                         "make one attempt and refuse another value")
    read_block_mb: float = setting(8.0, help="MiB fetched per store request while decoding (one request for a "
                                             "smaller video)")
    cache_max_gb: float = setting(0.0, help="GiB of whole store objects kept on local disk for corpora read every "
                                            "epoch (least recently used removed first); 0 = off, read from the "
                                            "store each time")

    def __post_init__(self):
        _set = object.__setattr__  # frozen: normalised once, here
        _set(self, "store_read_timeout_s", check_float("store_read_timeout_s", self.store_read_timeout_s))
        _set(self, "read_block_mb", check_float("read_block_mb", self.read_block_mb))
        _set(self, "cache_max_gb", check_float("cache_max_gb", self.cache_max_gb, positive=False))
        if self.cache_max_gb < 0:
            raise ValueError(f"cache_max_gb must be >= 0 GiB (0 = no cache), got {self.cache_max_gb!r}")
        check_int("store_max_attempts", self.store_max_attempts, 1, 20, "attempts")


def store_root(url: str) -> str:
    """The corpus URL ``url`` as a :class:`StoreSource` holds it: with one trailing ``/``."""
    return url if url.endswith("/") else url + "/"


def manifest_key(url: str, pattern: bool, video_list: Optional[str] = None) -> str:
    """What names one listing of a store, and so its manifest (``manifest.manifest_path``): the
    prefix's URL (:func:`store_root`: all its objects), or a brace pattern as given (its
    archives' members); with a video list, the list's absolute path too (a list's members only)."""
    key = url if pattern else store_root(url)
    return key + (f" listed by {Path(video_list).resolve()}" if video_list else "")


class StoreSource(VideoSource):
    """A corpus under an object-store prefix, read through fsspec.

    Args (all but ``url`` by keyword):
        url: ``s3://bucket/prefix/`` (a trailing ``/`` is implied) or another fsspec URL.
        storage_options: passed to the filesystem (``endpoint_url``, ``key``...), over the defaults below;
            credentials otherwise come from the store's standard configuration (for S3: ``AWS_*``
            variables incl. ``AWS_ENDPOINT_URL``, shared config files, instance roles).
        video_list, names, cache_dir, table: as :class:`~v2v_server.sources.source.VideoSource`'s.
        manifest: the manifest file (see ``manifest.manifest_path``); None keeps none.
        refresh_manifest: list the store again instead of reading the manifest.
        settings: timeouts, attempts, read blocks and the object cache (``cache_dir/objects``).
    """

    identity_costs_request = True  # an object's identity (ETag, generation) is read from the store

    def __init__(self, url: str, *, storage_options: Optional[dict] = None, video_list: Optional[str] = None,
                 manifest: Optional[str] = None, refresh_manifest: bool = False,
                 settings: StoreSettings = StoreSettings(), names: Optional[List[str]] = None,
                 cache_dir: Optional[str] = None, table: TableSettings = TableSettings()):
        super().__init__(store_root(url), video_list, names, cache_dir, table)
        self.protocol = url.split("://", 1)[0].lower()
        self.prefix = self.root.split("://", 1)[1]
        self.storage_options = dict(storage_options or {})
        self.settings = settings
        retry_policy(self.protocol, self.root, settings.store_read_timeout_s, settings.store_max_attempts)
        #: The objects under the prefix and the manifest file that keeps them.
        self.manifest = Manifest(self.root, manifest, refresh_manifest, self.archives.index)
        self._fs = None
        self.stats = ReadStats()
        self.cache = ObjectCache(Path(self.cache_dir) / "objects", settings.cache_max_gb)
        #: Archive -> why its index could not be read while listing.
        self._unreadable: Dict[str, str] = {}

    # ------------------------------------------------------------------ the filesystem
    @property
    def fs(self):
        """The store's filesystem (``store_io.make_filesystem``), made at the first use."""
        if self._fs is None:
            self._fs = make_filesystem(self.protocol, self.root, self.storage_options,
                                       self.settings.store_read_timeout_s, self.settings.store_max_attempts, self.stats)
        return self._fs

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
    def objects(self) -> Dict[str, ListedObject]:
        """Key relative to the prefix -> its entry (size, ETag; an archive member's: where it lies)
        of every object and archive member under the prefix: the manifest when there is one (and
        ``refresh_manifest`` is off), else a paginated listing of the store, then written as the manifest.

        Raises:
            StoreError: the listing fails (naming the URL).
        """
        if self.manifest.objects is not None:
            return self.manifest.objects
        got = self.manifest.read()
        if got is not None:
            log.info("%s: %d object(s) from the manifest %s (--refresh-manifest lists the store again)",
                     self.root, len(got), self.manifest.path)
            self.manifest.keep(got)
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
            objects[key[len(self.prefix):]] = ListedObject(int(info.get("size") or 0), etag_of(info))
        parts, _ = gather_pieces(objects, set(objects))  # split zip parts: read as their pieces joined
        self.archives.index.pieces.update(parts)
        for rel in [k for k in objects if k.lower().endswith(ARCHIVES)] + list(parts):  # archives: their members, once
            self._add_members(objects, rel)
        log.info("%s: listed %d object(s) in %.1f s", self.root, len(objects), time.monotonic() - t0)
        self.manifest.listed(objects)
        return objects

    def _add_members(self, objects: dict, archive: str) -> None:
        """Add the members of ``archive`` to ``objects`` as ``archive/member`` -> its entry (its
        size, the archive's ETag (a split part's: its pieces', joined by ``+``), where it lies); an
        unreadable archive gets no member (it is reported when listed)."""
        try:
            members = self.archives.members(archive)
        except Exception as e:  # noqa: BLE001 - one bad archive never stops the listing
            self._unreadable[archive] = f"{type(e).__name__}: {e}"
            return
        etag = "+".join(objects[p].tag if p in objects else "" for p in self.archives.pieces(archive))
        for name, entry in members.items():
            objects[f"{archive}/{name}"] = ListedObject(entry.size, etag, entry)

    def _exists(self, rel: str) -> bool:
        if self.manifest.entry(rel) is not None:
            return True
        if self.manifest.objects is not None and not self.names and not self.video_list:
            return False  # the whole prefix is listed
        t0 = time.perf_counter()
        try:
            self.fs.info(self._path(rel))  # one HEAD request
            return True
        except FileNotFoundError:  # not a fault: a split part is looked for piece by piece
            return False
        except Exception as e:
            raise VideoError(f"cannot open: {type(e).__name__}: {e}") from None
        finally:
            self.stats.reads += 1
            self.stats.read_s += time.perf_counter() - t0

    def _siblings(self, part: str) -> List[str]:
        stem = part[:-len(".zip")] + "_part"
        if self.manifest.objects is not None:
            found = [k for k in self.manifest.objects if k.startswith(stem)]
            if found or (not self.names and not self.video_list):
                return found
        if self.protocol in ("http", "https"):  # no listing: ask for each piece until one is missing
            return list(itertools.takewhile(self._exists, piece_names(part)))
        base, whole = self._path(""), self._path(stem)
        try:
            with self._request():  # the folder's names, not a glob: a part's name may hold [ ] * ?
                keys = self.fs.ls(whole.rpartition("/")[0], detail=False)
        except (VideoError, FileNotFoundError):
            return []
        return [k[len(base):] for k in keys if k.startswith(whole) and k.startswith(base)]

    def list_videos(self, extensions):
        names = self._names(extensions)
        if names is not None:  # nothing is listed from the store: a missing video is found when it is opened
            known = self.manifest.read()  # the tar members read at an earlier start
            if known is not None:
                self.manifest.keep(known)
            got = self._listed(names, lambda rel: True, extensions)
            if known is None and self.manifest.path and any(split_member(v) for v in got[0]):
                self.manifest.save_members()  # the shards' members, so that workers and restarts need not read headers
            return got
        videos, rejected = [], []
        for rel in sorted(self.objects()):
            if name_problem(rel, "key") is not None:
                rejected.append((printable(rel), name_problem(rel, "key")))
            elif rel.endswith("/") or not rel or rel.lower().endswith(ARCHIVES) or piece_archive(rel):
                continue  # an archive stands for its members, listed after it
            elif split_member(rel) is not None and not rel.lower().endswith(tuple(extensions)):
                if split_member(rel).archive.lower().endswith(".zip"):  # a zip part is a folder in a file
                    rejected.append((rel, f"not a video file (extension {Path(rel).suffix or 'none'!r})"))
                # a tar shard's metadata member (.json, .txt): not a video, not worth a line
            elif rel.lower().endswith(tuple(extensions)):
                videos.append(rel)
            else:
                rejected.append((rel, f"not a video file (extension {Path(rel).suffix or 'none'!r})"))
        return videos, rejected + self.archives.refused() + archive_problems(self.objects(), self._unreadable, extensions)

    # ------------------------------------------------------------------ reading
    @contextlib.contextmanager
    def open(self, rel: str):
        rel = base_path(rel)  # a segment reads its object (the pass keeps its time range)
        if split_member(rel) is None:
            with self._open_raw(rel) as f:
                yield f
            return
        with self.archives.open_member(rel, self.manifest.entry(rel)) as f:
            yield f

    def identity(self, rel: str) -> Optional[str]:
        rel = base_path(rel)
        member = split_member(rel)
        infos = []
        for obj in self.archives.pieces(member.archive) if member is not None else [rel]:  # a split zip part: each piece
            with self._request():
                infos.append(self.fs.info(self._path(obj)))  # one HEAD request: no content read
            self.stats.reads += 1
        tags, size = [etag_of(i) for i in infos], sum(int(i.get("size") or 0) for i in infos)
        now = "+".join(tags) if all(tags) else ""
        entry = self.manifest.entry(rel)  # the listing's entry: the object's, or the member's (its archive's ETag, where it lies)
        self._check_unchanged(entry, now)
        if not now:  # no version tag (an HTTP server without ETag): the size alone cannot vouch for the bytes
            return None
        return object_identity(rel, size, now, self.archives.member_at(rel, entry) if member is not None else None)

    def listed_identity(self, rel: str) -> Optional[str]:
        """:meth:`identity` as the listing (the manifest) gives it, without a request: None
        for an object or member it does not hold, or one without a version tag."""
        rel = base_path(rel)
        member = split_member(rel)
        objs = (self.archives.index.pieces.get(member.archive) or [member.archive]) if member is not None else [rel]
        return self.manifest.identity(rel, objs)

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

    def _check_unchanged(self, expected: Optional[ListedObject], now: str) -> None:
        """Raises VideoError: the object's ETag ``now`` differs from the listing's (``expected``:
        its manifest entry)."""
        if expected is not None and expected.tag and now and now != expected.tag:
            self.stats.skipped += 1
            raise VideoError(f"changed since it was listed (ETag {expected.tag} -> {now}); skipped until "
                             f"--refresh-manifest")

    @contextlib.contextmanager
    def _open_raw(self, rel: str, expected: Optional[ListedObject] = None):
        """The object at ``rel`` as a file, checked against the listing's ETag (``expected``:
        its manifest entry, looked up when not given)."""
        block = max(1, int(self.settings.read_block_mb * (1 << 20)))
        with self._request():
            f = self.fs.open(self._path(rel), "rb", block_size=block, cache_type="blockcache",
                             cache_options={"maxblocks": 4})
        try:
            now = etag_of(getattr(f, "details", None) or {})
            self._check_unchanged(self.manifest.entry(rel) if expected is None else expected, now)
            time_fetches(f, self.stats)
            if self.settings.cache_max_gb > 0:
                with self.cache.open(f"{self.root}{rel}", now, f) as local:
                    yield local
            else:
                yield f
        finally:
            f.close()

    def _cache_folders(self) -> List[Path]:
        return [self.cache.disk.folder] if self.settings.cache_max_gb > 0 else []

    def take_stats(self) -> dict:
        return self.stats.take()

    def spec(self) -> dict:
        return {"root": self.root, "storage_options": self.storage_options, "video_list": self.video_list,
                "manifest": self.manifest.path, "settings": self.settings, "cache_dir": self.cache_dir,
                "table": self.table}

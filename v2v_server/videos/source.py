"""Where the videos live: a corpus as a local folder or an object-store prefix (any URL fsspec
understands: ``s3://`` through s3fs, ``gs://`` through gcsfs, ``az://`` through adlfs), optionally
narrowed and ordered by a video list in the V2V authors' format.

Every reader of the corpus goes through a :class:`VideoSource`: ``v2v-serve`` (listing, shards,
the corpus fingerprint, ``--check``), its worker processes (``source.open(rel)`` per task), and
the Ray engine (``ray_data``). A source lists the corpus as **sample-id paths**: POSIX paths
relative to the folder or key prefix, so the same files in a folder and under a bucket prefix
give the same ids and, for the same seed, bit-identical samples. ``open(rel)`` yields what
``decode.open_video`` reads: a local path, or a file object on the stored object that fetches
it in ``read_block_mb`` blocks (PyAV reads straight from it, no local copy).

An object store is listed once and the listing is kept as a **manifest** (one JSON line per
object: key relative to the prefix, size in bytes, ETag), so a restart and every shard of the
corpus read the same listing without walking the bucket again; see :func:`manifest_path` for
where it is kept. A worker compares the ETag the store reports when it opens an object with
the manifest's: an object overwritten since it was listed is skipped with the key named.

Transient store errors are retried by the storage library (botocore's ``standard`` retry mode
for S3: ``store_max_attempts`` attempts with exponential backoff, for throttling, 5xx and
connection errors); a read that still fails, or a store that stops answering for
``store_read_timeout_s``, fails that video's task, whose windows the server skips and logs
once; the server stays up.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import time
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Sequence, Tuple, Union

from v2v_server.videos.decode import VideoError, inside, printable, scan_corpus, utf8_name

log = logging.getLogger("v2v.source")

#: Protocols read through fsspec, and the extra that installs each one's library.
STORE_EXTRAS = {"s3": "v2v[s3]", "s3a": "v2v[s3]", "gs": "v2v[gcs]", "gcs": "v2v[gcs]", "az": "v2v[azure]",
                "abfs": "v2v[azure]", "abfss": "v2v[azure]"}
MANIFEST_VERSION = 1


class StoreError(RuntimeError):
    """The corpus cannot be reached at all (no such bucket, refused credentials, no library for
    the URL's protocol); the message names the URL. ``v2v-serve`` exits 2 on it."""


def is_url(videos: Union[str, Path, None]) -> bool:
    """True for a corpus given as a URL (``s3://``, ``gs://``...), False for a local folder
    (``file://`` URLs included: they are folders)."""
    return isinstance(videos, str) and "://" in videos and not videos.startswith("file://")


def read_video_list(path: str) -> List[str]:
    """The videos a list file names, in its order, duplicates dropped: the V2V authors' format
    (HYLZ-2019/V2V ``config/webvid10000_unfiltered.txt``): one video per line, its first
    whitespace-separated field a path relative to the corpus root (later fields, such as
    frame counts, are ignored); ``#`` starts a comment line; blank lines are skipped. Leading
    ``./`` is dropped so ids match a folder's listing.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: naming the file, when it lists nothing.
    """
    if is_url(path):  # a list kept beside the corpus in the store
        import fsspec

        with fsspec.open(path, "rt", encoding="utf-8") as f:
            lines = f.read().splitlines()
    else:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    out, seen = [], set()
    for line in lines:
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        rel = s.split()[0]
        while rel.startswith("./"):
            rel = rel[2:]
        rel = rel.lstrip("/")
        if rel and rel not in seen:
            seen.add(rel)
            out.append(rel)
    if not out:
        raise ValueError(f"video_list {path}: lists no video")
    return out


def manifest_path(url: str, state_dir: Optional[str] = None, cache_dir: Optional[str] = None) -> Path:
    """Where the manifest of the corpus at ``url`` is kept: ``STATE_DIR/manifest-H.jsonl`` when
    the server has a ``state_dir`` (it then travels with the delivery journal), else
    ``CACHE_DIR/manifests/H.jsonl`` with ``cache_dir`` defaulting to ``$XDG_CACHE_HOME/v2v``
    (``~/.cache/v2v``); H is a hash of the URL. Shards on one host share it; shards on other
    hosts list the store once each and, the store unchanged, write the same manifest."""
    h = hashlib.sha256(url.encode("utf-8")).hexdigest()[:16]
    if state_dir:
        return Path(state_dir) / f"manifest-{h}.jsonl"
    base = Path(cache_dir) if cache_dir else Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "v2v"
    return base / "manifests" / f"{h}.jsonl"


def write_manifest(path: Path, url: str, objects: Dict[str, Tuple[int, str]]) -> None:
    """Write ``objects`` (key relative to the prefix -> (size in bytes, ETag)) atomically: a
    header line ``{"v2v_manifest": 1, "url", "objects", "listed_at"}``, then one
    ``[key, size, etag]`` JSON line per object, sorted by key."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(json.dumps({"v2v_manifest": MANIFEST_VERSION, "url": url, "objects": len(objects),
                            "listed_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}) + "\n")
        for key in sorted(objects):
            size, etag = objects[key]
            f.write(json.dumps([key, size, etag], ensure_ascii=False) + "\n")
    os.replace(tmp, path)


def read_manifest(path: Path, url: str) -> Optional[Dict[str, Tuple[int, str]]]:
    """The objects of the manifest at ``path`` (see :func:`write_manifest`), or None when there
    is none, it is of another URL or version, or it is cut short (a crash while written by
    another process: it is then listed again)."""
    try:
        with open(path, encoding="utf-8") as f:
            header = json.loads(f.readline() or "null")
            if not isinstance(header, dict) or header.get("v2v_manifest") != MANIFEST_VERSION or header.get("url") != url:
                return None
            objects = {}
            for line in f:
                key, size, etag = json.loads(line)
                objects[key] = (int(size), str(etag))
    except (OSError, ValueError, TypeError):
        return None
    return objects if len(objects) == header.get("objects") else None


def _etag(info: dict) -> str:
    """The version tag of an object in a listing or ``info()`` answer: S3's ETag, GCS's
    generation, Azure's etag (quotes stripped)."""
    for k in ("ETag", "etag", "generation", "md5Hash"):
        v = info.get(k)
        if v:
            return str(v).strip('"')
    return ""


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


class VideoSource:
    """A corpus: lists videos as sample-id paths and opens them for decoding. See the module
    docstring; :func:`open_source` builds one."""

    #: The corpus as given (a folder path or a URL), for logs and errors.
    root: str = ""
    #: The video list file that selects and orders the videos, if any.
    video_list: Optional[str] = None

    def list_videos(self, extensions: Sequence[str]) -> Tuple[List[str], List[Tuple[str, str]]]:
        """``(videos, rejected)``: sample-id paths of the videos (the list's order with a video
        list, else sorted), and ``(path, reason)`` for every entry not served."""
        raise NotImplementedError

    def open(self, rel: str):
        """A context manager giving what ``open_video`` reads for the video at ``rel``.

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
        """Keep the names of a video list that ``exists(name)`` and have a video extension."""
        videos, rejected = [], []
        for rel in names:
            if not rel.lower().endswith(tuple(extensions)):
                rejected.append((rel, f"listed in {self.video_list} but not a video file (extensions "
                                      f"{', '.join(extensions)})"))
            elif not exists(rel):
                rejected.append((rel, f"listed in {self.video_list} but missing from {self.root}"))
            else:
                videos.append(rel)
        return videos, rejected


class LocalSource(VideoSource):
    """A corpus folder (searched recursively, symlinks that stay inside it followed)."""

    def __init__(self, root: Union[str, Path], video_list: Optional[str] = None):
        root = str(root)
        self.root = root[len("file://"):] if root.startswith("file://") else root
        self.video_list = video_list

    def check(self) -> None:
        """Raises StoreError: the folder does not exist."""
        if not Path(self.root).is_dir():
            raise StoreError(f"--videos {self.root}: not a folder")

    def list_videos(self, extensions):
        if self.video_list:
            root = Path(self.root)
            return self._listed(read_video_list(self.video_list), lambda rel: inside(root, root / rel), extensions)
        found, rejected = scan_corpus(Path(self.root), extensions)
        return [p.as_posix() for p in found], [(p.as_posix(), why) for p, why in rejected]

    @contextlib.contextmanager
    def open(self, rel: str) -> Iterator[Path]:
        yield corpus_file(self.root, rel)

    def where(self, rel: str) -> str:
        return str(Path(self.root) / rel)

    def spec(self) -> dict:
        return {"root": self.root}


class _Stats:
    """Counters of one process's store reads (what ``take_stats`` hands to the server)."""

    def __init__(self):
        self.bytes = self.reads = self.retries = self.skipped = 0
        self.read_s = 0.0

    def take(self) -> dict:
        out = {"bytes": self.bytes, "reads": self.reads, "read_s": round(self.read_s, 6), "retries": self.retries,
               "skipped": self.skipped}
        self.__init__()
        return out


class StoreSource(VideoSource):
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
    """

    def __init__(self, url: str, storage_options: Optional[dict] = None, video_list: Optional[str] = None,
                 manifest: Optional[str] = None, refresh_manifest: bool = False, read_timeout_s: float = 20.0,
                 max_attempts: int = 3, read_block_mb: float = 8.0):
        self.protocol = url.split("://", 1)[0].lower()
        self.root = url if url.endswith("/") else url + "/"
        self.prefix = self.root.split("://", 1)[1]
        self.storage_options = dict(storage_options or {})
        self.video_list, self.manifest = video_list, manifest
        self.refresh_manifest = refresh_manifest
        self.read_timeout_s, self.max_attempts, self.read_block_mb = read_timeout_s, max_attempts, read_block_mb
        self._fs = None
        self._objects: Optional[Dict[str, Tuple[int, str]]] = None  # the manifest, loaded on first need
        self.stats = _Stats()

    # ------------------------------------------------------------------ the filesystem
    @property
    def fs(self):
        if self._fs is None:
            self._fs = self._make_fs()
        return self._fs

    def _make_fs(self):
        import fsspec

        try:
            cls = fsspec.get_filesystem_class(self.protocol)
        except (ImportError, ValueError) as e:
            extra = STORE_EXTRAS.get(self.protocol)
            raise StoreError(f"--videos {self.root}: no filesystem for {self.protocol}:// ({e})"
                             + (f"; pip install '{extra}'" if extra else "")) from None
        opts: dict = {"skip_instance_cache": True, "use_listings_cache": False}
        if self.protocol in ("s3", "s3a"):
            opts["config_kwargs"] = {"retries": {"mode": "standard", "max_attempts": self.max_attempts},
                                     "read_timeout": self.read_timeout_s, "connect_timeout": self.read_timeout_s}
        user = dict(self.storage_options)
        if "config_kwargs" in user and "config_kwargs" in opts:
            user["config_kwargs"] = {**opts["config_kwargs"], **user["config_kwargs"]}
        opts.update(user)
        fs = cls(**opts)
        if self.protocol in ("s3", "s3a"):
            fs.retries = 1  # s3fs's own retry loop off: botocore's retry mode above is the one policy
            self._count_retries(fs)
        return fs

    def _count_retries(self, fs) -> None:
        """Count botocore's retries (``ResponseMetadata.RetryAttempts`` of each answered call)."""
        stats = self.stats

        def after_call(parsed=None, **_):
            try:
                stats.retries += int(parsed["ResponseMetadata"].get("RetryAttempts", 0))
            except (TypeError, KeyError, ValueError):
                pass

        def on_client(client) -> None:
            client.meta.events.register("after-call.s3", after_call)

        fs._v2v_on_client = on_client
        orig = fs.set_session

        async def set_session(*a, **kw):
            client = await orig(*a, **kw)
            if not getattr(client, "_v2v_counted", False):
                on_client(client)
                client._v2v_counted = True
            return client

        fs.set_session = set_session

    def _fail(self, what: str, e: BaseException) -> StoreError:
        return StoreError(f"--videos {self.root}: {what}: {type(e).__name__}: {e}")

    def check(self) -> None:
        """Reach the store once (the bucket's metadata, not a listing).

        Raises:
            StoreError: naming the URL: no such bucket, credentials refused or missing, store
                unreachable, no library for the protocol.
        """
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
                self._objects = got
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
            objects[key[len(self.prefix):]] = (int(info.get("size") or 0), _etag(info))
        log.info("%s: listed %d object(s) in %.1f s", self.root, len(objects), time.monotonic() - t0)
        if self.manifest:
            try:
                write_manifest(Path(self.manifest), self.root, objects)
                log.info("manifest written to %s", self.manifest)
            except OSError as e:
                log.warning("cannot write the manifest %s: %s (the store is listed again at the next start)",
                            self.manifest, e)
        self.refresh_manifest = False
        self._objects = objects
        return objects

    def list_videos(self, extensions):
        if self.video_list:
            names = read_video_list(self.video_list)
            known = None  # with a list nothing is listed from the store: a manifest already there narrows it
            if self.manifest and not self.refresh_manifest:
                known = read_manifest(Path(self.manifest), self.root)
                self._objects = known
            return self._listed(names, (lambda rel: True) if known is None else known.__contains__, extensions)
        videos, rejected = [], []
        for rel in sorted(self.objects()):
            if not utf8_name(rel):
                rejected.append((printable(rel), "key is not valid UTF-8 (sample ids are UTF-8): rename it"))
            elif rel.endswith("/") or not rel:
                continue
            elif rel.lower().endswith(tuple(extensions)):
                videos.append(rel)
            else:
                rejected.append((rel, f"not a video file (extension {Path(rel).suffix or 'none'!r})"))
        return videos, rejected

    # ------------------------------------------------------------------ reading
    def _expected(self, rel: str) -> Optional[Tuple[int, str]]:
        if self._objects is None and self.manifest:
            self._objects = read_manifest(Path(self.manifest), self.root) or {}
        return (self._objects or {}).get(rel)

    @contextlib.contextmanager
    def open(self, rel: str):
        key = self.prefix + rel
        block = max(1, int(self.read_block_mb * (1 << 20)))
        t0 = time.perf_counter()
        try:
            f = self.fs.open(key, "rb", block_size=block, cache_type="blockcache", cache_options={"maxblocks": 4})
        except FileNotFoundError:
            self.stats.skipped += 1
            raise VideoError("missing from the store") from None
        except Exception as e:  # timeouts, refused reads: the file's verdict, never the worker's death
            raise VideoError(f"cannot open: {type(e).__name__}: {e}") from None
        finally:
            self.stats.read_s += time.perf_counter() - t0
        try:
            expected = self._expected(rel)
            now = _etag(getattr(f, "details", None) or {})
            if expected is not None and expected[1] and now and now != expected[1]:
                self.stats.skipped += 1
                raise VideoError(f"changed since it was listed (ETag {expected[1]} -> {now}); skipped until "
                                 f"--refresh-manifest")
            self._time_fetches(f)
            yield f
        finally:
            f.close()

    def _time_fetches(self, f) -> None:
        """Count the bytes and seconds of every range request of ``f``'s block cache."""
        cache = getattr(f, "cache", None)
        fetch = getattr(cache, "fetcher", None)
        if fetch is None:
            return
        stats = self.stats

        def timed(start, end):
            t = time.perf_counter()
            try:
                data = fetch(start, end)
            finally:
                stats.read_s += time.perf_counter() - t
                stats.reads += 1
            stats.bytes += len(data)
            return data

        cache.fetcher = timed

    def take_stats(self) -> dict:
        return self.stats.take()

    def spec(self) -> dict:
        return {"root": self.root, "storage_options": self.storage_options, "video_list": self.video_list,
                "manifest": self.manifest, "read_timeout_s": self.read_timeout_s, "max_attempts": self.max_attempts,
                "read_block_mb": self.read_block_mb}


def open_source(videos: Union[str, Path, None], *, storage_options: Optional[dict] = None,
                video_list: Optional[str] = None, manifest: Optional[str] = None, refresh_manifest: bool = False,
                read_timeout_s: float = 20.0, max_attempts: int = 3, read_block_mb: float = 8.0) -> VideoSource:
    """The source of a corpus given as a folder or a URL."""
    if isinstance(videos, VideoSource):
        return videos
    if is_url(str(videos)):
        return StoreSource(str(videos), storage_options, video_list, manifest, refresh_manifest, read_timeout_s,
                           max_attempts, read_block_mb)
    return LocalSource(videos, video_list)


def source_from_config(cfg, videos: Union[str, Path, None] = None) -> VideoSource:
    """The source ``cfg`` (a ``ServeConfig``) describes: ``videos`` or ``cfg.videos``, its
    ``video_list``, ``storage_options``, store timeouts and manifest (:func:`manifest_path`)."""
    videos = cfg.videos if videos is None else videos
    manifest = None
    if is_url(str(videos)) if videos is not None else False:
        manifest = str(manifest_path(StoreSource(str(videos)).root, cfg.state_dir, cfg.cache_dir))
    return open_source(videos, storage_options=cfg.storage_options, video_list=cfg.video_list, manifest=manifest,
                       refresh_manifest=cfg.refresh_manifest, read_timeout_s=cfg.store_read_timeout_s,
                       max_attempts=cfg.store_max_attempts, read_block_mb=cfg.read_block_mb)


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

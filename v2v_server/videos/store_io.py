"""Reading objects from a store: the fsspec filesystem with one retry policy, the counters of a
process's reads (bytes, range requests, seconds, retries, skipped objects) and the bounded local
cache of whole objects. ``videos.store.StoreSource`` wires them."""
from __future__ import annotations

import contextlib
import hashlib
import logging
import time
from pathlib import Path

log = logging.getLogger("v2v.source")

from v2v_server.faults import cause_of, warn_once
from v2v_server.videos.disk_cache import DiskCache, remove_quietly

#: Protocols read through fsspec, and the extra that installs each one's library.
STORE_EXTRAS = {"s3": "v2v[s3]", "s3a": "v2v[s3]", "gs": "v2v[gcs]", "gcs": "v2v[gcs]", "az": "v2v[azure]",
                "abfs": "v2v[azure]", "abfss": "v2v[azure]"}


class StoreError(RuntimeError):
    """The corpus cannot be reached at all (no such bucket, refused credentials, no library for
    the URL's protocol); the message names the URL. ``v2v-serve`` exits 2 on it."""


class ReadStats:
    """Counters of one process's store reads (what ``VideoSource.take_stats`` hands to the
    server): ``bytes`` fetched, range requests (``reads``), seconds waited (``read_s``),
    ``retries`` by the storage library, objects ``skipped`` (missing or changed)."""

    def __init__(self):
        self.bytes = self.reads = self.retries = self.skipped = 0
        self.read_s = 0.0

    def take(self) -> dict:
        """The counters since the last call, as a dict; then zero them."""
        out = {"bytes": self.bytes, "reads": self.reads, "read_s": round(self.read_s, 6), "retries": self.retries,
               "skipped": self.skipped}
        self.__init__()
        return out


def make_filesystem(protocol: str, root: str, storage_options: dict, read_timeout_s: float, max_attempts: int,
                    stats: ReadStats):
    """The fsspec filesystem of ``protocol``: no instance or listing cache; for S3 botocore's
    ``standard`` retry mode with ``max_attempts`` and ``read_timeout_s`` as the one retry
    policy (s3fs's own loop off), its retries counted in ``stats``; for GCS at an emulator's
    endpoint gcsfs's plain class (:func:`_gcs_emulator`); ``storage_options`` over these
    defaults.

    Raises:
        StoreError: naming ``root``, when no library serves ``protocol`` (with the extra to
            install).
    """
    import fsspec

    logging.getLogger("fsspec.caching").setLevel(logging.WARNING)  # a line per block fetched otherwise
    try:
        cls = fsspec.get_filesystem_class(protocol)
        if protocol in ("gs", "gcs") and _gcs_emulator(storage_options):
            from gcsfs.core import GCSFileSystem as cls  # see _gcs_emulator: no bucket-layout probe
    except (ImportError, ValueError) as e:
        extra = STORE_EXTRAS.get(protocol)
        raise StoreError(f"--videos {root}: no filesystem for {protocol}:// ({e})"
                         + (f"; pip install '{extra}'" if extra else "")) from None
    opts: dict = {"skip_instance_cache": True, "use_listings_cache": False}
    if protocol in ("s3", "s3a"):
        opts["config_kwargs"] = {"retries": {"mode": "standard", "max_attempts": max_attempts},
                                 "read_timeout": read_timeout_s, "connect_timeout": read_timeout_s}
    user = dict(storage_options)
    if "config_kwargs" in user and "config_kwargs" in opts:
        user["config_kwargs"] = {**opts["config_kwargs"], **user["config_kwargs"]}
    opts.update(user)
    fs = cls(**opts)
    if protocol in ("s3", "s3a"):
        fs.retries = 1  # s3fs's own retry loop off: botocore's retry mode above is the one policy
        _count_retries(fs, stats)
    return fs


def _gcs_emulator(storage_options: dict) -> bool:
    """True when gcsfs is pointed away from Google (``endpoint_url`` in ``storage_options`` or
    ``STORAGE_EMULATOR_HOST`` naming a host outside ``googleapis.com``): an emulator such as
    gcp-storage-emulator or fake-gcs-server.

    Such an endpoint gets gcsfs's plain ``gcsfs.core.GCSFileSystem``. Since gcsfs 2026.3 the
    class fsspec hands out for ``gs://`` is ``ExtendedGcsFileSystem``, which asks the gRPC
    Storage Control API for each bucket's layout (zonal, hierarchical) before reads and opens;
    an emulator serves the JSON API only, so each ask waits out gcsfs's 60 s retry deadline
    before falling back, and an unanswered ask is not remembered. Zonal and hierarchical
    buckets exist only on Google's own endpoints, which keep the extended class. (Setting
    ``GCSFS_EXPERIMENTAL_ZB_HNS_SUPPORT=false`` before gcsfs is first imported does the same
    for every endpoint.)"""
    import os
    from urllib.parse import urlparse

    endpoint = storage_options.get("endpoint_url") or os.environ.get("STORAGE_EMULATOR_HOST", "")
    if not endpoint or endpoint == "default":
        return False
    host = urlparse(endpoint if "://" in endpoint else f"http://{endpoint}").hostname or ""
    return not (host == "googleapis.com" or host.endswith(".googleapis.com"))


def _count_retries(fs, stats: ReadStats) -> None:
    """Count botocore's retries (``ResponseMetadata.RetryAttempts`` of each answered call)."""

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


def time_fetches(f, stats: ReadStats) -> None:
    """Count the bytes and seconds of every range request of the fsspec file ``f``'s block
    cache in ``stats``."""
    cache = getattr(f, "cache", None)
    fetch = getattr(cache, "fetcher", None)
    if fetch is None:
        return

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


class _LocalFault(Exception):
    """The object cache's own folder failed (its ``__cause__``), not the store."""


class ObjectCache:
    """A bounded local cache of whole objects in ``folder``: an entry is named by URL, key and
    ETag (a changed object is a new entry); the least recently used entries are removed while
    the cache would hold more than ``max_gb`` GiB (``disk_cache.DiskCache``, policy ``lru``: its
    atomic writes make it safe to share between the processes of a host)."""

    def __init__(self, folder: Path, max_gb: float):
        self.disk = DiskCache(folder, int(float(max_gb) * (1 << 30)), "lru")

    @contextlib.contextmanager
    def open(self, name: str, etag: str, f):
        """The object ``name`` (URL and key) of version ``etag`` as a local binary file, copied
        whole from the open object ``f`` on first use; ``f`` itself (rewound) when the object
        is larger than the whole budget, was evicted meanwhile, has no version tag (``etag``
        empty: nothing tells a later version from this one), or the cache's folder cannot be
        written (a full disk, the folder replaced or unmounted: logged once per cause, the
        partial copy removed); a store read that fails raises as it does without the cache.
        """
        if not etag:
            yield f
            return
        entry = hashlib.sha256(f"{name} {etag}".encode("utf-8")).hexdigest()[:32]
        path = self.disk.path(entry)
        try:
            if not path.is_file():
                self._copy(f, entry)
            else:
                self.disk.touch(entry)
            local = open(path, "rb")
        except _LocalFault as e:
            warn_once(log, ("object cache", cause_of(e.__cause__)), "object cache %s: %s; reading from the store",
                      self.disk.folder, e.__cause__)
            local = None
        except FileNotFoundError:  # over the whole budget, or evicted by another process meanwhile
            local = None
        if local is None:
            f.seek(0)
            yield f
            return
        with local:
            yield local

    def _copy(self, f, entry: str) -> None:
        """Copy the open object ``f`` whole into entry ``entry``.

        Raises:
            _LocalFault: the local folder or file failed (the partial copy removed).
            Exception: the store read failed, as raised by ``f.read``.
        """
        try:
            tmp = self.disk.temporary(entry)
            out = open(tmp, "wb")
        except OSError as e:
            raise _LocalFault() from e
        try:
            with out:
                while True:
                    chunk = f.read(1 << 22)
                    try:
                        out.write(chunk) if chunk else out.flush()
                    except OSError as e:
                        raise _LocalFault() from e
                    if not chunk:
                        break
        except BaseException:
            remove_quietly(tmp)
            raise
        try:
            self.disk.commit(tmp, entry)
        except OSError as e:
            raise _LocalFault() from e

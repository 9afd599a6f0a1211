"""Reading objects from a store: the fsspec filesystem with one retry policy, the counters of a
process's reads (bytes, range requests, seconds, retries, skipped objects) and the bounded local
cache of whole objects. ``sources.store.StoreSource`` wires them."""
from __future__ import annotations

import contextlib
import hashlib
import logging
import time
from pathlib import Path

log = logging.getLogger("v2v.source")

from v2v_server.faults import cause_of, warn_once
from v2v_server.disk_cache import DiskCache, remove_quietly
from v2v_server.sources.errors import StoreError

#: Protocols read through fsspec, and the extra that installs each one's library.
STORE_EXTRAS = {"s3": "v2v[s3]", "s3a": "v2v[s3]", "gs": "v2v[gcs]", "gcs": "v2v[gcs]", "az": "v2v[azure]",
                "abfs": "v2v[azure]", "abfss": "v2v[azure]"}


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
    """The fsspec filesystem of ``protocol``: no instance or listing cache, and the store
    settings' ``read_timeout_s`` (seconds a request may wait to connect, or between bytes of
    its answer) and ``max_attempts`` (attempts per request, with backoff) as the one retry
    policy of every store that takes them (:data:`RETRY_POLICY`):

    - S3 (s3fs): botocore's ``standard`` retry mode (s3fs's own loop off), its retries
      counted in ``stats``;
    - GCS (gcsfs): ``requests_timeout`` as aiohttp's connect and read timeouts, and gcsfs's
      retry loop (``gcsfs.retry.retry_request``, which a timeout also enters) bounded to
      ``max_attempts`` for the JSON API's requests (:func:`_gcs_class`); at an emulator's
      endpoint gcsfs's plain class (:func:`_gcs_emulator`);
    - Azure (adlfs): the Blob service client with azure-storage-blob's exponential retry
      policy of ``max_attempts - 1`` retries and ``connection_timeout``/``read_timeout``
      (:func:`_azure_client`);
    - http(s) (fsspec's aiohttp filesystem): the timeout as aiohttp's connect and read
      timeouts; one attempt per request (:func:`retry_policy` refuses another count).

    ``storage_options`` over these defaults; a store that cannot take a setting refuses any
    value but its default, by name (:func:`retry_policy`).

    Raises:
        StoreError: naming ``root``, when no library serves ``protocol`` (with the extra to
            install), or a retry setting this store cannot take.
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
    policy = retry_policy(protocol, root, read_timeout_s, max_attempts)
    opts: dict = {"skip_instance_cache": True, "use_listings_cache": False}
    if policy == "botocore":
        opts["config_kwargs"] = {"retries": {"mode": "standard", "max_attempts": max_attempts},
                                 "read_timeout": read_timeout_s, "connect_timeout": read_timeout_s}
    elif policy == "gcsfs":
        import aiohttp

        cls = _gcs_class(cls, max_attempts)
        opts["requests_timeout"] = aiohttp.ClientTimeout(sock_connect=read_timeout_s, sock_read=read_timeout_s)
    elif policy == "azure":  # adlfs passes these to each download; the client's own policy covers the rest
        opts.update(connection_timeout=read_timeout_s, read_timeout=read_timeout_s)
    elif policy == "aiohttp":
        import aiohttp

        opts["client_kwargs"] = {"timeout": aiohttp.ClientTimeout(sock_connect=read_timeout_s,
                                                                  sock_read=read_timeout_s)}
    user = dict(storage_options)
    for merged in ("config_kwargs", "client_kwargs"):
        if merged in user and merged in opts:
            user[merged] = {**opts[merged], **user[merged]}
    opts.update(user)
    fs = cls(**opts)
    if policy == "botocore":
        fs.retries = 1  # s3fs's own retry loop off: botocore's retry mode above is the one policy
        _count_retries(fs, stats)
    elif policy == "azure":
        fs.service_client = _azure_client(fs.service_client, read_timeout_s, max_attempts)
    return fs


#: protocol -> how the store settings' timeout and attempts reach its library (make_filesystem)
RETRY_POLICY = {"s3": "botocore", "s3a": "botocore", "gs": "gcsfs", "gcs": "gcsfs",
                "az": "azure", "abfs": "azure", "abfss": "azure", "http": "aiohttp", "https": "aiohttp"}
#: the store settings' defaults (owned here, where they are applied; ``store.StoreSettings`` reads them)
READ_TIMEOUT_S, MAX_ATTEMPTS = 20.0, 3


def retry_policy(protocol: str, root: str, read_timeout_s: float, max_attempts: int) -> str:
    """How ``protocol``'s filesystem takes the store settings (:data:`RETRY_POLICY`); a setting
    its library cannot take passes at its default (which describes the stores that take it)
    and is refused at any other value: fsspec's http(s) filesystem takes a timeout but makes
    one attempt per request, and other filesystems take neither.

    Raises:
        StoreError: naming ``root``, the setting and the stores that take it.
    """
    policy = RETRY_POLICY.get(protocol, "")
    refused = [("store_max_attempts", max_attempts, MAX_ATTEMPTS)] if policy in ("aiohttp", "") else []
    if not policy:
        refused.insert(0, ("store_read_timeout_s", read_timeout_s, READ_TIMEOUT_S))
    takers = {"store_read_timeout_s": "s3://, gs://, az:// and http(s)://", "store_max_attempts": "s3://, gs:// and az://"}
    for name, value, default in refused:
        if value != default:
            raise StoreError(f"--videos {root}: {name} {value!r} cannot be honoured for {protocol}:// (its "
                             f"filesystem takes no such setting; {takers[name]} do): leave it at its "
                             f"default {default!r}")
    return policy


def _gcs_class(base: type, max_attempts: int) -> type:
    """``base`` (a gcsfs filesystem class) with each JSON-API request (``_request``: listings,
    metadata and the range reads of an open file) attempted ``max_attempts`` times in all.
    gcsfs binds its count (``GCSFileSystem.retries``, 6) to ``_request`` when the class is
    defined (``gcsfs.retry.retry_request``), so the count is bound again here, on the same
    undecorated method.

    Raises:
        StoreError: this gcsfs defines ``_request`` without that decorator (the count could
            not be honoured).
    """
    from gcsfs.retry import retry_request

    defined = next(k.__dict__["_request"] for k in base.__mro__ if "_request" in k.__dict__)
    plain = getattr(defined, "__wrapped__", None)
    if plain is None:
        raise StoreError(f"store_max_attempts cannot be honoured: {base.__module__}.{base.__name__}._request "
                         f"has no retry count to bind (gcsfs 2026.10.1's is gcsfs.retry.retry_request's)")
    return type(base.__name__, (base,), {"retries": max_attempts, "_request": retry_request(retries=max_attempts)(plain)})


def _azure_client(client, read_timeout_s: float, max_attempts: int):
    """The Blob service client adlfs built (its account URL and credential), again with
    azure-storage-blob's exponential retry policy of ``max_attempts - 1`` retries (backoff
    1 s, then 1 + 2**k s, jittered) and ``read_timeout_s`` to connect and between bytes
    read: adlfs builds its client with the SDK's defaults (3 retries from 15 s) and takes no
    option for them."""
    from azure.storage.blob.aio import ExponentialRetry  # the async client takes the async policy

    retry = ExponentialRetry(initial_backoff=1, increment_base=2, retry_total=max_attempts - 1,
                             random_jitter_range=1)
    return type(client)(account_url=client.url, credential=client.credential, retry_policy=retry,
                        connection_timeout=read_timeout_s, read_timeout=read_timeout_s)


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

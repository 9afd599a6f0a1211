"""Real emulators of Google Cloud Storage and Azure Blob Storage for tests, shaped like
``harness.object_store.SeaweedS3``: each on a free loopback port, in its own temporary folder,
waited for with a bounded loop, stopped by pid (SIGTERM, then SIGKILL after ``grace_s``),
its folder removed.

- :class:`GcsEmulator`: ``gcp-storage-emulator`` (PyPI; the dev extra installs it), the GCS
  JSON API in one Python process, read through gcsfs with ``token="anon"``.
- :class:`AzuriteBlob`: Microsoft's Azurite (npm ``azurite``, :data:`AZURITE_VERSION`), its
  Blob service only, read through adlfs with the emulator's well-known account
  ``devstoreaccount1``. ``.ci/run`` installs Python packages only, so :func:`ensure_azurite`
  installs Azurite on first use into ``$XDG_CACHE_HOME/v2v-azurite-VERSION`` with npm.

``with GcsEmulator() as gcs: ...`` gives ``gcs.storage_options()`` (what ``open_source`` /
``StoreSource`` / the YAML's ``storage_options`` take), ``gcs.env()`` (the variables a client
reads instead), ``gcs.fs()`` and ``gcs.upload(folder, "gs://bucket/prefix/")``; the same for
``AzuriteBlob`` with ``az://container/prefix/``.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Dict, List

from harness.object_store import LocalServer, _free_ports

#: The Azurite release the tests run: the newest whose package accepts Node.js 20 (3.36 and
#: later declare Node >= 21 / 22).
AZURITE_VERSION = "3.35.0"
#: Azurite's fixed development account and key (public, documented by Microsoft).
AZURITE_ACCOUNT = "devstoreaccount1"
AZURITE_KEY = "Eby8vdM02xNOcqFlqUwJPLlmEtlCDXJ1OUzFT50uSRZ6IFsuFq2UVErCz4I6tq/K1SZFPTOtr/KBHBeksoGMGw=="


class EmulatorUnavailable(RuntimeError):
    """What an emulator needs is not on this machine (``npm`` for Azurite); tests skip on it."""


class _Emulator(LocalServer):
    """One emulator process on 127.0.0.1 (``harness.object_store.LocalServer``, whose ``upload``
    fills it): subclasses give ``_args()``, ``fs()`` and ``scheme``.

    Raises (from ``start``):
        RuntimeError: the process exited or did not answer within ``ready_timeout_s`` (the
            message holds its log tail).
    """

    _ready_path = "/"

    def _args(self) -> List[str]:
        raise NotImplementedError

    def fs(self, **kw):
        """The fsspec filesystem on this emulator (a fresh client on each call; ``kw`` to it)."""
        raise NotImplementedError

    def storage_options(self) -> dict:
        """The ``storage_options`` that point v2v's reader of this store at the emulator."""
        raise NotImplementedError

    def env(self) -> Dict[str, str]:
        """Environment variables that point a client of this store at the emulator."""
        raise NotImplementedError

    def start(self):
        self.dir = tempfile.mkdtemp(prefix=f"v2v-{self.name}-")
        self.port = _free_ports(1)[0]
        return self._launch(self._args(), "emulator.log")

    def _answers(self) -> bool:
        """True once the emulator answers HTTP on its port (any status: an unauthenticated
        request is refused by Azurite, which still means it is serving)."""
        import urllib.error
        import urllib.request

        try:
            urllib.request.urlopen(self.endpoint + self._ready_path, timeout=2).close()
            return True
        except urllib.error.HTTPError:
            return True
        except OSError:  # not up yet: connection refused or reset
            return False


class GcsEmulator(_Emulator):
    """``gcp-storage-emulator`` on 127.0.0.1, objects kept in memory (nothing on disk).

    Its objects carry a ``generation`` that changes on every overwrite (v2v's version tag for
    GCS) and an ``etag`` that is the content's MD5.

    Raises (from ``start``):
        EmulatorUnavailable: the ``gcp_storage_emulator`` package is not installed.
    """

    scheme = "gs"
    name = "gcs-emulator"
    _ready_path = "/storage/v1/b?project=v2v-test"
    project = "v2v-test"

    def start(self) -> "GcsEmulator":
        try:
            import gcp_storage_emulator  # noqa: F401
        except ImportError:
            raise EmulatorUnavailable("gcp-storage-emulator not installed (pip install gcp-storage-emulator: "
                                      "the dev extra installs it)") from None
        return super().start()

    def _args(self) -> List[str]:
        return [sys.executable, "-m", "gcp_storage_emulator", "start", "--host", "127.0.0.1",
                "--port", str(self.port), "--in-memory", "--quiet"]

    def storage_options(self) -> dict:
        return {"endpoint_url": self.endpoint, "token": "anon", "project": self.project}

    def env(self) -> Dict[str, str]:
        return {"STORAGE_EMULATOR_HOST": self.endpoint}

    def fs(self, **kw):
        # gcsfs's plain class: since gcsfs 2026.3 ``gcsfs.GCSFileSystem`` asks a gRPC API this
        # emulator does not serve for each bucket's layout, 60 s per call (see store_io)
        from gcsfs.core import GCSFileSystem

        return GCSFileSystem(skip_instance_cache=True, use_listings_cache=False, **self.storage_options(), **kw)


def azurite_dir(version: str = AZURITE_VERSION) -> Path:
    """Where :func:`ensure_azurite` keeps Azurite ``version``: ``$XDG_CACHE_HOME/v2v-azurite-VERSION``
    (``~/.cache/...``)."""
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return cache / f"v2v-azurite-{version}"


def ensure_azurite(version: str = AZURITE_VERSION, timeout_s: float = 300.0) -> Path:
    """The path of Azurite's Blob service script (``node_modules/azurite/dist/src/blob/main.js``),
    installed with ``npm install azurite@VERSION`` into :func:`azurite_dir` when missing (into a
    temporary folder first, then renamed: two processes installing at once both end with one
    whole copy).

    Raises:
        EmulatorUnavailable: ``node`` or ``npm`` is not on PATH.
        RuntimeError: npm failed or took longer than ``timeout_s`` (with its output's tail).
    """
    final = azurite_dir(version)
    main = Path("node_modules", "azurite", "dist", "src", "blob", "main.js")
    if (final / main).is_file():
        return final / main
    npm, node = shutil.which("npm"), shutil.which("node")
    if npm is None or node is None:
        raise EmulatorUnavailable(f"Azurite needs Node.js and npm on PATH (npm install azurite@{version}); "
                                  f"{'npm' if npm is None else 'node'} not found")
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=final.name + ".", dir=final.parent))
    try:
        try:
            done = subprocess.run([npm, "install", "--prefix", str(tmp), "--no-audit", "--no-fund",
                                   "--loglevel=error", f"azurite@{version}"], capture_output=True, text=True,
                                  timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise RuntimeError(f"npm install azurite@{version} took over {timeout_s} s") from None
        if done.returncode != 0 or not (tmp / main).is_file():
            raise RuntimeError(f"npm install azurite@{version} failed ({done.returncode}):\n"
                               f"{(done.stdout + done.stderr)[-3000:]}")
        try:
            os.rename(tmp, final)
        except OSError:  # another process installed it meanwhile: keep theirs
            if not (final / main).is_file():
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return final / main


class AzuriteBlob(_Emulator):
    """Azurite's Blob service on 127.0.0.1 (account ``devstoreaccount1``), data in its folder,
    no telemetry (``--disableTelemetry``), any API version the client speaks accepted
    (``--skipApiVersionCheck``: azure-storage-blob releases run ahead of the emulator's).

    Raises (from ``start``):
        EmulatorUnavailable, RuntimeError: from :func:`ensure_azurite`.
    """

    scheme = "az"
    name = "azurite"

    def __init__(self, version: str = AZURITE_VERSION, **kw):
        super().__init__(**kw)
        self.azurite_version = version

    def start(self) -> "AzuriteBlob":
        self.main_js = ensure_azurite(self.azurite_version)
        if shutil.which("node") is None:
            raise EmulatorUnavailable("Azurite needs Node.js on PATH; node not found")
        return super().start()

    def _args(self) -> List[str]:
        return [shutil.which("node"), str(self.main_js), "--blobHost", "127.0.0.1", "--blobPort", str(self.port),
                "--location", str(Path(self.dir) / "data"), "--silent", "--skipApiVersionCheck",
                "--disableTelemetry"]

    @property
    def connection_string(self) -> str:
        return (f"DefaultEndpointsProtocol=http;AccountName={AZURITE_ACCOUNT};AccountKey={AZURITE_KEY};"
                f"BlobEndpoint={self.endpoint}/{AZURITE_ACCOUNT};")

    def storage_options(self) -> dict:
        return {"connection_string": self.connection_string}

    def env(self) -> Dict[str, str]:
        return {"AZURE_STORAGE_CONNECTION_STRING": self.connection_string}

    def fs(self, **kw):
        from adlfs import AzureBlobFileSystem

        return AzureBlobFileSystem(skip_instance_cache=True, **self.storage_options(), **kw)

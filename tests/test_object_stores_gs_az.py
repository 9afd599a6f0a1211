"""gs:// and az:// corpora against real emulators (harness/cloud_emulators.py): gcp-storage-emulator
read through gcsfs, Azurite's Blob service read through adlfs. For each store: the listing's keys,
sizes and versions (GCS generation, Azure ETag), one epoch byte for byte the folder's (also through
a worker's source rebuilt from ``spec()``), a video's identity following an overwrite in place, and
the frame cache serving epoch 1 with no video byte fetched."""
from __future__ import annotations

import functools
import threading
import time
from pathlib import Path

import pytest

from harness.cloud_emulators import AzuriteBlob, EmulatorUnavailable, GcsEmulator
from v2v_server import cli
from v2v_server.ops.config import ServeConfig
from v2v_server.sources.errors import VideoError
from tests.store_checks import check_a_paused_store_fails_the_read, check_frame_cache_hit, samples
from v2v_server.ops.config import source_from_config
from v2v_server.sources.local import LocalSource
from v2v_server.sources.manifest import manifest_path
from v2v_server.sources.source_spec import source_from_spec
from v2v_server.sources.store import StoreSettings, StoreSource
from v2v_server.sources.errors import StoreError

ROOT = Path(__file__).resolve().parents[1]
CLIPS = ROOT / "v2v_server" / "sample_videos"
NAMES = sorted(p.name for p in CLIPS.glob("*.mp4"))
#: store -> (emulator, the library that reads it, the info() key holding the object's version)
STORES = {"gs": (GcsEmulator, "gcsfs", "generation"), "az": (AzuriteBlob, "adlfs", "etag")}


#: each test well under this; a store client stuck in a wait (gcsfs's bucket-layout probe against an
#: emulator: 60 s per call) fails here instead of running on for minutes
pytestmark = pytest.mark.timeout(60, func_only=True)  # the test bodies; Azurite's npm install bounds itself


def _cfg() -> ServeConfig:
    return ServeConfig(sequence_length=4, crop_size=64, max_samples_per_video=2)


@pytest.fixture(scope="module", params=sorted(STORES))
def store(request):
    """One emulator per store, shared by the module's tests of that store, stopped after them."""
    cls, library, _ = STORES[request.param]
    pytest.importorskip(library, reason=f"{library} not installed (the dev extra installs it)")
    try:
        emulator = cls().start()
    except EmulatorUnavailable as e:
        pytest.skip(str(e))
    try:
        yield emulator
    finally:
        emulator.stop()


@pytest.fixture(scope="module")
def url(store) -> str:
    """The bundled clips uploaded under a prefix of one bucket (container)."""
    u = f"{store.scheme}://corpus/clips/"
    store.upload(CLIPS, u, names=NAMES)
    return u


def _samples(root, names, epoch: int, cfg=None) -> dict:
    """sample id -> bytes of its arrays, for ``names`` of ``root`` (a folder or a source)."""
    return samples(cfg or _cfg(), root, names, epoch)


@functools.lru_cache(maxsize=None)
def _folder_samples(names: tuple, epoch: int) -> dict:
    return _samples(LocalSource(CLIPS), names, epoch)


def _version(store, key: str) -> str:
    """The object's version as the store's own client reports it (no v2v code involved)."""
    return str(store.fs().info(key)[STORES[store.scheme][2]]).strip('"')


def test_store_lists_the_clips_with_sizes_and_versions(store, url, tmp_path):
    cfg = ServeConfig(videos=url, storage_options=store.storage_options(), cache_dir=str(tmp_path))
    src = source_from_config(cfg)
    assert isinstance(src, StoreSource)
    src.check()  # the bucket (container) is reached
    videos, rejected = src.list_videos(cfg.video_extensions)
    assert videos == NAMES and rejected == []
    objects = src.objects()
    for name in NAMES:
        size, version = objects[name].size, objects[name].tag
        assert size == (CLIPS / name).stat().st_size
        assert version and version == _version(store, f"corpus/clips/{name}")
    assert len({v.tag for v in objects.values()}) == len(NAMES)
    # the manifest written under the cache folder gives a second source the same listing without the store
    assert manifest_path(url, str(tmp_path)).is_file()
    again = source_from_config(cfg)
    again._fs = False  # no filesystem: a request to the store would raise AttributeError
    assert again.objects() == objects


def test_the_environment_alone_points_at_the_store(store, url, monkeypatch):
    """No storage options: gcsfs reads STORAGE_EMULATOR_HOST, adlfs AZURE_STORAGE_CONNECTION_STRING
    (what worker processes inherit)."""
    for k, v in store.env().items():
        monkeypatch.setenv(k, v)
    src = StoreSource(url)
    src.check()
    assert src.list_videos((".mp4",)) == (NAMES, [])
    assert src.identity("bikes.mp4").split()[2] == _version(store, "corpus/clips/bikes.mp4")


def test_gcs_endpoints_of_google_keep_the_layout_probe(monkeypatch):
    """Only an endpoint away from Google gets gcsfs's plain class (store_io._gcs_emulator)."""
    from v2v_server.sources.store_io import _gcs_emulator

    monkeypatch.delenv("STORAGE_EMULATOR_HOST", raising=False)
    assert not _gcs_emulator({})
    assert not _gcs_emulator({"endpoint_url": "https://storage.googleapis.com"})
    assert not _gcs_emulator({"endpoint_url": "https://storage-acme.p.googleapis.com"})
    assert _gcs_emulator({"endpoint_url": "http://127.0.0.1:9023"})
    assert _gcs_emulator({"endpoint_url": "https://googleapis.com.example"})
    monkeypatch.setenv("STORAGE_EMULATOR_HOST", "localhost:9023")
    assert _gcs_emulator({})


def test_a_missing_bucket_is_named(store):
    src = StoreSource(f"{store.scheme}://no-such-bucket/clips/", storage_options=store.storage_options())
    with pytest.raises(Exception, match="no-such-bucket"):
        src.check()


def test_store_epoch_is_the_folder_epoch_byte_for_byte(store, url):
    src = StoreSource(url, storage_options=store.storage_options())
    videos, _ = src.list_videos(_cfg().video_extensions)
    want = _folder_samples(tuple(NAMES), 0)
    assert len(want) == 2 * len(NAMES)
    assert _samples(src, videos, 0) == want
    assert src.take_stats()["bytes"] >= sum((CLIPS / n).stat().st_size for n in NAMES)
    # a worker rebuilds the source from its spec (storage options included) and reads the same
    worker = source_from_spec(src.spec())
    assert _samples(worker, videos, 0) == want


def test_identity_follows_an_overwrite_in_place(store, url):
    u = f"{store.scheme}://corpus/ident/"
    store.upload(CLIPS, u, names=["bikes.mp4"])
    listed = StoreSource(u, storage_options=store.storage_options())
    listed.list_videos((".mp4",))
    first = listed.identity("bikes.mp4")
    assert first == f"object {(CLIPS / 'bikes.mp4').stat().st_size} {_version(store, 'corpus/ident/bikes.mp4')}"
    assert listed.identity("bikes.mp4") == first  # nothing written: the same identity
    store.upload(CLIPS, u, names=["bikes.mp4"])  # the same bytes written again: a new version all the same
    fresh = StoreSource(u, storage_options=store.storage_options())
    second = fresh.identity("bikes.mp4")
    assert second != first and second.startswith(first.rsplit(" ", 1)[0] + " ")  # same size, new version
    with pytest.raises(VideoError, match="changed since it was listed"):
        listed.identity("bikes.mp4")


def test_frame_cache_hit_saves_the_download(store, tmp_path):
    """Epoch 1 is cut from the frame cache's entries with one metadata request per video and no
    byte of video fetched; an object overwritten in place is a ``changed`` miss, decoded anew.
    Samples equal the folder's (``store_checks.check_frame_cache_hit``, the same check as S3's)."""
    check_frame_cache_hit(store, _cfg(), tmp_path, store.storage_options(), _folder_samples)


def _settled(store, url: str, **settings) -> StoreSource:
    """A source with these store settings that has listed the corpus and read from it once
    (its connection open), before the store goes silent."""
    src = StoreSource(url, storage_options=store.storage_options(), settings=StoreSettings(**settings))
    src.list_videos((".mp4",))
    with src.open("bikes.mp4") as f:
        assert f.read(8)[4:8] == b"ftyp"
    return src


def test_a_silent_store_fails_the_read_within_the_timeout_and_attempts(store, url):
    """store_read_timeout_s and store_max_attempts reach gcsfs and adlfs: one attempt of 1 s
    against a store that stops answering fails the read at once (gcsfs alone would wait for
    the answer with no timeout; adlfs's client would retry 3 times from 15 s)."""
    src = _settled(store, url, store_read_timeout_s=1.0, store_max_attempts=1)
    assert check_a_paused_store_fails_the_read(store, src, "webvid_like_596x336.mp4")[4:8] == b"ftyp"


def test_a_store_silent_for_less_than_the_attempts_is_retried(store, url):
    """Silent for one and a half timeouts: the read that timed out is attempted again and
    returns the object whole (store_max_attempts 4)."""
    src = _settled(store, url, store_read_timeout_s=1.0, store_max_attempts=4)
    store.pause()
    threading.Timer(1.6, store.resume).start()
    try:
        with src.open("webvid_like_596x336.mp4") as f:
            assert f.read() == (CLIPS / "webvid_like_596x336.mp4").read_bytes()
    finally:
        time.sleep(1.7)
        store.resume()


@pytest.mark.parametrize("url, key, value", [("https://127.0.0.1:9/clips/", "store_max_attempts", 5),
                                             ("memory://corpus/clips/", "store_read_timeout_s", 5.0),
                                             ("memory://corpus/clips/", "store_max_attempts", 2)])
def test_a_store_that_cannot_take_a_retry_setting_refuses_it_by_name(url, key, value, capsys):
    """fsspec's http(s) filesystem takes a timeout but makes one attempt; the memory filesystem
    takes neither: any value but the default is refused, naming the key, by the source and by
    v2v-serve (one line, exit 2); the defaults pass."""
    StoreSource(url)
    with pytest.raises(StoreError, match=f"--videos {url}: {key} {value!r} cannot be honoured"):
        StoreSource(url, settings=StoreSettings(**{key: value}))
    flag = {"store_max_attempts": "--store-max-attempts", "store_read_timeout_s": "--store-read-timeout"}[key]
    assert cli.main(["--videos", url, flag, str(value), "--bind", "tcp://127.0.0.1:0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"v2v-serve: --videos {url}: {key} {value!r} cannot be honoured"), err


def test_an_http_server_that_never_answers_fails_the_read_within_the_timeout():
    """store_read_timeout_s reaches fsspec's http(s) filesystem (aiohttp's read timeout): a
    server on 127.0.0.1 that accepts and never answers fails the open after about 1 s."""
    import socket

    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(8)
        url = f"http://127.0.0.1:{server.getsockname()[1]}/clips/"
        src = StoreSource(url, settings=StoreSettings(store_read_timeout_s=1.0))
        t0 = time.monotonic()
        with pytest.raises(VideoError):  # its metadata request timed out (aiohttp's default: 5 min in all)
            with src.open("bikes.mp4"):
                pass
        took = time.monotonic() - t0
    assert took < 20, f"a silent http server held the read {took:.1f} s"

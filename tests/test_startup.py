"""One start-up path (``ops.startup.start_source``) for every way of running the service:
``v2v-serve`` (``cli.main``), the in-process server (``service.local.local_server``) and the
Ray engine's scan (``ray_data.scan_corpus_windows``) refuse the same bad settings with the same
error, and build their source from the same configuration keys."""
from __future__ import annotations

from pathlib import Path

import pytest

from v2v_server import cli
from v2v_server.ops.config import ServeConfig, source_from_config
from v2v_server.ops.startup import resolve_config, start_source
from v2v_server.ray_data import SampleMaker, scan_corpus_windows
from v2v_server.service.local import local_server
from v2v_server.ops.startup import SAMPLE_VIDEOS
from v2v_server.disk_cache import cache_folder, default_cache_dir
from v2v_server.sources.manifest import manifest_path
from v2v_server.disk_cache import CacheDirError
from v2v_server.sources.errors import StoreError

CLIPS = str(SAMPLE_VIDEOS)


def _refusals(capsys, keys: dict, flags: list, videos: str, error: type) -> tuple:
    """The error each of the three paths gives for ``keys`` (as config keys and as the same
    ``flags`` on the command line): the CLI's stderr line, the local service's and the Ray
    scan's message."""
    assert cli.main(["--videos", videos, "--bind", "tcp://127.0.0.1:0", *flags]) == 2
    told = capsys.readouterr().err.strip().splitlines()
    cfg = ServeConfig(**keys)
    with pytest.raises(error) as local:
        with local_server(videos, workers=1, batch_size=2, config=cfg):
            pass
    with pytest.raises(error) as ray:
        scan_corpus_windows(videos, cfg)
    return told, str(local.value), str(ray.value)


def test_a_cache_dir_that_cannot_keep_the_cache_is_refused_by_every_path(tmp_path, capsys):
    bad = tmp_path / "not_a_folder"
    bad.write_text("a file")
    told, local, ray = _refusals(capsys, {"cache_dir": str(bad), "frame_cache_gb": 1.0},
                                 ["--cache-dir", str(bad), "--frame-cache-gb", "1"], CLIPS, CacheDirError)
    assert local == ray and local.startswith(f"--cache-dir {bad}: cannot keep a cache in {bad / 'frames'}"), local
    assert told == [f"v2v-serve: {local}"]


def test_a_missing_corpus_folder_is_refused_by_every_path(tmp_path, capsys):
    missing = str(tmp_path / "no_such_corpus")
    told, local, ray = _refusals(capsys, {}, [], missing, StoreError)
    assert local == ray == f"--videos {missing}: not a folder"
    assert told == [f"v2v-serve: {local}"]


def test_every_path_reads_the_video_list_of_the_config(tmp_path, capsys):
    """The local service builds its source from the configuration too (``source_from_config``):
    a missing list file is refused by it as by the others."""
    lst = tmp_path / "missing_list.txt"
    told, local, ray = _refusals(capsys, {"video_list": str(lst)}, ["--video-list", str(lst)], CLIPS,
                                 FileNotFoundError)
    assert local == ray == f"video_list {lst}: no such file"
    assert told == [f"v2v-serve: {local}"]


def test_the_cache_folder_is_resolved_once_and_carried_down(tmp_path, monkeypatch):
    """No ``cache_dir``: the start-up path resolves the host's default once; the source, the
    caches beside it (frame cache, corpus index) and the Ray actors' specs all use that folder."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    start = start_source(ServeConfig(frame_cache_gb=1.0))
    want = str(tmp_path / "xdg" / "v2v")
    assert cache_folder(None) == str(default_cache_dir()) == want
    assert start.config.cache_dir == start.source.cache_dir == start.caches.cache_dir == want
    assert str(start.caches.frame_cache.disk.folder) == str(tmp_path / "xdg" / "v2v" / "frames")
    actor = SampleMaker.arguments(resolve_config(ServeConfig()), CLIPS, ("voxels",))
    assert actor["source_spec"]["cache_dir"] == actor["caches_spec"]["cache_dir"] == want
    assert start.caches.corpus_index().path == Path(want) / "corpus_index.sqlite"
    bucket = source_from_config(ServeConfig(), "s3://corpus/clips/")  # not reached: built only
    assert Path(bucket.manifest.path).parent == Path(want) / "manifests"
    with pytest.raises(ValueError, match="needs a resolved cache folder"):
        manifest_path("s3://corpus/clips/", None)
    given = start_source(ServeConfig(cache_dir=str(tmp_path / "mine")))
    assert given.config.cache_dir == given.source.cache_dir == str(tmp_path / "mine")
    assert resolve_config(given.config) == given.config

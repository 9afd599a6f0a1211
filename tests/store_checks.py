"""Checks shared by the object-store tests: the same assertions against SeaweedFS S3
(``tests/test_object_store.py``) and the GCS and Azure emulators (``tests/test_object_stores_gs_az.py``)."""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional

from tests.cached import Cached, cached
from v2v_server.sources.local import LocalSource

ROOT = Path(__file__).resolve().parents[1]
CLIPS = ROOT / "v2v_server" / "sample_videos"
OUTPUTS = ("voxels", "frames")


def samples(cfg, root, names, epoch: int) -> dict:
    """sample id -> bytes of its :data:`OUTPUTS`, for ``names`` of ``root`` (a source, or a
    ``Cached`` one read through its frame cache)."""
    from v2v_server.samples.make import video_samples

    source, caches = (root.source, root.caches) if isinstance(root, Cached) else (root, None)
    return {k.sample_id(1): b"".join(a[o].tobytes() for o in OUTPUTS)
            for v in names for k, a, _ in video_samples(cfg.recipe, source, v, epoch, OUTPUTS, caches=caches)}


def check_frame_cache_hit(store, cfg, tmp_path: Path, storage_options: Optional[dict] = None,
                          folder_samples: Optional[Callable[[tuple, int], dict]] = None) -> None:
    """Two bundled clips uploaded under ``SCHEME://corpus/fc/`` of ``store`` (a
    ``harness.object_store.LocalServer``) and read with the frame cache: epoch 1 is cut from the
    cache's entries with one metadata request per video and no byte of video fetched; an object
    overwritten in place is a ``changed`` miss, decoded anew. Samples equal the folder's
    (``folder_samples(names, epoch)``, else made from the bundled clips).

    ``storage_options``: what the store's reader takes (None: it reads the environment)."""
    folder_samples = folder_samples or (lambda names, epoch: samples(cfg, LocalSource(CLIPS), names, epoch))
    url = f"{store.scheme}://corpus/fc/"
    names = ["bikes.mp4", "webvid_like_596x336.mp4"]
    store.upload(CLIPS, url, names=names)
    cache = str(tmp_path / "cache")
    src = cached(url, cache, storage_options=storage_options)
    assert samples(cfg, src, names, 0) == folder_samples(tuple(names), 0)
    first = src.take_stats()
    assert first["frame_cache"]["stored"] == 2 and first["bytes"] > 0, first
    assert samples(cfg, src, names, 1) == folder_samples(tuple(names), 1)
    second = src.take_stats()
    assert second["frame_cache"]["hits"] == 2 and second["bytes"] == 0 and second["reads"] == 2, second
    store.fs().put_file(str(CLIPS / "bigbuckbunny.mp4"), "corpus/fc/bikes.mp4")  # replaced in place
    now = tmp_path / "now"
    now.mkdir()
    (now / "bikes.mp4").write_bytes((CLIPS / "bigbuckbunny.mp4").read_bytes())
    fresh = cached(url, cache, storage_options=storage_options)  # new listing
    assert samples(cfg, fresh, ["bikes.mp4"], 2) == samples(cfg, LocalSource(now), ["bikes.mp4"], 2)  # decoded anew
    stats = fresh.take_stats()["frame_cache"]
    assert stats["misses"]["changed"] == 1 and stats["hits"] == 0, stats


def check_a_paused_store_fails_the_read(store, src, name: str) -> bytes:
    """Opening ``name`` of ``src`` while ``store`` (a harness server) stops answering fails with
    ``VideoError`` within 30 s, not a wait on a silent store; once it answers again the object
    reads. Returns its first 16 bytes, read then."""
    import time

    import pytest

    from v2v_server.sources.errors import VideoError

    store.pause()
    try:
        t0 = time.monotonic()
        with pytest.raises(VideoError, match="cannot open: "):
            with src.open(name):
                pass
        took = time.monotonic() - t0
    finally:
        store.resume()
    assert took < 30, f"a silent store held the read {took:.1f} s"
    with src.open(name) as f:  # answering again: reads resume
        return f.read(16)

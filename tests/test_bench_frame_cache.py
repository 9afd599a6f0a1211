"""``bench/frame_cache.py``: the worker path with the frame cache off, cold and warm in both
formats, the bytes of each format and a budget of half the corpus, on the bundled WebVid-like
clip (one round, two copies)."""
from __future__ import annotations

from bench.frame_cache import frames_per_video, measure
from bench.speed import clip_path


def test_frame_cache_bench_measures_each_path_and_format():
    r = measure(clip_path(), videos=2, rounds=1)
    assert r["bound"] > 0
    assert set(r["rows"]) == {"off", "raw epoch 0", "raw epoch 1", "zstd epoch 0", "zstd epoch 1"}
    assert all(v > 0 for v in r["rows"].values())
    # a warm entry skips decoding: epoch 1 makes more samples per CPU-second than the cold epoch
    for fmt in ("raw", "zstd"):
        assert r["rows"][f"{fmt} epoch 1"] > r["rows"][f"{fmt} epoch 0"]
    # an entry per copy; raw holds the kept region of every frame read, zstd fewer bytes
    n = frames_per_video(clip_path())
    assert r["bytes"]["raw"] >= n * 596 * int(336 * 0.54)
    assert 0 < r["bytes"]["zstd"] < r["bytes"]["raw"]
    # a budget of half the corpus keeps one of the two copies
    assert r["budget"]["hit_ratio"] == 0.5 and r["budget"]["rate"] > 0

"""One window rule for every reader of a video: on a clip with shot cuts, a frame of another size
inside a window, and a window that a cut drops after such a frame, ``--check``'s verdict, the
samples served and what the sample pass reports agree window by window, decoded or replayed from
the frame cache."""
from __future__ import annotations

import json
import time

import pytest

from harness.corpus import write_scenes_video
from v2v_server.samples.make import video_samples
from v2v_server.samples.recipe import SampleRecipe
from v2v_server.frames.check import check_video
from v2v_server.sources.local import RACY_NS, LocalSource
from tests.cached import Cached, cached as cached_corpus

CLIP = "scenes.mpg"


def _recipe(shot_cuts: str) -> SampleRecipe:
    """Windows of 11 frames (stride 10), at most 10 a video."""
    return SampleRecipe(sequence_length=2, num_bins=5, crop_size=16, max_samples_per_video=10, keep_top_fraction=1.0,
                        shot_cuts=shot_cuts)


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    """Scene a at 96x80 (frames 0-24), at 128x80 (25-29: the size changes inside window 2), scene b at
    128x80 (a cut near frame 30, inside window 2 under ``shot_cuts: avoid``), at 96x80 (the size
    changes again inside a later window, no cut there)."""
    d = tmp_path_factory.mktemp("window_pass")
    write_scenes_video(d / CLIP, [("a", 25, 96, 80), ("a", 5, 128, 80), ("b", 35, 128, 80), ("b", 30, 96, 80)])
    time.sleep(RACY_NS / 1e9 + 0.02)  # a file changed within the racy window is decoded and never stored
    return d


def _served(recipe: SampleRecipe, source) -> tuple:
    """The windows the sample pass serves, and its record (``window_pass.VideoPass``)."""
    source, caches = (source.source, source.caches) if isinstance(source, Cached) else (source, None)
    run = video_samples(recipe, source, CLIP, 0, ("frames",), caches=caches)
    return sorted({key.window for key, _, _ in run}), run.record()


def test_the_clip_holds_a_failed_window_that_a_cut_drops(corpus):
    """Without shot cuts avoided, a window holds the first size change; with, a cut falls inside
    that window after the change and drops it, and a later window still fails."""
    off = check_video(_recipe("off").windows, _recipe("off").decode, LocalSource(corpus), CLIP)
    avoid = check_video(_recipe("avoid").windows, _recipe("avoid").decode, LocalSource(corpus), CLIP)
    stride = _recipe("off").windows.window_stride
    first = off.failed_windows[0]
    assert any(first * stride < c < (first + 1) * stride for c in avoid.cuts), (off, avoid)
    assert avoid.dropped >= 1 and avoid.failed_windows, avoid


@pytest.mark.parametrize("shot_cuts", ["avoid", "off"])
@pytest.mark.parametrize("cached", [False, True])
def test_check_and_the_samples_served_agree_window_by_window(corpus, tmp_path, shot_cuts, cached):
    recipe = _recipe(shot_cuts)
    verdict = check_video(recipe.windows, recipe.decode, LocalSource(corpus), CLIP)
    failed = verdict.failed_windows
    source = cached_corpus(corpus, tmp_path) if cached else LocalSource(corpus)
    for _ in range(2 if cached else 1):  # the second pass replays the entry the first stored
        served, found = _served(recipe, source)
        assert served == [k for k in range(verdict.windows + len(failed)) if k not in failed], (verdict, served)
        assert found.cuts == (verdict.cuts if shot_cuts == "avoid" else ())
        assert found.dropped == verdict.dropped and found.frames == verdict.frames, (verdict, found)
    if cached:
        assert source.take_stats()["frame_cache"]["hits"] == 1


def test_the_sample_pass_reports_the_windows_check_fails(corpus):
    """A dropped window's failure is forgotten (its index goes to the next window, which is
    served), so the pass's failed windows and verdict are ``--check``'s."""
    recipe = _recipe("avoid")
    verdict = check_video(recipe.windows, recipe.decode, LocalSource(corpus), CLIP)
    served, found = _served(recipe, LocalSource(corpus))
    assert tuple(sorted(found.failed)) == verdict.failed_windows, (verdict, found)
    assert found.windows == verdict.windows + len(verdict.failed_windows)
    assert found.verdict(recipe.windows) == (verdict.windows, list(verdict.failed_windows), verdict.reason)


def test_the_pass_record_is_what_a_corpus_index_keeps(corpus):
    """The record of a pass round-trips through JSON with the facts ``--check`` prints."""
    recipe = _recipe("avoid")
    verdict = check_video(recipe.windows, recipe.decode, LocalSource(corpus), CLIP)
    _, found = _served(recipe, LocalSource(corpus))
    kept = json.loads(json.dumps(found.to_dict()))
    assert kept["frames"] == verdict.frames and kept["cuts"] == list(verdict.cuts) and kept["fps"] == 25.0
    assert (kept["width"], kept["height"]) == (96, 80) and kept["layout"] == recipe.reads.key
    assert len(kept["starts"]) == verdict.windows + len(verdict.failed_windows) and kept["error"] is None
    assert sorted(map(int, kept["failed"])) == list(verdict.failed_windows)
    stride = recipe.windows.window_stride
    # windows start at a shot's first frame + k x stride, and span no cut
    shots = [0] + kept["cuts"]
    assert all(any((s - c) % stride == 0 and s >= c for c in shots) for s in kept["starts"])
    assert not any(s < c <= s + stride for s in kept["starts"] for c in kept["cuts"])

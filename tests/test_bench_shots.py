"""bench/shots.py's second window pass (``shot_windows``): the starts the server's
``WindowLayout`` gives for a list of cuts, without decoding."""
from v2v_server.samples.recipe import SampleRecipe
from v2v_server.ops.startup import SAMPLE_VIDEOS
from v2v_server.frames.check import check_video
from v2v_server.sources.local import LocalSource

from bench.shots import shot_windows


def test_windows_fill_shots_and_never_span_a_cut():
    assert shot_windows([], 450, 201, 10) == [0, 200]
    assert shot_windows([5], 420, 201, 10) == [5, 205]
    assert shot_windows([5], 420, 201, 10, avoid_cuts=False) == [0, 200]  # the authors' layout
    assert shot_windows([201], 420, 201, 10) == [0, 201]  # a shot of exactly one window
    assert shot_windows([200], 420, 201, 10) == [200]  # 200 frames hold no window
    assert shot_windows([], 10_000, 201, 3) == [0, 200, 400]  # at most max_windows


def test_a_bundled_montage_gives_the_windows_the_server_counts():
    """The pass over a clip's cuts keeps as many windows as the server's window pass over its frames."""
    recipe = SampleRecipe(sequence_length=8, max_samples_per_video=1000)
    w = recipe.windows
    r = check_video(w, recipe.decode, LocalSource(SAMPLE_VIDEOS), "bikes.mp4")
    assert r.cuts and r.windows > 1
    kept = shot_windows(list(r.cuts), r.frames, w.frames_per_sample, w.max_samples_per_video)
    assert len(kept) == r.windows
    assert not [(s, c) for s in kept for c in r.cuts if s < c <= s + w.window_stride]

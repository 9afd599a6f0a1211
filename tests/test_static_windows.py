"""Static windows (``static_windows``, ``frames.motion``): a window whose frames barely change is
found from its frames before any simulation; ``keep`` (the default) serves today's samples,
``skip`` never serves one below ``STATIC_MOTION``, gives its index to the next window as a cut
does, and keeps every epoch exactly once."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from harness.motion_clips import source_images, write_video
from harness.serve import ServeProcess
from tests.store_checks import samples
from v2v_server.ops.config import ServeConfig
from v2v_server.samples.make import video_samples
from v2v_server.frames.check import check_video
from v2v_server.frames.decode import full_range
from v2v_server.sources.local import LocalSource
from v2v_server.frames.motion import STATIC_MOTION, MotionMeter
from v2v_server.frames.shots import WindowLayout

SPAN = 41  # sequence_length 8: 41-frame windows


@pytest.fixture(scope="module")
def still_then_pan(tmp_path_factory):
    """A clip of a real photograph held still for two windows, then panned 1 px a frame for two."""
    import cv2

    d = tmp_path_factory.mktemp("static")
    img = cv2.resize(source_images()[0][1], (400, 240), interpolation=cv2.INTER_AREA).astype(np.float32)
    frames = [img] * (2 * (SPAN - 1)) + [
        cv2.warpAffine(img, np.float32([[1, 0, -t], [0, 1, 0]]), (400, 240), borderMode=cv2.BORDER_REFLECT)
        for t in range(2 * (SPAN - 1) + 1)]
    write_video(str(d / "still_then_pan.mp4"), np.clip(np.rint(np.stack(frames)), 0, 255).astype(np.uint8))
    return d


def _cfg(static_windows: str) -> ServeConfig:
    return ServeConfig(sequence_length=8, crop_size=64, max_samples_per_video=10, keep_top_fraction=1.0,
                       static_windows=static_windows, shot_cuts="avoid")


def test_the_meter_measures_log_intensity_change_whatever_the_codes():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (64, 96), dtype=np.uint8)
    m = MotionMeter()
    assert m.score(a, full_range) == 0.0 and m.score(a.copy(), full_range) == 0.0  # still
    b = np.roll(a, 3, axis=1)
    moved = m.score(b, full_range)
    lut = np.log(1e-3 + (np.arange(256) / 255.0) ** 2.2)
    assert moved == pytest.approx(np.abs(lut[b[::4, ::4]] - lut[a[::4, ::4]]).mean(), rel=1e-5)
    # the same frames as 10-bit codes, expanded to 16-bit full range, measure the same
    m16 = MotionMeter()
    expand16 = lambda c: (c >> 2).astype(np.uint16) * np.uint16(257)  # noqa: E731
    m16.score(a.astype(np.uint16) << 2, expand16)
    assert m16.score(b.astype(np.uint16) << 2, expand16) == pytest.approx(moved, rel=1e-6)
    assert m.score(None, None) == 0.0 and m.score(a[:32], full_range) == 0.0  # counted, or another size


def test_a_static_window_gives_its_index_to_the_next_as_a_cut_does():
    lay = WindowLayout(5, 10, skip_static=True)
    events = [lay.step(i, static=i == 4) for i in range(13)]
    assert events[4].skips == 0 and events[4].ends is None and events[4].starts == 0
    assert events[8].ends == 0 and events[12].ends == 1 and lay.static == 1 and lay.completed == 2
    keep = WindowLayout(5, 10)
    assert keep.step(0).starts == 0 and [keep.step(i, static=True).ends for i in range(1, 5)][-1] == 0


def test_keep_serves_every_window_and_skip_none_below_the_threshold(still_then_pan):
    src = LocalSource(still_then_pan)
    rel = "still_then_pan.mp4"
    kept = [(k.sample_id(1), m["stats"]["motion"]) for k, _, m in video_samples(_cfg("keep").recipe, src, rel, 0,
                                                                              ("voxels",))]
    assert len(kept) == 4 and [m < STATIC_MOTION for _, m in kept] == [True, True, False, False]
    skip = _cfg("skip")
    got = list(video_samples(skip.recipe, src, rel, 0, ("voxels",)))
    assert [k.sample_id(1) for k, _, _ in got] == [f"{rel}#0", f"{rel}#1"]  # indices 0 .. n - 1, as after cuts
    assert all(m["stats"]["motion"] >= STATIC_MOTION for _, _, m in got)
    assert [m["src_start_frame"] for _, _, m in got] == [2 * (SPAN - 1), 3 * (SPAN - 1)]
    verdict = check_video(skip.recipe.windows, skip.recipe.decode, src, rel)
    assert verdict.windows == 2 and verdict.static == 2
    # the frame cache replays the pass that found them: the same samples
    from tests.cached import cached as cached_corpus

    cached = cached_corpus(still_then_pan, still_then_pan / "cache")
    first = samples(skip, cached, [rel], 0)
    assert samples(skip, cached, [rel], 0) == first == samples(skip, src, [rel], 0)
    assert cached.take_stats()["frame_cache"]["hits"] >= 1
    # keep is the recipe without the setting: the same fingerprint; skip is another recipe
    assert _cfg("keep").recipe.fingerprint() == ServeConfig(sequence_length=8, crop_size=64, max_samples_per_video=10,
                                                            keep_top_fraction=1.0).recipe.fingerprint()
    assert skip.recipe.fingerprint() != _cfg("keep").recipe.fingerprint()


def test_skip_served_by_v2v_serve_is_exactly_once_and_check_names_the_skips(still_then_pan, videos, tmp_path):
    from v2v_client import V2VStreamDataset

    corpus = tmp_path / "c"
    corpus.mkdir()
    import shutil

    shutil.copyfile(still_then_pan / "still_then_pan.mp4", corpus / "still_then_pan.mp4")
    shutil.copyfile(videos / "bikes.mp4", corpus / "bikes.mp4")
    args = ["--sequence-length", "8", "--crop-size", "64", "--keep-top-fraction", "1.0", "--static-windows", "skip",
            "--seed", "5", "--flow-preset", "ultrafast"]
    r = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--check", "--videos", str(corpus), *args],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and "2 static window(s) skipped" in r.stdout, r.stdout + r.stderr
    recipe = ServeConfig(sequence_length=8, crop_size=64, keep_top_fraction=1.0, static_windows="skip").recipe
    want = sorted(f"{v.path}#{k}" for v in (check_video(recipe.windows, recipe.decode, LocalSource(corpus), n)
                                               for n in ("still_then_pan.mp4", "bikes.mp4")) for k in range(v.windows))
    with ServeProcess(["--videos", str(corpus), "--workers", "2", "--batch-size", "2", *args]) as srv:
        got = [(sid, p["stats"]["motion"], b["voxels"][i]) for b in
               V2VStreamDataset(srv.endpoint, 2, outputs=("voxels",), timeout_s=120, raw=True)
               for i, (sid, p) in enumerate(zip(b["sample_ids"], b["params"])) if not b["padding"][i]]
    assert sorted(s for s, _, _ in got) == want and len(got) == len({s for s, _, _ in got})
    assert all(m >= STATIC_MOTION for _, m, _ in got)
    served = ServeConfig(sequence_length=8, crop_size=64, keep_top_fraction=1.0, static_windows="skip", seed=5,
                         flow_preset="ultrafast").recipe
    made = {k.sample_id(): a["voxels"] for n in ("still_then_pan.mp4", "bikes.mp4")
            for k, a, _ in video_samples(served, LocalSource(corpus), n, 0, ("voxels",))}
    assert all(np.array_equal(v.numpy(), made[sid]) for sid, _, v in got)  # the recipe's samples


def test_a_bad_value_is_refused_naming_the_setting():
    with pytest.raises(ValueError, match="static_windows"):
        ServeConfig(static_windows="drop")

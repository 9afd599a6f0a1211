"""Frame scale (the recipe's ``frame_height``): every decoded frame scaled with INTER_AREA on
full-range luma before the kept region and the frame cache, for every reader; entries keyed by
it; a bad value a configuration error naming the key."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from harness.corpus import write_size_change_video, write_video
from tests import sample_hashes
from tests.cached import Cached, cached
from tests.test_frames import write_clip
from v2v_server.samples.recipe import SampleRecipe
from v2v_server.frames.frame_pass import open_frames
from v2v_server.samples.make import video_samples
from v2v_server.frames.check import check_video
from v2v_server.frames.decode import decode_luma, feeding_rows, iter_luma, open_video, scale_frame, scaled_size
from v2v_server.sources.local import LocalSource
from v2v_wire.outputs import OUTPUTS

ROOT = Path(__file__).resolve().parents[1]
CLIPS = ROOT / "v2v_server" / "sample_videos"
#: windows of 9 frames, 32 px crops (frame_height >= 60 keeps 32 rows at the default 0.54)
SMALL = dict(sequence_length=4, num_bins=2, crop_size=32, max_samples_per_video=3)


@pytest.fixture(scope="module")
def corpus(tmp_path_factory) -> Path:
    """bikes.mp4 (8-bit limited range, 596 x 336 display), a 10-bit source (uint16 frames) and a
    phone-style portrait clip (coded 160 x 96, a display matrix turning it to 96 x 160)."""
    d = tmp_path_factory.mktemp("scale")
    shutil.copy(CLIPS / "bikes.mp4", d / "bikes.mp4")
    write_video(d / "ten_bit.mkv", 30, 120, 90, codec="ffv1", pix_fmt="yuv420p10le")
    texture = cv2.resize(np.random.default_rng(3).integers(0, 256, (24, 40), dtype=np.uint8), (160, 96))
    write_clip(d / "portrait.mp4", texture, n=14, rotation=90)
    return d


def _expected(path: Path, height: int, keep: float, n: int) -> list:
    """The first ``n`` frames as the recipe defines them: the decoded full-range frame,
    cv2.resize(INTER_AREA) to ``height`` rows (width rounded to the aspect ratio), then the top
    ``floor(height * keep)`` rows."""
    out = []
    for g in iter_luma(path):
        h, w = g.shape
        s = cv2.resize(g, (int(round(w * height / h)), height), interpolation=cv2.INTER_AREA)
        out.append(s[: int(np.floor(height * keep))].copy())
        if len(out) == n:
            break
    return out


@pytest.mark.parametrize("video,height", [("bikes.mp4", 120), ("bikes.mp4", 500), ("ten_bit.mkv", 64),
                                          ("portrait.mp4", 100)])
def test_scaled_frames_are_inter_area_of_full_range_then_kept_rows(corpus, video, height):
    """The frames the workers, ``--warm-cache`` and the Ray engine read (``open_frames``) are
    INTER_AREA of the full-range frame (down and up, rotated as displayed), then the kept rows;
    uint16 stays uint16."""
    cfg = SampleRecipe(**SMALL, frame_height=height)
    want = _expected(corpus / video, height, cfg.keep_top_fraction, 12)
    with open_frames(LocalSource(corpus), video, cfg.decode, cfg.windows) as fp:
        got = [f.expand(f.codes).copy() for f in (next(fp.frames) for _ in range(12))]
    assert got[0].shape == (cfg.decode.kept_rows(height), want[0].shape[1])
    assert got[0].dtype == want[0].dtype == (np.uint16 if video == "ten_bit.mkv" else np.uint8)
    for a, b in zip(got, want):
        np.testing.assert_array_equal(a, b)
    c, s, _ = open_video(corpus / video)  # the readers outside the sample pass (evaluation, benches)
    first = next(decode_luma(c, s, cfg.decode.kept_rows, height)).copy()
    c.close()
    np.testing.assert_array_equal(first, want[0])


def _whole_then_kept(a: np.ndarray, height: int, kept: int) -> np.ndarray:
    """What the recipe defines: the whole frame resized (INTER_AREA), then its top ``kept`` rows."""
    h, w = scaled_size(a.shape[0], a.shape[1], height)
    return (a if (h, w) == a.shape else cv2.resize(a, (w, h), interpolation=cv2.INTER_AREA))[:kept]


#: (H, W, frame_height, kept): HD to WebVid's height at the default 0.54, integer factors (OpenCV's
#: block-average path), enlargements, a factor near 1 whose cut would scale 1:1 (OpenCV copies
#: those), kept rows that end on a source row boundary (181 x 1080 / 336 is not whole, 168 is).
EDGES = [(1080, 1920, 336, 181), (720, 1280, 336, 181), (2160, 3840, 336, 181), (1080, 1920, 540, 291),
         (1080, 1920, 336, 168), (336, 596, 500, 270), (336, 596, 1000, 540), (285, 133, 284, 112),
         (1149, 165, 1148, 456), (1080, 1920, 1079, 582), (7, 5, 3, 1), (1, 4, 3, 2)]


def test_scaling_only_the_kept_rows_equals_scaling_the_whole_frame():
    """``scale_frame`` resizes only the rows that feed the kept rows, with the whole frame's
    factors: equal, value for value, to resizing the whole frame and cutting, for uint8 and
    uint16, shrinking and enlarging, at the edges above and 600 random sizes."""
    rng = np.random.default_rng(53)
    cases = EDGES + [(int(H), int(W), int(rng.integers(1, 2 * H + 2)), 0)
                     for H, W in zip(rng.integers(1, 1300, 600), rng.integers(1, 300, 600))]
    for i, (H, W, height, kept) in enumerate(cases):
        kept = kept or max(1, int(height * rng.random()))
        dtype = np.uint8 if i % 2 else np.uint16
        a = rng.integers(0, np.iinfo(dtype).max + 1, (H, W), dtype=dtype)
        want = _whole_then_kept(a, height, kept)
        got = scale_frame(a, height, kept)
        assert got.dtype == dtype and got.shape == want.shape, (H, W, height, kept)
        np.testing.assert_array_equal(got, want, err_msg=f"{H}x{W} -> {height} rows, {kept} kept")
    a = rng.integers(0, 256, (1080, 1920), dtype=np.uint8)  # rows given as a function of the scaled height
    np.testing.assert_array_equal(scale_frame(a, 336, lambda h: h // 2), _whole_then_kept(a, 336, 168))
    np.testing.assert_array_equal(scale_frame(a, 336), _whole_then_kept(a, 336, 336))


@pytest.mark.parametrize("H,W,height,kept", [e for e in EDGES if e[2] < e[0] and e[3] > 1])
def test_the_kept_rows_read_source_rows_up_to_their_area_only(H, W, height, kept):
    """Kept row y averages the source rows its area [y s, (y + 1) s) overlaps, s = H / height:
    a source row below ceil(kept s) changes no kept row, the last one that area reaches
    changes the last kept row, and ``feeding_rows`` covers it."""
    rng = np.random.default_rng(7)
    a = rng.integers(0, 200, (H, W), dtype=np.uint8)
    base = _whole_then_kept(a, height, kept)
    last = -(-kept * H // height) - 1  # the last source row kept row kept - 1 overlaps
    assert last < feeding_rows(H, height, kept) <= H
    below = a.copy()
    below[last + 1:] = 255
    np.testing.assert_array_equal(_whole_then_kept(below, height, kept), base)
    edge = a.copy()
    edge[last] = 255
    changed = np.flatnonzero((_whole_then_kept(edge, height, kept) != base).any(axis=1))
    assert changed.max() == kept - 1, changed


def test_frame_height_zero_is_the_decoded_frame(corpus):
    cfg = SampleRecipe(**SMALL)
    assert cfg.frame_height == 0
    plain = [g[: cfg.decode.kept_rows(g.shape[0])].copy() for _, g in zip(range(5), iter_luma(corpus / "bikes.mp4"))]
    with open_frames(LocalSource(corpus), "bikes.mp4", cfg.decode, cfg.windows) as fp:
        got = [f.expand(f.codes).copy() for f in (next(fp.frames) for _ in range(5))]
    for a, b in zip(got, plain):
        np.testing.assert_array_equal(a, b)
    assert SampleRecipe(**SMALL, frame_height=0).fingerprint() == cfg.fingerprint() != \
        SampleRecipe(**SMALL, frame_height=120).fingerprint()


@pytest.mark.parametrize("fmt", ["raw", "zstd"])
def test_cached_samples_equal_decoded_with_scaling(corpus, tmp_path, fmt):
    """Every output, cold and warm, equal to the decoded samples under a frame_height."""
    src = cached(corpus, tmp_path, fmt=fmt)
    for video, height in (("bikes.mp4", 100), ("ten_bit.mkv", 72)):
        cfg = SampleRecipe(**SMALL, frame_height=height)
        decoded = _samples(cfg, corpus, video)
        assert decoded and decoded != _samples(SampleRecipe(**SMALL), corpus, video)
        assert _samples(cfg, src, video) == decoded, (video, "cold")
        assert _samples(cfg, src, video) == decoded, (video, "warm")
    stats = src.take_stats()["frame_cache"]
    assert stats["stored"] == 2 and stats["hits"] == 2, stats


def test_entry_of_one_frame_height_is_not_hit_at_another(corpus, tmp_path):
    src = cached(corpus, tmp_path)
    for height in (100, 120, 0, 100):
        cfg = SampleRecipe(**SMALL, frame_height=height)
        assert _samples(cfg, src, "bikes.mp4") == _samples(cfg, corpus, "bikes.mp4"), height
    stats = src.take_stats()["frame_cache"]
    assert stats["stored"] == 3 and stats["hits"] == 1 and stats["misses"]["absent"] == 3, stats
    assert len(list((tmp_path / "frames").glob("*.v2vf"))) == 3


def test_check_judges_frame_sizes_as_the_workers_cut_them(tmp_path):
    """A stream whose frame size changes: under a frame_height both sizes scale to one height,
    so only a change of aspect ratio fails a window, in ``--check`` as in the workers. Windows
    at k x stride (``shot_cuts: off``): the shot detector sees the change of aspect as a cut,
    and under ``avoid`` no window would hold it."""
    d = tmp_path / "c"
    d.mkdir()
    write_size_change_video(d / "same_aspect.mpg", 14, 20, size1=(96, 80), size2=(144, 120))
    write_size_change_video(d / "other_aspect.mpg", 14, 20, size1=(96, 80), size2=(80, 80))
    cfg = SampleRecipe(sequence_length=4, num_bins=2, crop_size=16, max_samples_per_video=3, keep_top_fraction=1.0,
                      frame_height=40, shot_cuts="off")
    for name, fails in (("same_aspect.mpg", False), ("other_aspect.mpg", True)):
        v = check_video(cfg.windows, cfg.decode, LocalSource(d), name)
        run = video_samples(cfg, LocalSource(d), name, 0, ("voxels",))
        served = list(run)
        assert bool(v.failed_windows) == fails == bool(run.record().failed), (name, v, run.record())
        assert v.windows == len(served), (name, v)


@pytest.mark.parametrize("value,words", [(-1, "frame_height must be an integer >= 0"),
                                         ("336", "frame_height must be an integer"),
                                         (5000, "frame_height must be <= 4320"),
                                         (100, "frame_height 100 keeps 54 rows")])
def test_bad_frame_height_names_the_key(value, words):
    with pytest.raises(ValueError, match=words):
        SampleRecipe(frame_height=value)


def test_v2v_serve_bad_frame_height_is_a_configuration_error():
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--frame-height", "200", "--check"],
                       capture_output=True, text=True, cwd=ROOT, env=env, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    line = next(x for x in r.stderr.splitlines() if x.startswith("v2v-serve: configuration error: "))
    assert "frame_height 200 keeps 108 rows" in line and "crop_size 128" in line and ">= 238" in line, line


def _samples(cfg, root, video) -> dict:
    """{sample id: digest} of one video of ``root`` (a folder or a ``Cached`` corpus)."""
    source, caches = (root.source, root.caches) if isinstance(root, Cached) else (LocalSource(root), None)
    return {key.sample_id(cfg.crops_per_window): sample_hashes._digest(arrays, sample_hashes._canonical(meta))
            for key, arrays, meta in video_samples(cfg, source, video, 0, OUTPUTS, flow_grid=True, caches=caches)}


def test_served_samples_under_frame_height_are_the_recipes(corpus):
    """``v2v-serve --frame-height`` (two worker processes, the recipe sent to each): every sample
    that of ``video_samples`` under the same recipe, and not the unscaled one."""
    from harness.serve import served_samples

    flags = ["--sequence-length", "4", "--num-bins", "2", "--crop-size", "32", "--max-samples-per-video", "3",
             "--frame-height", "100", "--seed", "5"]
    cfg = SampleRecipe(**SMALL, frame_height=100, seed=5)
    want = {key.sample_id(1): arrays for key, arrays, _ in video_samples(cfg, LocalSource(corpus), "bikes.mp4", 0, ("voxels", "frames"))}
    got = dict(served_samples(["--videos", str(corpus), "--workers", "2", *flags, "--batch-size", "2",
                               "--outputs", "voxels,frames"]))
    assert set(want) <= set(got) and len(want) == 3
    for sid, arrays in want.items():
        for k in arrays:
            np.testing.assert_array_equal(got[sid][k].reshape(arrays[k].shape), arrays[k], err_msg=f"{sid} {k}")
    plain = next(video_samples(SampleRecipe(**SMALL, seed=5), LocalSource(corpus), "bikes.mp4", 0, ("frames",)))
    assert not np.array_equal(plain[1]["frames"], want[plain[0].sample_id(1)]["frames"])

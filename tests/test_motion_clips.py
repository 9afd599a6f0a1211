"""harness/motion_clips.py: camera-motion clips over still photographs (demo training variety)."""
import numpy as np
import pytest

from harness import motion_clips as mc
from v2v_server.samples.recipe import SampleRecipe
from v2v_server.frames.check import check_video
from v2v_server.sources.local import LocalSource
from v2v_server.frames.decode import decode_luma, open_video


def test_camera_path_is_smooth_and_starts_at_rest():
    p = mc.camera_path(250, np.random.default_rng(0))
    assert p.shape == (250, 4) and np.all(p[0] == 0)
    step = np.abs(np.diff(p[:, :2], axis=0))
    assert step.max() <= np.pi / 3 * 3.0   # px per frame, the documented bound at max_speed_px=3
    assert np.ptp(p[:, :2]) > 5.0      # but it does move
    assert np.array_equal(p, mc.camera_path(250, np.random.default_rng(0)))


def test_render_moves_real_content_and_is_seeded():
    rng = np.random.default_rng(1)
    img = (rng.random((120, 160)) * 255).astype(np.uint8)
    a = mc.render_clip(img, (32, 48), 20, np.random.default_rng(5))
    b = mc.render_clip(img, (32, 48), 20, np.random.default_rng(5))
    assert a.shape == (20, 32, 48) and a.dtype == np.uint8 and np.array_equal(a, b)
    diffs = [np.abs(a[i + 1].astype(int) - a[i]).mean() for i in range(19)]
    assert np.mean(diffs) > 1.0        # consecutive frames differ: events will fire
    assert a.std() > 20                # the texture is there, not a flat border


def test_clips_are_videos_the_server_accepts(tmp_path):
    paths = mc.make_clips(str(tmp_path), frames=12, size=(64, 96), seed=0)
    assert len(paths) >= 10            # the photographs scikit-image ships (+ matplotlib's)
    names = {p.rsplit("/", 1)[-1] for p in paths}
    assert "motion_camera.mp4" in names and "motion_astronaut.mp4" in names
    recipe = SampleRecipe(sequence_length=2, num_bins=5, crop_size=64)
    verdict = check_video(recipe.windows, recipe.decode, LocalSource(str(tmp_path)), "motion_astronaut.mp4")
    assert verdict.usable and verdict.frames == 12, verdict
    c, s, _ = open_video(tmp_path / "motion_astronaut.mp4")
    frames = np.stack([f.copy() for f in decode_luma(c, s)])
    assert frames.shape == (12, 64, 96)
    ref = mc.render_clip(dict(mc.source_images())["astronaut"], (64, 96), 12, np.random.default_rng([0, 0]))
    # H.264 at crf 18 keeps the content (the luma plane may be in video range, 16-235: compare
    # by correlation, not by value)
    assert np.corrcoef(frames.ravel().astype(float), ref.ravel().astype(float))[0, 1] > 0.97


def test_odd_frame_size_is_refused(tmp_path):
    with pytest.raises(ValueError, match="even"):
        mc.write_video(str(tmp_path / "x.mp4"), np.zeros((3, 31, 48), np.uint8))

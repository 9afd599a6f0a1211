"""Real encodings end to end: VP9 in WebM, AV1 in Matroska, HEVC in QuickTime, 10-bit HEVC and
VP9, and a variable-frame-rate MP4, made here with PyAV from real frames (bbb_camera_596x336.mp4, one shot), judged by
``v2v-serve --check`` and served by ``v2v-serve`` with the samples the recipe defines; a file
whose codec no decoder knows gets a verdict that says so."""
from __future__ import annotations

import os
import subprocess
import sys
from fractions import Fraction
from pathlib import Path

import av
import cv2
import numpy as np
import pytest

from v2v_server.samples.recipe import SampleRecipe
from v2v_server.frames.frame_pass import open_frames
from v2v_server.samples.make import video_samples
from v2v_server.sources.local import LocalSource
from v2v_server.luma import to_uint8
from v2v_server.frames.decode import open_video

ROOT = Path(__file__).resolve().parents[1]
CLIP = ROOT / "v2v_server" / "sample_videos" / "bbb_camera_596x336.mp4"
W, H, N = 160, 120, 48  # two windows of the recipe below (21 frames each, one shared)
#: windows of 4 x 5 bins (21 frames), 64 px crops (the kept 54 % of 120 rows is 64)
RECIPE = dict(sequence_length=4, crop_size=64, max_samples_per_video=2, seed=11, flow_preset="ultrafast")
FLAGS = ["--sequence-length", "4", "--crop-size", "64", "--max-samples-per-video", "2", "--seed", "11",
         "--flow-preset", "ultrafast"]
#: file -> (encoder, pixel format, what --check names: codec and pixel format)
ENCODINGS = {
    "vp9.webm": ("libvpx-vp9", "yuv420p", "vp9 yuv420p"),
    "vp9_10bit.webm": ("libvpx-vp9", "yuv420p10le", "vp9 yuv420p10le"),
    "av1.mkv": ("libsvtav1", "yuv420p", " yuv420p"),  # the decoder's name: libdav1d or av1
    "hevc.mov": ("libx265", "yuv420p", "hevc yuv420p"),
    "hevc_10bit.mkv": ("libx265", "yuv420p10le", "hevc yuv420p10le"),
    "vfr.mp4": ("libx264", "yuv420p", "h264 yuv420p"),
}
#: file -> why it could not be made here (filled by the ``corpus`` fixture)
MISSING: dict = {}
#: presentation-time steps of the variable-frame-rate file, ms (50, 25 and 12.5 fps)
VFR_STEPS = (20, 40, 80)


def _real_frames() -> list:
    """The first N frames of the one-shot bundled clip (596 x 336), centre-cut to 4:3 and resized to W x H, RGB."""
    out = []
    with av.open(str(CLIP)) as c:
        for fr in c.decode(video=0):
            rgb = fr.to_ndarray(format="rgb24")
            x = (rgb.shape[1] - rgb.shape[0] * 4 // 3) // 2
            out.append(cv2.resize(rgb[:, x:x + rgb.shape[0] * 4 // 3], (W, H), interpolation=cv2.INTER_AREA))
            if len(out) == N:
                break
    return out


def _encode(path: Path, codec: str, pix_fmt: str, frames: list, vfr: bool = False) -> None:
    with av.open(str(path), "w") as c:
        s = c.add_stream(codec, rate=25)
        s.width, s.height, s.pix_fmt = W, H, pix_fmt
        if codec == "libsvtav1":
            s.options = {"preset": "12"}
        if codec == "libx265":
            s.options = {"x265-params": "log-level=error"}
        tb, t = (Fraction(1, 1000), 0) if vfr else (Fraction(1, 25), 0)
        s.codec_context.time_base = tb
        for i, rgb in enumerate(frames):
            f = av.VideoFrame.from_ndarray(rgb, format="rgb24")
            f.pts, f.time_base = t, tb
            t += VFR_STEPS[i % 3] if vfr else 1
            for p in s.encode(f):
                c.mux(p)
        for p in s.encode():
            c.mux(p)


@pytest.fixture(scope="module")
def corpus(tmp_path_factory) -> Path:
    """Every encoding whose encoder PyAV's FFmpeg has, and ``unknown_codec.webm``: the VP9 file
    with its Matroska codec id changed to one no decoder knows."""
    d = tmp_path_factory.mktemp("encodings")
    frames = _real_frames()
    for name, (codec, pix_fmt, _) in ENCODINGS.items():
        if codec not in av.codecs_available:
            MISSING[name] = f"PyAV's FFmpeg has no {codec} encoder"
            continue
        try:
            _encode(d / name, codec, pix_fmt, frames, vfr=name.startswith("vfr"))
        except av.error.FFmpegError as e:  # e.g. a libvpx built without high bit depth refuses yuv420p10le
            MISSING[name] = f"PyAV's {codec} cannot encode {pix_fmt}: {e}"
            (d / name).unlink(missing_ok=True)
    if (d / "vp9.webm").exists():
        data = (d / "vp9.webm").read_bytes()
        assert data.count(b"V_VP9") == 1
        (d / "unknown_codec.webm").write_bytes(data.replace(b"V_VP9", b"V_XY9"))
    return d


def _need(corpus: Path, name: str) -> Path:
    if name in MISSING:
        pytest.skip(f"{name} not made: {MISSING[name]}")
    return corpus / name


@pytest.fixture(scope="module")
def check_lines(corpus) -> dict:
    """``v2v-serve --check`` of the folder: file -> its line of the report."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--videos", str(corpus), *FLAGS, "--check"],
                       capture_output=True, text=True, cwd=ROOT, env=env, timeout=120)
    return {line.split()[0]: line for line in (r.stdout + r.stderr).splitlines() if line.split()}


@pytest.mark.parametrize("name", list(ENCODINGS))
def test_check_judges_each_encoding(corpus, check_lines, name):
    """``v2v-serve --check`` decodes each file (up to the last window's frame): both windows
    usable, codec and pixel format named; the variable frame rate reported with its spread."""
    _need(corpus, name)
    line = check_lines[name]
    assert "2 window(s)" in line and f"41+ frames, {W}x{H}" in line and ENCODINGS[name][2] in line, line
    if name == "vfr.mp4":
        assert "variable frame rate: frame intervals 20-80 ms, taken as if evenly spaced at the average" in line, line
    else:
        assert "variable" not in line, line


def test_unknown_codec_gets_a_verdict(corpus, check_lines):
    if "vp9.webm" in MISSING:
        pytest.skip("the file with an unknown codec id is made from vp9.webm: " + MISSING["vp9.webm"])
    line = check_lines["unknown_codec.webm"]
    assert "unusable" in line and "unsupported codec" in line and "no decoder" in line, line


def test_served_samples_are_the_recipes_for_every_encoding(corpus):
    """One ``v2v-serve`` (two workers) over the whole folder, the unknown codec included: every
    sample of every decodable file delivered once, its voxels and frames those ``video_samples``
    makes from the file in this process; the unknown codec skipped, the service going on."""
    from harness.serve import served_samples

    cfg = SampleRecipe(**RECIPE)
    want = {}
    for name in sorted(ENCODINGS):
        if (corpus / name).exists():
            for key, arrays, _ in video_samples(cfg, LocalSource(corpus), name, 0, ("voxels", "frames")):
                want[key.sample_id(1)] = arrays
    assert len(want) == 2 * sum((corpus / n).exists() for n in ENCODINGS)
    got = {}
    for sid, arrays in served_samples(["--videos", str(corpus), "--workers", "2", *FLAGS, "--batch-size", "2",
                                       "--outputs", "voxels,frames"]):
        assert sid not in got, f"{sid} delivered twice"
        got[sid] = arrays
    assert sorted(got) == sorted(want)
    for sid, arrays in want.items():
        for k in ("voxels", "frames"):
            np.testing.assert_array_equal(got[sid][k].reshape(arrays[k].shape), arrays[k], err_msg=f"{sid} {k}")


@pytest.mark.parametrize("ten,eight", [("hevc_10bit.mkv", "hevc.mov"), ("vp9_10bit.webm", "vp9.webm")])
def test_ten_bit_frames_reach_the_core_as_uint16(corpus, ten, eight):
    """A 10-bit file's frames are uint16 at full range (0..65535), the same picture as the 8-bit
    encoding of the same frames (rounded to 8 bits, within what two lossy encodings differ by)."""
    _need(corpus, ten), _need(corpus, eight)
    cfg = SampleRecipe(**RECIPE)
    frames = {}
    for name in (ten, eight):
        with open_frames(LocalSource(corpus), name, cfg.decode, cfg.windows) as fp:
            frames[name] = [f.expand(f.codes).copy() for f in fp.frames]
    assert frames[ten][0].dtype == np.uint16 and frames[eight][0].dtype == np.uint8
    assert len(frames[ten]) == len(frames[eight]) >= 2 * 20 + 1  # both windows (with shot_cuts avoid, every frame)
    assert int(max(f.max() for f in frames[ten])) > 255 * 256  # full range, not 10-bit codes
    diff = np.mean([np.abs(to_uint8(a).astype(int) - b).mean() for a, b in zip(frames[ten], frames[eight])])
    assert diff < 4.0, diff


def test_variable_frame_rate_frames_are_taken_in_order(corpus):
    """The VFR file's presentation times step 20, 40 and 80 ms; the pass reads every frame once,
    in presentation order, by index (as if evenly spaced), and a sample records the stream's
    average rate as its ``video_fps``."""
    path = _need(corpus, "vfr.mp4")
    c, s, info = open_video(path)
    times = [float(f.pts * f.time_base) for f in c.decode(s)]
    c.close()
    steps = np.round(np.diff(times) * 1000).astype(int)
    assert sorted(set(steps.tolist())) == list(VFR_STEPS) and len(times) == N
    assert info.fps == pytest.approx(float(s.average_rate)) and info.fps == pytest.approx((N - 1) / times[-1], rel=0.1)
    cfg = SampleRecipe(**RECIPE)
    with open_frames(LocalSource(corpus), "vfr.mp4", cfg.decode, cfg.windows) as fp:
        read = [f.expand(f.codes).copy() for f in fp.frames]
    c, s, _ = open_video(path)
    order = [f.to_ndarray(format="gray")[: len(read[0])] for f in c.decode(s)][: len(read)]
    c.close()
    assert len(read) >= 2 * 20 + 1  # both windows (with shot_cuts avoid, every frame)
    # frame i of the pass is the i-th presented frame (swscale's grey is also full range: near equal)
    assert all(np.abs(a.astype(int) - b).mean() < 2 for a, b in zip(read, order))
    metas = [m for _, _, m in video_samples(cfg, LocalSource(corpus), "vfr.mp4", 0, ("voxels",))]
    assert [m["src_start_frame"] for m in metas] == [0, 20] and all(m["video_fps"] == info.fps for m in metas)

"""Frames as the paper's loader sees them: full-range luma (limited-range video expanded),
display rotation honoured, the real video stream chosen over a cover image. Clips are
written here with PyAV; the end-to-end test serves them through a real v2v-serve on
127.0.0.1 and reads them with V2VStreamDataset."""
from __future__ import annotations

from types import SimpleNamespace

import av
import numpy as np
import pytest
from v2v_server.samples.recipe import SampleRecipe

from v2v_server.luma import to_uint8
from v2v_server.frames.decode import choose_video_stream, is_full_range, iter_luma, open_video, range_table

S = 64  # clip side, pixels
LEVELS = (0, 255, 128)


def pattern(h: int = S, w: int = S, block: int = 8) -> np.ndarray:
    """uint8 (h, w): blocks of 0 / 255 / 128 arranged so that any 32 x 32 window holds
    complete blocks of all three levels."""
    by, bx = np.mgrid[0:h, 0:w] // block
    return np.asarray(LEVELS, np.uint8)[(bx + 2 * by) % 3]


def write_clip(path, grey: np.ndarray, n: int = 12, pix_fmt: str = "yuv420p", codec: str = "libx264",
               rotation=None, cover_first: bool = False, options=None) -> None:
    """Write ``n`` copies of the uint8 (H, W) image ``grey``. ``rotation``: display matrix,
    degrees counter-clockwise; ``cover_first``: a one-frame MJPEG stream before the video."""
    rgb = np.repeat(grey[..., None], 3, axis=2)
    with av.open(str(path), "w") as c:
        if cover_first:
            cov = c.add_stream("mjpeg", rate=1)
            cov.width, cov.height, cov.pix_fmt = 32, 32, "yuvj420p"
        s = c.add_stream(codec, rate=25, options=options or {})
        s.width, s.height, s.pix_fmt = grey.shape[1], grey.shape[0], pix_fmt
        if rotation is not None:
            s.set_display_rotation(rotation)
        if cover_first:
            img = av.VideoFrame.from_ndarray(np.full((32, 32, 3), 99, np.uint8), format="rgb24")
            for p in list(cov.encode(img.reformat(format="yuvj420p"))) + list(cov.encode()):
                c.mux(p)
        for _ in range(n):
            for p in s.encode(av.VideoFrame.from_ndarray(rgb, format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)


def levels_ok(frames: np.ndarray, top: int = 255, tol: float = 3.0) -> None:
    """Black reaches 0, white reaches full scale, mid-grey stays mid-grey (within codec error)."""
    f = frames.astype(np.float64) / top * 255
    assert np.percentile(f, 1) <= tol, np.percentile(f, 1)
    assert np.percentile(f, 99) >= 255 - tol, np.percentile(f, 99)
    mid = f[(f > 64) & (f < 192)]
    assert mid.size > 0.1 * f.size and abs(np.median(mid) - 128) <= tol, np.median(mid)


def test_range_tables():
    t8 = range_table(8, full_range=False)
    assert t8.dtype == np.uint8 and (t8[16], t8[126], t8[235]) == (0, 128, 255)
    assert t8[:17].max() == 0 and t8[235:].min() == 255  # footroom / headroom clip
    assert range_table(8, full_range=True) is None  # identity: no copy
    t10 = range_table(10, full_range=False)
    assert t10.dtype == np.uint16 and (t10[64], t10[940], t10[1023]) == (0, 65535, 65535)
    assert range_table(10, full_range=True)[1023] == 65535
    assert is_full_range("yuvj420p", 0) and is_full_range("yuv420p", 2) and not is_full_range("yuv420p", 0)
    assert is_full_range("gray", 0) and not is_full_range("gray", 1)
    assert np.array_equal(to_uint8(np.array([0, 128, 129, 385, 65535, 257 * 100], np.uint16)), [0, 0, 1, 1, 255, 100])
    with pytest.raises(ValueError, match="uint8 or uint16, got float32"):
        to_uint8(np.zeros(3, np.float32))
    with pytest.raises(ValueError, match="bit depth"):
        range_table(7, False)


@pytest.mark.parametrize("pix_fmt,codec,options", [
    ("yuv420p", "libx264", {}),              # limited range, the usual H.264
    ("yuvj420p", "libx264", {}),             # full range: must not be expanded twice
    ("yuv420p10le", "libx264", {}),          # 10-bit limited range -> uint16 0..65535
])
def test_decoded_luma_is_full_range(tmp_path, pix_fmt, codec, options):
    p = tmp_path / f"clip_{pix_fmt}.mkv"
    write_clip(p, pattern(), n=3, pix_fmt=pix_fmt, codec=codec, options=options)
    frames = np.stack([f.copy() for f in iter_luma(p)])
    assert frames.shape == (3, S, S)
    deep = pix_fmt.endswith("10le")
    assert frames.dtype == (np.uint16 if deep else np.uint8)
    levels_ok(frames, top=65535 if deep else 255)


def test_rotated_clip_is_decoded_as_displayed(tmp_path):
    ramp = np.tile(np.linspace(0, 255, S).astype(np.uint8), (S // 2, 1))  # (32, 64), brighter to the right
    write_clip(tmp_path / "plain.mp4", ramp, n=2)
    write_clip(tmp_path / "rot.mp4", ramp, n=2, rotation=90)
    plain = next(iter_luma(tmp_path / "plain.mp4")).copy()
    rot = next(iter_luma(tmp_path / "rot.mp4")).copy()
    assert plain.shape == (32, 64) and rot.shape == (64, 32)
    # 90 degrees counter-clockwise: the right edge comes to the top
    assert np.array_equal(rot, np.rot90(plain))
    assert rot[0].mean() > 240 and rot[-1].mean() < 15
    rows = next(iter_luma(tmp_path / "rot.mp4", rows=lambda h: h // 2)).copy()
    assert rows.shape == (32, 32)  # rows are cut from the displayed frame


def test_cover_image_stream_first_is_not_chosen(tmp_path):
    p = tmp_path / "cover.mkv"
    write_clip(p, pattern(), n=12, cover_first=True)
    c, s, info = open_video(p)
    c.close()
    assert info.stream_index == 1 and info.codec == "h264"
    assert sum(1 for _ in iter_luma(p)) == 12
    # an attached picture listed first (as demuxers list cover art of some containers) is never chosen
    attached = int(av.stream.Disposition.attached_pic)
    mk = lambda i, frames, disp: SimpleNamespace(index=i, frames=frames, disposition=disp, codec_context=object(),  # noqa: E731
                                                 average_rate=25, guessed_rate=25, duration=None, time_base=None,
                                                 metadata={})
    streams = [mk(0, 1000, attached), mk(1, 300, 0), mk(2, 200, int(av.stream.Disposition.default))]
    assert choose_video_stream(streams).index == 1  # most frames among real video streams
    assert choose_video_stream([mk(0, 0, 0), mk(1, 0, int(av.stream.Disposition.default))]).index == 1
    assert choose_video_stream([mk(0, 1, attached)]) is None


def test_served_end_to_end_full_range_rotated_and_cover(tmp_path):
    """limited.mp4 (0/128/255 blocks, H.264 yuv420p limited range), rot.mp4 (a horizontal ramp
    with a 90-degree display matrix) and cover.mkv (a one-frame MJPEG stream before the video)
    served by v2v-serve and read through V2VStreamDataset."""
    from v2v_client import V2VStreamDataset
    from harness.serve import ServeProcess

    corpus = tmp_path / "corpus"
    corpus.mkdir()
    write_clip(corpus / "limited.mp4", pattern())
    ramp = np.tile(np.linspace(0, 255, S).astype(np.uint8), (S // 2, 1))
    write_clip(corpus / "rot.mp4", ramp, rotation=90)
    write_clip(corpus / "cover.mkv", pattern(), cover_first=True)
    cfg = tmp_path / "serve.yaml"
    cfg.write_text("hflip_prob: 0.0\npause_enabled: false\nkeep_top_fraction: 1.0\n")
    args = ["--videos", str(corpus), "--config", str(cfg), "--workers", "1", "--sequence-length", "2",
            "--num-bins", "2", "--crop-size", "32", "--max-samples-per-video", "1", "--batch-size", "1",
            "--outputs", "voxels,frames", "--seed", "5"]
    got = {}
    with ServeProcess(args) as srv:
        for b in V2VStreamDataset(srv.endpoint, 1, outputs=("voxels", "frames"), timeout_s=120, raw=True):
            assert not b["padding"][0] and b["sample_ids"][0] not in got
            got[b["sample_ids"][0]] = b["frames"][0, :, 0].numpy()
    assert sorted(got) == ["cover.mkv#0", "limited.mp4#0", "rot.mp4#0"]
    assert got["limited.mp4#0"].dtype == np.uint8
    levels_ok(got["limited.mp4#0"])
    levels_ok(got["cover.mkv#0"])
    rot = got["rot.mp4#0"].astype(np.float64)  # (L + 1, 32, 32): rows uniform, brighter at the top
    assert rot.std(axis=2).max() < 3 and rot.std(axis=1).min() > 20
    assert np.all(np.diff(rot.mean(axis=2), axis=1) < 0)


def test_ten_bit_clip_feeds_the_core_at_full_precision(tmp_path, monkeypatch):
    """A 10-bit clip reaches the V2V core as uint16 0..65535; its frames output is 8-bit full range."""
    from v2v_server.samples import make as samples
    from v2v_server.sources.local import LocalSource

    write_clip(tmp_path / "deep.mkv", pattern(), n=6, pix_fmt="yuv420p10le")
    seen = []
    real = samples.simulate_voxels
    monkeypatch.setattr(samples, "simulate_voxels", lambda frames, *a, **k: (seen.append(frames.copy()), real(frames, *a, **k))[1])
    cfg = SampleRecipe(sequence_length=2, num_bins=2, crop_size=32, keep_top_fraction=1.0, pause_enabled=False)
    out = list(samples.video_samples(cfg, LocalSource(tmp_path), "deep.mkv", 0, ("voxels", "frames")))
    assert len(out) == 1 and seen[0].dtype == np.uint16
    levels_ok(seen[0], top=65535)
    assert out[0][1]["frames"].dtype == np.uint8
    levels_ok(out[0][1]["frames"])

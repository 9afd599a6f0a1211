"""trainer/recordings.py on the real recordings shipped in tests/data/events: pinned facts,
chunked = whole, bad recordings, voxel binning."""
from __future__ import annotations

import logging
import re
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from harness import data
from trainer.event_grids import count_edges, voxel_grids, window_edges
from trainer.recordings import EVENT_DTYPE, RecordingError, open_recording, read_all

DAVIS, EVT2, EVT3 = (p.name for p in (data.DAVIS346, data.EVT2, data.EVT3))


def shared(name: str) -> Path:
    """A recording of ``tests/data/events`` (shipped with the repository)."""
    return data.RECORDINGS / name


# read once with this reader, then pinned: (events, ON events, first t us, last t us, W, H, frames)
FACTS = {
    DAVIS: (78830, 41257, 1589163147368868, 1589163149728813, 346, 260, 59),
    EVT2: (521252, 185861, 913716224, 913812095, 640, 480, 0),
    EVT3: (1218618, 553295, 11200224, 21968221, 1280, 720, 0),
}


@pytest.mark.parametrize("name", list(FACTS))
def test_shared_recording_facts(name):
    rec = open_recording(shared(name))
    n, n_on, t0, t1, w, h, nf = FACTS[name]
    assert (rec.width, rec.height) == (w, h)
    total, on, first, last, prev = 0, 0, None, None, -1
    for ev in rec.chunks():
        assert ev.dtype == EVENT_DTYPE and 0 < ev.size < n  # chunks, never the whole recording
        assert ev["t"][0] >= prev and np.all(np.diff(ev["t"]) >= 0)
        first = int(ev["t"][0]) if first is None else first
        last, prev = int(ev["t"][-1]), int(ev["t"][-1])
        total += ev.size
        on += int((ev["p"] == 1).sum())
        assert set(np.unique(ev["p"])) <= {-1, 1}
    assert (total, on, first, last) == (n, n_on, t0, t1)
    assert rec.dropped_backward == 0 and not rec.truncated
    fr = rec.frames()
    assert (0 if fr is None else len(fr.t_us)) == nf
    if nf:  # DAVIS346 APS at 25 Hz, 500 us exposure; the timestamp is the exposure's middle
        assert fr.images.shape == (nf, h, w) and fr.images.dtype == np.uint8
        assert np.all(np.abs(np.diff(fr.t_us) - 40000) <= 1)
        assert np.all(fr.exposure_us[:, 1] - fr.exposure_us[:, 0] == 500)
        assert np.array_equal(fr.t_us, fr.exposure_us.mean(1).astype(np.int64))
        assert fr.t_us[0] == 1589163147365215 and rec.imu() is not None and len(rec.imu()) > 0


def test_evt2_size_inferred_from_header_or_given(caplog):
    p = shared(EVT2)
    with caplog.at_level(logging.WARNING, logger="trainer.recordings"):
        rec = open_recording(p)
    assert (rec.width, rec.height) == (640, 480) and "gen3" in rec.size_source
    assert "carries no geometry" in caplog.text
    given = open_recording(p, size=(640, 480))
    assert given.size_source == "argument" and (given.width, given.height) == (640, 480)


@pytest.mark.parametrize("name", [DAVIS, EVT2, EVT3])
def test_chunked_reading_equals_reading_whole(name):
    """The chunks concatenated equal faery's whole-file array, and a [start, end) cut equals
    the same slice of it."""
    import faery

    p = shared(name)
    rec = open_recording(p)
    whole = faery.events_stream_from_file(p, dimensions_fallback=(rec.width, rec.height)).to_array()
    got = read_all(rec)
    assert np.array_equal(got["t"], whole["t"].astype(np.int64))
    assert np.array_equal(got["x"], whole["x"]) and np.array_equal(got["y"], whole["y"])
    assert np.array_equal(got["p"] == 1, whole["on"])
    a, b = int(got["t"][len(got) // 3]), int(got["t"][2 * len(got) // 3])
    cut = read_all(rec, a, b)
    assert np.array_equal(cut, got[(got["t"] >= a) & (got["t"] < b)])


@pytest.mark.parametrize("name, version", [("x.es", None), ("x.dat", None), ("x.csv", None), ("x.aedat4", None),
                                           ("x_evt2.raw", "evt2"), ("x_evt3.raw", "evt3")])
def test_formats_written_by_faery_read_back(tmp_path, name, version):
    """Real Gen3 events written by faery's encoders in each format come back unchanged (t from 0:
    the writers start at t0 = 0; faery 0.7.1 writes no EVT 2.1, so that decoder is untested here)."""
    import faery

    ev = read_all(open_recording(shared(EVT2)))[:50000]
    ev["t"] -= ev["t"][0]
    arr = np.zeros(len(ev), faery.EVENTS_DTYPE)
    arr["t"], arr["x"], arr["y"], arr["on"] = ev["t"], ev["x"], ev["y"], ev["p"] > 0
    p = tmp_path / name
    faery.events_stream_from_array(arr, dimensions=(640, 480)).to_file(p, version=version)
    rec = open_recording(p, size=(640, 480) if name.endswith(".csv") else None)
    assert (rec.width, rec.height) == (640, 480)
    assert rec.size_source == ("argument" if name.endswith(".csv") else "header")
    assert np.array_equal(read_all(rec), ev) and rec.frames() is None


def _write_ecd(root: Path, ev: np.ndarray, frames=None):
    """TEST FIXTURE: the IJRR/ECD text layout (t in seconds) from real events; frames as
    ``(t_us, uint8 image)`` pairs into images/ and images.txt."""
    import cv2

    root.mkdir(parents=True, exist_ok=True)
    with open(root / "events.txt", "w") as f:
        for e in ev:
            f.write(f"{e['t'] / 1e6:.6f} {e['x']} {e['y']} {1 if e['p'] > 0 else 0}\n")
    if frames:
        (root / "images").mkdir(exist_ok=True)
        lines = []
        for i, (t, img) in enumerate(frames):
            cv2.imwrite(str(root / "images" / f"frame_{i:08d}.png"), img)
            lines.append(f"{t / 1e6:.6f} images/frame_{i:08d}.png")
        (root / "images.txt").write_text("\n".join(lines) + "\n")


def test_ecd_text_layout_chunked_equals_whole(tmp_path):
    rec = open_recording(shared(DAVIS))
    ev = read_all(rec)[:20000]
    ev["t"] -= ev["t"][0] - 1_000_000  # ECD times start near 0 s: microsecond-exact in "%.6f"
    fr = rec.frames()
    _write_ecd(tmp_path / "ecd", ev, [(int(ev["t"][0]) + 40000 * i, fr.images[i]) for i in range(3)])
    ecd = open_recording(tmp_path / "ecd")
    assert (ecd.format, ecd.width, ecd.height, ecd.size_source) == ("ecd", 346, 260, "frames")
    ecd.text_chunk_bytes = 1000  # lines split across many reads
    parts = list(ecd.chunks())
    assert len(parts) > 100 and np.array_equal(np.concatenate(parts), ev)
    assert len(ecd.frames().t_us) == 3 and np.array_equal(ecd.frames().images[1], fr.images[1])
    assert np.array_equal(read_all(open_recording(tmp_path / "ecd" / "events.txt")), ev)


def test_h5_layout_read_in_chunks(tmp_path, monkeypatch):
    from tests.test_trainer_eval import H, W, write_moving_edge_h5

    from trainer.recordings import H5Sequence

    p = tmp_path / "edge.h5"
    write_moving_edge_h5(p)
    monkeypatch.setattr("trainer.recordings._H5_CHUNK", 7)  # several chunks from the small file
    rec, seq = open_recording(p), H5Sequence(str(p))
    assert len(list(rec.chunks())) > 1
    ev = read_all(rec)
    assert (rec.width, rec.height) == (W, H) and len(ev) == len(seq.ts)
    assert np.array_equal(ev["t"], np.round(seq.ts * 1e6).astype(np.int64)) and np.array_equal(ev["x"], seq.xs)
    assert np.array_equal(ev["y"], seq.ys) and np.array_equal(ev["p"], np.where(seq.ps > 0, 1, -1))
    assert np.array_equal(rec.frames().images, seq.images)


# -- bad recordings, made in tmp_path from the real ones --

def test_empty_files_are_errors(tmp_path):
    for name in ("empty.raw", "empty.aedat4", "empty.h5"):
        (tmp_path / name).write_bytes(b"")
        with pytest.raises(RecordingError, match="empty file") as e:
            open_recording(tmp_path / name)
        assert e.value.path == str(tmp_path / name)
    header_only = tmp_path / "header_only.raw"  # a RAW header and no event
    header_only.write_bytes(shared(EVT3).read_bytes()[:225])
    with pytest.raises(RecordingError, match="no events"):
        read_all(open_recording(header_only))


def test_wrong_format_is_an_error_naming_the_file(tmp_path):
    raw_as_aedat = tmp_path / "camera.aedat4"
    raw_as_aedat.write_bytes(shared(EVT2).read_bytes())
    with pytest.raises(RecordingError, match=r"camera\.aedat4: not an AEDAT4 file"):
        open_recording(raw_as_aedat)
    aedat_as_raw = tmp_path / "camera.raw"
    aedat_as_raw.write_bytes(shared(DAVIS).read_bytes()[:100000])
    with pytest.raises(RecordingError, match=r"camera\.raw: not a Prophesee RAW file"):
        open_recording(aedat_as_raw)
    as_h5 = tmp_path / "camera.h5"
    as_h5.write_bytes(shared(DAVIS).read_bytes()[:1000])
    with pytest.raises(RecordingError, match="not an HDF5 file"):
        open_recording(as_h5)
    with pytest.raises(RecordingError, match="unknown recording extension '.mp4'"):
        (tmp_path / "clip.mp4").write_bytes(b"\x00" * 10)
        open_recording(tmp_path / "clip.mp4")


def test_truncated_aedat4_keeps_the_events_before_the_cut(tmp_path, caplog):
    src = shared(DAVIS).read_bytes()
    p = tmp_path / "cut.aedat4"
    p.write_bytes(src[:len(src) // 2])
    full = read_all(open_recording(shared(DAVIS)))
    rec = open_recording(p)
    with caplog.at_level(logging.WARNING, logger="trainer.recordings"):
        got = read_all(rec)
    assert rec.truncated and "truncated" in caplog.text and "cut.aedat4" in caplog.text
    assert 0 < len(got) < len(full) and np.array_equal(got, full[:len(got)])
    assert 0 < len(rec.frames().t_us) < 59


def test_truncated_raw_inside_a_word_warns(tmp_path, caplog):
    src = shared(EVT3).read_bytes()
    p = tmp_path / "cut.raw"
    p.write_bytes(src[:1_000_000])  # the 225-byte header, then 999775 bytes: half of a 2-byte EVT3 word at the end
    rec = open_recording(p)
    with caplog.at_level(logging.WARNING, logger="trainer.recordings"):
        got = read_all(rec)
    assert rec.truncated and "ends inside a 2-byte EVT3 word" in caplog.text
    full = read_all(open_recording(shared(EVT3)))
    assert 0 < len(got) < len(full) and np.array_equal(got[:-100], full[:len(got) - 100])


def test_events_outside_the_sensor_are_an_error(tmp_path):
    with pytest.raises(RecordingError, match=r"prophesee_gen3_evt2\.raw: an event lies outside the 320x240 sensor "
                                             r"\(. overflow .*size from argument"):
        read_all(open_recording(shared(EVT2), size=(320, 240)))
    ev = read_all(open_recording(shared(DAVIS)))[:500]
    _write_ecd(tmp_path / "ecd", ev)
    with pytest.raises(RecordingError, match="outside the 100x100 sensor"):
        read_all(open_recording(tmp_path / "ecd", size=(100, 100)))
    with pytest.raises(RecordingError, match="no images to take the sensor size from"):
        open_recording(tmp_path / "ecd")


@pytest.mark.parametrize("geometry, why", [
    (b"99999x99999", "each side must be 1 to 65536 pixels"),  # over uint16 x, y
    (b"70000x720", "each side must be 1 to 65536 pixels"),
    (b"65536x65536", "over the 67108864 this reader takes"),  # fits uint16, but 16 GiB per uint8 frame
    (b"0x0", "each side must be 1 to 65536 pixels"),
    (b"-1280x720", "each side must be 1 to 65536 pixels"),
    (b"1280x-720", "each side must be 1 to 65536 pixels"),
    (b"1280 by 720", "not WIDTHxHEIGHT"),
])
def test_a_raw_header_size_out_of_bounds_names_the_file_and_the_field(tmp_path, geometry, why):
    """A header's sensor size is checked before anything is sized by it (x, y are uint16, and
    MAX_SENSOR_PIXELS bounds a frame): a RecordingError naming the file and the header field,
    not an OverflowError from the decoder or an allocation of the stated size."""
    src = shared(EVT3).read_bytes()
    assert src.count(b"% geometry 1280x720\n") == 1
    bad = tmp_path / "camera.raw"
    bad.write_bytes(src.replace(b"% geometry 1280x720\n", b"% geometry " + geometry + b"\n"))
    with pytest.raises(RecordingError, match=r"camera\.raw: the RAW header field 'geometry'") as e:
        read_all(open_recording(bad))
    assert why in str(e.value) and e.value.path == str(bad)
    if geometry == b"99999x99999":  # a size given explicitly is used instead: the file reads
        assert len(read_all(open_recording(bad, size=(1280, 720)))) == FACTS[EVT3][0]


def test_a_size_argument_or_h5_resolution_out_of_bounds_names_the_field(tmp_path):
    from tests.test_trainer_eval import write_moving_edge_h5

    import h5py

    with pytest.raises(RecordingError, match=r"prophesee_gen3_evt2\.raw: the size argument: sensor size 99999x480: "
                                             r"each side"):
        open_recording(shared(EVT2), size=(99999, 480))
    with pytest.raises(RecordingError, match="the size argument: sensor size 640.5x480: not whole numbers"):
        open_recording(shared(EVT2), size=(640.5, 480))
    for resolution, why in (((70000, 10), "10x70000: each side"), ((-4, 10), "10x-4: each side"),
                            ((50000, 50000), "50000x50000 = 2500000000 pixels")):
        p = tmp_path / "edge.h5"
        write_moving_edge_h5(p)
        with h5py.File(p, "r+") as f:
            f.attrs["sensor_resolution"] = resolution
        with pytest.raises(RecordingError, match=r"edge\.h5: the attribute 'sensor_resolution': sensor size "
                                                 + re.escape(why)):
            open_recording(p)


@pytest.mark.parametrize("width, height, why", [("99999", "480", "99999x480: each side must be 1 to 65536"),
                                                 ("-5", "480", "-5x480: each side"), ("abc", "480", "not whole numbers"),
                                                 ("65535", "65535", "over the 67108864 this reader takes")])
def test_a_dat_header_size_out_of_bounds_names_the_fields(tmp_path, width, height, why):
    """faery takes its fallback size for a DAT Width or Height it cannot parse: the header's
    fields are checked here, so the file is refused instead of read at a size it never stated."""
    import faery

    ev = read_all(open_recording(shared(EVT2)))[:5000]
    arr = np.zeros(len(ev), faery.EVENTS_DTYPE)
    arr["t"], arr["x"], arr["y"], arr["on"] = ev["t"] - ev["t"][0], ev["x"], ev["y"], ev["p"] > 0
    good = tmp_path / "good.dat"
    faery.events_stream_from_array(arr, dimensions=(640, 480)).to_file(good)
    assert good.read_bytes().count(b"% Width 640\n% Height 480\n") == 1
    bad = tmp_path / "camera.dat"
    bad.write_bytes(good.read_bytes().replace(b"% Width 640\n% Height 480\n",
                                              f"% Width {width}\n% Height {height}\n".encode()))
    with pytest.raises(RecordingError, match=r"camera\.dat: the DAT header fields 'Width' and 'Height': sensor size ") as e:
        open_recording(bad)
    assert why in str(e.value)


def test_an_aedat4_frame_outside_the_sensor_names_the_frame():
    rec = open_recording(shared(DAVIS), size=(100, 100))
    with pytest.raises(RecordingError, match=r"davis346_road\.aedat4: frame 0: its region 346x260 at offset \(0, 0\) "
                                             r"lies outside the 100x100 sensor"):
        rec.frames()


def test_backward_timestamps_are_dropped_and_counted(tmp_path, caplog):
    ev = read_all(open_recording(shared(DAVIS)))[:3000]
    ev["t"] -= ev["t"][0] - 1_000_000
    bad = ev.copy()
    bad["t"][1000:1010] = bad["t"][999] - 5000  # ten events 5 ms in the past
    _write_ecd(tmp_path / "ecd", bad)
    rec = open_recording(tmp_path / "ecd", size=(346, 260))
    with caplog.at_level(logging.WARNING, logger="trainer.recordings"):
        got = read_all(rec)
    assert rec.dropped_backward == 10 and "dropped 10 events" in caplog.text
    assert np.array_equal(got, np.delete(ev, np.arange(1000, 1010))) and np.all(np.diff(got["t"]) >= 0)


def test_frames_whose_timestamps_do_not_increase_are_dropped(tmp_path, caplog):
    rec = open_recording(shared(DAVIS))
    fr = rec.frames()
    t = [int(x) for x in fr.t_us[1:5]]
    t[2] = t[1]  # a repeated frame timestamp
    _write_ecd(tmp_path / "ecd", read_all(rec, int(fr.t_us[1]), int(fr.t_us[4]))[:100], list(zip(t, fr.images[1:5])))
    with caplog.at_level(logging.WARNING, logger="trainer.recordings"):
        got = open_recording(tmp_path / "ecd").frames()
    assert list(got.t_us) == [t[0], t[1], t[3]] and np.array_equal(got.images[2], fr.images[4])
    assert "dropping 1 frames" in caplog.text


def test_prophesee_backward_time_word_is_clamped_by_faery(tmp_path):
    """A damaged EVT3 TIME_LOW word (set to 0) puts one event 17 us in the past: faery clamps
    it to the previous timestamp, so the stream stays ordered and keeps every event."""
    src = shared(EVT3).read_bytes()
    w = np.frombuffer(src[225:], "<u2").copy()
    typ = w >> 12
    hit = np.flatnonzero((typ[:-2] == 6) & np.isin(typ[1:-1], [0, 2, 3]) & ((w[:-2] & 0xFFF) > 2000))
    w[hit[len(hit) // 2]] = 6 << 12  # TIME_LOW = 0
    p = tmp_path / "damaged.raw"
    p.write_bytes(src[:225] + w.tobytes())
    rec = open_recording(p)
    got, full = read_all(rec), read_all(open_recording(shared(EVT3)))
    assert len(got) == len(full) and np.all(np.diff(got["t"]) >= 0) and rec.dropped_backward == 0
    diff = np.flatnonzero(got["t"] != full["t"])
    assert len(diff) == 1 and got["t"][diff[0]] == got["t"][diff[0] - 1] < full["t"][diff[0]]


# -- the paper's discrete voxel grid --

def _voxels_direct(ev, edges, num_bins, h, w):
    """The paper's definition, one event at a time in exact rational arithmetic."""
    out = np.zeros((len(edges) - 1, num_bins, h, w), np.int64)
    for e in ev:
        t = int(e["t"])
        for k in range(len(edges) - 1):
            t0, t1 = int(edges[k]), int(edges[k + 1])
            if t0 <= t < t1:
                b = min(int(Fraction(t - t0, t1 - t0) * num_bins), num_bins - 1)
                out[k, b, e["y"], e["x"]] += 1 if e["p"] > 0 else -1
    return out


def test_voxel_grids_between_frames_equal_the_direct_definition():
    rec = open_recording(shared(DAVIS))
    edges = rec.frames().t_us[10:14]
    ev = read_all(rec, int(edges[0]), int(edges[-1]))
    expect = _voxels_direct(ev, edges, 5, rec.height, rec.width)
    grids = list(voxel_grids(rec.chunks(), edges, 5, rec.height, rec.width))
    assert [k for k, _, _ in grids] == [0, 1, 2] and int(np.abs(expect).sum()) > 1000
    for k, vox, cnt in grids:
        assert vox.dtype == np.int32 and np.array_equal(vox, expect[k])
        inside = ev[(ev["t"] >= edges[k]) & (ev["t"] < edges[k + 1])]
        assert int(cnt.sum()) == len(inside)
    # chunk boundaries do not matter: 7-event chunks give the same grids
    small = (ev[i:i + 7] for i in range(0, len(ev), 7))
    for (_, a, ca), (_, b, cb) in zip(grids, voxel_grids(small, edges, 5, rec.height, rec.width)):
        assert np.array_equal(a, b) and np.array_equal(ca, cb)


def test_voxel_grids_fixed_windows_and_empty_intervals():
    rec = open_recording(shared(EVT2))
    t0 = rec.first_t_us()
    edges = window_edges(t0, t0 + 9_999, 2_000)  # 5 windows of 2 ms
    assert np.array_equal(edges, t0 + np.arange(0, 12_000, 2_000))
    ev = read_all(rec, t0, int(edges[-1]))
    expect = _voxels_direct(ev[::50], edges, 3, rec.height, rec.width)
    got = [v for _, v, _ in voxel_grids([ev[::50]], edges, 3, rec.height, rec.width)]
    assert len(got) == 5 and all(np.array_equal(g, e) for g, e in zip(got, expect))
    # intervals before the first event and after the last still come out, empty
    late = np.concatenate(([t0 - 4000, t0 - 2000], edges))
    grids = list(voxel_grids([ev[:10]], late, 3, rec.height, rec.width))
    assert len(grids) == len(late) - 1 and not grids[0][1].any() and not grids[-1][1].any()
    with pytest.raises(ValueError):
        list(voxel_grids([ev], edges[::-1], 3, rec.height, rec.width))


def test_grids_of_a_fixed_number_of_events():
    rec = open_recording(shared(EVT2))
    ev = read_all(rec)
    edges = count_edges(rec.chunks(), 100_000)
    small = count_edges((ev[i:i + 999] for i in range(0, len(ev), 999)), 100_000)
    assert np.array_equal(edges, small) and len(edges) == 7 and edges[-1] == ev["t"][-1] + 1
    assert np.array_equal(edges[:-1], ev["t"][::100_000])
    counts = [int(c.sum()) for _, _, c in voxel_grids(rec.chunks(), edges, 5, rec.height, rec.width)]
    assert sum(counts) == len(ev) and all(abs(c - 100_000) < 100 for c in counts[:-1])  # ties at the edges
    assert counts[-1] == len(ev) - sum(counts[:-1])


# -- v2v-eval --recording --

def _mp4_frames(path: Path) -> int:
    import av

    with av.open(str(path)) as c:
        return sum(1 for _ in c.decode(video=0))


@pytest.fixture(scope="module")
def tiny_checkpoints(tmp_path_factory):
    """Randomly initialised e2vid and evflow checkpoints (B = 5, 4 base channels), as v2v-train writes them."""
    import torch

    from trainer.config import default_config, merge
    from trainer.core import Trainer

    root = tmp_path_factory.mktemp("ck")
    out = {}
    for task in ("e2vid", "evflow"):
        cfg = merge(default_config(task), {"model": {"num_bins": 5, "base_num_channels": 4}})
        out[task] = str(Trainer(cfg, str(root / task), torch.device("cpu")).save_checkpoint())
    return out


def test_eval_scores_davis_between_frame_timestamps(tmp_path, tiny_checkpoints):
    import json

    from trainer.evaluate import main

    p = shared(DAVIS)
    assert main(["--checkpoint", tiny_checkpoints["e2vid"], "--recording", str(p), "--end", "0.3", "--device", "cpu",
                 "--out", str(tmp_path / "ev"), "--write-video", str(tmp_path / "vid"), "--save-images", "4"]) == 0
    res = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    fr = open_recording(p).frames()
    t_first = FACTS[DAVIS][2]
    kept = fr.images[(fr.t_us >= t_first) & (fr.t_us <= t_first + 300_000)]
    info = res["recordings"][str(p)]
    # the first APS frame precedes the first event: the cut starts at the second
    assert info["binning"] == "between consecutive frame timestamps" and info["grids"] == len(kept) - 1 == 6
    assert res["frames"] == info["frames_scored"] == 6
    gt = kept[1:] / 255.0  # the constant-mean baseline pins which frames were scored
    assert res["mean"]["base_mse"] == pytest.approx(np.mean((gt - gt.mean()) ** 2), rel=1e-5)
    assert np.isfinite(res["mean"]["mse"]) and np.isfinite(res["mean"]["ssim"])
    assert sorted(q.name for q in (tmp_path / "ev").glob("*_cmp_*.png")) == ["davis346_road_cmp_00000.png",
                                                                          "davis346_road_cmp_00004.png"]
    assert len(list((tmp_path / "vid").glob("davis346_road_0*.png"))) == 6
    assert _mp4_frames(tmp_path / "vid" / "davis346_road.mp4") == 6


def test_eval_records_a_truncated_recording_as_truncated(tmp_path, tiny_checkpoints, caplog):
    """A recording cut short: v2v-eval warns that it is truncated and metrics.json says so too,
    although the pass that scores the grids stops before the cut (a fact of the file, found by
    the pass that read its frames, is not undone by a later pass that ends earlier)."""
    import json

    from trainer.evaluate import main

    src = shared(DAVIS).read_bytes()
    p = tmp_path / "cut.aedat4"
    p.write_bytes(src[:len(src) // 2])
    with caplog.at_level(logging.WARNING, logger="trainer.recordings"):
        assert main(["--checkpoint", tiny_checkpoints["e2vid"], "--recording", str(p), "--end", "0.2", "--device",
                     "cpu", "--out", str(tmp_path / "ev")]) == 0
    assert "truncated" in caplog.text
    info = json.loads((tmp_path / "ev" / "metrics.json").read_text())["recordings"][str(p)]
    assert info["truncated"] is True and info["frames_scored"] > 0
    assert main(["--checkpoint", tiny_checkpoints["e2vid"], "--recording", str(shared(DAVIS)), "--end", "0.2",
                 "--device", "cpu", "--out", str(tmp_path / "whole")]) == 0
    assert json.loads((tmp_path / "whole" / "metrics.json").read_text())["recordings"][str(shared(DAVIS))][
        "truncated"] is False


def test_eval_writes_video_of_a_recording_without_frames(tmp_path, tiny_checkpoints):
    import json

    from trainer.evaluate import main

    p = shared(EVT3)
    assert main(["--checkpoint", tiny_checkpoints["e2vid"], "--recording", str(p), "--end", "0.1",
                 "--window-ms", "40", "--device", "cpu", "--out", str(tmp_path)]) == 0
    info = json.loads((tmp_path / "metrics.json").read_text())["recordings"][str(p)]
    assert info["binning"] == "fixed windows of 40 ms" and info["grids"] == 3 and info["frames_scored"] == 0
    assert info["end_us"] - info["start_us"] == 120_000 and info["sensor_size"] == [1280, 720]
    import cv2

    png = cv2.imread(str(tmp_path / "prophesee_evk4_evt3_00002.png"), cv2.IMREAD_GRAYSCALE)
    assert png.shape == (720, 1280) and _mp4_frames(tmp_path / "prophesee_evk4_evt3.mp4") == 3
    # a flow network: its flow colour-coded
    assert main(["--checkpoint", tiny_checkpoints["evflow"], "--recording", str(shared(EVT2)), "--window-ms", "25",
                 "--device", "cpu", "--out", str(tmp_path / "flow")]) == 0
    assert _mp4_frames(tmp_path / "flow" / "prophesee_gen3_evt2_flow.mp4") == 4  # 96 ms of events
    assert main(["--checkpoint", tiny_checkpoints["evflow"], "--recording", str(shared(EVT2)), "--events-per-grid",
                 "200000", "--device", "cpu", "--out", str(tmp_path / "count")]) == 0
    info = json.loads((tmp_path / "count" / "metrics.json").read_text())["recordings"][str(shared(EVT2))]
    assert info["binning"] == "200000 events per grid" and info["grids"] == 3  # 521252 events


def test_eval_resizes_frames_to_the_sensor_and_names_bad_recordings(tmp_path, tiny_checkpoints, caplog):
    import json

    import cv2

    from trainer.evaluate import main

    rec = open_recording(shared(DAVIS))
    fr = rec.frames()
    ev = read_all(rec, int(fr.t_us[0]), int(fr.t_us[4]))  # from before frame 1 to frame 4
    small = [(int(t), cv2.resize(im, (173, 130), interpolation=cv2.INTER_AREA))
             for t, im in zip(fr.t_us[1:5], fr.images[1:5])]
    _write_ecd(tmp_path / "ecd", ev, small)  # frames at half the sensor's size
    ck = tiny_checkpoints["e2vid"]
    assert main(["--checkpoint", ck, "--recording", str(tmp_path / "ecd"), "--sensor-size", "346", "260",
                 "--device", "cpu", "--out", str(tmp_path / "ev")]) == 0
    res = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert res["frames"] == 3 and res["recordings"][str(tmp_path / "ecd")]["sensor_size"] == [346, 260]
    (tmp_path / "empty.aedat4").write_bytes(b"")
    with caplog.at_level(logging.ERROR, logger="trainer.evaluate"):
        assert main(["--checkpoint", ck, "--recording", str(tmp_path / "empty.aedat4"), "--device", "cpu",
                     "--out", str(tmp_path / "x")]) == 2
    assert "empty.aedat4: empty file" in caplog.text

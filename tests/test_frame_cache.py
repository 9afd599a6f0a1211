"""The decoded-frame cache (v2v_server/frames/frame_cache.py): samples cut from cached frames are
the samples cut from decoded ones, cold or warm, in both formats and for awkward sources; every
fault of an entry (a killed writer, a full budget or disk, a truncated or bit-flipped entry, a
source replaced in place, the folder deleted while serving, two writers at once) ends in
decoding, with no sample lost or altered and the cause counted."""
from __future__ import annotations

import itertools
import json
import multiprocessing as mp
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import av
import numpy as np
import pytest

from harness.corpus import write_size_change_video, write_video
from harness.faults_fs import replace_with_a_file
from tests import sample_hashes
from tests.cached import Cached, cached
from v2v_server.ops.config import ServeConfig
from v2v_server.samples.recipe import SampleRecipe
from v2v_server.samples.make import video_samples
from v2v_server.frames.frame_cache import MAGIC
from v2v_server.sources.local import RACY_NS, LocalSource
from v2v_wire.outputs import DEFAULT_OUTPUTS, OUTPUTS

ROOT = Path(__file__).resolve().parents[1]
CLIPS = ROOT / "v2v_server" / "sample_videos"
#: a short recipe: windows of 9 frames, 32 px crops, so the synthetic clips give several samples
SMALL = dict(sequence_length=4, num_bins=2, crop_size=32, max_samples_per_video=4)


def _samples(cfg, root, video, epoch=0, outputs=DEFAULT_OUTPUTS) -> dict:
    """{sample id: (sha of each array, params)} of one video of one epoch of ``root`` (a folder
    or a ``VideoSource``)."""
    out = {}
    source, caches = (root.source, root.caches) if isinstance(root, Cached) else (LocalSource(root), None)
    for key, arrays, meta in video_samples(cfg, source, video, epoch, outputs, flow_grid=True, caches=caches):
        out[key.sample_id(cfg.crops_per_window)] = sample_hashes._digest(arrays, sample_hashes._canonical(meta))
    return out


def _settle() -> None:
    """Wait out the racy window (``sources.local.RACY_NS``) of files this test just wrote: a file
    changed within it is decoded and not stored (git's racy rule)."""
    time.sleep(RACY_NS / 1e9 + 0.02)


def _entries(cache_dir) -> list:
    d = Path(cache_dir) / "frames"
    return sorted(p for p in d.glob("*.v2vf")) if d.is_dir() else []


def test_pinned_table_holds_cold_and_warm(tmp_path):
    """The committed sample table (tests/data/sample_hashes.json) is what the cache serves, cold
    (decoding and storing) and warm (cut from the entries), for every recipe of the table."""
    want = json.loads(sample_hashes.TABLE.read_text())
    src = cached(CLIPS, tmp_path)
    for state in ("cold", "warm"):
        got = sample_hashes.compute(src.source, src.caches)
        assert got == want, state
        stats = src.take_stats()["frame_cache"]
        if state == "warm":
            assert not any(stats["misses"].values()) and stats["hits"] > 0
        else:
            assert stats["stored"] == 6 and stats["misses"]["absent"] == 6  # one entry per clip and frames_per_sample


def _awkward_corpus(d: Path) -> Path:
    d.mkdir()
    write_video(d / "ten_bit.mkv", 30, 96, 80, codec="ffv1", pix_fmt="yuv420p10le")
    write_video(d / "grey.mkv", 30, 96, 80, codec="ffv1", pix_fmt="gray", gray=True)
    write_size_change_video(d / "size_change.mpg", 14, 20, size1=(96, 80), size2=(80, 64))
    with av.open(str(d / "rotated.mp4"), "w") as c:  # a phone clip: a display matrix turns it a quarter
        s = c.add_stream("libx264", rate=25)
        s.width, s.height, s.pix_fmt = 96, 64, "yuv420p"
        s.set_display_rotation(90)
        for i in range(30):
            img = np.tile(np.linspace(20, 220, 96, dtype=np.uint8), (64, 1))
            img[:, (i * 3) % 90:(i * 3) % 90 + 6] = 250
            for p in s.encode(av.VideoFrame.from_ndarray(np.repeat(img[..., None], 3, 2), format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    _settle()  # written just now: stored only once older than the racy window
    return d


@pytest.mark.parametrize("fmt", ["raw", "zstd"])
def test_awkward_sources_identical_cached_and_decoded(tmp_path, fmt):
    """A 10-bit source (uint16 frames), a grey full-range one, a rotated phone clip and a stream
    whose frame size changes mid-way: every output (polarity counts too), one and four crops,
    cached (cold and warm) equal to decoded."""
    corpus = _awkward_corpus(tmp_path / "corpus")
    src = cached(corpus, tmp_path / "cache", fmt=fmt)
    for crops in (1, 4):
        cfg = SampleRecipe(**SMALL, crops_per_window=crops, keep_top_fraction=1.0)
        for video in sorted(p.name for p in corpus.iterdir()):
            decoded = _samples(cfg, corpus, video, outputs=OUTPUTS)
            assert decoded, video
            assert _samples(cfg, src, video, outputs=OUTPUTS) == decoded, (video, "cold")
            assert _samples(cfg, src, video, outputs=OUTPUTS) == decoded, (video, "warm")
    stats = src.take_stats()["frame_cache"]
    assert stats["hits"] == 12 and stats["stored"] == 4, stats  # one entry serves one and four crops


def test_later_epochs_draw_anew_from_the_same_entry(tmp_path):
    cfg = SampleRecipe(**SMALL)
    src = cached(CLIPS, tmp_path)
    e0 = _samples(cfg, src, "bikes.mp4", epoch=0)
    e1 = _samples(cfg, src, "bikes.mp4", epoch=1)
    assert e1 == _samples(cfg, CLIPS, "bikes.mp4", epoch=1)
    assert all(e0[k]["voxels"] != e1[k]["voxels"] for k in e0)
    assert src.take_stats()["frame_cache"]["hits"] == 1


def _flip_byte(path: Path, at: int) -> None:
    with open(path, "r+b") as f:
        f.seek(at)
        b = f.read(1)
        f.seek(at)
        f.write(bytes([b[0] ^ 0x10]))


@pytest.mark.parametrize("fault", ["truncated", "bit_flip_frame", "bit_flip_trailer", "not_an_entry"])
@pytest.mark.parametrize("fmt", ["raw", "zstd"])
def test_damaged_entry_is_decoded_again(tmp_path, fault, fmt):
    cfg = SampleRecipe(**SMALL)
    video = "bikes.mp4"
    want = _samples(cfg, CLIPS, video)
    src = cached(CLIPS, tmp_path, fmt=fmt)
    assert _samples(cfg, src, video) == want
    (entry,) = _entries(tmp_path)
    size = entry.stat().st_size
    if fault == "truncated":
        os.truncate(entry, size // 2)
    elif fault == "bit_flip_frame":
        _flip_byte(entry, 20_000)  # inside frame 0 or 1: found while reading, the rest decoded
    elif fault == "bit_flip_trailer":
        _flip_byte(entry, size - len(MAGIC) - 20 - 40)
    else:
        entry.write_bytes(b"not an entry at all" * 10)
    src.take_stats()
    assert _samples(cfg, src, video) == want
    stats = src.take_stats()["frame_cache"]
    assert stats["misses"]["corrupt"] == 1 and stats["hits"] == 0, stats
    # a fault found on opening is decoded and stored in the same pass; one found mid-read is
    # decoded from that frame on, and the next pass stores the video again
    assert stats["stored"] == (0 if fault == "bit_flip_frame" else 1), stats
    if fault == "bit_flip_frame":
        assert _samples(cfg, src, video) == want
        assert src.take_stats()["frame_cache"]["stored"] == 1
    assert _samples(cfg, src, video) == want
    assert src.take_stats()["frame_cache"]["hits"] == 1


def _rewrite_trailer(entry: Path, change) -> None:
    """Rewrite the trailer of ``entry`` as ``change(meta)`` leaves it, with a valid CRC-32 (a
    trailer written wrong, not damaged)."""
    import struct
    import zlib

    data = entry.read_bytes()
    foot = struct.Struct("<QI")
    n, _ = foot.unpack(data[-len(MAGIC) - foot.size:-len(MAGIC)])
    end = len(data) - len(MAGIC) - foot.size
    meta = json.loads(data[end - n:end])
    change(meta)
    t = json.dumps(meta).encode()
    entry.write_bytes(data[:end - n] + t + foot.pack(len(t), zlib.crc32(t)) + MAGIC)


@pytest.mark.parametrize("field", ["shape", "huge_shape", "offset", "dtype"])
def test_trailer_that_passes_its_crc_but_sizes_frames_wrong_is_corrupt(tmp_path, field):
    """A trailer with a valid CRC whose frame sizes do not hold (another shape than its bytes,
    a 100000 x 100000 frame, a frame past the data, an unknown dtype) is a corrupt entry found
    before any frame is read or allocated: decoded, removed, stored again."""
    cfg = SampleRecipe(**SMALL)
    want = _samples(cfg, CLIPS, "bikes.mp4")
    src = cached(CLIPS, tmp_path)
    assert _samples(cfg, src, "bikes.mp4") == want
    (entry,) = _entries(tmp_path)

    def change(m):
        if field == "shape":
            m["shapes"][0][1] += 1
        elif field == "huge_shape":
            m["shapes"] = [[0, 100_000, 100_000]]
        elif field == "offset":
            m["offsets"][-1] = 1 << 40
        else:
            m["dtype"] = "<f8"

    _rewrite_trailer(entry, change)
    src.take_stats()
    assert _samples(cfg, src, "bikes.mp4") == want
    stats = src.take_stats()["frame_cache"]
    assert stats["misses"]["corrupt"] == 1 and stats["stored"] == 1, stats


def test_source_replaced_in_place_is_a_miss(tmp_path):
    corpus = tmp_path / "corpus"
    corpus.mkdir()
    shutil.copy(CLIPS / "bikes.mp4", corpus / "v.mp4")
    _settle()
    cfg = SampleRecipe(**SMALL)
    src = cached(corpus, tmp_path / "cache")
    _samples(cfg, src, "v.mp4")
    shutil.copy(CLIPS / "webvid_like_596x336.mp4", corpus / "v.mp4")  # same name, other content
    _settle()
    src.take_stats()
    assert _samples(cfg, src, "v.mp4") == _samples(cfg, corpus, "v.mp4")
    stats = src.take_stats()["frame_cache"]
    assert stats["misses"]["changed"] == 1 and stats["hits"] == 0 and stats["stored"] == 1
    assert len(_entries(tmp_path / "cache")) == 1  # the stale entry was replaced, not kept beside


def test_rewrite_in_place_keeping_size_mtime_and_inode_is_a_miss(tmp_path):
    """An uncompressed AVI whose frames 10.. are inverted in place after it was cached, its
    size, inode and modification time (to the nanosecond) kept, as ``rsync --inplace -t`` or a
    tool that restores mtimes leaves it: the change time differs, so the entry is a miss
    (``changed``) and the samples are those of the new bytes, never the cached frames."""
    import re
    import struct

    corpus = tmp_path / "corpus"
    corpus.mkdir()
    w, h = 96, 64
    v = write_video(corpus / "v.avi", 40, w, h, codec="rawvideo", pix_fmt="gray", gray=True)
    _settle()
    cfg = SampleRecipe(**SMALL)
    src = cached(corpus, tmp_path / "cache")
    before = _samples(cfg, src, "v.avi")
    assert src.take_stats()["frame_cache"]["stored"] == 1
    st, data = os.stat(v), v.read_bytes()
    frames = [m.end() for m in re.finditer(re.escape(b"00dc" + struct.pack("<I", w * h)), data)]
    assert len(frames) == 40
    with open(v, "r+b") as f:
        for at in frames[10:]:
            f.seek(at)
            f.write((255 - np.frombuffer(data, np.uint8, w * h, at)).astype(np.uint8).tobytes())
    os.utime(v, ns=(st.st_atime_ns, st.st_mtime_ns))
    now = os.stat(v)
    assert (now.st_size, now.st_mtime_ns, now.st_ino) == (st.st_size, st.st_mtime_ns, st.st_ino)
    _settle()
    got = _samples(cfg, src, "v.avi")
    assert got == _samples(cfg, corpus, "v.avi") and got != before
    stats = src.take_stats()["frame_cache"]
    assert stats["misses"]["changed"] == 1 and stats["hits"] == 0 and stats["stored"] == 1, stats


def test_a_file_changed_within_the_timestamp_resolution_is_not_stored(tmp_path):
    """git's racy rule: a file whose change time is within ``RACY_NS`` of its stat is decoded
    and not stored (a write in the same clock tick could leave its identity unchanged); once
    older, it is stored and hit."""
    corpus = tmp_path / "corpus"
    corpus.mkdir()
    shutil.copy(CLIPS / "bikes.mp4", corpus / "v.mp4")
    cfg = SampleRecipe(**SMALL)
    src = cached(corpus, tmp_path / "cache")
    from v2v_server.sources.local import racy

    st = os.stat(corpus / "v.mp4")
    assert racy(st, st.st_ctime_ns) and not racy(st, st.st_ctime_ns + RACY_NS + 1)
    os.utime(corpus / "v.mp4")  # changed now
    got = _samples(cfg, src, "v.mp4")  # looked up at once: within RACY_NS of the change
    stats = src.take_stats()["frame_cache"]
    want = _samples(cfg, corpus, "v.mp4")
    assert got == want
    if stats["misses"]["unverified"] != 1:
        pytest.skip(f"the lookup came later than RACY_NS after the change (a loaded machine): {stats}")
    assert stats["stored"] == 0 and not _entries(tmp_path / "cache"), stats
    _settle()
    assert _samples(cfg, src, "v.mp4") == want and _samples(cfg, src, "v.mp4") == want
    stats = src.take_stats()["frame_cache"]
    assert stats["stored"] == 1 and stats["hits"] == 1, stats


def test_cache_folder_deleted_while_serving(tmp_path):
    """The folder removed mid-write (the entry cannot be committed) and between epochs."""
    cfg = SampleRecipe(**SMALL)
    want = _samples(cfg, CLIPS, "bikes.mp4")
    src = cached(CLIPS, tmp_path)
    got = {}
    run = video_samples(cfg, src.source, "bikes.mp4", 0, DEFAULT_OUTPUTS, flow_grid=True, caches=src.caches)
    for i, (key, arrays, meta) in enumerate(run):
        got[key.sample_id(1)] = sample_hashes._digest(arrays, sample_hashes._canonical(meta))
        if i == 0:
            shutil.rmtree(tmp_path / "frames")
    assert got == want
    stats = src.take_stats()["frame_cache"]
    assert stats["not_stored"]["write_error"] == 1 and stats["stored"] == 0, stats
    assert _samples(cfg, src, "bikes.mp4") == want  # the folder is made again
    assert src.take_stats()["frame_cache"]["stored"] == 1
    shutil.rmtree(tmp_path / "frames")
    assert _samples(cfg, src, "bikes.mp4") == want
    assert src.take_stats()["frame_cache"]["misses"]["absent"] == 1


@pytest.mark.parametrize("flags", [("--frame-cache-gb", "1"), ("--frame-cache-gb", "1", "--warm-cache")])
def test_unusable_cache_dir_at_start_is_one_clear_line(tmp_path, flags):
    """``--cache-dir`` naming a file: v2v-serve exits 2 at once with one line naming the path,
    before any worker starts (serving would otherwise decode every epoch it was asked to cache)."""
    bad = tmp_path / "not_a_folder"
    bad.write_text("a file")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--videos", str(CLIPS),
                        "--bind", "tcp://127.0.0.1:0", "--cache-dir", str(bad), *flags],
                       capture_output=True, text=True, timeout=60, env=env)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert lines[0].startswith(f"v2v-serve: --cache-dir {bad}: cannot keep a cache in {bad / 'frames'}"), lines


def test_budget_holds_and_keeps_what_it_admitted(tmp_path):
    """A budget below the corpus: entries are admitted until full and kept (policy ``keep``);
    the next epoch hits those and decodes the rest; the folder never holds more than the budget."""
    cfg = SampleRecipe(**SMALL)
    clips = ["bikes.mp4", "webvid_like_596x336.mp4", "bigbuckbunny.mp4"]
    probe = cached(CLIPS, tmp_path / "probe")
    sizes = {}
    for c in clips:
        _samples(cfg, probe, c)
        sizes[c] = max(_entries(tmp_path / "probe"), key=lambda p: p.stat().st_mtime_ns).stat().st_size
    budget = sizes["bikes.mp4"] + sizes["webvid_like_596x336.mp4"] + sizes["bigbuckbunny.mp4"] // 2
    src = cached(CLIPS, tmp_path / "cache", gb=budget / (1 << 30))
    for epoch in (0, 1):
        for c in clips:
            assert _samples(cfg, src, c, epoch) == _samples(cfg, CLIPS, c, epoch)
            assert sum(p.stat().st_size for p in _entries(tmp_path / "cache")) <= budget
        stats = src.take_stats()["frame_cache"]
        if epoch == 0:
            assert stats["stored"] == 2 and stats["not_stored"]["budget"] == 1, stats
        else:
            assert stats["hits"] == 2 and stats["misses"]["absent"] == 1, stats


def _make_samples(root: str, cache_dir: str, video: str, kill_after: int) -> None:
    """In a fresh process: make ``video``'s samples through the cache, SIGKILL itself after
    ``kill_after`` of them (-1: never)."""
    import signal

    cfg = SampleRecipe(**SMALL)
    src = cached(root, cache_dir)
    for i, _ in enumerate(video_samples(cfg, src.source, video, 0, DEFAULT_OUTPUTS, caches=src.caches)):
        if i == kill_after:
            os.kill(os.getpid(), signal.SIGKILL)


def test_writer_killed_mid_write_leaves_no_entry(tmp_path):
    code = ("import sys; from tests.test_frame_cache import _make_samples; "
            f"_make_samples({str(CLIPS)!r}, {str(tmp_path)!r}, 'bikes.mp4', 1)")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, timeout=120)
    assert r.returncode == -9
    assert not _entries(tmp_path) and list((tmp_path / "frames").glob("*.tmp"))  # the half-written file
    cfg = SampleRecipe(**SMALL)
    src = cached(CLIPS, tmp_path)
    assert _samples(cfg, src, "bikes.mp4") == _samples(cfg, CLIPS, "bikes.mp4")
    assert src.take_stats()["frame_cache"]["stored"] == 1
    assert len(_entries(tmp_path)) == 1 and not list((tmp_path / "frames").glob("*.tmp"))  # the dead writer's file removed


def test_two_writers_make_one_entry(tmp_path):
    """Two processes decode the same video at once: one entry, which then serves both."""
    ctx = mp.get_context("spawn")
    procs = [ctx.Process(target=_make_samples, args=(str(CLIPS), str(tmp_path), "bikes.mp4", -1)) for _ in range(2)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
        assert p.exitcode == 0
    assert len(_entries(tmp_path)) == 1 and not list((tmp_path / "frames").glob("*.tmp"))
    # and two interleaved passes in one process, both driven to their end so that both writers
    # commit: the second finds the entry there, drops its own and is counted neither stored nor
    # not stored (an abandoned pass would count as incomplete)
    cfg = SampleRecipe(**SMALL)
    src = cached(CLIPS, tmp_path / "one")
    passes = [video_samples(cfg, src.source, "bikes.mp4", 0, DEFAULT_OUTPUTS, flow_grid=True,
                                         caches=src.caches) for _ in range(2)]
    got: tuple = ({}, {})
    for pair in itertools.zip_longest(*passes):
        for seen, sample in zip(got, pair):
            assert sample is not None, "the two passes gave different numbers of samples"
            key, arrays, meta = sample
            seen[key.sample_id(1)] = sample_hashes._digest(arrays, sample_hashes._canonical(meta))
    assert got[0] == got[1] == _samples(cfg, CLIPS, "bikes.mp4")
    stats = src.take_stats()["frame_cache"]
    assert stats["stored"] == 1 and stats["misses"]["absent"] == 2, stats
    assert stats["not_stored"] == dict.fromkeys(stats["not_stored"], 0), stats
    assert len(_entries(tmp_path / "one")) == 1 and not list((tmp_path / "one" / "frames").glob("*.tmp"))
    assert _samples(cfg, src, "bikes.mp4") == got[0]  # the one entry serves the same samples
    stats = src.take_stats()["frame_cache"]
    assert stats["hits"] == 1 and stats["stored"] == 0, stats


def test_full_disk_is_decoded_and_counted(tmp_path):
    """A real full disk: a 2 MiB tmpfs (needs mount rights; skipped without them)."""
    mnt = tmp_path / "small"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mnt)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.decode().strip()}")
    try:
        cfg = SampleRecipe(**SMALL)
        src = cached(CLIPS, mnt, gb=1.0)
        assert _samples(cfg, src, "webvid_like_596x336.mp4") == _samples(cfg, CLIPS, "webvid_like_596x336.mp4")
        stats = src.take_stats()["frame_cache"]
        assert stats["not_stored"]["disk_full"] == 1 and stats["stored"] == 0, stats
        assert not list((mnt / "frames").iterdir())  # no entry, no temporary file left
    finally:
        subprocess.run(["umount", "--lazy", str(mnt)], check=False)  # detached even while a file is open


def test_settings_that_change_frames_name_other_entries(tmp_path):
    src = cached(CLIPS, tmp_path)
    for kw in ({}, {"decode_fast": "all"}, {"keep_top_fraction": 0.8}):
        cfg = SampleRecipe(**SMALL, **kw)
        assert _samples(cfg, src, "bikes.mp4") == _samples(cfg, CLIPS, "bikes.mp4")
    assert src.take_stats()["frame_cache"]["hits"] == 0
    assert len(_entries(tmp_path)) == 3


def _served(corpus: Path, *extra: str, epochs: int = 2, after_first_batch=None, done=None, log=None) -> dict:
    """{(epoch, sample id): bytes of every output} of epochs 0 .. ``epochs`` - 1 served by
    v2v-serve with two workers (padding rows left out), and the frame-cache and filesystem-error
    metrics of the last /metrics page, read once ``done(metrics)`` holds (default: the cache's
    gauges counted an entry). ``after_first_batch()`` runs once the first batch arrived; ``log``
    (a list) gets the server's log lines."""
    import time
    import urllib.request

    from harness.faults import Layout
    from harness.serve import ServeProcess, free_port
    from v2v_client import V2VStreamDataset

    done = done or (lambda m: m.get("v2v_frame_cache_entries", 1) > 0)
    out, port = {}, free_port()
    with ServeProcess(["--videos", str(corpus), "--workers", "2", *Layout(L=4, crop=64, windows=2, batch=2).args(),
                       "--outputs", "voxels,frames,flow", "--metrics-port", str(port),
                       *extra]) as srv:
        ds = V2VStreamDataset(srv.endpoint, 2, outputs=("voxels", "frames", "flow"), timeout_s=120, raw=True)
        for epoch in range(epochs):
            ds.set_epoch(epoch)
            for b in ds:
                for i, sid in enumerate(b["sample_ids"]):
                    if b["padding"][i]:
                        continue
                    key = (b["epoch"], sid)
                    assert key not in out, f"{key} delivered twice"
                    out[key] = b"".join(np.asarray(b[k][i]).tobytes() for k in ("voxels", "frames", "flow"))
                if after_first_batch is not None:
                    after_first_batch()
                    after_first_batch = None
        deadline = time.monotonic() + 20
        while True:  # the page is rendered at most once a second, the cache's folder scanned every few
            page = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
            metrics = {line.split()[0]: float(line.split()[1]) for line in page.splitlines()
                       if line.startswith(("v2v_frame_cache", "v2v_fs_errors")) and "_created" not in line}
            if done(metrics) or time.monotonic() > deadline:
                break
            time.sleep(0.5)
        if log is not None:
            log += srv.lines
        return out, metrics


def test_served_epochs_identical_with_the_cache_and_epoch_one_hits(tmp_path):
    """v2v-serve with two workers: both epochs byte for byte those of a server without the
    cache; epoch 1 cut from the entries (hits in /metrics), the gauges set."""
    corpus = tmp_path / "corpus"
    corpus.mkdir()
    for name in ("bikes.mp4", "webvid_like_596x336.mp4"):
        shutil.copy(CLIPS / name, corpus / name)
    plain, _ = _served(corpus)
    cached, m = _served(corpus, "--frame-cache-gb", "1", "--cache-dir", str(tmp_path / "cache"))
    assert len(plain) == 8 and cached == plain  # 2 windows of each clip, 2 epochs
    # every pass over a video is a hit or a miss; a video may be passed over more than once an
    # epoch (a pass whose samples were dropped before their fetch is made again) and a pass may
    # open a video while another still stores it: each video is stored once, epoch 1 hits
    misses = m['v2v_frame_cache_misses_total{cause="absent"}']
    assert m["v2v_frame_cache_hits_total"] >= 1 and m["v2v_frame_cache_hits_total"] + misses >= 4, m
    assert m["v2v_frame_cache_stored_total"] == 2, m
    assert m["v2v_frame_cache_budget_bytes"] == 1 << 30 and m["v2v_frame_cache_entries"] == 2


def test_cache_folder_replaced_by_a_file_while_serving(tmp_path):
    """The cache folder turned into a file mid-run (what a vanished mount, a failing disk's EIO
    or an NFS ESTALE look like to a scan): the server's gauge scan counts it and logs it once,
    workers serve by decoding, and every sample of both epochs arrives once, byte for byte
    what a server without the cache sends."""
    corpus = tmp_path / "corpus"
    corpus.mkdir()
    for name in ("bikes.mp4", "webvid_like_596x336.mp4"):
        shutil.copy(CLIPS / name, corpus / name)
    plain, _ = _served(corpus)
    frames = tmp_path / "cache" / "frames"

    def replace():
        replace_with_a_file(frames)  # workers may make the folder again meanwhile: it repeats

    log: list = []
    key = 'v2v_fs_errors_total{where="frame_cache"}'
    cached, m = _served(corpus, "--frame-cache-gb", "1", "--cache-dir", str(tmp_path / "cache"),
                        after_first_batch=replace, done=lambda m: m.get(key, 0) >= 2, log=log)
    assert len(plain) == 8 and cached == plain
    assert m[key] >= 2, m  # every scan counted (one every FRAME_CACHE_SCAN_S) ...
    told = [line for line in log if "v2v_fs_errors_total" in line]
    assert len(told) == 1 and str(frames) in told[0] and "ENOTDIR" in told[0], told  # ... logged once
    assert not any("server loop failed" in line or "Traceback" in line for line in log), "".join(log)


def test_ray_stage_hits_its_node_local_cache(tmp_path):
    """The Ray engine's sample maker (one per actor) reads the node's cache under its cache_dir."""
    import json as _json

    from v2v_server.ray_data import SampleMaker, epoch_descriptors, scan_corpus_windows

    cfg = ServeConfig(**SMALL, frame_cache_gb=1.0, cache_dir=str(tmp_path))
    rc = scan_corpus_windows(str(CLIPS), cfg)
    maker = SampleMaker.of(cfg, rc.root, ("voxels", "frames"))
    plain = SampleMaker.of(ServeConfig(**SMALL), rc.root, ("voxels", "frames"))

    def rows(m, epoch):
        return {str(r["sample_id"][0]): r["voxels"].tobytes() + r["frames"].tobytes()
                for d in epoch_descriptors(rc, epoch) for r in m.video_rows(d["video"], epoch, _json.loads(d["entries"]))}

    for epoch in (0, 1):
        assert rows(maker, epoch) == rows(plain, epoch)
    stats = maker.caches.take_stats()["frame_cache"]
    assert stats["hits"] == stats["stored"] == len(epoch_descriptors(rc, 0)), stats


def test_ray_stage_reads_a_video_whole_only_to_store_it(tmp_path, monkeypatch):
    """Rows of a video's first window only: the pass that stores the video reads it to its end
    (the entry committed, nothing dropped as incomplete); the pass replaying that entry stops
    after the window, as a pass without a cache stops decoding. Rows as without the cache."""
    import json as _json

    from v2v_server.ray_data import SampleMaker, epoch_descriptors, scan_corpus_windows
    from v2v_server.frames import frame_cache
    from v2v_wire.ids import parse_sample_id

    cfg = ServeConfig(**SMALL, frame_cache_gb=1.0, cache_dir=str(tmp_path))
    rc = scan_corpus_windows(str(CLIPS), cfg)
    (d,) = [d for d in epoch_descriptors(rc, 0) if d["video"] == "bikes.mp4"]
    entries = _json.loads(d["entries"])
    first = [e for e in entries if parse_sample_id(e[0]).window == 0]
    assert 0 < len(first) < len(entries)
    replay: dict = {}
    read = frame_cache.CachedVideo.read

    def counted(self):
        replay.update(stored=self.frames, read=0)
        for a in read(self):
            replay["read"] += 1
            yield a

    monkeypatch.setattr(frame_cache.CachedVideo, "read", counted)
    maker = SampleMaker.of(cfg, rc.root, ("voxels",))
    plain = SampleMaker.of(ServeConfig(**SMALL), rc.root, ("voxels",))

    def rows(m):
        return {str(r["sample_id"][0]): r["voxels"].tobytes() for r in m.video_rows("bikes.mp4", 0, first)}

    want = rows(plain)
    assert rows(maker) == want and not replay
    stats = maker.caches.take_stats()["frame_cache"]
    assert stats["stored"] == 1 and stats["not_stored"]["incomplete"] == 0, stats
    assert rows(maker) == want
    assert maker.caches.take_stats()["frame_cache"]["hits"] == 1
    assert replay["read"] == cfg.recipe.windows.window_stride + 1 < replay["stored"], replay  # window 0 ends at the next one's first frame


def test_an_entry_is_stored_by_its_owners_commit_of_a_whole_pass(tmp_path):
    """The block that opens a pass stores its entry with ``FramePass.commit``, and only once the
    pass is whole: a commit mid-pass is refused, and leaving the block without one stores nothing
    (counted incomplete); a pass read to its end and committed is stored, once, and the next
    pass replays it whole."""
    from v2v_server.frames.frame_pass import open_frames

    cfg = SampleRecipe(shot_cuts="off", **SMALL)
    src = cached(CLIPS, tmp_path)
    with open_frames(src.source, "bikes.mp4", cfg.decode, cfg.windows, src.frame_cache) as fp:
        next(fp.frames)
        with pytest.raises(RuntimeError, match="reading"):
            fp.commit()
    with pytest.raises(RuntimeError, match="closed"):
        fp.commit()
    stats = src.take_stats()["frame_cache"]
    assert _entries(tmp_path) == [] and stats["stored"] == 0 and stats["not_stored"]["incomplete"] == 1, stats
    with open_frames(src.source, "bikes.mp4", cfg.decode, cfg.windows, src.frame_cache) as fp:
        n = sum(1 for _ in fp.frames)
        assert fp.storing and _entries(tmp_path) == []  # whole, not yet stored
        fp.commit()
        assert not fp.storing and fp.writer.outcome == "stored"
        with pytest.raises(RuntimeError, match="committed"):
            fp.commit()
    assert len(_entries(tmp_path)) == 1 and src.take_stats()["frame_cache"]["stored"] == 1
    with open_frames(src.source, "bikes.mp4", cfg.decode, cfg.windows, src.frame_cache) as fp:
        assert fp.cached and sum(1 for _ in fp.frames) == n == cfg.windows.frame_limit(fp.declared)


def test_tar_member_entries_follow_their_shard(tmp_path):
    """Tar shards: a member's entry records its shard's identity and its offset; rewriting the
    shard is a miss."""
    import tarfile

    shard = tmp_path / "corpus" / "s.tar"
    shard.parent.mkdir()
    with tarfile.open(shard, "w") as t:
        t.add(CLIPS / "bikes.mp4", arcname="a.mp4")
    _settle()
    cfg = SampleRecipe(**SMALL)
    src = cached(shard.parent, tmp_path / "cache")
    want = _samples(cfg, shard.parent, "s.tar/a.mp4")
    assert _samples(cfg, src, "s.tar/a.mp4") == want and _samples(cfg, src, "s.tar/a.mp4") == want
    assert src.take_stats()["frame_cache"]["hits"] == 1
    with tarfile.open(shard, "w") as t:  # the same member name, other content
        t.add(CLIPS / "webvid_like_596x336.mp4", arcname="a.mp4")
    _settle()
    # the same source object: its index of the shard follows the shard's identity
    assert _samples(cfg, src, "s.tar/a.mp4") == _samples(cfg, shard.parent, "s.tar/a.mp4")
    assert src.take_stats()["frame_cache"]["misses"]["changed"] == 1


def test_warm_cache_then_check(tmp_path):
    """``v2v-serve --warm-cache`` stores every video, a second run finds them cached, and
    ``--check`` reports the cache."""
    args = [sys.executable, "-m", "v2v_server.cli", "--workers", "2", "--cache-dir", str(tmp_path),
            "--sequence-length", "8"]
    r = subprocess.run(args + ["--warm-cache"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "needs a frame cache" in r.stderr
    args += ["--frame-cache-gb", "1"]
    r = subprocess.run(args + ["--warm-cache"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and "4 stored" in r.stdout and "0 not stored" in r.stdout, r.stdout + r.stderr
    r = subprocess.run(args + ["--warm-cache"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and "4 already cached" in r.stdout, r.stdout + r.stderr
    r = subprocess.run(args + ["--check"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and "4 entries" in r.stdout and "4 of 4 videos cached (100%)" in r.stdout, r.stdout
    entry = max(_entries(tmp_path), key=lambda p: p.stat().st_size)
    os.truncate(entry, 100)
    r = subprocess.run(args + ["--check"], capture_output=True, text=True, timeout=300)
    assert "3 of 4 videos cached (75%), misses: corrupt 1" in r.stdout, r.stdout


def test_warm_cache_in_one_process_reads_through_the_callers_source(tmp_path, monkeypatch):
    """With one worker the warm-up reads every video through the source it is given (never
    rebuilt from its spec), each video's state from that video's counters alone."""
    from v2v_server.ops import warm
    from v2v_server.sources import source_spec

    cfg = ServeConfig(**SMALL, workers=1)
    src = cached(CLIPS, tmp_path)
    videos = ["bikes.mp4", "webvid_like_596x336.mp4"]

    def built(spec):
        raise AssertionError("the source was built again")

    monkeypatch.setattr(source_spec, "source_from_spec", built)
    first = warm.warm_cache(cfg, src.source, src.caches, videos)
    assert [r["state"] for r in first] == ["stored", "stored"] and all(r["frames"] > 0 for r in first), first
    again = warm.warm_cache(cfg, src.source, src.caches, videos)
    assert [r["state"] for r in again] == ["cached", "cached"], again
    assert [r["frames"] for r in again] == [r["frames"] for r in first]


def test_warm_states_come_from_the_pass_itself(tmp_path):
    """A warm-up's state and bytes are what became of the entry its own pass wrote
    (``EntryWriter.outcome``) or replayed (``FramePass.damaged``): stored with its bytes, cached,
    a damaged entry not cached (removed and the rest decoded), over the budget not stored."""
    from v2v_server.ops.warm import warm_video

    cfg = ServeConfig(**SMALL, workers=1)
    src = cached(CLIPS, tmp_path / "big")
    stored = warm_video(cfg, src.source, "bikes.mp4", src.caches)
    entry, = _entries(tmp_path / "big")
    assert stored["state"] == "stored" and 0 < stored["bytes"] <= entry.stat().st_size, stored
    assert warm_video(cfg, src.source, "bikes.mp4", src.caches) == dict(stored, state="cached", bytes=0)
    with open(entry, "r+b") as f:  # a flipped bit in the first frame: the trailer holds, the frame fails its sum
        f.seek(64)
        byte = f.read(1)
        f.seek(64)
        f.write(bytes([byte[0] ^ 1]))
    damaged = warm_video(cfg, src.source, "bikes.mp4", src.caches)
    assert damaged["state"].startswith("not stored") and damaged["frames"] == stored["frames"], damaged
    assert _entries(tmp_path / "big") == []  # removed; the rest decoded, not stored
    tiny = cached(CLIPS, tmp_path / "tiny", gb=1e-6)
    assert warm_video(cfg, tiny.source, "bikes.mp4", tiny.caches)["state"] == "not stored: budget"


def test_frame_cache_gauges_and_status_line_from_worker_counters():
    """The server's frame-cache gauges, hit ratio and status line, from the counters workers
    report (malformed ones ignored)."""
    from prometheus_client.exposition import generate_latest

    from v2v_server.ops.metrics import ServerMetrics
    from v2v_wire.worker_messages import Done

    m = ServerMetrics(progress=False)
    assert m.frame_cache_state(0, 0, 1 << 30)["frame_cache_hit_ratio"] == 0.0
    for fc in ({"hits": 3, "misses": {"absent": 1, "corrupt": 1}, "stored": 1},
               {"hits": 2, "misses": {"changed": 1, "absent": -4}},
               {"hits": True, "misses": "none"}):
        m.on_worker_message(Done(1, store={"frame_cache": fc}))
    state = m.frame_cache_state(3 << 29, 2, 1 << 30)
    assert state == {"frame_cache_bytes": 3 << 29, "frame_cache_entries": 2, "frame_cache_budget": 1 << 30,
                     "frame_cache_hit_ratio": 5 / 8}
    assert m.frame_cache_line(3 << 29, 2, 1 << 30) == (
        "5 hit(s), misses absent 1, changed 1, corrupt 1, unverified 0 (62% hits), 2 entries, 1.50 of 1.00 GiB")
    page = generate_latest(m.registry).decode()
    assert "v2v_frame_cache_hits_total 5.0" in page and 'v2v_frame_cache_misses_total{cause="corrupt"} 1.0' in page

"""The corpus index (``v2v_server.frames.corpus_index``): ``--check`` and the Ray engine's scan
answer a video from it while its identity holds, decode it again when it changes, and the file
is plain SQLite a user can query."""
from __future__ import annotations

import json
import logging
import os
import shutil
import sqlite3
import time

import pytest

from v2v_server.ops.config import ServeConfig
from v2v_server.frames.check import check_corpus, check_video
from v2v_server.frames.corpus_index import INDEX_FILE, CorpusIndex, Verdict, layout_key
from v2v_server.frames.host_caches import HostCaches
from v2v_server.sources.local import RACY_NS, LocalSource
from v2v_server.frames.window_pass import StreamFacts


class CountingSource(LocalSource):
    """A folder source that counts the videos it opens (each open is a decode pass)."""

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.opened: list = []

    def open(self, rel):
        self.opened.append(rel)
        return super().open(rel)


def settle() -> None:
    """Wait out the racy window: a file written just now has no identity the index trusts."""
    time.sleep(2 * RACY_NS / 1e9)


@pytest.fixture
def corpus(tmp_path, videos):
    d = tmp_path / "corpus"
    d.mkdir()
    for name in ("bbb_camera_596x336.mp4", "bikes.mp4", "bigbuckbunny.mp4"):
        shutil.copyfile(videos / name, d / name)
    settle()
    return d


RECIPE = ServeConfig(sequence_length=8).recipe  # 41-frame windows: every clip gives some
WINDOWS = (RECIPE.windows, RECIPE.decode)  # what a pass reads: check_video's and layout_key's first arguments


def test_a_second_check_answers_from_the_index_without_opening_a_video(corpus, tmp_path):
    cache = tmp_path / "cache"
    names = sorted(p.name for p in corpus.iterdir())
    first_src = CountingSource(corpus)
    first = check_corpus(*WINDOWS, first_src, names, caches=HostCaches(str(cache)))
    assert sorted(first_src.opened) == names and all(r.usable for r in first)
    again_src = CountingSource(corpus)  # another process, the same host
    again = check_corpus(*WINDOWS, again_src, names, caches=HostCaches(str(cache)))
    assert again_src.opened == [] and again == first
    # the file is plain SQLite: one row per video under this layout, with the verdict's facts
    with sqlite3.connect(cache / INDEX_FILE) as db:
        rows = db.execute("SELECT location, windows, frames, width, height, codec, cuts FROM entries "
                          "WHERE layout = ? ORDER BY location", (layout_key(*WINDOWS),)).fetchall()
    assert [os.path.basename(r[0]) for r in rows] == names
    for r, c in zip(rows, sorted(first, key=lambda c: c.path)):
        assert (r[1], r[2]) == (c.windows, c.frames) and (r[3], r[4], r[5]) == (c.stream.width, c.stream.height,
                                                                                c.stream.codec)
        assert json.loads(r[6]) == list(c.cuts)


def test_a_rewritten_video_or_another_layout_is_read_again(corpus, tmp_path, videos):
    cache = tmp_path / "cache"
    src, caches = CountingSource(corpus), HostCaches(str(cache))
    before = check_video(*WINDOWS, src, "bikes.mp4", caches)
    shutil.copyfile(videos / "bbb_camera_596x336.mp4", corpus / "bikes.mp4")  # same name, other content
    settle()
    after = check_video(*WINDOWS, src, "bikes.mp4", caches)
    assert src.opened == ["bikes.mp4", "bikes.mp4"]
    assert (after.frames, after.cuts) != (before.frames, before.cuts)
    assert after == check_video(*WINDOWS, src, "bikes.mp4", caches) and len(src.opened) == 2  # the new entry holds
    other = ServeConfig(sequence_length=4).recipe
    assert layout_key(other.windows, other.decode) != layout_key(*WINDOWS)
    check_video(other.windows, other.decode, src, "bikes.mp4", caches)
    assert len(src.opened) == 3 and len(CorpusIndex(cache / INDEX_FILE)) == 2


#: A verdict as ``--check`` makes it, for the index's own tests.
VERDICT = Verdict(path="a.mp4", usable=True, windows=2, frames=401, reason="", cause="", cuts=(30, 76), dropped=0,
                  stream=StreamFacts(width=64, height=48, codec="h264", pix_fmt="yuv420p", fps=25.0),
                  failed_windows=(1,), more=True)


def test_an_identity_that_cannot_vouch_is_neither_recorded_nor_answered(tmp_path):
    """A video without an identity (changed within the timestamp resolution of now, an object
    without a version tag: ``VideoSource.identity`` None) is decoded every time, as the frame
    cache does; an entry answers only the identity it was made from."""
    index = CorpusIndex(tmp_path / INDEX_FILE)
    verdict = VERDICT
    assert not index.record("/c/a.mp4", None, "L", verdict) and len(index) == 0
    assert index.record("/c/a.mp4", "file 1 2 3 4", "L", verdict) and len(index) == 1
    assert index.lookup("/c/a.mp4", None, "L") is None
    assert index.lookup("/c/a.mp4", "file 1 2 3 5", "L") is None  # changed since
    assert index.lookup("/c/a.mp4", "file 1 2 3 4", "M") is None  # another layout
    assert index.lookup("/c/a.mp4", "file 1 2 3 4", "L") == verdict


def test_a_stored_verdict_reads_back_as_the_record_it_was(tmp_path):
    """The ``result`` column holds the verdict's fields as JSON and reads back as the same frozen
    record (tuples, stream facts); a key it does not name (a printed size) is left aside, and a
    field of another type is the index's fault, naming the entry and the field."""
    index = CorpusIndex(tmp_path / INDEX_FILE)
    assert index.record("/c/a.mp4", "id", "L", VERDICT)
    assert index.lookup("/c/a.mp4", "id", "L") == VERDICT
    with sqlite3.connect(tmp_path / INDEX_FILE) as db:
        result = json.loads(db.execute("SELECT result FROM entries").fetchone()[0])
        assert result["stream"] == {"width": 64, "height": 48, "codec": "h264", "pix_fmt": "yuv420p", "fps": 25.0}
        assert result["cuts"] == [30, 76] and "size" not in result
        db.execute("UPDATE entries SET result = ?", (json.dumps({**result, "size": "64x48 h264 yuv420p 25 fps"}),))
    assert index.lookup("/c/a.mp4", "id", "L") == VERDICT
    with sqlite3.connect(tmp_path / INDEX_FILE) as db:
        db.execute("UPDATE entries SET result = ?", (json.dumps({**result, "cuts": ["30"]}),))
    assert index.lookup("/c/a.mp4", "id", "L") is None
    assert "the entry of /c/a.mp4 holds cuts ['30'] in its result" in index.fault


@pytest.mark.parametrize("version", ["2", "3"])
def test_an_index_whose_table_has_other_columns_is_made_anew(tmp_path, version):
    """A file whose ``entries`` table was made with other columns (here without ``cause``), of
    another version or of this one, is started afresh at open: its table made anew, its rows
    gone, and the index serves (no fault, an entry kept and answered)."""
    path = tmp_path / INDEX_FILE
    with sqlite3.connect(path) as db:
        db.execute("CREATE TABLE entries (location TEXT NOT NULL, layout TEXT NOT NULL, identity TEXT NOT NULL, "
                   "frames INTEGER NOT NULL, windows INTEGER NOT NULL, usable INTEGER NOT NULL, reason TEXT NOT NULL, "
                   "cuts TEXT NOT NULL, width INTEGER, height INTEGER, codec TEXT, fps REAL, result TEXT NOT NULL, "
                   "written_at REAL NOT NULL, PRIMARY KEY (location, layout))")
        db.execute("INSERT INTO entries VALUES ('/c/b.mp4', 'L', 'id', 1, 1, 1, '', '[]', 1, 1, 'h264', 25.0, '{}', 0)")
        db.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
        db.execute("INSERT INTO meta VALUES ('version', ?)", (version,))
    db.close()
    index = CorpusIndex(path)
    assert index.fault is None and len(index) == 0
    assert index.record("/c/a.mp4", "id", "L", VERDICT) and index.lookup("/c/a.mp4", "id", "L") == VERDICT
    assert index.fault is None


def test_an_unreadable_index_is_one_warning_and_the_check_goes_on(corpus, tmp_path, caplog):
    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / INDEX_FILE).write_bytes(b"this is not an SQLite file" * 100)
    src = CountingSource(corpus)
    with caplog.at_level(logging.WARNING, logger="v2v"):
        results = check_corpus(*WINDOWS, src, ["bikes.mp4", "bbb_camera_596x336.mp4"], caches=HostCaches(str(cache)))
    assert all(r.usable for r in results) and len(src.opened) == 2
    lines = [r.getMessage() for r in caplog.records if "corpus index" in r.getMessage()]
    assert len(lines) == 1 and str(cache / INDEX_FILE) in lines[0], lines


def test_the_ray_scan_counts_windows_from_the_index(corpus, tmp_path):
    """``ray_data.scan_corpus_windows`` under ``shot_cuts: avoid`` (it decodes to find the cuts)
    records each video, and a second scan with the same ``cache_dir`` takes the counts from the
    index: an entry edited in the file is what the second scan reports."""
    from v2v_server.ray_data import scan_corpus_windows

    cfg = ServeConfig(sequence_length=8, cache_dir=str(tmp_path / "cache"))
    first = scan_corpus_windows(corpus, cfg)
    assert first.windows == {r.path: r.windows for r in check_corpus(cfg.recipe.windows, cfg.recipe.decode,
                                                                           LocalSource(corpus),
                                                                           sorted(first.windows))}
    with sqlite3.connect(tmp_path / "cache" / INDEX_FILE) as db:
        loc = str(corpus / "bikes.mp4")
        result = json.loads(db.execute("SELECT result FROM entries WHERE location = ?", (loc,)).fetchone()[0])
        db.execute("UPDATE entries SET result = ? WHERE location = ?", (json.dumps({**result, "windows": 7}), loc))
    assert scan_corpus_windows(corpus, cfg).windows == {**first.windows, "bikes.mp4": 7}


@pytest.mark.parametrize("recipe", [(), ("--crops-per-window", "2"),
                                    ("--crops-per-window", "3", "--shot-cuts", "off", "--static-windows", "skip")],
                         ids=["one-crop", "two-crops", "three-crops-no-cuts-static-skipped"])
def test_the_server_starts_from_the_index_knowing_its_epoch_and_opening_no_empty_video(corpus, tmp_path, recipe):
    """After a pass that filled the index (``--check``), a server of the same layout knows an
    epoch's size at start (its log; the ``v2v_epoch_samples`` gauge) and never opens the
    videos the index knows to give no window; one epoch delivers exactly that many samples,
    the number ``--check`` printed: ``crops_per_window`` samples a window, whatever the recipe."""
    import subprocess
    import sys

    from harness.serve import ServeProcess
    from v2v_client import V2VStreamDataset

    layout = ["--crop-size", "64", "--max-samples-per-video", "2", "--flow-preset", "ultrafast", "--seed", "3",
              "--cache-dir", str(tmp_path / "cache"), *recipe]
    r = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--check", "--videos", str(corpus), *layout],
                       capture_output=True, text=True, timeout=300)
    summary = r.stdout.splitlines()[-1]
    empty = [line.split()[0] for line in r.stdout.splitlines() if " unusable " in line]
    samples = int(summary.split(", ")[1].split()[0])
    windows = sum(int(line.split()[1]) for line in r.stdout.splitlines()[1:-1] if line.split()[2] == "window(s)")
    assert r.returncode == 0 and samples > 0, r.stdout
    assert samples == windows * (int(recipe[1]) if recipe else 1), r.stdout
    assert empty, r.stdout  # the 201-frame windows: bigbuckbunny.mp4 (132 frames) gives none
    with ServeProcess(["--videos", str(corpus), "--workers", "1", "--batch-size", "1",
                       "--log-level", "info", *layout]) as srv:
        ids = [sid for b in V2VStreamDataset(srv.endpoint, 1, outputs=("voxels",), timeout_s=120)
               for sid, pad in zip(b["sample_ids"], b["padding"]) if not pad]
    log = srv.log
    assert len(ids) == len(set(ids)) == samples
    assert f"{len(empty)} video(s) not opened: the corpus index" in log
    assert f"3 video(s) (3 counted: {samples} samples per epoch)" in log  # the plan's size, known at start
    for name in empty:  # named once, from the index: a read would have named it again, without the remark
        lines = [ln for ln in log.splitlines() if f"{corpus / name}:" in ln]
        assert len(lines) == 1 and "skipped" in lines[0] and "(known from the corpus index: not opened)" in lines[0]


def test_the_ray_count_of_an_epoch_is_the_samples_it_lists(corpus, tmp_path):
    """With ``crops_per_window`` 2 the Ray engine's ``samples_per_epoch`` (its log, Ray Train's
    epoch sizes) is the rows ``epoch_descriptors`` lists and ``--check``'s count."""
    import subprocess
    import sys

    from v2v_server.ray_data import epoch_descriptors, scan_corpus_windows

    cfg = ServeConfig(sequence_length=8, crops_per_window=2, cache_dir=str(tmp_path / "cache"))
    rc = scan_corpus_windows(corpus, cfg)
    rows = sum(len(json.loads(d["entries"])) for d in epoch_descriptors(rc, 0, crops_per_window=2))
    r = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--check", "--videos", str(corpus),
                        "--sequence-length", "8", "--crops-per-window", "2", "--cache-dir", str(tmp_path / "cache")],
                       capture_output=True, text=True, timeout=300)
    assert rc.samples_per_epoch == rows == 2 * sum(rc.windows.values()) > 0
    assert f", {rows} sample(s) per epoch ({rows // 2} window(s) x 2 crops);" in r.stdout, r.stdout


def test_the_epoch_size_known_at_start_is_a_gauge():
    from v2v_server.ops.metrics import ServerMetrics

    m = ServerMetrics(progress=False)
    m.set_state(epoch_samples=None)
    assert b"v2v_epoch_samples 0.0" in m.exposition(now=0.0)  # not known
    m.set_state(epoch_samples=1234)
    assert b"v2v_epoch_samples 1234.0" in m.exposition(now=100.0)


def test_a_served_epoch_or_a_warm_up_fills_the_index_for_the_next_start(corpus, tmp_path):
    """The first pass that learns a video writes its entry: one epoch served (no ``--check``)
    or ``--warm-cache``; the next server start then knows the epoch's size and opens no video
    known to give none. Such an entry lacks ``--check``'s frame timing, so ``--check`` decodes
    the video again and its verdicts equal a check's on a fresh index."""
    import subprocess
    import sys

    from harness.serve import ServeProcess
    from v2v_client import V2VStreamDataset

    layout = ["--crop-size", "64", "--max-samples-per-video", "2", "--flow-preset", "ultrafast", "--seed", "3"]

    def epoch(cache):
        with ServeProcess(["--videos", str(corpus), "--workers", "1", "--batch-size", "1",
                           "--log-level", "info", "--cache-dir", str(cache), *layout]) as srv:
            ids = [sid for b in V2VStreamDataset(srv.endpoint, 1, outputs=("voxels",), timeout_s=120)
                   for sid, pad in zip(b["sample_ids"], b["padding"]) if not pad]
        return ids, srv.log

    def check(cache, *extra):
        return subprocess.run([sys.executable, "-m", "v2v_server.cli", "--videos", str(corpus), *layout,
                               "--cache-dir", str(cache), *extra], capture_output=True, text=True, timeout=300)

    ids, log = epoch(tmp_path / "a")
    assert "corpus index" not in log  # nothing known at the first start
    with sqlite3.connect(tmp_path / "a" / INDEX_FILE) as db:
        rows = db.execute("SELECT location, windows, result FROM entries").fetchall()
    assert len(rows) == 3 and sum(r[1] for r in rows) == len(ids) > 0
    assert all(json.loads(r[2])["frame_timing"] is False for r in rows)
    again, log = epoch(tmp_path / "a")
    empty = [os.path.basename(r[0]) for r in rows if r[1] == 0]
    assert sorted(again) == sorted(ids) and empty
    assert f"3 video(s) (3 counted: {len(ids)} samples per epoch)" in log and f"{len(empty)} video(s) not opened" in log
    # --check answers a sample pass's entries by decoding (its own timing), as on a fresh index
    assert check(tmp_path / "a", "--check").stdout == check(tmp_path / "fresh", "--check").stdout
    # --warm-cache writes the entries too
    r = check(tmp_path / "w", "--warm-cache", "--frame-cache-gb", "1")
    assert r.returncode == 0, r.stderr
    with sqlite3.connect(tmp_path / "w" / INDEX_FILE) as db:
        assert sorted(db.execute("SELECT location, windows FROM entries")) == sorted((r[0], r[1]) for r in rows)


# ---------------------------------------------------------------- faults of an index that opens
# The index is a cache: a damaged, read-only or locked file, or an entry holding a value v2v
# never writes, is one warning naming the file and the fault; the verdicts and samples are
# those of a run without it, and no command ends in a traceback.

CHECK = ["--sequence-length", "8", "--workers", "2"]  # two processes: the fault is still named once


def _check(corpus, cache, *extra):
    import subprocess
    import sys

    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--check", "--videos", str(corpus), *CHECK,
                        "--cache-dir", str(cache), *extra], capture_output=True, text=True, timeout=300)
    return r, time.monotonic() - t0


def _filled(corpus, tmp_path):
    """A cache folder whose index knows the corpus (a --check ran), its file checkpointed (every
    entry in the main file, no WAL), and the fresh check's output."""
    cache = tmp_path / "cache"
    r, _ = _check(corpus, cache)
    assert r.returncode == 0 and "corpus index" not in r.stderr, r.stderr
    with sqlite3.connect(cache / INDEX_FILE) as db:
        db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        assert db.execute("SELECT COUNT(*) FROM entries").fetchone()[0] == 3
    return cache, r.stdout


def _garble_entries(path) -> None:
    """Overwrite the pages of the ``entries`` table and its key with bytes no B-tree page holds,
    leaving the schema and ``meta`` pages whole: the file opens, then a read of an entry fails."""
    with sqlite3.connect(path) as db:
        size = db.execute("PRAGMA page_size").fetchone()[0]
        roots = [r for (r,) in db.execute("SELECT rootpage FROM sqlite_master WHERE tbl_name = 'entries'")]
    assert len(roots) == 2
    with open(path, "r+b") as f:
        for page in roots:
            f.seek((page - 1) * size)
            f.write(b"\xde\xad\xbe\xef" * (size // 4))


def _one_warning(stderr: str, path, words: str) -> None:
    lines = [ln for ln in stderr.splitlines() if "corpus index" in ln]
    assert len(lines) == 1 and f"corpus index {path}: " in lines[0] and words in lines[0], stderr
    assert "Traceback" not in stderr


def test_a_damaged_index_is_one_warning_and_the_check_answers_as_without_it(corpus, tmp_path):
    cache, fresh = _filled(corpus, tmp_path)
    _garble_entries(cache / INDEX_FILE)
    r, _ = _check(corpus, cache)
    assert r.returncode == 0 and r.stdout == fresh
    _one_warning(r.stderr, cache / INDEX_FILE, "database disk image is malformed (the file is damaged")


def test_an_entry_holding_what_v2v_never_writes_is_one_warning(corpus, tmp_path):
    cache, fresh = _filled(corpus, tmp_path)
    with sqlite3.connect(cache / INDEX_FILE) as db:
        db.execute("UPDATE entries SET result = ? WHERE location = ?",
                   (json.dumps({"usable": True, "windows": "many"}), str(corpus / "bikes.mp4")))
    r, _ = _check(corpus, cache)
    assert r.returncode == 0 and r.stdout == fresh
    _one_warning(r.stderr, cache / INDEX_FILE, f"the entry of {corpus / 'bikes.mp4'} holds windows 'many'")


def test_a_locked_index_is_one_warning_after_one_wait_not_one_per_video(corpus, tmp_path):
    """Another process holds the write lock (a ``sqlite3`` shell inside ``BEGIN EXCLUSIVE``): the
    first write (at open) waits ``BUSY_TIMEOUT_S`` once, then the index is off; without the
    guard each video's entry waited 30 s and the check died with ``database is locked``."""
    from v2v_server.frames.corpus_index import BUSY_TIMEOUT_S

    cache = tmp_path / "cache"
    cache.mkdir()
    holder = sqlite3.connect(cache / INDEX_FILE, isolation_level=None)
    try:
        holder.execute("CREATE TABLE other (x)")
        holder.execute("BEGIN EXCLUSIVE")
        holder.execute("INSERT INTO other VALUES (1)")
        r, took = _check(corpus, cache)
        fresh, _ = _check(corpus, tmp_path / "fresh")
    finally:
        holder.close()
    assert r.returncode == 0 and r.stdout == fresh.stdout
    _one_warning(r.stderr, cache / INDEX_FILE, "database is locked (another process holds its lock)")
    assert took < 3 * 30, took  # three videos: one wait of BUSY_TIMEOUT_S, not a 30 s wait per video
    assert BUSY_TIMEOUT_S < 30


def _read_only(path):
    """Make the file ``path`` read-only for this process: its mode as a user; as root, whom
    modes do not stop, the immutable attribute (``chattr +i``, ext4 and most local file
    systems). Returns the undo, or skips naming why neither holds."""
    import subprocess

    if os.geteuid() != 0:
        os.chmod(path, 0o444)
        return lambda: os.chmod(path, 0o644)
    r = subprocess.run(["chattr", "+i", str(path)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"running as root, where a file's mode does not stop a write, and chattr +i fails here "
                    f"({r.stderr.strip() or r.returncode}): no read-only file to test with")
    return lambda: subprocess.run(["chattr", "-i", str(path)], check=True)


def test_a_read_only_index_is_one_warning_and_the_check_goes_on(corpus, tmp_path):
    """Written by another user (or on a read-only file system): it is read-only here, and a check
    under another layout must write. One warning, the verdicts of a check without it."""
    cache, _ = _filled(corpus, tmp_path)
    undo = _read_only(cache / INDEX_FILE)
    try:
        r, _ = _check(corpus, cache, "--sequence-length", "6")
    finally:
        undo()
    fresh, _ = _check(corpus, tmp_path / "fresh", "--sequence-length", "6")
    assert r.returncode == 0 and r.stdout == fresh.stdout
    _one_warning(r.stderr, cache / INDEX_FILE, "attempt to write a readonly database (it cannot be written")


def test_after_a_fault_every_method_answers_as_an_empty_index(tmp_path, caplog):
    """``lookup``, ``windows`` and ``record`` meet the fault of one entry (a non-integer
    ``windows``); from then on the index is off in this process: nothing is answered, nothing
    kept, one warning."""
    index = CorpusIndex(tmp_path / INDEX_FILE)
    verdict = VERDICT
    for loc in ("/c/a.mp4", "/c/b.mp4"):
        assert index.record(loc, "id", "L", verdict)
    with sqlite3.connect(tmp_path / INDEX_FILE) as db:
        db.execute("UPDATE entries SET windows = '2.5x' WHERE location = '/c/b.mp4'")
    with caplog.at_level(logging.WARNING, logger="v2v"):
        got = list(index.windows([("a", "/c/a.mp4", "id"), ("b", "/c/b.mp4", "id")], "L"))
        assert got == [] and index.fault is not None
        assert "holds windows '2.5x', not a count" in index.fault
        assert index.lookup("/c/a.mp4", "id", "L") is None and not index.record("/c/c.mp4", "id", "L", verdict)
        assert list(index.windows([("a", "/c/a.mp4", "id")], "L")) == [] and len(index) == 0
    lines = [r.getMessage() for r in caplog.records if "corpus index" in r.getMessage()]
    assert len(lines) == 1 and str(tmp_path / INDEX_FILE) in lines[0], lines


@pytest.mark.parametrize("fault", ["windows-value", "locked"])
def test_a_server_starting_on_a_faulty_index_serves_the_whole_epoch(corpus, tmp_path, fault):
    """``v2v-serve`` reads the index at start (``known_windows``) and its workers write to it: a
    ``windows`` value v2v never writes, or a lock another process holds, is one warning, the
    epoch's size is then unknown (not a wrong one) and every sample is served."""
    from harness.serve import ServeProcess
    from v2v_client import V2VStreamDataset

    layout = ["--crop-size", "64", "--max-samples-per-video", "2", "--flow-preset", "ultrafast", "--seed", "3",
              "--sequence-length", "8"]
    cache = tmp_path / "cache"
    r, _ = _check(corpus, cache, *layout)
    samples = int(r.stdout.splitlines()[-1].split(", ")[1].split()[0])
    holder = sqlite3.connect(cache / INDEX_FILE, isolation_level=None)
    if fault == "windows-value":
        holder.execute("UPDATE entries SET windows = 'two' WHERE location = ?", (str(corpus / "bikes.mp4"),))
        words = f"the entry of {corpus / 'bikes.mp4'} holds windows 'two', not a count"
    else:
        holder.execute("BEGIN EXCLUSIVE")
        holder.execute("DELETE FROM entries")  # not committed: the server would read the entries, and cannot
        words = "database is locked (another process holds its lock)"
    try:
        with ServeProcess(["--videos", str(corpus), "--workers", "1", "--batch-size", "1",
                           "--log-level", "info", "--cache-dir", str(cache), *layout]) as srv:
            ids = [sid for b in V2VStreamDataset(srv.endpoint, 1, outputs=("voxels",), timeout_s=120)
                   for sid, pad in zip(b["sample_ids"], b["padding"]) if not pad]
    finally:
        holder.close()
    assert len(ids) == len(set(ids)) == samples > 0
    _one_warning(srv.log, cache / INDEX_FILE, words)
    assert "unknown yet samples per epoch)" in srv.log, srv.log


def _write_ntsc(path, frames: int) -> None:
    """A clip of ``frames`` 64x48 frames at 30000/1001 Hz (NTSC's 29.97)."""
    import av
    import numpy as np
    from fractions import Fraction

    with av.open(str(path), "w") as c:
        s = c.add_stream("mpeg4", rate=Fraction(30000, 1001))
        s.width, s.height, s.pix_fmt = 64, 48, "yuv420p"
        for i in range(frames):
            y = np.full((48, 64, 3), 40, np.uint8)
            y[:, (2 * i) % 56:(2 * i) % 56 + 8] = 220
            for p in s.encode(av.VideoFrame.from_ndarray(y, format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)


def test_the_index_keeps_typed_stream_facts_and_the_exact_frame_rate(tmp_path):
    """A row's size, codec and frame rate come from the verdict's typed ``stream``: 29.97 Hz
    stays 30000/1001 (printed as 30 by ``--check``), and a clip too short for a
    window has the cause ``short``, the code the server logs it by."""
    d = tmp_path / "corpus"
    d.mkdir()
    _write_ntsc(d / "ntsc.mp4", 60)
    _write_ntsc(d / "short.mp4", 10)
    settle()
    cache = tmp_path / "cache"
    src, caches = LocalSource(d), HostCaches(str(cache))
    ntsc, short = (check_video(*WINDOWS, src, name, caches) for name in ("ntsc.mp4", "short.mp4"))
    assert ntsc.stream.text() == "64x48 mpeg4 yuv420p 30 fps" and ntsc.stream.fps == 30000 / 1001
    assert (ntsc.cause, short.cause) == ("", "short") and not short.usable
    with sqlite3.connect(cache / INDEX_FILE) as db:
        rows = dict((os.path.basename(r[0]), r[1:]) for r in db.execute(
            "SELECT location, width, height, codec, fps, cause FROM entries WHERE layout = ?", (layout_key(*WINDOWS),)))
    assert rows["ntsc.mp4"] == (64, 48, "mpeg4", 30000 / 1001, "")
    assert rows["short.mp4"][3:] == (30000 / 1001, "short")
    again = check_video(*WINDOWS, src, "ntsc.mp4", caches)  # answered from the index: the same typed facts
    assert again.stream == ntsc.stream and again == ntsc

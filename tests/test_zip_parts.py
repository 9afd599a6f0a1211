"""Zip parts (OpenVid-1M's distribution) served in place: stored, deflated and ZIP64 parts and a
part split into ``_partaa`` / ``_partab`` pieces give the samples of the same clips as files;
a folder of parts, one part and a brace range list the same members; a member's frame-cache
identity follows its part (the racy rule included); segments of a member; and each bad part or
member (corrupt or truncated central directory, a piece missing, a member that is not a video,
is corrupt or is missing) named once while the rest is served. The parts in S3:
``tests/test_object_store.py``."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import pytest

from harness.corpus import write_zip_parts
from tests.cached import cached
from tests.store_checks import samples
from tests.test_object_store import CLIPS, LAYOUT, _epoch
from v2v_server.samples.recipe import SampleRecipe
from v2v_server.sources.local import RACY_NS, LocalSource
from v2v_server.sources.source_spec import open_source

EXTS = (".mp4",)
MEMBERS = ["p-0.zip/000000.mp4", "p-0.zip/000001.mp4", "p-1.zip/clips/000000.mp4", "p-2.zip/000000.mp4",
           "p-3.zip/000000.mp4", "p-3.zip/000001.mp4"]


def _settle() -> None:
    """Wait out the racy window of files just written (``local.RACY_NS``)."""
    time.sleep(RACY_NS / 1e9 + 0.02)


@pytest.fixture(scope="module")
def parts(tmp_path_factory):
    if shutil.which("zip") is None:
        pytest.skip("Info-ZIP's zip not installed (it writes the ZIP64 part)")
    tmp = tmp_path_factory.mktemp("zips")
    write_zip_parts(tmp / "parts", tmp / "ref", CLIPS)
    _settle()
    return tmp / "parts", tmp / "ref"


def test_zip_parts_give_the_samples_of_the_same_files(parts):
    folder, ref = parts
    # what makes each part what it is named, read by other tools than ours
    assert b"PK\x06\x06" in (folder / "p-2.zip").read_bytes()  # the ZIP64 end of central directory record
    assert subprocess.run(["zipinfo", "-v", str(folder / "p-2.zip")], capture_output=True,
                          text=True).stdout.count("64-bit sizes") >= 1
    with zipfile.ZipFile(folder / "p-1.zip") as z:
        assert [i.compress_type for i in z.infolist()] == [zipfile.ZIP_DEFLATED]
    assert sorted(p.name for p in folder.iterdir()) == ["p-0.zip", "p-1.zip", "p-2.zip", "p-3_partaa", "p-3_partab",
                                                        "p-3_partac"]
    src = LocalSource(folder)
    videos, rejected = src.list_videos(EXTS)
    assert videos == MEMBERS
    assert rejected == [("p-0.zip/readme.txt", "not a video file (extension '.txt')")]
    cfg = LAYOUT.cfg()
    got = samples(cfg, src, videos, 0)
    assert len(got) == 12 and got == samples(cfg, LocalSource(ref), videos, 0)
    # a brace range of parts, one part, and a part given whole or in pieces list the same members
    assert open_source(str(folder / "p-{0..3}.zip")).list_videos(EXTS) == (videos, rejected)
    assert open_source(str(folder / "p-3.zip")).list_videos(EXTS) == (MEMBERS[4:], [])
    lst = folder.parent / "list.txt"
    lst.write_text("p-3.zip/000001.mp4\np-1.zip\np-0.zip/gone.mp4\n")
    listed = LocalSource(folder, video_list=str(lst)).list_videos(EXTS)
    assert listed == (["p-3.zip/000001.mp4", "p-1.zip/clips/000000.mp4"],
                      [("p-0.zip/gone.mp4", f"listed in {lst} but missing from {folder}")])


def test_a_member_follows_its_part_in_the_frame_cache(tmp_path):
    """A zip member's identity is its part's (each piece's, for a split part) with the member's
    offset, size and CRC-32; it is None while the part is racy; a part rewritten in place
    (same member name, other content) is a frame-cache miss and serves the new content."""
    folder = tmp_path / "c"
    folder.mkdir()

    def write(clip: str) -> None:
        with zipfile.ZipFile(folder / "a.zip", "w", zipfile.ZIP_DEFLATED) as z:
            z.write(CLIPS / clip, "x.mp4")

    write("bikes.mp4")
    src = cached(folder, tmp_path / "cache")
    assert src.source.identity("a.zip/x.mp4") is None  # just written: racy, decoded and not stored
    _settle()
    with zipfile.ZipFile(folder / "a.zip") as z:
        info = z.getinfo("x.mp4")
    ident = src.source.identity("a.zip/x.mp4")
    assert ident.startswith("zip ") and ident.endswith(
        f" member {info.header_offset} {info.file_size} {info.compress_size} {info.CRC} 8 0")
    recipe = SampleRecipe(sequence_length=4, num_bins=2, crop_size=32, max_samples_per_video=2)
    cfg = type("Cfg", (), {"recipe": recipe})

    def plain(clip):
        (tmp_path / "ref" / "a.zip").mkdir(parents=True, exist_ok=True)
        shutil.copy(CLIPS / clip, tmp_path / "ref" / "a.zip" / "x.mp4")
        return samples(cfg, LocalSource(tmp_path / "ref"), ["a.zip/x.mp4"], 0)

    want = plain("bikes.mp4")
    assert samples(cfg, src, ["a.zip/x.mp4"], 0) == want == samples(cfg, src, ["a.zip/x.mp4"], 0)
    assert src.take_stats()["frame_cache"]["hits"] == 1
    write("webvid_like_596x336.mp4")
    _settle()
    assert src.source.identity("a.zip/x.mp4") != ident
    assert samples(cfg, src, ["a.zip/x.mp4"], 0) == plain("webvid_like_596x336.mp4") != want
    assert src.take_stats()["frame_cache"]["misses"]["changed"] == 1
    # a split part: rewriting one piece changes every member's identity
    data = (folder / "a.zip").read_bytes()
    (folder / "a.zip").unlink()
    (folder / "a_partaa").write_bytes(data[:1000])
    (folder / "a_partab").write_bytes(data[1000:])
    _settle()
    split = LocalSource(folder)
    assert split.list_videos(EXTS) == (["a.zip/x.mp4"], [])
    before = split.identity("a.zip/x.mp4")
    assert before.count(" + ") == 1
    (folder / "a_partab").write_bytes(data[1000:])
    _settle()
    assert split.identity("a.zip/x.mp4") != before


def test_segments_of_a_deflated_member(tmp_path):
    """A time range of a deflated member (a seek to the key frame before it, backwards through
    the streaming reader) gives the frames of the same range of the file."""
    from v2v_server.ops.config import ServeConfig
    from v2v_server.frames.frame_pass import open_frames

    clip = "bbb_camera_596x336.mp4"
    with zipfile.ZipFile(tmp_path / "p.zip", "w", zipfile.ZIP_DEFLATED) as z:
        z.write(CLIPS / clip, clip)
    shutil.copy(CLIPS / clip, tmp_path / clip)
    lst = tmp_path / "list.txt"
    lst.write_text(f"p.zip/{clip} 2 6\n{clip} 2 6\n")
    cfg = ServeConfig(sequence_length=8, video_list=str(lst))
    src = LocalSource(tmp_path, video_list=str(lst))
    videos, _ = src.list_videos(EXTS)
    assert videos == [f"p.zip/{clip}#t=2,6", f"{clip}#t=2,6"]

    def frames(video):
        with open_frames(src, video, cfg.recipe.decode, cfg.recipe.windows) as fp:
            return [f.expand(f.codes).tobytes() for f in fp.frames]

    assert frames(videos[0]) == frames(videos[1]) and len(frames(videos[1])) == 100  # 2.00 .. 5.96 s


def _bad_parts(folder: Path) -> None:
    """One good part among parts and members that cannot be served."""
    folder.mkdir()
    with zipfile.ZipFile(folder / "good.zip", "w") as z:
        z.write(CLIPS / "bikes.mp4", "000000.mp4")
        z.writestr("000000.json", "{}")
    good = (folder / "good.zip").read_bytes()
    (folder / "truncated.zip").write_bytes(good[:-30])  # the end record cut short
    cd = good.rfind(b"PK\x01\x02")
    (folder / "corrupt.zip").write_bytes(good[:cd] + b"XX\x01\x02" + good[cd + 4:])  # a central header's signature
    (folder / "gap_partaa").write_bytes(good[:1000])
    (folder / "gap_partac").write_bytes(good[2000:])  # gap_partab missing
    (folder / "cut_partaa").write_bytes(good[:1000])  # its last piece missing
    with zipfile.ZipFile(folder / "members.zip", "w") as z:
        z.writestr("notavideo.mp4", b"this is not a video file\n" * 200)  # fixed: random bytes can probe as audio
    shutil.copy(CLIPS / "bikes.mp4", folder / "clip.mp4")
    subprocess.run(["zip", "-q", "-P", "secret", "encrypted.zip", "clip.mp4"], cwd=folder, check=True)  # Info-ZIP
    (folder / "clip.mp4").unlink()
    with zipfile.ZipFile(folder / "crc.zip", "w", zipfile.ZIP_DEFLATED) as z:
        z.write(CLIPS / "bikes.mp4", "000000.mp4")
    crc = bytearray((folder / "crc.zip").read_bytes())
    crc[len(crc) // 2] ^= 0xFF
    (folder / "crc.zip").write_bytes(bytes(crc))


def test_bad_parts_and_members_are_named_once_and_the_rest_served(tmp_path):
    if shutil.which("zip") is None:
        pytest.skip("Info-ZIP's zip not installed (it writes the encrypted part)")
    folder = tmp_path / "parts"
    _bad_parts(folder)
    _settle()
    r = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--check", "--videos", str(folder),
                        *LAYOUT.args()], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    want = {
        "truncated.zip": "ignored      zip part cannot be read: BadZipFile: File is not a zip file",
        "corrupt.zip": "ignored      zip part cannot be read: BadZipFile: Bad magic number for central directory",
        "gap.zip": "ignored      split zip part: piece gap_partab is missing (found gap_partaa, gap_partac)",
        "cut.zip": "ignored      zip part cannot be read: BadZipFile: File is not a zip file (read as its pieces "
                   "cut_partaa joined: is a later piece missing?)",
        "members.zip/notavideo.mp4": "unusable     cannot open:",
        "crc.zip/000000.mp4": "unusable     cannot open: ZipMemberError: zip member 000000.mp4: corrupt data "
                              "(BadZipFile: Bad CRC-32",
        "good.zip/000000.json": "ignored      not a video file (extension '.json')",
        "encrypted.zip/clip.mp4": "unusable     zip member clip.mp4: encrypted (not served)",
        "good.zip/000000.mp4": "2 window(s)",
    }
    for name, verdict in want.items():
        found = [line for line in lines if line.split()[0] == name]
        assert len(found) == 1 and verdict in found[0], (name, lines)
    assert "1 usable video(s) of 4, 2 sample(s) per epoch" in lines[-1] and "5 other entries ignored" in lines[-1]
    got, log = _epoch(str(folder), "--log-level", "INFO")
    assert sorted(got) == ["good.zip/000000.mp4#0", "good.zip/000000.mp4#1"]
    for name in want:
        if name != "good.zip/000000.mp4":
            assert sum(name in line for line in log.splitlines()) == 1, (name, log)


def test_archives_find_a_split_part_and_read_it_joined(tmp_path):
    """``Archives`` over a folder's primitives: a split part's pieces found in order and read as
    the bytes ``cat`` would join; a gap named; a part that is neither whole nor in pieces missing."""
    import contextlib

    from v2v_server.sources.archive_members import Archives
    from v2v_server.sources.errors import VideoError

    data = os.urandom(10_000)
    for i, piece in enumerate(("x_partaa", "x_partab", "x_partac")):
        (tmp_path / piece).write_bytes(data[i * 4000:(i + 1) * 4000])
    (tmp_path / "y_partaa").write_bytes(b"a")
    (tmp_path / "y_partac").write_bytes(b"c")

    @contextlib.contextmanager
    def open_raw(rel, expected=None):
        with open(tmp_path / rel, "rb") as f:
            yield f

    archives = Archives(str(tmp_path), open_raw, lambda rel: (tmp_path / rel).is_file(),
                        lambda part: os.listdir(tmp_path), lambda archive: None)
    assert archives.pieces("x.zip") == ["x_partaa", "x_partab", "x_partac"]
    with archives.open("x.zip") as f:
        assert f.read() == data
        f.seek(3990)
        assert f.read(20) == data[3990:4010]  # across two pieces
        assert f.seek(-5, os.SEEK_END) == 9995 and f.read() == data[-5:]
    with pytest.raises(VideoError, match=r"piece y_partab is missing \(found y_partaa, y_partac\)"):
        archives.pieces("y.zip")
    with pytest.raises(VideoError, match="missing from"):
        archives.pieces("z.zip")


def test_zip_parts_served_over_zeromq_as_the_files(parts):
    """The server and its worker processes (each building the source from its spec, finding the
    split part's pieces itself) serve the parts' epoch as the files' byte for byte."""
    folder, ref = parts
    from_parts, _ = _epoch(str(folder))
    assert len(from_parts) == 12 and from_parts == _epoch(str(ref))[0]


def test_pairing_a_list_with_archive_members_is_by_id_path_then_file_name():
    from v2v_server.sources.archive_members import pair_members

    members = ["p0.zip/a.mp4", "p0.zip/dir/b.mp4", "p1.zip/c.mp4", "p1.zip/x/d.mp4", "p2.zip/d.mp4", "p2.zip/x/e.mp4",
               "p3.zip/y/f.mp4", "p4.zip/z/f.mp4"]
    entries = ["a.mp4", "b.mp4", "dir/b.mp4", "p1.zip/c.mp4", "a.mp4#t=1,3", "d.mp4", "x/d.mp4", "zz.mp4",
               "dir/zz.mp4", "e.mp4", "a.mp4", "f.mp4", "y/e.mp4"]
    ids, refused = pair_members(entries, members, "L.csv", "P")
    # a bare name by its file name (b.mp4 sits in a folder of its part) unless a member's path
    # is the name (d.mp4), a path by the member's path, an id as it is, a segment keeps its
    # range; duplicates once
    assert ids == ["p0.zip/a.mp4", "p0.zip/dir/b.mp4", "p1.zip/c.mp4", "p0.zip/a.mp4#t=1,3", "p2.zip/d.mp4",
                   "p1.zip/x/d.mp4", "p2.zip/x/e.mp4"]
    assert refused == [
        ("f.mp4", "listed in L.csv: more than one member of P is named so (p3.zip/y/f.mp4, p4.zip/z/f.mp4): "
                  "name one as part.zip/member in the list"),
        ("(3 entries)", "listed in L.csv but no member of P: zz.mp4, dir/zz.mp4, y/e.mp4")]
    many = [f"n{i}.mp4" for i in range(7)]
    assert pair_members(many, members, "L", "P")[1] == [
        ("(7 entries)", "listed in L but no member of P: n0.mp4, n1.mp4, n2.mp4, n3.mp4, n4.mp4, ...")]


def test_openvid_parts_and_their_csv_serve_each_long_clip_of_the_named_member(tmp_path):
    """OpenVid's CSV names clips without their part: given with the parts (a brace range, a
    split part among them), each row is paired with its member, so every long clip's windows
    are served holding that member's frames; the table's short row is skipped unopened, the
    filter drops its row, and the row of a part not downloaded is one line."""
    pytest.importorskip("duckdb")
    from harness.corpus import write_openvid

    layout = write_openvid(tmp_path, CLIPS)
    _settle()
    parts, table = tmp_path / "parts", str(tmp_path / "OpenVid.csv")
    pattern = str(parts / "OpenVid_part{0..2}.zip")
    r = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--check", "--videos", pattern,
                        "--video-list", table, "--video-list-filter", '"motion score" > 0.5', *LAYOUT.args(),
                        "--cache-dir", str(tmp_path / "cache")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    lines = {line.split()[0]: line for line in r.stdout.splitlines()[1:-1]}
    assert sorted(k for k in lines if k in layout) == sorted(layout)
    assert all("window(s)" in lines[k] for k in layout), r.stdout
    assert "1 row(s) of" in r.stdout and "skipped without opening" in r.stdout
    assert f"listed in {table} but no member of the 3 archive(s) given in {parts}/: elsewhere_5.mp4" in r.stdout
    assert "calm_2.mp4" not in r.stdout
    assert f"{len(layout)} usable video(s) of {len(layout)}" in r.stdout
    # given the folder of parts instead (how OpenVid-1M lands on disk), the rows pair with the same members
    assert LocalSource(parts, video_list=table).list_videos(EXTS) == (list(layout), [
        ("(3 entries)", f"listed in {table} but no member of the archives in {parts}: short_9.mp4, calm_2.mp4, "
                        "elsewhere_5.mp4")])
    src = open_source(pattern, video_list=table)
    videos, _ = src.list_videos(EXTS)
    assert videos == list(layout)  # the table's order
    cfg = LAYOUT.cfg()
    got = samples(cfg, src, videos, 0)
    assert len(got) == 2 * len(layout) and got == samples(cfg, LocalSource(tmp_path / "ref"), videos, 0)

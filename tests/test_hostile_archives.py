"""Hostile and careless archives, built byte by byte: zip parts whose central directory points
several entries at one local header or at overlapping bytes (the overlapping "zip bomb"), a
member running into the central directory or past the end of the file (a zip entry of 8 GiB, a
tar shard cut short), an entry whose local header names another member,
two members of one name in a zip part or a tar shard, a sparse tar member (its bytes not in
one piece) and links in a tar shard. Each is refused with one line naming the part and the members and why; the rest of
the part is served, by ``--check``, by the server and from a bucket's listing and manifest."""
from __future__ import annotations

import io
import struct
import subprocess
import sys
import tarfile
import time
import zlib
from pathlib import Path

import pytest

from tests.test_object_store import _source, store  # noqa: F401  (store: the session's SeaweedFS S3 server)
from v2v_server.sources.local import RACY_NS

LAYOUT = ["--sequence-length", "8", "--crop-size", "64", "--max-samples-per-video", "2", "--flow-preset",
          "ultrafast", "--seed", "3"]


class ZipWriter:
    """A zip part written field by field (APPNOTE 4.3.7 local headers, 4.3.12 central-directory
    entries, 4.3.16 the end record), so that its entries may say what no zip tool writes."""

    def __init__(self):
        self.body = bytearray()
        self.entries = []  # central-directory entries, in order

    def local(self, name: str, data: bytes, method: int = 0, size: int = None) -> int:
        """A local header for ``name`` and its (compressed) ``data``; returns its offset."""
        offset = len(self.body)
        self.body += struct.pack("<4s2B4HL2L2H", b"PK\x03\x04", 20, 0, 0x800, method, 0, 0x21,
                                 self.crc(data, method, size), len(data), size or len(data), len(name.encode()), 0)
        self.body += name.encode() + data
        return offset

    @staticmethod
    def crc(data: bytes, method: int, size: int = None) -> int:
        return zlib.crc32(data if method == 0 else zlib.decompress(data, -15))

    def entry(self, name: str, offset: int, crc: int, csize: int, size: int, method: int = 0) -> None:
        """A central-directory entry for ``name`` pointing at the local header at ``offset``; sizes
        of 4 GiB or more go in a ZIP64 extra field (APPNOTE 4.5.3)."""
        extra = b""
        if max(csize, size) >= 0xFFFFFFFF:
            extra = struct.pack("<2H2Q", 1, 16, size, csize)
            csize = size = 0xFFFFFFFF
        self.entries.append(struct.pack("<4s4B4HL2L5H2L", b"PK\x01\x02", 45, 3, 45, 0, 0x800, method, 0, 0x21,
                                        crc, csize, size, len(name.encode()), len(extra), 0, 0, 0, 0o100644 << 16,
                                        offset) + name.encode() + extra)

    def member(self, name: str, data: bytes) -> None:
        """A plain stored member: its local header and its entry."""
        self.entry(name, self.local(name, data), zlib.crc32(data), len(data), len(data))

    def write(self, path: Path) -> None:
        directory = b"".join(self.entries)
        end = struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, len(self.entries), len(self.entries), len(directory),
                          len(self.body), 0)
        path.write_bytes(bytes(self.body) + directory + end)


def _deflated(data: bytes) -> bytes:
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    return c.compress(data) + c.flush()


@pytest.fixture
def hostile(tmp_path, videos):
    """A folder of parts, each with one good member (a real clip) beside what is hostile."""
    good = (videos / "bikes.mp4").read_bytes()
    other = (videos / "bbb_camera_596x336.mp4").read_bytes()
    d = tmp_path / "parts"
    d.mkdir()
    # 1. three entries at one local header: one 16 MiB kernel of zeros, inflated by each
    z = ZipWriter()
    kernel = _deflated(bytes(16 << 20))
    at = z.local("a.mp4", kernel, method=8, size=16 << 20)
    for name in ("a.mp4", "b.mp4", "c.mp4"):
        z.entry(name, at, zlib.crc32(bytes(16 << 20)), len(kernel), 16 << 20, method=8)
    z.member("good.mp4", good)
    z.write(d / "shared.zip")
    # 2. overlapping members: x's stored bytes run over y's header and data (a quoted overlap)
    z = ZipWriter()
    inner = ZipWriter()
    inner.local("y.mp4", good)
    quoted = bytes(inner.body)
    at_x = z.local("x.mp4", quoted)
    at_y = at_x + 30 + len("x.mp4")  # y's header lies inside x's data
    z.entry("x.mp4", at_x, zlib.crc32(quoted), len(quoted), len(quoted))
    z.entry("y.mp4", at_y, zlib.crc32(good), len(good), len(good))
    z.member("good.mp4", good)
    z.write(d / "overlap.zip")
    # 3. an entry whose local header names another member, and one whose bytes run into the directory
    z = ZipWriter()
    z.entry("renamed.mp4", z.local("original.mp4", good), zlib.crc32(good), len(good), len(good))
    z.member("good.mp4", good)
    z.entry("long.mp4", z.local("long.mp4", other[:1000]), zlib.crc32(other), len(other), len(other))
    z.write(d / "lying.zip")
    # 4. two members named clip.mp4 (bikes, then bbb): the last is what unzip leaves on disk
    z = ZipWriter()
    z.member("clip.mp4", good)
    z.member("clip.mp4", other)
    z.write(d / "twice.zip")
    # 5. the same in a tar shard
    with tarfile.open(d / "twice.tar", "w") as tar:
        for data in (good, other):
            info = tarfile.TarInfo("clip.mp4")
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    # 6. a sparse tar member (GNU tar -S: a hole, then a clip), beside a plain one
    work = tmp_path / "sparse"
    work.mkdir()
    with open(work / "hole.mp4", "wb") as f:
        f.truncate(1 << 20)
        f.seek(1 << 20)
        f.write(good)
    (work / "plain.mp4").write_bytes(good)
    subprocess.run(["tar", "-S", "-cf", str(d / "sparse.tar"), "hole.mp4", "plain.mp4"], cwd=work, check=True)
    # 7. a hard link and a symbolic link to a shard's clip: the clip again under two more ids
    with tarfile.open(d / "links.tar", "w") as tar:
        info = tarfile.TarInfo("a.mp4")
        info.size = len(good)
        tar.addfile(info, io.BytesIO(good))
        for name, kind in (("b.mp4", tarfile.LNKTYPE), ("c.mp4", tarfile.SYMTYPE)):
            link = tarfile.TarInfo(name)
            link.type, link.linkname = kind, "a.mp4"
            tar.addfile(link)
    time.sleep(2 * RACY_NS / 1e9)
    return d


def _check(folder: Path, cache: Path, *extra):
    return subprocess.run([sys.executable, "-m", "v2v_server.cli", "--check", "--videos", str(folder), *LAYOUT,
                           "--cache-dir", str(cache), *extra], capture_output=True, text=True, timeout=300)


def _lines(stdout: str) -> dict:
    """--check's table: the first column -> the rest of the line."""
    rows = stdout.splitlines()[1:-1]
    return {r.split()[0]: " ".join(r.split()[1:]) for r in rows}


def test_hostile_zip_entries_are_refused_by_name_and_the_rest_served(hostile, tmp_path):
    r = _check(hostile, tmp_path / "cache")
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    rows = _lines(r.stdout)
    assert rows["shared.zip"].startswith("ignored zip part: members a.mp4, b.mp4, c.mp4 overlap (bytes 0-")
    assert "3 central-directory entries" in rows["shared.zip"] and "unzip -t refuses the part" in rows["shared.zip"]
    assert rows["overlap.zip"].startswith("ignored zip part: members x.mp4, y.mp4 overlap")
    assert rows["lying.zip/renamed.mp4"].startswith("unusable zip member renamed.mp4: the local header at offset 0 "
                                                    "names 'original.mp4', not this member")
    assert rows["lying.zip/long.mp4"].startswith("ignored zip part: its bytes") and "run past the end of the file" in \
        rows["lying.zip/long.mp4"]
    assert not any(k.split("/")[-1] in ("a.mp4", "b.mp4", "c.mp4", "x.mp4", "y.mp4") for k in rows
                   if k.endswith(".mp4") and k.split("/")[0] in ("shared.zip", "overlap.zip")), rows
    for part in ("shared.zip", "overlap.zip", "lying.zip"):  # the rest of each part is served
        assert rows[f"{part}/good.mp4"].startswith("2 window(s)"), rows
    # of two members named clip.mp4 the last (bbb, 596x336) is served, the first is named
    for part in ("twice.zip", "twice.tar"):
        assert rows[f"{part}/clip.mp4"].startswith("2 window(s)") and "596x336" in rows[f"{part}/clip.mp4"], rows
    assert rows["twice.zip"].startswith("ignored zip part: 2 members are named clip.mp4; the last (at offset ")
    assert rows["twice.zip"].endswith("is served, as tar and unzip extract it, the one at offset 0 is not")
    assert rows["twice.tar"].startswith("ignored tar shard: 2 members are named clip.mp4; the last (at offset ")
    # a sparse tar member is not read in place (its bytes are not in one piece); its neighbour is served
    assert rows["sparse.tar/hole.mp4"].startswith("ignored tar shard: a sparse member (tar -S)")
    assert rows["sparse.tar/plain.mp4"].startswith("2 window(s)")
    # links in a shard are not followed: the clip is served once, under its own name
    assert rows["links.tar/a.mp4"].startswith("2 window(s)")
    assert rows["links.tar/b.mp4"].startswith("ignored tar shard: a hard link to a.mp4: not served")
    assert rows["links.tar/c.mp4"].startswith("ignored tar shard: a symbolic link to a.mp4: not served")
    summary = r.stdout.splitlines()[-1]
    assert summary.startswith("7 usable video(s) of 8, 14 sample(s) per epoch") and "8 other entries ignored" in summary


def test_the_server_serves_the_rest_and_logs_each_refusal(hostile, tmp_path):
    from harness.serve import ServeProcess
    from v2v_client import V2VStreamDataset

    with ServeProcess(["--videos", str(hostile), "--workers", "1", "--batch-size", "2",
                       "--cache-dir", str(tmp_path / "cache"), *LAYOUT]) as srv:
        got = [(sid, b["voxels"][i]) for b in V2VStreamDataset(srv.endpoint, 2, outputs=("voxels",), timeout_s=120)
               for i, sid in enumerate(b["sample_ids"]) if not b["padding"][i]]
    ids = [sid for sid, _ in got]
    assert all(v.abs().sum() > 0 for _, v in got)
    videos = {sid.split("#")[0] for sid in ids}
    assert videos == {"shared.zip/good.mp4", "overlap.zip/good.mp4", "lying.zip/good.mp4", "twice.zip/clip.mp4",
                      "twice.tar/clip.mp4", "sparse.tar/plain.mp4", "links.tar/a.mp4"}, videos
    assert len(ids) == len(set(ids)) == 14
    log = srv.log
    assert "Traceback" not in log
    for words in ("shared.zip: zip part: members a.mp4, b.mp4, c.mp4 overlap", "overlap.zip: zip part: members "
                  "x.mp4, y.mp4 overlap", "lying.zip/long.mp4: zip part: its bytes",
                  "twice.zip: zip part: 2 members are named clip.mp4", "twice.tar: tar shard: 2 members are named",
                  "renamed.mp4: the local header at offset 0 names 'original.mp4'",
                  "sparse.tar/hole.mp4: tar shard: a sparse member"):
        assert sum(words in line for line in log.splitlines()) == 1, (words, log)


def test_a_bucket_of_hostile_parts_names_each_refusal_again_from_its_manifest(hostile, tmp_path, store):
    """The parts in S3 (SeaweedFS): the listing names each refusal, and so does a restart that
    reads the manifest instead of the parts' central directories (the refusals travel in its
    header); the members served are those of the folder."""
    store.upload(hostile, "s3://corpus/hostile/")
    first = _source(store, tmp_path, "s3://corpus/hostile/").list_videos((".mp4",))
    again = _source(store, tmp_path, "s3://corpus/hostile/").list_videos((".mp4",))
    folder = _check(hostile, tmp_path / "cache-folder")
    listed = sorted(k for k, v in _lines(folder.stdout).items() if not v.startswith("ignored"))
    assert sorted(first[0]) == sorted(again[0]) == listed
    assert sorted(first[1]) == sorted(again[1])
    named = {where: why for where, why in first[1]}
    assert named["shared.zip"].startswith("zip part: members a.mp4, b.mp4, c.mp4 overlap")
    assert named["overlap.zip"].startswith("zip part: members x.mp4, y.mp4 overlap")
    assert named["lying.zip/long.mp4"].startswith("zip part: its bytes")
    assert named["twice.zip"].startswith("zip part: 2 members are named clip.mp4")
    assert named["twice.tar"].startswith("tar shard: 2 members are named clip.mp4")
    assert named["sparse.tar/hole.mp4"].startswith("tar shard: a sparse member")


def test_names_holding_a_control_character_are_refused_by_name(tmp_path, videos):
    """A newline (or another control character) in a file name, a zip member's or a tar
    member's would end a line of the log, of --check's table and of a trainer's resume hello
    (sample ids travel newline-joined: a resumed trainer would get those samples again): each
    is refused, shown escaped on one line; the other videos are served."""
    good = (videos / "bikes.mp4").read_bytes()
    d = tmp_path / "corpus"
    d.mkdir()
    (d / "plain.mp4").write_bytes(good)
    (d / "two\nlines.mp4").write_bytes(good)
    z = ZipWriter()
    z.member("ok.mp4", good)
    z.member("tab\there.mp4", good)
    z.write(d / "p.zip")
    with tarfile.open(d / "s.tar", "w") as tar:
        for name in ("fine.mp4", "cr\rhere.mp4", "meta\nsilent.json"):
            info = tarfile.TarInfo(name)
            info.size = len(good)
            tar.addfile(info, io.BytesIO(good))
    time.sleep(2 * RACY_NS / 1e9)
    r = _check(d, tmp_path / "cache")
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    rows = _lines(r.stdout)
    assert len(r.stdout.splitlines()) == 8, r.stdout  # header, 3 videos, 3 refusals, summary: one line each
    assert {k for k, v in rows.items() if not v.startswith("ignored")} == {"plain.mp4", "p.zip/ok.mp4",
                                                                         "s.tar/fine.mp4"}
    assert rows["two\\nlines.mp4"] == ("ignored name holds the control character \\n (sample ids travel one per "
                                       "line): rename it")
    assert rows["p.zip/tab\\there.mp4"].startswith("ignored zip part member: name holds the control character \\t")
    assert rows["s.tar/cr\\rhere.mp4"].startswith("ignored tar shard member: name holds the control character \\r")


def test_a_member_whose_sizes_run_past_the_end_loses_only_itself(tmp_path, videos):
    """A size that runs past the end of the file (a lying entry: 8 GiB stored in a small part; a
    tar shard cut short in its last member) is not an overlap of entries: only that member is
    refused, named on one line, and the good member beside it is served. Several entries at one
    local header (the zip-bomb layout) still refuse the part (test above)."""
    good = (videos / "bikes.mp4").read_bytes()
    d = tmp_path / "corpus"
    d.mkdir()
    z = ZipWriter()
    z.entry("big.mp4", z.local("big.mp4", good[:1000]), zlib.crc32(good), 8 << 30, 8 << 30)
    z.member("ok.mp4", good)
    z.write(d / "liar.zip")
    z = ZipWriter()
    z.member("ok.mp4", good)
    z.entry("long.mp4", z.local("long.mp4", good[:1000]), zlib.crc32(good), len(good), len(good))
    z.write(d / "cut.zip")
    shard = io.BytesIO()
    with tarfile.open(fileobj=shard, mode="w") as tar:
        for name in ("fine.mp4", "cut.mp4"):
            info = tarfile.TarInfo(name)
            info.size = len(good)
            tar.addfile(info, io.BytesIO(good))
    (d / "cut.tar").write_bytes(shard.getvalue()[:2 * 512 + len(good) + 4096])
    time.sleep(2 * RACY_NS / 1e9)
    r = _check(d, tmp_path / "cache")
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    rows = _lines(r.stdout)
    for served in ("liar.zip/ok.mp4", "cut.zip/ok.mp4", "cut.tar/fine.mp4"):
        assert rows[served].startswith("2 window(s)"), rows
    size = (d / "liar.zip").stat().st_size
    assert rows["liar.zip/big.mp4"] == (f"ignored zip part: its bytes 0-{30 + 7 + (8 << 30)} run past the end of the "
                                        f"file ({size} bytes): corrupt or hostile, not served"), rows
    assert rows["cut.zip/long.mp4"].startswith("ignored zip part: its bytes") and "past the end of the file" in \
        rows["cut.zip/long.mp4"], rows
    assert rows["cut.tar/cut.mp4"].startswith("ignored tar shard: its bytes") and "run past the end of the shard" \
        in rows["cut.tar/cut.mp4"], rows
    assert not any("overlap" in v for v in rows.values()), rows
    assert r.stdout.splitlines()[-1].startswith("3 usable video(s) of 3, 6 sample(s) per epoch"), r.stdout

"""The corpus walk (``folder_scan.scan_corpus_names``): what it lists and rejects in a real folder
with links of every kind, and the extension rule it shares with ``Path.suffix``."""
import os
from pathlib import Path

import pytest

from v2v_server.sources.names import name_suffix
from v2v_server.sources.folder_scan import scan_corpus, scan_corpus_names

EXT = (".mp4", ".mkv", ".tar")


def test_names_suffix_is_path_suffix():
    for name in ["a.mp4", "B.MP4", ".mp4", "x.", "noext", "a.b.mkv", "..", "a..mp4", ".a.b"]:
        assert name_suffix(name) == Path(name).suffix, name


@pytest.fixture
def tree(tmp_path):
    root = tmp_path / "root"
    (root / "sub" / "deep").mkdir(parents=True)
    (tmp_path / "outside.mp4").write_bytes(b"x")
    (tmp_path / "outdir").mkdir()
    for name in ["a.mp4", "B.MP4", ".mp4", "x.", "s.tar", "z.txt", "Ä.mp4", "sub/w.mp4", "sub/deep/v.mp4"]:
        (root / name).write_bytes(b"x")
    (root / "folder.mp4").mkdir()
    os.mkfifo(root / "fifo.mp4")
    os.symlink("..", root / "sub" / "loop_dir")  # back to the root: walked once
    os.symlink("sub/deep", root / "deep_alias")  # a folder inside the root, by a second name
    os.symlink("loop.mp4", root / "loop.mp4")
    os.symlink("nowhere.mp4", root / "dangling.mp4")
    os.symlink(str(tmp_path / "outside.mp4"), root / "out.mp4")
    os.symlink(str(tmp_path / "outdir"), root / "outdir")
    os.symlink("a.mp4", root / "link_in.mp4")
    with open(os.fsencode(str(root)) + b"/bad\xff.mp4", "wb") as f:
        f.write(b"x")
    return root


def test_the_walk_lists_videos_and_names_every_other_entry(tree):
    videos, rejected = scan_corpus_names(tree, EXT)
    # a folder with two names is walked once, under the name met first (folders are walked last
    # name first), so ``deep_alias`` gives nothing
    assert videos == ["B.MP4", "a.mp4", "link_in.mp4", "s.tar", "sub/deep/v.mp4", "sub/w.mp4", "Ä.mp4"]
    assert rejected == [
        (".mp4", "not a video file (extension 'none')"),
        ("bad\\xff.mp4", "file name is not valid UTF-8 (sample ids are UTF-8): rename it"),
        ("dangling.mp4", "dangling symlink"),
        ("fifo.mp4", "not a video file (extension '.mp4')"),
        ("loop.mp4", "symlink loop"),
        ("out.mp4", "points outside the corpus root"),
        ("outdir", "points outside the corpus root"),
        ("x.", "not a video file (extension 'none')"),
        ("z.txt", "not a video file (extension '.txt')"),
    ]
    assert scan_corpus(tree, EXT) == ([Path(v) for v in videos], [(Path(r), why) for r, why in rejected])


def test_a_missing_root_is_one_rejected_entry(tmp_path):
    videos, rejected = scan_corpus_names(tmp_path / "missing", EXT)
    assert videos == [] and [r for r, _ in rejected] == ["."]
    assert rejected[0][1].startswith("folder cannot be resolved")
    (tmp_path / "f.mp4").write_bytes(b"x")
    assert scan_corpus_names(tmp_path / "f.mp4", EXT)[1][0][1].startswith("folder cannot be read")

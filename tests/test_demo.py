"""README's main job: ``v2v-demo`` serves the bundled clips in-process and writes a preview."""
from __future__ import annotations

import json
import threading

import pytest

from v2v_client import demo
from v2v_server.service.local import local_server


@pytest.mark.timeout(240)
def test_demo_serves_bundled_clips_and_stops(tmp_path, capsys):
    before = {t.name for t in threading.enumerate()}
    png = tmp_path / "preview.png"
    assert demo.main(["--workers", "1", "--batch-size", "2", "--batches", "2", "--preview", str(png), "--json"]) == 0
    assert png.stat().st_size > 1000 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    printed = capsys.readouterr().out.strip().splitlines()
    report = json.loads(printed[-1])
    # the closing lines say what the numbers mean, in words (no bare wait fraction or epoch list)
    said = "\n".join(printed[-4:-1])
    assert said.startswith("read 2 batches (3 samples, 3 different) in ") and "samples/s" in said, said
    assert "the demo trains nothing, so it waited for each batch" in said and "would not wait at all" in said
    assert "The batches came from epoch" in said and "an epoch is one pass over every window" in said
    # one epoch of the bundled clips is 3 samples (batches of 2, then 1)
    assert report["batches"] == 2 and report["samples"] == report["unique_samples"] == 3
    # the server thread (and with it its worker pool) is gone once main returns
    assert "v2v-demo-server" not in {t.name for t in threading.enumerate()} - before


def test_demo_refuses_an_empty_folder(tmp_path):
    with pytest.raises(ValueError, match="no video files"):
        with local_server(str(tmp_path), workers=1, batch_size=2):
            pass


def test_a_preview_path_that_is_not_a_png_or_lies_in_the_bundled_clips_is_refused_in_one_line(tmp_path, capsys):
    """``--preview`` must name a PNG (OpenCV picks the writer by the extension) outside the corpus
    it reads, the bundled clips when no ``--videos`` is given; nothing is started or written."""
    from v2v_server.ops.startup import SAMPLE_VIDEOS

    for path, why in ((tmp_path / "preview.jpg", "it must name a .png file"),
                      (SAMPLE_VIDEOS / "bikes.mp4", "is inside the corpus (--videos)"),
                      (SAMPLE_VIDEOS / "preview.png", "is inside the corpus (--videos)")):
        assert demo.main(["--preview", str(path)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"v2v-demo: --preview {path}: {why}"), err
        assert not (SAMPLE_VIDEOS / "preview.png").exists()


def test_a_corpus_that_is_not_there_or_holds_no_video_is_one_line(tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    for videos, why in ((tmp_path / "none", "not a folder"), (empty, "no video files")):
        assert demo.main(["--videos", str(videos), "--preview", str(tmp_path / "p.png")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("v2v-demo: ") and why in err[0], err
    assert not (tmp_path / "p.png").exists()

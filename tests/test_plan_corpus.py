"""A plan server over a corpus that is not what a plan's reader saw last (docs/delivery.md, "A corpus
that changed"), and the files it does not serve: real ``v2v-serve`` processes on 127.0.0.1 over
copies of the bundled clips, read by ``V2VStreamDataset``."""
from __future__ import annotations

import shutil
import subprocess
import sys

import pytest

from harness.serve import ServeProcess
from v2v_client import V2VStreamDataset
from tests.test_corpus_index import settle

#: windows of 201 frames (the default recipe's): bigbuckbunny.mp4 (132 frames) gives none
LAYOUT = ["--crop-size", "32", "--max-samples-per-video", "2", "--flow-preset", "ultrafast", "--seed", "3",
          "--shot-cuts", "off", "--shuffle-buffer", "4", "--batch-size", "2", "--workers", "1"]


@pytest.fixture
def corpus(tmp_path, videos):
    d = tmp_path / "corpus"
    d.mkdir()
    for name in ("bikes.mp4", "bigbuckbunny.mp4"):
        shutil.copyfile(videos / name, d / name)
    settle()
    return d


def epoch_ids(endpoint: str, batch: int = 2):
    """The sample ids of one epoch's rows that hold a sample, in plan order."""
    ds = V2VStreamDataset(endpoint, batch, outputs=("voxels",), timeout_s=120)
    return [sid for b in ds for sid, pad in zip(b["sample_ids"], b["padding"].tolist()) if not pad]


def test_a_plan_server_names_each_file_the_corpus_index_knows_gives_no_window_once(corpus, tmp_path):
    """After ``--check`` filled the corpus index, a plan server never opens bigbuckbunny.mp4 (too
    short for one window) and names it once, with the reason ``--check`` found and where the
    verdict came from; the epoch holds the other file's samples only, as many as ``--check`` said."""
    args = ["--videos", str(corpus), "--cache-dir", str(tmp_path / "cache"), *LAYOUT]
    r = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--check", *args], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    verdict = next(ln for ln in r.stdout.splitlines() if ln.startswith("bigbuckbunny.mp4"))
    assert " unusable " in verdict, r.stdout
    with ServeProcess(args + ["--log-level", "info"], ready_timeout_s=120) as srv:
        ids = epoch_ids(srv.endpoint)
    named = [ln for ln in srv.log.splitlines() if "bigbuckbunny.mp4" in ln]
    assert len(named) == 1, srv.log
    assert f"skipped {corpus / 'bigbuckbunny.mp4'}: " in named[0] and "shorter than one window" in named[0]
    assert named[0].endswith("(known from the corpus index: not opened)")
    assert "1 skipped file(s)" in srv.log
    assert ids and all(sid.startswith("bikes.mp4") for sid in ids) and len(set(ids)) == len(ids)


#: windows of 41 frames, no shot cuts: bikes.mp4 (250 frames) gives 6, bigbuckbunny.mp4 (132) 3
SHORT = ["--sequence-length", "8", "--crop-size", "32", "--flow-preset", "ultrafast", "--shot-cuts", "off",
         "--shuffle-buffer", "4", "--batch-size", "2", "--workers", "1"]


def rows_of(ds, steps=None):
    """(sample id, voxels digest) of each row holding a sample, and the last batch's position."""
    import hashlib

    rows, position = [], None
    for i, b in enumerate(ds):
        if i == steps:
            break
        rows += [(sid, hashlib.sha1(b["voxels"][j].numpy().tobytes()).hexdigest())
                 for j, sid in enumerate(b["sample_ids"]) if not b["padding"][j]]
        position = b["position"]
    return rows, position


def test_a_position_taken_before_a_file_was_replaced_under_its_name_is_refused_naming_it(tmp_path, videos):
    """A position resumes across a restart of the server on the same files (the rest of the epoch,
    the same ids and bytes); once bikes.mp4 is replaced by another cut (fewer windows) while the
    server is down, the same position is refused in one line naming bikes.mp4, never read as
    other samples."""
    from v2v_wire.plan import PlanMismatch

    corpus = tmp_path / "corpus"
    corpus.mkdir()
    for name in ("bikes.mp4", "bbb_camera_596x336.mp4"):
        shutil.copyfile(videos / name, corpus / name)
    settle()
    args = ["--videos", str(corpus), "--cache-dir", str(tmp_path / "cache"), *SHORT]
    with ServeProcess(args, ready_timeout_s=120) as srv:
        whole, _ = rows_of(V2VStreamDataset(srv.endpoint, 2, outputs=("voxels",), timeout_s=120))
        head, position = rows_of(V2VStreamDataset(srv.endpoint, 2, outputs=("voxels",), timeout_s=120), steps=2)
    assert position["sample_in_epoch"] == 4 and head == whole[:4] and any(s.startswith("bikes.mp4") for s, _ in whole)
    with ServeProcess(args, ready_timeout_s=120) as srv:  # the same files: the position holds
        ds = V2VStreamDataset(srv.endpoint, 2, outputs=("voxels",), timeout_s=120)
        ds.load_state_dict(position)
        rest, _ = rows_of(ds)
    assert head + rest == whole
    shutil.copyfile(videos / "bigbuckbunny.mp4", corpus / "bikes.mp4")  # another cut under the same name
    settle()
    with ServeProcess(args, ready_timeout_s=120) as srv:
        ds = V2VStreamDataset(srv.endpoint, 2, outputs=("voxels",), timeout_s=120)
        ds.load_state_dict(position)
        with pytest.raises(PlanMismatch) as err:
            rows_of(ds)
    line = str(err.value)
    assert "\n" not in line and "manifest" in line and "1 file(s) changed" in line and "bikes.mp4" in line, line
    assert "bbb_camera" not in line

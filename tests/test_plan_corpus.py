"""A plan server over a corpus that is not what a plan's reader saw last (docs/plan.md, "A corpus
that changed"), and the files it does not serve: real ``v2v-serve`` processes on 127.0.0.1 over
copies of the bundled clips, read by ``V2VStreamDataset``."""
from __future__ import annotations

import shutil
import subprocess
import sys
import time

import pytest

from harness.serve import ServeProcess
from v2v_client import V2VStreamDataset
from v2v_server.sources.local import RACY_NS

#: windows of 201 frames (the default recipe's): bigbuckbunny.mp4 (132 frames) gives none
LAYOUT = ["--crop-size", "32", "--max-samples-per-video", "2", "--flow-preset", "ultrafast", "--seed", "3", "--shot-cuts", "off",
          "--shuffle-buffer", "4", "--batch-size", "2", "--workers", "1", "--delivery", "plan"]


def settle() -> None:
    """Wait out the racy window: a file written just now has no identity the corpus index trusts."""
    time.sleep(2 * RACY_NS / 1e9)


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

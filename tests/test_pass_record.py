"""One record of what a pass reads (``frames.pass_record.PassRecord``), one key from it: a change
of any field gives a new frame-cache entry, a new corpus-index row and a new recipe fingerprint;
a setting outside the record (it changes samples, not what a pass reads) reuses them all."""
from __future__ import annotations

import sqlite3
import time
from pathlib import Path

import pytest

import v2v_server.frames.pass_record as pass_record
from harness.corpus import write_scenes_video
from tests.cached import Cached, cached
from v2v_server.samples.recipe import SampleRecipe
from v2v_server.frames.check import check_video
from v2v_server.frames.corpus_index import INDEX_FILE, INDEX_VERSION, CorpusIndex, Verdict, layout_key
from v2v_server.frames.frame_cache import FrameCache
from v2v_server.frames.frame_pass import corpus_key, entry_settings
from v2v_server.frames.video_read import read_video, reraise
from v2v_server.sources.local import RACY_NS
from v2v_server.sources.source_spec import open_source

CLIP = "scenes.mpg"
# small windows over a small clip: every variant below still gives windows
BASE = dict(sequence_length=2, num_bins=5, crop_size=16, max_samples_per_video=4, keep_top_fraction=0.9)

#: For each field of the record: (the recipe's keys before, after) that change it alone, or the
#: module constant of ``pass_record`` to patch (a detector or motion measure of another build).
CHANGES = {
    "decode_fast": ({}, {"decode_fast": "all"}),
    "keep_top_fraction": ({}, {"keep_top_fraction": 0.75}),
    "frame_height": ({}, {"frame_height": 40}),
    "frames_per_sample": ({}, {"sequence_length": 3}),
    "max_samples_per_video": ({}, {"max_samples_per_video": 3}),
    "shot_cuts": ({}, {"shot_cuts": "off"}),
    "static_windows": ({}, {"static_windows": "skip"}),
    "shot_detector": ({}, "DETECTOR_VERSION"),
    "static_motion": ({"static_windows": "skip"}, "MOTION_VERSION"),
}
#: Fields a change brings with it: the versions of what decides windows only under a setting.
FOLLOWS = {"shot_cuts": ["shot_detector"], "static_windows": ["static_motion"]}
#: Settings outside the record: they change samples (and so the fingerprint), not what a pass reads.
OUTSIDE = {"crop_size": 24, "hflip_prob": 0.25, "seed": 7, "decode_threads": 2,
           "ranges": {"threshold": [0.3, 0.4]}, "pause_enabled": False}


@pytest.fixture
def corpus(tmp_path: Path) -> Path:
    d = tmp_path / "corpus"
    d.mkdir()
    write_scenes_video(d / CLIP, [("a", 30, 64, 48), ("b", 30, 64, 48)])
    time.sleep(RACY_NS / 1e9 + 0.02)  # out of the racy window: the cache and the index vouch for it
    return d


def _read(recipe: SampleRecipe, corpus: Cached) -> None:
    """One sample pass (stored in the frame cache) and one ``--check`` pass (recorded in the index)."""
    with read_video(corpus.source, CLIP, recipe.reads, corpus.caches, handler=reraise) as read:
        for _ in read.frames:
            pass
    assert check_video(recipe.windows, recipe.decode, corpus.source, CLIP, corpus.caches).usable


def _keys(recipe: SampleRecipe, corpus: Path) -> dict:
    return {"pass": recipe.reads.key,
            "entry": FrameCache.entry_name(corpus_key(open_source(str(corpus))), CLIP,
                                           entry_settings(recipe.decode, recipe.windows)),
            "index": layout_key(recipe.windows, recipe.decode)}


def _stored(cache: Path) -> tuple:
    with sqlite3.connect(cache / INDEX_FILE) as db:
        rows = db.execute("SELECT layout FROM entries").fetchall()
    return len(list((cache / "frames").glob("*.v2vf"))), len(rows)


def test_every_field_of_the_record_is_changed_by_the_test():
    assert set(CHANGES) == set(SampleRecipe().reads.values())


@pytest.mark.parametrize("name", list(CHANGES))
def test_a_change_of_any_field_is_a_new_entry_row_and_fingerprint(name, corpus, tmp_path, monkeypatch):
    before, after = CHANGES[name]
    cache = tmp_path / "cache"
    source = cached(corpus, cache)
    old = SampleRecipe(**{**BASE, **before})
    _read(old, source)
    assert _stored(cache) == (1, 1)
    was, fingerprint = _keys(old, corpus), old.fingerprint()  # this build's record, before another's is made
    if isinstance(after, str):
        monkeypatch.setattr(pass_record, after, getattr(pass_record, after) + "-another")
        new = SampleRecipe(**{**BASE, **before})
    else:
        new = SampleRecipe(**{**BASE, **before, **after})
    changed = [k for k, v in old.reads.values().items() if new.reads.values()[k] != v]
    assert changed == [name] + FOLLOWS.get(name, [])
    now = _keys(new, corpus)
    assert all(was[k] != now[k] for k in was), (was, now)
    assert new.fingerprint() != fingerprint
    _read(new, source)  # nothing of the old pass is reused: a new entry and a new row
    assert _stored(cache) == (2, 2)


def test_a_setting_outside_the_record_reuses_the_entry_and_the_row(corpus, tmp_path):
    cache = tmp_path / "cache"
    source = cached(corpus, cache)
    base = SampleRecipe(**BASE)
    _read(base, source)
    for key, value in OUTSIDE.items():
        other = SampleRecipe(**{**BASE, key: value})
        assert other.reads == base.reads and _keys(other, corpus) == _keys(base, corpus), key
        if key != "decode_threads":  # the fingerprint covers the samples, more than the pass
            assert other.fingerprint() != base.fingerprint(), key
        _read(other, source)
    assert _stored(cache) == (1, 1)
    assert source.frame_cache.take_stats()["hits"] >= len(OUTSIDE)


def test_the_default_recipe_keeps_its_fingerprint():
    """Fingerprints are the same as before the pass record fed them: a resumed job or a written
    shard of the default recipe is still accepted."""
    assert SampleRecipe().fingerprint() == "269ecabd4b2ccc39"


def test_rows_of_another_index_version_are_swept(tmp_path):
    path = tmp_path / INDEX_FILE
    index = CorpusIndex(path)
    verdict = Verdict(path="a.mp4", usable=True, windows=2, frames=401, reason="", cause="", cuts=(), dropped=0,
                      stream=None)
    assert index.record("/c/a.mp4", "file 1 2 3 4", "L", verdict) and len(index) == 1
    index.close()
    with sqlite3.connect(path) as db:
        db.execute("UPDATE meta SET value = ? WHERE key = 'version'", (str(INDEX_VERSION - 1),))
    assert len(CorpusIndex(path)) == 0

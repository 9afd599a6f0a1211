"""Beyond one host: --shard, one plan read over several servers, metrics. Real servers on 127.0.0.1
on the real clips; every test is bounded in time and stops what it starts."""
from __future__ import annotations

import collections
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request

import pytest
import torch

from v2v_client import V2VStreamDataset
from v2v_client.endpoints import expand_dns, resolve_endpoints, split_endpoints
from v2v_wire.plan import PlanMismatch
from v2v_server.ops.config import ServeConfig, parse_shard
from v2v_server.frames.check import check_corpus
from v2v_server.ops.startup import select_shard, shard_of
from v2v_server.sources.local import LocalSource
from v2v_server.ops.logs import JsonFormatter
from harness.serve import ServeProcess, free_port, served_samples
from v2v_server.sources.folder_scan import scan_corpus

L, CROP, WINDOWS, BATCH = 4, 64, 2, 2
OUTPUTS = ("voxels", "frames")


def layout(*extra):
    return ["--sequence-length", str(L), "--crop-size", str(CROP), "--max-samples-per-video", str(WINDOWS),
            "--batch-size", str(BATCH), "--seed", "5", "--flow-preset", "ultrafast", "--workers", "1", *extra]


def corpus(tmp_path, videos, copies=1):
    d = tmp_path / "corpus"
    d.mkdir(exist_ok=True)
    for p in sorted(videos.glob("*.mp4")):
        for c in range(copies):
            shutil.copy(p, d / (p.name if c == 0 else f"{p.stem}_{c}{p.suffix}"))
    return d


def expected_ids(root, sequence_length=L, crop_size=CROP, windows=WINDOWS):
    """Every sample id one epoch of ``root`` holds, from ``--check``'s verdicts (a window it says
    cannot be made, e.g. where the frame size changes, holds none)."""
    cfg = ServeConfig(sequence_length=sequence_length, crop_size=crop_size, max_samples_per_video=windows, workers=1)
    vids = [p.as_posix() for p in scan_corpus(root, cfg.video_extensions)[0]]
    out = []
    for r in check_corpus(cfg.recipe.windows, cfg.recipe.decode, LocalSource(root), vids):
        failed = set(r.failed_windows)
        out += [f"{r.path}#{k}" for k in range(r.windows + len(failed)) if k not in failed]
    return sorted(out)


def read_all(ds, limit_s=120.0):
    """{sample id: (voxels, frames)} and the ids in the plan's order, for one rank's epoch (padding
    rows left out)."""
    got, order = {}, []
    t0 = time.monotonic()
    for b in ds:
        for i, sid in enumerate(b["sample_ids"]):
            if b["padding"][i]:
                continue
            order.append(sid)
            got[sid] = (b["voxels"][i].clone(), b["frames"][i].clone())
        assert time.monotonic() - t0 < limit_s
    return got, order


# ---------------------------------------------------------------------------------- shard: pure part
def test_shard_spec_is_checked_and_names_the_field():
    assert parse_shard(None) == (0, 1) and parse_shard("1/3") == (1, 3) and parse_shard(" 0 / 2 ") == (0, 2)
    for bad in ("2/2", "a/b", "1", "-1/2", "0/0"):
        with pytest.raises(ValueError, match="shard"):
            parse_shard(bad)
    with pytest.raises(ValueError, match="shard"):
        ServeConfig(shard="3/2")
    assert ServeConfig(shard="1/ 4").shard == "1/4"


def test_shards_partition_any_corpus_and_the_hash_is_stable_across_processes():
    names = [f"dir{i % 7}/clip_{i}.mp4" for i in range(300)]
    for n in (1, 2, 3, 5):
        parts = [select_shard(names, i, n) for i in range(n)]
        assert sorted(sum(parts, [])) == sorted(names)  # every file in exactly one shard
        assert all(len(p) > 0 for p in parts)
    # the hash does not depend on Python's per-process salt (PYTHONHASHSEED) nor on the host
    code = "from v2v_server.ops.startup import shard_of; print([shard_of(f'dir/c{i}.mp4', 4) for i in range(50)])"
    outs = {subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                           env=dict(os.environ, PYTHONHASHSEED=str(seed))).stdout for seed in (1, 2)}
    assert len(outs) == 1 and json.loads(outs.pop()) == [shard_of(f"dir/c{i}.mp4", 4) for i in range(50)]


def test_check_lists_only_the_shards_files_and_logs_json(videos):
    found = [p.as_posix() for p in scan_corpus(videos, (".mp4",))[0]]
    for i in range(2):
        r = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--check", "--videos", str(videos), "--shard",
                            f"{i}/2", "--log-format", "json", *layout()], capture_output=True, text=True, timeout=120)
        listed = [ln.split()[0] for ln in r.stdout.splitlines()[1:-1] if " ignored " not in ln]
        assert sorted(listed) == sorted(select_shard(found, i, 2)), r.stdout
        logs = [json.loads(ln) for ln in r.stderr.splitlines() if ln.strip()]
        assert logs and all({"time", "level", "logger", "message"} <= set(d) for d in logs)
        assert any(f"shard {i}/2" in d["message"] for d in logs)


def test_json_formatter_keeps_exceptions():
    import logging

    try:
        raise ValueError("boom")
    except ValueError:
        rec = logging.LogRecord("v2v", logging.ERROR, __file__, 1, "bad %s", ("file",), sys.exc_info())
    d = json.loads(JsonFormatter().format(rec))
    assert d["message"] == "bad file" and d["level"] == "ERROR" and "ValueError: boom" in d["exception"]


# ---------------------------------------------------------------------------------- endpoints
def test_endpoint_lists_and_dns_names_with_several_addresses():
    assert split_endpoints("tcp://a:1, tcp://b:2,tcp://a:1") == ["tcp://a:1", "tcp://b:2"]
    assert split_endpoints(["tcp://a:1", "ipc:///tmp/x"]) == ["tcp://a:1", "ipc:///tmp/x"]
    for bad in ("", "a:1", [" "]):
        with pytest.raises(ValueError):
            split_endpoints(bad)

    def fake(host, port, *_):
        table = {"v2v-server": ["10.0.0.2", "10.0.0.1"], "localhost": ["127.0.0.1", "::1"],
                 "one": ["10.0.0.9"], "six": ["fd00::2", "fd00::1"]}
        if host not in table:
            raise socket.gaierror("no such name")
        return [(socket.AF_INET6 if ":" in a else socket.AF_INET, socket.SOCK_STREAM, 6, "", (a, port))
                for a in table[host]]

    # a headless Service: one endpoint per address (sorted, so every rank sees the same order)
    assert expand_dns("tcp://v2v-server:5555", fake) == ["tcp://10.0.0.1:5555", "tcp://10.0.0.2:5555"]
    assert expand_dns("tcp://six:5555", fake) == ["tcp://[fd00::1]:5555", "tcp://[fd00::2]:5555"]
    # one server, however many address families; names kept so reconnects resolve again
    for keep in ("tcp://localhost:5555", "tcp://one:5555", "tcp://missing:5555", "tcp://127.0.0.1:5555",
                 "ipc:///tmp/v2v"):
        assert expand_dns(keep, fake) == [keep]
    assert resolve_endpoints("tcp://v2v-server:1,tcp://10.0.0.1:1", fake) == ["tcp://10.0.0.1:1", "tcp://10.0.0.2:1"]


# ---------------------------------------------------------------------------------- shards -> one trainer
def raw_epoch(ds, limit_s=180.0):
    """{sample id: {output: bytes}} of one rank's epoch (padding rows left out), and the ids in order."""
    got, order = {}, []
    t0 = time.monotonic()
    for b in ds:
        for i, sid in enumerate(b["sample_ids"]):
            if not b["padding"][i]:
                order.append(sid)
                got[sid] = {k: b[k][i].numpy().tobytes() for k in OUTPUTS}
        assert time.monotonic() - t0 < limit_s
    return got, order


def test_each_shard_serves_its_own_files_and_the_pair_the_bytes_of_one_unsharded_server(tmp_path, videos):
    """Each shard alone serves exactly the ids of its files (``shard_of``); read together, every id
    of the corpus once, each with the wire bytes one unsharded server gives it."""
    root = corpus(tmp_path, videos)
    want = expected_ids(root)
    assert {s.split("#")[0] for s in want} == {p.name for p in root.glob("*.mp4")}  # every clip gives windows
    base = ["--videos", str(root), *layout()]
    single = {sid: {k: a.tobytes() for k, a in arrays.items()} for sid, arrays in served_samples(base, OUTPUTS)}
    assert sorted(single) == want
    with ServeProcess(base + ["--shard", "0/2"]) as a, ServeProcess(base + ["--shard", "1/2"]) as b:
        for i, srv in enumerate((a, b)):
            alone, _ = raw_epoch(V2VStreamDataset(srv.endpoint, outputs=OUTPUTS, raw=True, timeout_s=60))
            assert sorted(alone) == [s for s in want if shard_of(s.split("#")[0], 2) == i]
        sharded, order = raw_epoch(V2VStreamDataset(f"{a.endpoint},{b.endpoint}", outputs=OUTPUTS, raw=True,
                                                    timeout_s=60))
    assert sorted(order) == want  # every id of the epoch exactly once, nothing from elsewhere
    for sid in want:  # the same id carries the same bytes whichever topology served it
        assert sharded[sid] == single[sid], sid


def test_loadtest_reads_several_servers_as_one_plan_epoch_after_epoch(videos):
    """``v2v-loadtest`` given two shards reads their interleaved plan as a trainer does: 24
    batches run through several epochs, each holding every id of the corpus; it reports each
    server's samples, those of its own files in each epoch read, summing to the total."""
    want = expected_ids(videos)
    base = ["--videos", str(videos), *layout()]
    with ServeProcess(base + ["--shard", "0/2"]) as a, ServeProcess(base + ["--shard", "1/2"]) as b:
        out = subprocess.run([sys.executable, "-m", "v2v_client.loadtest", "--connect", a.endpoint, "--connect",
                              b.endpoint, "--batches", "24", "--outputs", "voxels", "--json", "--timeout", "60"],
                             capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["batches"] == 24 and not r["ended_early"]
    # unique: (epoch, id) pairs, none twice; 8 samples an epoch, 2 a batch: the epochs between the
    # first (its first batch the unmeasured warmup) and the last are whole
    assert r["unique_samples"] == r["samples"] and len(r["epochs_seen"]) >= 3
    assert len(want) * (len(r["epochs_seen"]) - 2) < r["unique_samples"] <= len(want) * len(r["epochs_seen"])
    assert r["samples"] <= 24 * BATCH and r["samples_per_s"] > 0
    per, epochs = r["per_server"], len(r["epochs_seen"])
    assert sorted(per) == sorted([a.endpoint, b.endpoint]) and sum(v["samples"] for v in per.values()) == r["samples"]
    for k, srv in enumerate((a, b)):  # each epoch read whole holds the shard's own ids, once each
        own = sum(1 for s in want if shard_of(s.split("#")[0], 2) == k)
        assert own * (epochs - 2) <= per[srv.endpoint]["samples"] <= own * epochs, (k, own, per)
        assert f"{srv.endpoint}: {per[srv.endpoint]['samples']} samples, " in out.stdout


def _kill(proc):
    proc.proc.send_signal(signal.SIGKILL)
    proc.proc.wait(10)


def test_a_shard_killed_and_restarted_mid_epoch_loses_and_doubles_nothing(tmp_path, videos):
    """The reader asks again what goes unanswered (``retry_s``): a shard SIGKILLed mid-epoch and
    started again on its address costs nothing but time."""
    root = corpus(tmp_path, videos, copies=2)
    want = expected_ids(root)
    base = ["--videos", str(root), *layout()]
    a = ServeProcess(base + ["--shard", "0/2"]).start()
    b = ServeProcess(base + ["--shard", "1/2"]).start()
    b2 = None
    order = []
    try:
        ds = V2VStreamDataset([a.endpoint, b.endpoint], outputs=OUTPUTS, prefetch=1, retry_s=2.0, timeout_s=120)
        it = iter(ds)
        for step, batch in enumerate(it):
            order += [s for s, p in zip(batch["sample_ids"], batch["padding"].tolist()) if not p]
            if step == 1:  # a step of each shard read (interleaved: step t is shard t mod 2's)
                break
        _kill(b)  # mid-epoch: shard 1 has more to serve
        b2 = ServeProcess(base + ["--shard", "1/2", "--bind", b.endpoint]).start()
        t0 = time.monotonic()
        for batch in it:
            order += [s for s, p in zip(batch["sample_ids"], batch["padding"].tolist()) if not p]
            assert time.monotonic() - t0 < 180
    finally:
        for p in (a, b, b2):
            if p is not None:
                p.stop()
    dup = [s for s, n in collections.Counter(order).items() if n > 1]
    assert not dup and sorted(order) == want, (dup, sorted(set(want) - set(order)))


def test_an_older_position_resumes_every_shard_after_a_trainer_and_server_restart(tmp_path, videos):
    """A position kept at step 2, the trainer reads on to step 5 and dies with both servers; fresh
    servers know nothing, and the step-2 position reads the rest of the epoch: nothing lost, and
    what came after the checkpoint is read again, in the same order."""
    root = corpus(tmp_path, videos, copies=2)
    want = expected_ids(root)
    base = ["--videos", str(root), *layout()]
    shards = [ServeProcess(base + ["--shard", f"{i}/2"]).start() for i in range(2)]
    eps = [s.endpoint for s in shards]
    trained, later = [], []
    try:
        it = iter(V2VStreamDataset(eps, outputs=OUTPUTS, timeout_s=60))
        for step in range(5):
            batch = next(it)
            rows = [s for s, p in zip(batch["sample_ids"], batch["padding"].tolist()) if not p]
            (trained if step < 2 else later).extend(rows)
            if step == 1:
                ckpt = json.loads(json.dumps(batch["position"]))  # a checkpoint, as a trainer stores it
        it.close()
        for s in shards:  # both hosts go down
            _kill(s)
        shards = [ServeProcess(base + ["--shard", f"{i}/2", "--bind", eps[i]]).start() for i in range(2)]
        again = V2VStreamDataset(eps, outputs=OUTPUTS, timeout_s=60)
        again.load_state_dict(ckpt)
        _, rest = raw_epoch(again)
    finally:
        for s in shards:
            s.stop()
    assert rest[:len(later)] == later
    assert sorted(trained + rest) == want and len(trained + rest) == len(set(trained + rest))


# ---------------------------------------------------------------------------------- DDP


def _ranks(endpoint, world):
    out = [None] * world

    def run(r):
        out[r] = list(V2VStreamDataset(endpoint, outputs=OUTPUTS, timeout_s=60, rank=r, world_size=world))

    ts = [threading.Thread(target=run, args=(r,)) for r in range(world)]
    for t in ts:
        t.start()
    for t in ts:
        t.join(180)
    return out


def _check_ranks(per_rank, want, single):
    counts = [len(b) for b in per_rank]
    assert len(set(counts)) == 1, counts  # equal batch counts per rank
    real = []
    for batches in per_rank:
        for b in batches:
            for i, sid in enumerate(b["sample_ids"]):
                if not b["padding"][i]:
                    real.append(sid)
                    assert torch.equal(b["voxels"][i], single[sid][0]), sid
    assert sorted(real) == want  # every id exactly once across ranks


@pytest.mark.parametrize("shards", [1, 2])
def test_servers_feed_two_ranks_each_id_once_equal_batch_counts(tmp_path, videos, shards):
    root = corpus(tmp_path, videos)
    want = expected_ids(root)
    base = ["--videos", str(root), *layout()]
    with ServeProcess(base) as one:
        single, _ = read_all(V2VStreamDataset(one.endpoint, outputs=OUTPUTS, timeout_s=60))
    procs = [ServeProcess(base + (["--shard", f"{i}/{shards}"] if shards > 1 else [])).start() for i in range(shards)]
    try:
        per_rank = _ranks(",".join(p.endpoint for p in procs), 2)
    finally:
        for p in procs:
            p.stop()
    _check_ranks(per_rank, want, single)


# ---------------------------------------------------------------------------------- metrics
def _get(port, path):
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=5) as r:
            return r.status, r.read().decode()
    except urllib.error.HTTPError as e:
        return e.code, e.read().decode()


def _scrape(port):
    from prometheus_client.parser import text_string_to_metric_families

    code, text = _get(port, "/metrics")
    assert code == 200
    out = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def test_metrics_probes_and_counters_move(videos):
    port = free_port()
    with ServeProcess(["--videos", str(videos), *layout("--workers", "2", "--metrics-port", str(port))]) as srv:
        assert _get(port, "/healthz") == (200, "ok\n")
        assert _get(port, "/nope")[0] == 404
        deadline = time.monotonic() + 60
        while _get(port, "/readyz")[0] != 200:  # workers up, socket bound, corpus scanned
            assert time.monotonic() < deadline
            time.sleep(0.2)
        m0 = _scrape(port)
        assert m0[("v2v_samples_sent_total", ())] == 0 and m0[("v2v_ready", ())] == 1
        assert m0[("v2v_workers", ())] == 2
        it = iter(V2VStreamDataset(srv.endpoint, outputs=OUTPUTS, timeout_s=60))
        got = [next(it) for _ in range(3)]
        want = sum(len(b["sample_ids"]) for b in got)
        deadline = time.monotonic() + 10  # the page is rendered at most once a second (EXPOSITION_S)
        while (m1 := _scrape(port))[("v2v_samples_sent_total", ())] < want and time.monotonic() < deadline:
            time.sleep(0.2)
        it.close()
    sent = m1[("v2v_samples_sent_total", ())]
    assert sent >= want
    assert m1[("v2v_batches_sent_total", ())] >= 3 and m1[("v2v_samples_made_total", ())] >= sent
    assert m1[("v2v_sent_bytes_total", ())] >= sum(b["voxels"].numel() for b in got)  # int8 voxels at least
    for stage in ("decode", "simulate", "serialize", "send"):
        assert m1[("v2v_worker_busy_seconds_total", (("stage", stage),))] > 0, stage
    assert m1[("v2v_worker_busy_seconds_total", (("stage", "flow"),))] == 0  # nobody asked for flow
    assert m1[("v2v_epoch_videos", ())] == len(list(videos.glob("*.mp4"))) and m1[("v2v_pending_fetches", ())] >= 0
    assert m1[("v2v_shuffle_buffer_capacity_samples", ())] >= 1 and m1[("v2v_shuffle_buffer_samples", ())] >= 0


def test_the_epoch_samples_gauge_is_the_epoch_served_once_known(tmp_path, videos):
    """``v2v_epoch_samples`` reads 0 while some video's slots are unknown, then the samples one
    epoch lists once its decodes have learned them all; a second start knows it from the corpus
    index before any fetch."""
    root = corpus(tmp_path, videos)
    port = free_port()

    def gauge():
        return _scrape(port)[("v2v_epoch_samples", ())]

    args = ["--videos", str(root), *layout("--metrics-port", str(port))]
    with ServeProcess(args) as srv:
        _wait_ready(port)
        assert gauge() == 0  # nothing decoded, no index: not known
        got, _ = read_all(V2VStreamDataset(srv.endpoint, outputs=OUTPUTS, timeout_s=60))
        deadline = time.monotonic() + 10  # the page is rendered at most once a second (EXPOSITION_S)
        while (n := gauge()) != len(got) and time.monotonic() < deadline:
            time.sleep(0.2)
    assert n == len(got) == len(expected_ids(root)) > 0
    with ServeProcess(args) as again:
        _wait_ready(port)
        deadline = time.monotonic() + 10
        while (n := gauge()) != len(got) and time.monotonic() < deadline:
            time.sleep(0.2)
    assert n == len(got)  # no fetch made: from the corpus index the first epoch filled
    assert f"counted: {len(got)} samples per epoch)" in again.log, again.log


def _wait_ready(port):
    deadline = time.monotonic() + 60
    while _get(port, "/readyz")[0] != 200:  # workers up, socket bound, corpus scanned
        assert time.monotonic() < deadline
        time.sleep(0.2)


def test_progress_line_shows_videos_rate_fetches_and_workers(capsys):
    from v2v_server.ops.metrics import ServerMetrics

    m = ServerMetrics(progress=True)
    state = dict(epoch_videos=3, pending_fetches=2, workers=4, workers_busy=3, shuffle_samples=5, shuffle_capacity=48)
    m._progress._last -= 2.0  # two seconds ago
    m.on_batch_sent(4, 3_000_000)
    m.set_state(**state)
    try:
        assert m._progress.bar.n == 4
        line = m._progress.line
        assert line.startswith("3 videos, 1.") and line.endswith(
            "MB/s, 2 fetch(es) waiting, workers busy 3/4, shuffle buffer 5/48")
    finally:
        m.close()
    assert ServerMetrics(progress=False)._progress is None
    # an epoch's size, once the plan knows it: the line names it
    m = ServerMetrics(progress=True)
    try:
        m._progress._last -= 2.0
        m.on_batch_sent(4, 1000)
        m.set_state(**state, epoch_samples=10)
        assert m._progress.line.startswith("10 samples/epoch, 3 videos")
    finally:
        m.close()


# ---------------------------------------------------------------------------------- identity and resume
@pytest.mark.parametrize("shards,why", [(("0/2", "1/3"), "different numbers of shards"),
                                        (("0/3", "1/3"), "served by none")])
def test_servers_that_are_not_one_sharding_are_refused_naming_both(tmp_path, videos, shards, why):
    base = ["--videos", str(videos), *layout()]
    with ServeProcess(base + ["--shard", shards[0]]) as a, ServeProcess(base + ["--shard", shards[1]]) as b:
        with pytest.raises(ValueError, match=why) as e:
            V2VStreamDataset(f"{a.endpoint},{b.endpoint}", outputs=("voxels",), timeout_s=60).plan_info()
        assert a.endpoint in str(e.value) and b.endpoint in str(e.value)


def test_corpus_listings_that_differ_and_a_position_under_another_recipe_are_refused(tmp_path, videos):
    root = corpus(tmp_path, videos)
    other = tmp_path / "other"
    shutil.copytree(root, other)
    next(other.glob("*.mp4")).unlink()  # one file fewer on this host
    with ServeProcess(["--videos", str(root), "--shard", "0/2", *layout()]) as a, \
            ServeProcess(["--videos", str(other), "--shard", "1/2", *layout()]) as b:
        with pytest.raises(ValueError, match="different corpus listings"):
            V2VStreamDataset(f"{a.endpoint},{b.endpoint}", outputs=("voxels",), timeout_s=60).plan_info()
    with ServeProcess(["--videos", str(root), "--seed", "1", *layout()]) as s1:
        position = next(iter(V2VStreamDataset(s1.endpoint, outputs=("voxels",), timeout_s=60)))["position"]
    with ServeProcess(["--videos", str(root), "--seed", "1", *layout(), "--crops-per-window", "2"]) as s2:
        ds = V2VStreamDataset(s2.endpoint, outputs=("voxels",), timeout_s=60)
        ds.load_state_dict(position)
        with pytest.raises(PlanMismatch, match="recipe") as e:
            next(iter(ds))
        assert "\n" not in str(e.value)

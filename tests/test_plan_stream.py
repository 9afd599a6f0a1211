"""Serving by plan end to end (docs/delivery.md): real servers (in this process, and ``v2v-serve``
as a child) over the bundled clips, read by ``V2VStreamDataset`` through real
DataLoaders. Each test checks what a user is promised: every sample of an epoch once, at the same
positions at any layout, bit-identical batches from two reads, a checkpoint that resumes at another
world size, a server killed mid-epoch costing only the fetches in flight."""
from __future__ import annotations

import hashlib
import os
import threading
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from harness.serve import ServeProcess, free_port
from v2v_client import V2VStreamDataset
from v2v_server.ops.config import load_config
from v2v_server.service.local import local_server
from v2v_wire.plan import PlanMismatch

#: 8 voxel grids of 0.2 s a window: the bundled clips give 24 samples an epoch (``v2v-serve --check``)
RECIPE = {"sequence_length": 8, "shuffle_buffer": 8}
SAMPLES = 24


@pytest.fixture(scope="module")
def server():
    with local_server(None, workers=2, batch_size=4, config=load_config(None, RECIPE)) as endpoint:
        yield endpoint


def read(ds, workers: int = 0, context=None, steps=None):
    """(sample id or None, padding, voxels digest, position) of every row, and the last position."""
    loader = torch.utils.data.DataLoader(ds, batch_size=None, num_workers=workers, multiprocessing_context=context)
    rows, last = [], None
    for i, b in enumerate(loader):
        if steps is not None and i == steps:
            break
        for j, sid in enumerate(b["sample_ids"]):
            digest = hashlib.sha1(b["voxels"][j].numpy().tobytes()).hexdigest()[:12]
            rows.append((sid, bool(b["padding"][j]), digest))
        last = b["position"]
    return rows, last


def real_ids(rows):
    return [sid for sid, pad, _ in rows if not pad]


def test_every_rank_reads_a_fixed_slice_and_the_epoch_holds_every_sample_once(server):
    layouts = {}
    for world, batch, workers in ((1, 4, 0), (2, 3, 2), (3, 2, 1)):
        per_rank = [read(V2VStreamDataset(server, batch, rank=r, world_size=world), workers)[0] for r in range(world)]
        steps = {len(rows) // batch for rows in per_rank}
        assert len(steps) == 1  # every rank the same number of steps
        ids = [sid for rows in per_rank for sid in real_ids(rows)]
        assert len(ids) == SAMPLES and len(set(ids)) == SAMPLES
        # the global sequence: step-major, rank-minor slices of it
        seq = [per_rank[r][s * batch + i] for s in range(steps.pop()) for r in range(world) for i in range(batch)]
        pads = [pad for _, pad, _ in seq]
        assert pads == sorted(pads)  # padding only at the tail
        layouts[(world, batch)] = [row for row in seq if not row[1]]
    sequences = list(layouts.values())
    assert all(s == sequences[0] for s in sequences)  # the same sequence, the same bytes, at any layout


def test_len_and_the_epochs_order_are_the_trainers(server):
    ds = V2VStreamDataset(server, 5)
    first = real_ids(read(ds)[0])
    assert len(ds) == -(-SAMPLES // 5)  # known once an epoch was decoded (or the corpus index knew it)
    ds.set_epoch(1)
    second = real_ids(read(ds)[0])
    assert sorted(first) == sorted(second) and first != second


def test_a_checkpoint_resumes_at_another_world_size_without_a_repeat_or_a_loss(server):
    before = []
    for r in range(2):
        rows, position = read(V2VStreamDataset(server, 3, rank=r, world_size=2), steps=2)
        before += real_ids(rows)
    assert position["sample_in_epoch"] == 12
    ds = V2VStreamDataset(server, 5, rank=0, world_size=1)
    ds.load_state_dict(position)
    after = real_ids(read(ds, workers=2)[0])
    assert sorted(before + after) == sorted(set(before + after)) and len(before + after) == SAMPLES


def test_a_batch_of_padding_only_has_the_shapes_and_dtypes_of_a_batch_of_samples(server):
    """Batches of 5 over 2 ranks: rank 1's last step lies past the epoch's end (every row padding);
    its tensors are zeros of the shapes and dtypes of the batches that carry samples."""
    batches = list(torch.utils.data.DataLoader(V2VStreamDataset(server, 5, rank=1, world_size=2), batch_size=None))
    assert batches[-1]["padding"].all() and not batches[0]["padding"].any()
    for name, t in batches[-1].items():
        if isinstance(t, torch.Tensor) and name != "padding":
            assert (t.shape, t.dtype) == (batches[0][name].shape, batches[0][name].dtype), name
            assert not t.any(), name


def test_spawned_dataloader_workers_read_the_plan(server):
    rows, _ = read(V2VStreamDataset(server, 4), workers=2, context="spawn")
    assert len(set(real_ids(rows))) == SAMPLES


def test_two_jobs_read_one_server_at_once_each_its_own_whole_epoch(server):
    # a sweep: two trainers of other layouts, epochs and outputs share the decode workers; each
    # reads its epoch exactly, the same bytes as a job reading alone
    alone = {e: read(_at_epoch(V2VStreamDataset(server, 4), e))[0] for e in (0, 1)}
    got = {}

    def job(name, epoch, batch, outputs):
        got[name] = read(_at_epoch(V2VStreamDataset(server, batch, outputs=outputs), epoch))[0]

    threads = [threading.Thread(target=job, args=("a", 0, 3, ("voxels",))),
               threading.Thread(target=job, args=("b", 1, 5, ("voxels", "frames", "flow")))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    for name, epoch in (("a", 0), ("b", 1)):
        assert len(real_ids(got[name])) == len(set(real_ids(got[name]))) == SAMPLES
        assert [r for r in got[name] if not r[1]] == [r for r in alone[epoch] if not r[1]]


def _at_epoch(ds, epoch):
    ds.set_epoch(epoch)
    return ds


def test_a_position_of_another_plan_is_refused_in_one_line(server):
    ds = V2VStreamDataset(server, 4)
    _, position = read(ds, steps=1)
    position = {**position, "plan": {**position["plan"], "seed": 99}}
    other = V2VStreamDataset(server, 4)
    other.load_state_dict(position)
    with pytest.raises(PlanMismatch) as err:
        len(other)
    assert "\n" not in str(err.value) and "seed 99 (this plan: 0)" in str(err.value)


def test_epochs_read_in_turn_from_a_position_at_an_epochs_end_go_on_with_the_next(server):
    """``PlanEpochs`` (v2v-train's and v2v-loadtest's reader) resumed at the position kept after
    epoch 0's last step reads epoch 1 from its start, not an empty pass."""
    from v2v_client import PlanEpochs

    _, end = read(V2VStreamDataset(server, 4))
    assert (end["epoch"], end["sample_in_epoch"]) == (0, SAMPLES)
    epochs = PlanEpochs(V2VStreamDataset(server, 4))
    epochs.load_state_dict(end)
    it = iter(epochs)
    got = [next(it) for _ in range(SAMPLES // 4 + 1)]
    assert [int(b["epoch"]) for b in got] == [1] * (SAMPLES // 4) + [2]
    assert [b["position"]["sample_in_epoch"] for b in got] == [4 * (k + 1) for k in range(SAMPLES // 4)] + [4]


def test_a_corpus_never_scanned_unfolds_as_it_decodes_and_a_server_started_again_reads_its_index(tmp_path):
    """No pass before the first batch: the server learns each video's windows from its first
    decode, so ``len`` is unknown (TypeError, as for a dataset without one) until the epoch is
    read; the corpus index keeps what the decodes found, so a server started again knows the
    epoch at start and serves the same sequence, byte for byte."""
    from v2v_server.ops.plan_start import plan_manifest
    from v2v_server.ops.startup import start_source

    cfg = load_config(None, {**RECIPE, "cache_dir": str(tmp_path)})
    assert plan_manifest(start_source(cfg)).samples is None  # nothing known, nothing read
    with local_server(None, workers=2, batch_size=4, config=cfg) as endpoint:
        ds = V2VStreamDataset(endpoint, 3)
        with pytest.raises(TypeError, match="not known yet"):
            len(ds)
        first, _ = read(ds)
        assert len(real_ids(first)) == len(set(real_ids(first))) == SAMPLES
        assert len(ds) == -(-SAMPLES // 3)  # learned from the decodes
    manifest = plan_manifest(start_source(cfg))
    assert manifest.samples == SAMPLES
    with local_server(None, workers=1, batch_size=4, config=cfg) as endpoint:
        ds = V2VStreamDataset(endpoint, 3)
        assert len(ds) == -(-SAMPLES // 3)
        assert read(ds)[0] == first


def test_a_server_killed_mid_epoch_costs_only_the_fetches_in_flight(tmp_path):
    """``v2v-serve`` killed (SIGKILL) after two steps and started again on the same
    address: the reader asks its unanswered fetches again and gets the same epoch, bit for bit."""
    bind = f"tcp://127.0.0.1:{free_port()}"
    args = ["--sequence-length", "8", "--shuffle-buffer", "8", "--workers", "1",
            "--bind", bind]
    with ServeProcess(args, ready_timeout_s=120) as srv:
        whole, _ = read(V2VStreamDataset(bind, 4, retry_s=2.0, timeout_s=120))
        ds = V2VStreamDataset(bind, 4, retry_s=2.0, timeout_s=120)
        it = iter(torch.utils.data.DataLoader(ds, batch_size=None))
        got = [next(it), next(it)]
        srv.proc.send_signal(signal.SIGKILL)
        srv.proc.wait(10)
    with ServeProcess(args, ready_timeout_s=120) as srv:
        got += list(it)
        assert srv.stop() == 130  # SIGINT: one line, the shell's code for it
    assert "Traceback" not in srv.log
    ids = [sid for b in got for sid, pad in zip(b["sample_ids"], b["padding"].tolist()) if not pad]
    assert ids == real_ids(whole)
    again = [hashlib.sha1(b["voxels"][j].numpy().tobytes()).hexdigest()[:12] for b in got
             for j in range(len(b["sample_ids"])) if not b["padding"][j]]
    assert again == [d for _, pad, d in whole if not pad]


def test_a_hostile_client_gets_one_line_and_the_server_serves_on(server):
    import zmq

    from v2v_wire.protocol import pack, unpack

    plan = V2VStreamDataset(server, 1).plan_info().plan.to_dict()
    fetch = {"type": "fetch", "request": 7, "epoch": 0, "start": 0, "stop": 1, "outputs": ["voxels"], "plan": plan}
    ctx = zmq.Context()
    try:
        for bad, why, code in ((b"\xc1garbage", "not valid msgpack", "bad"),
                               (pack({**fetch, "stop": 10 ** 6}), "'stop'", "bad"),
                               (pack({**fetch, "v": 0}), "protocol version", "bad"),
                               (pack({**fetch, "outputs": ["x"]}), "outputs", "bad"),
                               (pack({**fetch, "plan": {**plan, "recipe": "0" * 16}}), "another plan: recipe", "plan")):
            sock = ctx.socket(zmq.DEALER)  # one peer each: a peer that keeps sending garbage is banned
            sock.setsockopt(zmq.LINGER, 0)
            sock.connect(server)
            sock.send(bad)
            assert sock.poll(10000)
            h = unpack(sock.recv_multipart()[0])
            sock.close()
            assert h["type"] == "refused" and why in h["message"] and "\n" not in h["message"]
            assert h["code"] == code, (why, h)
    finally:
        ctx.term()
    assert len(set(real_ids(read(V2VStreamDataset(server, 4))[0]))) == SAMPLES


def test_a_loop_stopped_past_the_task_timeout_costs_no_worker_and_no_window(caplog):
    """Workers are read whatever the readers do: a reader that stops for three task timeouts
    in the middle of an epoch finds every sample made, and no worker was called hung (the
    timeout is above a window's decode on a busy machine: a worker's own silence is not tested)."""
    import logging
    import time

    cfg = load_config(None, {**RECIPE, "task_timeout_s": 8.0})
    with caplog.at_level(logging.WARNING, logger="v2v.server"), \
            local_server(None, workers=2, batch_size=4, config=cfg) as endpoint:
        ds = V2VStreamDataset(endpoint, 2)
        it = iter(torch.utils.data.DataLoader(ds, batch_size=None))
        got = [next(it)]
        time.sleep(25.0)
        got += list(it)
    ids = [sid for b in got for sid, pad in zip(b["sample_ids"], b["padding"].tolist()) if not pad]
    assert len(ids) == len(set(ids)) == SAMPLES
    assert "worker restarted" not in caplog.text and "died" not in caplog.text


def _torchrun(nproc: int, *args) -> list:
    import json
    import sys

    out = Path(args[1])
    out.mkdir(exist_ok=True)
    for p in out.glob("rank*.json"):
        p.unlink()
    r = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(nproc),
                        "-m", "harness.plan_job", *[str(a) for a in args]], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    return [json.loads(p.read_text()) for p in sorted(out.glob("rank*.json"))]


def test_ddp_ranks_with_dataloader_workers_stop_mid_epoch_and_resume_at_another_world_size(server, tmp_path):
    """torchrun, 2 ranks, a plain DataLoader with 2 workers each, DDP steps: stopped after 3 steps
    of epoch 0, resumed from rank 0's position on 1 rank: each epoch's samples once."""
    first = _torchrun(2, server, tmp_path / "a", "--stop-after", "3")
    assert [r["steps"] for r in first] == [{"0": 3}, {"0": 3}]
    second = _torchrun(1, server, tmp_path / "b", "--resume", tmp_path / "a" / "position.json")
    seen = [tuple(s) for r in first + second for s in r["seen"]]
    for epoch in (0, 1):
        ids = [sid for e, sid in seen if e == epoch]
        assert len(ids) == len(set(ids)) == SAMPLES, epoch


def test_lightning_ddp_reads_the_plan_with_the_dataset_built_before_fit(server, tmp_path):
    """Lightning's Trainer (ddp, 2 CPU ranks, its fetcher a batch ahead), the dataset built before
    the process group exists and read through a DataLoader with 2 workers: the same steps on both
    ranks, every sample of the epoch once."""
    import json
    import sys

    out = tmp_path / "out"
    out.mkdir()
    # its own session: Lightning starts rank 1 as rank 0's child, so a hang is killed whole, with what it said
    proc = subprocess.Popen([sys.executable, "-m", "harness.lightning_ddp", server, str(out)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        _, err = proc.communicate(timeout=200)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        pytest.fail(f"the Lightning job ran past 200 s; it said: {proc.communicate(timeout=30)[1][-4000:]}")
    assert proc.returncode == 0, err[-3000:]
    ranks = [json.loads((out / f"rank{i}.json").read_text()) for i in range(2)]
    assert [r["dataset_world_size"] for r in ranks] == [2, 2]
    assert ranks[0]["batches"] == ranks[1]["batches"] == -(-SAMPLES // 4)
    seen = ranks[0]["seen"] + ranks[1]["seen"]
    assert len(seen) == len(set(seen)) == SAMPLES


def test_a_check_first_lets_a_server_serving_by_plan_know_the_epoch_at_start(tmp_path):
    """``v2v-serve --check`` fills the corpus index: a server serving by plan started after it
    knows every video's windows, so ``len`` answers before any decode."""
    out = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--check", "--cache-dir", str(tmp_path),
                          "--sequence-length", "8"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and f"{SAMPLES} sample(s) per epoch" in out.stdout, out.stderr
    cfg = load_config(None, {**RECIPE, "cache_dir": str(tmp_path)})
    with local_server(None, workers=1, batch_size=4, config=cfg) as endpoint:
        assert len(V2VStreamDataset(endpoint, 5)) == -(-SAMPLES // 5)



def test_a_dataset_is_truthy_without_asking_the_server():
    """``if ds:`` (Lightning modules and loops write it) is true at once: Python would otherwise ask
    ``len``, which asks the server and refuses while the epoch's length is not known."""
    ds = V2VStreamDataset("tcp://127.0.0.1:9", retry_s=1.0, timeout_s=1.0)  # no server there
    assert bool(ds) is True
    with pytest.raises(TimeoutError):
        len(ds)


def test_the_batch_size_is_the_servers_unless_given(server):
    ds = V2VStreamDataset(server, timeout_s=60)
    assert ds.batch_size == 4
    assert [len(b["padding"]) for b in ds] == [4] * -(-SAMPLES // 4)
    assert V2VStreamDataset(server, 3).batch_size == 3


def test_loadtest_reads_a_plans_epochs_in_turn_and_refuses_credits(server, capsys):
    """``v2v-loadtest`` at a server serving by plan reads epoch after epoch, as a trainer does,
    counting rows with a sample; ``--credits`` (push only) is refused in one line."""
    from v2v_client.loadtest import main, run_loadtest

    steps = SAMPLES // 4
    r = run_loadtest(server, steps + 2, timeout_s=60, warmup=0)
    assert r["batches"] == steps + 2 and r["epochs_seen"] == [0, 1]
    assert r["samples"] == (steps + 2) * 4 and r["unique_samples"] == r["samples"]
    assert main(["--connect", server, "--batches", "1", "--credits", "2"]) == 2
    assert capsys.readouterr().err.strip() == ("v2v-loadtest: --credits was push delivery's, which v2v no longer has: "
                                               "drop it (docs/delivery.md)")


def test_compressed_rows_are_the_batches_plain_rows_are(server):
    """With ``compression`` the server's workers compress each sample once and the rows travel as
    their frames (a padding row carries none): each batch decodes to the plain one, bit for bit,
    and the wire carries fewer bytes."""
    import numpy as np
    import zmq

    from v2v_wire.codecs import decode_batch_arrays
    from v2v_wire.plan_messages import Fetch, PlanAsk, plan_server_message
    from v2v_wire.protocol import decode_arrays, pack, unpack

    for codec in ("zstd", "lz4"):
        plain = list(V2VStreamDataset(server, outputs=("voxels", "frames", "flow"), compression="none", timeout_s=60))
        packed = list(V2VStreamDataset(server, outputs=("voxels", "frames", "flow"), compression=codec, timeout_s=60))
        assert len(plain) == len(packed) == -(-SAMPLES // 4)
        for a, b in zip(plain, packed):
            assert a["sample_ids"] == b["sample_ids"]
            for k in ("voxels", "frames", "flow", "padding"):
                assert torch.equal(a[k], b[k]), k
    ctx = zmq.Context()
    sock = ctx.socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(server)
    try:
        def ask(header):
            sock.send(pack(header))
            assert sock.poll(60_000)
            frames = sock.recv_multipart()
            return plan_server_message(unpack(frames[0])), frames[1:]

        info, _ = ask(PlanAsk().to_wire())
        assert "zstd" in info.stream["codecs"]
        # epoch 5, made after the reads above asked for zstd (none of it decoded ahead): every array as
        # compressed frames
        sizes = {}
        for codec in ("none", "zstd"):
            rows, frames = ask(Fetch(1, 5, SAMPLES - 4, SAMPLES + 2, ("voxels",), info.plan, codec).to_wire())
            assert rows.padding == [False] * 4 + [True] * 2
            arrays = decode_batch_arrays(rows.arrays, frames)
            sizes[codec] = sum(len(f) for f in frames)
            if codec == "none":
                want = decode_arrays(rows.arrays, frames)["voxels"]
            else:
                assert all(s.get("codec") == "zstd" for s in rows.arrays)
                assert np.array_equal(arrays["voxels"], want) and len(want) == 4  # the rows with a sample
        assert sizes["zstd"] * 3 < sizes["none"]
    finally:
        sock.close()
        ctx.term()


def test_a_corpus_with_every_kind_of_bad_file_holds_each_usable_sample_once_an_epoch(tmp_path):
    """``harness.corpus.make_fault_corpus`` (empty, truncated, random, unsupported and too short
    files, non-videos, links out of the corpus) and a file whose frame size changes, served by plan:
    each of two epochs holds every sample ``--check`` lists, once and nothing else (a bad file's
    slots are what its decode gave), each bad file is logged once, and no traceback."""
    from harness.corpus import make_fault_corpus, write_size_change_video
    from tests.test_scale_out import expected_ids, layout

    span = 4 * 5 + 1  # test_scale_out.layout's windows: 4 voxels of 5 bins
    corpus = tmp_path / "faulty"
    exp = make_fault_corpus(corpus, Path(__file__).resolve().parents[1] / "v2v_server" / "sample_videos", span)
    write_size_change_video(corpus / "size_change.mpg", span + span // 2, 2 * span)
    expected = expected_ids(corpus)
    assert any(s.startswith("size_change.mpg#") for s in expected)
    with ServeProcess(["--videos", str(corpus), *layout("--workers", "2")], ready_timeout_s=120) as srv:
        ds = V2VStreamDataset(srv.endpoint, timeout_s=120)
        for epoch in range(2):
            ds.set_epoch(epoch)
            rows, _ = read(ds)
            assert sorted(real_ids(rows)) == expected, epoch
        assert srv.stop() == 130
    skipped = [k for k, v in exp.items() if v == "skipped" and k != "deleted_during_epoch.mp4"]  # not deleted here
    assert len(skipped) == 7 and all(sum(f"{corpus / k}" in ln and "skipped" in ln for ln in srv.log.splitlines()) == 1 for k in skipped), srv.log
    assert "Traceback" not in srv.log

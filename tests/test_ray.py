"""V2V on Ray Data (``v2v_server.ray_data``) on a local Ray instance: same samples as the ZeroMQ path,
exactly once across 2 ranks, resume, bad files. One Ray session for the module (2 CPUs, no
dashboard); every test is bounded in time."""
from __future__ import annotations

import json
import logging
import re
import shutil
import subprocess
import sys
import threading
from collections import Counter

import numpy as np
import pytest

ray = pytest.importorskip("ray", reason="the 'ray' extra is not installed (pip install -e '.[ray]')")
pytest.importorskip("ray.data", reason="the 'ray' extra is not installed (pip install -e '.[ray]')")

from v2v_client import V2VStreamDataset  # noqa: E402
from v2v_server.ops.config import ServeConfig  # noqa: E402
from harness.serve import ServeProcess  # noqa: E402
from v2v_server.ray_data import epoch_descriptors, scan_corpus_windows, v2v_dataset  # noqa: E402

L, B, CROP, MAXW, SEED = 4, 5, 64, 3, 11
WINDOW = L * B + 1


def layout(**kw) -> ServeConfig:
    kw = {"max_samples_per_video": MAXW, **kw}
    return ServeConfig(sequence_length=L, num_bins=B, crop_size=CROP, seed=SEED, **kw)


def serve_args(videos, *extra):
    return ["--videos", str(videos), "--workers", "2", "--sequence-length", str(L), "--num-bins", str(B),
            "--crop-size", str(CROP), "--max-samples-per-video", str(MAXW), "--seed", str(SEED), *extra]


#: the clips the tests of padding, descriptors and training steps read: their counts (3 clips x 3
#: windows at L = 4) are facts of these files, so another bundled clip changes none of them
CLIPS = ("bigbuckbunny.mp4", "bikes.mp4", "webvid_like_596x336.mp4")


@pytest.fixture(scope="module")
def clips(tmp_path_factory, videos):
    """A folder holding copies of :data:`CLIPS` (a copy: the server refuses links leaving its root)."""
    d = tmp_path_factory.mktemp("clips")
    for name in CLIPS:
        shutil.copyfile(videos / name, d / name)
    return d


def checked_ids(root, cfg: ServeConfig) -> list:
    """Every sample id of one epoch of the folder ``root`` by ``--check``'s verdicts (the
    ZeroMQ path's scan, not the Ray engine's)."""
    from v2v_server.frames.check import check_corpus
    from v2v_server.sources.folder_scan import scan_corpus
    from v2v_server.sources.local import LocalSource

    vids = [p.as_posix() for p in scan_corpus(root, cfg.video_extensions)[0]]
    return sorted(f"{r.path}#{k}" for r in check_corpus(cfg.recipe.windows, cfg.recipe.decode, LocalSource(root),
                                                           vids)
                  for k in range(r.windows))


@pytest.fixture(scope="module")
def ray_session():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    ctx = ray.data.DataContext.get_current()
    ctx.enable_progress_bars = False
    yield
    ray.shutdown()


def rows_by_id(ds):
    out = {}
    for r in ds.take_all():
        assert r["sample_id"] not in out or r["padding"], f"{r['sample_id']} twice"
        if not r["padding"]:
            out[r["sample_id"]] = r
    return out


def plan_epoch(endpoint, epoch: int = 0, outputs=("voxels", "frames", "flow")):
    """The batches of ``epoch`` of the plan ``v2v-serve`` serves at ``endpoint``, in wire dtypes."""
    ds = V2VStreamDataset(endpoint, outputs=outputs, timeout_s=60, raw=True, rank=0, world_size=1)
    ds.set_epoch(epoch)
    return ds


@pytest.mark.timeout(240)
def test_epoch_has_every_id_once_and_the_zeromq_path_content(ray_session, videos):
    cfg = layout()
    want = checked_ids(videos, cfg)
    corpus = scan_corpus_windows(videos, cfg)
    assert corpus.samples_per_epoch == len(want) and not corpus.skipped
    ds = v2v_dataset(corpus, cfg, epoch=1)
    rows = ds.take_all()
    ids = [r["sample_id"] for r in rows]
    assert sorted(ids) == want and not any(r["padding"] for r in rows)
    with ServeProcess(serve_args(videos, "--batch-size", "4")) as srv:  # epoch 1 of its plan
        zmq_rows = {}
        for b in plan_epoch(srv.endpoint, 1):
            for i, sid in enumerate(b["sample_ids"]):
                if not b["padding"][i]:
                    zmq_rows[sid] = ({k: b[k][i].numpy() for k in ("voxels", "frames", "flow")}, b["params"][i])
    assert set(zmq_rows) == set(ids)
    for r in rows:
        arrays, params = zmq_rows[r["sample_id"]]
        assert r["voxels"].dtype == np.int16 and r["voxels"].shape == (L, B, CROP, CROP)
        np.testing.assert_array_equal(r["voxels"], arrays["voxels"].astype(np.int16))
        assert r["frames"].dtype == np.uint8 and r["frames"].shape == (L + 1, 1, CROP, CROP)
        np.testing.assert_array_equal(r["frames"], arrays["frames"])
        assert r["flow"].dtype == arrays["flow"].dtype == np.float16
        np.testing.assert_array_equal(r["flow"], arrays["flow"])
        # the params, statistics included (the flow's: of the tracked grid on both engines), are one
        assert json.loads(r["params"]) == params and "flow_mag" in params["stats"]
        assert np.abs(r["voxels"]).sum() > 0  # real events, not placeholder zeros


@pytest.mark.timeout(300)
def test_a_shard_is_the_same_samples_through_every_engine(ray_session, clips, tmp_path):
    """One start-up path (``ops.startup.start_source``): ``v2v-serve --shard 1/2``, the in-process
    server and the Ray engine with ``shard: 1/2`` serve the same ids with the same arrays, the
    same shard of the listing; a video the host's corpus index knows to give no window is left
    unopened by all three."""
    from harness.corpus import write_video
    from v2v_server.ops.startup import start_source
    from v2v_server.service.local import local_server

    # --check teaches the host's corpus index that brief.mp4 gives no window

    corpus = tmp_path / "corpus"
    shutil.copytree(clips, corpus)
    write_video(corpus / "brief.mp4", 9, 96, 64)  # shard 1 of 2 by its name; shorter than one window
    cache = tmp_path / "cache"
    cfg = layout(shard="1/2", cache_dir=str(cache), shot_cuts="off", batch_size=2)
    cli_args = serve_args(corpus, "--shard", "1/2", "--cache-dir", str(cache), "--shot-cuts", "off",
                          "--batch-size", "2")
    checked = subprocess.run([sys.executable, "-m", "v2v_server.cli", *cli_args, "--check"], capture_output=True,
                             text=True, timeout=120)
    assert checked.returncode == 0 and "brief.mp4" in checked.stdout, checked.stdout + checked.stderr
    start = start_source(cfg, str(corpus))
    assert start.videos == ["bigbuckbunny.mp4", "brief.mp4", "webvid_like_596x336.mp4"]
    assert list(start.skipped) == ["brief.mp4"] and "brief.mp4" not in start.served and start.listed == 4

    def stream(endpoint) -> dict:
        out = {}
        for b in plan_epoch(endpoint, 0, ("voxels", "frames")):
            for i, sid in enumerate(b["sample_ids"]):
                if b["padding"][i]:
                    continue
                assert sid not in out, sid
                out[sid] = (b["voxels"][i].numpy().astype(np.int16), b["frames"][i].numpy())
        return out

    with ServeProcess(cli_args) as srv:
        served = stream(srv.endpoint)
    assert "1 video(s) not opened" in srv.log
    with local_server(None, workers=1, batch_size=2, config=ServeConfig.from_dict(
            {**cfg.to_dict(), "videos": str(corpus)})) as endpoint:
        local = stream(endpoint)
    rows = {r["sample_id"]: r for r in v2v_dataset(corpus, cfg, epoch=0, outputs=("voxels", "frames")).take_all()}
    want = sorted(f"{v}#{k}" for v in ("bigbuckbunny.mp4", "webvid_like_596x336.mp4") for k in range(MAXW))
    assert sorted(served) == sorted(local) == sorted(rows) == want
    for sid in want:
        for got in (local[sid], (rows[sid]["voxels"], rows[sid]["frames"])):
            np.testing.assert_array_equal(got[0], served[sid][0])
            np.testing.assert_array_equal(got[1], served[sid][1])


@pytest.mark.timeout(240)
def test_two_ranks_get_equal_batches_and_the_epoch_exactly_once(ray_session, clips):
    cfg = layout(max_samples_per_video=2)  # 3 clips x 2 windows; minus one excluded: 5, odd
    corpus = scan_corpus_windows(clips, cfg)
    done = {"bikes.mp4#1"}
    want = {f"{v}#{k}" for v, n in corpus.windows.items() for k in range(n)} - done
    ds = v2v_dataset(corpus, cfg, epoch=0, outputs=("voxels",), exclude=done, ranks=2)
    splits = ds.streaming_split(2, equal=True)
    got = [[], []]
    batches = [0, 0]
    errors = []

    def consume(i):
        try:
            for b in splits[i].iter_batches(batch_size=2, batch_format="numpy"):
                batches[i] += 1
                got[i].extend(zip(b["sample_id"], b["padding"]))
                assert b["voxels"].shape[1:] == (L, B, CROP, CROP)
        except Exception as e:  # surfaced below
            errors.append(e)

    threads = [threading.Thread(target=consume, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(200)
    assert not errors and not any(t.is_alive() for t in threads)
    assert len(got[0]) == len(got[1]) == 3 and batches[0] == batches[1] == 2
    real = [sid for g in got for sid, pad in g if not pad]
    assert Counter(real) == Counter(want)  # every id once; the padding row repeats one of them
    assert sum(pad for g in got for _, pad in g) == 1


def test_descriptors_leave_consumed_ids_and_finished_videos_out(clips):
    cfg = layout()
    corpus = scan_corpus_windows(clips, cfg)
    done = {"bikes.mp4#0", "bikes.mp4#1", "bikes.mp4#2", "bigbuckbunny.mp4#1"}
    descs = epoch_descriptors(corpus, 3, done, ranks=4)
    assert "bikes.mp4" not in {d["video"] for d in descs}  # never opened
    entries = [tuple(e) for d in descs for e in json.loads(d["entries"])]
    assert len(entries) == 8 and all(d["epoch"] == 3 for d in descs)
    assert sorted(sid for sid, pad in entries if not pad) == sorted(
        {f"{v}#{k}" for v in corpus.windows for k in range(3)} - done)
    assert [sid for sid, pad in entries if pad] == ["bigbuckbunny.mp4#0", "bigbuckbunny.mp4#2", "webvid_like_596x336.mp4#0"]
    with pytest.raises(ValueError, match="ranks"):
        epoch_descriptors(corpus, 0, ranks=0)


@pytest.mark.timeout(240)
def test_resume_with_exclude_list_gives_the_rest_of_the_epoch(ray_session, videos):
    cfg = layout(max_samples_per_video=2)
    first = rows_by_id(v2v_dataset(videos, cfg, epoch=2, outputs=("frames",)))
    consumed = sorted(first)[:4]
    rest = rows_by_id(v2v_dataset(videos, cfg, epoch=2, outputs=("frames",), exclude=consumed))
    assert set(rest) == set(first) - set(consumed)
    for sid, r in rest.items():  # the same samples as in the uninterrupted epoch
        np.testing.assert_array_equal(r["frames"], first[sid]["frames"])
        assert r["params"] == first[sid]["params"]


@pytest.mark.timeout(240)
def test_bad_files_are_skipped_with_the_servers_reasons(ray_session, videos, tmp_path, caplog):
    from harness.corpus import write_video

    root = tmp_path / "corpus"
    root.mkdir()
    shutil.copy(videos / "bikes.mp4", root / "bikes.mp4")
    shutil.copy(videos / "bikes.mp4", root / "deleted_after_scan.mp4")
    (root / "zero_length.mp4").write_bytes(b"")
    (root / "random_bytes.mp4").write_bytes(np.random.default_rng(0).bytes(50_000))
    write_video(root / "shorter_than_window.mp4", WINDOW - 1, 160, 120)
    cfg = layout()
    with ServeProcess(serve_args(root)) as srv:  # what v2v-serve says about them, reading an epoch
        for _ in plan_epoch(srv.endpoint, 0, ("voxels",)):
            pass
    served = dict(re.findall(r"skipped (\S+): (.*)", srv.log))
    with caplog.at_level(logging.WARNING, logger="v2v.ray"):
        corpus = scan_corpus_windows(root, cfg)
    mine = {str(root / k): v for k, v in corpus.skipped.items()}
    assert set(mine) == {str(root / n) for n in ("zero_length.mp4", "random_bytes.mp4", "shorter_than_window.mp4")}
    assert {k: served[k] for k in mine} == mine  # same verdicts, word for word
    for path, reason in mine.items():
        assert f"skipped {path}: {reason}" in caplog.text
    # a file that goes bad after the scan: its rows become padding carrying the reason; the job goes on
    (root / "deleted_after_scan.mp4").unlink()
    rows = v2v_dataset(corpus, cfg, outputs=("voxels",), ranks=2).take_all()
    good = sorted(r["sample_id"] for r in rows if not r["padding"])
    assert good == [f"bikes.mp4#{k}" for k in range(3)]
    lost = [json.loads(r["params"]) for r in rows if r["sample_id"].startswith("deleted_after_scan")]
    assert len(lost) == 3 and all(p["skipped"] == "missing, or points outside the corpus root" for p in lost)
    assert len(rows) == 6 and all(r["padding"] for r in rows if r["sample_id"].startswith("deleted"))


@pytest.mark.timeout(400)
def test_v2v_train_on_two_ray_ranks_resumes_without_the_consumed_ids(ray_session, clips, tmp_path):
    import csv

    import torch

    import trainer.train as tr
    from trainer.config import apply_overrides, load_config
    from trainer.ray_train import _State

    (tmp_path / "serve.yaml").write_text("sequence_length: 4\nnum_bins: 3\ncrop_size: 32\nmax_samples_per_video: 3\n"
                                         "seed: 5\n")
    out = tmp_path / "run"
    sets = ["model.num_bins=3", "model.base_num_channels=4", "log.checkpoint_every=1", "log.image_every=0"]
    # a checkpoint of an earlier run that had trained on 4 of the epoch's 9 samples
    cfg = apply_overrides(load_config(None, "evflow"), sets)
    first = ["bigbuckbunny.mp4#0", "bigbuckbunny.mp4#2", "bikes.mp4#1", "webvid_like_596x336.mp4#2"]
    before = tr.Trainer(cfg, str(out), torch.device("cpu"))
    before.save_checkpoint(_State({"engine": "ray", "consumed": {0: first}, "epochs_done": []}))
    argv = ["--engine", "ray", "--videos", str(clips), "--serve-config", str(tmp_path / "serve.yaml"),
            "--task", "evflow", "--out", str(out), "--device", "cpu", "--no-progress", "--num-workers", "2",
            "--cpus-per-worker", "0.5", "--batch-size", "2", "--max-steps", "50", "--resume", "auto"]
    assert tr.main(argv + [a for kv in sets for a in ("--set", kv)]) == 0
    # 5 samples left + 1 padding row = 3 rows per rank: batches of 2 and 1 on each rank
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ranks"] == 2 and summary["steps"] == 2 and summary["samples"] == 5
    step1 = torch.load(out / "checkpoint_0000001.pt", weights_only=False)["stream_state"]
    # both ranks' ids: step 1 takes 2 rows on each rank, and the padding row lands in step 1
    # or step 2 depending on how Ray splits the blocks (3 or 4 real ids on top of the 4 before)
    assert set(first) < set(step1["consumed"][0]) and len(step1["consumed"][0]) in (6, 7, 8)
    last = torch.load(out / "checkpoint_last.pt", weights_only=False)
    # the epoch counts as done only when the union of consumed ids holds all 9 (5 + 4 trained: none twice)
    assert last["step"] == 2 and last["stream_state"] == {"engine": "ray", "consumed": {}, "epochs_done": [0]}
    rows = list(csv.DictReader(open(out / "train_log.csv")))
    assert [int(r["step"]) for r in rows] == [1, 2]
    assert all(np.isfinite(float(r["loss"])) for r in rows if int(r["samples"]))
    # rank 0's TensorBoard events, under the stream engine's tags (trainer/tensorboard_log.py)
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    assert len(list(out.glob("events.out.tfevents.*"))) == 1
    acc = EventAccumulator(str(out), size_guidance={"scalars": 0, "tensors": 0})
    acc.Reload()
    assert [(e.step, e.value) for e in acc.Scalars("stream/samples")] == [(int(r["step"]), float(r["samples"]))
                                                                           for r in rows]
    assert [e.step for e in acc.Scalars("loss/total")] == [1, 2]
    assert {"config/text_summary", "recipe/text_summary"} <= set(acc.Tags()["tensors"])
    assert tr.main(argv + [a for kv in sets for a in ("--set", kv)]) == 0  # nothing left: returns at once


@pytest.mark.timeout(400)
def test_v2v_train_fast_on_two_ray_ranks_steps_as_one_process(ray_session, clips, tmp_path):
    """``v2v-train --engine ray --set speed=fast`` on 2 ranks trains channels-last E2VID with the
    fused Adam; its parameters after its 2 steps equal those of one process taking the same 2
    steps on the union of the ranks' samples: in each tensor at most 1 % of the elements (one in
    small ones) differ by more than 1e-6, 1 % of one step at lr 1e-4. The ranks' weighted sum and
    the one batch's mean differ by rounding only, but rounding can flip the sign of an element's
    near-zero gradient, which Adam's normalised step turns into up to 2 x lr for that element
    (seen: 4 of 9216 elements at 5e-6, and on another split 1.08e-6); a gradient in
    the wrong layout moves most elements."""
    import torch

    import trainer.train as tr
    from trainer.core import Trainer
    from trainer.ray_train import V2VCollate
    from trainer.tasks import stream_outputs
    from v2v_server.ops.config import load_config as load_serve_config

    serve_yaml = tmp_path / "serve.yaml"
    serve_yaml.write_text("sequence_length: 3\nnum_bins: 3\ncrop_size: 32\nmax_samples_per_video: 2\nseed: 5\n")
    out = tmp_path / "run"
    sets = ["model.num_bins=3", "model.base_num_channels=4", "speed=fast", "log.checkpoint_every=1",
            "log.image_every=0"]
    argv = ["--engine", "ray", "--videos", str(clips), "--serve-config", str(serve_yaml), "--task", "e2vid",
            "--out", str(out), "--device", "cpu", "--no-progress", "--num-workers", "2", "--cpus-per-worker", "0.5",
            "--batch-size", "2", "--max-steps", "50"]
    assert tr.main(argv + [a for kv in sets for a in ("--set", kv)]) == 0
    # 6 samples, 3 rows per rank in 2 steps (how many in which step depends on Ray's blocks)
    first = set(torch.load(out / "checkpoint_0000001.pt", weights_only=False)["stream_state"]["consumed"][0])
    last = torch.load(out / "checkpoint_last.pt", weights_only=False)
    assert last["step"] == 2 and last["config"]["speed"] == "fast" and 0 < len(first) < 6

    scfg = load_serve_config(str(serve_yaml), {})
    rows = v2v_dataset(scan_corpus_windows(clips, scfg), scfg, epoch=0,
                       outputs=stream_outputs(last["config"])).take_all()
    assert len(rows) == 6 and first < {r["sample_id"] for r in rows}

    def batch(keep):
        chosen = [r for r in rows if keep(r["sample_id"])]
        return V2VCollate(False)({k: np.stack([r[k] for r in chosen]) for k in chosen[0]})

    one = Trainer(last["config"], str(tmp_path / "one"), torch.device("cpu"))
    assert one.model.unetrecurrent.head.conv2d.weight.is_contiguous(memory_format=torch.channels_last)
    for b in (batch(lambda s: s in first), batch(lambda s: s not in first)):
        one.train_step(b)
    ray_sd = last["model"]
    for k, v in one.model.state_dict().items():
        diff = (ray_sd[k].double() - v.double()).abs()
        off = int((diff > 1e-6).sum())
        assert off <= max(1, diff.numel() // 100), \
            f"{k}: {off} of {diff.numel()} elements differ by more than 1e-6 (largest {float(diff.max()):.3g})"


@pytest.mark.timeout(300)
def test_ray_train_ranks_read_a_plan_each_its_slice_and_the_epoch_exactly_once(ray_session, clips, tmp_path):
    """Ray Train's ``TorchTrainer`` on 2 ranks over ``v2v-serve``: each rank's
    ``V2VStreamDataset`` finds its rank in the process group Ray Train made, both take the same
    number of steps, and the epoch's samples arrive once, those ``--check`` counts."""
    from pathlib import Path

    from ray.train import RunConfig, ScalingConfig
    from ray.train.torch import TorchTrainer

    def loop(config):
        import torch
        import torch.distributed as dist

        from v2v_client import V2VStreamDataset

        ds = V2VStreamDataset(config["endpoint"], 2, outputs=("voxels",))
        steps = [[sid for sid, pad in zip(b["sample_ids"], b["padding"].tolist()) if not pad]
                 for b in torch.utils.data.DataLoader(ds, batch_size=None)]
        Path(config["out"], f"rank{dist.get_rank()}.json").write_text(
            json.dumps({"world": dist.get_world_size(), "steps": steps}))

    with ServeProcess(serve_args(clips)) as srv:
        TorchTrainer(loop, train_loop_config={"endpoint": srv.endpoint, "out": str(tmp_path)},
                     scaling_config=ScalingConfig(num_workers=2, resources_per_worker={"CPU": 0.5}),
                     run_config=RunConfig(storage_path=str(tmp_path / "ray"), name="plan")).fit()
    ranks = [json.loads((tmp_path / f"rank{r}.json").read_text()) for r in range(2)]
    assert [r["world"] for r in ranks] == [2, 2] and len(ranks[0]["steps"]) == len(ranks[1]["steps"])
    ids = [sid for r in ranks for step in r["steps"] for sid in step]
    assert Counter(ids) == Counter(checked_ids(clips, layout()))


"""TensorBoard event files of a run (trainer/tensorboard_log.py): a short v2v-train run on the
CPU against the FakeV2VStream fixture, resumed from an earlier checkpoint, then v2v-eval into
the same run; the event files read back with TensorBoard's own EventAccumulator."""
from __future__ import annotations

import csv
import json
import time
from pathlib import Path

import pytest
import torch

pytest.importorskip("tensorboard")
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator  # noqa: E402

from tests.test_trainer_eval import write_moving_edge_h5  # noqa: E402
from tests.trainer_fixtures import FakeV2VStream  # noqa: E402
from trainer.tasks import get_task  # noqa: E402
from trainer.tensorboard_log import PREVIEW_TAG, WAIT_FRACTION_TAG, column_tag  # noqa: E402

torch.set_num_threads(2)


def _events(run: Path) -> EventAccumulator:
    acc = EventAccumulator(str(run), size_guidance={"scalars": 0, "images": 0, "tensors": 0})
    acc.Reload()
    return acc


def _train(monkeypatch, out: Path, *extra: str) -> int:
    import trainer.train as tr

    monkeypatch.setattr(tr, "make_stream", lambda endpoint, task, timeout_s, raw, **kw:
                        FakeV2VStream(outputs=get_task(task).outputs, num_batches=10, raw=raw))
    return tr.main(["--config", "trainer/configs/evflow.yaml", "--connect", "tcp://127.0.0.1:1", "--out", str(out),
                    "--device", "cpu", "--no-progress", "--set", "model.base_num_channels=4",
                    "--set", "model.num_bins=3", "--set", "log.every=2", "--set", "log.image_every=2",
                    "--set", "log.checkpoint_every=2", *extra])


def test_a_resumed_run_and_its_evaluation_read_back_as_the_csv_once_per_step(tmp_path, monkeypatch):
    run = tmp_path / "run"
    assert _train(monkeypatch, run, "--max-steps", "4") == 0
    # TensorBoard reads a run's event files in name order: a time in seconds, then this process's
    # writer count, not zero-padded (9 sorts after 10); sessions a second apart, as processes are
    time.sleep(1.05 - time.time() % 1)
    # resumed from step 2: steps 3 and 4 of the first session are trained and logged again
    assert _train(monkeypatch, run, "--max-steps", "5", "--resume", str(run / "checkpoint_0000002.pt")) == 0
    rows = list(csv.DictReader(open(run / "train_log.csv")))
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4, 5]
    acc = _events(run)
    scalars = set(acc.Tags()["scalars"])
    for column in rows[0]:
        tag = column_tag(column)
        if tag is None or rows[0][column] == "":
            continue
        assert tag in scalars, column
        events = acc.Scalars(tag)
        assert [e.step for e in events] == [1, 2, 3, 4, 5], tag  # each step once, the resumed session's
        for e, r in zip(events, rows):
            assert e.value == pytest.approx(float(r[column]), rel=1e-6, abs=1e-6), (tag, e.step)
    assert {"loss/total", "loss/flow_l1", "optim/lr", "optim/grad_norm", "speed/samples_per_s"} <= scalars
    assert all(float(r["grad_norm"]) > 0 and float(r["samples_per_s"]) > 0 for r in rows)
    waits = acc.Scalars(WAIT_FRACTION_TAG)
    assert [e.step for e in waits] == [2, 4, 5] and all(0 <= e.value <= 1 for e in waits)
    images = acc.Images(PREVIEW_TAG)
    assert [e.step for e in images] == [2, 4, 5]
    assert images[0].width > images[0].height > 0  # voxel | prediction | ground truth side by side
    assert {"config/text_summary", "recipe/text_summary"} <= set(acc.Tags()["tensors"])
    # each session's recipe text: the stream's recipe(), as JSON (a plan's: tests/test_trainer_stream.py)
    recipes = acc.Tensors("recipe/text_summary")
    assert [e.step for e in recipes] == [1, 3]
    expected = FakeV2VStream(outputs=get_task("evflow").outputs, num_batches=10).recipe()
    assert all(json.loads(e.tensor_proto.string_val[0].decode()) == expected for e in recipes)
    # where each batch lay in its epoch (its position): the resumed session's go on from step 2's
    assert [int(r["sample_in_epoch"]) for r in rows] == [2, 4, 6, 8, 10]

    from trainer.evaluate import main as v2v_eval

    h5 = tmp_path / "edge.h5"
    write_moving_edge_h5(h5)
    assert v2v_eval(["--checkpoint", str(run / "checkpoint_last.pt"), "--h5", str(h5), "--device", "cpu",
                     "--tensorboard", str(run)]) == 0
    acc = _events(run)
    aee = acc.Scalars("eval/aee")
    assert [e.step for e in aee] == [5] and aee[0].value > 0
    assert [e.step for e in acc.Scalars("loss/total")] == [1, 2, 3, 4, 5]  # the training curves stay


def test_no_tensorboard_writes_no_event_files_and_eval_refuses_a_missing_run(tmp_path, monkeypatch, capsys):
    assert _train(monkeypatch, tmp_path / "run", "--max-steps", "1", "--no-tensorboard") == 0
    assert (tmp_path / "run" / "train_log.csv").exists()
    assert not list((tmp_path / "run").glob("events.out.tfevents.*"))
    from trainer.evaluate import main as v2v_eval

    missing = tmp_path / "no-run"
    assert v2v_eval(["--checkpoint", str(tmp_path / "run" / "checkpoint_last.pt"), "--h5", "x.h5",
                     "--tensorboard", str(missing)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == f"v2v-eval: --tensorboard {missing}: not a folder (give a v2v-train run's --out)"
    assert not missing.exists()

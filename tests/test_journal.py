"""The delivery journal (--state-dir): records survive a restart, a resume state replaces a
record, closed epochs beyond the newest kept ones are dropped (but for a consumer told fewer newer
ones complete), a torn last record costs only itself, another recipe's journal is refused."""
from __future__ import annotations

import pytest

import msgpack

from v2v_server.delivery.journal import FILE, Journal, JournalError
from v2v_wire.ids import SampleKey as K


def test_records_survive_a_restart_and_a_resume_state_replaces_them(tmp_path):
    j = Journal(str(tmp_path), "r1")
    a, b = ("c:a", 0), ("c:b", 0)
    j.delivered(a, 0, [K("x.mp4", 0), K("x.mp4", 1)])
    j.delivered(b, 0, [K("y.mp4", 0)])
    j.delivered(a, 1, [K("x.mp4", 0)])
    j.replaced(b, -1, {0: {K("y.mp4", 0), K("y.mp4", 1)}})
    j.close()  # a killed server leaves the same file: every record is one write
    k = Journal(str(tmp_path), "r1")
    assert k.records == {a: {0: {K("x.mp4", 0), K("x.mp4", 1)}, 1: {K("x.mp4", 0)}},
                         b: {0: {K("y.mp4", 0), K("y.mp4", 1)}}}
    k.epoch_complete(0)
    k.close()
    m = Journal(str(tmp_path), "r1", keep_epochs=1)  # epoch 0 is the newest closed one: kept
    assert m.completed == 0 and m.records == k.records == {
        a: {0: {K("x.mp4", 0), K("x.mp4", 1)}, 1: {K("x.mp4", 0)}}, b: {0: {K("y.mp4", 0), K("y.mp4", 1)}}}
    m.consumer_told(a, 1)
    m.consumer_told(b, 1)
    m.epoch_complete(1)
    m.close()
    n = Journal(str(tmp_path), "r1", keep_epochs=1)  # epoch 1 closed and told to both: epoch 0 leaves the file
    assert n.completed == 1 and n.records == {a: {1: {K("x.mp4", 0)}}}
    n.close()


def test_a_ddp_ranks_batch_counts_survive_a_restart_a_release_a_resume_state_and_a_rewrite(tmp_path):
    """Each grant record is one batch; a release takes one back; a resume state sets the counts
    it yielded; a rewrite keeps the sums: a restarted server tells a DDP group the counts its
    ranks' grants reached (docs/delivery.md, "DDP"; simulator findings F32, F33)."""
    j = Journal(str(tmp_path), "r1")
    r0, r1 = ("g:job", 0), ("g:job", 1)
    for i in range(3):
        j.delivered(r0, 0, [K("x.mp4", i)])
    j.delivered(r0, 1, [K("x.mp4", 0)])
    j.undelivered(r0, 1, [K("x.mp4", 0)])  # granted, then given back unused
    j.delivered(r1, 0, [K("x.mp4", 3)])
    j.delivered(r1, 0, [K("x.mp4", 4)])
    j.replaced(r1, -1, {0: {K("x.mp4", 3)}}, {0: 1})  # its state was saved after one batch
    j.delivered(r1, 1, [K("y.mp4", 0)])
    j.close()
    k = Journal(str(tmp_path), "r1")
    assert k.batches == {r0: {0: 3, 1: 0}, r1: {0: 1, 1: 1}}
    k.epoch_complete(0)  # rewritten: one record per consumer and epoch
    k.close()
    m = Journal(str(tmp_path), "r1")
    assert m.batches == {r0: {0: 3, 1: 0}, r1: {0: 1, 1: 1}}
    m.close()


def test_a_torn_last_record_costs_only_itself_and_another_recipe_is_refused(tmp_path):
    j = Journal(str(tmp_path), "r1")
    j.delivered(("c:a", 0), 0, [K("x.mp4", 0)])
    j.delivered(("c:a", 0), 0, [K("x.mp4", 1)])
    j.close()
    p = tmp_path / FILE
    p.write_bytes(p.read_bytes()[:-3])  # the server died inside the last write
    k = Journal(str(tmp_path), "r1")
    assert k.records == {("c:a", 0): {0: {K("x.mp4", 0)}}}
    k.close()
    with pytest.raises(JournalError, match="another sample recipe"):
        Journal(str(tmp_path), "r2")
    (tmp_path / FILE).write_bytes(b"not a journal")
    with pytest.raises(JournalError, match="not a v2v delivery journal"):
        Journal(str(tmp_path), "r1")


def test_records_name_samples_by_their_number_in_the_video_and_read_back_as_keys(tmp_path):
    """On disk a record holds ``[video, index]`` (index = window x K + crop), the format state
    directories already hold; read back under the recipe's K it gives the same keys."""
    j = Journal(str(tmp_path), "r1", crops_per_window=3)
    j.delivered(("c:a", 0), 0, [K("x.mp4", 2, 1), K("x.mp4", 0, 0)])
    j.close()
    records = list(msgpack.Unpacker(open(tmp_path / FILE, "rb"), raw=False))
    assert records[-1] == {"d": ["c:a", 0], "e": 0, "k": [["x.mp4", 7], ["x.mp4", 0]]}
    k = Journal(str(tmp_path), "r1", crops_per_window=3)
    assert k.records == {("c:a", 0): {0: {K("x.mp4", 2, 1), K("x.mp4", 0, 0)}}}
    k.close()


def test_a_folder_that_fails_while_serving_is_counted_and_written_again_whole(tmp_path):
    """The state folder replaced by a file while serving: the failed write is told (the server
    counts and logs it) and never raised; records stay current in memory and, once the folder
    can be made again, the file is written again whole, so a restart reads every record."""
    import shutil

    d = tmp_path / "state"
    told = []
    j = Journal(str(d), "r1", on_error=lambda path, e: told.append((path, type(e).__name__)))
    a = ("c:a", 0)
    j.delivered(a, 0, [K("x.mp4", 0)])
    shutil.rmtree(d)
    d.write_text("a file where the folder was")
    j.delivered(a, 1, [K("x.mp4", 0)])  # appended to the open, unlinked file: lost with it
    j.epoch_complete(0)  # the whole write fails
    assert told == [(d / FILE, "NotADirectoryError")] and j.failed
    j.delivered(a, 1, [K("x.mp4", 1)])
    j.sync(0.0)  # before RETRY_S: nothing tried
    assert len(told) == 1
    j.sync(1e12)  # still a file: tried, told again
    assert len(told) == 2 and j.failed
    d.unlink()
    j.sync(2e12)
    assert not j.failed
    j.delivered(a, 1, [K("x.mp4", 2)])
    j.close()
    k = Journal(str(d), "r1")
    assert k.completed == 0 and k.records == {a: {0: {K("x.mp4", 0)}, 1: {K("x.mp4", 0), K("x.mp4", 1), K("x.mp4", 2)}}}
    k.close()


def test_unusable_state_dir_at_start_is_one_clear_line(tmp_path):
    """``--state-dir`` naming a file: v2v-serve exits 2 with one line naming it. The journal is
    the promise that a restart repeats nothing; serving without it would break that silently."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    bad = tmp_path / "state"
    bad.write_text("a file")
    r = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--videos", str(root / "v2v_server" / "sample_videos"),
                        "--delivery", "push", "--epochs", "1", "--bind", "tcp://127.0.0.1:0", "--state-dir", str(bad)],
                       capture_output=True, text=True, timeout=60, env=dict(os.environ, PYTHONPATH=str(root)))
    lines = [line for line in r.stderr.strip().splitlines() if "v2v-serve:" in line and " INFO " not in line]
    assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith(f"v2v-serve: --state-dir {bad}:"), r.stderr


def test_a_terminal_gone_turns_the_progress_line_off_and_is_counted_once(monkeypatch, caplog):
    """The progress line's stderr a pipe nobody reads any more (a hung-up terminal): the write
    fails (BrokenPipeError), the line goes off, serving's counters go on, one count and one log
    line with where it happened."""
    import logging
    import os
    import sys

    from v2v_server.ops.metrics import ServerMetrics

    r, w = os.pipe()
    os.close(r)
    stream = os.fdopen(w, "w", buffering=1)
    monkeypatch.setattr(sys, "stderr", stream)
    m = ServerMetrics(progress=True)
    with caplog.at_level(logging.ERROR, logger="v2v.metrics"):
        for _ in range(50):  # tqdm writes at its own pace: enough batches for it to write
            m.on_batch_sent(4, 1000)
    monkeypatch.undo()
    assert m.fs_errors_total("progress") == 1
    assert m.totals()["batches_sent"] == 50
    assert sum("progress" in rec.getMessage() for rec in caplog.records) == 1
    try:
        stream.close()
    except OSError:
        pass


def test_a_grant_given_back_unused_leaves_the_record_after_a_restart(tmp_path):
    """A granted batch is journaled before its grant is sent; given back unused, its samples
    leave the consumer's record, and a restarted server reads both records."""
    j = Journal(str(tmp_path), "r1")
    a = ("c:a", 0)
    j.delivered(a, 0, [K("x.mp4", 0), K("x.mp4", 1)])
    j.delivered(a, 0, [K("x.mp4", 2)])
    j.undelivered(a, 0, [K("x.mp4", 2)])
    j.close()
    k = Journal(str(tmp_path), "r1")
    assert k.records == {a: {0: {K("x.mp4", 0), K("x.mp4", 1)}}}
    k.close()


def test_the_journals_bench_drives_the_core_it_measures(tmp_path):
    """``python -m bench.journal`` (docs/delivery.md's cost of ``--state-dir``) runs against the
    core as it is: both runs acknowledge batches, the journal's run leaves a journal whose
    records a restart reads."""
    from bench.journal import run

    assert run(30, 12) > 0
    assert run(30, 12, str(tmp_path)) > 0
    kept = Journal(str(tmp_path), "bench")
    recorded = sum(len(keys) for record in kept.records.values() for keys in record.values())
    assert recorded >= 30 * 12 and recorded % 12 == 0, recorded  # whole batches, at least those asked for
    kept.close()


@pytest.mark.parametrize("epochs,first", [(None, 1), (3, 1), (1, None)])
def test_a_server_restarted_after_an_epoch_completed_starts_after_it(tmp_path, epochs, first):
    """A server killed as epoch 0 completed leaves a journal with its watermark (and epoch 0's
    records, kept as complete): the restarted server makes epoch 1 (or nothing more, when
    epoch 0 was the last), never epoch 0 again (it had doubled a whole epoch for a new reader)."""
    from v2v_server.delivery.core import DeliveryCore, DeliveryPolicy
    from v2v_wire.messages import Hello

    j = Journal(str(tmp_path), "r1")
    j.delivered(("c:a", 0), 0, [K("a.mp4", 0)])
    j.epoch_complete(0)
    j.close()
    k = Journal(str(tmp_path), "r1")
    assert k.completed == 0 and k.records == {("c:a", 0): {0: {K("a.mp4", 0)}}}
    core = DeliveryCore(["a.mp4"], DeliveryPolicy(batch_size=1, epochs=epochs, lease_s=100.0, client_timeout_s=100.0,
                                                  max_credits=4, task_timeout_s=100.0), list, journal=k)
    core.hello(b"v", Hello(("voxels",), 2), 0.0)
    task = core.task_for(b"w", 0.0)
    assert (task.epoch if task is not None else None) == first
    k.close()


def test_a_resume_older_than_an_epoch_the_restarted_server_closed_gets_that_epoch_again(tmp_path):
    """A trainer's checkpoint predates epoch 0's completion, and the server restarts from its
    journal after epoch 0 closed: as the server that closed it would (it keeps the newest
    complete epochs), the restarted one reopens epoch 0 for that trainer's samples its model
    lost, and makes only those (the other reader's stay its own): none reaches no loop
    (docs/delivery.md limit (e); simulator finding F1, `trainers` seed 0)."""
    from v2v_server.delivery.core import DeliveryCore, DeliveryPolicy
    from v2v_wire.messages import Hello, Resume

    j = Journal(str(tmp_path), "r1")
    j.delivered(("c:a", 0), 0, [K("a.mp4", 0), K("a.mp4", 1)])
    j.delivered(("c:b", 0), 0, [K("a.mp4", 2), K("a.mp4", 3)])
    j.epoch_told(0)
    j.epoch_complete(0)
    j.close()
    k = Journal(str(tmp_path), "r1")
    core = DeliveryCore(["a.mp4"], DeliveryPolicy(batch_size=1, epochs=2, lease_s=100.0, client_timeout_s=100.0,
                                                  max_credits=4, task_timeout_s=100.0), list, journal=k)
    core.hello(b"a", Hello(("voxels",), 2, consumer="a", resume=Resume(-1, {0: frozenset({K("a.mp4", 0)})})), 0.0)
    task = core.task_for(b"w", 0.0)
    assert task is not None and task.epoch == 0 and task.video == "a.mp4"
    assert set(task.skip) == {(0, 0), (2, 0), (3, 0)}  # (window, crop): a.mp4#1 only is owed again
    k.close()


def test_a_restarted_server_still_refuses_a_resume_further_behind_than_its_consumer_was_told(tmp_path):
    """The newest epoch each consumer was told complete is journaled: a server restarted after
    reader a was told every epoch complete still refuses a's resume from before epoch 0 ended
    (its records of epoch 0 are gone: its loss would be silent), and lets in one within two
    epochs (docs/delivery.md limit (e); simulator finding F20)."""
    from tests.test_delivery_core import TinyStream
    from v2v_wire.messages import Hello, Resume

    s = TinyStream(Journal(str(tmp_path), "r1"))
    s.read_every_epoch(b"a", "a")
    s.core.journal.close()
    t = TinyStream(Journal(str(tmp_path), "r1"))
    assert t.core.journal.told_to == {("c:a", 0): 2}
    [(_, err)] = t.core.hello(b"a.2", Hello(("voxels",), 1, consumer="a", resume=Resume(-1, {})), 0.0)
    assert err.code == "resume" and "up to 2" in err.message, err
    [(_, welcome)] = t.core.hello(b"a.3", Hello(("voxels",), 1, consumer="a", resume=Resume(1, {})), 0.0)
    assert welcome.to_wire()["type"] == "welcome", welcome
    t.core.journal.close()


def _first_life(tmp_path, a_told: int) -> None:
    """A server's life over a journal: reader a was granted a.mp4#0 of epoch 0, told epochs up to
    ``a_told`` complete and killed; reader b read everything else of 3 epochs and was told each
    complete; the server closed all three (the records of a consumer told are journaled before the
    epoch closes, as ``closing.EpochEnds`` does, and told again after)."""
    a, b = ("c:a", 0), ("c:b", 0)
    j = Journal(str(tmp_path), "r1")
    j.delivered(a, 0, [K("a.mp4", 0)])
    j.delivered(b, 0, [K("a.mp4", 1), K("a.mp4", 2), K("a.mp4", 3)])
    for e in (1, 2):
        j.delivered(b, e, [K("a.mp4", i) for i in range(4)])
    j.epoch_told(2)
    j.consumer_told(a, min(a_told, 1))
    j.consumer_told(b, 1)
    j.epoch_complete(2)
    j.consumer_told(a, a_told)
    j.consumer_told(b, 2)
    j.close()


def test_a_restarted_server_keeps_a_lagging_consumers_records_of_an_older_epoch(tmp_path):
    """Reader a was told epochs 0 and 1 complete (not 2) holding a sample of epoch 0, then
    resumes from a checkpoint of no sample against a server restarted from its journal. A
    running server keeps a's records of epoch 0 (within two epochs of what it was told) and
    makes that sample again; the restarted one must too: it answered epoch_done 0, 1, 2 and end,
    and the sample reached no loop, in silence (docs/delivery.md limit (e); simulator finding
    F39, ``mixed`` seed 12000)."""
    from tests.test_delivery_core import TinyStream
    from v2v_wire.messages import Resume

    _first_life(tmp_path, a_told=1)
    t = TinyStream(Journal(str(tmp_path), "r1"))
    assert t.core.journal.records.get(("c:a", 0)) == {0: {K("a.mp4", 0)}}
    t.turn()
    t.hello(b"a.2", "a", Resume(-1, {}))
    for _ in range(5):
        t.turn()
    assert t.got[b"a.2"] == [(0, "a.mp4#0")] and [e for e, _ in t.told[b"a.2"]] == [0, 1, 2]
    t.core.journal.close()


def test_a_restarted_server_refuses_a_consumer_told_every_epoch_whose_records_are_gone(tmp_path):
    """Reader a holds a sample of epoch 0 only and was told every epoch complete: its record of
    epoch 0 is forgotten (two newer epochs were told it). The newest epoch told it stays for
    good, so its resume from a checkpoint of no sample is refused in one line, before any
    batch (it was let in, and told every epoch complete, once its last record went: simulator
    finding F39, ``mixed`` seed 53491)."""
    from tests.test_delivery_core import TinyStream
    from v2v_wire.messages import Hello, Resume

    _first_life(tmp_path, a_told=2)
    t = TinyStream(Journal(str(tmp_path), "r1"))
    assert t.core.journal.told_to[("c:a", 0)] == 2
    t.turn()  # the scheduler forgets a's record of epoch 0 (two newer epochs were told it)
    [(_, err)] = t.core.hello(b"a.2", Hello(("voxels",), 1, consumer="a", resume=Resume(-1, {})), t.now)
    assert err.code == "resume" and "up to 2" in err.message, err
    t.core.journal.close()

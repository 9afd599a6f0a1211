"""One plan over several servers, each serving one shard (``v2v-serve --shard I/N``): real
servers on 127.0.0.1 on the bundled clips, read by ``V2VStreamDataset`` given
every endpoint. Every test is bounded in time and stops what it starts."""
from __future__ import annotations

import pytest
import torch

from harness.serve import ServeProcess
from v2v_client import V2VStreamDataset
from v2v_server.ops.startup import shard_of

from tests.test_scale_out import OUTPUTS, corpus, expected_ids, layout


def read(ds, **kw):
    """{sample id: (voxels, frames)}, the ids in order, the padding rows and the last position."""
    got, order, padding, last = {}, [], 0, None
    for b in torch.utils.data.DataLoader(ds, batch_size=None, **kw):
        for j, sid in enumerate(b["sample_ids"]):
            if b["padding"][j]:
                padding += 1
                continue
            got[sid] = (b["voxels"][j].clone(), b["frames"][j].clone())
            order.append(sid)
        last = b["position"]
    return got, order, padding, last


@pytest.mark.timeout(600)
def test_two_shards_read_as_one_plan_every_id_once_with_one_servers_content(tmp_path, videos):
    """Two shards read together give every id of the corpus once per epoch with the content one
    unsharded server gives it; two ranks take fixed slices of the same steps; a position taken
    mid-epoch resumes at another world size with nothing repeated or lost."""
    root = corpus(tmp_path, videos)
    want = expected_ids(root)
    base = ["--videos", str(root), *layout()]
    with ServeProcess(base) as one:
        single, _, _, _ = read(V2VStreamDataset(one.endpoint, outputs=OUTPUTS, timeout_s=120))
    with ServeProcess(base + ["--shard", "0/2"]) as a, ServeProcess(base + ["--shard", "1/2"]) as b:
        both = f"{a.endpoint},{b.endpoint}"
        sharded, order, padding, _ = read(V2VStreamDataset(both, outputs=OUTPUTS, timeout_s=120))
        assert sorted(order) == sorted(single) == want  # every id once, nothing from elsewhere
        for sid in want:
            assert torch.equal(single[sid][0], sharded[sid][0]) and torch.equal(single[sid][1], sharded[sid][1])
        shard_sizes = [sum(1 for s in want if shard_of(s.split("#")[0], 2) == i) for i in range(2)]
        assert padding < 2 * max(shard_sizes) - len(want) + 2  # a shorter shard's tail, and the last batch's
        # the endpoints in either order, and two ranks: the same sequence, split in fixed slices
        ranks = [read(V2VStreamDataset([b.endpoint, a.endpoint], rank=r, world_size=2, outputs=OUTPUTS,
                                       timeout_s=120))[1] for r in range(2)]
        assert sorted(ranks[0] + ranks[1]) == want
        steps = V2VStreamDataset(both, rank=0, world_size=2, timeout_s=120)
        assert len(steps) == len(V2VStreamDataset(both, rank=1, world_size=2, timeout_s=120))
        # a position after 2 steps of one rank resumes at world size 2 (each rank its slice)
        ds = V2VStreamDataset(both, outputs=OUTPUTS, timeout_s=120)
        first, position = [], None
        for i, batch in enumerate(ds):
            first += [s for s, p in zip(batch["sample_ids"], batch["padding"].tolist()) if not p]
            position = batch["position"]
            if i == 1:
                break
        rest = []
        for r in range(2):
            again = V2VStreamDataset(both, rank=r, world_size=2, outputs=OUTPUTS, timeout_s=120)
            again.load_state_dict(position)
            rest += read(again)[1]
        assert sorted(first + rest) == want and first == order[:len(first)]


@pytest.mark.timeout(300)
def test_servers_that_are_not_one_sharding_are_refused_naming_them(tmp_path, videos):
    root = corpus(tmp_path, videos)
    base = ["--videos", str(root), *layout()]
    with ServeProcess(base + ["--shard", "0/2"]) as a, ServeProcess(base + ["--shard", "0/2"]) as b:
        with pytest.raises(ValueError, match=r"not one sharding of one corpus .*shard\(s\) served twice: 0/2 by "
                                             r".*shard\(s\) 1/2 served by none of them"):
            V2VStreamDataset([a.endpoint, b.endpoint], timeout_s=60).plan_info()
    with ServeProcess(base) as whole, ServeProcess(base + ["--shard", "1/2"]) as b:
        with pytest.raises(ValueError, match=rf"^{b.endpoint}: serve\(s\) one shard while {whole.endpoint} serves "
                                             r"the whole corpus: read shards .* or hosts of the whole corpus, not both"):
            V2VStreamDataset([whole.endpoint, b.endpoint], timeout_s=60).plan_info()
    with ServeProcess(base + ["--shard", "0/2"]) as a, ServeProcess(base + ["--shard", "1/2", "--seed", "9"]) as b:
        with pytest.raises(ValueError, match="different sample recipes"):
            V2VStreamDataset([a.endpoint, b.endpoint], timeout_s=60).plan_info()


def steps_of(ds, **kw):
    """Each batch's rows as (sample id or None, padding), and {sample id: (voxels, frames)}."""
    steps, content = [], {}
    for b in torch.utils.data.DataLoader(ds, batch_size=None, **kw):
        steps.append([(sid, bool(p)) for sid, p in zip(b["sample_ids"], b["padding"].tolist())])
        for j, sid in enumerate(b["sample_ids"]):
            if not b["padding"][j]:
                content[sid] = (b["voxels"][j].clone(), b["frames"][j].clone())
    return steps, content


@pytest.mark.timeout(600)
def test_batches_smaller_than_the_shards_end_the_epoch_on_every_rank_at_the_same_step(tmp_path, videos):
    """Two shards of a corpus never scanned (each pair of servers a fresh --cache-dir), batches of
    one row, fewer than the shards: at world size 1 without DataLoader workers and with 2 (each
    worker's steps lie in one shard), and at world size 2 (each rank's rows in one shard; the
    ranks read one after the other, so neither learns the epoch's end from the other's fetches),
    every rank ends the epoch at the interleaved epoch's last step, and the rows are one sequence
    holding each id of the corpus once with the bytes one unsharded server gives it."""
    root = corpus(tmp_path, videos)
    want = expected_ids(root)
    base = ["--videos", str(root), *layout()]
    with ServeProcess(base) as one:
        _, single = steps_of(V2VStreamDataset(one.endpoint, 1, outputs=OUTPUTS, timeout_s=120))
    sizes = [sum(1 for s in want if shard_of(s.split("#")[0], 2) == i) for i in range(2)]
    assert min(sizes) > 0 and sorted(single) == want
    total = max((s - 1) * 2 + i + 1 for i, s in enumerate(sizes))  # the interleaved epoch, its padding included

    def shards(name):
        cache = ["--cache-dir", str(tmp_path / name)]
        return ServeProcess(base + cache + ["--shard", "0/2"]), ServeProcess(base + cache + ["--shard", "1/2"])

    def check(content):
        for sid, (voxels, frames) in content.items():
            assert torch.equal(voxels, single[sid][0]) and torch.equal(frames, single[sid][1]), sid

    a, b = shards("one-rank")
    with a, b:
        sequence, content = steps_of(V2VStreamDataset([a.endpoint, b.endpoint], 1, outputs=OUTPUTS, timeout_s=120))
    assert len(sequence) == total and sorted(sid for (sid, pad), in sequence if not pad) == want
    check(content)
    a, b = shards("two-workers")
    with a, b:
        got, content = steps_of(V2VStreamDataset([a.endpoint, b.endpoint], 1, outputs=OUTPUTS, timeout_s=120),
                                num_workers=2)
    assert got == sequence
    check(content)
    a, b = shards("two-ranks")
    with a, b:
        ranks = [steps_of(V2VStreamDataset([a.endpoint, b.endpoint], 1, rank=r, world_size=2, outputs=OUTPUTS,
                                           timeout_s=120)) for r in range(2)]
    assert [len(s) for s, _ in ranks] == [-(-total // 2)] * 2
    merged = [row for step in zip(ranks[0][0], ranks[1][0]) for rows in step for row in rows]
    assert merged[:total] == [row for rows in sequence for row in rows]
    assert all(sid is None and pad for sid, pad in merged[total:])  # the last step's rows past the epoch
    for _, content in ranks:
        check(content)

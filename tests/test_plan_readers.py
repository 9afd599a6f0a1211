"""How a trainer's loader reaches a plan server (docs/delivery.md, "The contract"): ``set_epoch`` and
``load_state_dict`` reaching persistent DataLoader workers, the main process's ``state_dict`` while
DataLoader workers read, and a server bound to an IPv6 address. Real ``v2v-serve`` children on
the bundled clips (4 voxel grids of 64 x 64, 2 windows a clip: 8 samples an epoch), read by real
DataLoader workers; every row is compared by sample id and the bytes of its voxels."""
from __future__ import annotations

import hashlib
import socket

import pytest
import torch

from harness.serve import ServeProcess
from v2v_client import V2VStreamDataset

from tests.test_scale_out import layout

ARGS = [*layout()]  # the bundled clips, batches of 2


@pytest.fixture(scope="module")
def server():
    with ServeProcess(ARGS) as srv:
        yield srv.endpoint


def rows(batches):
    """(epoch, sample id or None, padding, sha1 of the row's voxels) of every row, in order."""
    return [(b["epoch"], sid, bool(b["padding"][j]), hashlib.sha1(b["voxels"][j].numpy().tobytes()).hexdigest())
            for b in batches for j, sid in enumerate(b["sample_ids"])]


def alone(server, epoch: int, steps=None):
    """Epoch ``epoch`` read by a fresh dataset without DataLoader workers: its rows and each
    batch's position."""
    ds = V2VStreamDataset(server, 2, outputs=("voxels",), timeout_s=120)
    ds.set_epoch(epoch)
    batches = list(ds)[:steps]
    return rows(batches), [b["position"] for b in batches]


@pytest.mark.timeout(400)
@pytest.mark.parametrize("context", ["fork", "spawn"])
def test_set_epoch_and_load_state_dict_reach_persistent_dataloader_workers(server, context):
    """One DataLoader with 2 persistent workers, ``ds.set_epoch(e)`` before each pass: each pass
    is epoch e, the rows (ids and bytes) a reader without workers gets of epoch e. Then a
    position mid-epoch 1 loaded in the main process: the next pass of the same workers reads
    epoch 1 from there, and a ``set_epoch(2)`` after it the whole of epoch 2."""
    want = {e: alone(server, e) for e in (0, 1, 2)}
    assert sorted(want[0][0]) != sorted(want[1][0]) and want[0][0] != want[1][0]  # the epochs differ
    ds = V2VStreamDataset(server, 2, outputs=("voxels",), timeout_s=120)
    loader = torch.utils.data.DataLoader(ds, batch_size=None, num_workers=2, persistent_workers=True,
                                         multiprocessing_context=context)
    for e in (0, 1, 2):
        ds.set_epoch(e)
        assert rows(loader) == want[e][0], f"pass {e}"
    ds.load_state_dict(want[1][1][1])  # after 2 steps of epoch 1
    assert rows(loader) == want[1][0][4:]
    ds.set_epoch(2)
    assert rows(loader) == want[2][0]


@pytest.mark.timeout(300)
def test_the_main_processs_state_with_dataloader_workers_is_refused_naming_the_batch_position(server):
    """With DataLoader workers the main process cannot know which batches the loop took (the
    workers read ahead): ``ds.state_dict()`` there refuses in one line naming ``batch["position"]``,
    which resumes the rest of the epoch exactly (ids and bytes). Before a pass yields, or after
    ``set_epoch``, it is the pass's start; without workers, the last batch's position."""
    want, positions = alone(server, 0)
    ds = V2VStreamDataset(server, 2, outputs=("voxels",), timeout_s=120)
    assert ds.state_dict()["sample_in_epoch"] == 0
    it = iter(torch.utils.data.DataLoader(ds, batch_size=None, num_workers=2))
    taken = [next(it), next(it)]
    with pytest.raises(RuntimeError) as err:
        ds.state_dict()
    assert "\n" not in str(err.value) and 'batch["position"]' in str(err.value)
    del it
    assert rows(taken) == want[:4]
    again = V2VStreamDataset(server, 2, outputs=("voxels",), timeout_s=120)
    again.load_state_dict(taken[-1]["position"])
    assert rows(torch.utils.data.DataLoader(again, batch_size=None, num_workers=2)) == want[4:]
    ds.set_epoch(1)
    assert {k: ds.state_dict()[k] for k in ("epoch", "sample_in_epoch")} == {"epoch": 1, "sample_in_epoch": 0}
    ds.set_epoch(0)
    it = iter(ds)  # no workers: what this process read is what the loop took
    next(it)
    assert {k: ds.state_dict()[k] for k in ("plan", "epoch", "sample_in_epoch")} == positions[0]


@pytest.mark.timeout(300)
def test_a_plan_server_bound_to_ipv6_loopback_is_read(server):
    """``v2v-serve --bind tcp://[::1]:PORT``: ``V2VStreamDataset`` reads it, the rows (ids and
    bytes) the same server on 127.0.0.1 gives."""
    try:
        with socket.socket(socket.AF_INET6) as s:
            s.bind(("::1", 0))
            port = s.getsockname()[1]
    except OSError as e:
        pytest.skip(f"this machine has no IPv6 loopback: {e}")
    endpoint = f"tcp://[::1]:{port}"
    with ServeProcess([*ARGS, "--bind", endpoint]):
        ds = V2VStreamDataset(endpoint, 2, outputs=("voxels",), timeout_s=30)
        got = rows(torch.utils.data.DataLoader(ds, batch_size=None, num_workers=1))
    want = alone(server, 0)[0]
    assert got == want and len({sid for _, sid, pad, _ in got if not pad}) == 8

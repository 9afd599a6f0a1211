"""How a trainer's loader reaches a plan server (docs/plan.md, "The contract"): ``set_epoch`` and
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

ARGS = ["--delivery", "plan", *layout()]  # the bundled clips, batches of 2


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

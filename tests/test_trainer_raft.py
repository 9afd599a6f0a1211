"""RAFT flow at train time (``loss.flow_source: raft-small | raft-large``, trainer/raft_flow.py).

torchvision (and so RAFT itself) cannot be installed on these machines: the tests give our code
a stand-in network with RAFT's call signature, and a stand-in ``torchvision.models.optical_flow``
module where the loading path is under test. What they check is ours: the authors' input
preparation and output layout, the weight lookup, the refusal before any step, and the tasks
using the computed flow instead of the stream's.
"""
from __future__ import annotations

import sys
import time
import types

import pytest
import torch

from tests.trainer_fixtures import FakeV2VStream
from trainer.config import apply_overrides, default_config, merge
from trainer.core import Trainer
from trainer.raft_flow import FlowSourceUnavailable, RaftFlow, load_raft, raft_pair_flow
from trainer.tasks import stream_outputs

TINY = {"e2vid": {"num_bins": 3, "base_num_channels": 4}, "evflow": {"num_bins": 3, "base_num_channels": 4}}


class StandInRaft(torch.nn.Module):
    """RAFT's call signature: ``net(img1, img2, num_flow_updates=k)`` -> list of (N, 2, H, W)
    flows, the last the finest. Its flow is ``scale * (img2 - img1)`` in channels 0-1, so a test
    can tell which frame went where; it records what it was given."""

    def __init__(self, weights=None):
        super().__init__()
        self.scale = torch.nn.Parameter(torch.ones(()))
        self.calls = []

    def forward(self, img1, img2, num_flow_updates=12):
        self.calls.append((img1.clone(), img2.clone(), num_flow_updates))
        flow = (img2 - img1)[:, :2] * self.scale
        return [torch.zeros_like(flow), flow]


@pytest.fixture
def stand_in_torchvision(monkeypatch, tmp_path):
    """A ``torchvision.models.optical_flow`` whose raft_small / raft_large are StandInRaft, and
    $TORCH_HOME at an empty folder; returns the folder where weights are looked for."""
    of = types.ModuleType("torchvision.models.optical_flow")
    of.raft_small = of.raft_large = StandInRaft
    models = types.ModuleType("torchvision.models")
    models.optical_flow = of
    tv = types.ModuleType("torchvision")
    tv.models = models
    for name, mod in (("torchvision", tv), ("torchvision.models", models), ("torchvision.models.optical_flow", of)):
        monkeypatch.setitem(sys.modules, name, mod)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.delenv("V2V_RAFT_WEIGHTS", raising=False)
    ckpts = tmp_path / "torch" / "hub" / "checkpoints"
    ckpts.mkdir(parents=True)
    return ckpts


def test_frames_are_prepared_as_the_authors_inference_raft_and_the_padding_is_cut():
    net = StandInRaft()
    a = torch.rand(2, 1, 37, 150)
    b = torch.rand(2, 1, 37, 150)
    flow = raft_pair_flow(net, a, b, num_flow_updates=7)
    img1, img2, k = net.calls[0]
    assert k == 7
    assert img1.shape == (2, 3, 128, 152)  # sides: multiples of 8, at least 128
    for img, src in ((img1, a), (img2, b)):
        assert torch.equal(img[:, :, :37, :150], (src * 2 - 1).expand(-1, 3, -1, -1))  # [0, 1] -> [-1, 1], grey x3
        assert img[:, :, 37:].abs().max() == 0 and img[:, :, :, 150:].abs().max() == 0  # zero padding
    assert flow.shape == (2, 2, 37, 150) and flow.dtype == torch.float32 and not flow.requires_grad
    assert torch.allclose(flow, (b - a).expand(-1, 2, -1, -1) * 2)
    with pytest.raises(ValueError, match="N, 1\\|3, H, W"):
        raft_pair_flow(net, a, b[:, :, :36])


def test_sequence_flow_has_the_layout_of_the_streams_flow_slice():
    """Entry k of ``RaftFlow(frames, start)`` is the flow frame start+k -> start+k+1, as the
    stream's ``flow[:, start:]``; one batched call for every pair."""
    net = StandInRaft()
    frames = torch.rand(2, 6, 1, 16, 16)  # L = 5 voxels
    flow = RaftFlow("raft_small", torch.device("cpu"), num_flow_updates=12, net=net)(frames, start=2)
    assert flow.shape == (2, 3, 2, 16, 16) and len(net.calls) == 1
    for k in range(3):
        want = (frames[:, 2 + k + 1] - frames[:, 2 + k]) * 2
        assert torch.allclose(flow[:, k], want.expand(-1, 2, -1, -1), atol=1e-6)


def test_without_torchvision_v2v_train_refuses_before_any_step(tmp_path, monkeypatch, caplog):
    import trainer.train as tr

    monkeypatch.setitem(sys.modules, "torchvision", None)  # what an install without torchvision sees

    class Stream:  # opened beside the model's build: never read, closed
        read, closed = False, False

        def __iter__(self):
            Stream.read = True
            return iter(())

        def close(self):
            Stream.closed = True

    monkeypatch.setattr(tr, "make_stream", lambda *a, **k: Stream())
    rc = tr.main(["--task", "e2vid", "--connect", "tcp://127.0.0.1:1", "--out", str(tmp_path), "--device", "cpu",
                  "--no-progress", "--set", "loss.flow_source=raft_small"])
    deadline = time.monotonic() + 10
    while not Stream.closed and time.monotonic() < deadline:  # the stream may open after the refusal
        time.sleep(0.05)
    assert rc == 2 and not Stream.read and Stream.closed  # no batch read, no step taken, the stream closed
    msg = (tmp_path / "train.log").read_text()
    assert "loss.flow_source=raft-small: RAFT needs torchvision" in msg and "loss.flow_source=stream" in msg


def test_missing_weights_are_named_with_every_place_looked_at(stand_in_torchvision, tmp_path, monkeypatch):
    with pytest.raises(FlowSourceUnavailable, match=r"no local RAFT large weights; looked at .*raft_large\*\.pth"):
        load_raft("raft_large", torch.device("cpu"))
    monkeypatch.setenv("V2V_RAFT_WEIGHTS", str(tmp_path / "nowhere.pth"))
    with pytest.raises(FlowSourceUnavailable, match="nowhere.pth"):
        load_raft("raft_small", torch.device("cpu"))
    bad = tmp_path / "bad.pth"
    torch.save({"not": torch.zeros(1)}, bad)
    with pytest.raises(FlowSourceUnavailable, match="is not a raft_small state dict"):
        load_raft("raft_small", torch.device("cpu"), weights=str(bad))
    with pytest.raises(ValueError, match="raft-small"):
        load_raft("stream", torch.device("cpu"))


def test_the_trainer_names_raft_as_the_server_does_and_reads_torchvisions_spelling():
    for given in ("raft-small", "raft_small"):
        cfg = apply_overrides(default_config("e2vid"), [f"loss.flow_source={given}"])
        assert cfg["loss"]["flow_source"] == "raft-small"
    with pytest.raises(ValueError, match=r"\['stream', 'raft-small', 'raft-large'\], got 'raft'"):
        apply_overrides(default_config("evflow"), ["loss.flow_source=raft"])


def test_e2vid_temporal_consistency_uses_raft_small_on_the_frames(stand_in_torchvision, tmp_path):
    torch.save(StandInRaft().state_dict(), stand_in_torchvision / "raft_small-0123abcd.pth")
    cfg = merge(default_config("e2vid"), {"model": TINY["e2vid"], "loss": {"flow_source": "raft-small"}})
    assert stream_outputs(cfg) == ("voxels", "frames")  # the server's flow is not asked for
    t = Trainer(cfg, str(tmp_path / "run"), torch.device("cpu"))
    net = t.spec.raft.net
    assert not net.training and not any(p.requires_grad for p in net.parameters())
    batch = next(iter(FakeV2VStream(outputs=stream_outputs(cfg), sequence_length=4)))
    assert "flow" not in batch
    stats = t.train_step(batch)
    assert torch.isfinite(torch.tensor(stats["loss"])) and stats["tc"] > 0
    # one call: the pairs from voxel l0 = 2 of L = 4 on, for the 2 samples; 12 iterations
    (img1, _, k), = net.calls
    assert img1.shape[0] == 2 * 2 and k == 12


def test_evflow_targets_come_from_raft_large(stand_in_torchvision, tmp_path):
    torch.save(StandInRaft().state_dict(), stand_in_torchvision / "raft_large-2dfb8e49.pth")
    cfg = merge(default_config("evflow"), {"model": TINY["evflow"], "loss": {"flow_source": "raft_large",
                                                                           "raft_num_flow_updates": 5}})
    assert stream_outputs(cfg) == ("voxels", "frames")
    t = Trainer(cfg, str(tmp_path / "run"), torch.device("cpu"))
    batch = next(iter(FakeV2VStream(outputs=stream_outputs(cfg), sequence_length=4)))
    stats = t.train_step(batch)
    (img1, img2, k), = t.spec.raft.net.calls
    assert img1.shape[0] == 2 * 4 and k == 5  # every voxel's pair, 2 samples x L = 4
    frames = batch["frames"].float() / 255
    assert torch.allclose(img2[:, 0, :32, :32], frames[:, 1:].flatten(0, 1)[:, 0] * 2 - 1, atol=1e-6)
    assert stats["aee"] > 0 and torch.isfinite(torch.tensor(stats["loss"]))

"""The trainer's networks as the V2V authors' driver runs them (HYLZ-2019/V2V): input padding to
multiples of 16 on odd sensor sizes, and their released checkpoint formats loaded through
trainer.checkpoints (state dicts built from the listing of their classes in
tests/data/zoo_reference.json, not downloaded weights)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from trainer.checkpoints import AUTHORS_FORMATS, detect_format, load_authors_checkpoint
from trainer.zoo import build_model

REF = json.loads((Path(__file__).parent / "data" / "zoo_reference.json").read_text())


def authors_forward_sequence(model, events, gt=None, beta=0.0):
    """Transcription of the authors' ``forward_sequence`` (model/train_utils.py) and
    ``forward_sequence_evflow`` (model/train_flow_utils.py): pad every voxel to multiples of 16
    at the bottom and right with zeros, run the network on the padded grid, crop the output."""
    B, T, C, H, W = events.shape
    PAD = 16
    padded_h = int(np.ceil(H / PAD) * PAD)
    padded_w = int(np.ceil(W / PAD) * PAD)
    padded_events = torch.zeros((B, T, C, padded_h, padded_w))
    padded_events[:, :, :, :H, :W] = events
    if gt is not None:
        padded_gt = torch.zeros((B, T, 1, padded_h, padded_w))
        padded_gt[:, :, :, :H, :W] = gt
    outs, states = [], None
    for t in range(T):
        if isinstance(model, torch.nn.Module) and model.__class__.__name__ == "EVFlowNet":
            pred = model(padded_events[:, t])
        elif gt is not None:
            pred, states = model(padded_events[:, t], states, gt_image=padded_gt[:, t], beta=beta)
        else:
            pred, states = model(padded_events[:, t], states)
        outs.append(pred[:, :, :H, :W])
    return torch.stack(outs, 1)


def ours_sequence(model, events, gt=None, beta=0.0):
    outs, states = [], None
    for t in range(events.shape[1]):
        if model.__class__.__name__ == "EVFlowNet":
            outs.append(model(events[:, t]))
        elif gt is not None:
            pred, states = model(events[:, t], states, gt_image=gt[:, t], beta=beta)
            outs.append(pred)
        else:
            pred, states = model(events[:, t], states)
            outs.append(pred)
    return torch.stack(outs, 1)


#: narrower networks than the paper's (the padding does not depend on the widths), for CPU time
NARROW = {"e2vid": {"base_num_channels": 8}, "evflow": {"base_num_channels": 8}, "hypere2vid": {"base_num_channels": 8},
          "etnet": {"d_model": 32, "nhead": 2, "encoder_layers": 1, "decoder_layers": 1, "dim_feedforward": 64}}


@pytest.mark.parametrize("size", [(180, 240), (260, 346)])
@pytest.mark.parametrize("task", ["e2vid", "evflow", "hypere2vid", "etnet"])
def test_outputs_equal_the_authors_padding_on_odd_sizes(task, size):
    torch.manual_seed(0)
    model = build_model(task, NARROW[task]).eval()
    events = torch.randn(1, 2, 5, *size) * 2
    with torch.no_grad():
        ours = ours_sequence(model, events)
        theirs = authors_forward_sequence(model, events)
    assert ours.shape == (1, 2, 2 if task == "evflow" else 1, *size)
    assert torch.equal(ours, theirs)


def test_hypere2vid_curriculum_frame_padded_as_theirs():
    torch.manual_seed(0)
    model = build_model("hypere2vid", NARROW["hypere2vid"]).eval()
    events, gt = torch.randn(1, 2, 5, 180, 240), torch.rand(1, 2, 1, 180, 240)
    with torch.no_grad():
        assert torch.equal(ours_sequence(model, events, gt, 0.5), authors_forward_sequence(model, events, gt, 0.5))


def test_padding_to_8_would_differ_from_theirs():
    """The comparison above is sensitive: E2VID run on an input padded only to multiples of 8
    (184 x 240 instead of 192 x 240) gives another image."""
    torch.manual_seed(0)
    model = build_model("e2vid", {}).eval()
    events = torch.randn(1, 1, 5, 180, 240) * 2
    with torch.no_grad():
        ours, _ = model(events[:, 0])
        inner = model.unetrecurrent
        x = torch.nn.functional.pad(events[:, 0], (0, 0, 0, 4))
        # the network body on a 184 x 240 grid, without the trainer's own padding step
        f = inner.head(x)
        head, blocks, st = f, [], None
        for enc in inner.encoders:
            f, st = enc(f, None)
            blocks.append(f)
        eight = inner._decode(f, blocks, head)[..., :180, :240]
    assert float((ours - eight).abs().max()) > 1e-6


def _random_state_dict(listing: dict, prefix: str = "") -> dict:
    g = torch.Generator().manual_seed(1)
    return {prefix + k: torch.randn(shape, generator=g) if shape else torch.tensor(3) for k, shape in listing.items()}


@pytest.mark.parametrize("name", ["e2vid", "e2vid++", "hypere2vid", "etnet"])
@pytest.mark.parametrize("prefix", ["", "_orig_mod.module."])
def test_authors_checkpoint_formats_load(tmp_path, name, prefix):
    listing = REF[name]["state_dict"]
    sd = _random_state_dict(listing, prefix)
    path = tmp_path / f"{name}.pth"
    torch.save({"state_dict": sd}, path)
    assert detect_format(sd) == name
    got, model = load_authors_checkpoint(str(path), None, torch.device("cpu"))
    assert got == name and not model.training
    own = model.state_dict()
    assert len(own) == len(listing)
    key = "unetrecurrent.head.conv2d.weight" if name != "etnet" else "head.conv2d.weight"
    theirs = prefix + ("unetflow.head.conv2d.weight" if name == "e2vid++" else key)
    assert torch.equal(own[key], sd[theirs])
    with torch.no_grad():
        img, _ = model(torch.randn(1, 5, 36, 50))
    assert img.shape == (1, 1, 36, 50)


def test_e2vid_plus_plus_image_is_the_first_prediction_channel(tmp_path):
    sd = _random_state_dict(REF["e2vid++"]["state_dict"])
    torch.save({"state_dict": sd}, tmp_path / "pp.pth")
    _, pp = load_authors_checkpoint(str(tmp_path / "pp.pth"), "e2vid++", torch.device("cpu"))
    e2vid = build_model("e2vid", {}).eval()
    one = {k.replace("unetflow.", "unetrecurrent."): v for k, v in sd.items()}
    one["unetrecurrent.pred.conv2d.weight"] = one["unetrecurrent.pred.conv2d.weight"][:1]
    one["unetrecurrent.pred.conv2d.bias"] = one["unetrecurrent.pred.conv2d.bias"][:1]
    e2vid.load_state_dict(one)
    v = torch.randn(1, 5, 32, 48)
    with torch.no_grad():
        assert torch.equal(pp(v)[0], e2vid(v)[0])


def test_a_checkpoint_of_another_format_is_refused_naming_it(tmp_path):
    sd = _random_state_dict(REF["e2vid++"]["state_dict"])
    torch.save({"state_dict": sd}, tmp_path / "pp.pth")
    with pytest.raises(ValueError, match=r"'hypere2vid' format .*missing key"):
        load_authors_checkpoint(str(tmp_path / "pp.pth"), "hypere2vid", torch.device("cpu"))
    sd = _random_state_dict(REF["e2vid"]["state_dict"])
    sd["unetrecurrent.pred.conv2d.weight"] = torch.randn(3, 32, 1, 1)
    torch.save({"state_dict": sd}, tmp_path / "e.pth")
    with pytest.raises(ValueError, match="of another shape"):
        load_authors_checkpoint(str(tmp_path / "e.pth"), "e2vid", torch.device("cpu"))
    torch.save({"state_dict": {"foo.weight": torch.zeros(1)}}, tmp_path / "x.pth")
    with pytest.raises(ValueError, match="cannot tell"):
        load_authors_checkpoint(str(tmp_path / "x.pth"), None, torch.device("cpu"))
    with pytest.raises(ValueError, match="unknown checkpoint format"):
        load_authors_checkpoint(str(tmp_path / "x.pth"), "firenet", torch.device("cpu"))
    assert set(AUTHORS_FORMATS) >= {"e2vid", "e2vid++", "hypere2vid", "etnet", "evflow"}

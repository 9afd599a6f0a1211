"""``v2v_client.reference_layout.to_reference_layout`` against what the V2V authors' training
dataset yields for the same window shape (tests/data/reference_layout.json: their
``WebvidDatasetV2`` run on CPU on the bundled bikes.mp4 by harness/reference_layout.py)."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from tests.trainer_fixtures import FakeV2VStream
from v2v_client.reference_layout import DATA_SOURCES, to_reference_layout

REF = json.loads((Path(__file__).parent / "data" / "reference_layout.json").read_text())


def stream_batch(raw=True):
    ds = FakeV2VStream(outputs=("voxels", "frames", "flow"), batch_size=2, sequence_length=REF["sequence_length"],
                       num_bins=REF["num_bins"], crop=REF["crop_size"], num_batches=1, raw=raw)
    return next(iter(ds))


@pytest.mark.parametrize("layout,additional", [("reconstruction", False), ("additional_frame", True)])
@pytest.mark.parametrize("raw", [True, False])
def test_keys_shapes_dtypes_and_ranges_match_the_authors_dataset(layout, additional, raw):
    b = stream_batch(raw)
    out = to_reference_layout(b, additional_frame=additional)
    ref = REF[layout]
    for key in ("frame", "events", "data_source_idx"):
        assert list(out[key].shape) == ref[key]["shape"], key
        assert str(out[key].dtype).replace("torch.", "") == ref[key]["dtype"], key
    assert set(out["v2e_params"]) == set(ref["v2e_params"])
    for k, v in out["v2e_params"].items():
        assert list(v.shape) == ref["v2e_params"][k]["shape"] and str(v.dtype) == "torch." + ref["v2e_params"][k]["dtype"]
        assert torch.isfinite(v).all() and (v >= 0).all(), k
    assert ref["frame"]["min"] >= 0 and ref["frame"]["max"] <= 1
    assert 0 <= float(out["frame"].min()) and float(out["frame"].max()) <= 1
    assert int(out["data_source_idx"][0]) == int(ref["data_source_idx"]["min"]) == REF["data_sources"].index("webvid")
    assert tuple(REF["data_sources"]) == DATA_SOURCES
    # frames: the end of each voxel (theirs) or all L + 1 (additional_frame); values as /255
    f = b["frames"].float() / 255 if raw else b["frames"]
    torch.testing.assert_close(out["frame"], f if additional else f[:, 1:])
    torch.testing.assert_close(out["events"], b["voxels"].float())
    assert out["flow"].dtype == torch.float32 and out["flow"].shape == b["flow"].shape
    # our extras under our names
    assert out["sample_ids"] == b["sample_ids"] and out["params"] == b["params"]
    assert (out["epoch"], out["step"], out["position"]) == (b["epoch"], b["step"], b["position"])
    assert "batch_id" not in out
    p = b["params"][1]
    assert float(out["v2e_params"]["pos_thres"][1]) == pytest.approx(p["pos_threshold"])
    assert float(out["v2e_params"]["hot_pixel_fraction"][1]) == pytest.approx(p["hot_pixel_count"] / 32**2)


def test_bad_input_is_named():
    b = stream_batch()
    with pytest.raises(ValueError, match="data_source"):
        to_reference_layout(b, data_source="youtube")
    with pytest.raises(ValueError, match="'frames' must be"):
        to_reference_layout({**b, "frames": b["frames"][:, 1:]})
    with pytest.raises(ValueError, match="no 'voxels'"):
        to_reference_layout({"frames": b["frames"]})

"""Derive tests/data/reference_layout.json: what the V2V authors' training dataset
(HYLZ-2019/V2V ``data/v2v_datasets.py`` ``WebvidDatasetV2``) yields through torch's
``default_collate`` for two samples of the bundled clip ``bikes.mp4``, sequence length 4,
5 bins, crop 32: for each key its shape, dtype and value range, once as their reconstruction
configs use it and once with ``output_additional_frame`` (their flow-training configs).
``tests/test_reference_layout.py`` checks ``v2v_client.reference_layout.to_reference_layout``
against it.

Run on CPU with a checkout of the authors' repository (numpy, opencv, torch; their
``ffmpeg`` import is stubbed, only the opencv reader is used)::

    python harness/reference_layout.py /path/to/V2V > tests/data/reference_layout.json
"""
from __future__ import annotations

import json
import os
import sys
import tempfile
import types
from pathlib import Path

VIDEO = Path(__file__).resolve().parents[1] / "v2v_server" / "sample_videos" / "bikes.mp4"
BASE = dict(data_source_name="webvid", video_reader="opencv", sequence_length=4, pause_granularity=5,
            proba_pause_when_running=0.0102, proba_pause_when_paused=0.9791, crop_size=32, random_flip=True,
            num_bins=5, min_resize_scale=1, max_resize_scale=1, frames_per_bin=1, threshold_range=[0.05, 2],
            max_thres_pos_neg_gap=1.5, base_noise_std_range=[0, 0.1], hot_pixel_std_range=[0, 10],
            max_samples_per_shot=10)


def describe(v):
    if isinstance(v, dict):
        return {k: describe(x) for k, x in v.items()}
    return {"shape": list(v.shape), "dtype": str(v.dtype).replace("torch.", ""), "min": float(v.min()),
            "max": float(v.max())}


def main() -> None:
    repo = sys.argv[1]
    sys.path.insert(0, repo)
    sys.modules.setdefault("ffmpeg", types.ModuleType("ffmpeg"))
    import cv2
    import numpy as np
    from torch.utils.data import default_collate
    from data.v2v_datasets import WebvidDatasetV2
    from utils.data import data_sources

    n = int(cv2.VideoCapture(str(VIDEO)).get(cv2.CAP_PROP_FRAME_COUNT))
    out = {"source": "HYLZ-2019/V2V 62ce9c8 WebvidDatasetV2 on bikes.mp4, built by harness/reference_layout.py",
           "data_sources": list(data_sources), "sequence_length": 4, "num_bins": 5, "crop_size": 32}
    with tempfile.TemporaryDirectory() as d:
        lst = os.path.join(d, "list.txt")
        Path(lst).write_text(f"{VIDEO.name} {n} 0.2 0.2\n")
        for name, extra in (("reconstruction", {}), ("additional_frame", {"output_additional_frame": True})):
            np.random.seed(0)
            ds = WebvidDatasetV2(str(VIDEO.parent), {**BASE, **extra, "video_list_file": lst})
            out[name] = describe(default_collate([ds[0], ds[1]]))
    json.dump(out, sys.stdout, indent=1)
    print()


if __name__ == "__main__":
    main()

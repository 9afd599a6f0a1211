"""Hashes of the bundled clips' samples: the table that proves a refactor changed no sample.

Every sample of the bundled clips (``v2v_server/sample_videos``) is made for two seeds, one and
four crops per window, with every default output (``DEFAULT_OUTPUTS``; the opt-in
``polarity_counts`` is tested against its equations in ``tests/test_polarity_counts.py``), as a worker makes it for the wire, and hashed as a
client receives it (dtype, shape and bytes of each array, and the sample's params as canonical
msgpack): a tracked flow option's ``flow_grid`` is hashed as the dense ``flow`` the client makes
of it (``v2v_client.flowgrid``, in the server's ``flow_dtype``), so the table pins the flow a
trainer sees, which is bit for bit the dense flow the server's own expansion gives. ``tests/data/sample_hashes.json``
holds the committed table; ``tests/test_sample_hashes.py`` recomputes it and compares.

    python -m tests.sample_hashes            # print differences against the committed table
    python -m tests.sample_hashes --write    # write the table (only for an intended change)
"""
from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import msgpack
import numpy as np
import torch

from v2v_server.samples.recipe import SampleRecipe
from v2v_server.samples.make import video_samples
from v2v_server.sources.local import LocalSource
from v2v_server.service.worker import wire_arrays
from v2v_client.flowgrid import expand_flow_grid
from v2v_wire.outputs import DEFAULT_OUTPUTS

ROOT = Path(__file__).resolve().parents[1]
CLIPS = ROOT / "v2v_server" / "sample_videos"
TABLE = Path(__file__).resolve().parent / "data" / "sample_hashes.json"

#: (name, config overrides): the default recipe, and a short one so the 132-frame clip gives samples;
#: windows laid out as the authors' loader does (``shot_cuts: off``), so the montages give samples
#: and the table pins the windows whatever they hold.
RECIPES = [
    (f"seed{seed}-crops{crops}", {"seed": seed, "crops_per_window": crops, "shot_cuts": "off"})
    for seed in (0, 1) for crops in (1, 4)
] + [("short-seed0-crops1", {"seed": 0, "crops_per_window": 1, "sequence_length": 8, "shot_cuts": "off"})]
#: The clips the table pins (the bundled clips it was made from).
PINNED_CLIPS = ("bigbuckbunny.mp4", "bikes.mp4", "webvid_like_596x336.mp4")


def _digest(arrays: dict, meta: dict) -> dict:
    out = {}
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
        out[name] = h.hexdigest()[:24]
    out["params"] = hashlib.sha256(msgpack.packb(meta, use_bin_type=True, strict_types=False)).hexdigest()[:24]
    return out


def _canonical(meta: dict) -> dict:
    """``meta`` with keys sorted at every level, so the hash does not depend on insertion order."""
    if isinstance(meta, dict):
        return {k: _canonical(meta[k]) for k in sorted(meta)}
    if isinstance(meta, (list, tuple)):
        return [_canonical(v) for v in meta]
    return meta


def _as_received(cfg: SampleRecipe, arrays: dict) -> dict:
    """The wire arrays with ``flow_grid`` made dense as a client does (``raw`` dtypes)."""
    out = dict(arrays)
    g = out.pop("flow_grid", None)
    if g is not None:
        dtype = torch.float16 if cfg.flow_dtype == "float16" else torch.float32
        out["flow"] = expand_flow_grid(torch.from_numpy(g), (cfg.crop_size, cfg.crop_size), dtype).numpy()
    return out


def compute(source=None, caches=None) -> dict:
    """{recipe: {sample_id: {output or "params": hash}}} for every sample of the bundled clips
    (``source``: a ``VideoSource`` over their folder, default the folder itself; ``caches``:
    the host's caches the passes read through, ``HostCaches``, default none)."""
    source = LocalSource(CLIPS) if source is None else source
    table = {}
    for name, overrides in RECIPES:
        cfg = SampleRecipe(**overrides)
        rows = {}
        for clip in PINNED_CLIPS:
            for key, arrays, meta in video_samples(cfg, source, clip, 0, DEFAULT_OUTPUTS, flow_grid=True,
                                                   caches=caches):
                rows[key.sample_id(cfg.crops_per_window)] = _digest(_as_received(cfg, wire_arrays(cfg, arrays)), _canonical(meta))
        table[name] = rows
    return table


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--write", action="store_true", help="write the table instead of comparing")
    args = p.parse_args(argv)
    table = compute()
    if args.write:
        TABLE.write_text(json.dumps(table, indent=1, sort_keys=True) + "\n")
        print(f"wrote {TABLE} ({sum(len(v) for v in table.values())} samples)")
        return 0
    want = json.loads(TABLE.read_text())
    bad = [(r, s) for r in want for s in want[r] if table.get(r, {}).get(s) != want[r][s]]
    bad += [(r, s) for r in table for s in table[r] if s not in want.get(r, {})]
    for r, s in bad:
        print(f"differs: {r} {s}: {table.get(r, {}).get(s)} != {want.get(r, {}).get(s)}")
    print(f"{sum(len(v) for v in want.values()) - len(bad)} of {sum(len(v) for v in want.values())} samples equal")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())

"""TEST FIXTURE (not a product stub): a small in-process stand-in for
the stream ``trainer.data.make_stream`` opens (``v2v_client.PlanEpochs``) that yields batches in
the client's documented format,
so the trainer can be unit-tested without a running ``v2v-serve``.

Each sample is a window sliding over a real video frame (bikes.mp4) by a constant
(sx, sy) pixels per video frame, so the ground-truth optical flow between voxel
boundaries is exact: (num_bins * sx, num_bins * sy) pixels. Voxels come from the real
V2V core (``v2v_server.simulation.simulate.simulate_voxels``).
"""
from __future__ import annotations

import numpy as np
import torch

from v2v_server.simulation.simulate import SensorParams, simulate_voxels
from tests.conftest import read_luma_clip


class FakeV2VStream(torch.utils.data.IterableDataset):
    """Batches like ``V2VStreamDataset(outputs=..., raw=...)`` read epoch after epoch: ``voxels`` (B, L, nb, S, S),
    ``frames`` (B, L+1, 1, S, S), ``flow`` (B, L, 2, S, S), ``sample_ids``, ``params``,
    ``epoch``, ``step`` (of the pass; here it begins at the epoch's start) and ``position``
    (``epoch`` and ``sample_in_epoch`` after the step; a plan's also names the plan). ``num_batches`` per epoch, ``epochs`` epochs;
    deterministic in (seed, batch index), with ``state_dict``/``load_state_dict`` of the batches
    handed out, and :meth:`recipe` (the TensorBoard ``recipe`` text, as ``PlanEpochs.recipe``)."""

    def __init__(self, outputs=("voxels", "frames", "flow"), batch_size=2, sequence_length=4, num_bins=3,
                 crop=32, num_batches=50, epochs=1, seed=0, raw=True, fixed=False):
        super().__init__()
        self.outputs, self.B, self.L, self.nb, self.S = tuple(outputs), batch_size, sequence_length, num_bins, crop
        self.num_batches, self.epochs, self.seed, self.raw, self.fixed = num_batches, epochs, seed, raw, fixed
        self.texture = read_luma_clip("bikes.mp4", n=1, size=(96, 128))[0]
        self.pos = 0  # batches handed out so far (over all epochs)
        self.yielded_ids = []

    def state_dict(self):
        return {"pos": self.pos}

    def recipe(self):
        return {"fixture": "FakeV2VStream", "sequence_length": self.L, "num_bins": self.nb, "crop_size": self.S,
                "batch_size": self.B, "outputs": list(self.outputs), "seed": self.seed}

    def load_state_dict(self, sd):
        self.pos = int(sd["pos"])

    def _sample(self, rng):
        n = self.L * self.nb + 1
        th, tw = self.texture.shape
        sx, sy = (int(v) for v in rng.integers(-1, 2, size=2))

        def start(s, size):
            lo, hi = max(0, -s * (n - 1)), size - self.S - max(0, s * (n - 1))
            return int(rng.integers(lo, hi + 1))

        x0, y0 = start(sx, tw), start(sy, th)
        vid = np.stack([self.texture[y0 + sy * i: y0 + sy * i + self.S, x0 + sx * i: x0 + sx * i + self.S]
                        for i in range(n)])
        # the content moves by -s pixels per video frame when the window moves by +s
        flow = np.zeros((self.L, 2, self.S, self.S), np.float32)
        flow[:, 0] = -sx * self.nb
        flow[:, 1] = -sy * self.nb
        params = SensorParams(0.2, 0.2)
        vox, _ = simulate_voxels(np.ascontiguousarray(vid), params, self.nb, rng=rng)
        frames = vid[:: self.nb][:, None]
        return vox, frames, flow, params.summary()

    def __iter__(self):
        while self.pos < self.num_batches * self.epochs:
            i = self.pos
            rng = np.random.default_rng([self.seed, 0 if self.fixed else i])
            samples = [self._sample(rng) for _ in range(self.B)]
            vox = np.stack([s[0] for s in samples])
            frames = np.stack([s[1] for s in samples])
            flow = np.stack([s[2] for s in samples])
            b = {"sample_ids": [f"fake-{i}-{k}" for k in range(self.B)], "params": [s[3] for s in samples],
                 "epoch": i // self.num_batches, "step": i % self.num_batches,
                 "position": {"epoch": i // self.num_batches, "sample_in_epoch": (i % self.num_batches + 1) * self.B}}
            if "voxels" in self.outputs:
                b["voxels"] = torch.from_numpy(vox.astype(np.int8)) if self.raw else torch.from_numpy(vox.astype(np.float32))
            if "frames" in self.outputs:
                b["frames"] = torch.from_numpy(frames) if self.raw else torch.from_numpy(frames.astype(np.float32) / 255)
            if "flow" in self.outputs:
                b["flow"] = torch.from_numpy(flow.astype(np.float16 if self.raw else np.float32))
            self.pos += 1
            self.yielded_ids.append(i)
            yield b


def write_edge_events(f, width, height, nev, crossing_time, keep=lambda t: True):
    """Writes ``events/{xs,ys,ts,ps}`` into the open H5 file ``f`` for a vertical edge: each
    column x with ``keep(crossing_time(x))`` fires ``nev`` positive events per row at
    ``crossing_time(x)``, sorted by time (stable)."""
    xs, ys, ts = [], [], []
    for x in range(width):
        t = crossing_time(x)
        if keep(t):
            for y in range(height):
                xs += [x] * nev
                ys += [y] * nev
                ts += [t] * nev
    order = np.argsort(ts, kind="stable")
    xs, ys, ts = np.array(xs)[order], np.array(ys)[order], np.array(ts)[order]
    f.create_dataset("events/xs", data=xs.astype(np.uint16))
    f.create_dataset("events/ys", data=ys.astype(np.uint16))
    f.create_dataset("events/ts", data=ts.astype(np.float64))
    f.create_dataset("events/ps", data=np.ones(len(xs), np.uint8))


def write_mvsec_like_h5(path, height=16, width=48, speed=200.0, image_dt=0.01, n_images=8,
                        flow_t0=0.003, flow_dt=0.02, n_flows=4, nev=2):
    """TEST FIXTURE: an H5 file in the layout the V2V reference's ``scripts/mvsec_to_h5.py``
    writes, for a vertical edge moving right at ``speed`` px/s: each column x the edge crosses
    fires ``nev`` events per row at t_x = (x + 0.5) / speed. Images every ``image_dt`` s;
    ground-truth flows at their *own* timestamps ``flow_t0 + k * flow_dt`` (``flow_ts``), flow
    k being the displacement over the interval that ends at its timestamp, ``speed *
    flow_dt`` px in x; NaN in the top quarter of rows (no depth) and zero in the right eighth
    of columns (MVSEC's invalid pixels). Returns ``(image_ts, flow_ts)``."""
    import h5py

    image_ts = np.arange(n_images) * image_dt
    flow_ts = flow_t0 + np.arange(n_flows) * flow_dt
    with h5py.File(path, "w") as f:
        f.attrs["sensor_resolution"] = (height, width)
        write_edge_events(f, width, height, nev, lambda x: (x + 0.5) / speed)
        cols = np.arange(width)[None, :] + 0.5
        for i, t in enumerate(image_ts):
            d = f.create_dataset(f"images/image{i:09d}", data=np.where(cols < speed * t, 200, 50).astype(np.uint8).repeat(height, 0))
            d.attrs["timestamp"] = t
        for k, t in enumerate(flow_ts):
            fl = np.zeros((2, height, width), np.float32)
            fl[0] = speed * flow_dt
            fl[:, : height // 4] = np.nan
            fl[:, :, width - width // 8:] = 0.0
            d = f.create_dataset(f"flow/flow{k:09d}", data=fl)
            d.attrs["timestamp"] = t
    return image_ts, flow_ts

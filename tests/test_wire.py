"""The wire between server and trainer: a tracked option's compact flow reaches the trainer as
the dense flow the server would have sent; compressed batches decode to the arrays the workers
made, for clients that compress and clients that do not on one server; a corrupt compressed
frame is an error of its own reader. A real v2v-serve on 127.0.0.1 over the real clips (and a
hand-written server for the corrupt frame); every test is bounded in time and stops what it
starts."""
from __future__ import annotations

import functools
import itertools
import threading
import time

import numpy as np
import pytest
import torch
import zmq

from harness.serve import ServeProcess
from v2v_client import PlanServerError, V2VStreamDataset, expand_flow_grid
from v2v_client.endpoints import auto_compression
from v2v_wire.codecs import decode_batch_arrays
from v2v_server.samples.recipe import SampleRecipe
from v2v_server.flow.estimate import FlowEstimator, to_float16
from v2v_wire.ids import parse_sample_id
from v2v_wire.plan import PlanIdentity
from v2v_wire.plan_messages import Fetch, PlanInfo, Rows
from v2v_wire.protocol import DEFAULT_OUTPUTS, is_loopback, pack, unpack
from v2v_server.samples.make import make_sample, video_samples
from v2v_server.sources.local import LocalSource
from v2v_server.service.worker import wire_arrays

L, B, CROP, MAXW, SEED = 8, 5, 96, 2, 7


def recipe(**kw) -> SampleRecipe:
    return SampleRecipe(sequence_length=L, num_bins=B, crop_size=CROP, max_samples_per_video=MAXW, seed=SEED,
                       **kw)


def serve_args(videos, *extra):
    return ["--videos", str(videos), "--workers", "2", "--sequence-length", str(L), "--num-bins", str(B),
            "--crop-size", str(CROP), "--max-samples-per-video", str(MAXW), "--seed", str(SEED),
            "--batch-size", "2", *extra]


@functools.lru_cache(maxsize=None)
def dense_flows(videos, clip: str, epoch: int) -> dict:
    """sample id -> the dense float32 flow the server's own expansion gives."""
    cfg = recipe(flow_dtype="float32")
    return {key.sample_id(): a["flow"] for key, a, _ in video_samples(cfg, LocalSource(videos), clip, epoch, ("flow",))}


def want_flow(videos, batch: dict, i: int) -> np.ndarray:
    sid = batch["sample_ids"][i]
    return dense_flows(videos, parse_sample_id(sid).video, batch["epoch"])[sid]


def first_batches(ds, n: int) -> list:
    """The first ``n`` batches of epoch 0, each with its padding rows left out."""
    it = iter(ds)
    try:
        out = []
        for b in itertools.islice(it, n):
            keep = [i for i, p in enumerate(b["padding"].tolist()) if not p]
            out.append({**{k: v[keep] for k, v in b.items() if isinstance(v, torch.Tensor) and k != "padding"},
                        "sample_ids": [b["sample_ids"][i] for i in keep], "epoch": int(b["epoch"])})
        return out
    finally:
        it.close()


@pytest.fixture(scope="module")
def server(videos):
    with ServeProcess(serve_args(videos)) as srv:
        yield srv


def test_tracked_flow_reaches_the_trainer_as_the_server_s_dense_flow(server, videos):
    """The wire carries the grid; the trainer gets float32 (B, L, 2, H, W) flow equal to the
    server's dense expansion (bit for bit after float16 rounding, the old wire's precision)."""
    for b in first_batches(V2VStreamDataset(server.endpoint, outputs=("flow",), timeout_s=60), 2):
        fl = b["flow"]
        assert "flow_grid" not in b and fl.dtype == torch.float32 and fl.shape == (len(b["sample_ids"]), L, 2, CROP, CROP)
        for i in range(len(b["sample_ids"])):
            want = want_flow(videos, b, i)
            got = fl[i].numpy()
            assert np.abs(want).max() > 0.5  # real motion, not an all-zero field
            np.testing.assert_array_equal(to_float16(got).view(np.uint16), to_float16(want).view(np.uint16))
            np.testing.assert_allclose(got, want, rtol=2 ** -11, atol=1e-6)


def test_raw_flow_is_the_old_float16_wire_flow(server, videos):
    for b in first_batches(V2VStreamDataset(server.endpoint, outputs=("flow", "voxels"), raw=True, timeout_s=60), 1):
        assert b["flow"].dtype == torch.float16 and b["voxels"].dtype in (torch.int8, torch.int16, torch.int32)
        for i in range(len(b["sample_ids"])):
            np.testing.assert_array_equal(b["flow"][i].numpy().view(np.uint16),
                                          to_float16(want_flow(videos, b, i)).view(np.uint16))


def test_the_torch_expansion_for_other_devices_equals_the_cpu_one_bit_for_bit():
    """On a CPU tensor the client expands with the server's loop; on a GPU with torch ops. Run
    here on the CPU (no GPU on CI), the torch ops give the same float32 bits."""
    from v2v_client.flowgrid import _expand_torch

    g = torch.from_numpy(np.random.default_rng(0).normal(0, 3, (2, 5, 2, 8, 8)).astype(np.float32))
    for size in ((CROP, CROP), (37, 90)):
        a, b = expand_flow_grid(g, size), _expand_torch(g, *size)
        assert a.shape == b.shape == (2, 5, 2) + size
        assert torch.equal(a.view(torch.int32), b.view(torch.int32))


def test_the_numpy_expansion_of_a_client_only_install_equals_the_numba_loop_bit_for_bit():
    """Without numba (``pip install v2v[client]``) the wire's expansion runs as numpy operations:
    the same float32 bits as the numba loop, for grids of any size and crops of any shape."""
    from v2v_wire.flowgrid import HAVE_NUMBA, expand_grids

    assert HAVE_NUMBA  # this environment has the server's packages
    rng = np.random.default_rng(1)
    for shape, size in (((40, 2, 8, 8), (CROP, CROP)), ((3, 2, 5, 5), (37, 90)), ((2, 2, 12, 12), (64, 200)),
                        ((1, 2, 2, 2), (1, 5))):
        g = rng.normal(0, 3, shape).astype(np.float32)
        a, b = expand_grids(g, size, use_numba=True), expand_grids(g, size, use_numba=False)
        assert a.shape == b.shape == shape[:2] + size
        assert np.array_equal(a.view(np.int32), b.view(np.int32))


def test_only_tracked_options_have_a_grid_and_expansion_checks_its_input(real_clip):
    cfg = recipe(flow_preset="ultrafast")
    est = FlowEstimator("ultrafast")
    with pytest.raises(ValueError, match="only tracked options"):
        est.voxel_flow_grids(real_clip[: 2 * B + 1], B)
    from v2v_server.samples.make import plan_window

    plan = plan_window(cfg, 0, "x.mp4#0", 0, (real_clip.shape[1], real_clip.shape[2]))
    frames = np.zeros((plan.consumed, CROP, CROP), np.uint8)
    out = make_sample(cfg, plan, frames, ("flow",), est, flow_grid=True).arrays
    assert set(out) == {"flow"} and out["flow"].shape == (L, 2, CROP, CROP)  # dense for non-tracked options
    with pytest.raises(ValueError, match=r"\(\.\.\., 2, n, n\)"):
        expand_flow_grid(torch.zeros(3, 8, 8), (CROP, CROP))


# ---------------------------------------------------------------------- compression
@functools.lru_cache(maxsize=None)
def wire_samples(videos, clip: str, epoch: int) -> dict:
    """sample id -> the arrays a worker puts on the wire (flow as its grid)."""
    cfg = recipe()
    return {key.sample_id(): wire_arrays(cfg, a) for key, a, _ in video_samples(cfg, LocalSource(videos), clip, epoch,
                                                                                    DEFAULT_OUTPUTS, flow_grid=True)}


def assert_batch_is_the_samples(videos, h: dict, arrays: dict) -> None:
    for i, sid in enumerate(h["sample_ids"]):
        want = wire_samples(videos, parse_sample_id(sid).video, h["epoch"])[sid]
        assert set(arrays) == set(want)
        for name, a in want.items():
            np.testing.assert_array_equal(arrays[name][i], a, err_msg=f"{sid} {name}")


class RawClient:
    """A DEALER speaking the plan protocol by hand (``plan_ask``, then ``fetch`` after
    ``fetch``), to see the rows as they travel."""

    def __init__(self, endpoint: str, compression: str):
        self.sock = zmq.Context.instance().socket(zmq.DEALER)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.connect(endpoint)
        self.compression = compression
        self.info = PlanInfo.from_wire(self._ask({"type": "plan_ask"}, "plan")[0])
        self.steps = ((epoch, start) for epoch in itertools.count() for start in range(0, self.info.samples, 2))

    def _ask(self, header: dict, kind: str, timeout_s: float = 60.0):
        self.sock.send(pack(header))
        deadline = time.monotonic() + timeout_s
        while self.sock.poll(max(1, int((deadline - time.monotonic()) * 1000))):
            frames = self.sock.recv_multipart(copy=False)
            h = unpack(frames[0])
            assert h["type"] == kind, h
            return h, frames[1:]
        raise TimeoutError(f"no {kind}")

    def batch(self):
        """(header, frames) of the next two positions' rows, the padding rows left out of the
        header's ids (they carry no arrays)."""
        epoch, start = next(self.steps)
        fetch = Fetch(start, epoch, start, start + 2, DEFAULT_OUTPUTS, self.info.plan, self.compression)
        h, frames = self._ask(fetch.to_wire(), "rows")
        return {**h, "sample_ids": [s for s, p in zip(h["sample_ids"], h["padding"]) if not p]}, frames

    def close(self):
        self.sock.close(0)


def compressed_batches(client: RawClient, codec: str, n: int, videos, limit: int = 12) -> int:
    """Fetch rows until ``n`` batches came compressed with ``codec`` (samples made before the
    server had such a fetch may come plain), checking every batch against the samples; returns
    the compressed bytes of the voxels seen against their size."""
    got, packed, raw = 0, 0, 0
    for _ in range(limit):
        h, frames = client.batch()
        if not h["sample_ids"]:
            continue
        arrays = decode_batch_arrays(h["arrays"], frames)
        assert_batch_is_the_samples(videos, h, arrays)
        specs = {s["name"]: s for s in h["arrays"]}
        if all(s.get("codec") == codec for s in specs.values()):
            got += 1
            packed += sum(p[1] for p in specs["voxels"]["parts"])
            raw += arrays["voxels"].nbytes
            if got == n:
                return packed / raw
    raise AssertionError(f"fewer than {n} of {limit} batches came compressed with {codec}")


@pytest.mark.parametrize("codec", ["lz4", "zstd"])
def test_compressed_batches_decode_to_the_same_arrays(server, videos, codec):
    client = RawClient(server.endpoint, codec)
    try:
        assert compressed_batches(client, codec, 2, videos) < 0.5  # voxels compress (6-12x on real samples)
    finally:
        client.close()


def test_mixed_clients_one_compressing_one_not_on_one_server(server, videos):
    """A zstd connection and a plain one read the same server at once; each gets its form, and
    both decode to the samples."""
    client = RawClient(server.endpoint, "zstd")
    ds = V2VStreamDataset(server.endpoint, raw=True, compression="none", timeout_s=60)
    try:
        for step, b in enumerate(first_batches(ds, 3)):
            for i, sid in enumerate(b["sample_ids"]):  # voxels and frames as the workers made them
                want = wire_samples(videos, parse_sample_id(sid).video, b["epoch"])[sid]
                np.testing.assert_array_equal(b["voxels"][i].numpy(), want["voxels"], err_msg=sid)
                np.testing.assert_array_equal(b["frames"][i, :, 0].numpy(), want["frames"], err_msg=sid)
            if step == 0:
                assert compressed_batches(client, "zstd", 1, videos) < 0.5
    finally:
        client.close()


def fake_plan_server(router, stop, rows_for):
    """Answer what readers ask a fake server's ROUTER socket until ``stop`` (an Event) is set:
    a plan of 2 samples of voxels (2, 30, 40) int8, and each fetch with ``rows_for(fetch)``:
    (array spec, frames)."""
    info = PlanInfo(PlanIdentity("m" * 16, "r" * 16, 0), 2, {"batch_size": 2, "crop_size": 40,
                                                              "outputs": ["voxels"]}).to_wire()
    while not stop.is_set():
        if not router.poll(200):
            continue
        ident, msg = router.recv_multipart()
        h = unpack(msg)
        if h["type"] == "plan_ask":
            router.send_multipart([ident, pack(info)])
        elif h["type"] == "fetch":
            f = Fetch.from_wire(h)
            spec, frames = rows_for(f)
            rows = Rows(f.request, f.epoch, f.start, ["a#0", "a#1"], [False, False], [{}, {}], [spec], 2)
            router.send_multipart([ident, pack(rows.to_wire()), *frames])


def test_a_corrupt_compressed_frame_is_an_error_of_its_reader():
    """Rows whose zstd frame does not decompress end that reader's epoch with a PlanServerError
    naming the array; the process and other readers go on."""
    from v2v_wire import codecs

    ctx = zmq.Context.instance()
    router = ctx.socket(zmq.ROUTER)
    router.setsockopt(zmq.LINGER, 0)
    port = router.bind_to_random_port("tcp://127.0.0.1")
    good = (np.arange(2 * 30 * 40) % 7).astype(np.int8).reshape(2, 30, 40)
    parts = list(codecs.pack("zstd", {"0": good[0], "1": good[1]}).values())  # as a worker compresses
    bad = bytearray(parts[1])
    bad[len(bad) // 2] ^= 0x55  # one altered byte
    corrupt = [True]  # the first fetch gets the altered frame

    def rows_for(f):
        second = bytes(bad) if corrupt and corrupt.pop() else parts[1]
        return ({"name": "voxels", "dtype": "int8", "shape": [2, 30, 40], "codec": "zstd",
                 "parts": [["int8", len(parts[0])], ["int8", len(second)]]}, [parts[0], second])

    stop = threading.Event()
    t = threading.Thread(target=fake_plan_server, args=(router, stop, rows_for), daemon=True)
    t.start()
    try:
        endpoint = f"tcp://127.0.0.1:{port}"
        bad_ds = V2VStreamDataset(endpoint, outputs=("voxels",), compression="zstd", raw=True, timeout_s=10)
        with pytest.raises(PlanServerError, match=r"array 'voxels' part 1: zstd frame does not decompress"):
            next(iter(bad_ds))
        ok_ds = V2VStreamDataset(endpoint, outputs=("voxels",), compression="zstd", raw=True, timeout_s=10)
        b = next(iter(ok_ds))
        assert torch.equal(b["voxels"], torch.from_numpy(good)) and b["sample_ids"] == ["a#0", "a#1"]
    finally:
        stop.set()
        t.join(30)
        router.close(0)


def test_auto_compression_is_none_nearby_and_what_the_server_has_across_hosts():
    """compression="auto": nothing on ipc:// and loopback; zstd to other hosts when this side
    and the server (its stream info's ``codecs``) both have it, else nothing."""
    from v2v_wire.codecs import available

    assert is_loopback("ipc:///tmp/x.sock") and is_loopback("tcp://127.0.0.1:5555") and is_loopback("tcp://[::1]:5")
    assert is_loopback("tcp://localhost:5555") and not is_loopback("tcp://10.0.0.7:5555")
    assert available("zstd")  # this environment has the wire's packages
    assert auto_compression("tcp://10.0.0.7:5555", ("lz4", "zstd")) == "zstd"
    assert auto_compression("tcp://10.0.0.7:5555", ("lz4",)) == "none"  # a server without zstandard
    for nearby in ("ipc:///tmp/x.sock", "tcp://127.0.0.1:5555", "tcp://localhost:5555"):
        assert auto_compression(nearby, ("lz4", "zstd")) == "none"


def test_an_array_spec_whose_shape_overflows_is_a_protocol_error():
    """A header whose shape multiplies past 64 bits sizes nothing: its product is not wrapped
    to a size that matches the frame (then a reshape error, not a protocol error)."""
    from v2v_wire.protocol import ProtocolError, decode_arrays

    with pytest.raises(ProtocolError, match="needs"):
        decode_arrays([{"name": "voxels", "dtype": "uint8", "shape": [1 << 32, 1 << 32]}], [b""])


@pytest.mark.parametrize("spec", [
    {"name": "voxels", "dtype": "uint8", "shape": [True, 4]},  # a boolean is not a whole number here
    {"name": "voxels", "dtype": "uint8", "shape": [2, -1]},
    {"name": "voxels", "dtype": "uint8", "shape": [2.0, 4]},
    {"name": "voxels", "dtype": "uint8", "shape": (2, 4)},  # a list, as msgpack gives it
    {"name": "voxels", "dtype": "uint8", "shape": [1] * 9},
    {"name": "voxels", "dtype": "object", "shape": [2, 4]},
    {"name": 3, "dtype": "uint8", "shape": [2, 4]},
    ["voxels", "uint8", [2, 4]],
])
def test_one_array_spec_check_refuses_a_malformed_spec_on_every_path(spec):
    """``v2v_wire.protocol.array_spec`` is the one check of an array spec: socket frames
    (``decode_arrays``) and shared-memory slots (``service.shm.slot_layout``)
    refuse the same specs, booleans in a shape included."""
    from v2v_server.service.shm import slot_layout
    from v2v_wire.protocol import ProtocolError, array_spec, decode_arrays

    good = {"name": "voxels", "dtype": "uint8", "shape": [2, 4]}
    assert array_spec(good) == ("voxels", np.dtype("uint8"), [2, 4])
    assert decode_arrays([good], [bytes(8)])["voxels"].shape == (2, 4)
    for check in (lambda: array_spec(spec), lambda: decode_arrays([spec], [bytes(8)]), lambda: slot_layout([spec])):
        with pytest.raises(ProtocolError):
            check()

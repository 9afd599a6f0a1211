"""``pip install v2v[client]`` on a trainer host: torch, pyzmq, msgpack, numpy, PyYAML and nothing
of the server's (no numba, PyAV or OpenCV), and that install reads a real server's stream; and
``pip install v2v`` alone (no torch): ``import v2v_client`` works, and the plan protocol
(``v2v_wire.plan_messages`` on a DEALER socket) reads a server's rows as numpy arrays.

A fresh virtual environment (no system site packages) in a temporary folder gets torch (the
local 2.13.0 CPU wheel pip finds) and then the project with its ``client`` extra, built from a
copy of the sources; a ``v2v-serve`` of the main environment serves the bundled clips by plan
(the default delivery) and the venv's python reads batches through ``V2VStreamDataset``, and
``v2v-loadtest`` measures it. The base install gets a venv of its own, which asks the same kind
of server for its plan and fetches the epoch's first two positions. Skipped only when
no venv with pip can be made here.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from harness.serve import ServeProcess

ROOT = Path(__file__).resolve().parents[1]
L, B, CROP = 4, 5, 64
SOURCES = ("pyproject.toml", "README.md", "v2v_wire", "v2v_server", "v2v_client", "trainer")

#: Reads one batch through the network side alone: the plan protocol by hand on a DEALER socket.
NETWORK_READER = textwrap.dedent("""
    import json, sys, time
    import zmq
    import v2v_client
    from v2v_client.endpoints import split_endpoints
    from v2v_wire.codecs import decode_batch_arrays
    from v2v_wire.plan_messages import Fetch, PlanAsk, PlanInfo, Rows, plan_server_message
    from v2v_wire.protocol import pack, unpack

    endpoint, = split_endpoints(sys.argv[1])
    sock = zmq.Context.instance().socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(endpoint)

    def ask(message, kind, deadline=time.monotonic() + 180):
        sock.send(pack(message.to_wire()))
        while time.monotonic() < deadline:
            if sock.poll(1000):
                frames = sock.recv_multipart(copy=False)
                got = plan_server_message(unpack(frames[0]))
                assert isinstance(got, kind), got
                return got, frames[1:]
        raise TimeoutError(f"no {kind.__name__} within 180 s")

    info, _ = ask(PlanAsk(), PlanInfo)
    rows, frames = ask(Fetch(1, 0, 0, 2, ("voxels", "frames"), info.plan), Rows)
    arrays = decode_batch_arrays(rows.arrays, frames)
    sock.close()
    try:
        v2v_client.V2VStreamDataset
        needs_torch = None
    except ImportError as e:
        needs_torch = str(e)
    print(json.dumps({
        "types": sorted({type(v).__module__ + "." + type(v).__name__ for v in arrays.values()}),
        "shapes": {k: list(v.shape) for k, v in arrays.items()},
        "dtypes": {k: str(v.dtype) for k, v in arrays.items()},
        "events": int(abs(arrays["voxels"].astype("int64")).sum()),
        "sample_ids": [s for s, p in zip(rows.sample_ids, rows.padding) if not p],
        "torch_loaded": "torch" in sys.modules,
        "needs_torch": needs_torch,
    }))
""")

READER = textwrap.dedent("""
    import importlib.util, json, sys
    from v2v_client import V2VStreamDataset
    from v2v_wire.flowgrid import HAVE_NUMBA
    ds = V2VStreamDataset(sys.argv[1], outputs=("voxels", "frames", "flow", "polarity_counts"), timeout_s=180)
    it = iter(ds)
    b = next(it)
    it.close()
    print(json.dumps({
        "shapes": {k: list(v.shape) for k, v in b.items() if hasattr(v, "shape")},
        "dtypes": {k: str(v.dtype) for k, v in b.items() if hasattr(v, "dtype")},
        "events": float(b["voxels"].abs().sum()),
        "importable": {m: importlib.util.find_spec(m) is not None for m in ("numba", "av", "cv2", "torch", "zmq")},
        "loaded": sorted(m for m in ("numba", "av", "cv2", "v2v_server") if m in sys.modules),
        "have_numba": HAVE_NUMBA,
    }))
""")


def _run(cmd, timeout_s: float, **kw) -> subprocess.CompletedProcess:
    """Run a command of the venv without this environment's PYTHONPATH (it would shadow the install)."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, env=env, **kw)
    assert r.returncode == 0, f"{' '.join(map(str, cmd))} failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return r


def _venv_with(tmp: Path, torch: bool, extras: str) -> Path:
    """A fresh venv in ``tmp`` (no system site packages) with this checkout installed from a
    copy of its sources (``extras``: e.g. ``"[client]"``), torch 2.13.0 first when ``torch``;
    returns its python."""
    venv = tmp / "venv"
    made = subprocess.run([sys.executable, "-m", "venv", str(venv)], capture_output=True, text=True, timeout=300)
    py = venv / "bin" / "python"
    if made.returncode != 0 or not py.exists():
        pytest.skip(f"cannot make a virtual environment with pip here: {made.stderr.strip()[-300:]}")
    src = tmp / "src"
    for name in SOURCES:
        p = ROOT / name
        if p.is_dir():
            shutil.copytree(p, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            src.mkdir(exist_ok=True)
            shutil.copy2(p, src / name)
    if torch:
        _run([py, "-m", "pip", "install", "-q", "torch==2.13.0"], 900)
    _run([py, "-m", "pip", "install", "-q", f"{src}{extras}"], 900)
    return py


@pytest.fixture(scope="module")
def client_venv(tmp_path_factory) -> Path:
    """The venv's python, with ``v2v[client]`` installed from a copy of this checkout."""
    return _venv_with(tmp_path_factory.mktemp("client-install"), True, "[client]")


@pytest.fixture(scope="module")
def base_venv(tmp_path_factory) -> Path:
    """The venv's python, with ``v2v`` (no extra, so no torch) installed from a copy of this checkout."""
    return _venv_with(tmp_path_factory.mktemp("base-install"), False, "")


@pytest.mark.timeout(1800)
def test_client_extra_installs_no_server_packages_and_reads_a_stream(client_venv, videos):
    listed = _run([client_venv, "-m", "pip", "list", "--format", "json"], 120).stdout
    names = {p["name"].lower() for p in json.loads(listed)}
    assert {"torch", "pyzmq", "msgpack", "numpy", "pyyaml", "v2v"} <= names
    assert not names & {"numba", "llvmlite", "av", "opencv-contrib-python-headless", "opencv-python",
                        "prometheus-client", "tqdm"}, sorted(names)
    args = ["--videos", str(videos), "--workers", "1", "--sequence-length", str(L), "--num-bins", str(B),
            "--crop-size", str(CROP), "--max-samples-per-video", "1", "--batch-size", "2", "--seed", "3"]
    with ServeProcess(args) as srv:
        # the venv's python, from a folder outside the checkout: it imports the installed v2v only
        out = _run([client_venv, "-c", READER, srv.endpoint], 600, cwd=client_venv.parent.parent).stdout
        # the console script pip wrote (its entry, v2v_wire.commands, needs nothing of the server's)
        measured = _run([client_venv.parent / "v2v-loadtest", "--connect", srv.endpoint, "--batches", "1", "--warmup",
                         "0", "--outputs", "voxels"], 600, cwd=client_venv.parent.parent).stdout
    assert measured.startswith("1 batches"), measured
    got = json.loads(out.strip().splitlines()[-1])
    assert got["importable"] == {"numba": False, "av": False, "cv2": False, "torch": True, "zmq": True}
    assert got["loaded"] == [] and got["have_numba"] is False
    n = got["shapes"]["voxels"][0]
    assert got["shapes"]["voxels"] == [n, L, B, CROP, CROP] and got["dtypes"]["voxels"] == "torch.float32"
    assert got["shapes"]["frames"] == [n, L + 1, 1, CROP, CROP]
    assert got["shapes"]["flow"] == [n, L, 2, CROP, CROP] and got["dtypes"]["flow"] == "torch.float32"
    assert got["shapes"]["polarity_counts"] == [n, L, 2, B, CROP, CROP]
    assert got["events"] > 0


@pytest.mark.timeout(1800)
def test_base_install_imports_v2v_client_without_torch_and_reads_a_batch(base_venv, videos):
    listed = _run([base_venv, "-m", "pip", "list", "--format", "json"], 120).stdout
    names = {p["name"].lower() for p in json.loads(listed)}
    assert {"pyzmq", "msgpack", "numpy", "pyyaml", "v2v"} <= names
    assert not names & {"torch", "numba", "av", "opencv-contrib-python-headless"}, sorted(names)
    args = ["--videos", str(videos), "--workers", "1", "--sequence-length", str(L), "--num-bins", str(B),
            "--crop-size", str(CROP), "--max-samples-per-video", "1", "--batch-size", "2", "--seed", "3"]
    with ServeProcess(args) as srv:
        out = _run([base_venv, "-c", NETWORK_READER, srv.endpoint], 600, cwd=base_venv.parent.parent).stdout
    got = json.loads(out.strip().splitlines()[-1])
    assert got["torch_loaded"] is False and got["types"] == ["numpy.ndarray"]
    n = len(got["sample_ids"])
    assert n == 2 and {s.split("#")[0] for s in got["sample_ids"]} <= {p.name for p in videos.glob("*.mp4")}
    assert got["shapes"]["voxels"] == [n, L, B, CROP, CROP] and got["dtypes"]["voxels"] in ("int8", "int16", "int32")
    assert got["shapes"]["frames"] == [n, L + 1, CROP, CROP] and got["dtypes"]["frames"] == "uint8"
    assert got["events"] > 0
    assert "pip install 'v2v[client]'" in got["needs_torch"]

"""Shared fixtures: the real clips bundled with the project (``harness.data.SAMPLE_VIDEOS``)."""
from __future__ import annotations

import functools
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from harness.data import ROOT, SAMPLE_VIDEOS

#: The material folder CI keeps beside the clone: the suite must not read it (a user's clone has
#: nothing there). ``tests/test_data_paths.py`` checks the source for any path leading out of the
#: repository; this guard refuses, while the suite runs, the reads that would use this one.
BESIDE = ROOT.parent / "shared"


def in_beside(path) -> bool:
    """Whether ``path`` (str, bytes or path-like; relative to the working directory) lies in
    :data:`BESIDE`, the folder beside the repository the suite must not read."""
    try:
        p = os.path.abspath(os.fsdecode(path))
    except (TypeError, ValueError):
        return False  # a file descriptor or something else that names no path
    return p == str(BESIDE) or p.startswith(str(BESIDE) + os.sep)


def _refuse_reads_beside(event: str, args: tuple) -> None:
    """Audit hook (``sys.addaudithook``): an open, listing or glob of a path beside the
    repository raises ``PermissionError`` naming it, so the test that made it fails."""
    if event in ("open", "os.listdir", "os.scandir", "glob.glob") and args and in_beside(args[0]):
        raise PermissionError(f"test material outside the repository: {os.fsdecode(args[0])} (the suite reads "
                              f"only what the repository holds: harness/data.py names it)")


sys.addaudithook(_refuse_reads_beside)


@pytest.fixture(autouse=True)
def _own_home_cache(tmp_path_factory, monkeypatch):
    """Each test gets its own home cache (``$XDG_CACHE_HOME/v2v``: manifests, the corpus index),
    so what one test's passes learned (a server start reads the corpus index) never changes
    another's, whatever the order, and the suite leaves the user's ``~/.cache`` alone."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path_factory.mktemp("xdg-cache")))


def pytest_configure(config):
    """Module- and session-scoped fixtures (started before any test's own home cache) get one
    of the session's, under pytest's temporary folder, not the user's ``~/.cache``."""
    import tempfile

    if "XDG_CACHE_HOME" not in os.environ:
        config._v2v_home_cache = tempfile.TemporaryDirectory(prefix="v2v-tests-xdg-")
        os.environ["XDG_CACHE_HOME"] = config._v2v_home_cache.name


def pytest_unconfigure(config):
    held = getattr(config, "_v2v_home_cache", None)
    if held is not None:
        os.environ.pop("XDG_CACHE_HOME", None)
        held.cleanup()


def video_dir() -> Path:
    """Folder of the real clips the tests read: the bundled ones, inside the repository."""
    return SAMPLE_VIDEOS


@functools.lru_cache(maxsize=4)
def read_luma_clip(name: str = "bikes.mp4", n: int = 60, size=(96, 128)) -> np.ndarray:
    """First n full-range luma frames of a real clip, resized to size=(H, W), uint8 (n, H, W)."""
    import cv2

    from v2v_server.frames.decode import iter_luma

    out = []
    frames = iter_luma(video_dir() / name)  # the stream's reader (full-range luma)
    for g in frames:
        out.append(cv2.resize(g, (size[1], size[0]), interpolation=cv2.INTER_AREA))
        if len(out) == n:
            break
    frames.close()
    arr = np.stack(out)
    arr.setflags(write=False)
    return arr


@pytest.fixture(scope="session")
def videos() -> Path:
    return video_dir()


@pytest.fixture
def bikes_corpus(tmp_path, videos) -> Path:
    """A corpus folder holding a copy of bikes.mp4 (a copy: the server refuses links leaving its
    root)."""
    import shutil

    d = tmp_path / "vids"
    d.mkdir()
    shutil.copyfile(videos / "bikes.mp4", d / "bikes.mp4")
    return d


@pytest.fixture(scope="session")
def real_clip() -> np.ndarray:
    return read_luma_clip()


#: a short recipe: windows of 41 frames (8 voxel grids of 0.2 s at 25 fps) in batches of 2, so the
#: bundled clips give samples fast
SHORT_RECIPE = "sequence_length: 8\nbatch_size: 2\n"


@pytest.fixture
def short_recipe(tmp_path) -> str:
    """The path (str) of :data:`SHORT_RECIPE` written as a recipe file in the test's own folder."""
    p = tmp_path / "short.yaml"
    p.write_text(SHORT_RECIPE)
    return str(p)


@pytest.fixture
def inductor_cache(tmp_path):
    """Inductor's kernel cache in the test's own folder, for a test that compiles with inductor
    in its process or in processes it starts (they inherit ``TORCHINDUCTOR_CACHE_DIR``).
    Inductor takes a cached ``.so`` that exists as built: one left short in the machine's shared
    cache (``/tmp/torchinductor_<user>``) by another process made a CI run's compiled steps
    fail with "file too short", whatever the code under test."""
    from torch._inductor.utils import fresh_cache

    with fresh_cache(dir=str(tmp_path)):
        yield


@pytest.fixture(scope="session", autouse=True)
def _warm_kernel_cache():
    """Compile (or load from numba's cache) the kernel's common signatures once, before any
    test starts a server: on a cold cache every worker process would otherwise compile it
    (~15 s) while a test waits for its first batch."""
    from v2v_server.simulation.simulate import SensorParams, simulate_voxels

    frames = np.zeros((6, 4, 4), np.uint8)
    simulate_voxels(frames, SensorParams(0.1, 0.1, 0.01), 5, rng=np.random.default_rng(0))
    simulate_voxels(frames, SensorParams(0.1, 0.1, 0.01), 5, rng=np.random.default_rng(0), compute_dtype=np.float64)


@pytest.fixture(autouse=True)
def _ordinary_scheduling(request):
    """Each test starts with the suite's process on the ordinary time-sharing policy, and a test
    that leaves it real-time is named: the process's children inherit the policy, and a
    real-time server or busy process beside it starves everything else on the machine. SVT-AV1,
    the encoder tests/test_encodings.py makes its AV1 clip with, puts the encoding thread on
    SCHED_FIFO when it runs as root."""
    yield
    if sys.platform.startswith("linux") and os.sched_getscheduler(0) != os.SCHED_OTHER:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        with open(os.environ.get("V2V_SCHED_LOG", os.devnull), "a") as f:
            f.write(f"{request.node.nodeid} left the test process on a real-time policy\n")

"""Shared fixtures: the real clips in ../shared/data/videos (the bundled copies as fallback)."""
from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_VIDEOS = ROOT.parent / "shared" / "data" / "videos"
BUNDLED_VIDEOS = ROOT / "v2v_server" / "sample_videos"


def video_dir() -> Path:
    """Folder of real clips: ../shared/data/videos beside the checkout, else the bundled copies."""
    return SHARED_VIDEOS if SHARED_VIDEOS.is_dir() else BUNDLED_VIDEOS


@functools.lru_cache(maxsize=4)
def read_luma_clip(name: str = "bikes.mp4", n: int = 60, size=(96, 128)) -> np.ndarray:
    """First n full-range luma frames of a real clip, resized to size=(H, W), uint8 (n, H, W)."""
    import cv2

    from v2v_server.videos.decode import iter_luma

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


@pytest.fixture(scope="session", autouse=True)
def _warm_kernel_cache():
    """Compile (or load from numba's cache) the kernel's common signatures once, before any
    test starts a server: on a cold cache every worker process would otherwise compile it
    (~15 s) while a test waits for its first batch."""
    from v2v_server.simulation.simulate import SensorParams, simulate_voxels

    frames = np.zeros((6, 4, 4), np.uint8)
    simulate_voxels(frames, SensorParams(0.1, 0.1, 0.01), 5, rng=np.random.default_rng(0))
    simulate_voxels(frames, SensorParams(0.1, 0.1, 0.01), 5, rng=np.random.default_rng(0), compute_dtype=np.float64)

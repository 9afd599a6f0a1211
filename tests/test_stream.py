"""End to end: a real v2v-serve on 127.0.0.1 with 2 workers on the real clips, read through
V2VStreamDataset. Every test is bounded in time and stops what it starts."""
from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import time

import pytest
import torch

from v2v_client import V2VStreamDataset
from harness.serve import ServeProcess, free_port
from v2v_server.samples.recipe import SampleRecipe
from v2v_server.frames.check import check_video
from v2v_server.sources.local import LocalSource
from v2v_server.sources.folder_scan import find_videos



L, B, CROP, MAXW = 8, 5, 96, 3


def expected_ids(videos):
    cfg = SampleRecipe(sequence_length=L, num_bins=B, max_samples_per_video=MAXW)
    ids = set()
    for rel in find_videos(videos, (".mp4",)):
        n = check_video(cfg.windows, cfg.decode, LocalSource(str(videos)), rel.as_posix()).windows
        ids.update(f"{rel.as_posix()}#{k}" for k in range(n))
    return ids


def serve_args(videos, *extra):
    return ["--videos", str(videos), "--workers", "2", "--sequence-length", str(L), "--num-bins", str(B),
            "--crop-size", str(CROP), "--max-samples-per-video", str(MAXW), "--seed", "7", *extra]


def _rows(ds):
    """[(sample id, padding, batch, row)] of every row ``ds`` yields."""
    return [(sid, bool(b["padding"][i]), b, i) for b in ds for i, sid in enumerate(b["sample_ids"])]


def test_one_epoch_serves_every_sample_once_with_correct_layout(videos):
    want = expected_ids(videos)
    assert len(want) >= 6  # bikes, bigbuckbunny and webvid_like each give windows at L = 8
    with ServeProcess(serve_args(videos, "--batch-size", "4")) as srv:
        rows = _rows(V2VStreamDataset(srv.endpoint, 4, timeout_s=120))
    assert sorted(sid for sid, pad, _, _ in rows if not pad) == sorted(want)  # every id of the epoch, exactly once
    assert len(rows) == -(-len(want) // 4) * 4  # whole batches: the last one's tail is padding
    for sid, pad, b, i in rows:
        assert b["epoch"] == 0 and len(b["sample_ids"]) == 4
        v, f, fl = b["voxels"][i], b["frames"][i], b["flow"][i]
        assert v.shape == (L, B, CROP, CROP) and v.dtype == torch.float32
        assert f.shape == (L + 1, 1, CROP, CROP) and f.dtype == torch.float32
        assert fl.shape == (L, 2, CROP, CROP) and fl.dtype == torch.float32
        if pad:  # past the epoch's end: no sample, zeros
            assert sid is None and not v.any() and not f.any() and not fl.any()
            continue
        assert torch.equal(v, v.round())  # signed event counts
        assert v.abs().sum() > 0 and (v > 0).any() and (v < 0).any()
        assert 0.0 <= f.min() and f.max() <= 1.0 and f.std() > 0.01
        # flow is composed over the B one-frame links (flow.py): each link stays within the crop;
        # a fast pan (bikes.mp4 has 30 px per frame) legitimately moves content beyond it per voxel
        assert torch.isfinite(fl).all() and fl.abs().max() < B * CROP
        p = b["params"][i]
        assert p["pos_threshold"] > 0 and p["neg_threshold"] > 0
        ratio = max(p["pos_threshold"], p["neg_threshold"]) / min(p["pos_threshold"], p["neg_threshold"])
        assert 0.05 <= min(p["pos_threshold"], p["neg_threshold"]) <= 2.0 and ratio <= 1.5 + 1e-9
        assert 0 <= p["noise_std"] <= 0.1


def test_voxels_only_reader_gets_no_flow_and_frames_and_workers_make_none(videos):
    with ServeProcess(serve_args(videos, "--batch-size", "2")) as srv:
        ds = V2VStreamDataset(srv.endpoint, 2, outputs=("voxels",), timeout_s=120)
        it = iter(ds)
        b = next(it)
        it.close()
        assert set(k for k in b if isinstance(b[k], torch.Tensor)) == {"voxels", "padding"}
        assert b["padding"].dtype == torch.bool and not b["padding"].any()
        assert "flow" not in b and "frames" not in b
        busy = ds.plan_info(refresh=True).stream["feed"]["busy_s"]
    assert busy["simulate"] > 0 and busy["flow"] == 0, busy  # the workers computed no flow for it


def test_absent_server_is_a_clear_error_not_a_hang():
    ds = V2VStreamDataset(f"tcp://127.0.0.1:{free_port()}", 2, retry_s=1.0, timeout_s=1.5)
    t = time.monotonic()
    with pytest.raises(TimeoutError, match="is a v2v-serve running there"):
        next(iter(ds))
    assert time.monotonic() - t < 10


def test_server_killed_mid_stream_gives_error_after_timeout(videos):
    srv = ServeProcess(serve_args(videos, "--batch-size", "2")).start()
    try:
        first = next(iter(V2VStreamDataset(srv.endpoint, 1, timeout_s=120)))  # decoded and kept by the server
        ds = V2VStreamDataset(srv.endpoint, 1, timeout_s=2.0, retry_s=1.0, prefetch=1)
        it = iter(ds)
        assert next(it)["sample_ids"] == first["sample_ids"]
        srv.proc.kill()
        t = time.monotonic()
        with pytest.raises(TimeoutError, match="no rows for 2.0 s"):
            for _ in range(100):
                next(it)
        assert time.monotonic() - t < 15
    finally:
        srv.stop()


def test_dataloader_with_pin_memory(videos):
    with ServeProcess(serve_args(videos, "--batch-size", "2")) as srv:
        ds = V2VStreamDataset(srv.endpoint, 2, outputs=("voxels", "frames"), timeout_s=120)
        with pytest.warns(UserWarning) if not torch.cuda.is_available() else contextlib.nullcontext():
            dl = torch.utils.data.DataLoader(ds, batch_size=None, pin_memory=True)
            it = iter(dl)
            b = next(it)
        assert b["voxels"].shape == (2, L, B, CROP, CROP) and b["voxels"].abs().sum() > 0
        assert isinstance(b["sample_ids"], list) and all(s in expected_ids(videos) for s in b["sample_ids"])
        del it


def test_loadtest_cli_reports_json(videos):
    with ServeProcess(serve_args(videos, "--batch-size", "2")) as srv:
        out = subprocess.run([sys.executable, "-m", "v2v_client.loadtest", "--connect", srv.endpoint,
                              "--batches", "3", "--json", "--outputs", "voxels,frames"],
                             capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    r = json.loads(out.stdout.strip().splitlines()[-1])
    for k in ("batches", "samples", "unique_samples", "seconds", "batches_per_s", "samples_per_s",
              "mbytes_per_s", "wait_fraction"):
        assert k in r
    assert r["batches"] == 3 and r["samples"] == r["unique_samples"] == 6, r
    assert r["batches_per_s"] > 0 and 0 <= r["wait_fraction"] <= 1, r


def test_bad_config_fails_at_startup_naming_field(tmp_path, videos):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("num_bins: 0\n")
    out = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--config", str(cfg), "--videos", str(videos)],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "num_bins" in out.stderr and str(cfg) in out.stderr
    cfg.write_text("sequence_lenght: 10\n")
    out = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--config", str(cfg)],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "sequence_lenght" in out.stderr


def test_sigterm_ends_a_worker_at_once_without_unwinding_through_library_code():
    """What a worker does on SIGTERM (the pool's stop): exit 0 at once. An exception raised
    from the handler would be caught by whatever code the signal lands in (numba's compiler
    catches and prints them) and print a traceback on a clean shutdown."""
    code = ("import os, signal, time\n"
            "from v2v_server.service.worker import exit_on_sigterm\n"
            "exit_on_sigterm()\n"
            "try:\n"
            "    os.kill(os.getpid(), signal.SIGTERM)\n"
            "    time.sleep(5)\n"
            "except BaseException as e:\n"
            "    print('caught', type(e).__name__)\n"
            "print('went on')\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert (r.returncode, r.stdout, r.stderr) == (0, "", "")


def test_ipv6_loopback_on_both_ends(videos):
    import socket

    try:
        s = socket.socket(socket.AF_INET6)
        s.bind(("::1", 0))
        port = s.getsockname()[1]
        s.close()
    except OSError as e:
        pytest.skip(f"this machine has no IPv6 loopback: {e}")
    endpoint = f"tcp://[::1]:{port}"
    with ServeProcess(["--videos", str(videos), "--bind", endpoint, "--crop-size", "64", "--sequence-length", "4",
                       "--max-samples-per-video", "1", "--batch-size", "2"]):
        rows = _rows(V2VStreamDataset(endpoint, 2, outputs=("voxels",), timeout_s=120))
    ids = [sid for sid, pad, _, _ in rows if not pad]
    assert len(ids) == len(set(ids)) == 4 and all(b["voxels"][i].abs().sum() > 0 for sid, pad, b, i in rows if not pad)


def test_a_workers_socket_path_too_long_is_blamed_on_tmpdir_not_the_endpoint(videos, tmp_path):
    deep = tmp_path / ("d" * 60) / ("e" * 60)
    deep.mkdir(parents=True)
    out = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--videos", str(videos), "--bind",
                          f"tcp://127.0.0.1:{free_port()}"], capture_output=True, text=True, timeout=60,
                         env={**__import__("os").environ, "TMPDIR": str(deep)})
    assert out.returncode == 2
    assert "TMPDIR" in out.stderr and "Traceback" not in out.stderr, out.stderr


def test_sigterm_to_the_process_group_stops_the_server_without_restarting_workers(videos):
    """A supervisor that signals the whole process group (systemd's default KillMode, a
    container stop with an init that forwards to the group, ``kill -TERM -PGID``): the workers
    exit at once (status 0) while the server shuts down, and the server takes that for the
    shutdown it is, not for crashes: no "died ... restarting" line, no restart counted, exit
    status 0. Idle workers show it best: nothing delays their exit."""
    import os
    import signal
    import threading
    import urllib.error
    import urllib.request

    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "v2v_server.cli",
                             *serve_args(videos, "--bind", f"tcp://127.0.0.1:{free_port()}", "--metrics-port", str(port))],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    lines: list = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + 120
        while True:  # a worker said ready (the pool's workers start together)
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/readyz", timeout=2) as r:
                    if r.status == 200:
                        break
            except (urllib.error.URLError, OSError):
                pass
            assert time.monotonic() < deadline and proc.poll() is None, "".join(lines)
            time.sleep(0.2)
        time.sleep(2.0)  # and the other worker too
        os.killpg(proc.pid, signal.SIGTERM)
        code = proc.wait(60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)
    reader.join(10)
    log = "".join(lines)
    assert "SIGTERM: shutting down" in log, log
    assert "restarting" not in log and "died" not in log and " 0 worker restart(s)" in log, log
    assert code == 143, log  # 128 + SIGTERM: a stop by a signal is not a stream that ended


def test_a_clip_too_short_for_one_window_is_skipped_without_a_warning(videos):
    """bigbuckbunny.mp4 (132 frames) gives no window of 30 voxels x 5 bins (151 frames): an
    INFO line says so, no WARNING (a short clip is no fault of the file)."""
    args = ["--videos", str(videos), "--workers", "1", "--sequence-length", "30", "--crop-size", "32",
            "--batch-size", "1", "--max-samples-per-video", "1", "--shot-cuts", "off"]
    with ServeProcess(args) as srv:
        rows = _rows(V2VStreamDataset(srv.endpoint, 1, outputs=("voxels",), timeout_s=120))
    ids = [sid for sid, pad, _, _ in rows if not pad]
    assert ids and len(ids) == len(set(ids)) and not any(s.startswith("bigbuckbunny.mp4#") for s in ids), ids
    assert "INFO skipped " in srv.log and "bigbuckbunny.mp4: 132 frames, shorter than one window of 151" in srv.log
    assert "WARNING" not in srv.log


def test_a_worker_stopped_before_it_says_ready_is_replaced_and_the_epoch_served(videos):
    """The only worker, stopped (SIGSTOP) as soon as it is spawned, before its first message: it
    holds no task to time out, so the server replaces it once ``START_S`` passes, and the epoch is
    served whole (before, such a server served nothing for good)."""
    import os
    import signal
    import threading

    from harness.faults import worker_pids
    from v2v_server.service.worker_side import START_S

    want = expected_ids(videos)
    srv = ServeProcess(serve_args(videos, "--batch-size", "4", "--workers", "1", "--task-timeout", "5"))
    starting = threading.Thread(target=srv.start, daemon=True)
    starting.start()
    stopped: list = []
    deadline = time.monotonic() + 60
    while not stopped and time.monotonic() < deadline:  # the worker's interpreter is still starting
        stopped = worker_pids(srv.proc.pid) if srv.proc is not None else []
        time.sleep(0.002)
    for pid in stopped:
        os.kill(pid, signal.SIGSTOP)
    starting.join(60)
    try:
        t0 = time.monotonic()
        rows = _rows(V2VStreamDataset(srv.endpoint, 4, timeout_s=START_S + 45, raw=True))
    finally:
        for pid in stopped:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGCONT)
        srv.stop()
    assert len(stopped) == 1
    assert sorted(sid for sid, pad, _, _ in rows if not pad) == sorted(want)
    assert f"said nothing in the {START_S:.0f} s since it started; restarted" in srv.log, srv.log[-3000:]
    assert time.monotonic() - t0 > 1.0  # the first rows waited for the worker started in its place

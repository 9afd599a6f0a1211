"""Push delivery is gone (docs/delivery.md): each of its names, flags, config keys, settings,
resume states and wire messages is refused in one line that says what to use instead, through
the real entry points (imports, ``v2v-serve`` as a child process, the dataset, a socket)."""
from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

import msgpack
import pytest
import zmq

from harness.serve import ServeProcess
from v2v_client import PlanServerError, V2VStreamDataset
from v2v_wire.plan import PlanMismatch
from v2v_wire.protocol import PROTOCOL_VERSION

ROOT = Path(__file__).resolve().parents[1]
OLD = 10  # the last protocol version of push delivery


def _serve(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "v2v_server.cli", "--bind", "tcp://127.0.0.1:0", *args],
                          capture_output=True, text=True, cwd=ROOT, env=env, timeout=timeout)


@pytest.mark.parametrize("name, instead", [("V2VPushDataset", "use V2VStreamDataset"),
                                           ("StreamLoader", "use torch's DataLoader(V2VStreamDataset(...)"),
                                           ("ResumeState", "use a batch's 'position'"),
                                           ("PushServerError", "use PlanServerError"),
                                           ("dist_position", "use V2VStreamDataset")])
def test_importing_a_push_name_says_what_to_use_in_one_line(name, instead):
    with pytest.raises(ImportError) as err:
        exec(f"from v2v_client import {name}", {})
    line = str(err.value)
    assert "\n" not in line and line.startswith(f"v2v_client.{name} was removed with push delivery: {instead}")


def test_a_push_name_is_refused_without_torch_installed():
    """The table of push delivery's names is read by ``import v2v_client`` on a host without torch."""
    code = ("import sys; sys.modules['torch'] = None\n"
            "try:\n    from v2v_client import V2VPushDataset\n"
            "except ImportError as e:\n    print(e)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == ("v2v_client.V2VPushDataset was removed with push delivery: use V2VStreamDataset "
                                "(docs/delivery.md)")


@pytest.mark.parametrize("args, flag, key, instead", [
    (["--delivery", "push"], "--delivery", "delivery_mode", "read the server with v2v_client.V2VStreamDataset"),
    (["--epochs", "2"], "--epochs", "epochs", "ds.set_epoch(e) for each"),
    (["--state-dir", "X"], "--state-dir", "state_dir", "a checkpoint is the trainer's position"),
    (["--revoke-s", "1"], "--revoke-timeout", "revoke_s", "a plan server hands out no batch to take back")])
def test_v2v_serve_refuses_a_push_flag_in_one_line_and_exits_2(tmp_path, args, flag, key, instead):
    r = _serve("--videos", str(tmp_path), *args)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.splitlines()
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith(f"v2v-serve: {flag} ({key}) was push delivery's, which v2v no longer has: ")
    assert instead in lines[0] and lines[0].endswith("(docs/delivery.md)")


def test_v2v_serve_takes_delivery_plan_as_the_only_delivery(tmp_path):
    """``--delivery plan`` is no error: the start goes on to the next problem (an empty folder)."""
    r = _serve("--videos", str(tmp_path / "missing"), "--delivery", "plan")
    assert r.returncode == 2 and r.stderr.strip() == f"v2v-serve: --videos {tmp_path / 'missing'}: not a folder"


def test_a_config_file_with_a_push_key_is_refused_in_one_line(tmp_path):
    cfg = tmp_path / "serve.yaml"
    cfg.write_text("sequence_length: 8\nepochs: 2\n")
    r = _serve("--config", str(cfg))
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.strip() == (f"v2v-serve: configuration error: {cfg}: --epochs (epochs) was push delivery's, "
                                "which v2v no longer has: the trainer owns its epochs: ds.set_epoch(e) for each, and "
                                "stop when done (docs/delivery.md)")


def test_a_push_setting_given_to_the_dataset_is_refused_in_one_line():
    with pytest.raises(ValueError) as err:
        V2VStreamDataset("tcp://127.0.0.1:1", credits=4)
    assert str(err.value) == ("credits: setting(s) of push delivery, which v2v no longer has (docs/delivery.md): "
                              "drop them")
    with pytest.raises(TypeError, match="unexpected keyword argument 'credit'"):  # a typo is not taken for push's
        V2VStreamDataset("tcp://127.0.0.1:1", credit=4)


def test_a_push_resume_state_is_refused_in_one_line_naming_the_position():
    ds = V2VStreamDataset("tcp://127.0.0.1:1", 4)  # no server is asked
    with pytest.raises(PlanMismatch) as err:
        ds.load_state_dict({"consumer": "x", "completed_epoch": 0, "delivered": {}})
    line = str(err.value)
    assert "\n" not in line and line.startswith("a resume state of push delivery, which v2v no longer has")
    assert "resume from a batch's 'position'" in line


def _old_hello(endpoint: str) -> list:
    """What a server answers a push client's ``hello`` at protocol 10 within 60 s: the decoded
    headers, waiting 1 s more for any further message."""
    ctx = zmq.Context.instance()
    sock = ctx.socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    try:
        sock.connect(endpoint)
        sock.send(msgpack.packb({"v": OLD, "type": "hello", "outputs": ["voxels"], "credits": 2,
                                 "consumer": "old-client"}, use_bin_type=True))
        got = []
        wait_ms = 60_000
        while sock.poll(wait_ms):
            got.append(msgpack.unpackb(sock.recv_multipart()[0], raw=False))
            wait_ms = 1000
        return got
    finally:
        sock.close()


@pytest.mark.timeout(300)
def test_an_old_push_client_gets_one_error_at_its_version_and_the_server_serves_on(videos):
    args = ["--videos", str(videos), "--workers", "1", "--sequence-length", "4", "--crop-size", "32",
            "--max-samples-per-video", "1", "--batch-size", "2", "--flow-preset", "ultrafast"]
    with ServeProcess(args) as srv:
        answers = _old_hello(srv.endpoint)
        assert len(answers) == 1, answers
        error = answers[0]
        assert error["v"] == OLD and error["type"] == "error"
        assert "\n" not in error["message"]
        assert f"protocol version {OLD}, expected {PROTOCOL_VERSION}" in error["message"]
        assert "push server or V2VPushDataset is gone" in error["message"]
        assert V2VStreamDataset(srv.endpoint, timeout_s=60).plan_info().samples != 0  # the next reader is served


def test_a_server_of_another_protocol_version_is_refused_naming_it():
    """A server answering at protocol 10 (an older v2v-serve, here a ROUTER in the test): the
    reader raises PlanServerError naming both versions at the first answer, not a timeout."""
    ctx = zmq.Context.instance()
    router = ctx.socket(zmq.ROUTER)
    router.setsockopt(zmq.LINGER, 0)
    port = router.bind_to_random_port("tcp://127.0.0.1")
    asked = []

    def answer():
        if router.poll(30_000):
            peer, header = router.recv_multipart()[:2]
            asked.append(msgpack.unpackb(header, raw=False))
            message = f"protocol version {PROTOCOL_VERSION}, expected {OLD}"
            router.send_multipart([peer, msgpack.packb({"v": OLD, "type": "error", "code": "version",
                                                        "message": message})])

    t = threading.Thread(target=answer, daemon=True)
    t.start()
    try:
        with pytest.raises(PlanServerError) as err:
            V2VStreamDataset(f"tcp://127.0.0.1:{port}", 4, timeout_s=30).plan_info()
    finally:
        t.join(35)
        router.close()
    assert asked and asked[0]["type"] == "plan_ask" and asked[0]["v"] == PROTOCOL_VERSION
    line = str(err.value)
    assert "\n" not in line and line.startswith(f"tcp://127.0.0.1:{port}: protocol version {OLD}, "
                                                f"expected {PROTOCOL_VERSION}: the peer runs an older v2v")

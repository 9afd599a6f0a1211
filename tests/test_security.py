"""Nobody without an allowed key reads the stream; non-loopback binds need keys."""
from __future__ import annotations

import subprocess
import sys

import pytest

from harness.faults import Layout, good_corpus
from v2v_client import StreamTimeout, V2VPushDataset
from v2v_server.ops.config import ServeConfig, is_loopback, load_config
from harness.serve import ServeProcess

LAYOUT = Layout(L=4, crop=64, windows=1, batch=1)


def keygen(folder, name):
    out = subprocess.run([sys.executable, "-m", "v2v_server.ops.keygen", name, "--out", str(folder)],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return folder / f"{name}.key", folder / f"{name}.key_secret"


def allowlist(tmp_path):
    """Keys of a server, an allowed trainer and a stranger (``v2v-keygen``), and the folder of
    allowed public keys: ``(allow, server_pub, server_sec, good_pub, good_sec, stranger_sec)``."""
    keys, allow = tmp_path / "keys", tmp_path / "allowed"
    allow.mkdir()
    server_pub, server_sec = keygen(keys, "server")
    good_pub, good_sec = keygen(keys, "trainer")
    _, stranger_sec = keygen(keys, "stranger")
    (allow / "trainer.key").write_bytes(good_pub.read_bytes())
    return allow, server_pub, server_sec, good_pub, good_sec, stranger_sec


def test_curve_allowlist(tmp_path):
    allow, server_pub, server_sec, good_pub, good_sec, stranger_sec = allowlist(tmp_path)
    assert (server_sec.stat().st_mode & 0o777) == 0o600
    corpus = good_corpus(tmp_path)
    args = ["--videos", str(corpus), "--workers", "1", "--curve-secret-key", str(server_sec),
            "--curve-allow", str(allow), *LAYOUT.args()]
    with ServeProcess(args) as srv:
        with pytest.raises(StreamTimeout):  # no keys at all: the CURVE handshake never completes
            next(iter(V2VPushDataset(srv.endpoint, timeout_s=2)))
        with pytest.raises(StreamTimeout):  # a key that is not on the allowlist: ZAP refuses it
            next(iter(V2VPushDataset(srv.endpoint, timeout_s=2, curve_keys=(str(stranger_sec), str(server_pub)))))
        it = iter(V2VPushDataset(srv.endpoint, timeout_s=30, curve_keys=(str(good_sec), str(server_pub))))
        b = next(it)
        it.close()
        assert b["voxels"].shape[0] == 1
    assert "CurveZMQ on: 1 allowed client key(s)" in srv.log


def test_non_loopback_bind_needs_keys_or_insecure(tmp_path):
    assert is_loopback("tcp://127.0.0.1:5555") and is_loopback("tcp://localhost:1") and is_loopback("ipc:///tmp/x")
    assert not is_loopback("tcp://0.0.0.0:5555") and not is_loopback("tcp://*:5555")
    with pytest.raises(ValueError, match="not a loopback address"):
        ServeConfig(bind="tcp://0.0.0.0:5555")
    assert ServeConfig(bind="tcp://0.0.0.0:5555", insecure=True).insecure
    # the CLI refuses before binding anything
    out = subprocess.run([sys.executable, "-m", "v2v_server.cli", "--bind", "tcp://0.0.0.0:5999"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "curve_secret_key" in out.stderr and "--insecure" not in out.stdout
    with pytest.raises(ValueError, match="together"):
        load_config(None, {"curve_secret_key": str(tmp_path / "x")})


def test_client_key_errors_name_the_file(tmp_path):
    with pytest.raises(ValueError, match="client key"):
        V2VPushDataset("tcp://127.0.0.1:1", curve_keys=(str(tmp_path / "missing"), str(tmp_path / "s.key")))
    pub, sec = keygen(tmp_path, "c")
    with pytest.raises(ValueError, match="no secret key"):
        V2VPushDataset("tcp://127.0.0.1:1", curve_keys=(str(pub), str(pub)))


def test_sample_ids_cannot_name_files(tmp_path):
    """A resume state naming files outside the corpus changes nothing: the server only ever
    opens the files it found under its root."""
    corpus = good_corpus(tmp_path)
    import zmq

    from v2v_wire.protocol import pack, unpack

    with ServeProcess(["--videos", str(corpus), "--workers", "1", *LAYOUT.args()]) as srv:
        ctx = zmq.Context()
        s = ctx.socket(zmq.DEALER)
        s.setsockopt(zmq.LINGER, 0)
        s.connect(srv.endpoint)
        s.send(pack({"type": "hello", "outputs": ["frames"], "credits": 1,
                     "resume": {"completed_epoch": -1, "delivered": {"0": "../../../etc/passwd#0\n/etc/shadow#1"}}}))
        ids = []
        for _ in range(100):
            if s.poll(200):
                h = unpack(s.recv_multipart()[0])
                if h["type"] == "batch":
                    ids += h["sample_ids"]
                    break
        s.close()
        ctx.term()
    assert ids and all(not i.startswith(("/", "..")) for i in ids)
    assert "passwd" not in srv.log and "shadow" not in srv.log


def test_curve_allowlist_for_a_server_serving_by_plan(tmp_path):
    """``--delivery plan`` with CurveZMQ keys: V2VStreamDataset reads with an allowed key only."""
    from v2v_client import V2VStreamDataset

    allow, server_pub, server_sec, good_pub, good_sec, stranger_sec = allowlist(tmp_path)
    args = ["--videos", str(good_corpus(tmp_path)), "--workers", "1", "--delivery", "plan",
            "--curve-secret-key", str(server_sec), "--curve-allow", str(allow), *LAYOUT.args()]
    with ServeProcess(args) as srv:
        with pytest.raises(TimeoutError):  # no keys: the CURVE handshake never completes
            next(iter(V2VStreamDataset(srv.endpoint, 1, retry_s=1, timeout_s=2)))
        with pytest.raises(TimeoutError):  # a key that is not on the allowlist: ZAP refuses it
            next(iter(V2VStreamDataset(srv.endpoint, 1, retry_s=1, timeout_s=2,
                                     curve_keys=(str(stranger_sec), str(server_pub)))))
        b = next(iter(V2VStreamDataset(srv.endpoint, 1, timeout_s=60, curve_keys=(str(good_sec), str(server_pub)))))
        assert b["voxels"].shape[0] == 1
    assert "CurveZMQ on: 1 allowed client key(s)" in srv.log
    with pytest.raises(ValueError, match="no secret key"):
        V2VStreamDataset("tcp://127.0.0.1:1", 1, curve_keys=(str(good_pub), str(server_pub)))

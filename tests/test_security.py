"""Nobody without an allowed key reads the stream; non-loopback binds need keys."""
from __future__ import annotations

import re
import subprocess
import sys

import pytest

from harness.faults import Layout, expected_ids, good_corpus
from v2v_client import V2VStreamDataset
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
    missing = tmp_path / "missing"
    with pytest.raises(ValueError, match=f"client key {re.escape(str(missing))}"):
        V2VStreamDataset("tcp://127.0.0.1:1", 1, curve_keys=(str(missing), str(tmp_path / "s.key")))
    pub, sec = keygen(tmp_path, "c")
    with pytest.raises(ValueError, match="no secret key"):
        V2VStreamDataset("tcp://127.0.0.1:1", 1, curve_keys=(str(pub), str(pub)))


def test_curve_allowlist(tmp_path):
    """A server with CurveZMQ keys: V2VStreamDataset reads with an allowed key only."""
    allow, server_pub, server_sec, good_pub, good_sec, stranger_sec = allowlist(tmp_path)
    assert (server_sec.stat().st_mode & 0o777) == 0o600
    corpus = good_corpus(tmp_path)
    args = ["--videos", str(corpus), "--workers", "1",
            "--curve-secret-key", str(server_sec), "--curve-allow", str(allow), *LAYOUT.args()]
    with ServeProcess(args) as srv:
        with pytest.raises(TimeoutError):  # no keys: the CURVE handshake never completes
            next(iter(V2VStreamDataset(srv.endpoint, 1, retry_s=1, timeout_s=2)))
        with pytest.raises(TimeoutError):  # a key that is not on the allowlist: ZAP refuses it
            next(iter(V2VStreamDataset(srv.endpoint, 1, retry_s=1, timeout_s=2,
                                     curve_keys=(str(stranger_sec), str(server_pub)))))
        b = next(iter(V2VStreamDataset(srv.endpoint, 1, timeout_s=60, raw=True,
                                       curve_keys=(str(good_sec), str(server_pub)))))
        assert b["voxels"].shape[0] == 1 and b["voxels"].abs().sum() > 0
        assert not b["padding"][0] and b["sample_ids"][0] in expected_ids(corpus, LAYOUT)
    assert "CurveZMQ on: 1 allowed client key(s)" in srv.log
    with pytest.raises(ValueError, match="no secret key"):
        V2VStreamDataset("tcp://127.0.0.1:1", 1, curve_keys=(str(good_pub), str(server_pub)))

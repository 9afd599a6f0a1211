"""Run ``v2v-serve`` as a child process (a harness for benchmarks and tests; ``v2v-demo`` hosts the server in-process instead).

``ServeProcess`` binds to a free loopback port, waits until the server says it is serving,
and always stops it: SIGINT first, then SIGKILL after a grace period.
"""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from typing import List, Optional


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free on ``host`` a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class ServeProcess:
    """``with ServeProcess(["--workers", "2"]) as srv: ... srv.endpoint ...``

    Args:
        args: extra ``v2v-serve`` arguments (``--bind`` is added unless given).
        ready_timeout_s: seconds to wait for the server to report it is serving.
        log_path: file to which the server's stderr goes (kept in ``self.log`` otherwise).

    Raises:
        RuntimeError: when the server exits or stays silent before it serves; the message
            holds its log.
    """

    def __init__(self, args: Optional[List[str]] = None, ready_timeout_s: float = 60.0,
                 log_path: Optional[str] = None, env: Optional[dict] = None, wrap: Optional[List[str]] = None):
        self.args = list(args or [])
        self.wrap = list(wrap or [])  # a command the server runs under (e.g. unshare -m ... exec "$@")
        if "--bind" not in self.args:
            self.endpoint = f"tcp://127.0.0.1:{free_port()}"
            self.args += ["--bind", self.endpoint]
        else:
            self.endpoint = self.args[self.args.index("--bind") + 1]
        self.ready_timeout_s = ready_timeout_s
        self.log_path = log_path
        self.env = env
        self.lines: List[str] = []
        self.proc: Optional[subprocess.Popen] = None
        self._ready = threading.Event()

    @property
    def log(self) -> str:
        return "".join(self.lines)

    def start(self) -> "ServeProcess":
        env = dict(os.environ, PYTHONUNBUFFERED="1", **(self.env or {}))
        self.proc = subprocess.Popen([*self.wrap, sys.executable, "-m", "v2v_server.cli", *self.args],
                                     stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True, env=env)
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        deadline = time.monotonic() + self.ready_timeout_s
        while not self._ready.wait(0.1):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"v2v-serve did not start (exit code {self.proc.returncode}):\n{self.log}")
        return self

    def _read(self) -> None:
        fh = open(self.log_path, "a") if self.log_path else None
        try:
            for line in self.proc.stderr:
                self.lines.append(line)
                if fh:
                    fh.write(line)
                    fh.flush()
                if " serving " in line:
                    self._ready.set()
        finally:
            if fh:
                fh.close()

    def wait(self, timeout: float) -> int:
        """Wait for the server to exit by itself; returns its exit code.

        Raises:
            subprocess.TimeoutExpired: still running after ``timeout`` seconds.
        """
        return self.proc.wait(timeout)

    def stop(self, grace_s: float = 10.0) -> Optional[int]:
        """SIGINT, wait ``grace_s``, then SIGKILL. Returns the exit code."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(grace_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        if getattr(self, "_reader", None) is not None:
            self._reader.join(2.0)
        return self.proc.returncode

    def __enter__(self) -> "ServeProcess":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def served_samples(args: List[str], outputs=("voxels", "frames"), env=None, epoch: int = 0) -> List[tuple]:
    """Read epoch ``epoch`` of what a ``v2v-serve args`` child serves, whole, with raw wire dtypes:
    ``[(sample_id, {output: array})]`` in the plan's order, padding rows left out."""
    import numpy as np

    from v2v_client import V2VStreamDataset

    out = []
    with ServeProcess(args, env=env) as srv:
        ds = V2VStreamDataset(srv.endpoint, outputs=tuple(outputs), timeout_s=60, raw=True, rank=0, world_size=1)
        ds.set_epoch(epoch)
        for b in ds:
            out += [(sid, {k: np.asarray(b[k][i]) for k in outputs}) for i, sid in enumerate(b["sample_ids"])
                    if not bool(b["padding"][i])]
    return out

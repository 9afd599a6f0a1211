"""The server's ZeroMQ context and sockets: the client ROUTER bound to ``cfg.bind`` (with
CurveZMQ when configured) and the worker ROUTER on a private ``ipc://`` endpoint."""
from __future__ import annotations

import logging
import shutil
import tempfile
from pathlib import Path

import zmq

from v2v_server.ops.config import ServeConfig, is_loopback
from v2v_wire.protocol import MAX_CLIENT_MSG, is_ipv6

log = logging.getLogger("v2v.server")


class ServerSockets:
    """Created unbound; :meth:`bind` binds both; :meth:`close` closes everything, whatever
    state it is in (also after a failed bind)."""

    def __init__(self):
        self.ctx = zmq.Context()
        self.tmp = tempfile.mkdtemp(prefix="v2v-")
        self.frontend = self.ctx.socket(zmq.ROUTER)
        self.frontend.setsockopt(zmq.LINGER, 500)
        self.frontend.setsockopt(zmq.MAXMSGSIZE, 2 * MAX_CLIENT_MSG)  # past MAX_CLIENT_MSG: an error reply
        self.frontend.setsockopt(zmq.ROUTER_MANDATORY, 1)
        self.frontend.setsockopt(zmq.SNDHWM, 0)  # a reader's prefetch bounds what is queued for it
        self.backend = self.ctx.socket(zmq.ROUTER)
        self.backend.setsockopt(zmq.LINGER, 0)
        self.backend.setsockopt(zmq.RCVHWM, 4)
        self.backend_endpoint = f"ipc://{self.tmp}/workers"
        self.auth = None

    def bind(self, cfg: ServeConfig) -> str:
        """Bind the client socket to ``cfg.bind`` (CurveZMQ first when ``cfg`` has keys) and the
        worker socket; returns the endpoint actually bound (a port 0 resolved).

        Raises:
            ValueError: a key file without a secret key.
            zmq.ZMQError: the address cannot be bound.
        """
        if cfg.curve_secret_key is not None:
            self._setup_curve(cfg)
        elif not is_loopback(cfg.bind):
            log.warning("binding %s WITHOUT authentication or encryption (--insecure): anyone who can "
                        "reach it can read the stream", cfg.bind)
        if is_ipv6(cfg.bind):
            self.frontend.setsockopt(zmq.IPV6, 1)
        try:
            self.frontend.bind(cfg.bind)
        except zmq.ZMQError as e:
            raise OSError(f"cannot bind {cfg.bind}: {e}") from None
        bound = self.frontend.getsockopt_string(zmq.LAST_ENDPOINT)
        try:
            self.backend.bind(self.backend_endpoint)
        except zmq.ZMQError as e:
            raise OSError(f"cannot bind the workers' socket {self.backend_endpoint} (a folder under TMPDIR; "
                          f"ipc paths are limited to about 100 bytes: set a shorter TMPDIR): {e}") from None
        return bound

    def _setup_curve(self, cfg: ServeConfig) -> None:
        """CurveZMQ on the client socket: our key pair, and a ZAP authenticator that admits
        only the public keys found in ``curve_allow``."""
        import zmq.auth
        from zmq.auth.thread import ThreadAuthenticator

        public, secret = zmq.auth.load_certificate(cfg.curve_secret_key)
        if not secret:
            raise ValueError(f"curve_secret_key {cfg.curve_secret_key}: holds no secret key")
        self.auth = ThreadAuthenticator(self.ctx, log=logging.getLogger("v2v.auth"))
        self.auth.start()
        self.auth.configure_curve(domain="*", location=str(cfg.curve_allow))
        self.frontend.curve_secretkey = secret
        self.frontend.curve_publickey = public
        self.frontend.curve_server = True
        allowed = len(list(Path(cfg.curve_allow).glob("*.key")))
        log.info("CurveZMQ on: %d allowed client key(s) in %s", allowed, cfg.curve_allow)

    def close(self) -> None:
        """Close the sockets, stop the authenticator, end the context, remove the ipc folder."""
        self.frontend.close()
        self.backend.close()
        if self.auth is not None:
            self.auth.stop()
        self.ctx.term()
        shutil.rmtree(self.tmp, ignore_errors=True)

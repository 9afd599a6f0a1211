"""Trainer-side metrics of a ``V2VPushDataset``: how long the training loop waited for data.

``V2VPushDataset.metrics()`` returns :meth:`TrainerMetrics.snapshot`; to scrape them from the
trainer process with Prometheus, ``serve_trainer_metrics(ds, port)`` (needs prometheus-client).
"""
from __future__ import annotations

import threading
import time
from typing import Dict, Iterator, Optional


class TrainerMetrics:
    """Counters a dataset updates as its iterator hands batches to the training loop.

    ``wait_s`` is the wall time, in seconds, the loop spent inside ``next()`` (blocked waiting
    for a batch, plus the little bookkeeping done there); a loop whose ``wait_s`` grows about
    as fast as wall time is starved of data, one whose ``wait_s`` stays flat is GPU-bound.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.wait_s = 0.0
        self.batches = 0
        self.samples = 0
        self.bytes = 0
        self.per_endpoint: Dict[str, Dict[str, float]] = {}
        self.started: Optional[float] = None

    def wrap(self, it: Iterator[dict], default_endpoint: str) -> Iterator[dict]:
        """Yield from ``it``, timing each ``next()`` and counting what it returns; closing
        the wrapper closes ``it``."""
        try:
            while True:
                t0 = time.perf_counter()
                if self.started is None:
                    self.started = t0
                try:
                    b = next(it)
                except StopIteration:
                    return
                finally:
                    dt = time.perf_counter() - t0
                    with self._lock:
                        self.wait_s += dt
                self._count(b, str(b.get("endpoint", default_endpoint)))
                yield b
        finally:
            close = getattr(it, "close", None)
            if close is not None:
                close()

    def _count(self, b: dict, endpoint: str) -> None:
        n = len(b.get("sample_ids", ()))
        nbytes = sum(v.numel() * v.element_size() for v in b.values() if hasattr(v, "element_size"))
        with self._lock:
            self.batches += 1
            self.samples += n
            self.bytes += nbytes
            e = self.per_endpoint.setdefault(endpoint, {"batches": 0, "samples": 0, "bytes": 0})
            e["batches"] += 1
            e["samples"] += n
            e["bytes"] += nbytes

    def snapshot(self) -> dict:
        """``{"batches_received", "samples_received", "bytes_received", "wait_seconds",
        "seconds" (since the first next()), "wait_fraction", "per_endpoint": {endpoint:
        {"batches", "samples", "bytes"}}}`` -- plain numbers, safe to log as JSON."""
        with self._lock:
            secs = (time.perf_counter() - self.started) if self.started is not None else 0.0
            return {"batches_received": self.batches, "samples_received": self.samples,
                    "bytes_received": self.bytes, "wait_seconds": self.wait_s, "seconds": secs,
                    "wait_fraction": (self.wait_s / secs) if secs > 0 else 0.0,
                    "per_endpoint": {k: dict(v) for k, v in self.per_endpoint.items()}}


class _DatasetCollector:
    """A prometheus-client collector reading ``ds.metrics()`` at scrape time."""

    def __init__(self, ds) -> None:
        self.ds = ds

    def collect(self):
        from prometheus_client.core import CounterMetricFamily

        m = self.ds.metrics()
        wait = CounterMetricFamily("v2v_trainer_wait_seconds", "Seconds the training loop waited for a batch")
        wait.add_metric([], m["wait_seconds"])
        yield wait
        for name, key, doc in (("v2v_trainer_batches_received", "batches", "Batches handed to the training loop"),
                               ("v2v_trainer_samples_received", "samples", "Samples handed to the training loop"),
                               ("v2v_trainer_bytes_received", "bytes", "Tensor bytes handed to the training loop")):
            fam = CounterMetricFamily(name, doc, labels=["endpoint"])
            for ep, v in sorted(m["per_endpoint"].items()):
                fam.add_metric([ep], v[key])
            yield fam


def serve_trainer_metrics(ds, port: int, addr: str = "127.0.0.1", registry=None):
    """Expose ``ds.metrics()`` as Prometheus metrics (``v2v_trainer_*``) on ``addr:port``
    ``/metrics`` from a background thread; returns ``(server, thread)`` (see
    ``prometheus_client.start_http_server``). Needs prometheus-client."""
    from prometheus_client import REGISTRY, start_http_server

    registry = REGISTRY if registry is None else registry
    registry.register(_DatasetCollector(ds))
    return start_http_server(port, addr=addr, registry=registry)

"""What a running server is doing, for Prometheus, probes and a terminal.

``ServerMetrics`` is the one object ``service.plan_server`` tells about events (rows sent, a
worker restarted, ...) and, once per loop turn, about its state (fetches waiting, workers,
samples made ahead). It turns them into Prometheus metrics (``v2v_`` prefix, counters end in
``_total``, units in the name) on its own registry, serves them with ``/healthz`` and
``/readyz`` over HTTP (``--metrics-port``), and draws a live progress line when stderr is a
terminal. It never touches the server's own objects: everything arrives as plain numbers.

Metrics (``curl HOST:PORT/metrics`` lists them with their help text):

* counters: ``v2v_samples_made_total``, ``v2v_samples_sent_total``, ``v2v_batches_sent_total``,
  ``v2v_sent_bytes_total``, ``v2v_samples_asked_total`` (the samples fleet readers' makes named,
  made already or not, a make asked again not counted again: its rate over
  ``v2v_capacity_samples_per_second`` is the share of the host's capacity a job asks of it, what
  deploy/k8s-autoscale sizes a fleet by),
  ``v2v_workers_restarted_total``, ``v2v_files_skipped_total``, ``v2v_bad_messages_total``,
  ``v2v_worker_busy_seconds_total{stage}`` for stage in decode, simulate, flow, serialize,
  send (summed over workers; divided by wall time and workers it is each stage's busy
  fraction: ``rate(v2v_worker_busy_seconds_total[1m]) / v2v_workers``);
* gauges: ``v2v_pending_fetches`` (fetches waiting for their rows), ``v2v_workers`` (alive),
  ``v2v_capacity_samples_per_second`` (the decode capacity the host last said to a reader,
  :meth:`ServerMetrics.capacity`; absent before it is measured),
  ``v2v_workers_busy``, ``v2v_epoch_videos``, ``v2v_epoch_samples``,
  ``v2v_shuffle_buffer_samples`` and ``v2v_shuffle_buffer_capacity_samples`` (samples made and
  waiting for their fetch, and how many may wait), ``v2v_ready``;
* the frame cache (docs/frame_cache.md): counters ``v2v_frame_cache_hits_total``,
  ``v2v_frame_cache_misses_total{cause}``, ``v2v_frame_cache_stored_total``,
  ``v2v_frame_cache_written_bytes_total``, ``v2v_frame_cache_not_stored_total{cause}``; gauges
  ``v2v_frame_cache_bytes``, ``v2v_frame_cache_entries``, ``v2v_frame_cache_budget_bytes``;
* histograms of the samples made (``SampleHistograms``, from each sample's params, see
  ``samples/stats.py``): ``v2v_sample_events_per_pixel_second{polarity}``,
  ``v2v_sample_active_pixel_fraction``, ``v2v_sample_flow_px_per_frame``,
  ``v2v_sample_contrast_threshold{polarity}``, ``v2v_sample_noise_std``;
* ``v2v_fs_errors_total{where}``: filesystem errors of the work the server does on its own
  schedule (``FS_WHERE``), each logged once per cause; serving goes on (docs/faults.md).
"""
from __future__ import annotations

import errno
import logging
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, HTTPServer
from typing import Dict, Optional, Tuple, Union

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.exposition import CONTENT_TYPE_LATEST, generate_latest

from v2v_server.frames.frame_cache import MISS_CAUSES, SKIP_CAUSES
from v2v_wire.fleet import RateMeter
from v2v_wire.worker_messages import Done, Sample

#: Work a worker reports time for, in pipeline order.
STAGES = ("decode", "simulate", "flow", "serialize", "send")
#: Seconds without a loop turn after which /healthz reports the server wedged.
STALL_S = 60.0
#: Most seconds a rendered /metrics page is served again (Prometheus scrapes every 15 s or so).
EXPOSITION_S = 1.0

log = logging.getLogger("v2v.metrics")

#: The server's own filesystem work that may fail without stopping it, and what serving does
#: meanwhile (``ServerMetrics.on_fs_error``; docs/faults.md).
FS_WHERE = {
    "frame_cache": "the frame-cache gauges keep their last values; workers serve by decoding while the folder "
                   "is unusable",
    "progress": "the progress line is off",
}


class ServerMetrics:
    """Counters and gauges of one server, an HTTP endpoint for them, and a progress line.

    Args:
        progress: draw a live progress line on stderr (default: when stderr is a terminal).
    """

    def __init__(self, progress: Optional[bool] = None):
        self.registry = CollectorRegistry(auto_describe=True)
        r = self.registry

        def counter(name, doc, labels=()):
            return Counter(name, doc, labelnames=labels, registry=r)

        self.samples_made = counter("v2v_samples_made", "Samples received from workers")
        self.samples_sent = counter("v2v_samples_sent", "Samples sent to clients (re-sends included)")
        self.samples_asked = counter("v2v_samples_asked", "Samples fleet readers' makes named, made already or not, "
                                     "a make asked again not counted again (rate over "
                                     "v2v_capacity_samples_per_second: the share of the host's capacity a job "
                                     "asks of it)")
        self.batches_sent = counter("v2v_batches_sent", "Batches sent to clients (re-sends included)")
        self.bytes_sent = counter("v2v_sent_bytes", "Array bytes sent to clients")
        self.workers_restarted = counter("v2v_workers_restarted", "Worker processes that died and were replaced")
        self.files_skipped = counter("v2v_files_skipped", "Video files skipped as unusable")
        self.bad_messages = counter("v2v_bad_messages", "Client messages rejected as malformed")
        self.tasks_timed_out = counter("v2v_tasks_timed_out", "Tasks reassigned after their worker sent nothing")
        self.busy = counter("v2v_worker_busy_seconds", "Seconds workers spent per pipeline stage", ("stage",))
        self.store_bytes = counter("v2v_store_read_bytes", "Bytes workers fetched from the object store")
        self.store_reads = counter("v2v_store_reads", "Range requests workers made to the object store")
        self.store_seconds = counter("v2v_store_read_seconds", "Seconds workers waited for the object store "
                                     "(opens and range requests; / v2v_store_reads_total = mean read latency)")
        self.store_retries = counter("v2v_store_retries", "Store requests retried by the storage library")
        self.store_skipped = counter("v2v_store_objects_skipped", "Objects missing or changed since they were listed")
        self.shot_cuts = counter("v2v_shot_cuts", "Shot cuts met by sample passes (found while decoding, or stored "
                                 "with a frame-cache entry); every pass over a video counts its cuts")
        self.windows_cut = counter("v2v_windows_cut", "Windows a shot cut removed (shot_cuts: avoid): a window in "
                                   "progress that a cut fell inside")
        self.frame_cache = FrameCacheCounters(counter)
        self.sample_stats = SampleHistograms(r)
        self.fs_errors = counter("v2v_fs_errors", "Filesystem errors of the server's own periodic work, by where: "
                                 + "; ".join(f"{k} ({v})" for k, v in FS_WHERE.items()), ("where",))
        for w in FS_WHERE:
            self.fs_errors.labels(where=w)
        self._fs_seen: set = set()  # (where, cause) already logged
        for s in STAGES:
            self.busy.labels(stage=s)
        self._state: dict = {}
        self._lock = threading.Lock()
        self._last_turn = time.monotonic()
        self._ready = False
        r.register(_StateCollector(self))
        self.http: Optional[HTTPServer] = None
        self._expo_lock = threading.Lock()
        self._expo: Optional[bytes] = None
        self._expo_at = 0.0
        self.port: Optional[int] = None
        self._capacity, self._counted = RateMeter(), (0, 0.0)  # samples made and busy seconds it has taken
        self.said: Optional[float] = None  # the capacity last said to a reader (samples/s)
        self._progress: Optional[_Progress] = None
        if sys.stderr.isatty() if progress is None else progress:
            try:  # tqdm draws the line when it is made: a terminal already gone leaves it off
                self._progress = _Progress()
            except OSError as e:
                self.on_fs_error("progress", "stderr", e)

    # ------------------------------------------------------------------ events (plan_server.py calls these)
    def on_sample_made(self, params: Optional[dict] = None) -> None:
        """A sample kept from a worker; its ``params`` (the worker's map) feed the histograms."""
        self.samples_made.inc()
        if params is not None:
            self.sample_stats.observe(params)

    def on_make(self, samples: int) -> None:
        """A reader's make named ``samples`` samples it had not asked of this host already (a
        make of a video's windows only, or one placed elsewhere: 0; a retry counts only what its
        make before did not name)."""
        self.samples_asked.inc(samples)

    def on_batch_sent(self, nsamples: int, nbytes: int) -> None:
        self.batches_sent.inc()
        self.samples_sent.inc(nsamples)
        self.bytes_sent.inc(nbytes)
        if self._progress is not None:
            self._draw(lambda p: p.add(nsamples, nbytes))

    def _draw(self, fn) -> None:
        """``fn(progress line)``; a terminal gone (EIO after a hang-up) turns the line off."""
        try:
            fn(self._progress)
        except OSError as e:
            self._progress = None
            self.on_fs_error("progress", "stderr", e)

    def on_worker_restarted(self) -> None:
        self.workers_restarted.inc()

    def on_file_skipped(self) -> None:
        self.files_skipped.inc()

    def on_bad_message(self) -> None:
        self.bad_messages.inc()

    def on_task_timed_out(self) -> None:
        self.tasks_timed_out.inc()

    def on_fs_error(self, where: str, path, e: OSError) -> None:
        """The server's own filesystem work at ``where`` (a key of ``FS_WHERE``) failed on
        ``path``: counted every time, logged once per ``where`` and cause (the errno's name)
        for the life of the server, however often a periodic task meets it."""
        self.fs_errors.labels(where=where).inc()
        cause = errno.errorcode.get(getattr(e, "errno", None) or 0, type(e).__name__)
        if (where, cause) not in self._fs_seen:
            self._fs_seen.add((where, cause))
            log.error("%s: %s (%s): %s; counted in v2v_fs_errors_total{where=\"%s\"}, logged once",
                      path, getattr(e, "strerror", None) or e, cause, FS_WHERE[where], where)

    def fs_errors_total(self, where: str) -> int:
        """``v2v_fs_errors_total{where}`` so far."""
        return int(self.registry.get_sample_value("v2v_fs_errors_total", {"where": where}) or 0)

    def totals(self) -> Dict[str, int]:
        """The counters' current values by short name (``batches_sent``, ``samples_made``, ...):
        what the server's closing log line reports, read from the one place they are kept."""
        names = ("samples_made", "samples_sent", "batches_sent",
                 "workers_restarted", "files_skipped", "bad_messages", "tasks_timed_out")
        return {n: int(self.registry.get_sample_value(f"v2v_{n}_total") or 0) for n in names}

    def capacity(self, workers: int, now: float) -> Optional[float]:
        """The host's decode capacity at ``now`` (seconds, monotonic), in samples/s: the samples
        made over the ``workers`` workers' busy seconds per worker, both since the last call
        (``v2v_wire.fleet.RateMeter``); None before it is measured. What a fleet's readers weigh
        the host by (``Rows.rate``)."""
        made, busy = self.totals()["samples_made"], sum(self.busy_seconds().values())
        self._capacity.add(made - self._counted[0], (busy - self._counted[1]) / max(1, workers), now)
        self._counted = (made, busy)
        self.said = self._capacity.rate()
        return self.said

    def busy_seconds(self) -> Dict[str, float]:
        """Seconds the workers spent in each stage of ``STAGES`` so far, summed over workers."""
        return {s: float(self.registry.get_sample_value("v2v_worker_busy_seconds_total", {"stage": s}) or 0.0)
                for s in STAGES}

    def on_worker_message(self, msg: Union[Sample, Done]) -> None:
        """Add what a worker message checked at the edge (``worker_messages.worker_message``)
        carries: its stage seconds (``stages``: stage -> seconds since the worker's previous
        message), and a ``Done``'s shot ``cuts``, the windows they removed (``dropped``) and its
        object-store reads (``store``: ``bytes``, ``reads``, ``read_s``, ``retries``,
        ``skipped`` and the frame cache's counters, ``sources.source.VideoSource.take_stats``,
        whose values a counter ignores when malformed)."""
        if isinstance(msg, Done):
            for v, c in ((msg.cuts, self.shot_cuts), (msg.dropped, self.windows_cut)):
                if _count(v):
                    c.inc(v)
            store = msg.store
            for key, c in (("bytes", self.store_bytes), ("reads", self.store_reads), ("read_s", self.store_seconds),
                           ("retries", self.store_retries), ("skipped", self.store_skipped)):
                v = store.get(key)
                if _count(v):
                    c.inc(v)
            fc = store.get("frame_cache")
            if isinstance(fc, dict):
                self.frame_cache.add(fc)
        for s, v in msg.stages.items():
            if s in STAGES and 0 <= v < 1e6:
                self.busy.labels(stage=s).inc(v)

    def frame_cache_state(self, nbytes: int, entries: int, budget: int) -> dict:
        """The frame cache's part of ``set_state`` (``FrameCacheCounters.state``)."""
        return self.frame_cache.state(nbytes, entries, budget)

    def frame_cache_line(self, nbytes: int, entries: int, budget: int) -> str:
        """The frame cache's status line (``FrameCacheCounters.line``)."""
        return self.frame_cache.line(nbytes, entries, budget)

    def tick(self, state_fn, every_s: float = 0.25) -> None:
        """Call ``set_state(**state_fn())`` unless that was done less than ``every_s`` seconds
        ago (the server loop turns far more often than anyone scrapes)."""
        if time.monotonic() - self._last_turn >= every_s or not self._state:
            self.set_state(**state_fn())

    def set_state(self, **state) -> None:
        """The server's state after a loop turn: ``pending_fetches``, ``workers``, ``workers_busy``,
        ``epoch_videos``, ``epoch_samples`` (the samples every epoch lists, once the plan knows
        every video's: from the corpus index at start, else from the decodes; None before),
        ``shuffle_samples`` and ``shuffle_capacity`` (samples made ahead and how many may wait),
        and ``ready`` (socket bound, corpus scanned, a worker up). Also the liveness tick for
        ``/healthz``."""
        now = time.monotonic()
        with self._lock:
            self._state = state
            self._last_turn = now
            self._ready = bool(state.get("ready"))
        if self._progress is not None:
            self._draw(lambda p: p.show(now, state))

    # ------------------------------------------------------------------ probes
    def healthy(self) -> bool:
        """The server loop turned within ``STALL_S`` seconds."""
        with self._lock:
            return time.monotonic() - self._last_turn < STALL_S

    def ready(self) -> bool:
        with self._lock:
            return self._ready

    def snapshot(self) -> dict:
        with self._lock:
            return dict(self._state)

    def exposition(self, now: Optional[float] = None) -> bytes:
        """The Prometheus text of every metric, rendered at most once per ``EXPOSITION_S``
        seconds and served from that cache in between: a scrape storm costs the server's
        process (and so its main loop, under the GIL) one rendering per second, not one per
        scrape."""
        now = time.monotonic() if now is None else now
        with self._expo_lock:
            if self._expo is None or now - self._expo_at >= EXPOSITION_S:
                self._expo, self._expo_at = generate_latest(self.registry), now
            return self._expo

    def serve(self, host: str, port: int) -> int:
        """Serve ``/metrics`` (Prometheus text), ``/healthz`` and ``/readyz`` (200 or 503)
        from a daemon thread on ``host:port``; returns the port bound (``port`` 0 = any).

        Raises:
            OSError: when the address cannot be bound.
        """
        metrics = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self):  # noqa: N802 (http.server's naming)
                path = self.path.split("?", 1)[0]
                if path == "/metrics":
                    body, ctype, code = metrics.exposition(), CONTENT_TYPE_LATEST, 200
                elif path in ("/healthz", "/readyz"):
                    ok = metrics.healthy() if path == "/healthz" else (metrics.ready() and metrics.healthy())
                    body, ctype, code = (b"ok\n" if ok else b"not ready\n"), "text/plain", 200 if ok else 503
                else:
                    body, ctype, code = b"try /metrics, /healthz or /readyz\n", "text/plain", 404
                self.send_response(code)
                self.send_header("Content-Type", ctype)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args):  # scrapes every few seconds: keep them out of the log
                pass

        try:  # one thread answers every request in turn (no thread per scrape); a slow peer times out
            Handler.timeout = 5.0
            self.http = HTTPServer((host, port), Handler)
        except OSError as e:
            raise OSError(e.errno, f"metrics endpoint {host}:{port}: {e.strerror or e}") from None
        self.port = self.http.server_address[1]
        threading.Thread(target=self.http.serve_forever, name="v2v-metrics", daemon=True).start()
        log.info("metrics on http://%s:%d/metrics (also /healthz, /readyz)", host, self.port)
        return self.port

    def close(self) -> None:
        if self.http is not None:
            self.http.shutdown()
            self.http.server_close()
            self.http = None
        if self._progress is not None:
            self._draw(lambda p: p.close())


class FrameCacheCounters:
    """The frame cache's counters on a server's registry (``counter``: ``ServerMetrics``'s
    counter factory), fed by the workers' reports, and the hit and miss totals the gauges and
    the status line read."""

    def __init__(self, counter):
        self.fc_hits = counter("v2v_frame_cache_hits", "Videos cut from the frame cache instead of decoded")
        self.fc_misses = counter("v2v_frame_cache_misses", "Videos decoded with the frame cache on, by cause: absent "
                                 "(not stored yet), changed (the source's identity changed), corrupt (a damaged "
                                 "entry, removed), unverified (the source changed too recently, or has no version "
                                 "tag, for its identity to vouch for its bytes: not stored)", ("cause",))
        self.fc_stored = counter("v2v_frame_cache_stored", "Entries added to the frame cache")
        self.fc_written = counter("v2v_frame_cache_written_bytes", "Bytes of entries added to the frame cache")
        self.fc_not_stored = counter("v2v_frame_cache_not_stored", "Decoded videos not stored, by cause: budget, "
                                     "disk_full, write_error, incomplete", ("cause",))
        # the hit and miss totals again as plain numbers: the gauges and status line read them on
        # every loop turn, where reading the counters back would walk the whole registry
        self._fc_hits = 0
        self._fc_misses: Dict[str, float] = dict.fromkeys(MISS_CAUSES, 0)
        for c in MISS_CAUSES:
            self.fc_misses.labels(cause=c)
        for c in SKIP_CAUSES:
            self.fc_not_stored.labels(cause=c)

    def add(self, fc: dict) -> None:
        """Add a worker's frame-cache counters (``FrameCache.take_stats``)."""
        for key, c in (("hits", self.fc_hits), ("stored", self.fc_stored), ("bytes_written", self.fc_written)):
            if _count(fc.get(key)):
                c.inc(fc[key])
                if key == "hits":
                    self._fc_hits += fc[key]
        for key, causes, c in (("misses", MISS_CAUSES, self.fc_misses), ("not_stored", SKIP_CAUSES, self.fc_not_stored)):
            d = fc.get(key)
            if isinstance(d, dict):
                for cause in causes:
                    if _count(d.get(cause)):
                        c.labels(cause=cause).inc(d[cause])
                        if key == "misses":
                            self._fc_misses[cause] += d[cause]

    def looked(self) -> Tuple[int, Dict[str, int], float]:
        """Hits so far, misses by cause, and the hit ratio (0 before any lookup)."""
        hits = int(self._fc_hits)
        misses = {c: int(n) for c, n in self._fc_misses.items()}
        looked = hits + sum(misses.values())
        return hits, misses, hits / looked if looked else 0.0

    def state(self, nbytes: int, entries: int, budget: int) -> dict:
        """The frame cache's part of ``set_state``: its ``bytes``, ``entries`` and ``budget``
        (from a scan of its folder) and the hit ratio of the counters so far."""
        return {"frame_cache_bytes": nbytes, "frame_cache_entries": entries, "frame_cache_budget": budget,
                "frame_cache_hit_ratio": self.looked()[2]}

    def line(self, nbytes: int, entries: int, budget: int) -> str:
        """The frame cache's status line: hits and misses so far, the hit ratio, and the folder's
        ``entries`` and ``nbytes`` against the ``budget``."""
        hits, misses, ratio = self.looked()
        return (f"{hits} hit(s), misses {', '.join(f'{c} {n}' for c, n in misses.items())} ({ratio:.0%} hits), "
                f"{entries} entries, {nbytes / (1 << 30):.2f} of {budget / (1 << 30):.2f} GiB")

class SampleHistograms:
    """Histograms of the samples made, on ``registry``: their event rates, active pixels and flow
    (``params["stats"]``, ``samples.stats.event_stats``) and their drawn thresholds and noise.
    Buckets span the default recipe's draws and real sensors' rates (docs/fidelity.md)."""

    #: events / pixel / s: a still scene's noise (0.01) to a fast pan at a low threshold (1000)
    RATE_BUCKETS = (0.01, 0.03, 0.1, 0.3, 1, 3, 10, 30, 100, 300, 1000)
    FRACTION_BUCKETS = (0.01, 0.05, 0.1, 0.25, 0.5, 0.75, 0.9, 0.99, 1.0)
    FLOW_BUCKETS = (0.1, 0.25, 0.5, 1, 2, 4, 8, 16, 32)
    THRESHOLD_BUCKETS = (0.05, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0)
    NOISE_BUCKETS = (0.0, 0.01, 0.02, 0.05, 0.1, 0.2)
    #: log-intensity change per frame pair: a frozen window (under STATIC_MOTION, 0.005) to a fast pan
    MOTION_BUCKETS = (0.001, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5)

    def __init__(self, registry):
        def hist(name, doc, buckets, labels=()):
            return Histogram(name, doc, labelnames=labels, buckets=buckets, registry=registry)

        self.rate = hist("v2v_sample_events_per_pixel_second", "Signal events per pixel per second of each sample "
                         "made, by polarity (voxel sums over the sample's duration)", self.RATE_BUCKETS, ("polarity",))
        self.active = hist("v2v_sample_active_pixel_fraction", "Fraction of a sample's pixels with at least one event",
                           self.FRACTION_BUCKETS)
        self.flow = hist("v2v_sample_flow_px_per_frame", "Mean optical-flow magnitude of a sample, pixels per frame",
                         self.FLOW_BUCKETS)
        self.threshold = hist("v2v_sample_contrast_threshold", "Contrast threshold drawn for a sample (log "
                              "intensity), by polarity", self.THRESHOLD_BUCKETS, ("polarity",))
        self.noise = hist("v2v_sample_noise_std", "Background-noise sigma drawn for a sample (log intensity per "
                          "frame pair)", self.NOISE_BUCKETS)
        self.motion = hist("v2v_sample_window_motion", "Mean change of log intensity per frame pair of a sample's "
                           "window, before simulation (under 0.005: static, frames.motion)", self.MOTION_BUCKETS)

    def observe(self, params: dict) -> None:
        """Add one sample's ``params``; a missing or malformed value is left out (the map is the
        worker's, passed on to clients as it is)."""
        if not isinstance(params, dict):
            return
        st = params.get("stats") if isinstance(params.get("stats"), dict) else {}
        for value, h in ((st.get("rate_pos"), self.rate.labels(polarity="pos")),
                         (st.get("rate_neg"), self.rate.labels(polarity="neg")),
                         (st.get("active_fraction"), self.active), (st.get("flow_mag"), self.flow),
                         (params.get("pos_threshold"), self.threshold.labels(polarity="pos")),
                         (params.get("neg_threshold"), self.threshold.labels(polarity="neg")),
                         (params.get("noise_std"), self.noise), (st.get("motion"), self.motion)):
            if _count(value):
                h.observe(value)


def _count(v) -> bool:
    """Whether ``v`` is a plausible counter increment from a worker (a number, not a bool, in range)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and 0 <= v < 1e15


class _StateCollector:
    """Gauges built at scrape time from the latest ``set_state`` (clients come and go, so
    their series vanish with them)."""

    def __init__(self, m: ServerMetrics):
        self.m = m

    def describe(self):
        return []

    def collect(self):
        st = self.m.snapshot()
        for name, key, doc in (
            ("v2v_pending_fetches", "pending_fetches", "Fetches waiting for their rows"),
            ("v2v_workers", "workers", "Worker processes alive"),
            ("v2v_workers_busy", "workers_busy", "Workers making samples of a video"),
            ("v2v_epoch_videos", "epoch_videos", "Videos of an epoch"),
            ("v2v_epoch_samples", "epoch_samples", "Samples every epoch lists, once the plan knows every video's "
             "(from the corpus index at start, else from the decodes); 0 before"),
            ("v2v_shuffle_buffer_samples", "shuffle_samples", "Samples made and waiting for their fetch"),
            ("v2v_shuffle_buffer_capacity_samples", "shuffle_capacity", "Samples the store keeps before it drops "
             "unfetched ones: those made ahead (shuffle_buffer) and those fetched (batch_size), beside the largest "
             "video's"),
            ("v2v_frame_cache_bytes", "frame_cache_bytes", "Bytes of complete entries in this host's frame cache"),
            ("v2v_frame_cache_entries", "frame_cache_entries", "Entries (videos) in this host's frame cache"),
            ("v2v_frame_cache_budget_bytes", "frame_cache_budget", "The frame cache's budget (frame_cache_gb), bytes"),
        ):
            g = GaugeMetricFamily(name, doc)
            g.add_metric([], float(st.get(key) or 0))
            yield g
        said = self.m.said
        if said is not None:  # absent before measured: an autoscaler counts the host as missing, not idle
            g = GaugeMetricFamily("v2v_capacity_samples_per_second", "The decode capacity this host last said to a "
                                  "reader: samples made per second of its workers' busy time, times its workers")
            g.add_metric([], float(said))
            yield g
        g = GaugeMetricFamily("v2v_ready", "1 when the socket is bound, the corpus scanned and a worker is up")
        g.add_metric([], 1.0 if self.m.ready() else 0.0)
        yield g


class _Progress:
    """One live line on a terminal (tqdm): samples/s, MB/s, fetches waiting, workers busy."""

    def __init__(self):
        from tqdm import tqdm

        self.bar = tqdm(unit=" samples", dynamic_ncols=True, file=sys.stderr, leave=False,
                        bar_format="{n_fmt}{unit} [{elapsed}, {rate_fmt}]{postfix}")
        self.nbytes = 0
        self._last = time.monotonic()
        self._last_bytes = 0
        self.line = ""

    def add(self, nsamples: int, nbytes: int) -> None:
        self.bar.update(nsamples)
        self.nbytes += nbytes

    def show(self, now: float, st: dict) -> None:
        if now - self._last < 1.0:
            return
        mbs = (self.nbytes - self._last_bytes) / 1e6 / (now - self._last)  # over the last second or so
        self._last, self._last_bytes = now, self.nbytes
        per_epoch = f"{st['epoch_samples']} samples/epoch, " if st.get("epoch_samples") else ""
        self.line = (f"{per_epoch}{st.get('epoch_videos', 0)} videos, {mbs:.1f} MB/s, "
                     f"{st.get('pending_fetches', 0)} fetch(es) waiting, workers busy "
                     f"{st.get('workers_busy', 0)}/{st.get('workers', 0)}, shuffle buffer "
                     f"{st.get('shuffle_samples', 0)}/{st.get('shuffle_capacity', 0)}")
        if st.get("frame_cache_budget"):
            self.line += (f", frame cache {st.get('frame_cache_hit_ratio', 0.0):.0%} hits, "
                          f"{st.get('frame_cache_bytes', 0) / (1 << 30):.1f}/{st['frame_cache_budget'] / (1 << 30):.1f} GiB")
        self.bar.set_postfix_str(self.line)

    def close(self) -> None:
        self.bar.close()

"""Server configuration: defaults follow the paper's WebVid recipe (Lou et al. 2025, Sec. 4).

A ``ServeConfig`` is built from defaults, then a YAML file (``--config``), then command-line
flags; every value is validated once, at startup, and a bad one raises ``ValueError`` naming
the field.
"""
from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Optional, Tuple

import yaml

from .flow_options import DEFAULT_FLOW, FLOW_OPTIONS, check_option, unavailable_reason
from .protocol import OUTPUTS
from .simulate import ParamRanges

#: Optical-flow options by name (the table lives in flow_options.py).
FLOW_PRESETS = tuple(FLOW_OPTIONS)
FLOW_DTYPES = ("float16", "float32")
#: Upper limits (a typo like ``workers: 2000`` is an error, not a fork bomb or an OOM).
MAX_WORKERS = 256
MAX_PREFETCH = 256
MAX_CREDITS = 1024
VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".gif")


@dataclass
class ServeConfig:
    """Everything ``v2v-serve`` needs to know.

    Sample layout (paper's WebVid recipe): ``sequence_length`` L voxel grids of ``num_bins``
    B bins, ``frames_per_bin`` frame pairs per bin, so a sample spans
    ``L * B * frames_per_bin + 1`` frame indices (201 by default). Spatial: the top
    ``keep_top_fraction`` of each frame is kept (WebVid watermark), a random
    ``crop_size`` x ``crop_size`` crop (pixels) is taken, flipped horizontally with
    probability ``hflip_prob``. Pauses: a per-frame Markov chain repeats the previous frame.
    """

    videos: Optional[str] = None
    workers: int = 2
    bind: str = "tcp://127.0.0.1:5555"
    seed: int = 0
    epochs: Optional[int] = None
    batch_size: int = 12
    sequence_length: int = 40
    num_bins: int = 5
    frames_per_bin: int = 1
    crop_size: int = 128
    keep_top_fraction: float = 0.54
    hflip_prob: float = 0.5
    max_samples_per_video: int = 10
    #: random crops per decoded window, each its own sample (own crop, flip, pauses, sensor
    #: parameters); ids ``path#window.crop`` when > 1. Crops of one window share content and motion.
    crops_per_window: int = 1
    pause_enabled: bool = True
    p_pause_when_running: float = 0.0102
    p_pause_when_paused: float = 0.9791
    outputs: Tuple[str, ...] = OUTPUTS
    flow_preset: str = DEFAULT_FLOW
    flow_dtype: str = "float16"
    ranges: ParamRanges = field(default_factory=ParamRanges)
    decode_threads: int = 1
    video_extensions: Tuple[str, ...] = VIDEO_EXTENSIONS
    #: seconds between heartbeats to clients
    heartbeat_s: float = 1.0
    #: seconds an unacknowledged batch may stay with a client before it is sent again
    lease_s: float = 60.0
    #: seconds of silence after which a client is considered gone
    client_timeout_s: float = 10.0
    #: batches the server keeps assembled ahead of the clients' credits
    prefetch_batches: int = 2
    #: seconds a revoked batch may stay unanswered before its client is dropped (None: client_timeout_s)
    revoke_s: Optional[float] = None
    #: most batches one client may hold (its ``credits`` at hello); a larger request is refused
    max_credits: int = 64
    #: seconds a worker may send nothing on a task before the task is reassigned and the worker replaced
    task_timeout_s: float = 300.0
    #: refinement of frame pairs whose motion needs it: off | uniform:K | adaptive:λ_px | adaptive-dl:λ
    #: (see v2v_server/refine.py and docs/fidelity.md); recorded in each sample's params
    refine: str = "off"
    #: optional sensor non-idealities, all off by default (see v2v_server/nonideal.py)
    nonidealities: dict = field(default_factory=dict)
    #: dynamic-range degradation {probability, scale: [lo, hi]} (paper appendix "Dataset
    #: quality"; off when empty; see v2v_server/augment.py); recorded in each sample's params
    degrade_dynamic_range: dict = field(default_factory=dict)
    #: each video keeps one (c+, c-) drawn from (seed, video) for every epoch (the paper's
    #: "-F" datasets); recorded in each sample's params
    fixed_sensor_params: bool = False
    #: CurveZMQ: the server's secret key file (from ``v2v-keygen``)
    curve_secret_key: Optional[str] = None
    #: CurveZMQ: folder of allowed client public key files (``*.key``)
    curve_allow: Optional[str] = None
    #: allow a non-loopback bind without CurveZMQ (logs a warning)
    insecure: bool = False
    #: serve only shard I of N of the corpus ("I/N", 0 <= I < N; see corpus.shard_of); None = all
    shard: Optional[str] = None
    #: port of the HTTP endpoint with /metrics (Prometheus), /healthz and /readyz; None = off
    metrics_port: Optional[int] = None
    #: address the metrics endpoint binds (0.0.0.0 in a container so probes can reach it)
    metrics_host: str = "127.0.0.1"
    #: log lines as plain text or one JSON object per line (for log shippers)
    log_format: str = "text"

    # ------------------------------------------------------------------ derived
    @property
    def shard_spec(self) -> Tuple[int, int]:
        """``(index, count)`` of ``shard``; ``(0, 1)`` when the whole corpus is served."""
        return parse_shard(self.shard)

    @property
    def frames_per_sample(self) -> int:
        """Frame indices one sample spans: L * B * frames_per_bin + 1."""
        return self.sequence_length * self.num_bins * self.frames_per_bin + 1

    # ------------------------------------------------------------------ checks
    def validate(self) -> "ServeConfig":
        """Check every field; raise ``ValueError`` naming the first bad one. Returns self."""

        def pos_int(name, minimum=1):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
                raise ValueError(f"{name} must be an integer >= {minimum}, got {v!r}")

        def prob(name):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (0.0 <= v <= 1.0):
                raise ValueError(f"{name} must be a probability in [0, 1], got {v!r}")
            setattr(self, name, float(v))

        def pos_float(name):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
            setattr(self, name, float(v))

        for name in ("workers", "batch_size", "sequence_length", "num_bins", "frames_per_bin",
                     "crop_size", "max_samples_per_video", "decode_threads", "prefetch_batches",
                     "crops_per_window"):
            pos_int(name)
        if self.crop_size < 8:
            raise ValueError(f"crop_size must be >= 8 pixels, got {self.crop_size}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed must be an integer >= 0, got {self.seed!r}")
        if self.epochs is not None:
            pos_int("epochs")
        for name in ("hflip_prob", "p_pause_when_running", "p_pause_when_paused"):
            prob(name)
        if not isinstance(self.keep_top_fraction, (int, float)) or not (0 < self.keep_top_fraction <= 1):
            raise ValueError(f"keep_top_fraction must be in (0, 1], got {self.keep_top_fraction!r}")
        for name in ("heartbeat_s", "lease_s", "client_timeout_s", "task_timeout_s"):
            pos_float(name)
        if self.revoke_s is not None:
            pos_float("revoke_s")
        pos_int("max_credits")
        for name, hi, why in (("workers", MAX_WORKERS, "worker processes"),
                              ("prefetch_batches", MAX_PREFETCH, "batches assembled ahead"),
                              ("max_credits", MAX_CREDITS, "batches in flight per client")):
            if getattr(self, name) > hi:
                raise ValueError(f"{name} must be <= {hi} ({why}), got {getattr(self, name)}")
        if isinstance(self.outputs, str):
            self.outputs = tuple(s.strip() for s in self.outputs.split(",") if s.strip())
        outs = tuple(self.outputs)
        bad = [o for o in outs if o not in OUTPUTS]
        if bad or not outs:
            raise ValueError(f"outputs must be a non-empty subset of {list(OUTPUTS)}, got {list(outs)}")
        self.outputs = tuple(o for o in OUTPUTS if o in outs)
        self.flow_preset = check_option(self.flow_preset).name  # ValueError naming flow_preset
        why = unavailable_reason(self.flow_preset)
        if why:
            raise ValueError(f"flow_preset {self.flow_preset!r} cannot run here: {why}")
        if self.flow_dtype not in FLOW_DTYPES:
            raise ValueError(f"flow_dtype must be one of {list(FLOW_DTYPES)}, got {self.flow_dtype!r}")
        if not isinstance(self.ranges, ParamRanges):
            self.ranges = ParamRanges.from_dict(self.ranges)
        if not isinstance(self.bind, str) or "://" not in self.bind:
            raise ValueError(f"bind must be a ZeroMQ endpoint like tcp://127.0.0.1:5555, got {self.bind!r}")
        from .nonideal import NonIdealities
        from .refine import parse_refine

        spec = parse_refine(self.refine)
        self.refine = str(spec)
        try:
            ni = NonIdealities.from_dict(self.nonidealities or None)
        except ValueError as e:
            raise ValueError(f"nonidealities: {e}") from None
        self.nonidealities = ni.to_dict() if ni.enabled else {}
        if self.crop_size > 4096:
            raise ValueError(f"crop_size must be <= 4096 pixels, got {self.crop_size}")
        if (self.curve_secret_key is None) != (self.curve_allow is None):
            raise ValueError("curve_secret_key and curve_allow must be given together")
        if self.curve_secret_key is not None:
            if not Path(self.curve_secret_key).is_file():
                raise ValueError(f"curve_secret_key: no such file {self.curve_secret_key}")
            if not Path(self.curve_allow).is_dir():
                raise ValueError(f"curve_allow: no such folder {self.curve_allow}")
        from .augment import parse_degrade

        self.degrade_dynamic_range = parse_degrade(self.degrade_dynamic_range)
        if not isinstance(self.fixed_sensor_params, bool):
            raise ValueError(f"fixed_sensor_params must be true or false, got {self.fixed_sensor_params!r}")
        if not isinstance(self.insecure, bool):
            raise ValueError(f"insecure must be true or false, got {self.insecure!r}")
        if not is_loopback(self.bind) and self.curve_secret_key is None and not self.insecure:
            raise ValueError(f"bind {self.bind} is not a loopback address: give curve_secret_key and curve_allow "
                             f"(see v2v-keygen), or insecure: true to stream unauthenticated")
        if self.shard is not None:
            self.shard = "%d/%d" % parse_shard(self.shard)
        if self.metrics_port is not None and (isinstance(self.metrics_port, bool) or not isinstance(
                self.metrics_port, int) or not 0 <= self.metrics_port <= 65535):
            raise ValueError(f"metrics_port must be a TCP port in [0, 65535] (0 = any free port), "
                             f"got {self.metrics_port!r}")
        if self.log_format not in ("text", "json"):
            raise ValueError(f"log_format must be text or json, got {self.log_format!r}")
        if not isinstance(self.metrics_host, str) or not self.metrics_host:
            raise ValueError(f"metrics_host must be an address such as 127.0.0.1, got {self.metrics_host!r}")
        self.video_extensions = tuple(e.lower() for e in self.video_extensions)
        if self.videos is not None:
            self.videos = str(self.videos)
        return self

    # ------------------------------------------------------------------ io
    def to_dict(self) -> dict:
        """Plain, msgpack/YAML-safe dict (ranges as lists)."""
        d = asdict(self)
        d["ranges"] = self.ranges.to_dict()
        d["outputs"] = list(self.outputs)
        d["video_extensions"] = list(self.video_extensions)
        return d

    @classmethod
    def from_dict(cls, d: dict, source: str = "config") -> "ServeConfig":
        """Build and validate from a mapping; unknown keys raise ``ValueError`` naming them
        and ``source`` (the YAML file)."""
        if d is None:
            d = {}
        if not isinstance(d, dict):
            raise ValueError(f"{source}: top level must be a mapping of keys to values")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"{source}: unknown key(s) {unknown}; known keys: {sorted(known)}")
        kw = dict(d)
        for k in ("outputs", "video_extensions"):
            if k in kw and isinstance(kw[k], list):
                kw[k] = tuple(kw[k])
        cfg = cls(**kw)
        try:
            return cfg.validate()
        except ValueError as e:
            raise ValueError(f"{source}: {e}") from None


def parse_shard(spec) -> Tuple[int, int]:
    """``"I/N"`` -> ``(I, N)`` with ``0 <= I < N``; ``None`` -> ``(0, 1)``.

    Raises:
        ValueError: naming the field, for anything else (``"2/2"``, ``"a/b"``, ``"1"``).
    """
    if spec is None:
        return 0, 1
    m = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", str(spec))
    if not m or int(m.group(2)) < 1 or int(m.group(1)) >= int(m.group(2)):
        raise ValueError(f"shard must be \"I/N\" with 0 <= I < N (e.g. 0/2 and 1/2 for two hosts), got {spec!r}")
    return int(m.group(1)), int(m.group(2))


def is_loopback(endpoint: str) -> bool:
    """True for ipc://, inproc:// and tcp:// endpoints on 127.0.0.0/8, localhost or ::1."""
    scheme, _, rest = endpoint.partition("://")
    if scheme in ("ipc", "inproc"):
        return True
    host = rest.rsplit(":", 1)[0].strip("[]")
    if ";" in host:  # tcp://source;dest form: judge the address bound
        host = host.split(";", 1)[0]
    return host in ("localhost", "::1") or host.startswith("127.")


class _Loader(yaml.SafeLoader):
    """SafeLoader that also reads YAML 1.2 floats such as ``1.0e9`` or ``1e-3`` as numbers
    (YAML 1.1, PyYAML's default, reads them as strings)."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                |[-+]?\.(?:inf|Inf|INF)
                |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."))


def load_config(path: Optional[str], overrides: Optional[dict] = None) -> ServeConfig:
    """Defaults, then the YAML file at ``path`` (if any), then ``overrides`` (non-None values).

    Raises:
        ValueError: naming the file and the field for unknown keys or bad values, or when the
            file is not valid YAML.
        FileNotFoundError: when ``path`` does not exist.
    """
    data: dict = {}
    source = "command line"
    if path is not None:
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"config file not found: {p}")
        try:
            data = yaml.load(p.read_text(), Loader=_Loader) or {}
        except yaml.YAMLError as e:
            raise ValueError(f"{p}: not valid YAML: {e}") from None
        if not isinstance(data, dict):
            raise ValueError(f"{p}: top level must be a mapping of keys to values")
        source = str(p)
    for k, v in (overrides or {}).items():
        if v is not None:
            data[k] = v
    return ServeConfig.from_dict(data, source=source)

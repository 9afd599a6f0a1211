"""Server configuration: defaults follow the paper's WebVid recipe (Lou et al. 2025, Sec. 4).

A ``ServeConfig`` is built from defaults, then a YAML file (``--config``), then command-line
flags; every value is validated once, at startup, and a bad one raises ``ValueError`` naming
the field.
"""
from __future__ import annotations

import hashlib
import json
import math
import re
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Optional, Tuple

from v2v_server.delivery.batcher import SHUFFLES
from v2v_server.flow.options import DEFAULT_FLOW, FLOW_OPTIONS, check_option, unavailable_reason
from v2v_wire.outputs import ARRAYS
from v2v_wire.protocol import OUTPUTS, check_outputs, is_loopback  # noqa: F401  (is_loopback: config's checks and sockets use it)
from v2v_server.ops.settings import load_yaml, reference_markdown, setting
from v2v_server.checks import check_bool, check_choice, check_float, check_int, check_keys, check_prob
from v2v_server.simulation.simulate import ParamRanges
from v2v_server.videos.decode import DECODE_FAST
from v2v_server.videos.shots import SHOT_CUTS
from v2v_server.videos.frame_cache import FORMATS as FRAME_CACHE_FORMATS
from v2v_server.videos.store import StoreSettings

#: Optical-flow options by name (the table lives in v2v_server/flow/options.py).
FLOW_PRESETS = tuple(FLOW_OPTIONS)
#: Wire dtypes of dense flow (``v2v_wire.outputs``).
FLOW_DTYPES = ARRAYS["flow"].dtypes
#: Upper limits (a typo like ``workers: 2000`` is an error, not a fork bomb or an OOM).
MAX_WORKERS = 256
MAX_PREFETCH = 256
MAX_CREDITS = 1024
MAX_SHUFFLE_BUFFER = 4096
#: Largest frame_height (8K UHD).
MAX_FRAME_HEIGHT = 4320
#: Samples the shuffle buffer holds by default (its mixing measured: docs/shuffle.md).
SHUFFLE_BUFFER = 64
VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".gif")


@dataclass
class SampleRecipe:
    """The sample recipe: everything that decides a sample's content.

    Defaults follow the paper's WebVid recipe: ``sequence_length`` L voxel grids of
    ``num_bins`` B bins, ``frames_per_bin`` frame pairs per bin, so a sample spans
    ``L * B * frames_per_bin + 1`` frame indices (201 by default). Spatial: the top
    ``keep_top_fraction`` of each frame is kept (WebVid watermark), a random ``crop_size`` x
    ``crop_size`` crop (pixels) is taken, flipped horizontally with probability ``hflip_prob``.
    Pauses: a per-frame Markov chain repeats the previous frame.
    """

    seed: int = setting(0, help="base seed: sample content depends only on (seed, epoch, sample id)")
    sequence_length: int = setting(40, help="voxel grids per sample, L")
    num_bins: int = setting(5, help="temporal bins per voxel grid, B")
    frames_per_bin: int = setting(1, help="frame pairs summed into one bin; a sample spans L x B x this + 1 frames")
    crop_size: int = setting(128, help="square crop side, pixels")
    keep_top_fraction: float = setting(0.54, help="fraction of each frame's height, from the top, that crops come "
                                                  "from (WebVid's watermark; 1.0 for clips without one)")
    frame_height: int = setting(0, help="scale every decoded frame to this height in pixels (width keeps the aspect "
                                        "ratio; OpenCV INTER_AREA on full-range luma) before the kept region, the "
                                        "frame cache and the crops; 0 = frames as decoded (docs/frame_scale.md)")
    hflip_prob: float = setting(0.5, help="probability of a horizontal flip")
    max_samples_per_video: int = setting(10, help="windows (samples with crops_per_window 1) per video per epoch")
    shot_cuts: str = setting("avoid", help="avoid: windows lie inside one shot (they start at each shot's first "
                                           "frame + k x stride; shot cuts found while decoding, docs/corpora.md); "
                                           "off: windows at k x stride whatever they hold (the authors' loader)",
                             choices=SHOT_CUTS)
    crops_per_window: int = setting(1, help="random crops per decoded window, each its own sample (own crop, flip, "
                                            "pauses, sensor parameters; ids path#window.crop when > 1)")
    pause_enabled: bool = setting(True, help="pause augmentation (a Markov chain repeating the previous frame)")
    p_pause_when_running: float = setting(0.0102, help="probability that a pause starts at a frame")
    p_pause_when_paused: float = setting(0.9791, help="probability that a pause goes on at a frame")
    outputs: Tuple[str, ...] = setting(OUTPUTS, help="what clients may ask for (comma list)", cli=str)
    flow_preset: str = setting(DEFAULT_FLOW, help="optical flow option (docs/flow.md)", choices=tuple(FLOW_OPTIONS))
    flow_dtype: str = setting("float16", help="wire dtype of flow", choices=FLOW_DTYPES)
    ranges: ParamRanges = setting(help="sensor parameter ranges: threshold, ratio, noise_std, hot_pixel_fraction, "
                                       "hot_pixel_std as [lo, hi] (WebVid ranges)", flag="", factory=ParamRanges)
    refine: str = setting("off", help="off | uniform:K | adaptive:PX | adaptive-dl:L: sub-frames where motion needs "
                                      "them (docs/fidelity.md)")
    nonidealities: dict = setting(help="sensor non-idealities, all off by default (v2v_server/simulation/nonideal.py)", flag="",
                                  factory=dict)
    degrade_dynamic_range: dict = setting(help="{probability, scale: [lo, hi]}: dynamic-range degradation before V2V "
                                               "(paper appendix 'Dataset quality'; true = 0.8, [1, 3])", flag="",
                                          factory=dict)
    fixed_sensor_params: bool = setting(False, help="each video keeps one (c+, c-) drawn from (seed, video) for every "
                                                    "window and epoch (the paper's '-F' datasets)")
    decode_threads: int = setting(1, help="FFmpeg decoding threads per worker")
    decode_fast: str = setting("off", help="skip H.264's deblocking filter on some frames: off | noref | bidir | all "
                                           "(faster decoding, measured error: docs/decode_fast.md)",
                               choices=tuple(DECODE_FAST))

    @property
    def frames_per_sample(self) -> int:
        """Frame indices one sample spans: L * B * frames_per_bin + 1."""
        return self.sequence_length * self.num_bins * self.frames_per_bin + 1

    @property
    def window_stride(self) -> int:
        """Source frames from one window's start to the next: ``frames_per_sample - 1`` (200), so
        window k spans frames ``[k * stride, (k + 1) * stride]`` and shares its last frame with
        window k + 1's first: every frame pair of a video is in exactly one window. The authors'
        loader steps the same way (HYLZ-2019/V2V ``data/v2v_datasets.py``, ``step_size =
        frames_per_seq``)."""
        return self.frames_per_sample - 1

    def windows_in(self, frames: int) -> int:
        """Windows (of ``frames_per_sample`` frames, ``window_stride`` apart) a video of
        ``frames`` frames holds, at most ``max_samples_per_video``."""
        return max(0, min(self.max_samples_per_video, (frames - 1) // self.window_stride))

    def frames_for(self, windows: int) -> int:
        """Frames to decode for the first ``windows`` windows: ``windows * window_stride + 1``."""
        return windows * self.window_stride + 1 if windows > 0 else 0

    def fingerprint(self) -> str:
        """A short hash of what decides a sample's content (the recipe less the outputs each
        client asks for and the decoding threads): sample ids name the same samples only under
        the same fingerprint."""
        content = {k: v for k, v in self.recipe_dict().items() if k not in ("outputs", "decode_threads")}
        if not content["frame_height"]:  # no scaling: the fingerprint of the same recipe without the key
            del content["frame_height"]
        return hashlib.sha256(json.dumps(content, sort_keys=True, default=str).encode()).hexdigest()[:16]

    def recipe_dict(self) -> dict:
        """The recipe's keys as a plain, msgpack/YAML-safe dict (what a worker process gets)."""
        d = {f.name: getattr(self, f.name) for f in fields(SampleRecipe)}
        d.update(ranges=self.ranges.to_dict(), outputs=list(self.outputs))
        return d

    @classmethod
    def recipe_from_dict(cls, d: dict, source: str = "recipe") -> "SampleRecipe":
        """A validated ``SampleRecipe`` from ``recipe_dict()`` output.

        Raises:
            ValueError: naming ``source`` and the key, for an unknown key or a bad value.
        """
        check_keys(d, (f.name for f in fields(SampleRecipe)), source=source)
        r = SampleRecipe(**{k: (tuple(v) if k == "outputs" and isinstance(v, list) else v) for k, v in d.items()})
        try:
            r.validate_recipe()
        except ValueError as e:
            raise ValueError(f"{source}: {e}") from None
        return r

    def validate_recipe(self) -> None:
        """Check the recipe's fields; ``ValueError`` names the first bad one."""
        for name in ("sequence_length", "num_bins", "frames_per_bin", "max_samples_per_video", "decode_threads",
                     "crops_per_window"):
            check_int(name, getattr(self, name), 1)
        check_int("crop_size", self.crop_size, 8, 4096, "pixels")
        check_int("seed", self.seed, 0)
        for name in ("hflip_prob", "p_pause_when_running", "p_pause_when_paused"):
            setattr(self, name, check_prob(name, getattr(self, name)))
        if not isinstance(self.keep_top_fraction, (int, float)) or not (0 < self.keep_top_fraction <= 1):
            raise ValueError(f"keep_top_fraction must be in (0, 1], got {self.keep_top_fraction!r}")
        check_int("frame_height", self.frame_height, 0, MAX_FRAME_HEIGHT, "pixels; 0 = no scaling")
        if self.frame_height and math.floor(self.frame_height * self.keep_top_fraction) < self.crop_size:
            raise ValueError(f"frame_height {self.frame_height} keeps {math.floor(self.frame_height * self.keep_top_fraction)}"
                             f" rows (keep_top_fraction {self.keep_top_fraction}), fewer than crop_size "
                             f"{self.crop_size}: every crop would be enlarged again; use frame_height >= "
                             f"{math.ceil(self.crop_size / self.keep_top_fraction)} or 0 (no scaling)")
        self.outputs = check_outputs(self.outputs)
        self.flow_preset = check_option(self.flow_preset).name  # ValueError naming flow_preset
        why = unavailable_reason(self.flow_preset)
        if why:
            raise ValueError(f"flow_preset {self.flow_preset!r} cannot run here: {why}")
        check_choice("flow_dtype", self.flow_dtype, FLOW_DTYPES)
        check_choice("decode_fast", self.decode_fast, tuple(DECODE_FAST))
        check_choice("shot_cuts", self.shot_cuts, SHOT_CUTS)
        if not isinstance(self.ranges, ParamRanges):
            self.ranges = ParamRanges.from_dict(self.ranges)
        from v2v_server.samples.augment import parse_degrade
        from v2v_server.simulation.nonideal import NonIdealities
        from v2v_server.simulation.refine import parse_refine

        self.refine = str(parse_refine(self.refine))
        ni = NonIdealities.from_dict(self.nonidealities or None)  # ValueError naming nonidealities.<field>
        self.nonidealities = ni.to_dict() if ni.enabled else {}
        if "polarity_counts" in self.outputs and (self.nonidealities or self.refine != "off"):
            # N+ and N- come from plain V2V's kernel call only: not offered under refinement or
            # non-idealities (a client asking is told what is offered at its hello)
            if self.outputs != OUTPUTS:
                raise ValueError("outputs: polarity_counts is made by plain V2V only (refine: off, no "
                                 f"nonidealities); got refine {self.refine!r}, nonidealities {self.nonidealities}")
            self.outputs = tuple(o for o in self.outputs if o != "polarity_counts")
        self.degrade_dynamic_range = parse_degrade(self.degrade_dynamic_range)
        check_bool("pause_enabled", self.pause_enabled)
        check_bool("fixed_sensor_params", self.fixed_sensor_params)


@dataclass
class ServingSettings:
    """Serving: corpus, workers, transport, delivery, security and operations."""

    videos: Optional[str] = setting(None, help="corpus: a folder (searched recursively) or an object-store URL "
                                               "(s3://bucket/prefix/, gs://, az://; extras v2v[s3], v2v[gcs], "
                                               "v2v[azure]; docs/object_store.md); default: the bundled sample clips")
    video_list: Optional[str] = setting(None, help="list file selecting and ordering the videos (the V2V authors' "
                                                   "format: first field a path relative to videos, rest ignored, "
                                                   "# comments); nothing is listed from the store")
    storage_options: dict = setting(help="options for the store's filesystem (s3fs, gcsfs, adlfs), e.g. "
                                         "{endpoint_url: ..., anon: true}; credentials otherwise come from the "
                                         "environment (AWS_*, AWS_ENDPOINT_URL included)", flag="", factory=dict)
    cache_dir: Optional[str] = setting(None, help="folder of the store manifest when there is no state_dir, and "
                                                  "of the object and frame caches (default $XDG_CACHE_HOME/v2v)")
    cache_max_gb: float = setting(StoreSettings.cache_max_gb, help="GiB of whole store objects kept on local disk for corpora read every "
                                            "epoch (least recently used removed first); 0 = off, read from the "
                                            "store each time")
    frame_cache_gb: float = setting(0.0, help="GiB of decoded frames kept on this host's disk under cache_dir/frames, "
                                              "shared by every worker and server process of the host: each video is "
                                              "decoded once, later epochs cut their samples from the cache "
                                              "(docs/frame_cache.md); 0 = off")
    frame_cache_format: str = setting("raw", help="raw: frames as decoded, memory-mapped (fastest); zstd: frame "
                                                  "differences compressed (fewer bytes, more CPU per read)",
                                      choices=FRAME_CACHE_FORMATS)
    refresh_manifest: bool = setting(False, help="list the store again instead of reading the manifest written at "
                                                 "the first start")
    store_read_timeout_s: float = setting(StoreSettings.read_timeout_s, help="seconds a store request may stay unanswered before it fails "
                                                     "(then retried)", flag="--store-read-timeout")
    store_max_attempts: int = setting(StoreSettings.max_attempts, help="attempts per store request (botocore standard retry mode: "
                                              "exponential backoff on throttling, 5xx and connection errors)")
    read_block_mb: float = setting(StoreSettings.read_block_mb, help="MiB fetched per store request while decoding (one request for a "
                                             "smaller video)")
    workers: int = setting(2, help="worker processes")
    bind: str = setting("tcp://127.0.0.1:5555", help="ZeroMQ endpoint to bind (port 0 = any free port)")
    epochs: Optional[int] = setting(None, help="end the stream after this many epochs (default: unbounded)")
    end_grace_s: float = setting(600.0, help="with epochs: seconds the server stays up after the last epoch with no "
                                             "trainer connected, serving trainers that resume from an older "
                                             "checkpoint (the epochs they have not finished reopen for them)")
    state_dir: Optional[str] = setting(None, help="folder of the delivery journal: what each trainer acknowledged, "
                                                  "so a restarted server repeats nothing for any of them "
                                                  "(v2v_server/delivery/journal.py)")
    batch_size: int = setting(12, help="samples per batch (the last batch of an epoch may be smaller)")
    video_extensions: Tuple[str, ...] = setting(VIDEO_EXTENSIONS, help="file extensions served as videos", flag="")
    shuffle: str = setting("epoch", help="epoch: each epoch hands the videos out in an order drawn from (seed, "
                                         "epoch) and each made sample joins a random open batch of the shuffle "
                                         "buffer, so batches mix videos whatever the worker count; none: the "
                                         "listing's order, batches in the order samples are made (docs/shuffle.md)",
                           choices=SHUFFLES)
    shuffle_buffer: int = setting(SHUFFLE_BUFFER, help="samples the shuffle buffer holds (shuffle: epoch), rounded "
                                                       "up to whole batches: that many samples of server memory "
                                                       "(docs/shuffle.md has their size)")
    heartbeat_s: float = setting(1.0, help="seconds between heartbeats to clients")
    lease_s: float = setting(60.0, help="seconds before an unacknowledged batch is sent again", flag="--lease")
    client_timeout_s: float = setting(10.0, help="seconds of client silence before its batches go back to the queue",
                                      flag="--client-timeout")
    prefetch_batches: int = setting(2, help="batches assembled ahead of the clients' credits")
    revoke_s: Optional[float] = setting(None, help="seconds a client may leave a revoke unanswered before it is "
                                                   "dropped (default: the client timeout)", flag="--revoke-timeout")
    max_credits: int = setting(64, help="most batches one client may hold")
    task_timeout_s: float = setting(300.0, help="seconds a worker may send nothing on a task before the task is "
                                                "reassigned and the worker replaced", flag="--task-timeout")
    curve_secret_key: Optional[str] = setting(None, help="CurveZMQ: the server's secret key file (v2v-keygen)")
    curve_allow: Optional[str] = setting(None, help="CurveZMQ: folder of allowed client public key files (*.key)")
    insecure: bool = setting(False, help="allow a non-loopback bind without CurveZMQ (not recommended)")
    shard: Optional[str] = setting(None, help="serve only shard I of N of the corpus, as I/N (a stable hash of each "
                                              "file's relative path picks its shard)")
    metrics_port: Optional[int] = setting(None, help="port of the HTTP endpoint with /metrics, /healthz and /readyz "
                                                     "(0 = any free port; default off)")
    metrics_host: str = setting("127.0.0.1", help="address the metrics endpoint binds (0.0.0.0 in a container)")
    log_format: str = setting("text", help="log lines as text or one JSON object per line", choices=("text", "json"))

    @property
    def shard_spec(self) -> Tuple[int, int]:
        """``(index, count)`` of ``shard``; ``(0, 1)`` when the whole corpus is served."""
        return parse_shard(self.shard)

    def validate_serving(self) -> None:
        """Check the serving fields; ``ValueError`` names the first bad one."""
        check_int("workers", self.workers, 1, MAX_WORKERS, "worker processes")
        check_int("batch_size", self.batch_size, 1)
        check_int("prefetch_batches", self.prefetch_batches, 1, MAX_PREFETCH, "batches assembled ahead")
        check_choice("shuffle", self.shuffle, SHUFFLES)
        check_int("shuffle_buffer", self.shuffle_buffer, 1, MAX_SHUFFLE_BUFFER, "samples")
        check_int("max_credits", self.max_credits, 1, MAX_CREDITS, "batches in flight per client")
        if self.epochs is not None:
            check_int("epochs", self.epochs, 1)
        for name in ("heartbeat_s", "lease_s", "client_timeout_s", "task_timeout_s"):
            setattr(self, name, check_float(name, getattr(self, name)))
        self.end_grace_s = check_float("end_grace_s", self.end_grace_s, positive=False)
        if self.end_grace_s < 0:
            raise ValueError(f"end_grace_s must be >= 0 seconds, got {self.end_grace_s!r}")
        if self.revoke_s is not None:
            self.revoke_s = check_float("revoke_s", self.revoke_s)
        if not isinstance(self.bind, str) or "://" not in self.bind:
            raise ValueError(f"bind must be a ZeroMQ endpoint like tcp://127.0.0.1:5555, got {self.bind!r}")
        if (self.curve_secret_key is None) != (self.curve_allow is None):
            raise ValueError("curve_secret_key and curve_allow must be given together")
        if self.curve_secret_key is not None:
            if not Path(self.curve_secret_key).is_file():
                raise ValueError(f"curve_secret_key: no such file {self.curve_secret_key}")
            if not Path(self.curve_allow).is_dir():
                raise ValueError(f"curve_allow: no such folder {self.curve_allow}")
        check_bool("insecure", self.insecure)
        if not is_loopback(self.bind) and self.curve_secret_key is None and not self.insecure:
            raise ValueError(f"bind {self.bind} is not a loopback address: give curve_secret_key and curve_allow "
                             f"(see v2v-keygen), or insecure: true to stream unauthenticated")
        if self.shard is not None:
            self.shard = "%d/%d" % parse_shard(self.shard)
        if self.metrics_port is not None and (isinstance(self.metrics_port, bool) or not isinstance(
                self.metrics_port, int) or not 0 <= self.metrics_port <= 65535):
            raise ValueError(f"metrics_port must be a TCP port in [0, 65535] (0 = any free port), "
                             f"got {self.metrics_port!r}")
        check_choice("log_format", self.log_format, ("text", "json"))
        if not isinstance(self.metrics_host, str) or not self.metrics_host:
            raise ValueError(f"metrics_host must be an address such as 127.0.0.1, got {self.metrics_host!r}")
        self.video_extensions = tuple(e.lower() for e in self.video_extensions)
        if self.videos is not None:
            self.videos = str(self.videos)
        for name in ("video_list", "cache_dir"):
            v = getattr(self, name)
            if v is not None and (not isinstance(v, str) or not v):
                raise ValueError(f"{name} must be a path, got {v!r}")
        if not isinstance(self.storage_options, dict):
            raise ValueError(f"storage_options must be a mapping of filesystem options, got {self.storage_options!r}")
        check_bool("refresh_manifest", self.refresh_manifest)
        self.store_read_timeout_s = check_float("store_read_timeout_s", self.store_read_timeout_s)
        self.read_block_mb = check_float("read_block_mb", self.read_block_mb)
        self.cache_max_gb = check_float("cache_max_gb", self.cache_max_gb, positive=False)
        if self.cache_max_gb < 0:
            raise ValueError(f"cache_max_gb must be >= 0 GiB (0 = no cache), got {self.cache_max_gb!r}")
        self.frame_cache_gb = check_float("frame_cache_gb", self.frame_cache_gb, positive=False)
        if self.frame_cache_gb < 0:
            raise ValueError(f"frame_cache_gb must be >= 0 GiB (0 = no frame cache), got {self.frame_cache_gb!r}")
        check_choice("frame_cache_format", self.frame_cache_format, FRAME_CACHE_FORMATS)
        if self.frame_cache_gb > 0 and self.frame_cache_format == "zstd":
            try:
                import zstandard  # noqa: F401  (the zstd entries' codec; a decode host's [server] lacks it)
            except ImportError:
                raise ValueError("frame_cache_format zstd needs the zstandard package: pip install 'v2v[wire]'") from None
        check_int("store_max_attempts", self.store_max_attempts, 1, 20, "attempts")
        if self.state_dir is not None:
            if not isinstance(self.state_dir, str) or not self.state_dir:
                raise ValueError(f"state_dir must be a folder path, got {self.state_dir!r}")


@dataclass
class ServeConfig(ServingSettings, SampleRecipe):
    """Everything ``v2v-serve`` needs to know: the sample recipe (:class:`SampleRecipe`) and
    the serving settings (:class:`ServingSettings`). YAML files and flags name either's keys
    flat (``seed: 3``, ``--workers 8``); docs/config.md lists them (``python -m
    v2v_server.ops.config --markdown``)."""

    def validate(self) -> "ServeConfig":
        """Check every field; raise ``ValueError`` naming the first bad one. Returns self."""
        self.validate_serving()
        self.validate_recipe()
        return self

    def recipe(self) -> SampleRecipe:
        """The sample recipe alone: what the workers get, and what a resume state or a fan-in
        compares across servers."""
        return SampleRecipe(**{f.name: getattr(self, f.name) for f in fields(SampleRecipe)})

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
        check_keys(d, (f.name for f in fields(cls)), source=source)
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


def load_config(path: Optional[str], overrides: Optional[dict] = None) -> ServeConfig:
    """Defaults, then the YAML file at ``path`` (if any), then ``overrides`` (non-None values).

    Raises:
        ValueError: naming the file and the field for unknown keys or bad values, or when the
            file is not valid YAML.
        FileNotFoundError: when ``path`` does not exist.
    """
    data = load_yaml(path) if path is not None else {}
    source = str(Path(path)) if path is not None else "command line"
    for k, v in (overrides or {}).items():
        if v is not None:
            data[k] = v
    return ServeConfig.from_dict(data, source=source)


def main(argv=None) -> int:
    """``python -m v2v_server.ops.config --markdown``: print the configuration reference (docs/config.md)."""
    import argparse

    p = argparse.ArgumentParser(description=main.__doc__)
    p.add_argument("--markdown", action="store_true", required=True)
    p.parse_args(argv)
    print("# v2v-serve configuration\n\nEvery key can be set in a YAML file (`v2v-serve --config FILE`) and, "
          "where a flag is listed, on the command line (flags win over the file). Unknown keys and bad values stop "
          "the server at startup with the key and the file named. Generated by "
          "`python -m v2v_server.ops.config --markdown > docs/config.md`.\n")
    print(reference_markdown(ServeConfig, (SampleRecipe, ServingSettings)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

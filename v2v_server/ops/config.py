"""Server configuration: the composition of each stage's settings.

A ``ServeConfig`` is built from defaults, then a YAML file (``--config``), then command-line
flags; every value is validated once, when its part is built, and a bad one raises
``ValueError`` naming the field. The sample recipe's keys are owned by
``samples.recipe.SampleRecipe`` (defaults: the paper's WebVid recipe, Lou et al. 2025, Sec. 4),
the delivery keys by ``delivery.policy.DeliveryPolicy``, the object store's by
``sources.store.StoreSettings``, the rest by :class:`ServingSettings` here.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Tuple, Union

from v2v_server.checks import check_bool, check_choice, check_float, check_int
from v2v_server.delivery.policy import DeliveryPolicy
from v2v_server.samples.recipe import SampleRecipe
from v2v_server.settings import documented, load_yaml, owners, reference_markdown, setting, split_keys
from v2v_server.frames.host_caches import HostCaches
from v2v_server.frames.frame_cache import DEFAULT_FORMAT as DEFAULT_FRAME_CACHE_FORMAT, FORMATS as FRAME_CACHE_FORMATS
from v2v_server.disk_cache import cache_folder
from v2v_server.sources.source import VideoSource
from v2v_server.sources.source_spec import open_source
from v2v_server.sources.store import StoreSettings
from v2v_server.sources.video_tables import TABLE_FORMATS, TableSettings, table_format
from v2v_wire.plan_messages import MAX_WORKERS
from v2v_wire.protocol import is_loopback  # noqa: F401  (config's checks and sockets use it)
from v2v_wire.push_names import TAKEN, server_key_problem

__all__ = ["SampleRecipe", "DeliveryPolicy", "ServingSettings", "ServeConfig", "load_config", "parse_shard",
           "source_from_config"]

VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".gif")


@dataclass(frozen=True)
class ServingSettings:
    """Serving: corpus, workers, transport, security and operations."""

    videos: Optional[str] = setting(None, help="corpus: a folder (searched recursively) or an object-store URL "
                                               "(s3://bucket/prefix/, gs://, az://; extras v2v[s3], v2v[gcs], "
                                               "v2v[azure]; docs/object_store.md); default: the bundled sample clips")
    video_list: Optional[str] = setting(None, help="list file selecting and ordering the videos: lines `path`, "
                                                   "`path start end` (a segment) or the V2V authors' `path frames "
                                                   "[a b]`, the path relative to videos and everything before the "
                                                   "trailing numbers; # comments; or a metadata table (.csv, .tsv, "
                                                   ".jsonl, .json, .parquet; extra v2v[corpora]) whose rows name "
                                                   "the videos (docs/corpora.md); nothing is listed from the store")
    video_list_column: Optional[str] = setting(None, help="table video lists: the column holding a video's path "
                                                          "relative to videos, or a template over columns such as "
                                                          "'{videoID}.mp4'; default: the first of video, path, file")
    video_list_filter: Optional[str] = setting(None, help="table video lists: the rows served, an SQL expression "
                                                          "over the table's columns evaluated by DuckDB, e.g. "
                                                          "'frame >= 201 and \"motion score\" > 0.5'")
    storage_options: dict = setting(help="options for the store's filesystem (s3fs, gcsfs, adlfs), e.g. "
                                         "{endpoint_url: ..., anon: true}; credentials otherwise come from the "
                                         "environment (AWS_*, AWS_ENDPOINT_URL included)", flag="", factory=dict)
    cache_dir: Optional[str] = setting(None, help="folder of the store manifest, the plans' record, the corpus "
                                                  "index, and the object and frame caches (default $XDG_CACHE_HOME/v2v)")
    frame_cache_gb: float = setting(0.0, help="GiB of decoded frames kept on this host's disk under cache_dir/frames, "
                                              "shared by every worker and server process of the host: each video is "
                                              "decoded once, later epochs cut their samples from the cache "
                                              "(docs/frame_cache.md); 0 = off")
    frame_cache_format: str = setting(DEFAULT_FRAME_CACHE_FORMAT, help="raw: frames as decoded, memory-mapped (fastest); zstd: frame "
                                                  "differences compressed (fewer bytes, more CPU per read)",
                                      choices=FRAME_CACHE_FORMATS)
    refresh_manifest: bool = setting(False, help="list the store again instead of reading the manifest written at "
                                                 "the first start")
    workers: int = setting(2, help="worker processes")
    bind: str = setting("tcp://127.0.0.1:5555", help="ZeroMQ endpoint to bind (port 0 = any free port)")
    video_extensions: Tuple[str, ...] = setting(VIDEO_EXTENSIONS, help="file extensions served as videos", flag="")
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

    def __post_init__(self):
        """Check the serving fields (``ValueError`` names the first bad one) and normalise them."""
        _set = object.__setattr__  # frozen: normalised once, here
        check_int("workers", self.workers, 1, MAX_WORKERS, "worker processes")
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
            _set(self, "shard", "%d/%d" % parse_shard(self.shard))
        if self.metrics_port is not None and (isinstance(self.metrics_port, bool) or not isinstance(
                self.metrics_port, int) or not 0 <= self.metrics_port <= 65535):
            raise ValueError(f"metrics_port must be a TCP port in [0, 65535] (0 = any free port), "
                             f"got {self.metrics_port!r}")
        check_choice("log_format", self.log_format, ("text", "json"))
        if not isinstance(self.metrics_host, str) or not self.metrics_host:
            raise ValueError(f"metrics_host must be an address such as 127.0.0.1, got {self.metrics_host!r}")
        _set(self, "video_extensions", tuple(e.lower() for e in self.video_extensions))
        if self.videos is not None:
            _set(self, "videos", str(self.videos))
        for name in ("video_list", "cache_dir"):
            v = getattr(self, name)
            if v is not None and (not isinstance(v, str) or not v):
                raise ValueError(f"{name} must be a path, got {v!r}")
        for name in ("video_list_column", "video_list_filter"):
            v = getattr(self, name)
            if v is not None and (not isinstance(v, str) or not v.strip()):
                raise ValueError(f"{name} must be text, got {v!r}")
            if v is not None and not (self.video_list and table_format(self.video_list)):
                raise ValueError(f"{name} reads a table video list (video_list ending in "
                                 f"{', '.join(TABLE_FORMATS)}), got video_list {self.video_list!r}")
        if not isinstance(self.storage_options, dict):
            raise ValueError(f"storage_options must be a mapping of filesystem options, got {self.storage_options!r}")
        check_bool("refresh_manifest", self.refresh_manifest)
        _set(self, "frame_cache_gb", check_float("frame_cache_gb", self.frame_cache_gb, positive=False))
        if self.frame_cache_gb < 0:
            raise ValueError(f"frame_cache_gb must be >= 0 GiB (0 = no frame cache), got {self.frame_cache_gb!r}")
        check_choice("frame_cache_format", self.frame_cache_format, FRAME_CACHE_FORMATS)
        if self.frame_cache_gb > 0 and self.frame_cache_format == "zstd":
            try:
                import zstandard  # noqa: F401  (the zstd entries' codec; a decode host's [server] lacks it)
            except ImportError:
                raise ValueError("frame_cache_format zstd needs the zstandard package: pip install 'v2v[wire]'") from None


class ServeConfig:
    """Everything ``v2v-serve`` needs to know: the composition of each stage's settings.

    Parts (attribute: class, owner of its keys' defaults, help and checks):

    * ``recipe``: :class:`~v2v_server.samples.recipe.SampleRecipe`, what decides a sample's
      content (it composes the frames stage's ``WindowSettings`` and ``DecodeSettings``);
    * ``delivery``: :class:`~v2v_server.delivery.policy.DeliveryPolicy`, batches, the shuffle
      buffer, the task timeout;
    * ``serving``: :class:`ServingSettings`, corpus, workers, transport, security, operations;
    * ``store``: :class:`~v2v_server.sources.store.StoreSettings`, how an object-store corpus is read.

    YAML files and flags name every part's keys flat (``seed: 3``, ``--workers 8``), and so does
    the constructor (``ServeConfig(seed=3, workers=8)``); reading a flat key (``cfg.workers``)
    reads it from the part that owns it. Each part checks its keys when built, so a
    ``ServeConfig`` that exists is valid; it is immutable. docs/config.md lists the keys
    (``python -m v2v_server.ops.config --markdown``).

    Raises:
        ValueError: naming the key, for an unknown key or a bad value; a key push delivery had
            (``epochs``, ``state_dir``, ...) in one line saying what to do instead.
    """

    #: The parts, in the order docs/config.md lists them: (attribute, settings class).
    PARTS = (("recipe", SampleRecipe), ("delivery", DeliveryPolicy), ("serving", ServingSettings),
             ("store", StoreSettings))
    __slots__ = tuple(name for name, _ in PARTS)

    def __init__(self, **keys):
        for key, value in list(keys.items()):
            if key in TAKEN and value == TAKEN[key]:  # what every server does
                del keys[key]
            elif server_key_problem(key):  # push delivery's
                raise ValueError(server_key_problem(key))
        given = split_keys(ServeConfig, keys)
        recipe = SampleRecipe(**given["recipe"])
        for name, part in zip(self.__slots__, (recipe, DeliveryPolicy(**given["delivery"]),
                                               ServingSettings(**given["serving"]), StoreSettings(**given["store"]))):
            object.__setattr__(self, name, part)

    def __getattr__(self, name: str):
        part = _OWNERS.get(name)
        if part is None:
            raise AttributeError(f"ServeConfig has no key {name!r}")
        return getattr(object.__getattribute__(self, part), name)

    def __setattr__(self, name, value):
        raise AttributeError(f"ServeConfig is immutable: build another with ServeConfig.from_dict({{..., {name!r}: ...}})")

    def __eq__(self, other) -> bool:
        return isinstance(other, ServeConfig) and all(getattr(self, n) == getattr(other, n) for n in self.__slots__)

    def __repr__(self) -> str:
        return f"ServeConfig({', '.join(f'{n}={getattr(self, n)!r}' for n in self.__slots__)})"

    def __reduce__(self):
        return ServeConfig.from_dict, (self.to_dict(),)

    # ------------------------------------------------------------------ io
    def to_dict(self) -> dict:
        """Plain, msgpack/YAML-safe dict of every key, flat (ranges as lists)."""
        d = {}
        for name, cls in self.PARTS:
            part = getattr(self, name)
            d.update({f.name: getattr(part, f.name) for f in documented(cls)})
        d["ranges"] = self.recipe.ranges.to_dict()
        d["outputs"] = list(self.recipe.outputs)
        d["video_extensions"] = list(self.serving.video_extensions)
        return d

    @classmethod
    def from_dict(cls, d: dict, source: str = "config") -> "ServeConfig":
        """Build and validate from a flat mapping; unknown keys raise ``ValueError`` naming them
        and ``source`` (the YAML file)."""
        if d is None:
            d = {}
        if not isinstance(d, dict):
            raise ValueError(f"{source}: top level must be a mapping of keys to values")
        kw = dict(d)
        for k in ("outputs", "video_extensions"):
            if k in kw and isinstance(kw[k], list):
                kw[k] = tuple(kw[k])
        try:
            return cls(**kw)
        except ValueError as e:
            raise ValueError(f"{source}: {e}") from None


#: Flat key -> the ``ServeConfig`` part that owns it.
_OWNERS = owners(ServeConfig)


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


def source_from_config(cfg: ServeConfig, videos: Union[str, Path, None] = None) -> VideoSource:
    """The source ``cfg`` (a ``ServeConfig``) describes (``source_spec.open_source``): ``videos``
    or ``cfg.videos``, its ``video_list`` read with the table's column and filter (and the rows
    too short for a window left unopened, the frames side's rule ``WindowSettings.short_of``),
    ``storage_options``, store settings, and a store's objects kept as a manifest in the cache
    folder."""
    table = TableSettings(cfg.video_list_column, cfg.video_list_filter, cfg.recipe.windows.short_of)
    return open_source(cfg.videos if videos is None else videos, storage_options=cfg.storage_options,
                       video_list=cfg.video_list, table=table, keep_manifest=True, refresh_manifest=cfg.refresh_manifest,
                       settings=cfg.store, cache_dir=cache_folder(cfg.cache_dir))


def caches_from_config(cfg: ServeConfig) -> HostCaches:
    """The host's caches ``cfg`` describes, passed beside its source: the frame cache
    (``frame_cache_gb``, ``frame_cache_format``) and the corpus index, in the cache folder
    (``disk_cache.cache_folder`` of ``cache_dir``)."""
    return HostCaches.open(cache_folder(cfg.cache_dir), cfg.frame_cache_gb, cfg.frame_cache_format)


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
    print(reference_markdown(ServeConfig, [cls for _, cls in ServeConfig.PARTS]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

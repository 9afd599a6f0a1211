"""V2V as a Ray Data pipeline: window descriptors in, one row per training sample out.

For clusters that already run Ray: Ray places the decoding (a ``map_batches`` stage on an actor
pool of CPU workers) on CPU nodes, streams rows with backpressure to Ray Train ranks on GPU
nodes, and splits the stream between ranks (``streaming_split``). Sample content is made by the
same functions ``v2v-serve``'s workers call (``samples.video_samples``, ``window_pass.WindowPass``),
so a sample is identical, bit for bit, to what ``v2v-serve`` sends for the same
(seed, epoch, sample_id).

Layout of the pipeline:

1. :func:`scan_corpus_windows` lists the corpus (the start-up path ``v2v-serve`` runs) and counts
   each file's windows by demuxing its packets (no decoding, ~1/50 of a decode pass); a file that cannot be
   opened or is too short is skipped here with the same ``skipped PATH: reason`` line as
   ``v2v-serve``. The result (:class:`RayCorpus`) does not depend on the epoch: keep it.
2. :func:`epoch_descriptors` lists the epoch's sample ids, drops the excluded ones (resume:
   before any decoding), pads the list to a multiple of the rank count with flagged repeats
   (``padding``) and groups the ids by video: one descriptor per video, because a video is
   decoded once, sequentially, and all its windows are cut from that pass, as in ``v2v-serve``
   (seeking to each window costs a keyframe seek plus decoding up to the window start; see
   ``bench/ray_bench.py``).
3. :func:`v2v_dataset` turns them into ``ray.data.from_items`` (one block per video) and a
   ``map_batches`` stage with :class:`SampleMaker`, a class, so each actor builds its flow
   estimator and compiled kernels once.

Every descriptor entry gives exactly one row, always: a window the file could not give (a file
that fails part-way) becomes a ``padding`` row of zeros whose ``params`` hold ``{"skipped":
reason}``, so the row count stays a multiple of the rank count and ``streaming_split(n,
equal=True)`` drops nothing.

Rows: ``sample_id`` str; ``voxels`` int16 (L, B, S, S) signed event counts; ``frames`` uint8
(L + 1, 1, S, S) at voxel boundaries; ``flow`` float16/float32 (``flow_dtype``) (L, 2, S, S),
pixels from frame l to l + 1; ``polarity_counts`` uint8 (L, 2, B, S, S) N+ and N- per bin (opt-in)
(only the columns in ``outputs``; dtypes and layouts from ``v2v_wire.outputs``); ``params`` str (JSON of the
sample's parameters, as in the ZeroMQ batch header); ``epoch`` int64; ``padding`` bool.
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Iterable, Iterator, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from v2v_wire.plan import video_order
from v2v_server.frames.host_caches import HostCaches
from v2v_server.ops.config import ServeConfig, caches_from_config, source_from_config
from v2v_server.ops.startup import resolve_config, start_source
from v2v_wire.outputs import ARRAYS, DEFAULT_OUTPUTS, row_array, zeros_row
from v2v_wire.protocol import check_outputs
from v2v_server.flow.estimate import FlowEstimator
from v2v_wire.ids import make_sample_id, parse_sample_id, window_keys
from v2v_server.samples.make import video_samples
from v2v_server.samples.recipe import SampleRecipe
from v2v_wire.flowgrid import expand_grids
from v2v_server.frames.check import count_windows as check_count_windows
from v2v_server.frames.video_read import as_verdict
from v2v_server.sources.source import VideoSource
from v2v_server.sources.source_spec import source_from_spec

__all__ = ["RayCorpus", "scan_corpus_windows", "count_windows", "epoch_descriptors", "SampleMaker",
           "v2v_dataset", "VOXEL_DTYPE"]

log = logging.getLogger("v2v.ray")

#: Dtype of the ``voxels`` column (``outputs.ARRAYS["voxels"].column_dtype``): one dtype for
#: every row (Ray blocks need one per column). The ZeroMQ path narrows per batch to int8 when it
#: can; the values are the same.
VOXEL_DTYPE = np.dtype(ARRAYS["voxels"].column_dtype).type


@dataclass(frozen=True)
class RayCorpus:
    """A corpus and its windows per video (epoch-independent; reuse it across epochs).

    Attributes:
        root: the corpus: a folder, a store prefix URL, or a brace pattern of tar shards (as given).
        windows: usable video (POSIX path relative to ``root``) -> windows per epoch.
        skipped: unusable video -> reason (the ``skipped PATH: reason`` of ``v2v-serve``).
        crops_per_window: samples per window (the recipe's ``crops_per_window``).
    """

    root: str
    windows: Dict[str, int]
    skipped: Dict[str, str]
    crops_per_window: int = 1

    @property
    def samples_per_epoch(self) -> int:
        """Rows of an epoch before padding: ``crops_per_window`` per window, as
        :func:`epoch_descriptors` lists them and ``v2v-serve`` serves them."""
        return sum(self.windows.values()) * self.crops_per_window


def count_windows(cfg: ServeConfig, source: VideoSource, rel: str,
                  caches: Optional[HostCaches] = None) -> Tuple[int, Optional[str]]:
    """Windows the video at ``rel`` of ``source`` gives per epoch, and why it gives none
    (``frames.check.count_windows`` under ``cfg``'s recipe)."""
    r = cfg.recipe
    return check_count_windows(r.windows, r.decode, r.reads, source, rel, caches)


def scan_corpus_windows(videos: Union[str, Path], config: Optional[ServeConfig] = None) -> RayCorpus:
    """List the videos of ``videos`` (as ``v2v-serve --videos``: a folder or an object-store
    URL, with ``config``'s ``video_list``, ``storage_options`` and manifest), keep ``config``'s
    ``shard`` of them, and count their windows.

    Logs ``skipped PATH: reason`` (logger ``v2v.ray``, WARNING) for each unusable file and
    ``ignored PATH: reason`` (INFO) for other entries, as ``v2v-serve`` does.

    The corpus is opened, checked, listed and sharded, and the videos the host's corpus index
    knows to give no window left out unopened, by the start-up path ``v2v-serve`` runs
    (``ops.startup.start_source``): the same videos ``v2v-serve`` serves for the same settings.

    Raises:
        StoreError: ``videos`` is a local path but not a folder, or the store cannot be reached
            or listed (naming the URL).
        disk_cache.CacheDirError: a cache that is on cannot be kept in ``cache_dir`` (naming it).
    """
    start = start_source(config or ServeConfig(), videos)
    cfg, source, caches = start.config, start.source, start.caches
    for rel, reason in start.rejected:
        log.info("ignored %s: %s", source.where_ignored(rel), reason)
    windows, skipped = {}, {}
    for rel, (_, reason) in start.skipped.items():
        skipped[rel] = reason
        log.warning("skipped %s: %s (known from the corpus index: not opened)", source.where(rel), reason)
    for rel in start.served:
        n, reason = count_windows(cfg, source, rel, caches)
        if reason:
            skipped[rel] = reason
            log.warning("skipped %s: %s", source.where(rel), reason)
        else:
            windows[rel] = n
    # a brace pattern stays whole: the actors rebuild the source from it (its shards, its manifest)
    return RayCorpus(str(videos) if source.names else source.root, windows, skipped,
                     cfg.recipe.crops_per_window)


def epoch_descriptors(corpus: RayCorpus, epoch: int, exclude: Iterable[str] = (), ranks: int = 1,
                      crops_per_window: int = 1, shuffle_seed: Optional[int] = None) -> List[dict]:
    """The epoch's work, one descriptor per video, padded to a multiple of ``ranks`` rows.

    Each descriptor is ``{"video": rel, "epoch": epoch, "entries": JSON [[sample_id, padding],
    ...]}`` in window order; the videos in the corpus's order, or with ``shuffle_seed`` in
    ``v2v_wire.plan.video_order(videos, shuffle_seed, epoch)``, the production order of
    ``v2v-serve``'s plan. Ids in ``exclude`` (already consumed: resume) are left out, and a
    video with none left is not listed, so it is never opened. When the remaining count is not
    a multiple of ``ranks``, the first ids of the epoch are listed again with ``padding`` true
    (made from the same decode pass, no extra decoding) until it is. With ``crops_per_window``
    K > 1 each window lists its K crop ids (``path#k.c``, see ``ids.make_sample_id``).

    Raises:
        ValueError: ``ranks`` < 1.
    """
    if ranks < 1:
        raise ValueError(f"ranks must be >= 1, got {ranks}")
    exclude = set(exclude)
    kpw = crops_per_window
    videos = list(corpus.windows) if shuffle_seed is None else video_order(corpus.windows, shuffle_seed, epoch)
    todo = [(rel, make_sample_id(rel, k, c, kpw)) for rel in videos for k in range(corpus.windows[rel])
            for c in range(kpw)]
    todo = [(rel, sid) for rel, sid in todo if sid not in exclude]
    pad = (-len(todo)) % ranks if todo else 0
    entries: Dict[str, list] = {}
    for rel, sid in todo:
        entries.setdefault(rel, []).append([sid, False])
    for i in range(pad):
        rel, sid = todo[i % len(todo)]
        entries[rel].append([sid, True])
    return [{"video": rel, "epoch": int(epoch), "entries": json.dumps(e)} for rel, e in entries.items()]


def _zeros(recipe: SampleRecipe, outputs: Sequence[str]) -> Dict[str, np.ndarray]:
    """A padding row's arrays: zeros in each column's dtype and layout (``outputs.zeros_row``)."""
    return {k: zeros_row(k, recipe.sequence_length, recipe.num_bins, recipe.crop_size, recipe.flow_dtype) for k in outputs}


def _row_arrays(recipe: SampleRecipe, arrays: Dict[str, np.ndarray], sample_id: str) -> Dict[str, np.ndarray]:
    """A sample's arrays in their column dtypes and layouts (``outputs.row_array``: voxels
    int16, never wrapped; frames uint8 with a channel axis; flow ``recipe.flow_dtype``, as the
    ZeroMQ wire; polarity counts uint8)."""
    if "flow_grid" in arrays:  # a tracked option's grid, made dense as a client makes a worker's (same bits)
        arrays = dict(arrays)
        arrays["flow"] = expand_grids(arrays.pop("flow_grid"), (recipe.crop_size, recipe.crop_size))
    return {name: row_array(name, a, recipe.flow_dtype, sample_id) for name, a in arrays.items()}


class SampleMaker:
    """The ``map_batches`` stage: one Ray actor, one CPU; makes the samples of video descriptors.

    Built once per actor, from only what it uses: the sample recipe, the corpus's source (from
    the driver's ``VideoSource.spec()``) and the host's caches beside it (``HostCaches.spec()``), OpenCV set to one thread, the optical-flow estimator
    (and any compiled kernel sample making loads on first use). Each call takes a batch of
    descriptors (see :func:`epoch_descriptors`) and yields one single-row batch per entry,
    as soon as the sample is made (rows stream; the actor never holds a whole video).

    Args:
        recipe: the sample recipe (``ServeConfig.recipe``; it pickles to the actor).
        source_spec: ``VideoSource.spec()`` of the corpus as the driver opened it (a folder as
            seen from the actor's node, or an object-store URL read with the node's credentials).
        caches_spec: ``HostCaches.spec()`` of the caches ``cfg`` describes (the frame cache, the
            corpus index), at the same path on the actor's node.
        outputs: subset of ``OUTPUTS`` to make.

    """

    def __init__(self, recipe: SampleRecipe, source_spec: dict, caches_spec: dict, outputs: Sequence[str]):
        import cv2

        cv2.setNumThreads(1)
        self.recipe = recipe
        self.source = source_from_spec(source_spec)
        self.caches = HostCaches.from_spec(caches_spec)
        self.outputs = tuple(outputs)
        self.flow = FlowEstimator(self.recipe.flow_preset) if "flow" in self.outputs else None
        logging.basicConfig(level=logging.INFO, format="v2v-ray %(process)d: %(message)s")

    @staticmethod
    def arguments(cfg: ServeConfig, root: str, outputs: Sequence[str]) -> dict:
        """The constructor's arguments for the corpus at ``root`` served with ``cfg``: what the
        driver hands each actor (plain values that pickle)."""
        return {"recipe": cfg.recipe, "source_spec": source_from_config(cfg, root).spec(),
                "caches_spec": caches_from_config(cfg).spec(), "outputs": tuple(outputs)}

    @classmethod
    def of(cls, cfg: ServeConfig, root: str, outputs: Sequence[str]) -> "SampleMaker":
        """The stage as an actor builds it (:meth:`arguments`), in this process."""
        return cls(**cls.arguments(cfg, root, outputs))

    def __call__(self, batch: Mapping[str, np.ndarray]) -> Iterator[Dict[str, np.ndarray]]:
        for video, epoch, entries in zip(batch["video"], batch["epoch"], batch["entries"]):
            yield from self.video_rows(str(video), int(epoch), json.loads(str(entries)))

    def video_rows(self, video: str, epoch: int, entries: List[list]) -> Iterator[Dict[str, np.ndarray]]:
        """Decode ``video`` once and yield a row for every ``[sample_id, padding]`` entry."""
        wanted: Dict[str, List[bool]] = {}
        for sid, pad in entries:
            wanted.setdefault(sid, []).append(bool(pad))
        kpw = self.recipe.crops_per_window
        keep = {parse_sample_id(sid, kpw) for sid in wanted}
        skip = [key for w in range(self.recipe.max_samples_per_video) for key in window_keys(video, w, kpw)
                if key not in keep]
        # a tracked flow comes as its grid, as from a worker: the sample's statistics are of the same arrays;
        # one file's failure is that file's verdict, never the job's death
        with video_samples(self.recipe, self.source, video, epoch, self.outputs, skip, self.flow, flow_grid=True,
                           caches=self.caches, handler=as_verdict) as run:
            for key, arrays, meta in run:
                sid = key.sample_id(kpw)
                flags = wanted.pop(sid, None)
                if flags is None:
                    continue
                arrays = _row_arrays(self.recipe, arrays, sid)
                params = json.dumps(meta)
                for pad in flags:
                    yield self._row(sid, arrays, params, epoch, pad)
                if not wanted and not run.storing:
                    break  # the rest of the video is not read; a pass storing it into the frame cache ends whole
        if wanted:  # windows the file did not give: a verdict, and padding rows in their place
            found = run.record()
            error = found.reason(self.recipe.windows) or f"{found.frames} frames decoded, fewer than its packets promised"
            log.warning("skipped %s: %s", self.source.where(video), error)
            zeros = _zeros(self.recipe, self.outputs)
            for sid, flags in wanted.items():
                for _ in flags:
                    yield self._row(sid, zeros, json.dumps({"sample_id": sid, "skipped": error}), epoch, True)

    @staticmethod
    def _row(sid: str, arrays: Dict[str, np.ndarray], params: str, epoch: int, pad: bool) -> Dict[str, np.ndarray]:
        row = {"sample_id": np.array([sid], dtype=object), "params": np.array([params], dtype=object),
               "epoch": np.array([epoch], dtype=np.int64), "padding": np.array([pad])}
        row.update({k: a[None] for k, a in arrays.items()})
        return row


def v2v_dataset(
    videos: Union[str, Path, RayCorpus],
    config: Optional[ServeConfig] = None,
    *,
    epoch: Union[int, Sequence[int]] = 0,
    seed: Optional[int] = None,
    outputs: Sequence[str] = DEFAULT_OUTPUTS,
    exclude: Union[Iterable[str], Mapping[int, Iterable[str]]] = (),
    ranks: int = 1,
    concurrency: Union[int, Tuple[int, int], None] = None,
    resource: Optional[str] = None,
    maker: type = SampleMaker,
):
    """A ``ray.data.Dataset`` of V2V samples, one row per sample (columns: module docstring).

    Args:
        videos: corpus folder, or a :class:`RayCorpus` from :func:`scan_corpus_windows` (saves
            the packet count on every call).
        config: sample layout (``ServeConfig``; defaults: the paper's WebVid recipe).
        epoch: an epoch, or several (their rows follow each other; each is padded on its own).
        seed: overrides ``config.seed``; content depends only on (seed, epoch, sample_id).
            Each epoch lists the videos in the
            order ``v2v-serve`` hands them out in (drawn from (seed, epoch)); mix rows across
            videos as its shuffle buffer does with ``iter_batches(local_shuffle_buffer_size=
            config.shuffle_buffer)`` (``trainer.ray_train`` does).
        outputs: columns to make, from ``OUTPUTS`` (default ``DEFAULT_OUTPUTS``; ``polarity_counts``
            is opt-in); others are not computed.
        exclude: sample ids already consumed (of ``epoch``; a mapping epoch -> ids for several
            epochs): never decoded into rows.
        ranks: pad each epoch to a multiple of this row count (``padding`` true on the repeats)
            so ``streaming_split(ranks, equal=True)`` drops nothing.
        concurrency: actors of the map stage (an int, or (min, max) to autoscale); default:
            the CPUs of the cluster.
        resource: a custom resource name each actor needs 1 of (e.g. "v2v_cpu"), so that the
            stage runs only on nodes that declare it (keeps it off GPU nodes).
        maker: the stage's class (a :class:`SampleMaker` subclass, for fault benches).

    Raises:
        ValueError: an unknown output. ImportError: ray is not installed (``pip install
        'v2v[ray]'``).
    """
    try:
        import ray.data
    except ImportError as e:  # pragma: no cover - depends on the extra
        raise ImportError("v2v_dataset needs Ray Data: pip install 'v2v[ray]'") from e
    cfg = resolve_config(config or ServeConfig())  # the actors keep their caches where the scan did
    if seed is not None:
        cfg = ServeConfig.from_dict({**cfg.to_dict(), "seed": int(seed)}, source="ray config")
    outputs = check_outputs(outputs)
    missing = [o for o in outputs if o not in cfg.outputs]
    if missing:  # e.g. polarity_counts under refinement or non-idealities (ServeConfig.validate)
        raise ValueError(f"outputs {missing} are not made under this recipe; it makes {list(cfg.outputs)}")
    corpus = videos if isinstance(videos, RayCorpus) else scan_corpus_windows(videos, cfg)
    epochs = [int(epoch)] if isinstance(epoch, (int, np.integer)) else [int(e) for e in epoch]
    if isinstance(exclude, Mapping):
        excl = {int(e): set(v) for e, v in exclude.items()}
    else:
        excl = {epochs[0]: set(exclude)} if epochs else {}
    shuffle_seed = cfg.seed
    items = [d for e in epochs
             for d in epoch_descriptors(corpus, e, excl.get(e, ()), ranks, cfg.crops_per_window, shuffle_seed)]
    if not items:
        log.warning("no samples to make in %s for epoch(s) %s", corpus.root, epochs)
        return ray.data.from_items([{"video": "", "epoch": 0, "entries": "[]"}]).limit(0)
    ds = ray.data.from_items(items, override_num_blocks=len(items))
    if concurrency is None:
        if not ray.is_initialized():
            ray.init()  # what Ray Data would do on first use; we need the CPU count now
        concurrency = max(1, min(len(items), int(ray.cluster_resources().get("CPU", 1))))
    pool = (ray.data.ActorPoolStrategy(min_size=concurrency[0], max_size=concurrency[1])
            if isinstance(concurrency, tuple) else ray.data.ActorPoolStrategy(size=int(concurrency)))
    remote = {"resources": {resource: 1}} if resource else {}
    return ds.map_batches(
        maker, batch_size=1, batch_format="numpy", num_cpus=1, compute=pool,
        fn_constructor_kwargs=SampleMaker.arguments(cfg, corpus.root, outputs),
        **remote,
    )

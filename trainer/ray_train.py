"""``v2v-train --engine ray``: the same training steps, fed by a Ray Data pipeline, in Ray Train.

The driver lists the corpus (``v2v_server.ray_data.scan_corpus_windows``), builds the epochs' dataset
(``v2v_server.ray_data.v2v_dataset``) padded to a multiple of the rank count, and runs a
``TorchTrainer`` whose ranks each read ``get_dataset_shard("train").iter_torch_batches(...)``
(Ray Train splits the stream with ``streaming_split(n, equal=True)``; the padding makes it drop
nothing). Batches keep their wire dtypes (int16 voxels, uint8 frames, float16 flow) in pinned
host memory and become float32 on the device (``trainer.data.batch_to_device``).

Exactly once per epoch:

* padding rows (``padding`` true) are left out of the loss (``trainer.data.drop_padding``);
* gradients are averaged over the ranks weighted by each rank's real sample count
  (:class:`SampleWeightedAllReduce`), so a rank whose batch is all padding still joins the
  all-reduce (no DDP hang) and adds nothing;
* the ids each rank trained on are gathered into every checkpoint (``stream_state``:
  ``{"engine": "ray", "consumed": {epoch: [ids]}, "epochs_done": [...]}``); a restarted run
  (``--resume``, or the driver's own retry after a failed run, ``--max-failures``) builds its
  dataset without them. Samples trained after the last checkpoint are trained again after a
  failure, as are the model's updates from them: the model never sees a sample twice.

Checkpoints and logs are written by rank 0 to ``--out`` (shared storage on a multi-node
cluster): ``train_log.csv``, ``checkpoint_NNNNNNN.pt``, ``checkpoint_last.pt``, ``summary.json``,
TensorBoard event files under the tags of the stream engine (``trainer/tensorboard_log.py``; the
``recipe`` text is the serve config's sample recipe).
"""
from __future__ import annotations

import argparse
import dataclasses
import logging
import tempfile
import warnings
from collections import defaultdict
from pathlib import Path
from typing import Dict, Iterable, Optional

import numpy as np
import torch

from v2v_server.ops.config import ServeConfig
from v2v_wire.outputs import column_outputs
from v2v_server.settings import add_flags, flag_values

from .core import Trainer
from .data import drop_padding
from .loop import RunHooks, Schedule, train_loop
from .tasks import stream_outputs

__all__ = ["add_ray_arguments", "run_ray", "RayTrainer", "SampleWeightedAllReduce", "load_ray_state"]

log = logging.getLogger("trainer.ray")


def add_ray_arguments(p: argparse.ArgumentParser) -> None:
    """The ``--engine ray`` options of ``v2v-train``."""
    g = p.add_argument_group("Ray engine (--engine ray; needs pip install 'v2v[ray]')")
    g.add_argument("--serve-config", help="v2v-serve YAML config: the sample recipe and corpus (default: v2v-serve's "
                                          "defaults); the flags below override its keys")
    # the corpus and batch size are v2v-serve's keys: the same flags, from its config model
    add_flags(g, ServeConfig, only=("videos", "batch_size"))
    g.add_argument("--epochs", type=int, default=1, help="epochs the run trains (default 1; max_steps may end it "
                                                         "first)")
    g.add_argument("--num-workers", type=int, default=1, help="Ray Train ranks (default 1)")
    g.add_argument("--use-gpu", action="store_true", help="one GPU per rank")
    g.add_argument("--cpus-per-worker", type=float, default=1.0, help="CPUs reserved per rank (default 1)")
    g.add_argument("--address", help="Ray cluster address (ray://HOST:10001 or auto); default: a local Ray")
    g.add_argument("--data-workers", type=int, help="actors of the V2V map stage (default: the free CPUs)")
    g.add_argument("--data-resource", help="custom resource each V2V actor needs 1 of (keeps it off GPU nodes)")
    g.add_argument("--max-failures", type=int, default=0,
                   help="times a failed run is restarted from its last checkpoint (default 0)")


def v2v_collate(pin: bool):
    """A ``ray.data.collate_fn.NumpyBatchCollateFn`` doing :class:`V2VCollate`'s work."""
    from ray.data.collate_fn import NumpyBatchCollateFn

    class _Collate(V2VCollate, NumpyBatchCollateFn):
        pass

    return _Collate(pin)


class V2VCollate:
    """Ray Data numpy batch -> the stream batch contract of ``trainer.data``: the output
    columns (``voxels``, ``frames``, ``flow``, ``polarity_counts``) as tensors in their column dtypes (pinned when CUDA is present, so the
    host -> device copy is asynchronous), ``padding`` bool (B,), ``sample_ids`` and
    ``params`` lists of str, ``epochs`` list of int."""

    def __init__(self, pin: bool):
        self.pin = bool(pin)

    def __call__(self, batch: Dict[str, np.ndarray]) -> dict:
        out = {}
        for k in column_outputs(batch):  # the output columns (``v2v_wire.outputs``), in wire order
            with warnings.catch_warnings():  # Ray's zero-copy arrays are read-only; nothing writes them
                warnings.simplefilter("ignore", UserWarning)
                t = torch.from_numpy(np.ascontiguousarray(batch[k]))
            out[k] = t.pin_memory() if self.pin else t
        out["padding"] = torch.from_numpy(np.asarray(batch["padding"], dtype=bool))
        out["sample_ids"] = [str(s) for s in batch["sample_id"]]
        out["params"] = [str(s) for s in batch["params"]]
        out["epochs"] = [int(e) for e in batch["epoch"]]
        out["epoch"] = out["epochs"][0] if out["epochs"] else -1
        return out


class SampleWeightedAllReduce:
    """An optimiser wrapper for several ranks: before each ``step()`` the ranks' gradients are
    summed weighted by ``samples`` (this rank's real samples in the step, an int) and divided by
    the total, the gradient of the mean loss over all real samples of the step (DDP averages per
    rank instead, which would over-weight a rank with padding). A rank with no real sample
    still joins the all-reduce (gradient zero). When no rank has a sample, nothing steps.

    Each reduced gradient is written back with its parameter's strides (a channels-last weight
    gets a channels-last gradient): the fused optimisers of ``speed: fast`` update the gradient's
    memory element by element with the parameter's, so a contiguous gradient of a channels-last
    weight would update the wrong elements (on the CPU silently; CUDA raises).

    The total sample count stays on the device: with a fused optimiser (``fused=True``, what
    ``speed: fast`` selects on CUDA and the CPU) an empty step is skipped by the kernel itself
    (its ``found_inf`` input, as ``torch.amp.GradScaler`` skips a step), so ``step()`` never waits
    for the device. Other optimisers (the per-parameter loop of ``speed: eager``, ``foreach``)
    read the total once per step to skip an empty step.

    Everything else (``zero_grad``, ``state_dict``, ``param_groups``) is the wrapped optimiser's.

    Args:
        optimizer: the optimiser over (a superset of) ``params``.
        params: the parameters whose gradients are reduced (those with ``requires_grad``);
            float parameters on one device, the same ones in the same order on every rank.

    Call ``step()`` on every rank at the same point (``torch.distributed`` must be initialised).
    """

    def __init__(self, optimizer: torch.optim.Optimizer, params: Iterable[torch.nn.Parameter]):
        self.optimizer = optimizer
        self.params = [p for p in params if p.requires_grad]
        self.samples = 0
        self.fused = any(g.get("fused") for g in optimizer.param_groups)

    def __getattr__(self, name):
        return getattr(self.optimizer, name)

    def step(self):
        import torch.distributed as dist

        dev = self.params[0].device
        grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in self.params]
        # flatten() reads each gradient in logical (N, C, H, W) order whatever its strides: the
        # same order on every rank, undone by view_as below
        flat = torch.cat([g.detach().flatten().float() for g in grads] + [torch.ones(1, device=dev)])
        flat.mul_(float(self.samples))
        dist.all_reduce(flat)
        total = flat[-1]
        # every gradient is zero when the total is (each rank multiplied by its own count, 0)
        flat = flat[:-1].div_(total.clamp(min=1.0))
        o = 0
        for p, g in zip(self.params, grads):
            n = p.numel()
            v = flat[o:o + n].view_as(p)
            o += n
            if v.stride() == p.stride() and v.dtype == p.dtype:
                p.grad = v  # already in p's layout (NCHW, float32): a view, no copy
                continue
            if p.grad is None or g.stride() != p.stride() or g.dtype != p.dtype:
                g = torch.empty_like(p)  # preserve_format: p's strides (channels-last stays so)
            g.copy_(v)  # copy_ maps logical indices, whatever the strides
            p.grad = g
        if self.fused:
            # the fused kernel skips the update (parameters, moments, step counts) when
            # found_inf is non-zero: no host read of the total
            self.optimizer.found_inf = (total == 0).float()
            try:
                self.optimizer.step()
            finally:
                del self.optimizer.found_inf
            return
        if float(total) == 0:
            return
        self.optimizer.step()


class RayTrainer(Trainer):
    """:class:`trainer.core.Trainer` on one Ray Train rank: the same steps, plus the
    padding-only step a rank must still take so all ranks stay in step."""

    def train_step(self, batch: dict, sync: bool = True) -> dict:
        batch, n = drop_padding(batch)  # Trainer.train_step finds no padding left: subset once
        if isinstance(self.optimizer, SampleWeightedAllReduce):
            self.optimizer.samples = n
            if n == 0:  # nothing to learn here, but the other ranks wait for our gradient
                self.optimizer.zero_grad(set_to_none=True)
                self.optimizer.step()
                self.step += 1
                return {"loss": float("nan"), "samples": 0}
        return super().train_step(batch, sync)


class _State:
    """What ``Trainer.checkpoint`` stores as ``stream_state``."""

    def __init__(self, sd: dict):
        self.sd = sd

    def state_dict(self) -> dict:
        return self.sd


def load_ray_state(path: Optional[str]) -> dict:
    """The ``stream_state`` of a ``--engine ray`` checkpoint (empty state without one).

    Raises:
        ValueError: the checkpoint comes from another engine (a ``v2v-serve`` stream position
            cannot say which samples a Ray run consumed).
    """
    empty = {"engine": "ray", "consumed": {}, "epochs_done": []}
    if not path:
        return empty
    sd = torch.load(path, map_location="cpu", weights_only=False).get("stream_state")
    if sd is None:
        return empty
    if sd.get("engine") != "ray":
        raise ValueError(f"checkpoint {path} holds a v2v-serve stream position, not a Ray run's consumed ids")
    return {"engine": "ray", "consumed": {int(e): list(v) for e, v in sd["consumed"].items()},
            "epochs_done": [int(e) for e in sd["epochs_done"]]}


def _gather_state(consumed: Dict[int, set], prev: dict, epoch_sizes: Dict[int, int], world: int) -> dict:
    """Consumed ids of every rank (collective: all ranks call it at the same step)."""
    mine = {e: sorted(v) for e, v in consumed.items()}
    parts = [mine]
    if world > 1:
        import torch.distributed as dist

        parts = [None] * world
        dist.all_gather_object(parts, mine)
    merged: Dict[int, set] = defaultdict(set)
    for e, ids in prev["consumed"].items():
        merged[int(e)].update(ids)
    for part in parts:
        for e, ids in part.items():
            merged[int(e)].update(ids)
    done = set(prev["epochs_done"])
    for e, ids in list(merged.items()):
        if len(ids) >= epoch_sizes.get(e, epoch_sizes.get(str(e), 1 << 62)):
            done.add(e)
            del merged[e]
    return {"engine": "ray", "consumed": {e: sorted(v) for e, v in sorted(merged.items())},
            "epochs_done": sorted(done)}


def _train_loop(config: dict) -> None:
    """The per-rank loop (runs inside a Ray Train worker): ``trainer.loop.train_loop`` over this
    rank's shard, recording the ids it trains on for the checkpoints."""
    import ray.train
    import ray.train.torch

    ctx = ray.train.get_context()
    rank, world = ctx.get_world_rank(), ctx.get_world_size()
    logging.basicConfig(level=logging.INFO, format=f"%(asctime)s rank{rank} %(name)s: %(message)s")
    torch.set_num_threads(max(1, int(config["cpus_per_worker"])))
    cfg = config["cfg"]
    out = Path(config["out"])
    device = ray.train.torch.get_device() if config["use_gpu"] else torch.device("cpu")
    trainer = RayTrainer(cfg, str(out) if rank == 0 else tempfile.mkdtemp(prefix=f"v2v-rank{rank}-"), device)
    if config["resume"]:
        trainer.load_checkpoint(config["resume"])
    if world > 1:
        import torch.distributed as dist

        for t in trainer.model.state_dict().values():  # identical replicas, whatever each rank loaded
            dist.broadcast(t, 0)
        trainer.optimizer = SampleWeightedAllReduce(trainer.optimizer, trainer.model.parameters())
    prev = config["state"]
    epoch_sizes = {int(e): int(n) for e, n in config["epoch_sizes"].items()}
    consumed: Dict[int, set] = defaultdict(set)
    samples = [0]
    batches = ray.train.get_dataset_shard("train").iter_torch_batches(
        batch_size=int(config["batch_size"]), collate_fn=v2v_collate(device.type == "cuda"), prefetch_batches=2,
        # the server's shuffle buffer: rows of several videos in every batch
        local_shuffle_buffer_size=config["shuffle_buffer"], local_shuffle_seed=config["shuffle_seed"])

    def on_batch(batch: dict, stats: dict) -> None:
        for sid, e, pad in zip(batch["sample_ids"], batch["epochs"], batch["padding"].tolist()):
            if not pad:
                consumed[e].add(sid)
        samples[0] += stats.get("samples", 0)

    def save() -> None:  # collective: every rank calls it at the same step
        sd = _gather_state(consumed, prev, epoch_sizes, world)
        if rank == 0:
            trainer.save_checkpoint(_State(sd))
        ray.train.report({"step": trainer.step, "epochs_done": sd["epochs_done"]})

    def summary_extra() -> dict:  # collective
        counts = [samples[0]]
        if world > 1:
            import torch.distributed as dist

            counts = [None] * world
            dist.all_gather_object(counts, samples[0])
        return {"engine": "ray", "ranks": world, "samples": int(sum(counts))}

    lg = cfg["log"]
    train_loop(trainer, batches, int(config["max_steps"]),
               Schedule(int(lg["image_every"]), int(lg["checkpoint_every"]), progress=False,
                        log_every=int(lg.get("every", 10)), tensorboard=bool(lg.get("tensorboard", True))), save,
               RunHooks(on_batch=on_batch, files=rank == 0, csv_extra=("samples",), summary_extra=summary_extra,
                        final_checkpoint="always", recipe=lambda: config.get("recipe")))


def _torch_trainer(cfg: dict, args: argparse.Namespace, out: Path, resume, state: dict, epoch_sizes: dict,
                   batch_size: int, ds, scfg):
    """The Ray Train ``TorchTrainer`` of one attempt: ``args.num_workers`` ranks running
    ``_train_loop`` on the Ray dataset ``ds`` from ``resume`` / ``state``, with no restart of
    its own (``run_ray`` restarts from the last checkpoint). ``scfg`` (``ServeConfig``): its
    ``shuffle`` and ``shuffle_buffer`` size each rank's local shuffle buffer, as ``v2v-serve``'s."""
    from ray.train import FailureConfig, RunConfig, ScalingConfig
    from ray.train.torch import TorchTrainer

    loop_cfg = {"cfg": cfg, "out": str(out.resolve()), "resume": resume, "state": state,
                "max_steps": int(cfg["max_steps"]), "batch_size": batch_size, "epoch_sizes": epoch_sizes,
                "use_gpu": bool(args.use_gpu), "cpus_per_worker": args.cpus_per_worker,
                "shuffle_buffer": scfg.shuffle_buffer, "shuffle_seed": scfg.seed,
                # TensorBoard's recipe text (trainer.tensorboard_log)
                "recipe": {"fingerprint": scfg.recipe.fingerprint(), **dataclasses.asdict(scfg.recipe)}}
    return TorchTrainer(
        _train_loop, train_loop_config=loop_cfg, datasets={"train": ds},
        scaling_config=ScalingConfig(num_workers=args.num_workers, use_gpu=bool(args.use_gpu),
                                     resources_per_worker={"CPU": args.cpus_per_worker}),
        run_config=RunConfig(name=f"v2v-{cfg['task']}", storage_path=str((out / "ray").resolve()),
                             failure_config=FailureConfig(max_failures=0)),
    )


def run_ray(cfg: dict, args: argparse.Namespace, out: Path) -> int:
    """Driver of ``v2v-train --engine ray``; returns the exit code (2: bad arguments, 1: the run
    failed more than ``--max-failures`` times)."""
    try:
        import ray
        import ray.train.torch  # noqa: F401  (Ray Train, used by _torch_trainer)
    except ImportError:
        log.error("--engine ray needs Ray: pip install 'v2v[ray]'")
        return 2
    from v2v_server.ops.config import load_config as load_serve_config
    from v2v_server.ops.startup import SAMPLE_VIDEOS
    from v2v_server.ray_data import scan_corpus_windows, v2v_dataset

    try:
        scfg = load_serve_config(args.serve_config, flag_values(args, ServeConfig))
    except (ValueError, FileNotFoundError) as e:
        log.error("--serve-config: %s", e)
        return 2
    videos = scfg.videos or str(SAMPLE_VIDEOS)  # as v2v-serve: the bundled clips by default
    batch_size, epochs = scfg.batch_size, args.epochs  # per rank; a run trains whole epochs
    if int(cfg["model"]["num_bins"]) != scfg.num_bins:
        log.error("samples have %d bins, model.num_bins is %s: set one to the other", scfg.num_bins,
                  cfg["model"]["num_bins"])
        return 2
    if args.num_workers < 1:
        log.error("--num-workers must be >= 1")
        return 2
    if epochs < 1:
        log.error("--epochs must be >= 1")
        return 2
    if not ray.is_initialized():
        ray.init(address=args.address)
    data_workers = args.data_workers
    if data_workers is None:  # the CPUs the ranks leave free
        free = ray.cluster_resources().get("CPU", 1) - args.num_workers * args.cpus_per_worker
        data_workers = max(1, int(free))
    try:
        corpus = scan_corpus_windows(videos, scfg)
    except (FileNotFoundError, ValueError, RuntimeError) as e:  # StoreError (a missing folder too), CacheDirError
        log.error("%s", e)
        return 2
    if not corpus.samples_per_epoch:
        log.error("no usable video under %s", videos)
        return 2
    log.info("Ray engine: %d samples per epoch from %d videos (%d skipped), %d rank(s), batch %d per rank, "
             "%d V2V actor(s)", corpus.samples_per_epoch, len(corpus.windows), len(corpus.skipped), args.num_workers,
             batch_size, data_workers)
    failures = 0
    resume = cfg.get("resume")
    while True:
        if resume == "auto":
            resume = str(out / "checkpoint_last.pt") if (out / "checkpoint_last.pt").exists() else None
        state = load_ray_state(resume)
        todo = [e for e in range(epochs) if e not in set(state["epochs_done"])]
        if not todo:
            log.info("all %d epoch(s) already trained", epochs)
            return 0
        ds = v2v_dataset(corpus, scfg, epoch=todo, outputs=stream_outputs(cfg),
                         exclude={e: state["consumed"].get(e, ()) for e in todo}, ranks=args.num_workers,
                         concurrency=data_workers, resource=args.data_resource)
        try:
            _torch_trainer(cfg, args, out, resume, state, {e: corpus.samples_per_epoch for e in todo}, batch_size,
                           ds, scfg).fit()
            return 0
        except Exception as e:  # a rank or the run failed: restart from the last checkpoint, or give up
            failures += 1
            if failures > args.max_failures:
                log.error("Ray Train run failed (%s: %s); %d restart(s) allowed", type(e).__name__, e,
                          args.max_failures)
                return 1
            log.warning("Ray Train run failed (%s: %s); restarting from the last checkpoint (%d of %d)",
                        type(e).__name__, e, failures, args.max_failures)
            resume = "auto"

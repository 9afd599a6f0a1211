"""``V2VStreamDataset`` under Hugging Face Accelerate (docs/launchers.md, "Reading a plan").

``Accelerator.prepare(DataLoader(ds, batch_size=None))`` reads an IterableDataset one of two ways
(``accelerate.data_loader``):

* **dispatch** (the default for an IterableDataset): process 0 iterates the loader, concatenates
  one batch per process along dim 0, broadcasts the result and hands process ``r`` the ``r``-th
  equal slice; a batch may hold only tensors. So the dataset on process 0 yields, for each step,
  the batch of every rank in turn (rank ``r``'s at step ``s``: the one that rank reads per rank),
  each a :class:`PlanDispatchedBatch`: its tensors, and the sample ids, params, epoch, step and
  position of each row packed in a ``sample_meta`` uint8 tensor that every rank's slice decodes.
  Each rank's slice is then the batch it would read itself. The other processes' datasets read
  nothing.
* **per rank** (``dispatch_batches=False``): accelerate wraps the dataset in ``IterableDatasetShard``,
  which needs a loader batch size and keeps 1/N of what it reads: refused (:func:`check_loader`,
  from the dataset's ``set_epoch``, which accelerate calls first) in one line naming
  ``v2v_client.prepare_loader``, which builds accelerate's ``DataLoaderShard`` around the whole
  dataset: each rank reads its own batches.

Resuming (``use_stateful_dataloader=True``): accelerate writes every process's loader state to one
file name. Under dispatch only process 0's state says anything, so a stateful dispatcher is
refused as its pass begins unless ``prepare_loader`` made it (its save hook writes process 0's
state on every process), and so is one with DataLoader workers (accelerate snapshots between the
batches of one step, which the workers yield apart).
"""
from __future__ import annotations

import sys
from typing import List, Optional, Tuple

import msgpack
import torch

__all__ = ["PlanDispatchedBatch", "dispatched", "dispatcher_of", "dispatcher_asking_len", "check_loader",
           "prepare_loader", "unpack_rows"]

#: the key of a dispatched batch's packed rows: uint8 (rows, width), one msgpack
#: ``[sample_id, params, epoch, step, position]`` per row, zero-filled
META = "sample_meta"

#: bytes of a row's packed fields when DataLoader workers pack the batches of one step apart
#: (one width for all; the widest row of a group when one process packs them together)
ROW_WIDTH = 4096
_WIDTH_STEP = 64


class PlanDispatchedBatch(dict):
    """A plan batch as accelerate's dispatcher moves it: only tensors of ``batch_size`` rows (so
    accelerate can concatenate, broadcast, slice and place it; its functions rebuild a mapping
    with its own type); ``batch["sample_ids"]`` and ``["params"]`` (per row), ``["epoch"]``,
    ``["step"]`` and ``["position"]`` (the batch's) are decoded from ``sample_meta`` on access, so
    a training loop reads it as a plain batch; ``padding`` bool (rows,) flags the rows the loss
    must ignore."""

    FIELDS = ("sample_ids", "params", "epoch", "step", "position")

    def __missing__(self, key):
        if key not in self.FIELDS or META not in self:
            raise KeyError(key)
        rows = unpack_rows(dict.__getitem__(self, META))
        i = self.FIELDS.index(key)
        if key in ("sample_ids", "params"):
            return [row[i] for row in rows]
        return rows[0][i] if rows else None

    def get(self, key, default=None):
        try:
            return self[key]
        except KeyError:
            return default


def unpack_rows(meta: torch.Tensor) -> list:
    """The ``[sample_id, params, epoch, step, position]`` of each row of a ``sample_meta`` uint8
    tensor (rows, width), on any device."""
    out = []
    for row in meta.detach().cpu().numpy():
        unpacker = msgpack.Unpacker(raw=False, strict_map_key=False)
        unpacker.feed(row.tobytes())  # the zero fill after the row's object is never read
        out.append(next(unpacker))
    return out


def dispatched(batches: List[dict], workers: int) -> List[PlanDispatchedBatch]:
    """``batches`` (of one step, packed by one process) as :class:`PlanDispatchedBatch` es of one
    ``sample_meta`` width: the widest row's (one process packs every batch of a step), or
    :data:`ROW_WIDTH` with ``workers`` > 1 DataLoader workers (each packs its own).

    Raises:
        RuntimeError: with workers, a row wider than :data:`ROW_WIDTH` (one line).
    """
    packed = [[msgpack.packb([sid, p, int(b["epoch"]), int(b["step"]), b["position"]])
               for sid, p in zip(b["sample_ids"], b["params"])] for b in batches]
    longest = max(len(row) for rows in packed for row in rows)
    if workers > 1 and longest > ROW_WIDTH:
        raise RuntimeError(f"a row's ids and params take {longest} bytes, over the {ROW_WIDTH} that DataLoader "
                           "workers under accelerate's dispatcher pack into: use num_workers=0 under dispatch, or "
                           "dispatch_batches=False with v2v_client.prepare_loader")
    width = ROW_WIDTH if workers > 1 else -(-longest // _WIDTH_STEP) * _WIDTH_STEP
    out = []
    for b, rows in zip(batches, packed):
        d = PlanDispatchedBatch({k: v for k, v in b.items() if isinstance(v, torch.Tensor)})
        meta = torch.zeros((len(rows), width), dtype=torch.uint8)
        for i, row in enumerate(rows):
            meta[i, :len(row)] = torch.frombuffer(bytearray(row), dtype=torch.uint8)
        d[META] = meta
        out.append(d)
    return out


def _loader_of(ds):
    """The accelerate loader iterating ``ds`` now (directly or through ``IterableDatasetShard``),
    or None (accelerate not in use)."""
    if "accelerate.data_loader" not in sys.modules:
        return None
    from accelerate.state import GradientState

    for dl in GradientState().dataloader_references:
        inner = getattr(dl, "dataset", None) if dl is not None else None
        if inner is ds or getattr(inner, "dataset", None) is ds:
            return dl
    return None


def dispatcher_of(ds) -> Optional[Tuple[int, bool]]:
    """``(ranks, stateful)`` of the accelerate dispatcher over several processes iterating ``ds``
    now (registered once its iteration began), else None."""
    dl = _loader_of(ds)
    if dl is None:
        return None
    from accelerate.data_loader import DataLoaderDispatcher

    if isinstance(dl, DataLoaderDispatcher) and dl.dataset is ds and dl.state.num_processes > 1:
        return dl.state.num_processes, bool(getattr(dl, "use_stateful_dataloader", False))
    return None


def dispatcher_asking_len(ds) -> int:
    """The ranks of the accelerate dispatcher whose ``len`` asks ``len(ds)`` (it divides the loader's
    length by them, and process 0 reads every rank's batches), else 1. Found among the frames that
    called ``ds.__len__``."""
    if "accelerate.data_loader" not in sys.modules:
        return 1
    from accelerate.data_loader import DataLoaderDispatcher

    frame = sys._getframe(2)
    for _ in range(6):
        if frame is None:
            break
        me = frame.f_locals.get("self")
        if isinstance(me, DataLoaderDispatcher) and getattr(me, "dataset", None) is ds:
            return max(1, me.state.num_processes)
        frame = frame.f_back
    return 1


def check_loader(ds) -> None:
    """Refuse, on every process, the accelerate loader iterating ``ds`` (called from ``set_epoch``,
    which accelerate's loaders call as a pass begins) when it cannot read the plan exactly once:
    ``IterableDatasetShard`` around it (``dispatch_batches=False``), and under dispatch with
    ``use_stateful_dataloader=True``, a loader not made by ``prepare_loader`` (every process writes
    its state to one file, and only process 0's says anything) or one with DataLoader workers
    (accelerate snapshots between the batches of one step, which the workers yield apart).

    Raises:
        RuntimeError: one line saying what to do instead.
    """
    dl = _loader_of(ds)
    if dl is None:
        return
    if dl.dataset is not ds:
        raise RuntimeError("accelerate's dispatch_batches=False wraps V2VStreamDataset in IterableDatasetShard, which "
                           "needs a loader batch size and keeps 1/N of each rank's batches: build the loader with "
                           "v2v_client.prepare_loader(accelerator, DataLoader(ds, batch_size=None)) instead of "
                           "accelerator.prepare")
    dispatch = dispatcher_of(ds)
    if not dispatch or not dispatch[1]:
        return
    if getattr(dl, "num_workers", 0):
        raise RuntimeError("accelerate's dispatcher with use_stateful_dataloader=True snapshots the loader between "
                           "the batches of one step, which DataLoader workers yield apart: use num_workers=0 under "
                           "dispatch, or dispatch_batches=False with v2v_client.prepare_loader")
    if not getattr(ds, "gathers_state", False):
        raise RuntimeError("accelerate saves one loader state for every process, and under dispatch only process 0 "
                           "reads: build the loader with v2v_client.prepare_loader(accelerator, DataLoader(ds, "
                           "batch_size=None)), whose save hook writes process 0's state on every process")


def _world() -> int:
    dist = torch.distributed
    return dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1


def _share_first(loader):
    """A save-state pre-hook for a plan's loader: process 0's loader state in every process's
    snapshot (under dispatch only process 0 reads; per rank every rank at one step has the same
    state), so every process writes the same file."""
    def hook(models, weights, output_dir) -> None:
        snap = loader.state_dict()
        if _world() == 1 or not isinstance(snap, dict):
            return
        box = [snap if torch.distributed.get_rank() == 0 else None]
        torch.distributed.broadcast_object_list(box, src=0)
        if torch.distributed.get_rank() != 0:
            snap.clear()
            snap.update(box[0])
    return hook


def prepare_loader(accelerator, loader: torch.utils.data.DataLoader):
    """``loader`` (``DataLoader(ds, batch_size=None)`` over a ``V2VStreamDataset``) prepared by
    ``accelerator`` in the mode its ``DataLoaderConfiguration`` names, in place of
    ``accelerator.prepare(loader)``: needed for the per-rank mode (``dispatch_batches=False``),
    where accelerate's own ``prepare`` wraps the dataset in ``IterableDatasetShard``, which keeps
    1/N of each rank's batches; here it is accelerate's ``DataLoaderShard`` around the whole
    dataset, so each rank reads its own slices. Dispatch (the default) is built as accelerate
    builds it. With ``use_stateful_dataloader=True`` it registers a save hook writing process 0's
    loader state on every process (accelerate writes every process's state to one file name). The
    result is registered with the accelerator (``save_state`` / ``load_state`` cover it;
    ``accelerator.prepare`` passes it through).

    A loader this function made for ``accelerator`` is returned as it is (preparing it again
    would register a second loader, whose never-read state ``save_state`` writes first).

    Raises:
        TypeError: the loader does not read a V2VStreamDataset.
        ValueError: the loader batches the plan's batches again (``batch_size`` not None), or
            accelerate prepared it already (``accelerator.prepare``, or ``prepare_loader`` for
            another accelerator).
    """
    from accelerate.data_loader import prepare_data_loader

    made_for = getattr(loader, "_v2v_prepared_by", None)
    if made_for is accelerator:
        return loader
    if made_for is not None or getattr(loader, "_is_accelerate_prepared", False):
        raise ValueError("prepare_loader takes the DataLoader itself, not one accelerate prepared already: "
                         "call prepare_loader(accelerator, DataLoader(ds, batch_size=None)) once and use what it "
                         "returns")
    ds = loader.dataset
    if not callable(getattr(ds, "plan_info", None)):  # a V2VStreamDataset (its module imports this one)
        raise TypeError(f"prepare_loader reads a V2VStreamDataset; this loader reads {type(ds).__name__}")
    if loader.batch_size is not None:
        raise ValueError(f"the loader has batch_size={loader.batch_size}: {type(ds).__name__} yields whole batches, "
                         f"use DataLoader(ds, batch_size=None)")
    dispatch = accelerator.dispatch_batches
    if accelerator.num_processes > 1 and (dispatch is False or (dispatch is None and not accelerator.device_placement)):
        loader = prepare_data_loader(loader, accelerator.device, num_processes=1, process_index=0,
                                     put_on_device=accelerator.device_placement, dispatch_batches=False,
                                     non_blocking=accelerator.non_blocking,
                                     use_stateful_dataloader=accelerator.use_stateful_dataloader)
        loader._is_accelerate_prepared = True  # accelerate's own mark: prepare_data_loader registers it as it is
    loader = accelerator.prepare_data_loader(loader)
    if accelerator.use_stateful_dataloader:
        accelerator.register_save_state_pre_hook(_share_first(loader))
        ds.gathers_state = True
    loader._v2v_prepared_by = accelerator
    return loader

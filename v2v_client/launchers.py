"""``V2VPushDataset`` under Hugging Face Accelerate, which wraps the DataLoader it is given.

``Accelerator.prepare`` reads an IterableDataset in one of two ways (``accelerate.data_loader``):

* **dispatch** (``DataLoaderConfiguration(dispatch_batches=None)``, the default, or ``True``):
  process 0 iterates the loader, concatenates one batch per process along dim 0, broadcasts the
  result and hands process ``r`` the ``r``-th equal slice. A batch may hold only tensors, and the
  slices are equal row counts (``split_batches=True`` needs a loader batch size: accelerate refuses
  ``batch_size=None`` itself). So process 0 reads the
  whole stream as its one consumer (world size 1) and hands on :class:`DispatchedBatch` es:
  groups of N batches of one epoch padded to one row count (padding rows flagged), a group that
  the end of its epoch or of the stream cuts short completed with padding batches, the ids,
  params, epoch and batch id of each row packed in a ``sample_meta`` uint8 tensor that every
  rank's slice decodes. Each rank's slice is then exactly one of the stream's batches, and each
  step's slices share one epoch.
* **per rank** (``dispatch_batches=False``): accelerate wraps the dataset in ``IterableDatasetShard``,
  which needs a batch size and keeps 1/N of what it reads: with each rank reading its own share of
  the stream that would drop samples, so :func:`check_whole` (the dataset's ``set_epoch``, which
  accelerate calls first) refuses it in one line naming :func:`prepare_loader`. That builds
  accelerate's own ``DataLoaderShard`` around the unwrapped loader: device placement, ``set_epoch``,
  ``end_of_dataloader`` and its state snapshots stay accelerate's.

Resuming (``use_stateful_dataloader=True``, ``save_state`` / ``load_state``): accelerate saves the
loader state of every process under one file name (``dl_state_dict.bin``), so the last process to
write wins. :func:`prepare_loader` registers a save hook that gathers every rank's dataset state into
each rank's snapshot (``{"v2v_ranks": [state of rank 0, ...]}``): every process writes the same file
and each rank loads its own part (:func:`rank_part`). A stateful loader under more than one process
not made by :func:`prepare_loader` is refused at its first batch, as is ``skip_first_batches``
(it would throw away batches the server counts as delivered).

:func:`prepare_loader` takes a ``V2VStreamDataset``'s loader too: how a plan reads under accelerate is
``plan_accelerate``'s.

Reading ahead: accelerate's loaders take a batch (per rank) or a group (dispatch) before the loop
has received the one before. When the loop leaves or the stream fails, those batches go back to
the dataset, which yields them first next time (:class:`ReadAhead`).

Lightning's ``Trainer`` reads through ``_PrefetchDataFetcher`` (``lightning.pytorch.loops.fetchers``),
which takes ``prefetch_batches`` (1) batches ahead of the loop when the loader has no length (a
stream has none), and saves a stateful loader's ``state_dict()`` (torchdata's
``StatefulDataLoader``, :class:`~v2v_client.StreamLoader`) whenever it checkpoints: the batches
taken ahead are left out of that state until the loop receives them (:func:`lightning_ahead`).
"""
from __future__ import annotations

import sys
from typing import Callable, Iterator, List, Optional, Tuple

import msgpack
import torch

from .endpoint import padding_copy
from .resume import ResumeState

__all__ = ["DispatchedBatch", "ReadAhead", "prepare_loader", "check_whole", "adapt", "rank_part", "pack_rows",
           "unpack_rows", "unseen", "lightning_ahead"]

#: the key of a dispatched batch's packed rows: uint8 (rows, width), one msgpack
#: ``[sample_id, params, epoch, batch_id]`` per row, zero-filled
META = "sample_meta"
#: the key of the per-rank states :func:`prepare_loader`'s save hook writes
RANKS = "v2v_ranks"
#: torchdata StatefulDataLoader's key of its dataset's ``state_dict()`` in its own state
DATASET_STATE = "dataset_state"
_WIDTH_STEP = 64  # the packed rows' width is a multiple of this (bytes)


class DispatchedBatch(dict):
    """A batch as accelerate's dispatch mode moves it: only tensors of one leading size (rows),
    so accelerate can concatenate, broadcast, slice and place it (its functions rebuild a mapping
    with its own type). ``batch["sample_ids"]`` (list of str), ``batch["params"]`` (list of dicts),
    ``batch["epoch"]`` and ``batch["batch_id"]`` (int) are decoded from ``sample_meta`` on access,
    so a training loop reads it as it reads a plain batch; ``padding`` bool (rows,) flags the rows
    the loss must ignore."""

    FIELDS = ("sample_ids", "params", "epoch", "batch_id")

    def __missing__(self, key):
        if key not in self.FIELDS or META not in self:
            raise KeyError(key)
        rows = unpack_rows(dict.__getitem__(self, META))
        if key in ("sample_ids", "params"):
            return [r[self.FIELDS.index(key)] for r in rows]
        return int(rows[0][self.FIELDS.index(key)]) if rows else -1

    def get(self, key, default=None):
        try:
            return self[key]
        except KeyError:
            return default


def pack_rows(batch: dict) -> List[bytes]:
    """One msgpack ``[sample_id, params, epoch, batch_id]`` per sample of a stream batch."""
    return [msgpack.packb([sid, p, int(batch["epoch"]), int(batch["batch_id"])])
            for sid, p in zip(batch["sample_ids"], batch["params"])]


def unpack_rows(meta: torch.Tensor) -> list:
    """The ``[sample_id, params, epoch, batch_id]`` of each row of a ``sample_meta`` uint8 tensor
    (rows, width), on any device."""
    out = []
    for row in meta.detach().cpu().numpy():
        unpacker = msgpack.Unpacker(raw=False, strict_map_key=False)
        unpacker.feed(row.tobytes())  # the zero fill after the row's object is never read
        out.append(next(unpacker))
    return out


def dispatched(batch: dict, packed: List[bytes], rows: int, width: int) -> DispatchedBatch:
    """``batch`` as a :class:`DispatchedBatch` of ``rows`` rows (the rows past its own repeat its
    first sample, flagged in ``padding``) with its packed rows (``pack_rows``) in ``width`` bytes.

    Raises:
        TypeError: the batch holds something that is neither a tensor nor one of ``FIELDS``.
    """
    n = len(packed)
    fill = [0] * (rows - n)
    out = DispatchedBatch()
    for key, value in batch.items():
        if isinstance(value, torch.Tensor):
            out[key] = torch.cat([value, value[fill]]) if fill else value
        elif key not in DispatchedBatch.FIELDS:
            raise TypeError(f"batch entry {key!r} ({type(value).__name__}) cannot be dispatched by accelerate")
    out["padding"] = torch.cat([batch["padding"], torch.ones(len(fill), dtype=torch.bool)])
    meta = torch.zeros((rows, width), dtype=torch.uint8)
    for i, row in enumerate(packed + [packed[0]] * len(fill)):
        meta[i, :len(row)] = torch.frombuffer(bytearray(row), dtype=torch.uint8)
    out[META] = meta
    return out


def unseen(state: dict, batches: List[dict]) -> dict:
    """``state`` (a ``V2VPushDataset.state_dict()``, one server's or a fan-in's) without
    ``batches``, batches the dataset yielded that the training loop has not received: their
    samples (``padding`` False) are not handed on (``ResumeState.not_handed_on``), so a resume
    from it has them sent again (the server takes a hello's state as the truth). The state given
    is not changed.

    Raises:
        ValueError: a state of another format.
    """
    record = ResumeState()
    record.load(state)
    for b in batches:
        ids = [sid for sid, pad in zip(b["sample_ids"], b["padding"].tolist()) if not pad]
        record.not_handed_on(int(b["epoch"]), ids, endpoint=b.get("endpoint"))
    return record.state()


class ReadAhead:
    """What the loaders that read ahead of the training loop (accelerate's, Lightning's) make a
    ``V2VPushDataset``'s ``state_dict()`` say (:meth:`state`): ``held_state``, the state the
    dispatcher's snapshots must see while it hands out a group (:func:`_dispatch`); ``pending``,
    batches a Lightning fetcher took that its loop has not received yet; and the batches held
    over, yielded but never received by a loop that left or saw the stream fail: the dataset's
    next iteration yields those first (:meth:`replay`), before anything from the server, and its
    state leaves them out until then."""

    def __init__(self):
        self.held_state: Optional[dict] = None
        self.pending: List[dict] = []  # taken ahead of a Lightning loop, not received yet
        self.batches: List[dict] = []  # held over, oldest first
        self.before: Optional[dict] = None  # the dataset's state without them, when known

    def hold_over(self, batches: List[dict], before: Optional[dict] = None) -> None:
        """Hold ``batches`` over (they were pulled after those held already, if any)."""
        self.batches = list(batches) + self.batches
        self.before = before

    def replay(self, inner: Iterator[dict]) -> Iterator[dict]:
        """The batches held over, then ``inner``'s."""
        while self.batches:
            self.before = None
            yield self.batches.pop(0)
        yield from inner

    def state(self, live: Callable[[], dict]) -> dict:
        """The dataset's state: ``held_state`` when set, else ``live()`` (the stream's, which
        counts the batches held over) without the batches held over."""
        if self.held_state is not None:
            return self.held_state
        if not self.batches:
            state = live()
        else:
            state = self.before if self.before is not None else unseen(live(), self.batches)
        return unseen(state, self.pending) if self.pending else state

    def clear(self) -> None:
        """Forget the batches held over or pending (a loaded state says what the loop received)."""
        self.batches, self.pending, self.before = [], [], None


def _hold_over(ds, batches: Iterator[dict], unreceived: List[dict], before: Optional[dict] = None) -> None:
    """The loop left (or the stream failed) without receiving ``unreceived``, batches of the
    stream the loader took ahead of it: close the stream, and hold them over for the dataset's
    next iteration (:class:`ReadAhead`; ``before``: its state without them, when known)."""
    if hasattr(batches, "close"):
        batches.close()  # the connection says goodbye now, not when the iterator is collected
    if unreceived:
        ds.read_ahead.hold_over(unreceived, before)


def _read_ahead(ds, batches: Iterator[dict], ahead: int = 1, live: bool = False) -> Iterator[dict]:
    """``batches`` for a loader that reads ``ahead`` batches ahead of its loop (accelerate's
    ``DataLoaderShard`` and one-process ``DataLoaderDispatcher``: 1; Lightning's fetcher,
    :func:`lightning_ahead`): each batch is received by the loop once the loader has taken
    ``ahead`` more (or the stream ends). When the loop leaves (the loader drops this iterator) or
    the stream fails, the ``ahead`` batches yielded last never reached the loop: the dataset
    yields them first when it is iterated again (:class:`ReadAhead`), and its state leaves them
    out meanwhile. ``live``: the loader asks for the state while it holds batches ahead
    (Lightning's checkpoints), so the state leaves those out too (``ReadAhead.pending``);
    accelerate's snapshots are taken before each pull, and hold every batch up to the one the
    loop is about to receive."""
    pending: List[dict] = []  # yielded, not yet received by the loop, oldest first
    try:
        while True:
            try:
                b = next(batches)
            except StopIteration:
                pending = []  # the loader hands what it took on now
                return
            pending = (pending + [b])[-ahead:]
            if live:
                ds.read_ahead.pending = list(pending)
            yield b
    finally:
        if live:
            ds.read_ahead.pending = []
        _hold_over(ds, batches, pending)


#: the modules of Lightning's fetchers (the ``lightning`` package and the older ``pytorch_lightning``)
_FETCHERS = ("lightning.pytorch.loops.fetchers", "pytorch_lightning.loops.fetchers")


def lightning_ahead() -> int:
    """How many batches a Lightning ``Trainer`` reading the caller takes ahead of its loop: its
    ``_PrefetchDataFetcher`` pulls ``prefetch_batches`` (1) ahead when the loader has no length
    (a stream never has), 0 with a length or another fetcher (``training_step(dataloader_iter)``);
    0 without Lightning. Called when the caller's first batch is asked for, from inside the
    fetcher's pull: it finds the fetcher among the frames that called it."""
    kinds = tuple(sys.modules[m]._PrefetchDataFetcher for m in _FETCHERS
                  if hasattr(sys.modules.get(m), "_PrefetchDataFetcher"))
    frame = sys._getframe(1) if kinds else None
    while frame is not None:
        fetcher = frame.f_locals.get("self")
        if isinstance(fetcher, kinds):
            return int(fetcher.prefetch_batches) if fetcher.length is None else 0
        frame = frame.f_back
    return 0


def _dispatch(ds, batches: Iterator[dict], group: int) -> Iterator[DispatchedBatch]:
    """Process 0's stream for accelerate's dispatcher: groups of ``group`` batches of one epoch
    (a group that the end of its epoch or of the stream cuts short is completed with padding
    batches of that epoch, so every rank yields the same number of batches per epoch and each
    step's slices share one epoch), each padded to the group's largest row count.

    State: accelerate snapshots the loader state before each batch it takes, fetches a whole
    group before it hands the previous one to the loop, and its training step holds whole
    groups only. So while a group is handed out, ``ds.read_ahead.held_state`` is the state before it, and
    after its last batch the state after it (without the next epoch's first batch, pulled to
    learn that the epoch ended). When the loop leaves, the group fetched last (and that first
    batch) never reached it: the dataset yields them first when it is iterated again
    (:func:`_hold_over`)."""
    stash: Optional[dict] = None  # the next group's first batch (another epoch's)
    after: Optional[dict] = None  # the state after the group handed out last, with a stash
    unreceived: List[dict] = []  # stream batches pulled that the loop has not received, oldest first
    back_to: Optional[dict] = None  # the state without them
    try:
        while True:
            ds.read_ahead.held_state = None
            before = after if stash is not None else ds.state_dict()
            if not unreceived:
                back_to = before
            pulled, stash, after = ([stash] if stash is not None else []), None, None
            for b in batches:
                unreceived.append(b)
                if pulled and b["epoch"] != pulled[0]["epoch"]:
                    stash = b
                    after = unseen(ds.state_dict(), [stash])
                    break
                pulled.append(b)
                if len(pulled) == group:
                    break
            if not pulled:
                unreceived = []  # the stream ended: the loader hands its last group on now
                return
            epoch = pulled[0]["epoch"]
            members = pulled + [padding_copy(pulled[-1], epoch) for _ in range(group - len(pulled))]
            packed = [pack_rows(b) for b in members]
            rows = max(len(p) for p in packed)
            width = -(-max(len(r) for p in packed for r in p) // _WIDTH_STEP) * _WIDTH_STEP
            for i, (b, p) in enumerate(zip(members, packed)):
                last = i == len(members) - 1
                ds.read_ahead.held_state = after if last else before
                if last:  # the loader hands the previous group on once it holds this one
                    unreceived, back_to = pulled + ([stash] if stash is not None else []), before
                yield dispatched(b, p, rows, width)
    finally:
        ds.read_ahead.held_state = None
        _hold_over(ds, batches, unreceived, back_to)


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


def check_whole(ds) -> None:
    """Refuse accelerate's ``IterableDatasetShard`` around ``ds`` (``dispatch_batches=False``).

    Raises:
        RuntimeError: one line saying what to do instead.
    """
    dl = _loader_of(ds)
    if dl is not None and dl.dataset is not ds:
        raise RuntimeError("accelerate's dispatch_batches=False wraps V2VPushDataset in IterableDatasetShard, "
                           "which keeps 1/N of what each rank's own connection receives: build the loader with "
                           "v2v_client.prepare_loader(accelerator, DataLoader(ds, batch_size=None)) instead of "
                           "accelerator.prepare")


def adapt(ds, batches: Iterator[dict]) -> Iterator[dict]:
    """``ds``'s batches as the loader reading it needs them, decided at the first batch (when
    accelerate has registered its loader): accelerate's dispatcher over several processes gets
    :func:`_dispatch` with ``ds`` read as the only consumer (``ds.read_alone()``); accelerate's
    other loaders, which read one batch ahead, and Lightning's fetcher (:func:`lightning_ahead`)
    :func:`_read_ahead`; anything else gets the batches as they are.

    Raises:
        RuntimeError: (at the first batch) ``skip_first_batches``, or a stateful accelerate loader
            over several processes not made by :func:`prepare_loader`.
    """
    dl = _loader_of(ds)
    if dl is not None:
        if getattr(dl, "skip_batches", 0):
            raise RuntimeError("accelerate's skip_first_batches would throw away batches the v2v server counts as "
                               "delivered: resume with use_stateful_dataloader=True and save_state/load_state")
        from accelerate.data_loader import DataLoaderDispatcher

        processes = dl.state.num_processes if isinstance(dl, DataLoaderDispatcher) else 1
        stateful = getattr(dl, "use_stateful_dataloader", False)
        if stateful and _world() > 1 and not getattr(ds, "gathers_state", False):
            raise RuntimeError("accelerate saves one loader state for every process: build the loader with "
                               "v2v_client.prepare_loader(accelerator, DataLoader(ds, batch_size=None)), whose save "
                               "hook keeps each rank's V2VPushDataset state")
        if processes > 1:
            ds.read_alone()
            yield from _dispatch(ds, batches, processes)
        else:
            yield from _read_ahead(ds, batches)
        return
    ahead = lightning_ahead()
    yield from _read_ahead(ds, batches, ahead, live=True) if ahead else batches


def _world() -> int:
    dist = torch.distributed
    return dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1


def rank_part(state: dict, position: Callable[[], Tuple[int, int]]) -> dict:
    """This rank's part of a state :func:`prepare_loader`'s save hook gathered (``position()``:
    this process's ``(rank, world_size)``, asked only then); any other state as it is.

    Raises:
        ValueError: the state was saved by another number of ranks.
    """
    if isinstance(state, dict) and RANKS in state:
        rank, world = position()
        parts = state[RANKS]
        if len(parts) != world:
            raise ValueError(f"this V2VPushDataset state was saved by {len(parts)} ranks and is loaded by "
                             f"{world}: resume with the world size it was saved with")
        return parts[rank]
    return state


def _gather_states(loader):
    """A save-state pre-hook: every rank's dataset state (from its loader's snapshot) in each rank's snapshot."""
    def hook(models, weights, output_dir) -> None:
        snap = loader.state_dict()
        if not isinstance(snap, dict) or DATASET_STATE not in snap:
            return
        world = _world()
        rank = torch.distributed.get_rank() if world > 1 else 0
        parts: List[Optional[dict]] = [None] * world
        own = rank_part(snap[DATASET_STATE], lambda: (rank, world))
        if world > 1:
            torch.distributed.all_gather_object(parts, own)
        else:
            parts = [own]
        snap[DATASET_STATE] = {RANKS: parts}
    return hook


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
    """``loader`` (``DataLoader(ds, batch_size=None)`` over a ``V2VPushDataset`` or a
    ``V2VStreamDataset``) prepared by ``accelerator`` in the mode its ``DataLoaderConfiguration``
    names, in place of ``accelerator.prepare(loader)``: dispatch (the default) as accelerate builds
    it; per rank (``dispatch_batches=False``) as accelerate's ``DataLoaderShard`` around the whole
    dataset, so each rank reads its own share. With ``use_stateful_dataloader=True`` it registers
    the save hook that makes the saved loader state right for every rank (a stream: every rank's
    dataset state; a plan: process 0's loader state). The result is registered with the accelerator
    (``save_state`` / ``load_state`` cover it; ``accelerator.prepare`` passes it through).

    A loader this function made for ``accelerator`` is returned as it is (preparing it again
    would register a second loader, whose never-read state ``save_state`` writes first).

    Raises:
        TypeError: the loader reads neither a V2VPushDataset nor a V2VStreamDataset.
        ValueError: the loader batches the stream's batches again (``batch_size`` not None), or
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
    plan = callable(getattr(ds, "plan_info", None))  # a V2VStreamDataset (its module imports this one)
    if not plan and not callable(getattr(ds, "read_alone", None)):
        raise TypeError(f"prepare_loader reads a V2VPushDataset or a V2VStreamDataset; this loader reads "
                        f"{type(ds).__name__}")
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
        accelerator.register_save_state_pre_hook(_share_first(loader) if plan else _gather_states(loader))
        ds.gathers_state = True
    loader._v2v_prepared_by = accelerator
    return loader

"""Reading a server that serves by plan (``v2v-serve``'s default delivery, docs/delivery.md) as a torch
dataset: each rank's batch at each step is a fixed slice of the epoch's plan, fetched by position.

The dataset holds no socket and no lock: each process that iterates it (the main process, a
DataLoader worker started by fork, spawn or forkserver) opens its own connection, so it pickles
as plain settings. With ``k`` DataLoader workers, worker ``j`` reads steps ``j, j + k, ...``, and
the DataLoader's round robin yields them in step order.

**Several servers**: ``endpoint`` a list, a comma-separated string, or a ``tcp://NAME:PORT``
whose name resolves to several addresses (a Kubernetes headless Service). Hosts that each serve
the whole corpus are a fleet, read as the one plan a single server serves (``fleet_read``: each
video asked of the host it is routed to; hosts join, leave and straggle while a job reads).
Servers of one shard each (``v2v-serve --shard I/N``) are read as one plan, interleaved
(``v2v_wire.plan_shards``: global position t is shard t mod N's t // N); servers that are not one
sharding of one corpus under one recipe are refused, naming them. The fetch side, free of torch:
``fetch``, ``servers``, ``fleet_read``; this module's state: ``plan_state``.

**Compression** of the rows' arrays: ``"none"``, ``"lz4"`` or ``"zstd"`` (``v2v_wire.codecs``: the
server's workers compress each sample, the reading process decompresses); ``"auto"`` (default):
none to ``ipc://`` and loopback ``tcp://``, zstd to other hosts when both sides have
``zstandard`` (docs/wire.md measures the trade). The batches are the same either way.

Loaders that snapshot a dataset's state (torchdata's ``StatefulDataLoader``, Accelerate's with
``use_stateful_dataloader=True``) read :meth:`V2VStreamDataset.state_dict`: what this process (the
main process, or one DataLoader worker) has yielded, restored in the same worker by
:meth:`V2VStreamDataset.load_state_dict`. In the main process while DataLoader workers read, it
refuses (they read ahead of the loop): the checkpoint is the last batch's ``position``.
``set_epoch`` and ``load_state_dict`` in the main process reach the DataLoader workers' copies
at their next pass, persistent workers included (a block of shared memory made with the dataset).
Under Accelerate's dispatcher the process that reads yields every rank's batch of each step in turn
(``plan_accelerate``).
"""
from __future__ import annotations

import itertools
from typing import Dict, Iterator, Optional, Sequence, Tuple, Union

import torch

from v2v_wire.plan import PlanIdentity, Position, batch_positions, epoch_steps
from v2v_wire.plan_messages import Fetch, PlanInfo, Rows
from v2v_wire.protocol import DEFAULT_OUTPUTS, check_outputs
from v2v_wire.push_names import READER_SETTINGS, reader_settings_problem

from . import plan_accelerate
from .endpoints import load_curve_keys
from .fetch import PlanServerError
from .servers import Servers
from .plan_state import (_LENGTH_UNKNOWN, _Control, _check_layout, _check_reader, _check_settings, _loaded_position,
                         _pending_of, _read_layout, _reader_part, _reading_state, _rows, _start_of)
from .tensors import batch_to_torch

__all__ = ["V2VStreamDataset", "PlanEpochs", "open_stream", "PlanServerError"]


class V2VStreamDataset(torch.utils.data.IterableDataset):
    """One rank's batches of one epoch of the plan served at ``endpoint`` (``v2v-serve``).

    Args:
        endpoint: the server's address (``tcp://host:port``), or several shards' (module docstring).
        batch_size: rows per batch of this rank (>= 1; default: the server's, asked when needed).
        rank, world_size: this rank and the job's ranks (default: ``torch.distributed``'s when
            first needed, if initialised, else 0 and 1).
        outputs: which of ``OUTPUTS`` to read (default ``DEFAULT_OUTPUTS``; the server's workers
            make only the outputs its readers ask for).
        raw: keep the wire dtypes (``tensors.batch_to_torch``).
        prefetch: fetches in flight per process (>= 1).
        retry_s: seconds a fetch may go unanswered before it is asked again (a lost reply, a
            restarted server).
        timeout_s: seconds of silence from the server before :class:`TimeoutError`.
        curve_keys: ``(client_secret_file, server_public_file)`` from ``v2v-keygen`` (CurveZMQ).
        compression: ``"none"``, ``"lz4"``, ``"zstd"`` or ``"auto"`` (module docstring).

    Each item is a dict: the tensors of ``batch_to_torch`` with a leading axis of ``batch_size``,
    ``padding`` (bool (B,): rows that carry no sample, zeros: past the epoch's end or a window the
    file did not give), ``sample_ids`` (None for a row past the end), ``params``, ``epoch``,
    ``step``, ``servers`` ({server endpoint: rows of this batch holding a sample it served}, one
    entry per shard read), and ``position``: the checkpoint after this step
    (``Position.to_dict``), the same on every rank; :meth:`load_state_dict` takes it, at any
    world size and batch size.
    :meth:`state_dict` is what this process has read (the state torchdata's ``StatefulDataLoader``
    snapshots per DataLoader worker).

    Raises:
        ValueError: a bad setting, naming it, or a setting of the push delivery v2v no longer has
            (``credits``, ``shm``, ``reconnect``, ...; one line saying so).
        TypeError: a keyword argument neither reader takes.
    """

    def __init__(self, endpoint: Union[str, Sequence[str]], batch_size: Optional[int] = None, *,
                 rank: Optional[int] = None, world_size: Optional[int] = None,
                 outputs: Sequence[str] = DEFAULT_OUTPUTS, raw: bool = False,
                 prefetch: int = 2, retry_s: float = 10.0, timeout_s: float = 120.0,
                 curve_keys: Optional[Tuple[str, str]] = None, compression: str = "auto", **push_settings):
        super().__init__()
        _refuse_settings(push_settings)
        _check_settings(1 if batch_size is None else batch_size, prefetch, retry_s, timeout_s)
        self._servers = Servers(endpoint, compression)  # a bad endpoint or codec: an error here
        self.curve = load_curve_keys(*curve_keys) if curve_keys else None  # bad key files: an error here
        if rank is not None or world_size is not None:
            _check_layout(0 if rank is None else rank, 1 if world_size is None else world_size)
        self.endpoint, self._batch, self._rank, self._world = endpoint, batch_size, rank, world_size
        self.outputs = check_outputs(outputs, "outputs")
        self.raw, self.prefetch, self.retry_s, self.timeout_s = raw, prefetch, retry_s, timeout_s
        self.epoch, self.start = 0, 0
        self._resume: Optional[dict] = None  # a loaded position, checked once the plan is known
        self._pending: Optional[dict] = None  # a loaded reader state, read by the next __iter__ only
        self._reading: Optional[dict] = None  # what this process's iteration has yielded (state_dict)
        self._upcoming: Optional[dict] = None  # the loaded state an iteration not yet begun took
        self._dispatch: Optional[tuple] = None  # under accelerate's dispatcher: (ranks, stateful), once known
        self.gathers_state = False  # v2v_client.prepare_loader's save hook shares rank 0's loader state
        self._info: Optional[PlanInfo] = None
        # made before any DataLoader worker starts, so that set_epoch and load_state_dict in the
        # main process reach the workers' copies (persistent ones included) at their next pass
        self._control = _Control()
        self._seen = 0  # the control's generation this copy's epoch, start and loaded state are of

    # ------------------------------------------------------------------ layout
    @property
    def batch_size(self) -> int:
        """Rows per batch of this rank: as given, else the server's (asked when first needed;
        ``TimeoutError`` when it does not answer)."""
        return self._batch if self._batch is not None else self.plan_info().stream["batch_size"]

    @property
    def rank(self) -> int:
        """This rank: as given, else ``torch.distributed``'s when initialised (asked when first
        needed, so a dataset built before the process group, as a DataModule's, finds it), else 0."""
        return self._layout()[0]

    @property
    def world_size(self) -> int:
        """The job's ranks: as given, else ``torch.distributed``'s when initialised, else 1."""
        return self._layout()[1]

    def _layout(self) -> Tuple[int, int]:
        return _layout(self._rank, self._world)

    def __getstate__(self) -> dict:
        """Pickled (a DataLoader worker started by spawn or forkserver, where the process group
        and accelerate's loaders do not exist) with the layout and the dispatcher this process sees."""
        state = dict(self.__dict__)
        state["_rank"], state["_world"] = self._layout()
        state["_dispatch"] = self._dispatcher()
        state["_reading"] = state["_upcoming"] = None
        return state

    # ------------------------------------------------------------------ epochs and positions
    def set_epoch(self, epoch: int) -> None:
        """Read ``epoch`` next: from the loaded position when it is that epoch's, else from its start.

        Raises:
            ValueError: a bad epoch.
            RuntimeError: (called by accelerate's loader as it begins a pass) a way of accelerate's
                that cannot read the plan exactly once (one line saying what to do instead;
                ``plan_accelerate.check_loader``).
        """
        if not isinstance(epoch, int) or isinstance(epoch, bool) or epoch < 0:
            raise ValueError(f"epoch must be an int >= 0, got {epoch!r}")
        plan_accelerate.check_loader(self)
        self._control.adopt(self)
        self.epoch = epoch
        self.start = self._resume["sample_in_epoch"] if self._resume and self._resume["epoch"] == epoch else 0
        if self._pending is not None and self._pending["epoch"] != epoch:
            self._pending = None
        self._reading = None
        self._control.publish(self)

    def load_state_dict(self, state: dict) -> None:
        """Resume at a position (a batch's ``position``), taken at any world size and batch size:
        its epoch is read next, from that position. Or at a :meth:`state_dict` (what
        ``StatefulDataLoader`` restores): the next iteration reads from where that one stopped
        (one taken in the main process resumes at any layout; one taken in DataLoader worker ``j``
        of ``k`` only in worker ``j`` of ``k`` at the same world size and batch size).

        Raises:
            PlanMismatch: a malformed position (naming the field), one of another plan than the
                server's (one line naming what differs; checked when the server is first asked),
                or a resume state of the removed push delivery (the sample ids it delivered, which
                no position of a plan's fixed slices stands for).
            ValueError: a worker's state loaded elsewhere than that worker at that layout (one line).
        """
        pos = _loaded_position(state, self._info)
        reader = state.get("reader")
        self._control.adopt(self)
        if reader is None:
            self._resume, self._pending = pos.to_dict(), None
            self.set_epoch(pos.epoch)
            return
        self._pending = _pending_of(pos, _check_reader(reader), self._reader_world(), self.batch_size)
        self._control.publish(self)

    def state_dict(self) -> dict:
        """What this process has read: the position after the last step it yielded
        (``Position.to_dict``; exact without DataLoader workers, where it equals the last batch's
        ``position``; in a DataLoader worker, where the steps the other workers yielded are not
        counted, a lower bound) and, under ``reader``, where its next item is (``origin``,
        ``item``) and the layout (``worker``, ``workers``, ``world_size``, ``batch_size``,
        ``dispatch``) it reads with. No rank: every rank at one step has the same state.

        Under accelerate's dispatcher a step's group counts once all of its batches are yielded
        (accelerate snapshots before each batch it takes and hands a group out whole).

        Raises:
            TimeoutError: the server did not say what it serves (asked once per process).
            RuntimeError: asked in the main process while DataLoader workers read this epoch
                (since the last ``set_epoch`` or ``load_state_dict``) and handed batches on: they
                read ahead of the loop, so no process knows which batches the loop took (one line
                naming ``batch["position"]``, the checkpoint to keep).
        """
        if self._reading is None:  # a pass under way keeps its own progress
            self._control.adopt(self)
        if torch.utils.data.get_worker_info() is None and self._control.workers_yielded(self._seen):
            raise RuntimeError("state_dict() of a V2VStreamDataset read by DataLoader workers cannot say which batches "
                               "the loop took (the workers read ahead): checkpoint batch[\"position\"] of the last "
                               "batch the loop took, or read with torchdata's StatefulDataLoader")
        info = self.plan_info()
        r = self._reading
        if r is None:  # nothing read yet: where the next iteration starts
            w = torch.utils.data.get_worker_info()
            j, k = (w.id, w.num_workers) if w is not None else (0, 1)
            p = self._upcoming if self._upcoming is not None else self._pending
            epoch, origin, item = _start_of(p, self.epoch, self.start, j)
            position = p["position"] if p is not None else Position(info.plan, epoch, origin).to_dict()
            d = self._dispatcher()
            return {**position, "reader": _reader_part(j, k, self._reader_world(), self.batch_size, d[0] if d else 0,
                                                       origin, item)}
        done, reader = _reading_state(r, self.batch_size)
        return {**Position(info.plan, r["epoch"], done).to_dict(), "reader": reader}

    def _dispatcher(self) -> Optional[tuple]:
        """``(ranks, stateful)`` of accelerate's dispatcher reading this dataset now (as pickled
        into a spawned DataLoader worker, where it cannot be seen), else None."""
        return self._dispatch or plan_accelerate.dispatcher_of(self)

    def _reader_world(self) -> int:
        """The world size this process reads with: the dispatcher's ranks under it, else this rank's."""
        d = self._dispatcher()
        return d[0] if d else self.world_size

    def plan_info(self, refresh: bool = False, new_pass: bool = False) -> PlanInfo:
        """What the server(s) serve (asked once per dataset object and process; with ``refresh``,
        again while the epoch's samples are not known: the plan unfolds as the server decodes;
        with ``new_pass``, again of a fleet, whose hosts may serve another plan since the last
        pass: ``Servers.ask``).

        Raises:
            TimeoutError, PlanServerError, ValueError: as ``Servers.ask``.
            PlanMismatch: a loaded position of another plan."""
        if self._info is None or (refresh and self._info.samples is None) or (new_pass and self._servers.fleet):
            loaded = self._resume or (self._pending and self._pending["position"])
            prefer = PlanIdentity.from_dict(loaded["plan"]) if loaded else None  # a fleet reads the plan it names
            self._info = self._servers.ask(self.timeout_s, self.curve, prefer)
            for loaded in filter(None, (self._resume, self._pending and self._pending["position"])):
                Position.from_dict(loaded, expected=self._info.plan)
        return self._info

    def __bool__(self) -> bool:
        """True whatever ``len`` says (``if ds:`` would ask the server, and refuse while it learns the epoch)."""
        return True

    def __len__(self) -> int:
        """Steps of this rank in the epoch from its start position (every rank the same); asked by
        accelerate's dispatcher (``len`` of the loader it prepared), the batches it reads: the
        steps times its ranks, so the prepared loader's length is the steps each rank takes.

        Raises:
            TypeError: the epoch's samples are not known yet (learned from each video's first
            decode), as for a dataset without a length."""
        self._control.adopt(self)
        steps = epoch_steps(self.plan_info(refresh=True).samples, self.world_size, self.batch_size, self.start)
        if steps is None:
            raise TypeError(f"{self.endpoint}: {_LENGTH_UNKNOWN}")
        return steps * plan_accelerate.dispatcher_asking_len(self)

    # ------------------------------------------------------------------ reading
    def __iter__(self) -> Iterator[Dict]:
        """This process's batches. A loaded state is taken now, for this iteration only; the rest
        is decided at the first batch (when the loaders that create an iterator early, as
        ``StatefulDataLoader.state_dict`` does, have set the epoch and accelerate has registered its
        loader). Reading raises ``TimeoutError``, ``PlanMismatch`` or ``PlanServerError``."""
        self._control.adopt(self)
        pending, self._pending = self._pending, None
        self._reading, self._upcoming = None, pending
        return self._read(pending)

    def _read(self, pending: Optional[dict]) -> Iterator[Dict]:
        w = torch.utils.data.get_worker_info()
        j, k = (w.id, w.num_workers) if w is not None else (0, 1)
        layout = _read_layout(self._dispatcher(), self._layout())
        if layout is None:  # accelerate reads the loader on process 0 only
            return
        (rank, world, g), (epoch, origin, first) = layout, _start_of(pending, self.epoch, self.start, j)
        size = self.batch_size
        r = {"epoch": epoch, "origin": origin, "next": first, "last": None, "worker": j, "workers": k,
             "rank": rank, "world": world, "group": g, "per_step": world * size}
        self._reading, self._upcoming = r, None
        info = self.plan_info(refresh=True, new_pass=True)
        if pending is not None:
            Position.from_dict(pending["position"], expected=info.plan)
        steps = epoch_steps(info.samples, world, size, r["origin"])
        items = range(r["next"], steps * g, k) if steps is not None else itertools.count(r["next"], k)
        group = []  # under dispatch: this process's items of the current step, packed together
        with self._servers.link(self.timeout_s, self.curve) as link:
            for i, rows, arrays in link.fetch_all(
                    items, self.prefetch, self.retry_s,
                    lambda req, i: Fetch(req, r["epoch"], *_rows(r, i, size), self.outputs, info.plan),
                    lambda i: batch_positions(i // g, 0, world, size, r["origin"]).start,
                    (rank * k + j, world * k) if g == 1 else (j, k)):
                steps = steps if steps is not None else epoch_steps(rows.samples, world, size, r["origin"])
                if steps is not None and i // g >= steps:
                    break  # past the epoch's end, learned from the rows (fetched ahead)
                item = _item(info, r, i // g, size, rows, arrays, self.raw)
                item["servers"] = link.served(rows)
                if r["last"] is None:  # who reads the pass: after a worker's yield, what the loop took is unknown
                    self._control.mark_workers_yielded(self._seen if w is not None else -1)
                if g == 1:
                    r["last"], r["next"] = i, i + k
                    yield item
                    continue
                group.append((i, item))
                if k > 1 or i % g == g - 1 or (steps is not None and i + k >= steps * g):
                    packed = plan_accelerate.dispatched([b for _, b in group], k)
                    for (done, _), batch in zip(group, packed):
                        r["last"], r["next"] = done, done + k
                        yield batch
                    group = []


def _layout(rank: Optional[int], world: Optional[int]) -> Tuple[int, int]:
    """(rank, world size): as given, else ``torch.distributed``'s where initialised, else 0 and 1."""
    if rank is None or world is None:
        dist = torch.distributed
        on = dist.is_available() and dist.is_initialized()
        rank = rank if rank is not None else (dist.get_rank() if on else 0)
        world = world if world is not None else (dist.get_world_size() if on else 1)
        _check_layout(rank, world)
    return rank, world


def _item(info: PlanInfo, r: dict, step: int, batch_size: int, rows: Rows, arrays, raw: bool) -> Dict:
    """The dataset's item of ``step`` (the class docstring), read as ``r`` says in batches of ``batch_size``."""
    crop = info.stream.get("crop_size")
    item = batch_to_torch(arrays, raw, (crop, crop) if crop else None, info.stream.get("flow_dtype", "float16"))
    after = Position(info.plan, r["epoch"], r["origin"]).after(step + 1, r["world"], batch_size)
    item.update(padding=torch.tensor(rows.padding, dtype=torch.bool), sample_ids=rows.sample_ids,
                params=rows.params, epoch=r["epoch"], step=step, position=after.to_dict())
    return item


def _refuse_settings(settings: dict) -> None:
    """Refuse keyword arguments beyond the dataset's own: ``TypeError`` for one no reader takes,
    else ``ValueError`` in one line for push delivery's (``push_names.READER_SETTINGS``)."""
    for name in settings:
        if name not in READER_SETTINGS:
            raise TypeError(f"V2VStreamDataset() got an unexpected keyword argument {name!r}")
    if settings:
        raise ValueError(reader_settings_problem(settings))


def open_stream(endpoint, *, outputs: Sequence[str] = DEFAULT_OUTPUTS, raw: bool = False, timeout_s: float = 60.0,
                curve_keys: Optional[Tuple[str, str]] = None) -> "PlanEpochs":
    """What a trainer reads at ``endpoint`` (one server or several shards), one pass: the plan's
    epochs in turn (:class:`PlanEpochs` over a :class:`V2VStreamDataset` in the server's batch
    size), the server asked once here.

    Raises:
        TimeoutError: no server answered within ``timeout_s``.
        PlanServerError: a server refused or spoke another protocol version (one line).
        ValueError: a bad setting, naming it."""
    ds = V2VStreamDataset(endpoint, outputs=outputs, raw=raw, timeout_s=timeout_s, retry_s=min(10.0, timeout_s),
                          curve_keys=curve_keys)
    ds.plan_info()
    return PlanEpochs(ds)


class PlanEpochs(torch.utils.data.IterableDataset):
    """One pass over a plan's epochs in turn (``v2v-train``'s and ``v2v-loadtest``'s): the
    batches of ``dataset`` (a :class:`V2VStreamDataset`), each epoch's ``set_epoch`` after the
    last, from the epoch of a loaded position on. :meth:`state_dict` /
    :meth:`load_state_dict` are the dataset's (a position: the epoch and the samples read).
    An epoch without a batch from its start ends the pass; one resumed at its end (a position
    kept after its last step) goes on with the next epoch."""

    def __init__(self, dataset):
        super().__init__()
        self.dataset = dataset

    def __iter__(self):
        while True:
            last, epoch, resumed = None, self.dataset.epoch, self.dataset.start > 0
            for batch in self.dataset:
                last = batch["epoch"]
                yield batch
            if last is None and not resumed:
                return
            self.dataset.set_epoch((epoch if last is None else last) + 1)

    def state_dict(self) -> dict:
        return self.dataset.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.dataset.load_state_dict(state)

    def recipe(self) -> dict:
        """What the batches are made under, as the server(s) said it when first asked
        (``V2VStreamDataset.plan_info``; nothing is asked again): ``plan``, the plan's identity
        (the manifest's and the recipe's fingerprints, the seed, the shuffle buffer, the plan's
        version), and the stream's recipe (``PlanInfo.stream``: sequence length, bins, crop,
        frames per bin, outputs, flow preset and dtype, crops per window, batch size, corpus,
        shard, ...) without its ``feed``, the server's running figures (:meth:`server_feed`).
        ``v2v-train``'s TensorBoard ``recipe`` text."""
        info = self.dataset.plan_info()
        return {"plan": info.plan.to_dict(), **{k: v for k, v in info.stream.items() if k != "feed"}}

    def server_feed(self, timeout_s: Optional[float] = None) -> Optional[dict]:
        """What the dataset's server(s) report of their work, asked now (``Servers.feed``):
        ``workers``, ``samples_made``, ``samples_made_by_epoch`` (epoch -> samples made of it),
        ``busy_s`` (stage -> worker seconds), ``frame_cache_gb``; None from a server that does not
        report them. ``trainer.feed_report`` says from them
        what would feed a starved trainer. ``timeout_s``: how long the question may wait, for
        all the servers together (default: the dataset's ``timeout_s``; an interrupted
        ``v2v-train`` waits half a second at most: ``trainer.loop.INTERRUPTED_ASK_S``).

        Raises:
            TimeoutError: a server did not answer within ``timeout_s``."""
        ds = self.dataset
        return ds._servers.feed(ds.timeout_s if timeout_s is None else timeout_s, ds.curve)



"""Reading a server that serves by plan (``v2v-serve``'s default delivery, docs/delivery.md) as a torch
dataset: each rank's batch at each step is a fixed slice of the epoch's plan, fetched by position.

The dataset holds no socket and no lock: each process that iterates it (the main process, a
DataLoader worker started by fork, spawn or forkserver) opens its own connection, so it pickles
as plain settings. With ``k`` DataLoader workers, worker ``j`` reads steps ``j, j + k, ...``, and
the DataLoader's round robin yields them in step order.

**Several servers**, each serving one shard (``v2v-serve --shard I/N``): ``endpoint`` a list, a
comma-separated string, or a ``tcp://NAME:PORT`` whose name resolves to several addresses (a
Kubernetes headless Service). Their plans are read as one, interleaved (``v2v_wire.plan_shards``:
global position t is shard t mod N's t // N); servers that are not one sharding of one corpus
under one recipe are refused, naming them.

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
import json
import time
from collections.abc import Mapping
from dataclasses import replace
from typing import Dict, Iterator, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch
import zmq

from v2v_wire.plan import PlanIdentity, PlanMismatch, Position
from v2v_wire.plan_shards import (furthest_slot, interleaved, probes, shard_parts, shard_ranges, shards_identity,
                                  shards_samples, step_in_epoch)
from v2v_wire.plan_messages import Fetch, PlanAsk, PlanInfo, Refused, Rows, WireError, plan_server_message
from v2v_wire.codecs import available, check_compression, decode_batch_arrays
from v2v_wire.protocol import DEFAULT_OUTPUTS, MAX_BATCH_BYTES, ProtocolError, check_outputs, is_ipv6, pack, unpack

from . import plan_accelerate
from .endpoints import auto_compression, check_servers, load_curve_keys, resolve_endpoints, split_endpoints
from .tensors import batch_to_torch

__all__ = ["V2VStreamDataset", "PlanEpochs", "open_stream", "PlanServerError"]


class PlanServerError(RuntimeError):
    """The server refused a fetch, or sent what this client cannot read (the message says which
    endpoint and why, in one line)."""


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
    ``step``, and ``position``: the checkpoint after this step (``Position.to_dict``), the same on
    every rank; :meth:`load_state_dict` takes it, at any world size and batch size.
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
        _refuse_push(push_settings)
        _check_settings(1 if batch_size is None else batch_size, prefetch, retry_s, timeout_s)
        self._servers = _Servers(endpoint, compression)  # a bad endpoint or codec: an error here
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

    def plan_info(self, refresh: bool = False) -> PlanInfo:
        """What the server(s) serve (asked once per dataset object and process; with ``refresh``,
        again while the epoch's samples are not known: the plan unfolds as the server decodes).

        Raises:
            TimeoutError, PlanServerError, ValueError: as ``_Servers.ask``.
            PlanMismatch: a loaded position of another plan."""
        if self._info is None or (refresh and self._info.samples is None):
            self._info = self._servers.ask(self.timeout_s, self.curve)
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
        steps = _steps(self.plan_info(refresh=True).samples, self.start, self.world_size * self.batch_size)
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
        r = {"epoch": epoch, "origin": origin, "next": first, "last": None, "worker": j, "workers": k,
             "rank": rank, "world": world, "group": g, "per_step": world * self.batch_size}
        self._reading, self._upcoming = r, None
        info = self.plan_info(refresh=True)
        if pending is not None:
            Position.from_dict(pending["position"], expected=info.plan)
        steps = _steps(info.samples, r["origin"], r["per_step"])
        items = range(r["next"], steps * g, k) if steps is not None else itertools.count(r["next"], k)
        group = []  # under dispatch: this process's items of the current step, packed together
        with self._servers.link(self.timeout_s, self.curve) as link:
            for i, rows, arrays in link.fetch_all(
                    items, self.prefetch, self.retry_s,
                    lambda req, i: Fetch(req, r["epoch"], *_rows(r, i, self.batch_size), self.outputs, info.plan),
                    lambda i: r["origin"] + (i // g) * r["per_step"]):
                steps = steps if steps is not None else _steps(rows.samples, r["origin"], r["per_step"])
                if steps is not None and i // g >= steps:
                    break  # past the epoch's end, learned from the rows (fetched ahead)
                item = _item(info, r, i // g, rows, arrays, self.raw)
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


def _item(info: PlanInfo, r: dict, step: int, rows: Rows, arrays, raw: bool) -> Dict:
    """The dataset's item of ``step`` (the class docstring), read as ``r`` says."""
    crop = info.stream.get("crop_size")
    item = batch_to_torch(arrays, raw, (crop, crop) if crop else None, info.stream.get("flow_dtype", "float16"))
    after = r["origin"] + (step + 1) * r["per_step"]
    item.update(padding=torch.tensor(rows.padding, dtype=torch.bool), sample_ids=rows.sample_ids,
                params=rows.params, epoch=r["epoch"], step=step, position=Position(info.plan, r["epoch"], after).to_dict())
    return item


class _Control:
    """What every copy of one dataset reads at each pass: the epoch, start and loaded state that
    the main process set last (:meth:`publish`; a copy that has not seen it takes it, :meth:`adopt`),
    and whether DataLoader workers yielded batches of it.

    A uint8 torch tensor in shared memory, made with the dataset: a DataLoader worker started by
    fork maps the same pages, one started by spawn or forkserver gets them through torch's
    pickler (a shared-memory handle), so a persistent worker sees each ``set_epoch`` at its next
    pass. A plain pickle (or deepcopy) copies it: that copy is its own. Layout: int64 generation
    (bumped at each write), int64 generation some worker yielded a batch of (-1: none), int64
    length, then the state as JSON."""

    SIZE = 8192
    HEAD = 24

    def __init__(self):
        self.block = torch.zeros(self.SIZE, dtype=torch.uint8).share_memory_()
        self._words()[1] = -1

    def _words(self) -> np.ndarray:
        return self.block.numpy()[:self.HEAD].view(np.int64)

    def generation(self) -> int:
        """The number of writes so far."""
        return int(self._words()[0])

    def write(self, state: dict) -> int:
        """Store ``state`` (JSON-able); returns the new generation.

        Raises:
            ValueError: a state too large for the block (a position is a few hundred bytes)."""
        data = json.dumps(state).encode()
        if len(data) > self.SIZE - self.HEAD:
            raise ValueError(f"a loaded state of {len(data)} bytes does not fit the dataset's shared control "
                             f"({self.SIZE - self.HEAD} bytes)")
        words = self._words()
        self.block.numpy()[self.HEAD:self.HEAD + len(data)] = np.frombuffer(data, np.uint8)
        words[2] = len(data)
        words[0] += 1  # last: a reader seeing the new generation sees the whole state
        return int(words[0])

    def read(self) -> dict:
        """The state last written."""
        n = int(self._words()[2])
        return json.loads(self.block.numpy()[self.HEAD:self.HEAD + n].tobytes())

    def publish(self, ds: "V2VStreamDataset") -> None:
        """In the main process, write what ``ds``'s next pass reads (epoch, start, loaded state),
        for the DataLoader workers' copies; a worker's own load stays its own."""
        if torch.utils.data.get_worker_info() is None:
            ds._seen = self.write({"epoch": ds.epoch, "start": ds.start, "resume": ds._resume, "pending": ds._pending})
        else:
            ds._seen = self.generation()

    def adopt(self, ds: "V2VStreamDataset") -> None:
        """Give ``ds`` what the main process set last (``set_epoch``, ``load_state_dict``) when that
        copy has not seen it: a DataLoader worker's copy, made when the worker started."""
        gen = self.generation()
        if gen == ds._seen:
            return
        d = self.read()
        ds.epoch, ds.start, ds._resume, ds._pending = d["epoch"], d["start"], d["resume"], d["pending"]
        ds._reading, ds._upcoming, ds._seen = None, None, gen

    def mark_workers_yielded(self, generation: int) -> None:
        """Record that a DataLoader worker yielded a batch of the pass ``generation`` set up (-1:
        the main process read the last pass itself)."""
        self._words()[1] = generation

    def workers_yielded(self, generation: int) -> bool:
        """Whether a DataLoader worker yielded a batch of the pass ``generation`` set up."""
        return int(self._words()[1]) == generation


class _Servers:
    """The servers a dataset reads as one plan: one, or one per shard in shard order, each with
    its plan identity and the compression its fetches ask for (known once asked; pickled with
    the dataset, so a DataLoader worker asks nothing again)."""

    def __init__(self, endpoint, compression: str):
        split_endpoints(endpoint)  # a bad entry: ValueError, naming it
        if compression != "auto" and not available(check_compression(compression)):
            raise ValueError(f"compression {compression!r}: its library is not installed here (pip install 'v2v[wire]')")
        self.endpoint, self.compression = endpoint, compression
        self.shards: Optional[List[Tuple[str, PlanIdentity]]] = None  # (server, its plan), in shard order
        self.codecs: Dict[str, str] = {}  # server -> compression
        self.samples: List[Optional[int]] = []  # each shard's samples per epoch when asked (None: not known)

    def ask(self, timeout_s: float, curve: Optional[tuple]) -> PlanInfo:
        """What the servers serve, as one plan (resolving ``endpoint`` the first time).

        Raises:
            TimeoutError, PlanServerError: a server silent, or speaking another protocol version.
            ValueError: several servers that are not one sharding of one corpus."""
        servers = resolve_endpoints(self.endpoint) if self.shards is None else [ep for ep, _ in self.shards]
        infos = []
        for server in servers:
            with _Link(server, timeout_s, curve) as link:
                infos.append(link.ask())
        info, self.shards, self.samples = _as_one_plan(servers, infos)
        self.codecs = {ep: _codec_for(self.compression, ep, i.stream) for ep, i in zip(servers, infos)}
        return info

    def link(self, timeout_s: float, curve: Optional[tuple]):
        """A connection fetching rows of the plan: a ``_Link`` to the one server, else ``_Shards``."""
        if len(self.shards) == 1:
            return _Link(self.shards[0][0], timeout_s, curve, self.codecs[self.shards[0][0]])
        return _Shards(self.shards, timeout_s, curve, self.codecs, self.samples)

    def feed(self, timeout_s: float, curve: Optional[tuple]) -> Optional[dict]:
        """The servers' ``feed`` figures asked now (``plan_server.stream_info``), summed over the
        shards: ``workers``, ``samples_made``, ``busy_s`` (stage -> worker seconds) and the
        smallest ``frame_cache_gb``; None when a server does not report them.

        Raises:
            TimeoutError: the servers did not all answer within ``timeout_s`` (for all of them
                together: one silent shard cannot make the question wait once per shard)."""
        deadline = time.monotonic() + timeout_s
        figures = []
        for server in [ep for ep, _ in self.shards or ()] or resolve_endpoints(self.endpoint):
            with _Link(server, max(0.0, round(deadline - time.monotonic(), 2)), curve) as link:
                figures.append(link.ask().stream.get("feed"))
        if not figures or not all(isinstance(f, dict) for f in figures):
            return None
        busy: Dict[str, float] = {}
        for f in figures:
            for stage, v in (f.get("busy_s") or {}).items():
                busy[stage] = busy.get(stage, 0.0) + float(v)
        return {"workers": sum(int(f.get("workers") or 0) for f in figures),
                "samples_made": sum(int(f.get("samples_made") or 0) for f in figures),
                "frame_cache_gb": min(float(f.get("frame_cache_gb") or 0.0) for f in figures), "busy_s": busy}


def _as_one_plan(servers: List[str], infos: List[PlanInfo]):
    """``(PlanInfo, [(server, its plan identity)], [its samples per epoch or None])`` of the servers
    read as one plan: one server's own; several, each one shard of one corpus under one recipe,
    interleaved in shard order.

    Raises:
        ValueError: several servers that are not one sharding of one corpus (naming them)."""
    if len(servers) == 1:
        return infos[0], [(servers[0], infos[0].plan)], [infos[0].samples]
    whole = [ep for ep, i in zip(servers, infos) if not isinstance(i.stream.get("shard"), str)]
    if whole:
        raise ValueError(f"{', '.join(whole)}: serve(s) the whole corpus; several servers are read together when "
                         f"each serves one shard (v2v-serve --shard I/N)")
    check_servers({ep: i.stream for ep, i in zip(servers, infos)})
    ordered = sorted(zip(servers, infos), key=lambda x: int(x[1].stream["shard"].split("/")[0]))
    plan = shards_identity([i.plan for _, i in ordered])
    return (PlanInfo(plan, shards_samples([i.samples for _, i in ordered]), ordered[0][1].stream),
            [(ep, i.plan) for ep, i in ordered], [i.samples for _, i in ordered])


#: The removed push delivery's reader settings, which a plan has no use for: given here, they are
#: refused in one line.
PUSH_SETTINGS = ("credits", "heartbeat_s", "reconnect", "reconnect_timeout_s", "group", "shm", "compact_flow")


def _codec_for(compression: str, endpoint: str, stream: dict) -> str:
    """What fetches of ``endpoint`` ask for: ``compression``, or for ``"auto"``
    ``endpoints.auto_compression`` with the codecs the server lists in its stream info."""
    return compression if compression != "auto" else auto_compression(endpoint, stream.get("codecs", ()))


def _refuse_push(settings: dict) -> None:
    """One line for a setting only the removed push delivery read."""
    for name in settings:
        if name not in PUSH_SETTINGS:
            raise TypeError(f"V2VStreamDataset() got an unexpected keyword argument {name!r}")
    if settings:
        raise ValueError(f"{', '.join(sorted(settings))}: setting(s) of push delivery, which v2v no longer has "
                         f"(docs/delivery.md): drop them")


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
        """What the dataset's server(s) report of their work, asked now (``_Servers.feed``):
        ``workers``, ``samples_made``, ``busy_s`` (stage -> worker seconds), ``frame_cache_gb``;
        None from a server that does not report them. ``trainer.feed_report`` says from them
        what would feed a starved trainer. ``timeout_s``: how long the question may wait, for
        all the servers together (default: the dataset's ``timeout_s``; an interrupted
        ``v2v-train`` waits half a second at most: ``trainer.loop.INTERRUPTED_ASK_S``).

        Raises:
            TimeoutError: a server did not answer within ``timeout_s``."""
        ds = self.dataset
        return ds._servers.feed(ds.timeout_s if timeout_s is None else timeout_s, ds.curve)


def _check_settings(batch_size: int, prefetch: int, retry_s: float, timeout_s: float) -> None:
    for name, v in (("batch_size", batch_size), ("prefetch", prefetch)):
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            raise ValueError(f"{name} must be an int >= 1, got {v!r}")
    if not 0 < retry_s <= timeout_s:
        raise ValueError(f"retry_s must be > 0 and <= timeout_s, got {retry_s} and {timeout_s}")


_LENGTH_UNKNOWN = ("the epoch's length is not known yet: the server learns each video's windows from its first "
                   "decode (v2v-serve --check counts them ahead)")


def _steps(samples: Optional[int], origin: int, per_step: int) -> Optional[int]:
    """Steps from position ``origin`` to the end of an epoch of ``samples`` (None: not known yet)."""
    return None if samples is None else max(0, -(-(samples - origin) // per_step))


def _pending_of(pos: Position, reader: dict, world: int, batch_size: int) -> dict:
    """Where the next iteration reads from, for a loaded state (``pos``, its ``reader`` part), in
    this process (``world``, ``batch_size``: its layout).

    Raises:
        ValueError: a DataLoader worker's state loaded elsewhere than that worker at that layout.
    """
    pending = {"position": pos.to_dict(), "epoch": pos.epoch}
    if reader["workers"] == 1:  # the exact position: any layout
        pending["at"] = pos.sample_in_epoch
        return pending
    w = torch.utils.data.get_worker_info()
    here = (w.id, w.num_workers) if w is not None else (0, 1)
    if here != (reader["worker"], reader["workers"]) or (world, batch_size) != (reader["world_size"],
                                                                               reader["batch_size"]):
        raise ValueError(
            f"this state is DataLoader worker {reader['worker']} of {reader['workers']}'s at world size "
            f"{reader['world_size']} and batch size {reader['batch_size']}, loaded in "
            f"{'worker %d of %d' % here if w is not None else 'a process without workers'} at world size {world} "
            f"and batch size {batch_size}: only that worker's loader (StatefulDataLoader) resumes it; resume at "
            "another layout from a batch's position")
    pending.update(origin=reader["origin"], item=reader["item"])
    return pending


def _reading_state(r: dict, batch_size: int):
    """``(position, reader)`` of an iteration's progress ``r``: the position after its last step
    (exact with one worker), and the ``reader`` part of ``state_dict``."""
    g, k, item, last = r["group"], r["workers"], r["next"], r["last"]
    if g > 1 and last is not None and last % g != g - 1:
        item = last - last % g  # a group not yet handed out whole: read it again
    if k == 1:
        done = r["origin"] + -(-item // g) * r["per_step"]
    else:
        done = r["origin"] + (last // g + 1) * r["per_step"] if last is not None else r["origin"]
    return done, _reader_part(r["worker"], k, r["world"], batch_size, g if g > 1 else 0, r["origin"], item)


def _reader_part(worker: int, workers: int, world: int, batch_size: int, dispatch: int, origin: int,
                 item: int) -> dict:
    """The ``reader`` part of ``state_dict`` (``_check_reader`` reads it back): DataLoader worker
    ``worker`` of ``workers`` reading at ``world`` ranks (the dispatcher's under it) of
    ``batch_size`` rows, ``dispatch`` (the dispatcher's ranks, 0: none), from position ``origin``
    at its item ``item``."""
    return {"worker": worker, "workers": workers, "world_size": world, "batch_size": batch_size,
            "dispatch": dispatch, "origin": origin, "item": item}


def _start_of(pending: Optional[dict], epoch: int, start: int, worker: int) -> Tuple[int, int, int]:
    """Where an iteration of DataLoader worker ``worker`` (0 without workers) begins: ``(epoch,
    origin, item)``, from a loaded state's ``pending`` (``_pending_of``) where there is one, else
    at position ``start`` of ``epoch``."""
    if pending is None:
        return epoch, start, worker
    if "at" in pending:
        return pending["epoch"], pending["at"], worker
    return pending["epoch"], pending["origin"], pending["item"]


def _read_layout(dispatch: Optional[tuple], layout: Tuple[int, int]) -> Optional[Tuple[int, int, int]]:
    """``(rank, world, group)`` an iteration reads with, from accelerate's ``dispatch`` (``(ranks,
    stateful)`` or None) and this rank's ``layout``: under the dispatcher, rank 0 of its ranks,
    each step's group of their batches read together; else this rank alone (group 1). None: a
    rank other than 0 under the dispatcher (accelerate reads the loader on process 0 only)."""
    rank, world = layout
    g = dispatch[0] if dispatch else 1
    if g > 1:
        return None if rank != 0 else (0, g, g)
    return rank, world, g


def _rows(r: dict, i: int, batch_size: int) -> Tuple[int, int]:
    """Global positions ``[start, stop)`` of item ``i`` of an iteration read as ``r`` says: under
    the dispatcher step ``i // group``'s rank ``i % group``, else step ``i`` of this rank."""
    g = r["group"]
    s, rank = divmod(i, g) if g > 1 else (i, r["rank"])
    first = r["origin"] + s * r["per_step"] + rank * batch_size
    return first, first + batch_size


def _loaded_position(state, info: Optional[PlanInfo]) -> Position:
    """The position of a state given to ``load_state_dict``, checked against ``info``'s plan where
    the server was asked already (None: not yet).

    Raises:
        PlanMismatch: a resume state of the removed push delivery (one line saying what to resume from), a
            malformed position (naming the field), or one of another plan than ``info``'s.
    """
    if isinstance(state, dict) and "delivered" in state and "plan" not in state:
        raise PlanMismatch(f"a resume state of push delivery, which v2v no longer has (consumer {state.get('consumer')!r}, completed epoch "
                           f"{state.get('completed_epoch')!r}) is not a plan's position: resume from a batch's "
                           f"'position', or read an epoch from its start with set_epoch()")
    pos = Position.from_dict(state)
    if info is not None:
        Position.from_dict(state, expected=info.plan)
    return pos


def _check_reader(reader) -> dict:
    """A state's ``reader`` part, checked.

    Raises:
        PlanMismatch: a malformed one, naming the field.
    """
    if not isinstance(reader, Mapping):
        raise PlanMismatch(f"state field 'reader' must be a mapping, got {type(reader).__name__}")
    for key in ("worker", "workers", "world_size", "batch_size", "dispatch", "origin", "item"):
        v = reader.get(key)
        if not isinstance(v, int) or isinstance(v, bool) or v < (1 if key in ("workers", "world_size", "batch_size")
                                                                   else 0):
            raise PlanMismatch(f"state field 'reader.{key}' must be an int, got {v!r:.80}")
    if reader["worker"] >= reader["workers"]:
        raise PlanMismatch(f"state field 'reader.worker' must be below {reader['workers']}, got {reader['worker']}")
    return dict(reader)


def _check_layout(rank: int, world_size: int) -> None:
    if not isinstance(world_size, int) or isinstance(world_size, bool) or world_size < 1:
        raise ValueError(f"world_size must be an int >= 1, got {world_size!r}")
    if not isinstance(rank, int) or isinstance(rank, bool) or not 0 <= rank < world_size:
        raise ValueError(f"rank must be in 0..{world_size - 1}, got {rank!r}")


def _with_padding(arrays: Dict[str, np.ndarray], padding: List[bool]) -> Dict[str, np.ndarray]:
    """The batch's arrays, one row per row of ``padding``, from the wire's (``Rows``: the rows
    holding a sample only, in row order): zeros in each padding row; the wire's arrays as they
    are when no row is padding.

    Raises:
        ProtocolError: an array whose rows are not the rows holding a sample, naming it."""
    real = [i for i, pad in enumerate(padding) if not pad]
    out = {}
    for name, a in arrays.items():
        if a.ndim == 0 or a.shape[0] != len(real):
            raise ProtocolError(f"array {name!r}: {a.shape[0] if a.ndim else 0} rows, the rows hold "
                                f"{len(real)} samples")
        if len(real) == len(padding):
            out[name] = a
            continue
        out[name] = np.zeros((len(padding), *a.shape[1:]), a.dtype)
        out[name][real] = a
    return out


class _Link:
    """One process's connection to a plan server: a DEALER socket, requests numbered from 1."""

    def __init__(self, endpoint: str, timeout_s: float, curve: Optional[tuple] = None, compression: str = "none"):
        self.endpoint, self.timeout_s, self.compression = endpoint, timeout_s, compression
        self.ctx = zmq.Context()
        self.sock = self.ctx.socket(zmq.DEALER)
        self.sock.setsockopt(zmq.LINGER, 0)
        if is_ipv6(endpoint):  # tcp://[::1]:PORT: without it the connect is never made and every ask times out
            self.sock.setsockopt(zmq.IPV6, 1)
        if curve is not None:  # (client public, client secret, server public), connection.load_curve_keys
            self.sock.curve_publickey, self.sock.curve_secretkey, self.sock.curve_serverkey = curve
        self.sock.connect(endpoint)
        self.ids = itertools.count(1)

    def __enter__(self) -> "_Link":
        return self

    def __exit__(self, *exc) -> None:
        self.sock.close()
        self.ctx.term()

    def _send(self, header: dict) -> None:
        """Send without blocking: with no peer (a server not up yet, a CURVE handshake refused) the
        message is dropped, and the caller's deadline or retry asks again."""
        try:
            self.sock.send(pack(header), zmq.NOBLOCK)
        except zmq.Again:
            pass

    def _recv(self, deadline: float):
        """The next message (header, frames) before ``deadline``, or None."""
        wait = max(0.0, deadline - time.monotonic())
        if not self.sock.poll(int(wait * 1000)):
            return None
        frames = self.sock.recv_multipart(copy=False)
        try:
            h = unpack(frames[0])
            return plan_server_message(h), frames[1:]
        except (ProtocolError, WireError) as e:
            raise PlanServerError(f"{self.endpoint}: {e}") from None

    def ask(self) -> PlanInfo:
        deadline = time.monotonic() + self.timeout_s
        while True:
            self._send(PlanAsk().to_wire())
            got = self._recv(min(deadline, time.monotonic() + 5.0))
            if got is not None and isinstance(got[0], PlanInfo):
                return got[0]
            if got is not None and isinstance(got[0], Refused):
                raise PlanServerError(f"{self.endpoint}: {got[0].message}")
            if time.monotonic() >= deadline:
                raise TimeoutError(f"{self.endpoint}: no answer to 'what do you serve' within {self.timeout_s} s "
                                   "(is a v2v-serve running there?)")

    def fetch_all(self, steps, prefetch: int, retry_s: float, fetch_of, first_of=None) -> Iterator:
        """``(step, rows, arrays)`` for each of ``steps`` in order, ``prefetch`` fetches in
        flight; an unanswered fetch is asked again after ``retry_s`` (the first answer wins).
        ``fetch_of(request, step)``: the step's :class:`Fetch` under that request id.
        ``first_of`` is for ``_Shards``: one server's rows past the epoch's end carry its samples."""
        todo = iter(steps)
        waiting: Dict[int, int] = {}  # request id -> step
        asked: Dict[int, float] = {}  # step -> when last asked
        done: Dict[int, tuple] = {}
        order = []
        heard = time.monotonic()

        def send(step: int) -> None:
            req = next(self.ids)
            self._send(replace(fetch_of(req, step), compression=self.compression).to_wire())
            waiting[req], asked[step] = step, time.monotonic()

        for step in itertools.islice(todo, prefetch):
            order.append(step)
            send(step)
        while order:
            if order[0] in done:
                step = order.pop(0)
                yield (step,) + done.pop(step)
                nxt = next(todo, None)
                if nxt is not None:
                    order.append(nxt)
                    send(nxt)
                continue
            now = time.monotonic()
            for step in order:
                if step not in done and now - asked[step] >= retry_s:
                    send(step)  # a lost reply or a restarted server: ask again
            got = self._recv(now + min(retry_s, 1.0))
            if got is None:
                if time.monotonic() - heard > self.timeout_s:
                    raise TimeoutError(f"{self.endpoint}: no rows for {self.timeout_s} s (step {order[0]})")
                continue
            heard = time.monotonic()
            msg, frames = got
            if isinstance(msg, Refused):
                raise _refusal(self.endpoint, msg)
            if not isinstance(msg, Rows) or msg.request not in waiting:
                continue  # an answer to a request asked again, or to a plan_ask
            step = waiting.pop(msg.request)
            if step in done or step not in order:
                continue
            try:
                arrays = _with_padding(decode_batch_arrays(msg.arrays, frames, MAX_BATCH_BYTES), msg.padding)
            except ProtocolError as e:
                raise PlanServerError(f"{self.endpoint}: rows of step {step}: {e}") from None
            done[step] = (msg, arrays)


def _refusal(endpoint: str, msg: Refused) -> Exception:
    """The error a fetch's refusal raises: ``PlanMismatch`` for another plan's, else ``PlanServerError``."""
    if "another plan" in msg.message:
        return PlanMismatch(f"{endpoint}: {msg.message}")
    return PlanServerError(f"{endpoint}: {msg.message}")


class _InFlight:
    """What one ``_Shards.fetch_all`` has asked and not yet yielded: ``fetch_of`` its steps'
    fetches; ``order`` the steps asked, in order; ``parts`` step -> shard -> (rows, arrays), None
    until answered; ``probed`` (shard, its position) asked, True once a slot is seen there;
    ``waiting`` (shard, request id) -> ``("step", step)`` or ``("probe", position)``; ``asked``
    (shard, what) unanswered -> when last asked; ``seen`` one past the furthest global position a
    row with a sample id was read at."""

    def __init__(self, fetch_of):
        self.fetch_of = fetch_of
        self.order: List[int] = []
        self.parts: Dict[int, Dict[int, Optional[tuple]]] = {}
        self.probed: Dict[Tuple[int, int], bool] = {}
        self.waiting: Dict[Tuple[int, int], tuple] = {}
        self.asked: Dict[Tuple[int, tuple], float] = {}
        self.seen = 0


class _Shards:
    """Several servers, one shard each, read as one plan (``v2v_wire.plan_shards``): a fetch of
    global positions is asked of each shard holding some of them, and their rows are merged in
    the interleave's order. ``shards``: (server, its plan identity), in shard order; ``samples``:
    each shard's samples per epoch where known (None: not yet)."""

    def __init__(self, shards: List[Tuple[str, PlanIdentity]], timeout_s: float, curve: Optional[tuple],
                 codecs: Dict[str, str], samples: Sequence[Optional[int]]):
        self.plans = [plan for _, plan in shards]
        self.links = [_Link(ep, timeout_s, curve, codecs[ep]) for ep, _ in shards]
        self.timeout_s = timeout_s
        self.samples: List[Optional[int]] = list(samples)  # each shard's epoch, once it or its rows say

    def __enter__(self) -> "_Shards":
        return self

    def __exit__(self, *exc) -> None:
        for link in self.links:
            link.__exit__(*exc)

    def _part(self, k: int, f: Fetch) -> Fetch:
        """Shard ``k``'s part of fetch ``f`` (of global positions), in its own positions."""
        lo, hi = shard_ranges(f.start, f.stop, len(self.links))[k]
        return replace(f, start=lo, stop=hi, plan=self.plans[k])

    def fetch_all(self, steps, prefetch: int, retry_s: float, fetch_of, first_of) -> Iterator:
        """``_Link.fetch_all`` over the shards: each step's fetch split into the parts of the
        shards holding some of its rows, each asked on that shard's link (``prefetch`` steps in
        flight, an unanswered part asked again after ``retry_s``), the parts merged in the
        interleave's order.

        A step is yielded once it is known to lie in the epoch or past it (``first_of(step)``:
        the first global position of the step, every rank's; ``plan_shards.step_in_epoch``):
        where its rows hold no sample id and a shard's samples are not known yet, that shard is
        asked for one row at or after it (``plan_shards.probes``). So a rank whose rows lie in
        some shards only ends the epoch at the step every other rank ends it at.

        Raises:
            TimeoutError: no shard said anything for ``timeout_s`` while a part was awaited.
            PlanMismatch, PlanServerError: a shard refused a fetch or sent what cannot be read.
        """
        todo = iter(steps)
        flight = _InFlight(fetch_of)
        poller = zmq.Poller()
        for link in self.links:
            poller.register(link.sock, zmq.POLLIN)
        for step in itertools.islice(todo, prefetch):
            self._begin(flight, step)
        heard = time.monotonic()
        while flight.order:
            head = flight.order[0]
            if all(p is not None for p in flight.parts[head].values()):
                first = first_of(head)
                if step_in_epoch(first, self.samples, flight.seen) is not None:
                    flight.order.pop(0)
                    yield (head,) + self._merged(fetch_of(0, head), flight.parts.pop(head))
                    nxt = next(todo, None)
                    if nxt is not None:
                        self._begin(flight, nxt)
                    continue
                for k, q in probes(first, self.samples):
                    if (k, q) not in flight.probed:
                        flight.probed[(k, q)] = False
                        self._ask(flight, k, ("probe", q))
            now = time.monotonic()
            for (k, what), when in list(flight.asked.items()):
                if now - when >= retry_s:
                    self._ask(flight, k, what)  # a lost reply or a restarted server: ask again
            ready = dict(poller.poll(int(min(retry_s, 1.0) * 1000)))
            if not ready:
                if time.monotonic() - heard > self.timeout_s:
                    late = sorted({self.links[k].endpoint for k, _ in flight.asked})
                    raise TimeoutError(f"{', '.join(late)}: no rows for {self.timeout_s} s (step {head})")
                continue
            heard = time.monotonic()
            for k, link in enumerate(self.links):
                got = link._recv(heard) if link.sock in ready else None
                if got is not None:
                    self._receive(flight, k, *got)

    def _ask(self, flight: "_InFlight", k: int, what: tuple) -> None:
        """Ask shard ``k`` for ``what``: ``("step", step)``, its part of that step's fetch, or
        ``("probe", position)``, one row at its own ``position`` under the first step's epoch and
        outputs."""
        link = self.links[k]
        req = next(link.ids)
        if what[0] == "step":
            f = self._part(k, flight.fetch_of(req, what[1]))
        else:
            f = replace(flight.fetch_of(req, flight.order[0]), start=what[1], stop=what[1] + 1, plan=self.plans[k])
        link._send(replace(f, compression=link.compression).to_wire())
        flight.waiting[(k, req)], flight.asked[(k, what)] = what, time.monotonic()

    def _begin(self, flight: "_InFlight", step: int) -> None:
        """Ask each shard holding some of ``step``'s rows for its part."""
        f = flight.fetch_of(0, step)
        flight.parts[step] = dict.fromkeys(shard_parts(f.start, f.stop, len(self.links)))
        flight.order.append(step)
        for k in flight.parts[step]:
            self._ask(flight, k, ("step", step))

    def _receive(self, flight: "_InFlight", k: int, msg, frames) -> None:
        """Take shard ``k``'s message ``msg`` (its ``frames``): a step's part is kept for the merge,
        a probe's row settles where that shard's slots end; the shard's samples and the furthest
        slot seen are noted from either. Answers to requests asked again are dropped.

        Raises:
            PlanMismatch, PlanServerError: the shard refused a fetch, sent arrays that cannot be
                read, or answered a probe past its epoch's end without the epoch's samples.
        """
        link, n = self.links[k], len(self.links)
        if isinstance(msg, Refused):
            raise _refusal(link.endpoint, msg)
        what = flight.waiting.pop((k, msg.request), None) if isinstance(msg, Rows) else None
        if what is None or flight.asked.pop((k, what), None) is None:
            return  # an answer to a request asked again, or to a plan_ask
        if msg.samples is not None:
            self.samples[k] = msg.samples
        flight.seen = furthest_slot(flight.seen, k, n, msg.start, msg.sample_ids)
        if what[0] == "probe":
            slot = any(sid is not None for sid in msg.sample_ids)
            if not slot and msg.samples is None:
                raise PlanServerError(f"{link.endpoint}: position {what[1]} answered past the epoch's end "
                                      "without the epoch's samples")
            flight.probed[(k, what[1])] = slot
            return
        try:
            arrays = _with_padding(decode_batch_arrays(msg.arrays, frames, MAX_BATCH_BYTES), msg.padding)
        except ProtocolError as e:
            raise PlanServerError(f"{link.endpoint}: rows of step {what[1]}: {e}") from None
        flight.parts[what[1]][k] = (msg, arrays)

    def _merged(self, f: Fetch, got: dict):
        """One ``Rows`` and its arrays for global positions ``f.start .. f.stop - 1`` from each
        shard's part (``got``: shard -> (rows, arrays))."""
        order = interleaved(f.start, f.stop, len(self.links))
        pick = [(got[k][0], j) for k, j in order]
        rows = Rows(f.request, f.epoch, f.start, [r.sample_ids[j] for r, j in pick], [r.padding[j] for r, j in pick],
                    [r.params[j] for r, j in pick], [], shards_samples(self.samples))
        # a part of padding rows only holds each output's zeros in its wire form (a dense ``flow``
        # where samples carry a ``flow_grid``): its rows are zeros of a part with samples
        like = next((a for r, a in got.values() if not all(r.padding)), next(iter(got.values()))[1])

        def row(k: int, j: int, name: str) -> np.ndarray:
            a = got[k][1]
            return a[name][j] if name in a else np.zeros_like(like[name][0])

        return rows, {name: np.stack([row(k, j, name) for k, j in order]) for name in like}

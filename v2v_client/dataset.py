"""``V2VPushDataset``: a torch IterableDataset reading batches from ``v2v-serve``.

Each iterator owns one DEALER connection (:class:`Connection`) served by a background I/O
thread (``connection.py``). The thread says ``hello`` (the outputs wanted, its ``credits``, who it is and
the resume state), receives batches, answers revokes, sends heartbeats, and forwards an
``ack`` naming each batch as it is handed to the training loop (the ack frees exactly that
batch's credit). So the server never has more than ``credits`` batches in flight to this
iterator, and a slow trainer never grows anybody's memory.

Sharing one stream: the server hands every batch to exactly one connection. Each DataLoader
worker process (``num_workers > 0``) and each DDP rank opens its own connection when it
starts iterating, so they split the stream between them without duplicates. DDP ranks find
their ``rank``/``world_size`` when iteration starts (``dist_position``), or are given them, so
that each rank yields the same number of batches per epoch (see ``V2VPushDataset``).
"""
from __future__ import annotations

import logging
import os
import uuid
from dataclasses import replace
from typing import Iterator, Optional, Sequence, Tuple, Union

import torch

from v2v_wire.codecs import available, check_compression
from v2v_wire.protocol import DEFAULT_OUTPUTS, MAX_CREDITS, OUTPUTS, check_outputs

from .connection import StreamError, StreamTimeout, load_curve_keys
from .endpoint import EndpointStream, padding_copy
from .fanin import FanInStream, resolve_endpoints, split_endpoints
from .launchers import RANKS, ReadAhead, adapt, check_whole, rank_part
from .metrics import TrainerMetrics
from .options import StreamOptions, job_group
from .resume import ResumeState
from .tensors import batch_to_torch

__all__ = ["V2VPushDataset", "StreamError", "StreamTimeout", "batch_to_torch", "dist_position", "padding_copy"]

log = logging.getLogger("v2v.client")

#: why ``len()`` of the dataset fails: loaders that index or sample a dataset cannot read a stream
NO_LENGTH = ("V2VPushDataset is a stream without a length: hand loaders that index or sample a dataset "
             "(DeepSpeed's training_data=) DataLoader(ds, batch_size=None) instead; a DataLoader over it has no "
             "length either (test it with `is not None`, not `if loader:`)")


class V2VPushDataset(torch.utils.data.IterableDataset):
    """Batches of V2V training data streamed from a ``v2v-serve`` endpoint.

    Args:
        endpoint: ZeroMQ endpoint of the server, e.g. ``tcp://127.0.0.1:5555``; or several servers (shards,
            ``v2v-serve --shard I/N``): a list, a comma-separated string, or a ``tcp://NAME:PORT`` whose name
            resolves to several addresses (a Kubernetes headless Service). Then one connection per server is
            read and the batches are merged (``v2v_client.fanin``): ``credits`` is split between the servers,
            each reconnects on its own, the stream ends when every server ended it and ``state_dict()`` covers
            them all. ``rank``/``world_size`` apply to each server.
        outputs: which of ``OUTPUTS`` to receive (default ``DEFAULT_OUTPUTS``: ``"voxels"``,
            ``"frames"``, ``"flow"``; ``"polarity_counts"`` only when named; dtypes and shapes in
            ``v2v_wire.outputs``); the server's workers compute the union of what its connected
            clients ask for.
        credits: batches the server may have in flight to this iterator (prefetch depth);
            the server refuses more than its ``max_credits`` setting (default 64,
            ``DeliveryPolicy.max_credits``) with a clear error.
        timeout_s: seconds without any message from the server (batches or heartbeats) before iteration raises
            ``StreamTimeout``; also bounds the wait for the first answer, so an absent server gives a clear
            error, never a hang. A heartbeating server that has nothing to send yet (a hung worker, ranks still
            joining) is waited for.
        heartbeat_s: seconds between heartbeats to the server.
        raw: keep wire dtypes (int8/int16 voxels, uint8 frames, float16 flow) for
            conversion on the GPU.
        reconnect: on a silent or restarting server, reconnect (with the delivered-sample
            state, so nothing is repeated) for up to ``reconnect_timeout_s`` seconds
            instead of raising.
        curve_keys: ``(client_secret_file, server_public_file)`` from ``v2v-keygen`` to talk
            to a server that requires CurveZMQ.
        rank, world_size: DDP position; what is not given is resolved each time iteration starts
            (:func:`dist_position`: ``torch.distributed`` when initialised, else the ``RANK`` / ``WORLD_SIZE``
            that torchrun and Lightning set, else 0 and 1), so a dataset built before the process group exists
            still joins the group. With ``world_size > 1`` the ranks form one group on the server (``group``):
            nothing is sent until every rank said hello (or the server's client timeout passed), and every rank
            yields the same number of batches per epoch — a rank that got fewer repeats its last batch with every
            sample flagged in ``padding`` (see below). Use ``num_workers=0`` with DDP.
        group: name of the DDP group (see ``rank``); default: a loaded state's, else named from the job's
            launcher (:func:`resolve_position`), so two jobs never share one.
        shm: same-host hand-off. ``"auto"`` (default): for an ``ipc://`` endpoint, ask the server to leave each
            batch in its shared-memory batch file (``/dev/shm``) and send only a reference; the arrays are then
            copied out of the file once (no socket copy on either side; ``v2v_client.handoff``). The server
            agrees only when bound to ``ipc://``; anything else still arrives as socket frames, and the batches
            are the same either way. ``True`` asks for any endpoint, ``False`` never.
        compact_flow: a tracked flow option (the server's ``flow_preset``, default ``tracked``) sends each
            sample's flow as its grid of tracked points, 2 x n x n values per voxel grid (n = 8: 20 KB per
            sample against 2.6 MB dense), and this client makes it dense (``flow`` below, with the server's own
            bilinear weights; about one float16-to-float32 conversion pass of CPU). With ``compact_flow=True``
            the batch keeps ``flow_grid`` float32 (B, L, 2, n, n) instead of ``flow``, to expand on the GPU with
            ``v2v_client.expand_flow_grid(grid.to(device), (H, W))``; servers with another flow option still
            send (and this client yields) dense ``flow``.
        compression: how arrays that travel over the socket are compressed, per connection: ``"none"``,
            ``"lz4"`` or ``"zstd"`` (``v2v_wire.codecs``; the server's workers compress, this client's I/O
            thread decompresses, overlapped with training). ``"auto"`` (default): none for ``ipc://`` and
            loopback ``tcp://``, ``"zstd"`` to other hosts (when ``zstandard`` is installed here and on the
            server; docs/wire.md measures the trade). The batches are the same either way.

    Yields dicts, one per batch of B samples:
        ``voxels`` float32 (B, L, num_bins, H, W), signed event counts per bin;
        ``frames`` float32 in [0, 1] (B, L + 1, 1, H, W), the frame at each voxel boundary;
        ``flow`` float32 (B, L, 2, H, W), forward optical flow in pixels from frame l to
        l + 1 (channel 0 = x, 1 = y); with ``compact_flow`` and a tracked flow option
        instead ``flow_grid`` float32 (B, L, 2, n, n), the flow at the grid points;
        ``padding`` bool (B,): True for a repeated sample the loss must ignore (DDP padding
        batches; the filler rows of accelerate's dispatch, ``v2v_client.launchers``);
        ``sample_ids`` list of B str; ``params`` list of B dicts (sensor parameters and
        augmentation); ``epoch`` int; ``batch_id`` int (-1 for padding). Only requested
        outputs are present.

    Within an epoch each sample id is yielded once (``padding`` False) over all the connections
    that share the stream (DataLoader workers, DDP ranks): the server hands every batch to one, takes
    the resume state as the truth, and the client drops re-sent samples it already yielded.
    ``state_dict()`` / ``load_state_dict()`` (StatefulDataLoader's convention) carry those ids.

    Use with ``DataLoader(ds, batch_size=None, pin_memory=True)``; it has no length. Iteration ends
    when the server ends the stream (``--epochs``); leaving the loop early (``break``) acknowledges
    what was taken before saying goodbye. Iterate one dataset object with one iterator at a time (the
    server knows it as one consumer); DataLoader workers each get their own consumer id.

    Raises (from iteration):
        StreamTimeout: the server is absent or silent for ``timeout_s``.
        StreamError: the server reported an error, broke the protocol or shut down.
        ValueError: at construction, for bad ``outputs``, ``credits``, ``timeout_s``, ``rank``/``world_size`` or keys.
    """

    def __init__(self, endpoint: Union[str, Sequence[str]], outputs: Sequence[str] = DEFAULT_OUTPUTS, credits: int = 4,
                 timeout_s: float = 30.0, heartbeat_s: float = 1.0, raw: bool = False,
                 reconnect: bool = False, reconnect_timeout_s: float = 300.0,
                 curve_keys: Optional[Tuple[str, str]] = None, rank: Optional[int] = None,
                 world_size: Optional[int] = None, group: Optional[str] = None, shm: Union[bool, str] = "auto",
                 compact_flow: bool = False, compression: str = "auto"):
        super().__init__()
        outputs = _check_options(outputs, credits, timeout_s, group, shm, compact_flow, compression)
        # a position not given is resolved when iteration starts (``_position``): a dataset built
        # before the process group exists (a DataModule's __init__) still joins the DDP group
        self._auto_position = (rank is None, world_size is None)
        self._group = group  # None: resolved when iteration starts (``_position``)
        self._instance = uuid.uuid4().hex  # this reader process's token: one reader per consumer
        rank, world_size = _checked_position(rank, world_size)
        self.endpoint = endpoint
        #: every stream setting, read from here alone (a fan-in's children are made from it)
        self.options = StreamOptions(outputs=outputs, credits=credits, timeout_s=timeout_s, heartbeat_s=heartbeat_s,
                                     raw=raw, reconnect=reconnect, reconnect_timeout_s=reconnect_timeout_s,
                                     curve_keys=curve_keys, rank=rank, world_size=world_size, group=group, shm=shm,
                                     compact_flow=compact_flow, compression=compression)
        if curve_keys:
            load_curve_keys(*curve_keys)  # bad key files are an error here, not at the first iteration
        self._stream: Optional[EndpointStream] = None
        # several servers (a list, "a,b", or a DNS name with several addresses): fan-in
        self._fanin: Optional[FanInStream] = None
        self._meter = TrainerMetrics()
        self._link = None  # a StreamLoader's workers' receipt pipes and records (read_by, loader.py)
        self.read_ahead = ReadAhead()  # what accelerate's loaders, reading ahead of the loop, make state_dict() say
        if not isinstance(endpoint, str) or "," in endpoint:
            endpoints = split_endpoints(endpoint)
            if len(endpoints) == 1:
                self.endpoint = endpoints[0]
            else:
                self._fanin = self._make_fanin(endpoints)
        if self._fanin is None:
            self._stream = EndpointStream(self.endpoint, self.options, self._instance)

    # ------------------------------------------------------------------ fan-in and metrics
    def _make_fanin(self, endpoints) -> FanInStream:
        def child(ep: str, credits: int) -> EndpointStream:  # one server's stream: these options, its share
            return EndpointStream(ep, replace(self.options, credits=credits), self._instance)

        fanin = FanInStream(endpoints, child, self.options.credits)
        if self._stream is not None:
            fanin.load_state_dict(self._stream.state_dict())
        return fanin

    def read_by(self, link) -> None:
        """Read by the DataLoader workers of a ``StreamLoader``: ``link`` (``loader.LoaderLink``)
        holds each worker's receipt pipe and the record the main process keeps for it."""
        self._link = link

    @property
    def outputs(self) -> Tuple[str, ...]:
        """The outputs asked for (``options.outputs``)."""
        return self.options.outputs

    @property
    def rank(self) -> int:
        """This reader's DDP rank (``options.rank``; resolved when iteration starts when not given)."""
        return self.options.rank

    @property
    def world_size(self) -> int:
        """The DDP world size (``options.world_size``; resolved when iteration starts when not given)."""
        return self.options.world_size

    @property
    def info(self) -> Optional[dict]:
        """The server's stream info from its welcome (the first server's with a fan-in), once connected."""
        return (self._fanin or self._stream).info

    def held(self) -> int:
        """Batches received from the server(s) and neither handed to the training loop nor
        given back yet (bounded by ``credits``: what a stalled trainer holds)."""
        return (self._fanin or self._stream).held()

    def metrics(self) -> dict:
        """Trainer-side metrics: batches, samples and tensor bytes handed to the training loop
        (also per server), and seconds it waited for them; see ``v2v_client.metrics``."""
        return self._meter.snapshot()

    def _position(self) -> None:
        """Resolve the DDP position now (:func:`resolve_position`) and hand it to the per-server streams."""
        saved = (self._fanin or self._stream).record.position
        position = resolve_position(self._auto_position, self.options, self._group, saved)
        if position == (self.options.rank, self.options.world_size, self.options.group):
            return
        rank, world, group = position
        self.options = replace(self.options, rank=rank, world_size=world, group=group)  # a fan-in's children too
        if self._stream is not None:
            self._stream.set_position(rank, world, group)

    def read_alone(self) -> None:
        """Read as the job's one consumer (accelerate's dispatcher: process 0 reads for every rank)."""
        self.options = replace(self.options, rank=0, world_size=1)
        if self._stream is not None:
            self._stream.set_position(0, 1)

    def __len__(self) -> int:
        raise TypeError(NO_LENGTH)

    def __bool__(self) -> bool:
        """True whatever ``len`` says (``if self.ds:`` would ask ``__len__``, which refuses)."""
        return True

    def set_epoch(self, epoch: int) -> None:
        """Called before each pass by accelerate; refuses a wrapper keeping part (``launchers.check_whole``)."""
        check_whole(self)

    @property
    def consumer(self) -> str:
        """The id the server knows this reader by (DataLoader workers add ``/<worker id>``)."""
        return self._stream.consumer if self._stream is not None else ""

    @consumer.setter
    def consumer(self, value: str) -> None:
        if self._stream is not None:
            self._stream.consumer = value

    def __iter__(self) -> Iterator[dict]:
        self._position()
        if self._fanin is None:
            endpoints = resolve_endpoints(self.endpoint)
            if len(endpoints) > 1:  # e.g. a Kubernetes headless Service: one server per address
                self._fanin = self._make_fanin(endpoints)
        worker = torch.utils.data.get_worker_info()
        if worker is not None:  # in a DataLoader worker process
            if self._link is None:
                raise RuntimeError(
                    "V2VPushDataset read by DataLoader worker processes: a plain DataLoader cannot tell its "
                    "workers which batches reached the training loop, so batches it prefetched and dropped would "
                    "be lost or repeated. Build the loader with v2v_client.StreamLoader(ds, num_workers=..., ...) "
                    "(DataLoader's arguments), or use num_workers=0 (the dataset prefetches `credits` batches "
                    "in its own thread)")
            if self._fanin is not None:
                raise RuntimeError("V2VPushDataset over several servers is read with num_workers=0 (the fan-in "
                                   "reads every server in its own thread)")
            self._stream.attach_loader(worker.id, self._link.receipts[worker.id], self._link.records.get(worker.id))
        inner = self.read_ahead.replay(iter(self._fanin) if self._fanin is not None else iter(self._stream))
        return adapt(self, self._meter.wrap(inner, self.endpoint if isinstance(self.endpoint, str) else ""))

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """Where this consumer stands: epochs the server declared complete, the sample ids
        yielded so far in epochs still open, batches yielded per open epoch, and the consumer
        id the server knows it by. Plain, JSON/torch.save-safe data. With several servers: the
        epoch all of them completed and the ids yielded in later epochs. Under accelerate's
        loaders, as ``launchers.ReadAhead`` says.

        Raises:
            RuntimeError: the dataset is read by a ``StreamLoader``'s workers (their records are
                in the loader: checkpoint ``loader.state_dict()``).
        """
        if self._link is not None:
            raise RuntimeError("this V2VPushDataset is read by StreamLoader workers: checkpoint the loader "
                               "(loader.state_dict()), which holds what each worker's training loop received")
        return self.read_ahead.state((self._fanin or self._stream).state_dict)

    def load_state_dict(self, state) -> None:
        """Restore ``state_dict()`` output, or every rank's (:func:`state_for_rank`); the next
        iteration resumes the epoch without repeating or skipping samples (the server takes this
        state as the truth: samples yielded after it was saved are sent again).

        Raises:
            ValueError: for a state of another format (a rank's state loaded at another position
                is refused when iteration starts, naming what to load).
        """
        state = state_for_rank(state)
        ResumeState().load(state)  # ValueError for a state of another format, before anything changes
        self.read_ahead.clear()  # the state says what the loop received
        if self._stream is not None:
            self._stream.load_state_dict(state)
        if self._fanin is not None:
            self._fanin.load_state_dict(state)

    def close(self) -> None:
        """Close every open connection of this dataset (also done when iterators are collected)."""
        if self._fanin is not None:
            self._fanin.close()
        if self._stream is not None:
            self._stream.close()


def _check_options(outputs, credits, timeout_s, group, shm, compact_flow, compression) -> Tuple[str, ...]:
    """The constructor's option checks; the outputs as ``check_outputs`` gives them.

    Raises:
        ValueError: naming the argument and the value given.
    """
    outputs = check_outputs(outputs)
    if isinstance(credits, bool) or not isinstance(credits, int) or not 1 <= credits <= MAX_CREDITS:
        raise ValueError(f"credits must be an int in [1, {MAX_CREDITS}], got {credits!r}")
    if not timeout_s > 0:
        raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
    if group is not None and (not isinstance(group, str) or not group or len(group) > 128):
        raise ValueError(f"group must be a non-empty string of at most 128 characters, got {group!r}")
    if shm not in (True, False, "auto"):
        raise ValueError(f"shm must be True, False or 'auto', got {shm!r}")
    if not isinstance(compact_flow, bool):
        raise ValueError(f"compact_flow must be True or False, got {compact_flow!r}")
    if compression != "auto":
        check_compression(compression)
        if not available(compression):
            raise ValueError(f"compression {compression!r} needs its library here: pip install 'v2v[wire]'")
    return outputs


def _checked_position(rank: Optional[int], world_size: Optional[int]) -> Tuple[int, int]:
    """``(rank, world_size)`` with the stand-ins for what was not given (rank 0; a world just
    large enough for the rank) until iteration resolves them.

    Raises:
        ValueError: for a world size < 1 or a rank outside ``[0, world_size)``.
    """
    rank = 0 if rank is None else rank
    world_size = (rank + 1 if rank else 1) if world_size is None else world_size
    if isinstance(world_size, bool) or not isinstance(world_size, int) or world_size < 1:
        raise ValueError(f"world_size must be an int >= 1, got {world_size!r}")
    if isinstance(rank, bool) or not isinstance(rank, int) or not 0 <= rank < world_size:
        raise ValueError(f"rank must be an int in [0, world_size={world_size}), got {rank!r}")
    return rank, world_size


def state_for_rank(state) -> dict:
    """What this process loads of a saved state: one rank's state as it is; of every rank's
    states (a list, or ``{"v2v_ranks": [...]}``: what ``launchers.prepare_loader``'s save hook
    keeps) its own rank's at the world size they were saved at (``launchers.rank_part``), else all
    of them gathered (``ResumeState.gathered``: a job resumed at another world size)."""
    if isinstance(state, list) or (isinstance(state, dict) and RANKS in state
                                   and len(state[RANKS]) != dist_position()[1]):
        return ResumeState.gathered(state if isinstance(state, list) else state[RANKS]).state()
    return rank_part(state, dist_position)


def resolve_position(auto: Tuple[bool, bool], options: StreamOptions, group: Optional[str],
                     saved: Optional[Tuple[str, int, int]]) -> Tuple[int, int, str]:
    """``(rank, world_size, group)`` a dataset reads at when iteration starts: the rank and world
    size given to it, else :func:`dist_position`'s (``auto``: which were not given); the group
    given, else the one the loaded state was saved in (``saved``, ``ResumeState.position``), else
    ``options.job_group()`` (named from the job's launcher).

    Raises:
        ValueError: a rank outside ``[0, world_size)``.
    """
    rank, world = options.rank, options.world_size
    if auto[0] or auto[1]:
        r, w = dist_position()
        rank, world = (r if auto[0] else rank), (w if auto[1] else world)
        if not 0 <= rank < world:
            raise ValueError(f"rank {rank} is not in [0, world_size={world})")
    return rank, world, group or (saved[0] if saved is not None and saved[2] > 1 and saved[0] else None) or job_group()


def dist_position() -> Tuple[int, int]:
    """This process's DDP ``(rank, world_size)``: from ``torch.distributed`` when its process
    group is initialised, else from the ``RANK`` / ``WORLD_SIZE`` environment variables that
    torchrun, Lightning's launcher and most cluster launchers set, else ``(0, 1)``.

    Raises:
        ValueError: the two disagree (a process group of world size 1 in a process whose
            environment says 2: the ranks would not form one group and would yield unequal
            batch counts), the environment holds something that is not a rank, or it gives a
            WORLD_SIZE above 1 without a RANK and no process group is initialised.
    """
    env = None
    if os.environ.get("WORLD_SIZE") is not None:
        try:
            env = int(os.environ.get("RANK", "0")), int(os.environ["WORLD_SIZE"])
        except ValueError:
            raise ValueError(f"RANK={os.environ.get('RANK')!r} / WORLD_SIZE={os.environ.get('WORLD_SIZE')!r} "
                             f"in the environment are not integers") from None
    dist = None
    try:
        import torch.distributed as td

        if td.is_available() and td.is_initialized():
            dist = td.get_rank(), td.get_world_size()
    except (RuntimeError, ValueError):  # a backend half set up is the same as none here
        dist = None
    if dist is None and env is not None and env[1] > 1 and os.environ.get("RANK") is None:
        # no process group to ask (Lightning's rank 0 sets WORLD_SIZE without RANK, but has one by
        # the time it iterates): every process would take rank 0's share
        raise ValueError(f"WORLD_SIZE={env[1]} in the environment but no RANK and no torch.distributed process "
                         f"group: set RANK, or pass rank= and world_size= to V2VPushDataset explicitly")
    if dist is not None and env is not None and dist[1] != env[1]:
        raise ValueError(f"torch.distributed says world size {dist[1]} but WORLD_SIZE={env[1]} in the "
                         f"environment: pass rank= and world_size= to V2VPushDataset explicitly")
    return dist or env or (0, 1)

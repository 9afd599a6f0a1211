"""Reading a server that serves by plan (``v2v-serve --delivery plan``, docs/plan.md) as a torch
dataset: each rank's batch at each step is a fixed slice of the epoch's plan, fetched by position.

The dataset holds no socket and no lock: each process that iterates it (the main process, a
DataLoader worker started by fork, spawn or forkserver) opens its own connection, so it pickles
as plain settings. With ``k`` DataLoader workers, worker ``j`` reads steps ``j, j + k, ...``, and
the DataLoader's round robin yields them in step order.
"""
from __future__ import annotations

import itertools
import time
from typing import Dict, Iterator, Optional, Sequence

import torch
import zmq

from v2v_wire.messages import WireError
from v2v_wire.plan import PlanMismatch, Position
from v2v_wire.plan_messages import Fetch, PlanAsk, PlanInfo, Refused, Rows, plan_server_message
from v2v_wire.protocol import DEFAULT_OUTPUTS, MAX_BATCH_BYTES, ProtocolError, check_outputs, decode_arrays, pack, unpack

from .tensors import batch_to_torch

__all__ = ["V2VPlanDataset"]


class PlanServerError(RuntimeError):
    """The server refused a fetch, or sent what this client cannot read (the message says which
    endpoint and why, in one line)."""


class V2VPlanDataset(torch.utils.data.IterableDataset):
    """One rank's batches of one epoch of a plan served at ``endpoint``.

    Args:
        endpoint: the server's address (``tcp://host:port``).
        batch_size: rows per batch of this rank (>= 1).
        rank, world_size: this rank and the job's ranks (default: ``torch.distributed``'s when
            first needed, if initialised, else 0 and 1).
        outputs: which of ``OUTPUTS`` to read (default ``DEFAULT_OUTPUTS``, as
            ``V2VStreamDataset``'s: the server's workers make only the outputs its readers ask for).
        raw: keep the wire dtypes (``tensors.batch_to_torch``).
        prefetch: fetches in flight per process (>= 1).
        retry_s: seconds a fetch may go unanswered before it is asked again (a lost reply, a
            restarted server).
        timeout_s: seconds of silence from the server before :class:`TimeoutError`.

    Each item is a dict: the tensors of ``batch_to_torch`` with a leading axis of ``batch_size``,
    ``padding`` (bool (B,): rows that carry no sample, zeros: past the epoch's end or a window the
    file did not give), ``sample_ids`` (None for a row past the end), ``params``, ``epoch``,
    ``step``, and ``position``: the checkpoint after this step (``Position.to_dict``), the same on
    every rank; :meth:`load_state_dict` takes it, at any world size and batch size.

    Raises:
        ValueError: a bad setting, naming it.
    """

    def __init__(self, endpoint: str, batch_size: int, *, rank: Optional[int] = None,
                 world_size: Optional[int] = None, outputs: Sequence[str] = DEFAULT_OUTPUTS, raw: bool = False,
                 prefetch: int = 2, retry_s: float = 10.0, timeout_s: float = 120.0):
        super().__init__()
        for name, v in (("batch_size", batch_size), ("prefetch", prefetch)):
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"{name} must be an int >= 1, got {v!r}")
        if not 0 < retry_s <= timeout_s:
            raise ValueError(f"retry_s must be > 0 and <= timeout_s, got {retry_s} and {timeout_s}")
        if rank is not None or world_size is not None:
            _check_layout(0 if rank is None else rank, 1 if world_size is None else world_size)
        self.endpoint, self.batch_size, self._rank, self._world = endpoint, batch_size, rank, world_size
        self.outputs = check_outputs(outputs, "outputs")
        self.raw, self.prefetch, self.retry_s, self.timeout_s = raw, prefetch, retry_s, timeout_s
        self.epoch, self.start = 0, 0
        self._resume: Optional[dict] = None  # a loaded position, checked once the plan is known
        self._info: Optional[PlanInfo] = None

    # ------------------------------------------------------------------ layout
    @property
    def rank(self) -> int:
        """This rank: as given, else ``torch.distributed``'s when initialised (asked when first
        needed, so a dataset built before the process group, as a DataModule's, finds it), else 0."""
        return self._layout()[0]

    @property
    def world_size(self) -> int:
        """The job's ranks: as given, else ``torch.distributed``'s when initialised, else 1."""
        return self._layout()[1]

    def _layout(self):
        rank, world = self._rank, self._world
        if rank is None or world is None:
            dist = torch.distributed
            on = dist.is_available() and dist.is_initialized()
            rank = rank if rank is not None else (dist.get_rank() if on else 0)
            world = world if world is not None else (dist.get_world_size() if on else 1)
            _check_layout(rank, world)
        return rank, world

    def __getstate__(self) -> dict:
        """Pickled (a DataLoader worker started by spawn or forkserver, where the process group
        does not exist) with the layout this process sees."""
        state = dict(self.__dict__)
        state["_rank"], state["_world"] = self._layout()
        return state

    # ------------------------------------------------------------------ epochs and positions
    def set_epoch(self, epoch: int) -> None:
        """Read ``epoch`` next: from the loaded position when it is that epoch's, else from its start."""
        if not isinstance(epoch, int) or isinstance(epoch, bool) or epoch < 0:
            raise ValueError(f"epoch must be an int >= 0, got {epoch!r}")
        self.epoch = epoch
        self.start = self._resume["sample_in_epoch"] if self._resume and self._resume["epoch"] == epoch else 0

    def load_state_dict(self, state: dict) -> None:
        """Resume at a position (a batch's ``position``), taken at any world size and batch size:
        its epoch is read next, from that position.

        Raises:
            PlanMismatch: a malformed position (naming the field), one of another plan than the
                server's (one line naming what differs; checked when the server is first asked),
                or a push stream's resume state (``V2VStreamDataset`` / ``StreamLoader``: the sample
                ids it delivered, which no position of a plan's fixed slices stands for).
        """
        if isinstance(state, dict) and "delivered" in state and "plan" not in state:
            raise PlanMismatch(f"a push stream's resume state (of consumer {state.get('consumer')!r}, completed epoch "
                               f"{state.get('completed_epoch')!r}) is not a plan's position: resume from a batch's "
                               f"'position', or read an epoch from its start with set_epoch()")
        pos = Position.from_dict(state)
        self._resume = pos.to_dict()
        if self._info is not None:
            Position.from_dict(self._resume, expected=self._info.plan)
        self.set_epoch(pos.epoch)

    def plan_info(self) -> PlanInfo:
        """What the server serves (asked once per dataset object and process).

        Raises:
            TimeoutError: no answer within ``timeout_s``.
            PlanMismatch: a loaded position of another plan.
        """
        if self._info is None:
            with _Link(self.endpoint, self.timeout_s) as link:
                self._info = link.ask()
            if self._resume is not None:
                Position.from_dict(self._resume, expected=self._info.plan)
        return self._info

    def __len__(self) -> int:
        """Steps of this rank in the epoch from its start position (every rank the same)."""
        n = self.plan_info().samples
        return max(0, -(-(n - self.start) // (self.world_size * self.batch_size)))

    # ------------------------------------------------------------------ reading
    def __iter__(self) -> Iterator[Dict]:
        info = self.plan_info()
        steps = len(self)
        w = torch.utils.data.get_worker_info()
        mine = range(w.id, steps, w.num_workers) if w is not None else range(steps)
        per_step = self.world_size * self.batch_size
        with _Link(self.endpoint, self.timeout_s) as link:
            first = self.start + self.rank * self.batch_size  # of step 0
            for step, rows, arrays in link.fetch_all(mine, self.prefetch, self.retry_s, lambda req, s: Fetch(
                    req, self.epoch, first + s * per_step, first + s * per_step + self.batch_size, self.outputs, info.plan)):
                yield self._item(info, step, rows, arrays)

    def _item(self, info: PlanInfo, step: int, rows: Rows, arrays) -> Dict:
        crop = info.stream.get("crop_size")
        item = batch_to_torch(arrays, self.raw, (crop, crop) if crop else None,
                              info.stream.get("flow_dtype", "float16"))
        after = self.start + (step + 1) * self.world_size * self.batch_size
        item.update(padding=torch.tensor(rows.padding, dtype=torch.bool), sample_ids=rows.sample_ids,
                    params=rows.params, epoch=self.epoch, step=step,
                    position=Position(info.plan, self.epoch, after).to_dict())
        return item


def _check_layout(rank: int, world_size: int) -> None:
    if not isinstance(world_size, int) or isinstance(world_size, bool) or world_size < 1:
        raise ValueError(f"world_size must be an int >= 1, got {world_size!r}")
    if not isinstance(rank, int) or isinstance(rank, bool) or not 0 <= rank < world_size:
        raise ValueError(f"rank must be in 0..{world_size - 1}, got {rank!r}")


class _Link:
    """One process's connection to a plan server: a DEALER socket, requests numbered from 1."""

    def __init__(self, endpoint: str, timeout_s: float):
        self.endpoint, self.timeout_s = endpoint, timeout_s
        self.ctx = zmq.Context()
        self.sock = self.ctx.socket(zmq.DEALER)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.connect(endpoint)
        self.ids = itertools.count(1)

    def __enter__(self) -> "_Link":
        return self

    def __exit__(self, *exc) -> None:
        self.sock.close()
        self.ctx.term()

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
            self.sock.send(pack(PlanAsk().to_wire()))
            got = self._recv(min(deadline, time.monotonic() + 5.0))
            if got is not None and isinstance(got[0], PlanInfo):
                return got[0]
            if got is not None and isinstance(got[0], Refused):
                raise PlanServerError(f"{self.endpoint}: {got[0].message}")
            if time.monotonic() >= deadline:
                raise TimeoutError(f"{self.endpoint}: no answer to 'what do you serve' within {self.timeout_s} s "
                                   "(is a server with --delivery plan running there?)")

    def fetch_all(self, steps, prefetch: int, retry_s: float, fetch_of) -> Iterator:
        """``(step, rows, arrays)`` for each of ``steps`` in order, ``prefetch`` fetches in
        flight; an unanswered fetch is asked again after ``retry_s`` (the first answer wins).
        ``fetch_of(request, step)``: the step's :class:`Fetch` under that request id."""
        todo = iter(steps)
        waiting: Dict[int, int] = {}  # request id -> step
        asked: Dict[int, float] = {}  # step -> when last asked
        done: Dict[int, tuple] = {}
        order = []
        heard = time.monotonic()

        def send(step: int) -> None:
            req = next(self.ids)
            self.sock.send(pack(fetch_of(req, step).to_wire()))
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
                raise PlanMismatch(f"{self.endpoint}: {msg.message}") if "another plan" in msg.message else \
                    PlanServerError(f"{self.endpoint}: {msg.message}")
            if not isinstance(msg, Rows) or msg.request not in waiting:
                continue  # an answer to a request asked again, or to a plan_ask
            step = waiting.pop(msg.request)
            if step in done or step not in order:
                continue
            try:
                arrays = decode_arrays(msg.arrays, frames, MAX_BATCH_BYTES)
            except ProtocolError as e:
                raise PlanServerError(f"{self.endpoint}: rows of step {step}: {e}") from None
            done[step] = (msg, arrays)


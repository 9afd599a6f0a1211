"""A plan reader's state, apart from the dataset that reads (``plan_dataset.V2VStreamDataset``):
where an iteration starts and what it has read (a position and the ``reader`` part of
``state_dict``), a loaded state checked and placed, the layout an iteration reads with, and the
control block in shared memory through which ``set_epoch`` and ``load_state_dict`` in the main
process reach the DataLoader workers' copies (:class:`_Control`)."""
from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Optional, Tuple

import numpy as np
import torch

from v2v_wire.plan import PlanMismatch, Position, batch_positions
from v2v_wire.plan_messages import PlanInfo
from v2v_wire.push_names import resume_state_problem


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

    def publish(self, ds) -> None:
        """In the main process, write what ``ds``'s next pass reads (epoch, start, loaded state),
        for the DataLoader workers' copies; a worker's own load stays its own."""
        if torch.utils.data.get_worker_info() is None:
            ds._seen = self.write({"epoch": ds.epoch, "start": ds.start, "resume": ds._resume, "pending": ds._pending})
        else:
            ds._seen = self.generation()

    def adopt(self, ds) -> None:
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


def _check_settings(batch_size: int, prefetch: int, retry_s: float, timeout_s: float) -> None:
    for name, v in (("batch_size", batch_size), ("prefetch", prefetch)):
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            raise ValueError(f"{name} must be an int >= 1, got {v!r}")
    if not 0 < retry_s <= timeout_s:
        raise ValueError(f"retry_s must be > 0 and <= timeout_s, got {retry_s} and {timeout_s}")


_LENGTH_UNKNOWN = ("the epoch's length is not known yet: the server learns each video's windows from its first "
                   "decode (v2v-serve --check counts them ahead)")


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
    """Global positions ``[start, stop)`` of item ``i`` of an iteration read as ``r`` says
    (``v2v_wire.plan.batch_positions`` at its ``world``, from its ``origin``): under the
    dispatcher step ``i // group``'s rank ``i % group``, else step ``i`` of this rank."""
    g = r["group"]
    step, rank = divmod(i, g) if g > 1 else (i, r["rank"])
    rows = batch_positions(step, rank, r["world"], batch_size, r["origin"])
    return rows.start, rows.stop


def _loaded_position(state, info: Optional[PlanInfo]) -> Position:
    """The position of a state given to ``load_state_dict``, checked against ``info``'s plan where
    the server was asked already (None: not yet).

    Raises:
        PlanMismatch: a resume state of push delivery (one line saying what to resume from:
            ``push_names.resume_state_problem``), a malformed position (naming the field), or one
            of another plan than ``info``'s.
    """
    if resume_state_problem(state):
        raise PlanMismatch(resume_state_problem(state))
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

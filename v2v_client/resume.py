"""What one reader has had from a stream: :class:`ResumeState`, the one resume-state type of the
client (no torch, no socket), kept by a server's stream (``endpoint.EndpointStream``), by
``StreamLoader`` for each of its DataLoader workers (in the main process, from the loop's
receipts) and by a fan-in (what it handed to the loop from all its servers).

Plain form (``state()`` / ``load()``, what ``state_dict()`` holds; JSON- and torch.save-safe)::

    {"version": 1, "consumer": str, "completed_epoch": int, "delivered": {"<epoch>": [sample ids]},
     "batches": {"<epoch>": int}, "recipe": str | None,
     # optional: where it was saved ("group", "rank", "world_size"), a fan-in's per-shard batch
     # counts ("shard_batches": {shard: {"<epoch>": int}}, "shard_of": {endpoint: shard})}

Wire form (``hello_resume()``, a hello's ``resume``): ``messages.ResumeIds``. The rules the
record keeps are docs/delivery.md ("The client's book"): the ids of an epoch are forgotten when
the server says it is complete; a claim records a batch's new ids in the same step as the batch
is taken; a DataLoader worker's batches wait in ``pipeline`` until the loop's receipt.
"""
from __future__ import annotations

import threading
from typing import Callable, Dict, Iterable, Iterator, List, Optional, Set, Tuple

from v2v_wire.messages import MAX_MAP_LEN, ResumeIds

__all__ = ["ResumeState", "STATE_VERSION", "owed_padding", "take_epoch_end"]

STATE_VERSION = 1


def _epoch_map(value, what: str) -> Dict[int, object]:
    if not isinstance(value, dict):
        raise ValueError(f"resume state: {what} must be a map of epochs, got {type(value).__name__}")
    try:
        return {int(e): v for e, v in value.items()}
    except (TypeError, ValueError):
        raise ValueError(f"resume state: {what} keys must be epoch numbers") from None


class Pipeline(dict):
    """A DataLoader worker's batches yielded to the loader whose receipt has not come: batch id ->
    (epoch, sample ids). A hello names their ids as handed on (the loop may still receive them), so
    the server may take them and tell their epoch complete first: the record completes that epoch
    only once their receipts came, and a loop that leaves without them (:meth:`clear`) leaves it
    open, so the next hello has them owed again (docs/delivery.md, "DataLoader workers")."""

    def __init__(self):
        super().__init__()
        self.told = -1  # the newest epoch told complete (``complete_upto``)

    def complete_upto(self, epoch: int, completed: int) -> int:
        """Told ``epoch`` complete (``completed``: none newly), a record that completed ``completed``
        forgets the epochs up to the returned one: none while a batch of one told complete waits here."""
        self.told = max(self.told, epoch)
        if any(e <= self.told for e, _ in self.values()):
            return completed
        return max(self.told, completed)

    def queued(self, completed: int) -> Dict[int, int]:
        """A hello's ``queued``: batch id -> epoch of those after ``completed``, the oldest ``MAX_MAP_LEN``
        (the server tells their epochs to the connection only once it acks them; docs/delivery.md,
        "DataLoader workers")."""
        return dict(list((b, e) for b, (e, _) in self.items() if e > completed)[:MAX_MAP_LEN])

    def clear(self) -> None:
        """The loop left without these batches: what they wait for is not told complete any more."""
        super().clear()
        self.told = -1


class ResumeState:
    """One reader's record: ``consumer`` (the id the server knows it by), ``completed_epoch`` (the last epoch the
    server declared complete to it), ``delivered`` (epoch -> sample ids handed to the training loop, open epochs
    only), ``batches`` (epoch -> batches handed on, DDP padding included), ``recipe`` (the sample recipe's
    fingerprint the ids were made under), the DDP position it was saved at (``group``, ``rank``, ``world_size``),
    and in a DataLoader worker ``pipeline`` (batch id -> (epoch, sample ids) yielded to the DataLoader, receipt not
    yet come). Thread-safe (``lock``): an I/O thread records receipts while the consumer iterates."""

    def __init__(self, consumer: str = ""):
        self.lock, self.consumer, self.completed_epoch = threading.Lock(), consumer, -1
        self.delivered: Dict[int, Set[str]] = {}
        self.batches: Dict[int, int] = {}
        self.recipe: Optional[str] = None
        self.position: Optional[Tuple[str, int, int]] = None  # (group, rank, world size) it was saved at
        self.shard_batches: Dict[str, Dict[int, int]] = {}  # a fan-in's batches per shard per open epoch
        self.shard_of: Dict[str, str] = {}  # a fan-in's endpoint -> the shard it served
        self.pipeline = Pipeline()
        self.owed: Dict[int, int] = {}  # epoch told complete and open -> DDP padding to yield (not saved: told again)
        self.told: Dict[int, int] = {}  # epoch told complete and open -> the most batches its ends said (DDP)
        #: the consumers a state gathered from every rank of a job speaks for, each with its completed epoch
        self.supersedes: Tuple[Tuple[str, int, int], ...] = ()
        self.origins: Set[str] = set()  # the servers (their welcome's ``server``) that granted its ids

    def state(self) -> dict:
        """The plain form (module docstring)."""
        with self.lock:
            out = {"version": STATE_VERSION, "consumer": self.consumer, "completed_epoch": self.completed_epoch,
                   "delivered": {str(e): sorted(ids) for e, ids in self.delivered.items()},
                   "batches": {str(e): n for e, n in self.batches.items()}, "recipe": self.recipe}
            if self.position is not None:
                out.update(zip(("group", "rank", "world_size"), self.position))
            if self.supersedes:
                out["supersedes"] = [list(c) for c in self.supersedes]
            if self.origins:
                out["origins"] = sorted(self.origins)
            if self.shard_batches or self.shard_of:
                out["shard_batches"] = {sh: {str(e): n for e, n in per.items()} for sh, per in self.shard_batches.items()}
                out["shard_of"] = dict(self.shard_of)
            return out

    def load(self, state) -> None:
        """Take the plain form (``state()``, of this or an older release).

        Raises:
            ValueError: a state of another format, naming what is wrong.
        """
        if not isinstance(state, dict) or state.get("version") != STATE_VERSION:
            raise ValueError("state must come from V2VPushDataset.state_dict() (version 1)")
        completed = state.get("completed_epoch", -1)
        if isinstance(completed, bool) or not isinstance(completed, int) or completed < -1:
            raise ValueError(f"resume state: completed_epoch must be an integer >= -1, got {completed!r}")
        delivered = {e: set(ids) for e, ids in _epoch_map(state.get("delivered", {}), "delivered").items()}
        if not all(isinstance(s, str) for ids in delivered.values() for s in ids):
            raise ValueError("resume state: delivered must hold sample id strings")
        batches = {e: int(n) for e, n in _epoch_map(state.get("batches", {}), "batches").items()}
        shards = {str(sh): {e: int(n) for e, n in _epoch_map(per, "shard_batches").items()}
                  for sh, per in (state.get("shard_batches") or {}).items()}
        position = ((str(state.get("group") or ""), state["rank"], state["world_size"])
                    if isinstance(state.get("world_size"), int) and isinstance(state.get("rank"), int) else None)
        supersedes = tuple((str(k[0]), int(k[1]), int(k[2] if len(k) > 2 else completed))
                           for k in state.get("supersedes") or ())
        origins = {str(o) for o in state.get("origins") or ()}
        with self.lock:
            self.completed_epoch, self.delivered, self.batches = completed, delivered, batches
            self.shard_batches, self.shard_of = shards, dict(state.get("shard_of") or {})
            self.position, self.supersedes, self.origins, self.owed, self.told = position, supersedes, origins, {}, {}
            if isinstance(state.get("consumer"), str) and state["consumer"]:
                self.consumer = state["consumer"]
            if isinstance(state.get("recipe"), str):
                self.recipe = state["recipe"]

    def hello_resume(self) -> ResumeIds:
        """A hello's resume state: the completed epoch, the ids handed on per open epoch (in a DataLoader worker also
        those waiting in the loader's queues, the loop may still receive them, and those batches as ``queued``) and
        the batches per open epoch. It forgets the padding owed, keeping its count (``told``): those ends come again."""
        with self.lock:
            ids, self.owed = {e: set(v) for e, v in self.delivered.items()}, {}
            for e, sids in self.pipeline.values():
                if e > self.completed_epoch:
                    ids.setdefault(e, set()).update(sids)
            return ResumeIds(self.completed_epoch, {e: tuple(sorted(v)) for e, v in ids.items()}, dict(self.batches),
                             self.supersedes, tuple(sorted(self.origins))[-16:], self.pipeline.queued(self.completed_epoch))

    def check_recipe(self, recipe) -> Optional[str]:
        """A server's recipe fingerprint: why the record refuses it (its ids were made under
        another recipe), or None (the fingerprint is kept)."""
        with self.lock:
            if self.recipe is not None and isinstance(recipe, str) and recipe != self.recipe:
                return (f"it serves another sample recipe ({recipe}) than the one this resume state was made "
                        f"under ({self.recipe}): seed, sequence length, bins, crop or crops per window differ, "
                        f"so its sample ids name other samples. Resume against a server with the same recipe, or "
                        f"start without the state")
            if isinstance(recipe, str):
                self.recipe = recipe
        return None

    def key(self) -> Tuple[str, int]:
        """The consumer the server knew its reader as: ``("g:<group>", rank)`` (DDP), else ``("c:<id>", 0)``."""
        if self.position is not None and self.position[2] > 1:
            return "g:" + (self.position[0] or "default"), self.position[1]
        return "c:" + self.consumer, 0

    @classmethod
    def gathered(cls, states: List[dict]) -> "ResumeState":
        """One state for a job resumed at another world size, from the state of every rank of the job that saved
        them: the oldest completed epoch among them (a later one may lack what a rank had been granted and not
        taken), the ids of the later epochs together (a rank forgot only those of epochs its state completed), per
        epoch the most batches a rank yielded (where DDP padding counts from), and the consumers it speaks for
        (``supersedes``: every rank's, with its completed epoch: the server keeps what it granted in those).
        Every rank of the new job loads it (docs/delivery.md, "A world size changes").

        Raises:
            ValueError: no state, or one of another format.
        """
        if not states:
            raise ValueError("no rank's state to gather")
        parts = [cls() for _ in states]
        for p, st in zip(parts, states):
            p.load(st)
        out = cls(parts[0].consumer)
        out.completed_epoch = min(p.completed_epoch for p in parts)
        for p in parts:  # a part's epochs are all after its completed one
            for e, ids in p.delivered.items():
                out.delivered.setdefault(e, set()).update(ids)
            for e, n in p.batches.items():
                out.batches[e] = max(out.batches.get(e, 0), n)
            out.recipe = out.recipe or p.recipe
        out.supersedes = tuple(dict.fromkeys(k for p in parts for k in ((*p.key(), p.completed_epoch),) + p.supersedes))
        out.origins = set().union(*(p.origins for p in parts))
        return out

    def place(self, group: str, rank: int, world_size: int) -> None:
        """This state's reader is about to say hello as ``rank`` of ``world_size`` in ``group``. A state saved by
        one rank of a DDP job at another position speaks for that rank alone: refused. One reader's whole state
        (world size 1) may start every rank of a new job (it then speaks for that reader); a gathered one, any.

        Raises:
            ValueError: one line saying what to load instead.
        """
        with self.lock:
            saved = self.position
            if saved is not None and not self.supersedes and (saved[1], saved[2]) != (rank, world_size):
                if saved[2] > 1:
                    raise ValueError(
                        f"this V2VPushDataset state was saved by rank {saved[1]} of {saved[2]} and is loaded by rank "
                        f"{rank} of {world_size}: it holds that rank's samples only. Resume at world size {saved[2]} "
                        f"with each rank's own state, or load every rank's state in each rank: "
                        f"ds.load_state_dict({{'v2v_ranks': [state of rank 0, ..., state of rank {saved[2] - 1}]}})")
                self.supersedes = ((f"c:{self.consumer}", 0, self.completed_epoch),)  # one reader's, read by a job
                self.batches.clear()  # the reader's counts, not the rank's: DDP padding counts from 0
            self.position = (group if world_size > 1 else "", rank, world_size)

    def welcomed(self, server: Optional[str]) -> None:
        """Server ``server`` (its welcome's id) welcomed this state's hello: what it grants is
        named by its id from now on (``origins``), and the consumers a gathered state superseded
        are settled there (later hellos speak for this reader alone)."""
        with self.lock:
            self.supersedes = ()
            if not any(self.delivered.values()) and not self.pipeline:
                self.origins.clear()  # nothing of another server's left
            if isinstance(server, str) and server:
                self.origins.add(server)

    def complete(self, epoch: int, batches_due: Optional[int] = None, stale: bool = False) -> Optional[int]:
        """The server declared ``epoch`` complete: its ids (and those of every epoch before it) are forgotten once
        the padding it owes is yielded (``batches_due``: with DDP, batches every rank yields, never fewer than an end
        told before said; :meth:`count_padding`). Returns that padding, or None (complete already; ``stale``: told a
        session a hello ended, only its count kept) (docs/delivery.md, "Ends of epochs")."""
        with self.lock:
            if epoch <= self.completed_epoch:
                return None
            if batches_due is not None:
                due = self.told[epoch] = max(batches_due, self.told.get(epoch, 0))
                if stale:
                    return None
                self.owed[epoch] = max(0, due - self.batches.get(epoch, 0))
            self._forget_upto(self.pipeline.complete_upto(epoch, self.completed_epoch))
            return self.owed.get(epoch, 0)

    def is_complete(self, epoch: int) -> bool:
        with self.lock:
            return epoch <= self.completed_epoch

    def count_padding(self, epoch: Optional[int] = None) -> Optional[int]:
        """A DDP padding batch goes to the loop now: of the oldest epoch owing one, else of ``epoch``
        (a server's copy) if open and not told complete here; counted in it. Returns that epoch, or None."""
        with self.lock:
            e = min((e for e, n in self.owed.items() if n), default=epoch)
            if e is None or e <= self.completed_epoch or self.owed.get(e) == 0:
                return None
            self.batches[e] = self.batches.get(e, 0) + 1
            if e in self.owed:
                self.owed[e] -= 1
                self._forget_upto(self.pipeline.complete_upto(e, self.completed_epoch))
        return e

    def claim(self, epoch: int, batch_id: int, sample_ids: List[str], loader: bool) -> List[int]:
        """Positions of a claimed batch's samples neither handed on nor in the pipeline already.
        They are recorded as handed on (the batch counted), or with ``loader`` put in the
        pipeline until the training loop's receipt (:meth:`received`)."""
        with self.lock:
            seen = self.delivered.setdefault(epoch, set())
            queued = {s for e, ids in self.pipeline.values() if e == epoch for s in ids}
            keep = [i for i, sid in enumerate(sample_ids) if sid not in seen and sid not in queued]
            if loader:
                if keep:
                    self.pipeline[batch_id] = (epoch, [sample_ids[i] for i in keep])
            else:
                seen.update(sample_ids[i] for i in keep)
                self.batches[epoch] = self.batches.get(epoch, 0) + 1
        return keep

    def received(self, batch_ids: Iterable[int]) -> List[int]:
        """The training loop received these batches (a DataLoader worker's receipts): they count
        as handed on; returns those that were in the pipeline."""
        mine = []
        with self.lock:
            for bid in batch_ids:
                entry = self.pipeline.pop(bid, None)
                if entry is not None:
                    epoch, ids = entry
                    if epoch > self.completed_epoch:
                        self.delivered.setdefault(epoch, set()).update(ids)
                        self.batches[epoch] = self.batches.get(epoch, 0) + 1
                    mine.append(bid)
            self._forget_upto(self.pipeline.complete_upto(self.completed_epoch, self.completed_epoch))
        return mine

    def handed_on(self, epoch: int, sample_ids: Iterable[str], completed_epoch: int = -1,
                  shard: Optional[str] = None) -> None:
        """A batch of ``epoch`` reached the training loop (``StreamLoader``'s record of a worker,
        kept from the receipts in the main process; a fan-in's record): its ids and the batch
        count, after forgetting the epochs up to ``completed_epoch`` (what the worker knew
        complete when it yielded it); ``shard``: counted for that shard (a fan-in)."""
        with self.lock:
            if completed_epoch > self.completed_epoch:
                self._forget_upto(completed_epoch)
            if epoch <= self.completed_epoch:
                return
            self.delivered.setdefault(epoch, set()).update(sample_ids)
            per = self.batches if shard is None else self.shard_batches.setdefault(shard, {})
            per[epoch] = per.get(epoch, 0) + 1

    def not_handed_on(self, epoch: int, sample_ids: Iterable[str], endpoint: Optional[str] = None) -> None:
        """Undo :meth:`handed_on` for a batch of an open ``epoch`` that the training loop never
        received (``launchers.unseen``); ``endpoint``: a fan-in's, counted for the shard it serves."""
        with self.lock:
            if epoch > self.completed_epoch and epoch in self.delivered:
                self.delivered[epoch].difference_update(sample_ids)
                shard = self.shard_of.get(endpoint, endpoint)
                per = self.shard_batches.get(shard, {}) if self.shard_batches else self.batches
                if per.get(epoch, 0) > 0:
                    per[epoch] -= 1

    def _forget_upto(self, epoch: int) -> None:
        epoch = min([epoch] + [e - 1 for e, n in self.owed.items() if n])  # an epoch owing DDP padding stays open
        self.completed_epoch = max(self.completed_epoch, epoch)
        for d in [self.delivered, self.batches, self.owed, self.told, *self.shard_batches.values()]:
            for e in [e for e in d if e <= epoch]:
                del d[e]

    def pipeline_ids(self) -> List[int]:
        with self.lock:
            return list(self.pipeline)

    def clear_pipeline(self) -> None:
        """Forget the batches in the DataLoader's queues (they go back to the server)."""
        with self.lock:
            self.pipeline.clear()


def take_epoch_end(record: ResumeState, done, ddp: bool, current: bool) -> None:
    """An epoch end (``stream_messages.EpochDone``) the loop takes off its queue, recorded in the step
    that finds whether it was told to the current session (``current``; ``HeldBatches.of_session``):
    the epoch completes in ``record``, with DDP owing the padding its count says (``ResumeState.complete``);
    one told a session a hello ended keeps only its DDP count, as the server tells the new session
    again (docs/delivery.md, "Ends of epochs")."""
    if current or ddp:
        record.complete(done.epoch, done.batches if ddp else None, stale=not current)


def owed_padding(record: ResumeState, source: dict, copy: Callable[[dict, int], dict],
                 own: bool = False) -> Iterator[dict]:
    """The DDP padding batches ``record``'s reader yields now, each counted in the record as it is
    yielded (``ResumeState.count_padding``): what it owes, oldest epoch first, as ``copy(source,
    epoch)``; with ``own`` (``source`` is a padding batch the server sent), ``source`` itself for
    its epoch: one it owes there (its end came first: a hello reopened the epoch before the rank
    read that end), else one more batch of it if open here, else nothing (docs/delivery.md, "DDP")."""
    mine = source["epoch"] if own else None
    while (e := record.count_padding(mine)) is not None:
        if e == mine:
            mine = None
            yield source
        else:
            yield copy(source, e)

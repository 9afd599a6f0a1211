"""The delivery journal (``v2v-serve --state-dir DIR``): what each consumer acknowledged, kept
on disk so that a restarted server repeats nothing for any consumer, including one that has not
come back yet.

Without it a restarted server knows only the resume states of the trainers that said hello
again: a second, independent trainer that resumes later would find the first one sent samples
it already has. With it the server starts from the journal's records (the same call a resume
state makes, ``EpochScheduler.apply_resume``); a trainer's own resume state, when it says
hello, still replaces its record (it is authoritative for its own samples: what it acknowledged
after its checkpoint is owed again).

File ``DIR/delivered.journal``: a header (its recipe fingerprint and ``server``: the id every
server on this journal welcomes clients with, so their resume states name it) then msgpack
records appended as they happen:
``{"d": [consumer, rank], "e": epoch, "k": [[video, index], ...]}`` (one batch granted: the
consumer may hand it on, so the grant is written before it is sent; ``index`` is
``ids.SampleKey.ordinal``, the sample's number in its video under the journal's recipe; ``"n"``:
the batches it stands for when not one, as a rewrite merges them), ``{"u": [consumer, rank], "e":
epoch, "k": [...]}`` (a batch granted, then given back unused), ``{"s": [consumer, rank], "c":
completed_epoch, "r": {epoch: keys}, "b": {epoch: batches}}`` (a resume state replaced a record:
its samples and the batches it yielded), ``{"t": epoch}`` (an epoch was told complete to some
reader: a resume state may say it is complete), ``{"tc": [consumer, rank], "e": epoch}`` (the
newest epoch that consumer was told complete, kept for good: a resume state more than
``keep_epochs`` behind it is refused, docs/delivery.md limit (e)),
``{"done": epoch}`` (an epoch closed for good: a restart starts after it), ``{"o": epoch, "k":
[...]}`` (samples of a closed epoch that left a record since it closed, a resume state's or a
batch given back: a restart makes them again, ``EpochPlan.only``; a grant takes them out again),
``{"g": group, "e": epoch, "c": batches}`` (the ranks of a DDP group were told to yield that many
batches of the epoch). The batch counts (:attr:`Journal.batches`) are a DDP rank's in its group's
(``padding.GroupPadding``): a restarted server tells every rank of the group the count it was told
before, at least what its ranks' grants reach (a later hello's state may have lowered them since;
docs/delivery.md, "DDP"). The records of the newest ``keep_epochs`` closed epochs stay, and each consumer's of the
epochs within ``keep_epochs`` of the newest it was told complete (the scheduler's ``keep_epochs``: a
restarted server keeps the records a running one keeps, so a resume state older than their
completion reopens them alike, docs/delivery.md limit (e)), with the samples owed again and the
counts told in them while some consumer may resume into them; older ones are dropped. When an epoch
closes the file is rewritten from memory (a temporary file, fsync, rename) without them.

Durability: each record is one ``write`` to a file opened with ``O_APPEND`` (in the page cache
at once: it survives the server process being killed); ``fsync`` at most every ``fsync_s``
seconds (1 s) from the main loop and at close, and before any grant or epoch end is sent
(:meth:`durable`): a host crash loses only records no client was told of yet.

A write that fails while serving (a full or failing disk, the folder removed or replaced) never
stops the server: the records stay current in memory, the error goes to ``on_error`` (the
server counts it and logs it once), and every ``RETRY_S`` seconds :meth:`sync` tries to write
the file again whole from memory. Until then a restart reads the journal as it was when the
writes stopped: samples acknowledged since are sent again, none is lost.
"""
from __future__ import annotations

import contextlib
import logging
import os
import time
import uuid
from collections import Counter
from pathlib import Path
from typing import Callable, Dict, Hashable, Iterable, List, Optional, Set

import msgpack

from v2v_server.delivery.schedule import KEEP_EPOCHS
from v2v_wire.ids import SampleKey

log = logging.getLogger("v2v.server")

Records = Dict[Hashable, Dict[int, Set[SampleKey]]]

__all__ = ["Journal", "JournalError"]

FILE = "delivered.journal"
#: Seconds between attempts to write a journal whose writes failed again whole.
RETRY_S = 5.0


class JournalError(ValueError):
    """The journal belongs to another sample recipe, or cannot be read (the message says which)."""


def _keys(pairs, crops_per_window: int) -> Set[SampleKey]:
    """The sample keys of a record's ``[[video, index], ...]``."""
    return {SampleKey.at(str(v), int(i), crops_per_window) for v, i in pairs}


def _pairs(keys: Iterable[SampleKey], crops_per_window: int) -> List[list]:
    """A record's ``[[video, index], ...]`` of ``keys`` (the inverse of ``_keys``)."""
    return [[k.video, k.ordinal(crops_per_window)] for k in keys]


class Journal:
    """The journal in ``directory`` (created if missing).

    Args:
        directory: folder of the journal file.
        fingerprint: ``SampleRecipe.fingerprint()`` of the served recipe; a journal of another is refused.
        fsync_s: most seconds between ``fsync`` calls.
        crops_per_window: samples per window under that recipe (record numbers -> keys, ``ids.SampleKey.at``).
        keep_epochs: closed epochs whose records stay (``schedule.KEEP_EPOCHS``).
        on_error: told ``(path, OSError)`` of each write failing while serving (module docstring); default: logs it.

    Raises:
        JournalError: the journal was written under another recipe, or is not a journal.
        OSError: the folder cannot be created or written (at start).
    """

    def __init__(self, directory: str, fingerprint: str, fsync_s: float = 1.0, crops_per_window: int = 1,
                 on_error: Optional[Callable[[Path, OSError], None]] = None, keep_epochs: int = KEEP_EPOCHS):
        self.on_error = on_error or (lambda path, e: log.warning("%s: %s", path, e))
        self.failed = False  # a write failed: appends stop until the file is written again whole
        self._retry_at = 0.0
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.path = self.dir / FILE
        self.fingerprint = fingerprint
        self.server_id = uuid.uuid4().hex[:16]  # kept in the header: the same for every server on this journal
        self.fsync_s, self.crops_per_window, self.keep_epochs = fsync_s, crops_per_window, keep_epochs
        self.completed = -1  # the newest epoch closed for good
        self.told = -1  # the newest epoch told complete to some reader
        self.told_to: Dict[Hashable, int] = {}  # consumer -> the newest epoch it was told complete
        self.records: Records = {}
        self.batches: Dict[Hashable, Counter] = {}  # consumer -> epoch -> batches granted (as records)
        self.owed: Dict[int, Set[SampleKey]] = {}  # closed epoch -> samples that left a record since it closed
        self.counts: Dict[int, Dict[str, int]] = {}  # epoch -> DDP group -> the batches its ranks were told to yield
        self._dirty, self._last_sync = False, 0.0
        if self.path.exists():
            self._read()
        self._rewrite()
        self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND)

    # ------------------------------------------------------------------ reading
    def _read(self) -> None:
        with open(self.path, "rb") as f:
            unpacker = msgpack.Unpacker(f, raw=False, strict_map_key=False)
            try:
                header = next(unpacker)
            except (StopIteration, ValueError, msgpack.UnpackException) as e:
                raise JournalError(f"{self.path}: not a v2v delivery journal ({e or 'empty'})") from None
            if not isinstance(header, dict) or header.get("journal") != 1:
                raise JournalError(f"{self.path}: not a v2v delivery journal")
            if isinstance(header.get("server"), str):
                self.server_id = header["server"]
            if header.get("recipe") != self.fingerprint:
                raise JournalError(f"{self.path} was written by a server with another sample recipe (seed, "
                                   f"sequence length, bins, crops...): its sample ids name other samples. Use "
                                   f"another --state-dir, or delete it to start afresh")
            n = 0
            try:
                for rec in unpacker:
                    self._apply(rec)
                    n += 1
            except (ValueError, msgpack.UnpackException):  # a record torn by a crash: the ones before it stand
                log.warning("%s: the record after the %d-th is torn (the server stopped while writing it); "
                            "its samples are sent again", self.path, n)

    def _apply(self, rec: dict) -> None:
        k = self.crops_per_window
        if "done" in rec:
            self._complete(int(rec["done"]))
        elif "t" in rec:
            self.told = max(self.told, int(rec["t"]))
        elif "tc" in rec:
            c = tuple(rec["tc"])
            self.told_to[c] = max(self.told_to.get(c, -1), int(rec["e"]))
        elif "d" in rec:
            c, e, keys = tuple(rec["d"]), int(rec["e"]), _keys(rec["k"], k)
            self.owed.get(e, set()).difference_update(keys)
            if self._keeps(c, e):
                self.records.setdefault(c, {}).setdefault(e, set()).update(keys)
                self.batches.setdefault(c, Counter())[e] += int(rec.get("n", 1))
        elif "u" in rec:
            c, e = tuple(rec["u"]), int(rec["e"])
            d, keys = self.records.get(c, {}).get(e), _keys(rec["k"], k)
            if d is not None:
                d.difference_update(keys)
                if e <= self.completed:  # a closed epoch: made again after a restart
                    self.owed.setdefault(e, set()).update(keys)
                self.batches[c][e] = max(0, self.batches[c][e] - 1)
        elif "o" in rec:
            self.owed.setdefault(int(rec["o"]), set()).update(_keys(rec["k"], k))
        elif "g" in rec:  # appended only as it rises
            self.counts.setdefault(int(rec["e"]), {})[str(rec["g"])] = int(rec["c"])
        elif "s" in rec:
            self._replace(tuple(rec["s"]), int(rec["c"]), {int(e): _keys(ks, k) for e, ks in rec["r"].items()},
                          {int(e): int(n) for e, n in rec.get("b", {}).items()})

    def kept(self) -> Dict[int, Set[SampleKey]]:
        """The closed epochs it keeps records of, each with its samples that left a record since it closed."""
        return {e: self.owed.get(e, set()) for e in {e for r in self.records.values() for e in r} | set(self.owed)}

    def _keeps(self, consumer: Hashable, epoch: int) -> bool:
        """Whether ``consumer``'s records of ``epoch`` are kept: the open epochs and the newest ``keep_epochs`` closed
        ones, and those within ``keep_epochs`` of the newest it was told complete (as the scheduler's: limit (e))."""
        return epoch > min(self.completed, self.told_to.get(consumer, -1)) - self.keep_epochs

    def _complete(self, epoch: int) -> None:
        self.completed = max(self.completed, epoch)
        self.told = max(self.told, epoch)
        for c, d in list(self.records.items()) + list(self.batches.items()):
            for e in [e for e in d if not self._keeps(c, e)]:
                del d[e]
        for e in [e for e in {*self.owed, *self.counts} if not any(self._keeps(c, e) for c in self.told_to)
                  and e <= self.completed - self.keep_epochs]:  # no consumer may resume into it
            self.owed.pop(e, None), self.counts.pop(e, None)

    def _replace(self, consumer: Hashable, completed: int, delivered: Dict[int, Set[SampleKey]],
                 batches: Dict[int, int]) -> None:
        d, counts = self.records.setdefault(consumer, {}), self.batches.setdefault(consumer, Counter())
        for e in [e for e in d if e > completed]:
            if e <= self.completed:  # a closed epoch reopened: what left the record is made again after a restart
                self.owed.setdefault(e, set()).update(d[e] - delivered.get(e, set()))
            del d[e]
            counts.pop(e, None)
        for e in set(delivered) | set(batches):  # a rank's yielded padding alone counts too
            if e > completed and self._keeps(consumer, e):
                d[e], counts[e] = set(delivered.get(e, ())), batches.get(e, 0)

    # ------------------------------------------------------------------ writing
    def _append(self, rec: dict) -> None:
        self._apply(rec)  # in memory first: it stays current while writes fail
        if self.failed:
            return  # the next whole write keeps it
        try:
            os.write(self._fd, msgpack.packb(rec, use_bin_type=True))
        except OSError as e:
            self._fail(e)
            return
        self._dirty = True

    def _fail(self, e: OSError) -> None:
        """A write failed: no appending (a torn record ends what is read) until :meth:`sync` writes it whole."""
        self.failed = True
        self._retry_at = time.monotonic() + RETRY_S
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = None
        self.on_error(self.path, e)

    def _recover(self) -> None:
        """Write the file again whole from memory and append from there."""
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            self._rewrite()
            self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND)
        except OSError as e:
            self._retry_at = time.monotonic() + RETRY_S
            self.on_error(self.path, e)
            return
        self.failed = False
        log.info("%s: written again; the delivery journal is kept again", self.path)

    def delivered(self, consumer: Hashable, epoch: int, keys: Iterable[SampleKey]) -> None:
        """``consumer`` was granted one batch of ``epoch``, of samples ``keys``."""
        pairs = _pairs(keys, self.crops_per_window)
        if pairs and self._keeps(consumer, epoch):
            self._append({"d": list(consumer), "e": epoch, "k": pairs})

    def undelivered(self, consumer: Hashable, epoch: int, keys: Iterable[SampleKey]) -> None:
        """``consumer`` gave back one batch of ``epoch`` (``keys``) it was granted and never handed on."""
        pairs = _pairs(keys, self.crops_per_window)
        if pairs and self._keeps(consumer, epoch):
            self._append({"u": list(consumer), "e": epoch, "k": pairs})

    def replaced(self, consumer: Hashable, completed: int, delivered: Dict[int, Set[SampleKey]],
                 batches: Optional[Dict[int, int]] = None) -> None:
        """``consumer``'s resume state replaced its record in the epochs after ``completed``: its
        samples ``delivered`` and the ``batches`` it yielded, per epoch."""
        self._append({"s": list(consumer), "c": completed, "b": dict(batches or {}),
                      "r": {e: _pairs(ks, self.crops_per_window) for e, ks in delivered.items()}})

    def epoch_told(self, epoch: int, group: Optional[str] = None, batches: int = 0) -> None:
        """``epoch`` was told complete to some reader (its records stay: others may hold it); to the ranks of DDP
        ``group``, with the ``batches`` each yields (``padding.GroupPadding``: a restarted server binds them to it)."""
        if epoch > self.told:
            self._append({"t": epoch})
        if group is not None and batches > self.counts.get(epoch, {}).get(group, -1):
            self._append({"g": group, "e": epoch, "c": batches})

    def consumer_told(self, consumer: Hashable, epoch: int) -> None:
        """``consumer`` was told ``epoch`` complete (the newest it was told)."""
        if epoch > self.told_to.get(consumer, -1):
            self._append({"tc": list(consumer), "e": epoch})

    def epoch_complete(self, epoch: int) -> None:
        """Every epoch up to ``epoch`` is closed: the file is rewritten without the records no longer kept."""
        if epoch <= self.completed:
            return
        self._complete(epoch)
        if self.failed:
            return  # the next whole write (sync) leaves the epoch's records out
        try:
            os.close(self._fd)
            self._fd = None
            self._rewrite()
            self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND)
        except OSError as e:
            self._fail(e)

    def _rewrite(self) -> None:
        tmp = self.path.with_suffix(".tmp")
        with open(tmp, "wb") as f:
            f.write(msgpack.packb({"journal": 1, "recipe": self.fingerprint, "server": self.server_id}))
            if self.completed >= 0:
                f.write(msgpack.packb({"done": self.completed}))
            if self.told > self.completed:
                f.write(msgpack.packb({"t": self.told}))
            for consumer, e in self.told_to.items():  # before the records: they say which are kept (_keeps)
                f.write(msgpack.packb({"tc": list(consumer), "e": e}))
            for consumer, d in self.records.items():
                for e, ks in d.items():
                    f.write(msgpack.packb({"d": list(consumer), "e": e, "k": _pairs(sorted(ks), self.crops_per_window),
                                           "n": self.batches.get(consumer, {}).get(e, 0)}))
            for e, ks in self.owed.items():  # after the records: read back, a grant is no longer owed
                f.write(msgpack.packb({"o": e, "k": _pairs(sorted(ks), self.crops_per_window)}))
            for rec in [{"g": g, "e": e, "c": n} for e, told in self.counts.items() for g, n in told.items()]:
                f.write(msgpack.packb(rec))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self.path)
        self._dirty = False

    def sync(self, now: Optional[float] = None) -> None:
        """``fsync`` what was appended, at most every ``fsync_s`` seconds (always when ``now``
        is None); after a failed write, every ``RETRY_S`` seconds, write the file again whole."""
        force, now = now is None, time.monotonic() if now is None else now
        if self.failed:
            if force or now >= self._retry_at:
                self._recover()
            return
        if self._dirty and (force or now - self._last_sync >= self.fsync_s):
            self.durable(now)

    def durable(self, now: Optional[float] = None) -> None:
        """``fsync`` what was appended, now: the server calls it before a grant or an epoch's
        end leaves, so what a client was told survives a host crash (one ``fsync`` per loop turn
        that tells one; nothing when nothing was appended). A journal whose writes failed is
        left to :meth:`sync`'s retries (its records are current in memory only)."""
        if self.failed or not self._dirty:
            return
        try:
            os.fsync(self._fd)
        except OSError as e:
            self._fail(e)
            return
        self._dirty = False
        self._last_sync = time.monotonic() if now is None else now

    @property
    def unsynced(self) -> bool:
        """Whether records were appended since the last ``fsync`` (a host crash would lose them)."""
        return self._dirty and not self.failed

    def close(self) -> None:
        """``fsync`` and close the file."""
        self._dirty = True
        self.sync()
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

"""DDP padding, per group of ranks: what each rank of a group yielded per epoch, so that every
rank yields the same number of batches (docs/delivery.md, "DDP" and "Ends of epochs and of the
stream"). Pure."""
from __future__ import annotations

from typing import Callable, Dict, Optional, Tuple

from v2v_server.delivery.table import BatchRecord


class GroupPadding:
    """What DDP padding needs, per group of ranks (``world_size > 1``): how many batches of
    each epoch each rank yielded, and the group's last acknowledged batch (what a rank that was
    sent nothing repeats). Pure."""

    def __init__(self):
        self.taken: Dict[Tuple[str, int], Dict[int, int]] = {}  # (group, epoch) -> rank -> batches yielded
        self.pad_source: Dict[str, BatchRecord] = {}  # group -> its last acknowledged batch
        self.told: Dict[Tuple[str, int], int] = {}  # (group, epoch) -> the count its ranks were told
        self.world: Dict[str, int] = {}  # group -> the world size its newest hello named

    def resumed(self, group: str, rank: int, completed_epoch: int, batches: Dict[int, int]) -> None:
        """A rank's resume state: in each epoch after ``completed_epoch`` it yielded
        ``batches[epoch]`` batches (0 where the state names none)."""
        for (g, e), counts in self.taken.items():
            if g == group and e > completed_epoch:
                counts[rank] = batches.get(e, 0)
        for e, n in batches.items():
            if e > completed_epoch:
                self.taken.setdefault((group, e), {})[rank] = n

    def restarted(self, journal) -> None:
        """A restarted server's journal (``journal.Journal``): a DDP rank's (consumer ``("g:" + group, rank)``)
        grants of each epoch count as its state's, and the group of a rank told epochs up to ``e`` complete was
        told a count of each kept one, the one the journal says it was told (a later hello's state may have
        lowered the grants since), at least what its ranks' grants reached: the count binds its ranks' later
        hellos, as before the restart (docs/delivery.md, "Ends of epochs")."""
        for c in [c for c in journal.records if c[0].startswith("g:")]:
            self.resumed(c[0][2:], c[1], -1, journal.batches[c])
        for (name, _), upto in [(c, e) for c, e in journal.told_to.items() if c[0].startswith("g:")]:
            for key in [(name[2:], e) for e in range(max(0, upto - journal.keep_epochs), upto + 1)]:
                self.told.setdefault(key, max([*self.taken.get(key, {}).values(),
                                               journal.counts.get(key[1], {}).get(key[0], 0)]))

    def resized(self, group: str, world: int) -> None:
        """A rank of ``group`` said hello at world size ``world``: counts of ranks beyond it (an
        earlier world size of the job) no longer count, nor do the counts told to the ranks of another
        world size (none of them reads now: docs/delivery.md, "A world size changes")."""
        if self.world.get(group, world) != world:
            for key in [k for k in self.told if k[0] == group]:
                del self.told[key]
        self.world[group] = world
        for (g, _), counts in self.taken.items():
            if g == group:
                for r in [r for r in counts if r >= world]:
                    del counts[r]

    def acked(self, group: str, rank: int, batch: BatchRecord) -> None:
        """Rank ``rank`` of ``group`` was granted ``batch`` (it yields it)."""
        counts = self.taken.setdefault((group, batch.epoch), {})
        counts[rank] = counts.get(rank, 0) + 1
        self.pad_source[group] = batch

    def released(self, group: str, rank: int, batch: BatchRecord) -> None:
        """Rank ``rank`` gave back ``batch``, granted and counted before: it yielded it not."""
        counts = self.taken.get((group, batch.epoch), {})
        if counts.get(rank, 0) > 0:
            counts[rank] -= 1

    def room(self, c, epoch: int) -> Optional[int]:
        """How many more batches of ``epoch`` the rank of client ``c`` (``ledger.ClientRecord``) may
        be granted: None while no rank of its group was told a count of it, else that count less
        what the rank yielded. A batch of an epoch whose count was told goes only to a rank below it
        (or to a reader outside the group), so a told count never rises: a rank that ended on it
        cannot be told more (docs/delivery.md, "Ends of epochs")."""
        told = self.told.get((c.group, epoch))
        return None if told is None else told - self.taken.get((c.group, epoch), {}).get(c.rank, 0)

    def epoch_done(self, c, epoch: int) -> Tuple[int, Optional[BatchRecord]]:
        """For the rank of client ``c`` (``ledger.ClientRecord``) once ``epoch`` is complete:
        the batches every rank of its group reaches (the most any of them yielded), and a
        padding batch (batch id -1, a copy of the group's last acknowledged batch) when ``c``
        was never granted a batch and is behind, else None: a batch only sent to it may be
        revoked, leaving it nothing to repeat (docs/delivery.md, "DDP"). A count once told is
        never lowered: a rank's hello giving back a grant it counted comes after other ranks were
        told it ("Ends of epochs")."""
        counts = self.taken.get((c.group, epoch), {})
        most = max(max(counts.values(), default=0), self.told.get((c.group, epoch), 0))
        self.told[(c.group, epoch)] = most
        src = self.pad_source.get(c.group)
        if c.granted == 0 and counts.get(c.rank, 0) < most and src is not None:
            return most, BatchRecord(-1, epoch, src.keys, src.payload, outputs=src.outputs)
        return most, None

    def ranks(self, group: str, epoch: int) -> set:
        """The ranks a count of ``epoch`` concerns: those it counts, and every rank of the group's world size."""
        return set(self.taken.get((group, epoch), ())) | set(range(self.world.get(group, 0)))

    def prune(self, live_groups: set, forgotten: Callable[[int], bool],
              behind: Callable[[str, int, int], bool] = lambda group, rank, epoch: False) -> None:
        """Forget epochs ``forgotten(epoch)`` says are gone, but a group's counts of one while
        ``behind(group, rank, epoch)`` for some rank of it (it may yet be told that epoch's end:
        docs/delivery.md, "Ends of epochs"), and the last batch and world size of groups with no
        client left and no epoch counted (a rank between a drop and its next hello still pads)."""
        for (g, e) in [k for k in self.taken if forgotten(k[1])]:
            if not any(behind(g, r, e) for r in self.ranks(g, e)):
                del self.taken[(g, e)]
        for key in [k for k in self.told if forgotten(k[1]) and k not in self.taken]:
            del self.told[key]
        counted = {g for g, _ in self.taken}
        for g in [g for g in self.pad_source if g not in live_groups and g not in counted]:
            del self.pad_source[g]
        for g in [g for g in self.world if g not in live_groups and g not in counted]:
            del self.world[g]

"""Which hellos are let in, pure: one live reader per consumer, one world size per DDP group, and
resume states the server cannot tell are false. The rules are docs/delivery.md ("Who may say
hello"); :meth:`Admission.check` applies them in that order, :meth:`Admission.resume_problem` at a
cost linear in the state (a video's ids counted before they are parsed, other videos' skipped
unread: ``messages.Bound``).
"""
from __future__ import annotations

import logging
import sys
from typing import Dict, Hashable, List, Optional, Set, Tuple

from v2v_server.delivery.ledger import ClientRecord, DeliveryLedger
from v2v_server.delivery.schedule import EpochScheduler
from v2v_wire.messages import Hello, Resume
from v2v_wire.stream_messages import ServerError

__all__ = ["Admission", "WAIT", "name_of"]

log = logging.getLogger("v2v.server")

#: ``Admission.check``'s answer for a hello that waits for an older connection of its consumer.
WAIT = "wait"
#: Hellos forgotten for silence kept to wait again if their connection speaks (dead processes' too).
MAX_DORMANT = 4096


def name_of(consumer: Hashable) -> str:
    """A consumer as a log line or an error names it: ``DDP group "g" rank 1`` or ``consumer "id"``."""
    name, rank = consumer
    if name.startswith("g:"):
        return f"DDP group {name[2:]!r} rank {rank}"
    return f"consumer {name[2:]!r}"


class Admission:
    """The checks a hello passes (docs/delivery.md, "Who may say hello"), the hellos waiting
    for an older connection of their consumer (``pending``: ident -> (hello, since when)), and
    those forgotten for their connection's silence (``dormant``: ident -> hello), which wait again
    from when it speaks (a paused process's: its session awaits their welcome).

    Args:
        sched, ledger: the core's parts (read only).
        journal: ``journal.Journal`` or None.
        policy: the delivery settings (``core.DeliveryPolicy``): the outputs offered, the recipe's
            crops per window and the windows a file gives at most (bounds of a video's sample
            ids before its first pass).
        claim_margin_s: how long after a hello its consumer's older connection must still speak
            to count as alive (a dead process's last messages arrive before).
        server_id: the id this server's welcomes carry (what ``origins`` name).
        told_to: consumer -> the newest epoch it was told complete (``closing.EpochEnds.told_to``, read only).
    """

    def __init__(self, sched: EpochScheduler, ledger: DeliveryLedger, journal, policy, claim_margin_s: float,
                 server_id: str, told_to: Optional[Dict[Hashable, int]] = None):
        self.sched, self.ledger, self.journal = sched, ledger, journal
        self.told_to = {} if told_to is None else told_to
        self.offered = tuple(policy.offered)
        self.k, self.max_windows = policy.crops_per_window, policy.max_samples_per_video
        self.claim_margin_s, self.server_id = claim_margin_s, server_id
        self.pending: Dict[bytes, Tuple[Hello, float]] = {}
        self.heard: Dict[bytes, float] = {}  # a waiting hello's connection: when it last spoke
        self.dormant: Dict[bytes, Hello] = {}  # hellos forgotten for silence, oldest first (at most MAX_DORMANT)
        #: consumer -> (reader process, hello_id, connection) let in last
        self.instances: Dict[Hashable, Tuple[str, int, bytes]] = {}
        self._kept = 64  # instances kept at the last prune (:meth:`let_in`)
        self._last_turn: Optional[float] = None  # :meth:`silent`'s last call (the server's loop turn)
        self._stalled_until = float("-inf")  # the end of the server loop's last stall

    # ------------------------------------------------------------------ who reads
    def others(self, ident: bytes, consumers: Set[Hashable]) -> List[ClientRecord]:
        """The live connections, other than ``ident``, of any of ``consumers``."""
        return [c for i, c in self.ledger.clients.items() if i != ident and c.consumer in consumers]

    def check(self, ident: bytes, h: Hello, consumer: Hashable, group: Optional[str], now: float):
        """None (let in), :data:`WAIT`, or the ``ServerError`` that refuses the hello (docs/delivery.md,
        "Who may say hello")."""
        if any(o not in self.offered for o in h.outputs):
            return ServerError(f"this server offers only {list(self.offered)}; asked for {list(h.outputs)}", "outputs")
        speaks = self.speaks_for(consumer, h)
        last = [self.instances[w] for w in speaks if w in self.instances]  # not newer: older, or as old elsewhere
        if h.instance and any(i == h.instance and (n, c != ident) > (h.hello_id, False) for i, n, c in last):
            return ServerError("a newer connection of this reader took its consumer over", "fenced")
        since = self.pending.get(ident, (None, now))[1]
        foreign = [c for c in self.others(ident, speaks) if c.instance != h.instance or not h.instance]
        if foreign:
            alive = [c for c in foreign if self._alive(c, since)]
            if not alive:
                return WAIT
            return ServerError(f"{name_of(alive[0].consumer)} is read by another live connection "
                               f"({alive[0].ident.hex()[:12]}): one reader per consumer. "
                               + ("Give each DDP job on this server its own group=" if group is not None else
                                  "Give each reader its own consumer id (a new V2VPushDataset, or no state)")
                               + ", or stop the other reader", "claimed")
        if self._unproven(ident, h, speaks, since):
            return WAIT
        if group is not None:
            other = [c for c in self.ledger.clients.values()
                     if c.ident != ident and c.group == group and c.ddp and c.world_size != h.world_size]
            if other:  # an elastic restart's hello comes before the old ranks' connections are found gone
                alive = [c for c in other if self._alive(c, since)]
                if not alive:
                    return WAIT
                return ServerError(f"DDP group {group!r} is read at world size {alive[0].world_size} by live ranks; "
                                   f"this rank says {h.world_size}: give each DDP job on this server its own group=",
                                   "group")
        peers = set(speaks)
        if h.resume.supersedes and group is not None:  # the new job's ranks may have taken the old ones' records
            peers |= {("g:" + group, r) for r in range(h.world_size)}
        why = self.resume_problem(consumer, h.resume, peers)
        if why is not None:
            return ServerError(f"{name_of(consumer)}: its resume state {why}", "resume")
        return None

    def _alive(self, c: ClientRecord, since: float) -> bool:
        """Connection ``c``'s process lived after a hello that arrived at ``since``: it spoke twice,
        ``claim_margin_s`` apart, after it (a dead process's last messages come at once, however
        late: a cut held them, or a stalled server read them late), or named a batch sent to it
        after it (:meth:`spoke_of`). What it said before ``since`` is cleared: its next message
        starts the count (``ClientRecord.heard_from``; a stall of the server clears it too: :meth:`silent`)."""
        if c.heard_from is not None and c.heard_from < since:
            c.heard_from = None
        return c.heard_from is not None and c.heard >= c.heard_from + self.claim_margin_s or c.proved >= since

    def _unproven(self, ident: bytes, h: Hello, speaks: Set[Hashable], since: float) -> bool:
        """Another reader process than the hello's read one of ``speaks`` last, and the hello's own
        connection has not spoken ``claim_margin_s`` after it and after the server's last stall: it
        may be a dead process's hello, delivered late (a partition held it), whose state would undo
        what a newer process read (a DDP rank's too: docs/delivery.md, limit (g))."""
        other = any(self.instances[w][0] != h.instance for w in speaks if w in self.instances)
        return other and self.heard.get(ident, since) < max(since, self._stalled_until) + self.claim_margin_s

    def waits(self, ident: bytes, h: Hello, now: float) -> None:
        """The hello of connection ``ident`` waits (``pending``), since it first arrived."""
        if ident not in self.pending:
            self.pending[ident] = (h, now)
            self.heard[ident] = now
        else:
            self.pending[ident] = (h, self.pending[ident][1])

    def spoke(self, ident: bytes, now: float, bye: bool = False) -> None:
        """The connection of a waiting hello said something more (it lives), or ``bye``; that of
        a dormant one speaks: its hello waits again as if it arrived ``now``."""
        if bye:
            self.forget(ident)
        elif ident in self.pending:
            self.heard[ident] = now
        elif ident in self.dormant:
            log.info("client %s speaks again: its hello waits again", ident.hex())
            self.waits(ident, self.dormant.pop(ident), now)

    def forget(self, ident: bytes) -> float:
        """A waiting hello is answered or its connection gone; returns when it first arrived (or inf)."""
        self.heard.pop(ident, None)
        self.dormant.pop(ident, None)
        return self.pending.pop(ident, (None, float("inf")))[1]

    def silent(self, now: float, timeout_s: float) -> List[bytes]:
        """Waiting hellos whose connections were silent ``timeout_s`` (a dead process's, or a
        paused one's): forgotten, i.e. ``dormant``, holding nothing back, until their connection
        speaks (:meth:`spoke`; the oldest beyond :data:`MAX_DORMANT` are dropped). Silence is
        counted from the end of a stall of the server's own loop (longer than the ledger's
        ``stall_s``), as the ledger's deadlines are (``DeliveryLedger.expire``); a proof of life
        starts after the stall (what it read late may be a dead process's: :meth:`_alive`, :meth:`_unproven`)."""
        last, self._last_turn = self._last_turn, now
        if last is not None and self.ledger.stall_s is not None and now - last > self.ledger.stall_s:
            self._stalled_until = now
            for c in self.ledger.clients.values():
                c.heard_from = None
        gone = [i for i, t in self.heard.items() if now - max(t, self._stalled_until) > timeout_s]
        for ident in gone:
            log.info("client %s: its hello waited, silent for %.0f s; forgotten", ident.hex(), now - self.heard[ident])
            h = self.pending[ident][0]
            self.forget(ident)
            self.dormant[ident] = h
        while len(self.dormant) > MAX_DORMANT:
            del self.dormant[next(iter(self.dormant))]
        return gone

    def let_in(self, ident: bytes, h: Hello, speaks: Set[Hashable]) -> None:
        """A hello was let in: its reader process is the one that read ``speaks`` last. Entries of
        consumers the server keeps nothing of are dropped once they double (amortized linear)."""
        for w in speaks:
            self.instances[w] = (h.instance, h.hello_id, ident)
        if len(self.instances) > 2 * self._kept:
            s = self.sched
            known = set(self.ledger.table.stranded_consumers()) | {c.consumer for c in self.ledger.clients.values()}
            for recs in [p.records for p in s.plans.values()] + list(s.pending_records.values()):
                known.update(recs)
            self.instances = {w: i for w, i in self.instances.items() if w in known or w in speaks}
            self._kept = max(64, len(self.instances))

    def unread_hello(self, c: ClientRecord, hello_id: int) -> bool:
        """Connection ``c``'s heartbeat names a hello newer than the one let in for it, and none of its
        hellos waits: that hello was lost in a break ZeroMQ mended, so the client is asked for it again
        (``unknown_client`` naming it; one connection's messages arrive in order)."""
        let = self.instances.get(c.consumer)
        return (let is not None and let[2] == c.ident and hello_id > let[1]
                and c.ident not in self.pending and c.ident not in self.dormant)

    def spoke_of(self, c: ClientRecord, batch_ids) -> None:
        """Connection ``c`` named these batches (``hold``, ``ack``, ``released``): those sent to it
        were received, so its process lived when the newest of them was sent (``proved``; linear
        in the message)."""
        table = self.ledger.table
        for bid in batch_ids:
            if table.holds(c.ident, bid):
                c.proved = max(c.proved, table.get(bid).sent)

    def speaks_for(self, consumer: Hashable, h: Hello) -> Set[Hashable]:
        """The consumers a hello speaks for: its own, those its gathered state supersedes that
        are not in its own DDP world (those say hello themselves), and a DDP rank's group's ranks
        beyond its world size that no connection reads (the same job at an earlier world size)."""
        out = {consumer}
        for name, rank, _ in h.resume.supersedes:
            if not (h.world_size > 1 and name == "g:" + (h.group or "default") and rank < h.world_size):
                out.add((name, rank))
        if h.world_size > 1:
            out |= self.beyond("g:" + (h.group or "default"), h.world_size)
        return out

    def beyond(self, name: str, world: int) -> Set[Hashable]:
        """Ranks ``>= world`` of the group ``name`` the server keeps records or grants of, with
        no live connection (linear in the records kept)."""
        s = self.sched
        known = set(self.ledger.table.stranded_consumers())
        for recs in [p.records for p in s.plans.values()] + list(s.pending_records.values()):
            known.update(recs)
        live = {c.consumer for c in self.ledger.clients.values()}
        return {k for k in known if k[0] == name and k[1] >= world and k not in live}

    # ------------------------------------------------------------------ resume states
    def windows_of(self, video: str) -> Optional[int]:
        """Samples ``video`` gives (its last complete pass), or at most (the recipe's bound); None: unknown."""
        n = self.sched.counts.get(video)
        if n is None and self.max_windows is not None:
            n = self.max_windows * self.k
        return n

    def bound(self, video: str) -> Optional[int]:
        """What a resume state may name of ``video`` (``messages.Bound``): the samples it gives
        (``sys.maxsize`` while unknown), None for a video this server does not serve."""
        if video not in self.sched.known:
            return None
        n = self.windows_of(video)
        return sys.maxsize if n is None else n

    def granted_in(self, epoch: int, origins: Tuple[str, ...]) -> Optional[Dict[Hashable, Set]]:
        """Who this server granted what of ``epoch`` (consumer -> sample keys), when a resume
        state naming servers ``origins`` can be checked against it (docs/delivery.md, "Who may say
        hello": an epoch whose grants it knows; with ``--state-dir`` one not opened yet too, whose
        grants are the journal's records, on disk before any grant leaves); None when it cannot."""
        plan = self.sched.plans.get(epoch)
        if plan is not None and plan.only is not None:
            return None  # a complete epoch kept without every consumer's records (``EpochPlan.only``)
        if plan is None:
            known = self.journal is not None and epoch >= self.sched.next_epoch
            return self.sched.pending_records.get(epoch, {}) if known else None
        if self.journal is not None or set(origins) == {self.server_id} or (not origins and plan.served):
            return plan.records
        return None

    def resume_problem(self, consumer: Hashable, r: Resume, speaks: Set[Hashable]) -> Optional[str]:
        """Why the server can tell resume state ``r`` of ``consumer`` is false, or would lose
        samples (docs/delivery.md, limit (e)), or None (linear in its size); ``speaks``: the
        consumers whose grants its ids may name."""
        s, last = self.sched, self.sched.max_epochs
        top = max([r.completed_epoch] + [done for _, _, done in r.supersedes])  # a gathered state's ranks' too
        if last is not None and top >= last:
            return f"says epoch {top} is complete; this server serves epochs 0 to {last - 1} (--epochs {last})"
        if self.journal is not None and top > self.journal.told:
            return (f"says epoch {top} is complete; this server's journal ({self.journal.path}) told "
                    f"epochs up to {self.journal.told} complete: resume against the server and --state-dir the state "
                    f"was made with, or without the state")
        keep = s.keep_epochs
        dones = dict([(consumer, r.completed_epoch)] + [((n, k), d) for n, k, d in r.supersedes])
        for c in speaks:  # a rank beyond its world size it speaks for: with its own completed epoch
            dones.setdefault(c, r.completed_epoch)
        for c, done in dones.items():  # each consumer it speaks for, with its own completed epoch
            told = self.told_to.get(c)
            if told is not None and done < told - keep:
                who = "it" if c == consumer else name_of(c)
                return (f"says epoch {done} is its newest complete one; this server told {who} "
                        f"epochs up to {told} complete and keeps its records of the newest {keep} of "
                        f"them only, so what its model lost of epoch {done + 1} would reach no loop: "
                        f"load a checkpoint saved after epoch {told - keep} ended, or read on as a new consumer (no "
                        f"state; a DDP job under a new group=)")
        for e, keys in r.delivered.items():
            if e <= r.completed_epoch or not keys:
                continue
            if last is not None and e >= last:
                return f"names samples of epoch {e}; this server serves epochs 0 to {last - 1} (--epochs {last})"
            for key in keys:
                n = self.windows_of(key.video) if key.video in s.known else None
                if n is not None and key.ordinal(self.k) >= n:
                    return (f"names sample {key.sample_id(self.k)} of epoch {e}; {key.video} gives {n} sample(s) "
                            f"under this server's recipe")
            records = self.granted_in(e, r.origins)
            if records is not None:
                had = set().union(*(records.get(c, ()) for c in speaks))
                never = [k for k in keys if k.video in s.known and k not in had]
                if never:
                    return (f"names {len(never)} sample(s) of epoch {e} this server never granted to it (such as "
                            f"{min(never).sample_id(self.k)}): load the state this reader saved, or start it without one")
        return None

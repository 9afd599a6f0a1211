"""The invariants, checked as the simulated run goes (docs/simulator.md, "What it checks").

The oracle keeps its own books of what reached each training loop, independent of the
protocol's: a *lineage* is one training job's model (a job restarted from a checkpoint is the
same lineage, and forgets what it trained on after that checkpoint), and its *kept history*
is the (epoch, sample id) pairs its model was trained on (padding excluded).

* **No sample in two loops** (after every step): a pair reaches a kept history only if no
  kept history has it.
* **An announced epoch lacks nothing** (when the server announces an epoch complete): every
  sample of it is in a kept history, on its way to a loop (held granted, claimed or queued in
  a loader by a live process), or recorded at the server to an honest consumer that has not
  died for good (its next hello takes back what it lacks: a killed trainer, a model that
  resumed from an older checkpoint, a grant that never reached its client). At the end of a run every sample of every
  epoch is in exactly one kept history, except what the docs allow: a window that failed with
  a reason, and what was owed to a consumer that died for good: granted to it and never taken
  (at most ``GRANT_AHEAD + 1`` batches each; a ``StreamLoader`` worker's queued batches
  besides; a batch a connection gave back counts as held while no server has taken its
  ``released`` back: :meth:`Oracle.released`), or forgotten when it resumed from a checkpoint
  and not taken again before it died, or forgotten by a job whose resume the server refused as more than ``keep_epochs`` behind the
  epochs its consumer was told complete (limit (e): counted in ``refusals``, checked against the
  epochs announced; the job reads on as a new consumer, the old one is never read again).
* **Liveness**: every honest lineage's stream ends (the server's ``end``) by its deadline.
* **No false timeout**: only a worker the run made hang has its task expired (:meth:`Oracle.timed_out`);
  a window failed by worker crashes is excused only when every crash of its job was injected
  (``ServerProbe.excused``).
* **Memory** (after every server turn): the scheduler keeps at most 6 epochs open besides those
  it opened within the last ``2 lease_s + revoke_s`` (how long a reader sitting on its grants may
  keep another from being told an epoch complete, docs/delivery.md: a reader reads on meanwhile,
  and only epochs told complete can close); no client holds more batches than its credits; the
  table holds batches of open epochs only, but grants (a consumer's for good, whatever the
  epoch's books: at most twice the most credits per consumer) and grants given back (at most
  that for each of the up to three consumers of every job); the server keeps records for at
  most the epochs it can serve, each no larger than an epoch; a client holds at most its credits.
"""
from __future__ import annotations

from typing import Dict, Iterable, List, Optional, Set, Tuple

from v2v_client.session import GRANT_AHEAD

from harness.delivery_sim.world import Sim

Key = Tuple[int, str]


class Lineage:
    """One training job's model: its kept history and whether it is honest and alive."""

    def __init__(self, name: str, honest: bool = True):
        self.name, self.honest = name, honest
        self.history: List[Key] = []
        self.ended_at: Optional[float] = None
        self.dead_for_good = False
        self.error: Optional[str] = None
        self.deadline: Optional[float] = None  # its stream must end by then (else the run's deadline)
        self.forgotten: Set[Key] = set()  # what it forgot resuming from checkpoints (owed to it again)
        self.refusable = False  # a job the server may refuse as a second reader of a consumer (it then stops)
        self.given_up: Set[Key] = set()  # what it forgot, owed to a resume the server refused (limit (e))


    def refused(self) -> bool:
        """Refused as a second live reader of its consumer, as it may be (``refusable``)."""
        return self.refusable and self.error is not None and CLAIMED in self.error


#: what a refusal of a second live reader says (``admission.Admission.check``)
CLAIMED = "one reader per consumer"
#: what a refusal of a resume state too far behind its consumer's epochs says (limit (e), ``Admission.resume_problem``)
BEHIND = "would reach no loop"


class Oracle:
    """The books and the checks of one run (``corpus``: the server's ``Corpus``; ``epochs``:
    the bounded stream's epochs)."""

    def __init__(self, sim: Sim, corpus, epochs: Optional[int], epoch_size: int):
        self.sim, self.corpus, self.epochs = sim, corpus, epochs
        self.epoch_ids = corpus.epoch_ids()
        self.epoch_size = epoch_size
        self.lineages: Dict[str, Lineage] = {}
        self.kept: Dict[Key, str] = {}
        self.announced: Dict[int, float] = {}
        self.excused: Dict[int, Set[str]] = {}
        self.killed_with: Dict[str, Set[Key]] = {}  # consumer -> what its killed processes held
        self.killed_batches: Dict[str, int] = {}  # consumer -> batches held by its last killed process
        self.unread: Dict[Tuple[bytes, int], Tuple[str, Set[Key]]] = {}  # (connection, batch) -> released, not taken back
        self.dead_consumers: Set[str] = set()  # consumers that died for good
        self.live_clients: List = []  # objects with ``pending() -> Iterable[Key]`` and ``alive()``
        self.max_epoch_opened = -1
        self.opened_at: Dict[int, float] = {}  # when the server's books first showed each epoch open
        self.yields = 0
        self.holders = lambda epoch, sid: []  # where the server keeps a sample (set by the run: ServerProbe.holders)
        self.recorded_to = lambda epoch, sid: []  # the consumers it is recorded to (ServerProbe.recorded_to)
        self.owners: Set[str] = set()  # consumer keys of honest jobs (``ServerProbe`` format: "c:t0/0")
        self.refusals: List[Tuple[str, int]] = []  # resumes refused as behind (limit (e)): (lineage, its epoch)

    def lineage(self, name: str, honest: bool = True) -> Lineage:
        if name not in self.lineages:
            self.lineages[name] = Lineage(name, honest)
        return self.lineages[name]

    # ------------------------------------------------------------------ what loops get
    def yielded(self, lineage: str, item: dict) -> None:
        """A training loop of ``lineage`` got ``item`` (``sample_ids``, ``padding``, ``epoch``)."""
        lin = self.lineages[lineage]
        e = item["epoch"]
        self.yields += 1
        for sid, pad in zip(item["sample_ids"], item["padding"]):
            if pad:
                continue
            key = (e, sid)
            other = self.kept.get(key)
            if other is not None:
                self.sim.fail("doubled", f"sample {sid} of epoch {e} reached the loop of {lineage} and was "
                                         f"already in the loop of {other}")
            self.kept[key] = lineage
            lin.history.append(key)

    def rolled_back(self, lineage: str, kept: int) -> None:
        """``lineage`` resumed from a checkpoint taken after ``kept`` samples: its model forgot the rest."""
        lin = self.lineages[lineage]
        for key in lin.history[kept:]:
            if self.kept.get(key) == lineage:
                del self.kept[key]
        lin.forgotten.update(lin.history[kept:])
        del lin.history[kept:]
        lin.ended_at = None  # it reads again
        self.sim.log("oracle", f"{lineage} rolled back to {kept} samples")

    def ended(self, lineage: str) -> None:
        lin = self.lineages[lineage]
        if lin.ended_at is None:
            lin.ended_at = self.sim.now
            self.sim.log("oracle", f"{lineage}'s stream ended")

    def killed(self, consumer: str, held: Iterable[Key], batches: int, for_good: bool) -> None:
        """A process reading as ``consumer`` was killed holding ``held`` (granted, claimed or
        queued: on their way to its loop) in ``batches`` batches; ``for_good``: it never says
        hello again as that consumer."""
        self.killed_with.setdefault(consumer, set()).update(held)
        if batches or consumer not in self.killed_batches:
            self.killed_batches[consumer] = batches
        if for_good:
            self.dead_consumers.add(consumer)

    def released(self, ident: bytes, bid: int, consumer: str, keys: Set[Key]) -> None:
        """Connection ``ident`` of ``consumer`` gave back batch ``bid`` (samples ``keys``), which
        it had asked to hold: until a server takes it back (:meth:`taken_back`) it may be that
        consumer's grant still (the message lost with the process or the socket, or with a server
        that died before reading it), so if the consumer dies for good it counts as held then."""
        self.unread[(ident, bid)] = (consumer, keys)

    def taken_back(self, ident: bytes, bids: Iterable[int]) -> None:
        """A server read a ``released`` from ``ident`` and takes batches ``bids`` back."""
        for bid in bids:
            self.unread.pop((ident, bid), None)

    def dead_with(self, consumer: str) -> Set[Key]:
        """What a consumer that died for good may leave granted and never taken: what its killed
        processes held, and what its connections gave back that no server took back."""
        out = set(self.killed_with.get(consumer, ()))
        for who, keys in self.unread.values():
            if who == consumer:
                out |= keys
        return out

    def refused_behind(self, lineage: str, consumer: str, completed: int, keep_epochs: int) -> None:
        """The server refused ``lineage``'s resume state (completed epoch ``completed``) of
        ``consumer`` as more than ``keep_epochs`` behind the epochs it was told complete
        (docs/delivery.md, limit (e)); the job reads on as a new consumer. What its model forgot
        is owed to it no more, and ``consumer`` is never read again (its grants: limit (a)). A
        refusal while ``completed`` is within ``keep_epochs`` of every epoch announced complete
        is a false one."""
        lin = self.lineages[lineage]
        self.refusals.append((lineage, completed))
        newest = max(self.announced, default=-1)
        if completed >= newest - keep_epochs:
            self.sim.fail("refused", f"{lineage}'s resume state (epoch {completed} complete) was refused as behind, "
                                     f"though the newest epoch announced complete is {newest}")
        lin.given_up |= lin.forgotten
        lin.forgotten = set()
        self.dead_consumers.add(consumer)
        self.sim.log("oracle", f"{lineage}'s resume refused as behind: {len(lin.given_up)} samples it forgot are "
                               f"given up")

    # ------------------------------------------------------------------ workers
    def timed_out(self, worker: bytes, job, hung: bool) -> None:
        """The server expired ``worker``'s task of ``job`` (``Job``: epoch, video) and replaces the
        worker; ``hung``: the run made it hang. A worker that did not hang sends a sample well within
        the task timeout of the time the server reads it, so expiring its task is a fault of the
        server's clock (docs/delivery.md, "Workers"): the run fails (``timeout``)."""
        if not hung:
            self.sim.fail("timeout", f"worker {worker.decode()}'s task ({job.video}, epoch {job.epoch}) expired and "
                                     f"the worker was replaced, though it did not hang")

    # ------------------------------------------------------------------ announcements
    def on_announce(self, epoch: int) -> None:
        """The server announced ``epoch`` complete: every sample of it (but what failed with a
        reason) is in a kept history, on its way to a loop, or recorded at the server to an
        honest consumer that has not died for good (its next hello takes it back if it does
        not have it: docs/delivery.md, "Nothing is lost"), or held by one that died for good. A
        sample a job forgot resuming, that the server forgot too, is left to the final check (that
        job's next hello may be refused, limit (e), and then it is given up: :meth:`refused_behind`)."""
        self.announced[epoch] = self.sim.now
        pending = set()
        for c in self.live_clients:
            if c.alive():
                pending.update(c.pending())
        owed_dead = set().union(*(lin.forgotten for lin in self.lineages.values() if lin.dead_for_good))
        owed_later = set().union(*(lin.given_up | lin.forgotten for lin in self.lineages.values()))
        lost = []
        for sid in sorted(self.epoch_ids - self.excused.get(epoch, set())):
            key = (epoch, sid)
            if key in self.kept or key in pending:
                continue
            owners = self.recorded_to(epoch, sid)
            if not owners and key in owed_later:
                continue
            if any(o in self.owners and o not in self.dead_consumers for o in owners):
                continue
            if any(key in self.dead_with(o) or key in owed_dead for o in owners if o in self.dead_consumers):
                continue
            lost.append(sid)
        if lost:
            self.sim.fail("lost", f"epoch {epoch} announced complete, and {len(lost)} of its samples are in no training "
                                  f"loop, on no way to one, and recorded to no honest consumer: "
                                  f"{self._where(epoch, lost)}")

    # ------------------------------------------------------------------ the end
    def final(self, deadline: float) -> None:
        """At the end of a run: liveness, then every epoch exactly once (but the docs' exceptions)."""
        for lin in self.lineages.values():
            if lin.honest and lin.error is not None and not lin.refused():  # an error ends a DDP job for good too
                self.sim.fail("error", f"{lin.name} (an honest trainer) failed: {lin.error}")
        for lin in self.lineages.values():
            if lin.honest and not lin.dead_for_good and not lin.refused() and \
                    (lin.ended_at is None or lin.ended_at > (lin.deadline or 1e300)):
                by = deadline if lin.deadline is None else lin.deadline
                self.sim.fail("liveness", f"{lin.name}'s stream did not end by t={by:.1f} s "
                                          f"(epochs announced: {sorted(self.announced)})")
        if self.epochs is None:
            return
        allowed = set()
        for consumer in sorted(self.dead_consumers):
            allowed |= self.dead_with(consumer)
            self.dead_bound(consumer)
        for lin in self.lineages.values():  # owed again to a job that resumed, then died for good or was refused
            if lin.dead_for_good:
                allowed |= lin.forgotten
            allowed |= lin.given_up
        for e in range(self.epochs):
            excused = self.excused.get(e, set())
            lost = sorted(sid for sid in self.epoch_ids - excused
                          if (e, sid) not in self.kept and (e, sid) not in allowed)
            if lost:
                self.sim.fail("lost", f"{len(lost)} samples of epoch {e} reached no training loop: "
                                      f"{self._where(e, lost)}")

    def _where(self, epoch: int, sids: List[str]) -> str:
        """The first few of ``sids`` with where the server keeps each."""
        return ", ".join(f"{sid} (server: {', '.join(self.holders(epoch, sid))})" for sid in sids[:6]) + \
            (f" and {len(sids) - 6} more" if len(sids) > 6 else "")

    def dead_bound(self, consumer: str, extra: int = 0) -> None:
        """The docs' exception is bounded: a consumer that died for good held at most
        ``GRANT_AHEAD + 1`` batches granted and not taken (``extra``: a loader worker's queue).
        It counts what its last killed process held; releases no server took back are not
        counted: one may be stale (a later hello of that consumer, let in, replaced its record),
        and each connection's are bounded by the batches it asked to hold."""
        n = self.killed_batches.get(consumer, 0)
        if n > GRANT_AHEAD + 1 + extra:
            self.sim.fail("lost", f"{consumer} died for good holding {n} batches on their way to its loop; the "
                                  f"docs allow {GRANT_AHEAD + 1 + extra}")

    # ------------------------------------------------------------------ memory
    def memory(self, probe, max_credits: int, wait_s: float) -> None:
        """The bounds on what the server keeps (see the module docstring); ``wait_s``: how long
        a reader sitting on grants may delay another's end of an epoch (``2 lease_s + revoke_s``)."""
        fail = self.sim.fail
        for ident, held, credits in probe.client_holdings():
            if held > credits:
                fail("memory", f"client {ident.hex()[:8]} holds {held} batches with {credits} credits")
        plans = probe.plan_epochs()
        if plans:
            self.max_epoch_opened = max(self.max_epoch_opened, plans[-1])
        now = self.sim.now
        for e in plans:
            self.opened_at.setdefault(e, now)
        recent = [e for e in plans if self.opened_at[e] > now - wait_s]
        if len(plans) - len(recent) > 6:
            fail("memory", f"the scheduler keeps {len(plans)} epochs open: {plans} ({len(recent)} opened in the last "
                           f"{wait_s:g} s)")
        kept: Dict[object, int] = {}
        behind = []
        for bid, epoch, n, state, consumer in probe.batches():
            if state in ("granted", "stranded"):  # a consumer's for good, whatever the epoch's books
                kept[consumer] = kept.get(consumer, 0) + 1
                if kept[consumer] > 2 * max_credits:
                    fail("memory", f"the server keeps {kept[consumer]} batches granted to {consumer}; "
                                   f"credits are at most {max_credits}")
            elif epoch not in plans:  # a grant given back after its epoch was forgotten (only a grant outlives it)
                behind.append(bid)
        most = 2 * max_credits * 3 * len(self.lineages)
        if len(behind) > most:
            fail("memory", f"{len(behind)} batches of forgotten epochs stay in the table (such as {behind[:4]}); "
                           f"grants given back are at most {most}")
        for where, epoch, consumer, n in probe.records():
            if n > self.epoch_size:
                fail("memory", f"the server keeps {n} sample ids for {consumer} in epoch {epoch} ({where}); "
                               f"an epoch holds {self.epoch_size}")
            if epoch > self.max_epoch_opened + 2:
                fail("memory", f"the server keeps a record of {consumer} for epoch {epoch} ({where}); it has "
                               f"opened epochs up to {self.max_epoch_opened} only")

    def client_memory(self, clients: Iterable) -> None:
        """No client process holds more batches than its credits."""
        for c in clients:
            if c.alive() and c.held() > c.credit_limit():
                self.sim.fail("memory", f"{c.name} holds {c.held()} batches with {c.credit_limit()} credits")

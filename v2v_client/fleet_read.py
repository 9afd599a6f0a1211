"""Reading a fleet: hosts that each serve the whole corpus (a bucket, a shared folder), read as the
one plan a single server serves, each video made by the host the reader routes it to
(docs/scaling.md, "One plan, any fleet"). Free of torch.

* **The plan is the reader's.** The manifest is asked once a pass, of the first host that
  answers (``manifest_ask``, the hosts that said they serve the plan first, in turn,
  ``ASK_NEXT_S`` each: a host gone costs that, and leaves the fleet until it answers; a host
  whose manifest's fingerprint is not the plan identity's is left out for the pass), and
  the epoch's order is ``v2v_wire.plan.EpochPlan`` of it, the pure function every server
  computes: a position means the same sample at any fleet size, a single server included. It
  unfolds with each video's windows, as the corpus index gave them to the host asked, or as a
  host's decode learns them (a ``make`` of the video's windows, asked of the host the video is
  routed to, which keeps the samples it made for the makes that follow).
* **Routing** (``v2v_wire.fleet.Router``): each video of the positions this rank reads, from the
  step it yields to ``ahead`` positions past it (more while it waits, ``Router.slide``), is asked (``make``: the video and the samples
  of it this rank's rows hold) of the host its ranking and the hosts' queues pick, as each host
  says them to every reader of every job (the job's ranks and DataLoader workers route alike);
  its later samples go to the same host while it answers. A host with this reader's work that
  answered nothing, not even a ping, for ``hedge_s`` has its videos asked of their next hosts
  too; the first answer wins.
* **The pass turns in a thread of its own** (``Fleet.fetch_all``): the loop takes its steps from
  it, and while the loop holds them (a step's work, ``ReadAhead``'s batches, a DataLoader's
  prefetch, the job waiting on another rank) the pass goes on asking ahead, pinging its hosts
  and rescuing what its next step waits on.
* **The fleet changes**: the endpoint is resolved again every ``RESOLVE_S`` seconds; a new host
  serving the same plan takes work from its first answer, a host gone hands its videos to the
  next hosts of their rankings, a host of the fleet serving another plan is named once and left
  out, and a host that says the instance of one read already (one host under two names) is read
  once (``alias_of``).
* **A bad peer is left out**: a peer that sends what no v2v-serve of this protocol sends (not
  msgpack, another version, past the wire's bounds: ``fetch.BrokenPeer``), serves another plan
  than the fleet's when first asked (not one of its hosts: a made-up plan), or refuses every read
  of this reader (its outputs or compression) is named once in this process and left out
  (``Fleet.leave_out``: never asked again, not even what it serves, until the fleet's plan
  changes), its videos asked of their next hosts; a frame over the largest legitimate reply
  (``fetch.reply_limit``) cuts its connection before it is received. A host that refuses one
  make stays (``fleet_pass.refused``). With no host left: one error naming each peer left out
  and why.
* **A corpus that changed under the fleet** (docs/delivery.md): a pass reads only hosts serving
  its plan. A host of the fleet restarted with a file replaced serves another plan: it is named
  in one line, with the files whose tags differ from the pass's manifest (:func:`manifest_diff`),
  and left out for the pass; when no host serves the pass's plan any more, the pass fails in one
  line naming them and saying to start that epoch over (``PlanMismatch``), so no epoch holds
  samples of two versions of a file. The next pass reads the plan the hosts serve then
  (``servers.Servers.ask``), every peer asked again.

A host keeps no record of the reader: a ``make`` names its samples, and a restarted host makes
them again.
"""
from __future__ import annotations

import logging
import queue
import socket
import threading
import time
from collections import ChainMap
from dataclasses import replace
from typing import Dict, Iterator, List, Optional, Set, Tuple

import numpy as np
import zmq

from v2v_wire.fleet import HEDGE_S, Router
from v2v_wire.plan import Manifest, PlanIdentity, PlanMismatch
from v2v_wire.plan_messages import MAX_MAKE_SAMPLES, Fetch, Make, ManifestAsk, ManifestPart, PlanAsk, PlanInfo, Refused, Rows
from v2v_wire.protocol import MAX_HEADER_BYTES

from .endpoints import auto_compression, resolve_endpoints
from .fetch import POLL_S, BrokenPeer, Link, PlanServerError, ReadStopped, check_stopped, reply_limit, stopped_by, wait_readable
from .fleet_pass import HOST_REFUSALS, STEAL_S, Pass, ReaderMemory

__all__ = ["Fleet", "load_manifest", "read_manifest", "manifest_part", "asked_fleet", "listing_diff",
           "manifest_diff", "alias_of", "HEDGE_S", "RESOLVE_S", "ASK_NEXT_S", "HELD_STEPS"]

log = logging.getLogger("v2v.client")

#: Seconds between resolutions of the fleet's endpoint (a Kubernetes headless Service's name).
RESOLVE_S = 5.0
#: Seconds a host may take to answer what a pass asks the fleet once (the manifest, before the
#: next host is asked; what it serves, asked of every host at once by ``servers.Servers.ask``,
#: after the first answer): a live host's loop answers within its 0.1 s poll, a dead or
#: unreachable one never, and every pass (each epoch, each DataLoader worker) asks, so a gone
#: host costs this, not ``timeout_s``.
ASK_NEXT_S = 2.0
#: Steps a pass's thread holds read ahead of the loop (``Fleet.fetch_all``) while it goes on
#: turning the pass: asking ahead, rescuing what the next step waits on, pinging. A pass turned
#: only when its loop asks for a step stops all of that while the job waits on another rank or
#: the loop holds the batches it read ahead (``ReadAhead``, a DataLoader's prefetch): 128
#: simulated hosts, 8 readers, sigma 0.2 (``harness.fleet_sim``, docs/scaling.md).
HELD_STEPS = 1


def load_manifest(link: Link, plan: PlanIdentity, timeout_s: float, first: Optional[ManifestPart] = None) -> Manifest:
    """The manifest of ``link``'s server (:func:`read_manifest`), which must be ``plan``'s.

    Raises:
        TimeoutError: the server did not answer within ``timeout_s``.
        PlanServerError: it refused, or its manifest's fingerprint is not ``plan``'s (one line).
    """
    manifest = read_manifest(link, timeout_s, first)
    if manifest.fingerprint() != plan.manifest:
        raise PlanServerError(f"{link.endpoint}: its manifest's fingerprint is {manifest.fingerprint()}, its plan "
                              f"names {plan.manifest}")
    return manifest


def read_manifest(link: Link, timeout_s: float, first: Optional[ManifestPart] = None) -> Manifest:
    """The manifest of ``link``'s server, asked part by part (``manifest_ask``); ``first``: its
    part at offset 0 when already read (:meth:`Fleet._manifest`).

    Raises:
        TimeoutError: the server did not answer within ``timeout_s``.
        PlanServerError: it refused, or its parts stop short (one line).
    """
    videos: List[str] = []
    tags: List[Optional[str]] = []
    slots: List[Optional[int]] = []
    part = first
    while True:
        part = part or manifest_part(link, len(videos), timeout_s)
        if not part.videos and len(videos) < part.total:
            raise PlanServerError(f"{link.endpoint}: its manifest stops at {len(videos)} of {part.total} videos")
        videos += part.videos
        tags += part.tags
        slots += part.slots
        if len(videos) >= part.total:
            break
        part = None
    return Manifest.of(dict(zip(videos, slots)), part.crops_per_window,
                       dict(zip(videos, tags)) if part.tagged else None)


def manifest_part(link: Link, offset: int, timeout_s: float) -> ManifestPart:
    """The part of ``link``'s server's manifest from video ``offset`` on, asked again every 5 s
    while it is silent (a message to a host not connected yet is dropped).

    Raises:
        TimeoutError: no answer within ``timeout_s``.
        PlanServerError: it refused (one line)."""
    deadline = time.monotonic() + timeout_s
    while True:
        link._send(ManifestAsk(offset).to_wire())
        got = link._recv(min(deadline, time.monotonic() + 5.0))
        if got is not None and isinstance(got[0], ManifestPart) and got[0].offset == offset:
            return got[0]
        if got is not None and isinstance(got[0], Refused):
            raise PlanServerError(f"{link.endpoint}: {got[0].message}")
        if time.monotonic() >= deadline:
            raise TimeoutError(f"{link.endpoint}: no manifest within {timeout_s} s")


def asked_fleet(servers: List[str], first_s: float, wait_s: float, curve: Optional[tuple],
                left_out: Optional[Dict[str, str]] = None) -> Dict[str, PlanInfo]:
    """What each of ``servers`` serves, all asked at once: the first answer awaited ``first_s``
    seconds, the others ``wait_s`` more; in ``servers``' order, those that answered. One that
    answers what cannot be read (another protocol version) or refuses is named in one log line,
    left out, and noted in ``left_out`` (endpoint -> why); one noted there already is not asked.

    Raises:
        TimeoutError: none answered within ``first_s``, naming them.
        PlanServerError: none answered, and one refused, broke the protocol or was left out
            before: one line naming each and why it was left out."""
    left_out = {} if left_out is None else left_out
    infos: Dict[str, PlanInfo] = {}
    refused: Dict[str, str] = {}
    links = {ep: Link(ep, first_s, curve) for ep in servers if ep not in left_out}
    poller = zmq.Poller()
    try:
        for link in links.values():
            link._send(PlanAsk().to_wire())
            poller.register(link.sock, zmq.POLLIN)
        deadline = time.monotonic() + first_s
        while links and len(infos) + len(refused) < len(links) and time.monotonic() < deadline:
            ready = dict(wait_readable(poller.poll, deadline - time.monotonic()))
            for ep, link in links.items():
                if link.sock not in ready or ep in infos or ep in refused:
                    continue
                try:
                    got = link._recv(time.monotonic())
                except BrokenPeer as e:
                    refused[ep] = e.left_out_for
                else:
                    if got is not None and isinstance(got[0], PlanInfo):
                        if not infos:
                            deadline = min(deadline, time.monotonic() + wait_s)
                        infos[ep] = got[0]
                    elif got is not None and isinstance(got[0], Refused):
                        refused[ep] = got[0].message
                if ep in refused:
                    log.warning("%s: left out of the fleet: %s", ep, refused[ep])
    finally:
        for link in links.values():
            link.__exit__(None, None, None)
    left_out.update(refused)
    if not infos:
        if len(links) < len(servers) or refused:
            why = [f"{ep}: {left_out[ep]}" if ep in left_out else
                   f"{ep}: no answer within {first_s} s (a reply over {MAX_HEADER_BYTES} bytes cuts its connection)"
                   for ep in servers]
            raise PlanServerError("; ".join(why))
        raise TimeoutError(f"{', '.join(servers)}: no answer to 'what do you serve' within {first_s} s (is a "
                           "v2v-serve running there?)")
    return {ep: infos[ep] for ep in servers if ep in infos}


def listing_diff(ep_a: str, plan_a: PlanIdentity, ep_b: str, plan_b: PlanIdentity, timeout_s: float,
                 curve: Optional[tuple], most: int = 3) -> str:
    """:func:`manifest_diff` of two hosts' manifests, each named by its endpoint.

    Raises:
        TimeoutError, PlanServerError: as :func:`load_manifest`."""
    manifests = []
    for ep, plan in ((ep_a, plan_a), (ep_b, plan_b)):
        with Link(ep, timeout_s, curve) as link:
            manifests.append(load_manifest(link, plan, timeout_s))
    return manifest_diff(manifests[0], f"on {ep_a}", manifests[1], f"on {ep_b}", most) or \
        "listings differ in their crops per window"


def manifest_diff(a: Manifest, where_a: str, b: Manifest, where_b: str, most: int = 3) -> str:
    """The first files (at most ``most``) whose path or tag differs between manifests ``a`` and
    ``b`` (said to be ``where_a``, ``where_b``), as one clause: ``"listings differ in 1 file(s):
    a.mp4 (tag file 123 456 on tcp://a, tag file 123 789 on tcp://b)"``; "" when none does."""
    tagged = [dict(zip((v for v, _ in m.slots), m.tags or [None] * len(m.slots))) for m in (a, b)]
    ta, tb = tagged
    differ = sorted(v for v in set(ta) | set(tb) if ta.get(v, False) != tb.get(v, False))
    if not differ:
        return ""

    def side(v, d):
        return "absent" if v not in d else f"tag {d[v]}"

    shown = ", ".join(f"{v} ({side(v, ta)} {where_a}, {side(v, tb)} {where_b})" for v in differ[:most])
    return f"listings differ in {len(differ)} file(s): {shown}"


def alias_of(ep: str, info: PlanInfo, names: Dict[str, str]) -> Optional[str]:
    """The endpoint under which the host answering at ``ep`` is read already, else None
    (``names``: instance -> endpoint, given ``ep`` when its instance is new). Endpoints whose
    hosts say one instance (``PlanInfo.instance``) are one host under two names (``localhost``
    and ``127.0.0.1``, a DNS name and its address): it is read once, under the name it was first
    read under, and the other name is said in one log line."""
    if info.instance is None:
        return None
    kept = names.setdefault(info.instance, ep)
    if kept == ep:
        return None
    log.warning("%s: the same host as %s (it says the same instance, %s): read once, as %s", ep, kept,
                info.instance, kept)
    return kept


class Fleet:
    """Hosts serving one plan, read as it (module docstring).

    Args:
        endpoint: the fleet's endpoint spec (a list, a comma-separated string or a DNS name),
            resolved again every :data:`RESOLVE_S` seconds.
        hosts: ``(endpoint, PlanInfo)`` of the hosts serving ``plan``.
        plan: the plan read (its identity).
        timeout_s: seconds of silence from every host before ``TimeoutError``.
        curve: CurveZMQ keys (``endpoints.load_curve_keys``) or None.
        compression: the codec setting (``"auto"``: per host, ``endpoints.auto_compression``).
        memory: what the reader keeps across passes (``fleet_pass.ReaderMemory``: the windows,
            rates and hosts learned, the peers left out; kept by the caller, ``servers.Servers``,
            and pickled to its DataLoader workers; updated).
        ahead: positions past the step being read whose videos are asked for (None: ten decodes
            per worker of the fleet, as ``harness.fleet_sim`` measured is needed, at least the
            prefetched steps).
        hedge_s: :data:`HEDGE_S`.
    """

    def __init__(self, endpoint, hosts: List[Tuple[str, PlanInfo]], plan: PlanIdentity, timeout_s: float,
                 curve: Optional[tuple], compression: str, memory: ReaderMemory, ahead: Optional[int] = None,
                 hedge_s: float = HEDGE_S):
        self.endpoint, self.plan, self.timeout_s, self.curve = endpoint, plan, timeout_s, curve
        self.compression, self.memory, self.ahead = compression, memory, ahead
        self.changed: Dict[str, str] = {}  # host -> what it serves instead of the pass's plan (other_plan)
        self.unnamed: Dict[str, Tuple[str, Optional[Manifest]]] = {}  # other_plan's before the manifest is known
        self.names: Dict[str, str] = {}  # instance -> the endpoint its host is read under (alias_of)
        self.links: Dict[str, Link] = {}
        self.poller = zmq.Poller()  # every link's socket (fleet_pass.take waits on them)
        self.out_for_pass: Dict[str, str] = {}  # the fleet's hosts left out of this pass -> why (other_plan)
        self.members = {ep for ep, _ in hosts}  # the fleet's hosts: one serving another plan is out for the pass
        self.withdraws: Set[str] = set()  # hosts whose PlanInfo says they take a Withdraw
        self.router = Router([], hedge_s=min(hedge_s, timeout_s), now=time.monotonic(), patience_s=STEAL_S)
        self.stream: Optional[dict] = None  # the first host's stream info: a padding row's shapes before any row
        self.manifest: Optional[Manifest] = None
        for ep, info in hosts:
            self.join(ep, info, time.monotonic())
        self.resolved = time.monotonic()
        self._served: Tuple[Optional[Rows], Dict[str, int]] = (None, {})  # the step last yielded, and who made it
        # the loop's take of a step wakes the pass's thread out of its wait on the hosts (take)
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self.poller.register(self._wake_r.fileno(), zmq.POLLIN)  # a poll names it by its descriptor
        self._turning: Optional[Tuple[threading.Thread, threading.Event]] = None
        self._taken = 0  # what the loop took of the pass's thread (counted by the loop alone)

    def __enter__(self) -> "Fleet":
        return self

    def __exit__(self, *exc) -> None:
        self._stop_turning()
        for link in self.links.values():
            link.__exit__(*exc)
        self._wake_r.close()
        self._wake_w.close()

    # ------------------------------------------------------------------ the fleet
    def _link(self, ep: str) -> Link:
        if ep not in self.links:
            codec = self.compression if self.compression != "auto" else auto_compression(ep)
            # a make's reply holds at most MAX_MAKE_SAMPLES rows, of the recipe every host of the plan serves
            self.links[ep] = Link(ep, self.timeout_s, self.curve, codec, reply_limit(self.stream, MAX_MAKE_SAMPLES))
            self.poller.register(self.links[ep].sock, zmq.POLLIN)
        return self.links[ep]

    def join(self, ep: str, info: PlanInfo, now: float) -> None:
        """Host ``ep`` answered what it serves: it joins when that is this plan, else is named once."""
        problem = self.plan.problem(info.plan)
        if problem:
            self.other_plan(ep, problem.removeprefix("another plan: "))
            return
        if ep in self.router.hosts or ep in self.memory.same or ep in self.memory.left_out:
            return
        kept = alias_of(ep, info, self.names)
        if kept is not None:
            self.memory.same[ep] = kept
            return
        self.stream = self.stream or info.stream
        if info.withdraws:
            self.withdraws.add(ep)
        link = self._link(ep)
        codecs = info.stream.get("codecs", ())
        link.compression = self.compression if self.compression != "auto" else auto_compression(ep, codecs)
        self.router.join(ep, now, info.rate or self.memory.rates.get(ep), info.workers)

    def leave_out(self, ep: str, why: str) -> None:
        """Leave peer ``ep`` out of the fleet for this process: named in one log line (once: a
        peer left out before is not named again), its link closed (nothing more of it is
        received, nothing more sent to it), its videos' makes asked of their next hosts (``Pass.rescue``)."""
        if ep not in self.memory.left_out:
            log.warning("%s: left out of the fleet: %s", ep, why)
            self.memory.left_out[ep] = why
        self.router.leave(ep)
        link = self.links.pop(ep, None)
        if link is not None:
            self.poller.unregister(link.sock)
            link.__exit__(None, None, None)

    def left_out_line(self) -> str:
        """Each peer left out, for the process or this pass, and why, as one clause (``"a: why; b: why"``)."""
        return "; ".join(f"{ep}: {why}" for ep, why in {**self.out_for_pass, **self.memory.left_out}.items())

    def _resolve(self, now: float) -> None:
        """Resolve the endpoint again: ask new hosts what they serve; hand a gone host's videos on."""
        if now - self.resolved < RESOLVE_S:
            return
        self.resolved = now
        try:
            current = set(resolve_endpoints(self.endpoint))
        except (OSError, ValueError) as e:  # a name that stops resolving for a while: keep the fleet
            log.warning("%s: %s (the fleet stays as it was)", self.endpoint, e)
            return
        for ep in sorted(current - set(self.router.hosts) - {*self.out_for_pass, *self.memory.same, *self.memory.left_out}):
            self._link(ep)._send(PlanAsk().to_wire())  # its answer, a PlanInfo, joins it (Pass.receive)
        for ep in sorted(set(self.router.hosts) - current):
            self.router.leave(ep)

    def other_plan(self, ep: str, why: str, theirs: Optional[Manifest] = None, defer: bool = True) -> None:
        """Host ``ep`` serves another plan than the pass's: it leaves the fleet for the pass,
        named once in one line with the files whose tags differ from the pass's manifest
        (:func:`manifest_diff` against ``theirs``, its manifest, else read of it for at most
        :data:`ASK_NEXT_S` seconds), or ``why`` (one clause) where no file differs or the
        manifests are not known; before the pass's manifest is read, once it is (:meth:`_manifest`)
        unless not ``defer``. A peer not of the fleet's hosts (one that never served its plan:
        a made-up plan) is left out for the process instead (:meth:`leave_out`)."""
        if ep in self.out_for_pass or ep in self.memory.left_out:
            return
        if ep not in self.members:
            self.leave_out(ep, f"it serves another plan: {why}")
            return
        self.out_for_pass[ep] = f"it serves another plan: {why}"
        if ep in self.router.hosts:
            self.router.leave(ep)  # its videos' makes go to their next hosts (Pass.rescue)
        if self.manifest is None and defer:
            self.unnamed[ep] = (why, theirs)
            return
        files = ""
        if self.manifest is not None:
            try:
                if theirs is None:
                    with Link(ep, ASK_NEXT_S, self.curve) as link:
                        theirs = read_manifest(link, ASK_NEXT_S)
                files = manifest_diff(self.manifest, "in this pass's plan", theirs, "now")
            except BrokenPeer as e:  # not a v2v-serve: named for that, out for the process
                self.leave_out(ep, e.left_out_for)
                return
            except (TimeoutError, PlanServerError) as e:
                files = f"{why}; its listing could not be read ({e})"
        self.changed[ep] = files or why
        log.warning("%s: left out of the fleet for this pass: it serves another plan: %s", ep, self.changed[ep])

    def _name_unnamed(self) -> None:
        """Name the hosts :meth:`other_plan` left out before the pass's manifest was known."""
        unnamed, self.unnamed = self.unnamed, {}
        for ep, (why, theirs) in unnamed.items():
            self.out_for_pass.pop(ep, None)
            self.other_plan(ep, why, theirs, defer=False)

    def no_host_left(self, epoch: int) -> PlanMismatch:
        """The error of a pass of ``epoch`` that no host serves the plan of any more (each left
        out by :meth:`other_plan`): one line naming what they serve instead, the files that
        changed where known, and that the epoch starts over."""
        what = "; ".join(sorted(set(self.changed.values())))
        return PlanMismatch(f"{self.endpoint}: no host serves epoch {epoch}'s plan (manifest {self.plan.manifest}) any "
                            f"more: {what}; start epoch {epoch} over (set_epoch({epoch}), no position): its next pass "
                            "reads the plan the hosts serve now")

    def _manifest(self, epoch: int) -> Manifest:
        """The plan's manifest, of the first host that answers (:meth:`_first_part`) and serves
        it: one whose manifest is another's (restarted with a file replaced) is left out for the
        pass (:meth:`other_plan`).

        Raises:
            TimeoutError, PlanServerError: as :meth:`_first_part` and :func:`read_manifest`.
            PlanMismatch: every host that answered serves another manifest (:meth:`no_host_left`)."""
        if self.manifest is None:
            while self.manifest is None:
                if not self.router.hosts and self.unnamed:  # each left out for serving another manifest
                    self.manifest = self.memory.known.get(self.plan.manifest)
                    self._name_unnamed()
                    raise self.no_host_left(epoch)
                ep, first = self._first_part()
                try:
                    got = read_manifest(self.links[ep], self.timeout_s, first)
                except BrokenPeer as e:  # the next host that answers is read
                    self.leave_out(ep, e.left_out_for)
                    continue
                if got.fingerprint() == self.plan.manifest:
                    self.manifest = got
                else:
                    self.other_plan(ep, f"manifest {got.fingerprint()}", got)
            self.memory.known[self.plan.manifest] = self.manifest
            self._name_unnamed()
            for v, n in self.manifest.slots:
                if n is not None:
                    self.memory.windows.setdefault(v, n)
        return self.manifest

    def _first_part(self) -> Tuple[str, ManifestPart]:
        """``(host, its manifest's first part)``: the hosts asked in turn, each for
        :data:`ASK_NEXT_S` seconds, round after round until ``timeout_s``. A host asked that
        did not answer, or refused, is named in one log line and leaves the fleet (one silent
        joins again when it answers the ``plan_ask`` of ``_resolve``; one refusing, for the
        pass), so the pass routes nothing to it; one that breaks the protocol is left out
        (:meth:`leave_out`).

        Raises:
            TimeoutError: no host answered within ``timeout_s``, naming them.
            PlanServerError: no host serves the plan, or every host refused or was left out
                (naming each and why)."""
        hosts = list(self.router.hosts)
        if not hosts:
            raise PlanServerError(f"{self.endpoint}: no host serves the plan")
        deadline = time.monotonic() + self.timeout_s
        silent: List[str] = []
        refused: Dict[str, str] = {}
        while any(h not in refused and h not in self.memory.left_out for h in hosts):
            for ep in [h for h in hosts if h not in refused and h not in self.memory.left_out]:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"{', '.join(silent) or self.endpoint}: no manifest within {self.timeout_s} s (each host "
                                       f"asked in turn for {ASK_NEXT_S} s)")
                try:
                    first = manifest_part(self.links[ep], 0, min(ASK_NEXT_S, left))
                except TimeoutError:
                    silent += [] if ep in silent else [ep]
                    continue
                except BrokenPeer as e:
                    self.leave_out(ep, e.left_out_for)
                    continue
                except PlanServerError as e:
                    refused[ep] = str(e)
                    continue
                for h in (h for h in silent if h != ep):
                    log.warning("%s: left out of the fleet until it answers: no manifest within %s s (read from %s)",
                                h, ASK_NEXT_S, ep)
                    self.router.leave(h)
                for h, why in refused.items():
                    log.warning("left out of the fleet: %s", why)
                    self.out_for_pass[h] = why.removeprefix(f"{h}: ")
                    self.router.leave(h)
                return ep, first
        raise PlanServerError("; ".join([*refused.values(), *(f"{h}: {self.memory.left_out[h]}" for h in hosts
                                                             if h in self.memory.left_out)]))

    # ------------------------------------------------------------------ reading
    def pass_for(self, manifest: Manifest, first: Fetch, prefetch: int, retry_s: float, now: float,
                 reader: Tuple[int, int] = (0, 1)) -> Pass:
        """A pass over this fleet of the epoch of ``first`` (its first step's fetch, added), with
        the fleet's router, the reader's memory and what it knows of its hosts; ``reader``:
        ``Pass``'s."""
        return Pass(self.router, self.memory, manifest, self.plan, first, prefetch, retry_s, str(self.endpoint),
                    self.withdraws, ChainMap(self.out_for_pass, self.memory.left_out), self.stream, self.ahead, now,
                    reader)

    def turn(self, read: Pass, todo, fetch_of, now: float,
             hold: bool = False) -> Optional[Tuple[int, Rows, Dict[str, np.ndarray]]]:
        """One turn of the pass's loop: the hosts listened to (``Router.listen``: a loop held
        since its last turn took no host for silent), the endpoint resolved again (at most every
        :data:`RESOLVE_S`), the window filled from ``todo`` and asked for, the head's rows
        (``Pass.head_rows``) once known and the quiet hosts pinged (``Pass.ping``), else what it
        waits on rescued (``Pass.rescue``, pings included); what the pass asked is sent.
        ``hold``: the loop holds :data:`HELD_STEPS` steps it has not taken, so the head is not
        taken out (None) and what it waits on is rescued all the same.

        Raises:
            PlanMismatch, PlanServerError: as :meth:`check_hosts_left`; as ``Pass.ask``."""
        self.router.listen(now)
        self._resolve(now)
        head = read.turn(todo, fetch_of, now, hold)
        self.send_out(read)
        if head is None:
            self.check_hosts_left(read)
        return head

    def receive(self, read: Pass, ep: str, msg, frames, now: float) -> None:
        """Host ``ep``'s message to pass ``read``: taken by the pass (``Pass.receive``); a host
        that says what it serves joins (:meth:`join`); a host that refused every make of the
        reader is left out, of the pass (another plan, :meth:`other_plan`) or of the process
        (:meth:`leave_out`); what the pass asked is sent.

        Raises:
            BrokenPeer: rows whose arrays cannot be read (the caller leaves ``ep`` out).
            PlanServerError: every host refused a make of a video."""
        read.receive(ep, msg, frames, now)
        if isinstance(msg, PlanInfo):
            self.join(ep, msg, now)
        refusing, read.refusing = read.refusing, []
        for host, code, why in refusing:
            if code in HOST_REFUSALS:
                self.leave_out(host, why)
            else:  # restarted on a corpus that changed: named with the files, once
                self.other_plan(host, f"a make refused: {why}")
        self.send_out(read)

    def send_out(self, read: Pass) -> None:
        """Send what pass ``read`` asked (its outbox, emptied), each make compressed as its host's
        link is; nothing to a peer left out (its link is closed)."""
        out, read.outbox = read.outbox, []
        for ep, msg in out:
            link = self.links.get(ep)
            if link is None or ep in self.memory.left_out:
                continue
            if isinstance(msg, Make):
                msg = replace(msg, compression=link.compression)
            link._send(msg.to_wire())

    def check_hosts_left(self, read: Pass) -> None:
        """Fail a pass that waits for a host while every host it had is left out.

        Raises:
            PlanMismatch: every host left out of the pass serves another plan (:meth:`no_host_left`).
            PlanServerError: every host left out (naming each and why)."""
        if not read.parked or self.router.hosts or not (self.memory.left_out or self.out_for_pass):
            return  # a host to ask, or none joined yet: the makes wait for one
        if self.changed:  # never read on with samples of another version of a file
            raise self.no_host_left(read.epoch)
        raise PlanServerError(f"{self.endpoint}: no host left serving the plan: {self.left_out_line()}")

    def take(self, read: Pass, heard: float) -> float:
        """Wait up to half a second for the hosts' answers to pass ``read``, or until the loop
        takes a step, and take them (:meth:`receive`); returns when a host was last heard
        (``heard``, or now). A peer that sends what cannot be read (``fetch.BrokenPeer``) is left
        out (:meth:`leave_out`) and the others' answers taken.

        Raises:
            TimeoutError: no host said anything for ``timeout_s`` while the head waited."""
        ready = dict(wait_readable(self.poller.poll, min(read.retry_s, 0.5)))
        if ready.pop(self._wake_r.fileno(), None) is not None:  # the loop took a step: no host's word
            while True:
                try:
                    self._wake_r.recv(4096)
                except BlockingIOError:
                    break
        if not ready:
            if time.monotonic() - heard > self.timeout_s:
                late = sorted({h for v in read.videos.values() for h, _, _ in v.flight.values()})
                raise TimeoutError(f"{', '.join(late) or self.endpoint}: no rows for {self.timeout_s} s "
                                   f"(step {read.window[0]})")
            return heard
        heard = time.monotonic()
        for ep, link in list(self.links.items()):
            while self.links.get(ep) is link and link.sock in ready and link.sock.poll(0):
                try:
                    got = link._recv(heard)
                    if got is None:
                        break
                    self.receive(read, ep, *got, heard)
                except BrokenPeer as e:
                    self.leave_out(e.peer, e.left_out_for)
        return heard

    def fetch_all(self, steps, prefetch: int, retry_s: float, fetch_of, first_of=None,
                  reader: Tuple[int, int] = (0, 1)) -> Iterator:
        """``(step, rows, arrays)`` for each of ``steps`` in order: the rows of ``fetch_of(0,
        step)``'s positions, each made by the host its video is routed to (module docstring;
        one pass's state and decisions: ``fleet_pass.Pass``; ``reader``: this process's index
        among the job's readers and their count, ``Pass``'s). The manifest is read here; then a
        thread of the pass's own turns it (:meth:`turn`, :meth:`take`: it alone uses the sockets
        until the generator is closed), holding up to :data:`HELD_STEPS` steps the loop has not
        taken and turning on while it holds them. Closing the generator (or the read being
        stopped, ``fetch.stopped_by``) stops the thread and waits for it.

        Raises:
            TimeoutError: no host said anything for ``timeout_s`` while the reader waited.
            PlanMismatch: no host serves the pass's plan any more (:meth:`no_host_left`).
            PlanServerError: every host left out, or a host sent what cannot be read.
            ReadStopped: this thread's read was stopped.
        Each raised in the loop's thread after the steps held before it, the same object.
        """
        todo = iter(steps)
        first = next(todo, None)
        if first is None:
            return
        f0 = fetch_of(0, first)
        manifest = self._manifest(f0.epoch)
        read = self.pass_for(manifest, f0, prefetch, retry_s, time.monotonic(), reader)
        read.add(first, f0)
        handed: "queue.Queue" = queue.Queue(maxsize=HELD_STEPS)
        stop = threading.Event()
        thread = threading.Thread(target=self._turn_pass, args=(read, todo, fetch_of, handed, stop),
                                  name="v2v-fleet-pass", daemon=True)
        self._turning = (thread, stop)
        thread.start()
        try:
            while True:
                try:
                    kind, value = handed.get(timeout=POLL_S)
                except queue.Empty:
                    check_stopped()
                    continue
                if kind == "end":
                    return
                if kind == "error":
                    raise value
                self._taken += 1
                self._wake()
                step, rows, arrays, served = value
                self._served = (rows, served)
                yield step, rows, arrays
        finally:
            self._stop_turning()

    def _turn_pass(self, read: Pass, todo, fetch_of, handed: "queue.Queue", stop: threading.Event) -> None:
        """The pass's thread: turned at each answer of the hosts, each step the loop takes, or
        every half second, until its window is read; each head handed on with the hosts that
        made its rows, then ``("end", None)``, or ``("error", exception)``."""
        try:
            with stopped_by(stop):
                heard = time.monotonic()
                taken = self._taken
                while read.window:
                    if self._taken != taken:  # the loop took a step: it wants the next from now
                        taken = self._taken
                        read.wanted(time.monotonic())
                    head = self.turn(read, todo, fetch_of, time.monotonic(), hold=handed.full())
                    if head is not None:
                        handed.put(("step", (*head, dict(read.last_served[1]))))  # the loop alone takes: room
                        continue
                    heard = self.take(read, heard)
            item = ("end", None)
        except ReadStopped:
            return
        except BaseException as e:  # raised in the loop's thread, the same object (type and traceback kept)
            item = ("error", e)
        while not stop.is_set():
            try:
                handed.put(item, timeout=POLL_S)
                return
            except queue.Full:
                continue

    def _wake(self) -> None:
        """Wake the pass's thread out of its wait on the hosts (:meth:`take`)."""
        try:
            self._wake_w.send(b"\0")
        except (BlockingIOError, OSError):
            pass  # a wake already waiting, or the fleet closed

    def _stop_turning(self) -> None:
        """Stop the pass's thread, if one runs, and wait for it (within ``fetch.POLL_S``: its
        waits on the hosts look at its stop that often)."""
        if self._turning is not None:
            thread, stop = self._turning
            stop.set()
            self._wake()
            if thread is not threading.current_thread():
                thread.join()
            self._turning = None

    def served(self, rows: Rows) -> Dict[str, int]:
        """{host endpoint: rows of ``rows`` (the step last yielded) holding a sample it made}."""
        last, served = self._served
        return dict(served) if rows is last else {}

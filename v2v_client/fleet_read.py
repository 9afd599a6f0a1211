"""Reading a fleet: hosts that each serve the whole corpus (a bucket, a shared folder), read as the
one plan a single server serves, each video made by the host the reader routes it to
(docs/scaling.md, "One plan, any fleet"). Free of torch.

* **The plan is the reader's.** The manifest is asked once a pass, of the first host that
  answers (``manifest_ask``, the hosts asked in turn, ``ASK_NEXT_S`` each: a host gone costs
  that, and leaves the fleet until it answers; its fingerprint must be the plan identity's), and
  the epoch's order is ``v2v_wire.plan.EpochPlan`` of it, the pure function every server
  computes: a position means the same sample at any fleet size, a single server included. It
  unfolds with each video's windows, as the corpus index gave them to the host asked, or as a
  host's decode learns them (a ``make`` of the video's windows, asked of the host the video is
  routed to, which keeps the samples it made for the makes that follow).
* **Routing** (``v2v_wire.fleet.Router``): each video of the positions this rank reads, from the
  step it yields to ``ahead`` positions past it, is asked (``make``: the video and the samples
  of it this rank's rows hold) of the host its ranking and the hosts' queues pick, as each host
  says them to every reader of every job (the job's ranks and DataLoader workers route alike);
  its later samples go to the same host while it answers. A host with this reader's work that
  answered nothing, not even a ping, for ``hedge_s`` has its videos asked of their next hosts
  too; the first answer wins.
* **The fleet changes**: the endpoint is resolved again every ``RESOLVE_S`` seconds; a new host
  serving the same plan takes work from its first answer, a host gone hands its videos to the
  next hosts of their rankings, a host serving another plan is named once and left out, and
  a host that says the instance of one read already (one host under two names) is read once
  (``alias_of``).

A host keeps no record of the reader: a ``make`` names its samples, and a restarted host makes
them again.
"""
from __future__ import annotations

import logging
import time
from typing import Dict, Iterator, List, Optional, Set, Tuple

import numpy as np
import zmq

from v2v_wire.fleet import Router
from v2v_wire.plan import Manifest, PlanIdentity
from v2v_wire.plan_messages import ManifestAsk, ManifestPart, PlanAsk, PlanInfo, Refused, Rows

from .endpoints import auto_compression, resolve_endpoints
from .fetch import Link, PlanServerError
from .fleet_pass import STEAL_S, Pass, take

__all__ = ["Fleet", "load_manifest", "manifest_part", "asked_fleet", "listing_diff", "alias_of", "HEDGE_S",
           "RESOLVE_S", "ASK_NEXT_S"]

log = logging.getLogger("v2v.client")

#: Seconds a host may answer nothing while the reader waits on it before its videos are asked of
#: the next hosts of their rankings too (``Router``'s ``hedge_s``).
HEDGE_S = 10.0
#: Seconds between resolutions of the fleet's endpoint (a Kubernetes headless Service's name).
RESOLVE_S = 5.0
#: Seconds a host may take to answer what a pass asks the fleet once (the manifest; what it serves,
#: while the plan unfolds: ``servers.Servers.ask``) before the next host is asked: a live host's
#: loop answers within its 0.1 s poll, a dead or unreachable one never, and every pass (each
#: epoch, each DataLoader worker) asks, so a gone host costs this, not ``timeout_s``.
ASK_NEXT_S = 2.0


def load_manifest(link: Link, plan: PlanIdentity, timeout_s: float, first: Optional[ManifestPart] = None) -> Manifest:
    """The manifest of ``link``'s server, asked part by part (``manifest_ask``); ``first``: its
    part at offset 0 when already read (:meth:`Fleet._manifest`).

    Raises:
        TimeoutError: the server did not answer within ``timeout_s``.
        PlanServerError: it refused, or its manifest's fingerprint is not ``plan``'s (one line).
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
    manifest = Manifest.of(dict(zip(videos, slots)), part.crops_per_window,
                           dict(zip(videos, tags)) if part.tagged else None)
    if manifest.fingerprint() != plan.manifest:
        raise PlanServerError(f"{link.endpoint}: its manifest's fingerprint is {manifest.fingerprint()}, its plan "
                              f"names {plan.manifest}")
    return manifest


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


def asked_fleet(servers: List[str], first_s: float, wait_s: float, curve: Optional[tuple]) -> Dict[str, PlanInfo]:
    """What each of ``servers`` serves, all asked at once: the first answer awaited ``first_s``
    seconds, the others ``wait_s`` more; in ``servers``' order, those that answered. One that
    answers what cannot be read (another protocol version) is named in one log line and left out.

    Raises:
        TimeoutError: none answered within ``first_s``, naming them.
        PlanServerError: none answered, and one refused or spoke another version (its line)."""
    infos: Dict[str, PlanInfo] = {}
    refused: Dict[str, str] = {}
    links = {ep: Link(ep, first_s, curve) for ep in servers}
    poller = zmq.Poller()
    try:
        for link in links.values():
            link._send(PlanAsk().to_wire())
            poller.register(link.sock, zmq.POLLIN)
        deadline = time.monotonic() + first_s
        while len(infos) + len(refused) < len(servers) and time.monotonic() < deadline:
            ready = dict(poller.poll(int(max(0.0, deadline - time.monotonic()) * 1000)))
            for ep, link in links.items():
                if link.sock not in ready or ep in infos or ep in refused:
                    continue
                try:
                    got = link._recv(time.monotonic())
                except PlanServerError as e:
                    refused[ep] = str(e)
                    log.warning("%s: left out: %s", ep, e)
                    continue
                if got is not None and isinstance(got[0], PlanInfo):
                    if not infos:
                        deadline = min(deadline, time.monotonic() + wait_s)
                    infos[ep] = got[0]
                elif got is not None and isinstance(got[0], Refused):
                    refused[ep] = f"{ep}: {got[0].message}"
    finally:
        for link in links.values():
            link.__exit__(None, None, None)
    if not infos:
        if refused:
            raise PlanServerError("; ".join(refused.values()))
        raise TimeoutError(f"{', '.join(servers)}: no answer to 'what do you serve' within {first_s} s (is a "
                           "v2v-serve running there?)")
    return {ep: infos[ep] for ep in servers if ep in infos}


def listing_diff(ep_a: str, plan_a: PlanIdentity, ep_b: str, plan_b: PlanIdentity, timeout_s: float,
                 curve: Optional[tuple], most: int = 3) -> str:
    """The first files (at most ``most``) whose path or tag differs between two hosts' manifests, as
    one clause: ``"listings differ: a.mp4 (tag 123:456 on tcp://a, 123:789 on tcp://b), ..."``.

    Raises:
        TimeoutError, PlanServerError: as :func:`load_manifest`."""
    tagged = []
    for ep, plan in ((ep_a, plan_a), (ep_b, plan_b)):
        with Link(ep, timeout_s, curve) as link:
            m = load_manifest(link, plan, timeout_s)
        tagged.append(dict(zip((v for v, _ in m.slots), m.tags or [None] * len(m.slots))))
    a, b = tagged
    differ = sorted(v for v in set(a) | set(b) if a.get(v, False) != b.get(v, False))
    if not differ:
        return "listings differ in their crops per window"

    def side(v, d):
        return "absent" if v not in d else f"tag {d[v]}"

    shown = ", ".join(f"{v} ({side(v, a)} on {ep_a}, {side(v, b)} on {ep_b})" for v in differ[:most])
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
        windows: video -> windows learned so far (kept by the caller across passes; updated).
        rates: host -> the samples/s it said (kept by the caller across passes, so that an
            unchanged fleet routes each video where it did; updated).
        made: video -> the host whose rows of it were read last (its frame cache holds the
            video: kept by the caller across passes, ``Router.route``'s ``held``; updated).
        ahead: positions past the step being read whose videos are asked for (None: ten decodes
            per worker of the fleet, as ``harness.fleet_sim`` measured is needed, at least the
            prefetched steps).
        hedge_s: :data:`HEDGE_S`.
        same: endpoint -> the endpoint of the same host read in its place (:func:`alias_of`:
            kept by the caller across passes, so each is said once; updated).
    """

    def __init__(self, endpoint, hosts: List[Tuple[str, PlanInfo]], plan: PlanIdentity, timeout_s: float,
                 curve: Optional[tuple], compression: str, windows: Dict[str, int], ahead: Optional[int] = None,
                 hedge_s: float = HEDGE_S, rates: Optional[Dict[str, float]] = None,
                 made: Optional[Dict[str, str]] = None, same: Optional[Dict[str, str]] = None):
        self.endpoint, self.plan, self.timeout_s, self.curve = endpoint, plan, timeout_s, curve
        self.compression, self.windows, self.ahead = compression, windows, ahead
        self.rates = {} if rates is None else rates
        self.made = {} if made is None else made
        self.same = {} if same is None else same
        self.names: Dict[str, str] = {}  # instance -> the endpoint its host is read under (alias_of)
        self.links: Dict[str, Link] = {}
        self.poller = zmq.Poller()  # every link's socket (fleet_pass.take waits on them)
        self.workers: Dict[str, int] = {}
        self.refused: Set[str] = set()  # hosts serving another plan: named once, left out
        self.router = Router([], hedge_s=min(hedge_s, timeout_s), now=time.monotonic(), patience_s=STEAL_S)
        self.stream: Optional[dict] = None  # the first host's stream info: a padding row's shapes before any row
        for ep, info in hosts:
            self.join(ep, info, time.monotonic())
        self.resolved = time.monotonic()
        self.manifest: Optional[Manifest] = None
        self.like: Optional[Dict[str, np.ndarray]] = None  # one row of each array: a padding row's zeros
        self.last_served: Tuple[Optional[Rows], Dict[str, int]] = (None, {})  # the last step's rows by host

    def __enter__(self) -> "Fleet":
        return self

    def __exit__(self, *exc) -> None:
        for link in self.links.values():
            link.__exit__(*exc)

    # ------------------------------------------------------------------ the fleet
    def _link(self, ep: str) -> Link:
        if ep not in self.links:
            codec = self.compression if self.compression != "auto" else auto_compression(ep)
            self.links[ep] = Link(ep, self.timeout_s, self.curve, codec)
            self.poller.register(self.links[ep].sock, zmq.POLLIN)
        return self.links[ep]

    def join(self, ep: str, info: PlanInfo, now: float) -> None:
        """Host ``ep`` answered what it serves: it joins when that is this plan, else is named once."""
        problem = self.plan.problem(info.plan)
        if problem:
            if ep not in self.refused:
                log.warning("%s: left out of the fleet: it serves %s", ep, problem)
                self.refused.add(ep)
            return
        if ep in self.router.hosts or ep in self.same:
            return
        kept = alias_of(ep, info, self.names)
        if kept is not None:
            self.same[ep] = kept
            return
        self.stream = self.stream or info.stream
        link = self._link(ep)
        codecs = info.stream.get("codecs", ())
        link.compression = self.compression if self.compression != "auto" else auto_compression(ep, codecs)
        self.workers[ep] = int((info.stream.get("feed") or {}).get("workers") or 1)
        self.router.join(ep, now, self.rates.get(ep))

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
        for ep in sorted(current - set(self.router.hosts) - self.refused - set(self.same)):
            self._link(ep)._send(PlanAsk().to_wire())  # its answer, a PlanInfo, joins it (Pass.receive)
        for ep in sorted(set(self.router.hosts) - current):
            self.router.leave(ep)

    def _manifest(self) -> Manifest:
        """The plan's manifest, of the first host that answers (:meth:`_first_part`).

        Raises:
            TimeoutError, PlanServerError: as :meth:`_first_part` and :func:`load_manifest`."""
        if self.manifest is None:
            ep, first = self._first_part()
            self.manifest = load_manifest(self.links[ep], self.plan, self.timeout_s, first)
            for v, n in self.manifest.slots:
                if n is not None:
                    self.windows.setdefault(v, n)
        return self.manifest

    def _first_part(self) -> Tuple[str, ManifestPart]:
        """``(host, its manifest's first part)``: the hosts asked in turn, each for
        :data:`ASK_NEXT_S` seconds, round after round until ``timeout_s``. A host asked that
        did not answer, or refused, is named in one log line and leaves the fleet (one silent
        joins again when it answers the ``plan_ask`` of ``_resolve``), so the pass routes
        nothing to it.

        Raises:
            TimeoutError: no host answered within ``timeout_s``, naming them.
            PlanServerError: no host serves the plan, or every host refused (their lines)."""
        hosts = list(self.router.hosts)
        if not hosts:
            raise PlanServerError(f"{self.endpoint}: no host serves the plan")
        deadline = time.monotonic() + self.timeout_s
        silent: List[str] = []
        refused: Dict[str, str] = {}
        while len(refused) < len(hosts):
            for ep in [h for h in hosts if h not in refused]:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"{', '.join(silent) or self.endpoint}: no manifest within {self.timeout_s} s (each host "
                                       f"asked in turn for {ASK_NEXT_S} s)")
                try:
                    first = manifest_part(self.links[ep], 0, min(ASK_NEXT_S, left))
                except TimeoutError:
                    silent += [] if ep in silent else [ep]
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
                    self.refused.add(h)
                    self.router.leave(h)
                return ep, first
        raise PlanServerError("; ".join(refused.values()))

    # ------------------------------------------------------------------ reading
    def fetch_all(self, steps, prefetch: int, retry_s: float, fetch_of, first_of=None) -> Iterator:
        """``(step, rows, arrays)`` for each of ``steps`` in order: the rows of ``fetch_of(0,
        step)``'s positions, each made by the host its video is routed to (module docstring;
        one pass's state and decisions: ``fleet_pass.Pass``).

        Raises:
            TimeoutError: no host said anything for ``timeout_s`` while the reader waited.
            PlanServerError: no host left serving the plan, or a host sent what cannot be read.
        """
        manifest = self._manifest()
        todo = iter(steps)
        first = next(todo, None)
        if first is None:
            return
        f0 = fetch_of(0, first)
        read = Pass(self, manifest, f0, prefetch, retry_s)
        read.add(first, f0)
        while read.window:
            now = time.monotonic()
            self._resolve(now)
            read.fill(todo, fetch_of)
            read.ask_window(now)
            head = read.head_rows()
            if head is not None:
                yield head
                continue
            read.rescue(now)
            take(read, self.timeout_s)

    def served(self, rows: Rows) -> Dict[str, int]:
        """{host endpoint: rows of ``rows`` (the step last yielded) holding a sample it made}."""
        last, served = self.last_served
        return dict(served) if rows is last else {}

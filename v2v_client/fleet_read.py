"""Reading a fleet: hosts that each serve the whole corpus (a bucket, a shared folder), read as the
one plan a single server serves, each video made by the host the reader routes it to
(docs/scaling.md, "One plan, any fleet"). Free of torch.

* **The plan is the reader's.** The manifest is asked once of a host (``manifest_ask``; its
  fingerprint must be the plan identity's), and the epoch's order is ``v2v_wire.plan.EpochPlan``
  of it, the pure function every server computes: a position means the same sample at any fleet
  size, a single server included. It unfolds with each video's windows, as the corpus index gave
  them to the host asked, or as a host's decode learns them (a ``make`` of the video's windows,
  asked of the host the video is routed to, which keeps the samples it made for the makes that
  follow).
* **Routing** (``v2v_wire.fleet.Router``): each video of the positions this rank reads, from the
  step it yields to ``ahead`` positions past it, is asked (``make``: the video and the samples
  of it this rank's rows hold) of the host its ranking and the hosts' loads pick (its owner
  alone where the job has several readers, ranks or DataLoader workers: each then picks the
  same host); its later samples go to the same host while it answers. A host silent for
  ``hedge_s`` while the reader waits on it has its videos asked of their next hosts too; the
  first answer wins.
* **The fleet changes**: the endpoint is resolved again every ``RESOLVE_S`` seconds; a new host
  serving the same plan takes work from its first answer, a host gone hands its videos to the
  next hosts of their rankings, a host serving another plan is named once and left out.
* **A bad peer is left out**: a peer that sends what no v2v-serve of this protocol sends (not
  msgpack, another version, past the wire's bounds: ``fetch.BrokenPeer``), serves another plan, or
  refuses every read of this reader (its outputs or compression) is named once in this process
  and left out, its videos asked of their next hosts; a frame over the largest legitimate reply
  (``fetch.reply_limit``) cuts its connection before it is received. A host that refuses one
  make stays (``fleet_pass.Pass.receive``). With no host left: one error naming each peer left
  out and why.

A host keeps no record of the reader: a ``make`` names its samples, and a restarted host makes
them again.
"""
from __future__ import annotations

import logging
import time
from typing import Dict, Iterator, List, Optional, Tuple

import numpy as np
import zmq

from v2v_wire.fleet import Router
from v2v_wire.plan import Manifest, PlanIdentity
from v2v_wire.plan_messages import MAX_MAKE_SAMPLES, ManifestAsk, ManifestPart, PlanAsk, PlanInfo, Refused, Rows
from v2v_wire.protocol import MAX_HEADER_BYTES

from .endpoints import auto_compression, resolve_endpoints
from .fetch import BrokenPeer, Link, PlanServerError, reply_limit, wait_readable
from .fleet_pass import STEAL_S, Pass, take

__all__ = ["Fleet", "load_manifest", "asked_fleet", "listing_diff", "HEDGE_S", "RESOLVE_S"]

log = logging.getLogger("v2v.client")

#: Seconds a host may answer nothing while the reader waits on it before its videos are asked of
#: the next hosts of their rankings too (``Router``'s ``hedge_s``).
HEDGE_S = 10.0
#: Seconds between resolutions of the fleet's endpoint (a Kubernetes headless Service's name).
RESOLVE_S = 5.0


def load_manifest(link: Link, plan: PlanIdentity, timeout_s: float) -> Manifest:
    """The manifest of ``link``'s server, asked part by part (``manifest_ask``).

    Raises:
        TimeoutError: the server did not answer within ``timeout_s``.
        PlanServerError: it refused, or its manifest's fingerprint is not ``plan``'s (one line).
    """
    videos: List[str] = []
    tags: List[Optional[str]] = []
    slots: List[Optional[int]] = []
    total, kpw, tagged = None, 1, True
    while total is None or len(videos) < total:
        deadline = time.monotonic() + timeout_s
        while True:
            link._send(ManifestAsk(len(videos)).to_wire())
            got = link._recv(min(deadline, time.monotonic() + 5.0))
            if got is not None and isinstance(got[0], ManifestPart) and got[0].offset == len(videos):
                break
            if got is not None and isinstance(got[0], Refused):
                raise PlanServerError(f"{link.endpoint}: {got[0].message}")
            if time.monotonic() >= deadline:
                raise TimeoutError(f"{link.endpoint}: no manifest within {timeout_s} s")
        part: ManifestPart = got[0]
        total, kpw, tagged = part.total, part.crops_per_window, part.tagged
        if not part.videos and len(videos) < total:
            raise PlanServerError(f"{link.endpoint}: its manifest stops at {len(videos)} of {total} videos")
        videos += part.videos
        tags += part.tags
        slots += part.slots
    manifest = Manifest.of(dict(zip(videos, slots)), kpw, dict(zip(videos, tags)) if tagged else None)
    if manifest.fingerprint() != plan.manifest:
        raise PlanServerError(f"{link.endpoint}: its manifest's fingerprint is {manifest.fingerprint()}, its plan "
                              f"names {plan.manifest}")
    return manifest


def asked_fleet(servers: List[str], first_s: float, wait_s: float, curve: Optional[tuple],
                left_out: Optional[Dict[str, str]] = None) -> Dict[str, PlanInfo]:
    """What each of ``servers`` serves, all asked at once: the first answer awaited ``first_s``
    seconds, the others ``wait_s`` more; in ``servers``' order, those that answered. One that
    answers what cannot be read (another protocol version) or refuses is named in one log line,
    left out, and noted in ``left_out`` (endpoint -> why).

    Raises:
        TimeoutError: none answered within ``first_s``, naming them.
        PlanServerError: none answered, and one refused or broke the protocol: one line naming
            each and why it was left out."""
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
            ready = dict(wait_readable(poller.poll, deadline - time.monotonic()))
            for ep, link in links.items():
                if link.sock not in ready or ep in infos or ep in refused:
                    continue
                try:
                    got = link._recv(time.monotonic())
                except BrokenPeer as e:
                    refused[ep] = f"it breaks the protocol: {e.why}"
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
    if left_out is not None:
        left_out.update(refused)
    if not infos:
        if refused:
            silent = [f"{ep}: no answer within {first_s} s (a reply over {MAX_HEADER_BYTES} bytes cuts its connection)"
                      for ep in servers if ep not in refused]
            raise PlanServerError("; ".join([f"{ep}: {why}" for ep, why in refused.items()] + silent))
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
        readers: readers of the job routing the fleet at once, this one included (its ranks
            times their DataLoader workers: ``Router``'s ``readers``).
        left_out: peers left out -> why (kept by the caller across passes and pickled to its
            DataLoader workers, so that each is named once; updated: :meth:`leave_out`).
    """

    def __init__(self, endpoint, hosts: List[Tuple[str, PlanInfo]], plan: PlanIdentity, timeout_s: float,
                 curve: Optional[tuple], compression: str, windows: Dict[str, int], ahead: Optional[int] = None,
                 hedge_s: float = HEDGE_S, rates: Optional[Dict[str, float]] = None,
                 made: Optional[Dict[str, str]] = None, readers: int = 1, left_out: Optional[Dict[str, str]] = None):
        self.endpoint, self.plan, self.timeout_s, self.curve = endpoint, plan, timeout_s, curve
        self.compression, self.windows, self.ahead = compression, windows, ahead
        self.rates = {} if rates is None else rates
        self.made = {} if made is None else made
        self.links: Dict[str, Link] = {}
        self.poller = zmq.Poller()  # every link's socket (fleet_pass.take waits on them)
        self.workers: Dict[str, int] = {}
        self.left_out: Dict[str, str] = {} if left_out is None else left_out  # peers left out -> why (leave_out)
        self.router = Router([], hedge_s=min(hedge_s, timeout_s), now=time.monotonic(), patience_s=STEAL_S,
                             readers=readers)
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
            # a make's reply holds at most MAX_MAKE_SAMPLES rows, of the recipe every host of the plan serves
            self.links[ep] = Link(ep, self.timeout_s, self.curve, codec, reply_limit(self.stream, MAX_MAKE_SAMPLES))
            self.poller.register(self.links[ep].sock, zmq.POLLIN)
        return self.links[ep]

    def join(self, ep: str, info: PlanInfo, now: float) -> None:
        """Host ``ep`` answered what it serves: it joins when that is this plan, else is named once."""
        problem = self.plan.problem(info.plan)
        if problem:
            self.leave_out(ep, f"it serves {problem}")
            return
        if ep in self.router.hosts:
            return
        self.stream = self.stream or info.stream
        link = self._link(ep)
        codecs = info.stream.get("codecs", ())
        link.compression = self.compression if self.compression != "auto" else auto_compression(ep, codecs)
        self.workers[ep] = int((info.stream.get("feed") or {}).get("workers") or 1)
        self.router.join(ep, now, self.rates.get(ep))

    def leave_out(self, ep: str, why: str) -> None:
        """Leave peer ``ep`` out of the fleet for this process: named in one log line (once: a
        peer left out before is not named again), its link closed (nothing more of it is
        received), its videos' makes asked of their next hosts (``Pass.rescue``)."""
        if ep not in self.left_out:
            log.warning("%s: left out of the fleet: %s", ep, why)
            self.left_out[ep] = why
        self.router.leave(ep)
        link = self.links.pop(ep, None)
        if link is not None:
            self.poller.unregister(link.sock)
            link.__exit__(None, None, None)

    def left_out_line(self) -> str:
        """Each peer left out and why, as one clause (``"a: why; b: why"``)."""
        return "; ".join(f"{ep}: {why}" for ep, why in self.left_out.items())

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
        for ep in sorted(current - set(self.router.hosts) - set(self.left_out)):
            self._link(ep)._send(PlanAsk().to_wire())  # its answer, a PlanInfo, joins it (Pass.receive)
        for ep in sorted(set(self.router.hosts) - current):
            self.router.leave(ep)

    def _manifest(self) -> Manifest:
        if self.manifest is None:
            ep = next(iter(self.router.hosts), None)
            if ep is None:
                raise PlanServerError(f"{self.endpoint}: no host serves the plan")
            self.manifest = load_manifest(self.links[ep], self.plan, self.timeout_s)
            for v, n in self.manifest.slots:
                if n is not None:
                    self.windows.setdefault(v, n)
        return self.manifest

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

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
  of it this rank's rows hold) of the host its ranking and the hosts' loads pick; its later
  samples go to the same host while it answers. A host silent for ``hedge_s`` while the reader
  waits on it has its videos asked of their next hosts too; the first answer wins.
* **The fleet changes**: the endpoint is resolved again every ``RESOLVE_S`` seconds; a new host
  serving the same plan takes work from its first answer, a host gone hands its videos to the
  next hosts of their rankings, a host serving another plan is named once and left out.

A host keeps no record of the reader: a ``make`` names its samples, and a restarted host makes
them again.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Dict, Iterator, List, Optional, Set, Tuple

import numpy as np
import zmq

from v2v_wire.codecs import decode_batch_arrays
from v2v_wire.fleet import Router, rank_hosts
from v2v_wire.plan import EpochPlan, Manifest, PlanIdentity
from v2v_wire.plan_messages import (MAX_MAKE_PATH, MAX_MAKE_SAMPLES, Make, ManifestAsk, ManifestPart, PlanAsk,
                                     PlanInfo, Refused, Rows)
from v2v_wire.protocol import MAX_BATCH_BYTES, ProtocolError

from .endpoints import auto_compression, resolve_endpoints
from .fetch import Link, PlanServerError, _with_padding

__all__ = ["Fleet", "load_manifest", "asked_fleet", "listing_diff", "HEDGE_S", "RESOLVE_S"]

log = logging.getLogger("v2v.client")

#: Seconds a host may answer nothing while the reader waits on it before its videos are asked of
#: the next hosts of their rankings too (``Router``'s ``hedge_s``).
HEDGE_S = 10.0
#: Seconds between resolutions of the fleet's endpoint (a Kubernetes headless Service's name).
RESOLVE_S = 5.0
#: Videos whose windows a reader asks for at once while its plan unfolds, per host.
UNFOLD_PER_HOST = 4
#: Seconds the step being read may wait on a video before the next host of its ranking is asked
#: for a copy too (``Fleet._steal``).
STEAL_S = 1.0


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


def asked_fleet(servers: List[str], first: PlanInfo, wait_s: float, curve: Optional[tuple]) -> Dict[str, PlanInfo]:
    """What each of ``servers`` serves (``first``: the first's answer, asked already), the others
    asked at once and awaited ``wait_s`` seconds: those silent by then are left out, named in one
    log line (a fleet reads on with the rest, and a host that answers later joins,
    :meth:`Fleet._resolve`)."""
    infos = {servers[0]: first}
    links = {ep: Link(ep, wait_s, curve) for ep in servers[1:]}
    try:
        for link in links.values():
            link._send(PlanAsk().to_wire())
        deadline = time.monotonic() + wait_s
        poller = zmq.Poller()
        for link in links.values():
            poller.register(link.sock, zmq.POLLIN)
        while len(infos) < len(servers) and time.monotonic() < deadline:
            ready = dict(poller.poll(int(max(0.0, deadline - time.monotonic()) * 1000)))
            for ep, link in links.items():
                if link.sock in ready and ep not in infos:
                    got = link._recv(time.monotonic())
                    if got is not None and isinstance(got[0], PlanInfo):
                        infos[ep] = got[0]
    finally:
        for link in links.values():
            link.__exit__(None, None, None)
    for ep in servers:
        if ep not in infos:
            log.warning("%s: left out of the fleet for now: no answer to 'what do you serve' within %s s", ep, wait_s)
    return infos


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


@dataclass
class _Video:
    """What this reader asked of one video in one pass: the host asked, the samples asked of it
    (ordinal -> request id), and the requests in flight (request id -> (host, ordinals, asked at))."""

    host: Optional[str] = None
    position: int = 2 ** 62  # the first position of the epoch that needs it (the hosts' order)
    asked: Dict[int, int] = field(default_factory=dict)
    flight: Dict[int, Tuple[str, Tuple[int, ...], float]] = field(default_factory=dict)


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
        ahead: positions past the step being read whose videos are asked for (None: ten decodes
            per worker of the fleet, as ``harness.fleet_sim`` measured is needed, at least the
            prefetched steps).
        hedge_s: :data:`HEDGE_S`.
    """

    def __init__(self, endpoint, hosts: List[Tuple[str, PlanInfo]], plan: PlanIdentity, timeout_s: float,
                 curve: Optional[tuple], compression: str, windows: Dict[str, int], ahead: Optional[int] = None,
                 hedge_s: float = HEDGE_S):
        self.endpoint, self.plan, self.timeout_s, self.curve = endpoint, plan, timeout_s, curve
        self.compression, self.windows, self.ahead = compression, windows, ahead
        self.links: Dict[str, Link] = {}
        self.workers: Dict[str, int] = {}
        self.refused: Set[str] = set()  # hosts serving another plan: named once, left out
        self.router = Router([], hedge_s=min(hedge_s, timeout_s), now=time.monotonic())
        for ep, info in hosts:
            self._join(ep, info, time.monotonic())
        self.resolved = time.monotonic()
        self.manifest: Optional[Manifest] = None
        self.like: Optional[Dict[str, np.ndarray]] = None  # one row of each array: a padding row's zeros
        self._served: Tuple[Optional[Rows], Dict[str, int]] = (None, {})  # the last step's rows by host

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
        return self.links[ep]

    def _join(self, ep: str, info: PlanInfo, now: float) -> None:
        """Host ``ep`` answered what it serves: it joins when that is this plan, else is named once."""
        problem = self.plan.problem(info.plan)
        if problem:
            if ep not in self.refused:
                log.warning("%s: left out of the fleet: it serves %s", ep, problem)
                self.refused.add(ep)
            return
        if ep in self.router.hosts:
            return
        link = self._link(ep)
        codecs = info.stream.get("codecs", ())
        link.compression = self.compression if self.compression != "auto" else auto_compression(ep, codecs)
        self.workers[ep] = int((info.stream.get("feed") or {}).get("workers") or 1)
        self.router.join(ep, now)

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
        for ep in sorted(current - set(self.router.hosts) - self.refused):
            self._link(ep)._send(PlanAsk().to_wire())  # its answer, a PlanInfo, joins it (_receive)
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
        step)``'s positions, each made by the host its video is routed to (module docstring).

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
        epoch, outputs = f0.epoch, f0.outputs
        plan = EpochPlan(manifest, self.plan.seed, epoch, self.plan.shuffle_buffer)
        plan.learn(self.windows)
        workers = sum(self.workers.get(h, 1) for h in self.router.hosts) or 1
        ahead = self.ahead if self.ahead is not None else 10 * workers * manifest.crops_per_window * 2
        window: List[int] = [first]
        spans: Dict[int, Tuple[int, int]] = {first: (f0.start, f0.stop)}
        videos: Dict[str, _Video] = {}
        got: Dict[Tuple[str, int], tuple] = {}  # (video, ordinal) -> (sample id, padding, params, arrays row)
        flight: Dict[Tuple[str, int], tuple] = {}  # (host, request) -> ("make", video, ordinals) | ("ask",)
        told: Set[str] = set()  # videos whose windows were asked for
        heard = head_since = time.monotonic()
        exhausted = False

        def send(video: str, ordinals: Optional[Tuple[int, ...]], host: str, now: float) -> None:
            link = self.links[host]
            req = next(link.ids)
            v = videos.setdefault(video, _Video())
            link._send(Make(req, epoch, video, ordinals, outputs, self.plan, link.compression,
                            min(v.position, 2 ** 62 - 1)).to_wire())
            flight[(host, req)] = ("make", video, ordinals)
            v.flight[req] = (host, ordinals, now)
            for o in ordinals or ():
                v.asked[o] = req

        def ask(video: str, ordinals: Optional[Tuple[int, ...]], now: float, position: Optional[int] = None) -> None:
            if position is not None:
                v = videos.setdefault(video, _Video())
                v.position = min(v.position, position)
            if len(video.encode()) > MAX_MAKE_PATH:
                raise PlanServerError(f"{video[:80]}...: a path over {MAX_MAKE_PATH} bytes, which a fleet's make "
                                      "cannot name: read these hosts as shards (v2v-serve --shard I/N)")
            if ordinals is not None and len(ordinals) > MAX_MAKE_SAMPLES:
                for i in range(0, len(ordinals), MAX_MAKE_SAMPLES):
                    ask(video, ordinals[i:i + MAX_MAKE_SAMPLES], now)
                return
            v = videos.setdefault(video, _Video())
            count = len(ordinals) if ordinals else 1
            if v.host in self.router.hosts and not self.router.suspect(v.host, now):
                self.router.ask(v.host, epoch, video, count, now)
            else:
                v.host = self.router.route(epoch, video, count, now)
            if v.host is None:
                raise PlanServerError(f"{self.endpoint}: no host left serving the plan "
                                      f"({len(self.refused)} left out for serving another)")
            send(video, ordinals, v.host, now)

        while window:
            now = time.monotonic()
            self._resolve(now)
            while not exhausted and (spans[window[-1]][0] - spans[window[0]][0] < ahead or len(window) < prefetch):
                nxt = next(todo, None)
                if nxt is None:
                    exhausted = True
                    break
                f = fetch_of(0, nxt)
                window.append(nxt)
                spans[nxt] = (f.start, f.stop)
                if plan.complete and f.start >= len(plan):
                    break  # past the epoch's end: no step after it holds a sample
            # ask what the window's decided positions need, and the windows that decide the rest
            want: Dict[str, List[int]] = {}
            first_needed: Dict[str, int] = {}
            undecided = False
            for s in window:
                for p in range(*spans[s]):
                    if p >= plan.known:
                        undecided = undecided or not plan.complete
                        continue
                    key = plan.key(p)
                    if key is None:
                        continue
                    o = key.ordinal(manifest.crops_per_window)
                    if (key.video, o) not in got and o not in videos.get(key.video, _Video()).asked:
                        want.setdefault(key.video, []).append(o)
                        first_needed.setdefault(key.video, p)
            for video, ords in want.items():
                ask(video, tuple(sorted(set(ords))), now, first_needed[video])
            if undecided:
                budget = UNFOLD_PER_HOST * max(1, len(self.router.hosts)) - sum(
                    1 for w in flight.values() if w[0] == "make" and w[2] is None)
                for video in plan.next_videos(len(plan.videos)):
                    if budget <= 0:
                        break
                    if video not in self.windows and video not in told:
                        told.add(video)
                        ask(video, None, now, plan.known)
                        budget -= 1
            # the head step, once every row is known
            head = window[0]
            merged = self._step(plan, spans[head], got, epoch, manifest.crops_per_window)
            if merged is not None:
                window.pop(0)
                del spans[head]
                head_since = time.monotonic()
                yield (head,) + merged
                continue
            # hedges and lost replies
            waiting = [(epoch, video, len(v.flight)) for video, v in videos.items() if v.flight]
            for _, video, host in self.router.hedges(waiting, now):
                v = videos[video]
                v.host = host
                for req, (h, ords, _) in list(v.flight.items()):
                    send(video, ords, host, now)
            self._steal(plan, spans[head], videos, got, manifest.crops_per_window, send, epoch, now,
                        now - head_since >= STEAL_S)
            for video, v in list(videos.items()):
                for req, (h, ords, at) in list(v.flight.items()):
                    gone = h not in self.router.hosts
                    if gone or now - at >= retry_s:
                        del v.flight[req]
                        flight.pop((h, req), None)
                        if gone:  # left the fleet: its videos go to the next hosts of their rankings
                            v.host = None if v.host == h else v.host
                            ask(video, ords, now)
                        else:
                            send(video, ords, h, now)  # a lost reply or a restarted host: ask again
            # answers
            poller = zmq.Poller()
            for link in self.links.values():
                poller.register(link.sock, zmq.POLLIN)
            ready = dict(poller.poll(int(min(retry_s, 0.5) * 1000)))
            if not ready:
                if time.monotonic() - heard > self.timeout_s:
                    late = sorted({h for v in videos.values() for h, _, _ in v.flight.values()})
                    raise TimeoutError(f"{', '.join(late) or self.endpoint}: no rows for {self.timeout_s} s "
                                       f"(step {head})")
                continue
            heard = time.monotonic()
            for ep, link in list(self.links.items()):
                while link.sock in ready and link.sock.poll(0):
                    got_msg = link._recv(heard)
                    if got_msg is None:
                        break
                    self._receive(ep, *got_msg, flight, videos, got, plan, heard, epoch)

    def _steal(self, plan: EpochPlan, span: Tuple[int, int], videos: Dict[str, "_Video"], got: dict, kpw: int,
               send, epoch: int, now: float, late: bool) -> None:
        """Copies of the videos the step being read waits on (the first copy's rows win): of one to
        a host with nothing asked of it; once the step has waited :data:`STEAL_S` (``late``), of
        each to the next host of its ranking that does not hold it, where it goes first (its
        ``position`` is the fleet's earliest). A slow host's videos stop gating the fleet, at the
        cost of a decode where a host would otherwise idle or where the step would wait."""
        idle = [h for h, st in self.router.hosts.items() if not st.queued and not self.router.suspect(h, now)]
        if not idle and not late:
            return
        missing: Dict[str, List[int]] = {}
        for p in range(span[0], min(span[1], plan.known)):
            key = plan.key(p)
            if key is not None and (key.video, key.ordinal(kpw)) not in got:
                missing.setdefault(key.video, []).append(key.ordinal(kpw))
        weights = self.router.weights()
        for video, ords in missing.items():
            v = videos.get(video)
            if v is None or not v.flight:
                continue
            asked = {h for h, _, _ in v.flight.values()}
            h = next((x for x in idle if x not in asked), None)
            if h is None and late and len(asked) == 1:
                h = next((x for x in rank_hosts(video, list(self.router.hosts), weights)
                          if x not in asked and not self.router.suspect(x, now)), None)
            if h is None:
                continue
            send(video, tuple(sorted(ords)), h, now)
            self.router.ask(h, epoch, video, len(ords), now)
            if h in idle:
                idle.remove(h)

    def _receive(self, ep: str, msg, frames, flight, videos, got, plan: EpochPlan, now: float, epoch: int) -> None:
        """Take host ``ep``'s message: what a new host serves, a make's rows (kept by (video,
        ordinal); its video's windows unfold the plan), or a refusal (the host leaves the fleet)."""
        if isinstance(msg, PlanInfo):
            self._join(ep, msg, now)
            return
        if isinstance(msg, Refused):
            what = flight.pop((ep, msg.request), None)
            if what is not None:  # another plan now (restarted on other files), or a make it cannot take
                log.warning("%s: left out of the fleet: %s", ep, msg.message)
                self.refused.add(ep)
                self.router.leave(ep)  # its videos' makes go to their next hosts (fetch_all's retries)
            return
        if not isinstance(msg, Rows):
            return
        what = flight.pop((ep, msg.request), None)
        if what is None or what[0] != "make" or msg.epoch != epoch:
            return  # an answer to a request asked again, or of another pass
        _, video, ordinals = what
        v = videos[video]
        v.flight.pop(msg.request, None)
        if msg.windows is not None and video not in self.windows:
            self.windows[video] = msg.windows
            plan.learn(self.windows)
        try:
            arrays = _with_padding(decode_batch_arrays(msg.arrays, frames, MAX_BATCH_BYTES), msg.padding)
        except ProtocolError as e:
            raise PlanServerError(f"{ep}: rows of {video}: {e}") from None
        for j, o in enumerate(ordinals or ()):
            if (video, o) in got:
                continue  # another copy came first
            row = {name: a[j] for name, a in arrays.items()}
            got[(video, o)] = (msg.sample_ids[j], msg.padding[j], msg.params[j], row, ep)
            if not msg.padding[j] and self.like is None:
                self.like = row
        for req, (h, ords, _) in list(v.flight.items()):  # copies of what is now read
            if all((video, o) in got for o in ords or ()) and (ords or msg.windows is not None):
                del v.flight[req]
                flight.pop((h, req), None)
        done = not any(h == ep for h, _, _ in v.flight.values())
        self.router.answered(ep, epoch, video, len(ordinals or ()), now, done)
        if not v.flight:
            self.router.finished(epoch, video, now)

    def _step(self, plan: EpochPlan, span: Tuple[int, int], got: dict, epoch: int, kpw: int):
        """``(rows, arrays)`` of positions ``span`` once each is known (made, failed or past the
        epoch's end), their samples taken out of ``got``; None while one is not."""
        start, stop = span
        if stop > plan.known and not plan.complete:
            return None
        keys = [plan.key(p) for p in range(start, stop)]
        rows = []
        for key in keys:
            if key is None:
                rows.append((None, True, {"padding": "past the epoch's end"}, None, None))
            elif (key.video, key.ordinal(kpw)) in got:
                rows.append(got[(key.video, key.ordinal(kpw))])
            else:
                return None
        for key in keys:
            if key is not None:
                got.pop((key.video, key.ordinal(kpw)))
        like = next((r[3] for r in rows if not r[1]), self.like)
        if like is None:
            raise PlanServerError(f"{self.endpoint}: epoch {epoch} positions {start}..{stop - 1}: no row holds a sample "
                                  "and none was read before (the arrays' shapes are not known)")
        arrays = {name: np.stack([r[3][name] if not r[1] else np.zeros_like(like[name]) for r in rows])
                  for name in like}
        out = Rows(0, epoch, start, [r[0] for r in rows], [r[1] for r in rows], [r[2] for r in rows], [],
                   len(plan) if plan.complete else None)
        served: Dict[str, int] = {}
        for r in rows:
            if not r[1]:
                served[r[4]] = served.get(r[4], 0) + 1
        self._served = (out, served)
        return out, arrays

    def served(self, rows: Rows) -> Dict[str, int]:
        """{host endpoint: rows of ``rows`` (the step last yielded) holding a sample it made}."""
        last, served = self._served
        return dict(served) if rows is last else {}

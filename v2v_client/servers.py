"""Which servers a dataset reads as one plan, asked once and pickled with the dataset: one
server; one per shard, in shard order (``fetch.Shards``); or a fleet of hosts each serving the
whole corpus (``fleet_read.Fleet``). Free of torch."""
from __future__ import annotations

import logging
import time
from dataclasses import replace
from typing import Dict, List, Optional, Tuple

from v2v_wire.codecs import available, check_compression
from v2v_wire.plan import PlanIdentity
from v2v_wire.plan_messages import MAX_FETCH_ROWS, PlanInfo
from v2v_wire.plan_shards import shards_identity, shards_samples
from v2v_wire.protocol import MAX_BATCH_BYTES

from .endpoints import auto_compression, check_servers, resolve_endpoints, split_endpoints
from .fetch import Link, PlanServerError, Shards, reply_limit
from .fleet_pass import ReaderMemory
from .fleet_read import ASK_NEXT_S, Fleet, alias_of, asked_fleet, listing_diff, manifest_diff, read_manifest

__all__ = ["Servers", "FLEET_ASK_S"]

log = logging.getLogger("v2v.client")

#: Seconds a fleet's other hosts may take to say what they serve once its first host has: a host
#: silent at start is left out, and joins when it answers (``fleet_read.Fleet``).
FLEET_ASK_S = 10.0


class Servers:
    """The servers a dataset reads as one plan: one; one per shard, in shard order; or a fleet of
    hosts each serving the whole corpus (``fleet_read.Fleet``); each with its plan identity and
    the compression its fetches ask for (known once asked; pickled with the dataset, so a
    DataLoader worker asks nothing again)."""

    def __init__(self, endpoint, compression: str):
        split_endpoints(endpoint)  # a bad entry: ValueError, naming it
        if compression != "auto" and not available(check_compression(compression)):
            raise ValueError(f"compression {compression!r}: its library is not installed here (pip install 'v2v[wire]')")
        self.endpoint, self.compression = endpoint, compression
        self.shards: Optional[List[Tuple[str, PlanIdentity]]] = None  # (server, its plan), in shard order
        self.codecs: Dict[str, str] = {}  # server -> compression
        self.samples: List[Optional[int]] = []  # each shard's samples per epoch when asked (None: not known)
        self.fleet: Optional[List[Tuple[str, PlanInfo]]] = None  # a fleet's hosts, each with what it said last
        self.plan: Optional[PlanIdentity] = None  # a fleet's plan
        self.memory = ReaderMemory()  # what this process's passes over a fleet learned and keep
        self.max_msg = MAX_BATCH_BYTES  # the largest frame a shard's reply carries (fetch.reply_limit)

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        # the windows and manifests are learned again in each process: a corpus's worth is no pickle to send
        state["memory"] = replace(self.memory, windows={}, known={})
        return state

    def ask(self, timeout_s: float, curve: Optional[tuple], prefer: Optional[PlanIdentity] = None) -> PlanInfo:
        """What the servers serve, as one plan (resolving ``endpoint`` the first time). Several
        hosts that each serve the whole corpus are a fleet: its plan is ``prefer`` (a loaded
        position's) where a host serves it, else the first host's; a host serving another plan is
        named in one log line and left out, as is one silent for ``FLEET_ASK_S`` once another answered.
        Asked again of a fleet (at each pass), its plan holds while a host serves it; once every host
        that answers serves another (each restarted with a file replaced), the fleet is asked again
        as at first and its plan is theirs, said in one line naming the files that changed.

        Raises:
            TimeoutError, PlanServerError: a server silent, or speaking another protocol version.
            ValueError: several servers that are not one sharding of one corpus, nor a fleet."""
        if self.fleet is not None:
            return self._ask_fleet_again(timeout_s, curve, prefer)
        servers = resolve_endpoints(self.endpoint) if self.shards is None else [ep for ep, _ in self.shards]
        if len(servers) == 1:
            with Link(servers[0], timeout_s, curve) as link:
                infos = [link.ask()]
        else:  # asked at once: a silent or stopped first host costs no wait of its own
            answered = asked_fleet(servers, timeout_s, min(timeout_s, FLEET_ASK_S), curve, self.memory.left_out)
            if not isinstance(next(iter(answered.values())).stream.get("shard"), str):
                return self._ask_fleet(servers, answered, timeout_s, curve, prefer)
            infos = []
            for server in servers:  # shards: every one is needed
                if server not in answered:
                    with Link(server, timeout_s, curve) as link:
                        answered[server] = link.ask()
                infos.append(answered[server])
        info, self.shards, self.samples = _as_one_plan(servers, infos)
        self.max_msg = reply_limit(info.stream, MAX_FETCH_ROWS)  # a fetch's reply holds at most MAX_FETCH_ROWS rows
        self.codecs = {ep: _codec_for(self.compression, ep, i.stream) for ep, i in zip(servers, infos)}
        return info

    def _ask_fleet_again(self, timeout_s: float, curve: Optional[tuple], prefer: Optional[PlanIdentity]) -> PlanInfo:
        """What the fleet serves, asked again (at each pass; the plan's samples, while it
        unfolds) of its hosts at once (``fleet_read.asked_fleet``: the first answer awaited
        ``timeout_s``, the others ``ASK_NEXT_S`` more). The hosts that serve the plan are read
        first for the pass's manifest; each host keeps what it said now, so one serving another
        plan is left out of the pass and named (``fleet_read.Fleet.other_plan``); a peer left out
        (``left_out``) is not asked. When no host that answered serves the plan, the fleet of what
        they serve (:meth:`_replanned`).

        Raises:
            TimeoutError: no host answered within ``timeout_s``.
            PlanServerError: every host left out (one line naming each and why), or as :meth:`ask`
                asked first.
            ValueError: as :meth:`ask` asked first."""
        answered = asked_fleet([ep for ep, _ in self.fleet], timeout_s, min(timeout_s, ASK_NEXT_S), curve,
                               self.memory.left_out)
        serving = [ep for ep, i in answered.items() if i.plan == self.plan]
        if not serving:
            return self._replanned(self.plan, timeout_s, curve, prefer)
        self.fleet = sorted(((ep, answered.get(ep, i)) for ep, i in self.fleet if ep not in self.memory.left_out),
                            key=lambda h: h[0] not in serving)
        return answered[serving[0]]

    def _replanned(self, old: PlanIdentity, timeout_s: float, curve: Optional[tuple],
                   prefer: Optional[PlanIdentity]) -> PlanInfo:
        """The fleet asked again as at first, no host serving plan ``old`` any more: its plan is
        the one the hosts serve now (a loaded position's plan, ``prefer``, is checked against it
        by the caller), said in one log line naming the files whose tags changed since ``old``'s
        manifest where this process read it. Every peer is asked again, one left out before
        included: what it was left out for was judged against ``old``."""
        self.fleet = self.shards = None
        self.memory.left_out.clear()  # in place: the fleets of this process share it
        info = self.ask(timeout_s, curve, prefer)
        files = ""
        before = self.memory.known.get(old.manifest)
        if before is not None and self.fleet:  # (the endpoint may name one server or shards now)
            ep = self.fleet[0][0]
            try:
                with Link(ep, min(ASK_NEXT_S, timeout_s), curve) as link:
                    files = manifest_diff(before, "before", read_manifest(link, min(ASK_NEXT_S, timeout_s)), "now")
            except (TimeoutError, PlanServerError) as e:
                files = f"{ep}'s listing could not be read ({e})"
        log.warning("%s: no host serves the plan read last (manifest %s) any more: the fleet's plan is the one its "
                    "hosts serve now (manifest %s)%s", self.endpoint, old.manifest, info.plan.manifest,
                    f"; {files}" if files else "")
        return info

    def _ask_fleet(self, servers: List[str], infos: Dict[str, PlanInfo], timeout_s: float, curve: Optional[tuple],
                   prefer: Optional[PlanIdentity]) -> PlanInfo:
        """The fleet of the hosts that answered (``infos``, in ``servers``' order), each host once
        (``fleet_read.alias_of``); the others are named and left out (they join when they answer,
        ``fleet_read.Fleet``)."""
        names: Dict[str, str] = {}
        for ep, i in infos.items():
            kept = alias_of(ep, i, names)
            if kept is not None:
                self.memory.same[ep] = kept
        infos = {ep: i for ep, i in infos.items() if ep not in self.memory.same}
        for ep in servers:
            if ep not in infos and ep not in self.memory.same and ep not in self.memory.left_out:  # one left out was named then
                log.warning("%s: left out of the fleet for now: no answer to 'what do you serve' within %s s", ep,
                            min(timeout_s, FLEET_ASK_S))
        whole, first = next(iter(infos)), next(iter(infos.values()))
        sharded = [ep for ep, i in infos.items() if isinstance(i.stream.get("shard"), str)]
        if sharded:
            raise ValueError(f"{', '.join(sharded)}: serve(s) one shard while {whole} serves the whole corpus: "
                             "read shards (v2v-serve --shard I/N) or hosts of the whole corpus, not both")
        plans = [i.plan for i in infos.values()]
        plan = prefer if prefer is not None and prefer in plans else first.plan
        hosts = [(ep, i) for ep, i in infos.items() if i.plan == plan]
        _name_left_out(infos, plan, timeout_s, curve, self.memory.left_out)
        self.fleet, self.shards, self.plan = hosts, [(ep, i.plan) for ep, i in hosts], plan
        self.codecs = {ep: _codec_for(self.compression, ep, i.stream) for ep, i in hosts}
        info = hosts[0][1]
        known = [i.samples for _, i in hosts if i.samples is not None]
        return PlanInfo(info.plan, known[0] if known else None, info.stream)

    def link(self, timeout_s: float, curve: Optional[tuple]):
        """The fetch loop over the servers: ``Shards`` (one server is one shard), or a fleet's
        (``fleet_read.Fleet``)."""
        if self.fleet is not None:
            return Fleet(self.endpoint, self.fleet, self.plan, timeout_s, curve, self.compression, self.memory)
        return Shards(self.shards, timeout_s, curve, self.codecs, self.samples, self.max_msg)

    def feed(self, timeout_s: float, curve: Optional[tuple]) -> Optional[dict]:
        """The servers' ``feed`` figures asked now (``plan_server.stream_info``), summed over the
        shards or the fleet's hosts: ``workers``, ``samples_made``, ``samples_made_by_epoch``
        (epoch -> samples made of it, the servers' latest epochs: over the samples read of an
        epoch, 1.0 when each was made once), ``busy_s`` (stage -> worker seconds) and the smallest
        ``frame_cache_gb``; None when a server does not report them.

        Raises:
            TimeoutError: the servers did not all answer within ``timeout_s`` (for all of them
                together: one silent server cannot make the question wait once per server)."""
        deadline = time.monotonic() + timeout_s
        figures = []
        asked = [ep for ep, _ in self.shards or () if ep not in self.memory.left_out]  # a peer left out answers nothing
        for server in asked or resolve_endpoints(self.endpoint):
            with Link(server, max(0.0, round(deadline - time.monotonic(), 2)), curve) as link:
                figures.append(link.ask().stream.get("feed"))
        if not figures or not all(isinstance(f, dict) for f in figures):
            return None
        busy: Dict[str, float] = {}
        by_epoch: Dict[int, int] = {}
        for f in figures:
            for stage, v in (f.get("busy_s") or {}).items():
                busy[stage] = busy.get(stage, 0.0) + float(v)
            for e, n in (f.get("samples_made_by_epoch") or {}).items():
                by_epoch[int(e)] = by_epoch.get(int(e), 0) + int(n)
        return {"workers": sum(int(f.get("workers") or 0) for f in figures),
                "samples_made": sum(int(f.get("samples_made") or 0) for f in figures),
                "samples_made_by_epoch": by_epoch,
                "frame_cache_gb": min(float(f.get("frame_cache_gb") or 0.0) for f in figures), "busy_s": busy}


def _as_one_plan(servers: List[str], infos: List[PlanInfo]):
    """``(PlanInfo, [(server, its plan identity)], [its samples per epoch or None])`` of the servers
    read as one plan: one server's own; several, each one shard of one corpus under one recipe,
    interleaved in shard order.

    Raises:
        ValueError: several servers that are not one sharding of one corpus (naming them)."""
    if len(servers) == 1:
        return infos[0], [(servers[0], infos[0].plan)], [infos[0].samples]
    whole = [ep for ep, i in zip(servers, infos) if not isinstance(i.stream.get("shard"), str)]
    if whole:
        raise ValueError(f"{', '.join(whole)}: serve(s) the whole corpus while {servers[0]} serves one shard: read "
                         "shards (v2v-serve --shard I/N) or hosts of the whole corpus, not both")
    check_servers({ep: i.stream for ep, i in zip(servers, infos)})
    ordered = sorted(zip(servers, infos), key=lambda x: int(x[1].stream["shard"].split("/")[0]))
    plan = shards_identity([i.plan for _, i in ordered])
    return (PlanInfo(plan, shards_samples([i.samples for _, i in ordered]), ordered[0][1].stream),
            [(ep, i.plan) for ep, i in ordered], [i.samples for _, i in ordered])


def _codec_for(compression: str, endpoint: str, stream: dict) -> str:
    """What fetches of ``endpoint`` ask for: ``compression``, or for ``"auto"``
    ``endpoints.auto_compression`` with the codecs the server lists in its stream info."""
    return compression if compression != "auto" else auto_compression(endpoint, stream.get("codecs", ()))


def _name_left_out(infos: Dict[str, PlanInfo], plan: PlanIdentity, timeout_s: float, curve: Optional[tuple],
                   left_out: Dict[str, str]) -> None:
    """Name in one log line each host of ``infos`` serving another plan than ``plan``: what
    differs, and for another listing of the same recipe and seed the first files that differ;
    noted in ``left_out`` (endpoint -> why), so that no pass names it again."""
    for ep, i in infos.items():
        problem = plan.problem(i.plan)
        if not problem:
            continue
        if i.plan.manifest != plan.manifest and (i.plan.recipe, i.plan.seed) == (plan.recipe, plan.seed):
            ours = next(e for e, j in infos.items() if j.plan == plan)
            try:
                problem += "; " + listing_diff(ours, plan, ep, i.plan, timeout_s, curve)
            except (TimeoutError, PlanServerError) as e:
                problem += f"; its listing could not be read ({e})"
        log.warning("%s: left out of the fleet: it serves %s", ep, problem)
        left_out[ep] = f"it serves {problem}"

"""Fan-in: one trainer reading batches from several ``v2v-serve`` hosts (shards).

Hosts split the corpus statically (``v2v-serve --shard I/N``), so each server keeps its own
exactly-once guarantee; a trainer reads all of them through one iterator. This module is a
composition: it opens one single-server stream (:class:`~v2v_client.endpoint.EndpointStream`) per server and
merges their batches in arrival order. It uses only their public surface (``iter``,
``state_dict``, ``load_state_dict``, ``close``, ``info``), so whatever one connection does
(credits, leases, acknowledgements, reconnects, DDP ranks) it does here too, per server:

* each server is read by its own connection with its own credits (``credits`` is split
  evenly, at least 1 each) and reconnects on its own (``reconnect=True``);
* the merged stream ends when every server has ended its stream; an epoch counts as
  completed when every server has completed it (``state_dict()["completed_epoch"]`` is the
  minimum over servers);
* ``state_dict()`` covers all servers in the single-endpoint format (version 1): the
  completed epoch and the ids handed to the training loop in every epoch still open on some
  server. Sample ids name their video and shards hold disjoint videos, so each server takes
  what concerns it and ignores the rest: the same state resumes one server, several, or a
  different split of the same corpus.

Each per-server iterator runs in a small pump thread. To know that a server has a batch the
pump must take it from its iterator, which acknowledges it, so up to one batch per server can
be acknowledged before the training loop takes it; ``state_dict()`` counts only the batches
handed over, and every server knows the fan-in as one consumer (its id is in ``state_dict()``),
so the next iteration's resume state gets those batches sent again.

Before handing on any batch the fan-in checks that its servers are one sharding of one corpus
under one recipe (:func:`check_servers`, from each server's welcome).
"""
from __future__ import annotations

import ipaddress
import queue
import socket
import threading
import uuid
from typing import Callable, Dict, Iterator, List, Optional, Sequence, Union

from .resume import ResumeState

Endpoints = Union[str, Sequence[str]]

_DONE = object()


def split_endpoints(spec: Endpoints) -> List[str]:
    """Endpoints from a list or a comma-separated string, stripped, duplicates removed.

    Raises:
        ValueError: for an empty spec or an entry that is not a ZeroMQ endpoint
            (``tcp://host:port``, ``ipc://path``, ...), naming the entry.
    """
    items = spec.split(",") if isinstance(spec, str) else list(spec)
    out: List[str] = []
    for e in items:
        if not isinstance(e, str):
            raise ValueError(f"endpoint must be a string like tcp://host:5555, got {e!r}")
        e = e.strip()
        if not e:
            continue
        if "://" not in e:
            raise ValueError(f"endpoint {e!r} is not a ZeroMQ endpoint like tcp://host:5555")
        if e not in out:
            out.append(e)
    if not out:
        raise ValueError(f"no endpoint given in {spec!r}")
    return out


def _is_ip(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
        return True
    except ValueError:
        return False


def expand_dns(endpoint: str, getaddrinfo: Callable = socket.getaddrinfo) -> List[str]:
    """A ``tcp://NAME:PORT`` endpoint whose name resolves to several addresses (e.g. a
    Kubernetes headless Service in front of a StatefulSet) -> one endpoint per address.

    IPv4 addresses are used when there are any, else IPv6 (so ``localhost`` resolving to
    127.0.0.1 and ::1 stays one server). Anything else -- an IP literal, a name with a single
    address, a name that does not resolve (yet), ``ipc://`` -- is returned unchanged, so ZeroMQ
    resolves the name again on every reconnect.
    """
    scheme, _, rest = endpoint.partition("://")
    if scheme != "tcp" or ":" not in rest:
        return [endpoint]
    host, _, port = rest.rpartition(":")
    host = host.strip("[]")
    if not port.isdigit() or _is_ip(host) or host == "*" or ";" in host:
        return [endpoint]
    try:
        infos = getaddrinfo(host, int(port), 0, socket.SOCK_STREAM)
    except (OSError, UnicodeError):
        return [endpoint]
    v4 = sorted({i[4][0] for i in infos if i[0] == socket.AF_INET}, key=ipaddress.ip_address)
    v6 = sorted({i[4][0] for i in infos if i[0] == socket.AF_INET6}, key=ipaddress.ip_address)
    addrs = v4 or v6
    if len(addrs) <= 1:
        return [endpoint]
    return [f"tcp://{a}:{port}" if ":" not in a else f"tcp://[{a}]:{port}" for a in addrs]


def resolve_endpoints(spec: Endpoints, getaddrinfo: Callable = socket.getaddrinfo) -> List[str]:
    """``split_endpoints`` then ``expand_dns`` on each; order kept, duplicates removed."""
    out: List[str] = []
    for e in split_endpoints(spec):
        for x in expand_dns(e, getaddrinfo):
            if x not in out:
                out.append(x)
    return out


def check_servers(infos: Dict[str, dict]) -> None:
    """Check that the servers of a fan-in (endpoint -> welcome info) are one sharding of one
    corpus under one sample recipe: the same shard count N, each shard 0..N-1 once, the same
    corpus listing, the same recipe. Servers that do not say (older ones) are not checked.

    Raises:
        ValueError: naming the servers and what differs (shards missing or served twice
            lose or repeat samples in silence).
    """
    says = {ep: i for ep, i in infos.items() if isinstance(i.get("shard"), str)}
    if len(says) < 2:
        return
    shards = {ep: tuple(int(x) for x in i["shard"].split("/")) for ep, i in says.items()}
    listed = ", ".join(f"{ep} serves shard {i}/{n}" for ep, (i, n) in shards.items())
    counts = {n for _, n in shards.values()}
    problems = []
    if len(counts) > 1:
        problems.append(f"they split the corpus into different numbers of shards ({sorted(counts)})")
    else:
        n = counts.pop()
        seen: Dict[int, List[str]] = {}
        for ep, (i, _) in shards.items():
            seen.setdefault(i, []).append(ep)
        twice = {i: eps for i, eps in seen.items() if len(eps) > 1}
        missing = sorted(set(range(n)) - set(seen))
        if twice:
            problems.append("shard(s) served twice: " + "; ".join(f"{i}/{n} by {', '.join(e)}" for i, e in twice.items()))
        if missing:
            problems.append(f"shard(s) {', '.join(f'{i}/{n}' for i in missing)} served by none of them")
    for key, what in (("corpus", "corpus listings (their --videos folders hold different files)"),
                      ("recipe", "sample recipes (seed, sequence length, bins, crop...)")):
        values = {i.get(key) for i in says.values()}
        if len(values) > 1:
            problems.append(f"different {what}: " + ", ".join(f"{ep}: {i.get(key)}" for ep, i in says.items()))
    if problems:
        raise ValueError(f"the servers of this fan-in are not one sharding of one corpus ({listed}): "
                         + "; ".join(problems))


class FanInStream:
    """Merge the batches of several servers into one stream (see the module docstring).

    Args:
        endpoints: the servers, one ZeroMQ endpoint each (already resolved).
        make_child: ``make_child(endpoint, credits) -> endpoint.EndpointStream`` for one server.
        credits: total batches in flight over all servers; each gets
            ``max(1, ceil(credits / len(endpoints)))``.

    Iterating yields the children's batch dicts unchanged plus ``"endpoint"`` (str, the
    server it came from). Errors of any server (``StreamTimeout``, ``StreamError``) are
    raised from iteration; the other connections are closed.

    Raises:
        ValueError: for an empty endpoint list.
    """

    def __init__(self, endpoints: Sequence[str], make_child: Callable[[str, int], object], credits: int):
        self.endpoints = list(endpoints)
        if not self.endpoints:
            raise ValueError("fan-in needs at least one endpoint")
        self._make_child = make_child
        self.credits_each = max(1, -(-int(credits) // len(self.endpoints)))
        self._lock = threading.Lock()
        self._children: List = []
        self.counts: Dict[str, Dict[str, int]] = {e: {"batches": 0, "samples": 0} for e in self.endpoints}
        self.info: Optional[dict] = None
        # what the fan-in handed to the training loop (per shard "I/N" its batch counts, for DDP);
        # one consumer to every server, kept in state_dict(): a resumed fan-in is the same consumer,
        # so each server takes its resume state for the one it knows
        self.record = ResumeState(uuid.uuid4().hex)

    # ------------------------------------------------------------------ state
    def completed_epoch(self) -> int:
        """The last epoch every server has completed (-1 before any)."""
        with self._lock:
            children = list(self._children)
        base = self.record.completed_epoch
        if not children:
            return base
        return min(max(base, int(c.state_dict().get("completed_epoch", -1))) for c in children)

    def state_dict(self) -> dict:
        """Single-endpoint format (``ResumeState.state``) covering every server: the epoch all
        servers completed and the sample ids handed to the training loop in later epochs."""
        self.record.complete(self.completed_epoch())
        return self.record.state()

    def load_state_dict(self, state: dict) -> None:
        """Take a state from ``state_dict()`` (of a fan-in or of one endpoint); used by the
        next iteration for every server.

        Raises:
            ValueError: for a state of another format.
        """
        record = ResumeState(self.record.consumer)
        record.load(state)
        with self._lock:
            self.record, self._children = record, []

    # ------------------------------------------------------------------ iteration
    def __iter__(self) -> Iterator[dict]:
        state = self.state_dict()
        children = [self._make_child(ep, self.credits_each) for ep in self.endpoints]
        for ep, c in zip(self.endpoints, children):  # the fan-in's consumer id and recipe; the batches of its shard
            per = state.get("shard_batches", {}).get(state.get("shard_of", {}).get(ep, ep), {})
            c.load_state_dict(dict(state, batches=per))
        with self._lock:
            self._children = children
        items: "queue.Queue" = queue.Queue()
        go = [threading.Event() for _ in children]
        stop = threading.Event()
        pumps = [threading.Thread(target=_pump, args=(i, c, items, go[i], stop), daemon=True,
                                  name=f"v2v-fanin-{i}") for i, c in enumerate(children)]
        for t in pumps:
            t.start()
        running = len(children)
        held: list = []  # batches that arrived before every server said which shard it serves
        checked = False
        try:
            while running or held:
                if not checked and (all(c.info is not None for c in children) or not running):
                    check_servers({ep: c.info for ep, c in zip(self.endpoints, children) if c.info is not None})
                    checked = True
                    for i, item in held:
                        yield self._hand_on(i, item, children)
                    held = []
                if not running:
                    break
                try:
                    i, item = items.get(timeout=1.0)
                except queue.Empty:
                    if not any(t.is_alive() for t in pumps) and items.empty():
                        return
                    continue
                if item is _DONE:
                    running -= 1
                    continue
                if isinstance(item, BaseException):
                    raise item
                go[i].set()  # this server's pump may take its next batch
                if not checked:
                    held.append((i, item))
                    continue
                yield self._hand_on(i, item, children)
        finally:
            stop.set()
            for g in go:
                g.set()
            for c in children:
                c.close()
            for t in pumps:
                t.join(5.0)

    def _hand_on(self, i: int, item: dict, children) -> dict:
        """Record a batch of server ``i`` as handed to the training loop."""
        ep = self.endpoints[i]
        item["endpoint"] = ep
        info = children[i].info or {}
        shard = str(info.get("shard", ep))
        r = self.record
        with r.lock:
            r.shard_of[ep] = shard
            if isinstance(info.get("recipe"), str):
                r.recipe = info["recipe"]
        r.handed_on(int(item["epoch"]), item["sample_ids"], shard=shard)
        with self._lock:
            self.counts[ep]["batches"] += 1
            self.counts[ep]["samples"] += len(item["sample_ids"])
        if self.info is None:
            self.info = info
        return item

    def held(self) -> int:
        """Batches received from every server and neither taken nor given back yet."""
        with self._lock:
            children = list(self._children)
        return sum(c.held() for c in children)

    def close(self) -> None:
        """Close every server's open connections."""
        for c in list(self._children):
            c.close()


def _pump(i: int, child, items: "queue.Queue", go: threading.Event, stop: threading.Event) -> None:
    """Move one server's batches into the shared queue, one at a time (waits for ``go``)."""
    it = iter(child)
    try:
        for b in it:
            items.put((i, b))
            go.wait()
            go.clear()
            if stop.is_set():
                return
        items.put((i, _DONE))
    except BaseException as e:  # handed to the consumer, who raises it
        items.put((i, e))
    finally:
        it.close()

"""Where a reader's servers are and how it talks to them: endpoints (one server or several shards,
a DNS name standing for several), the check that several servers are one sharding of one corpus
under one recipe, the codec ``compression="auto"`` asks for, and CurveZMQ key files.
"""
from __future__ import annotations

import ipaddress
import socket
from typing import Callable, Dict, List, Sequence, Union

from v2v_wire.codecs import COMPRESSIONS, available
from v2v_wire.protocol import is_loopback

__all__ = ["split_endpoints", "expand_dns", "resolve_endpoints", "check_servers", "auto_compression", "AUTO_REMOTE",
           "load_curve_keys"]

Endpoints = Union[str, Sequence[str]]


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
    """Check that the servers read as one plan (endpoint -> stream info) are one sharding of one
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
        raise ValueError(f"the servers read as one plan are not one sharding of one corpus ({listed}): "
                         + "; ".join(problems))


#: Compression ``compression="auto"`` asks servers on other hosts for (docs/wire.md measures it:
#: 6.3x fewer bytes per default sample, decompressed at about 1.2 GB/s per core).
AUTO_REMOTE = "zstd"


def auto_compression(endpoint: str, server_codecs=COMPRESSIONS) -> str:
    """What ``compression="auto"`` asks of ``endpoint``: none for ``ipc://``, ``inproc://`` and
    loopback ``tcp://`` (bytes cost less than compressing them), ``AUTO_REMOTE`` across hosts when
    its library is installed here and the server has it (``server_codecs``), else none."""
    remote = not is_loopback(endpoint) and available(AUTO_REMOTE) and AUTO_REMOTE in server_codecs
    return AUTO_REMOTE if remote else "none"


def load_curve_keys(client_secret_file: str, server_public_file: str) -> tuple:
    """(client public, client secret, server public) Z85 keys from ``v2v-keygen`` files.

    Raises:
        ValueError: naming the file, when it is missing or holds no key of the right kind.
    """
    import zmq.auth

    try:
        pub, sec = zmq.auth.load_certificate(client_secret_file)
    except (OSError, ValueError) as e:
        raise ValueError(f"client key {client_secret_file}: {e}") from None
    if not sec:
        raise ValueError(f"client key {client_secret_file}: holds no secret key (use the .key_secret file)")
    try:
        server_pub, _ = zmq.auth.load_certificate(server_public_file)
    except (OSError, ValueError) as e:
        raise ValueError(f"server key {server_public_file}: {e}") from None
    return pub, sec, server_pub

"""deploy/ cannot rot silently: every image, compose file and Kubernetes manifest is parsed, and
every v2v-serve / v2v-train flag, port and path it uses is checked against the programs'
own argument parsers, config loaders and the images' files. Where the Kubernetes schemas
(kubernetes-validate) or kubectl are installed, the manifests are validated with them too."""
from __future__ import annotations

import json
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path, PurePosixPath

import pytest
import yaml

from trainer.config import apply_overrides, load_config as load_trainer_config
from trainer.train import build_arg_parser as train_parser
from v2v_server.cli import build_parser as serve_parser, config_from_args
from v2v_server.service.shm import shm_bytes

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"
K8S = DEPLOY / "k8s"
PARSERS = {"v2v-serve": serve_parser, "v2v-train": train_parser}
#: flags whose value is a path inside the container
PATH_FLAGS = {"--config", "--videos", "--curve-secret-key", "--curve-allow", "--out"}


# ---------------------------------------------------------------------------------- parsing helpers
def dockerfile(name: str) -> dict:
    """{"from", "copies": [(src, dst)], "expose": [int], "user", "entrypoint", "cmd", "healthcheck", "workdir", "run"}"""
    text = (DEPLOY / name).read_text()
    text = re.sub(r"\\\n", " ", "\n".join(ln for ln in text.splitlines() if not ln.lstrip().startswith("#")))
    out = {"copies": [], "expose": [], "run": []}
    for line in text.splitlines():
        if not line.strip():
            continue
        op, _, rest = line.strip().partition(" ")
        op, rest = op.upper(), rest.strip()
        if op == "FROM":
            out["from"] = rest
        elif op == "COPY":
            *src, dst = rest.split()
            out["copies"] += [(s, dst) for s in src]
        elif op == "EXPOSE":
            out["expose"] += [int(p) for p in rest.split()]
        elif op in ("ENTRYPOINT", "CMD"):
            out[op.lower()] = json.loads(rest)  # exec form only: no shell in between
        elif op == "HEALTHCHECK":
            out["healthcheck"] = json.loads(rest.split(" CMD ", 1)[1])
        elif op in ("USER", "WORKDIR"):
            out[op.lower()] = rest
        elif op == "RUN":
            out["run"].append(rest)
    return out


def image_file(image: dict, path: str) -> Path:
    """The repository file an image holds at ``path`` (through its COPY lines), or fail."""
    p = PurePosixPath(path)
    wd = PurePosixPath(image.get("workdir", "/"))
    for src, dst in image["copies"]:
        d = PurePosixPath(dst) if dst.startswith("/") else wd / dst
        d = d / src if dst.endswith("/") and dst != "./" and not src.endswith("/") else d
        if dst in ("./", "."):
            d = wd / src
        try:
            rel = p.relative_to(d)
        except ValueError:
            continue
        f = ROOT / src / rel
        if f.exists():
            return f
    raise AssertionError(f"{path}: not in the image (no COPY brings it)")


def size_bytes(text) -> int:
    """``512m`` (Docker) or ``1Gi`` / ``500M`` (Kubernetes) in bytes."""
    m = re.fullmatch(r"(\d+)\s*([kmgKMG]i?)?[bB]?", str(text).strip())
    assert m, text
    unit = (m.group(2) or "").lower()
    mult = {"": 1, "k": 1024, "m": 1024 ** 2, "g": 1024 ** 3, "ki": 1024, "mi": 1024 ** 2, "gi": 1024 ** 3}[unit]
    if text[-1] in "KMG" and not str(text).endswith("i"):  # Kubernetes decimal units
        mult = {"K": 10 ** 3, "M": 10 ** 6, "G": 10 ** 9}[text[-1]]
    return int(m.group(1)) * mult


def program(argv):
    """("v2v-serve" | "v2v-train", args) for a container's argv; None for anything else."""
    if argv and argv[0] == "torchrun":
        i = argv.index("-m")
        assert argv[i + 1] == "trainer.train", argv
        return "v2v-train", argv[i + 2:]
    if argv and argv[0] in PARSERS:
        return argv[0], argv[1:]
    return None


def flag_values(args, flag):
    return [args[i + 1] for i, a in enumerate(args[:-1]) if a == flag]


def check_flags(prog, args, subst=None):
    """Every flag exists in the program's parser and the whole line parses; returns the
    parsed namespace (``$(VAR)`` replaced through ``subst``)."""
    parser = PARSERS[prog]()
    known = {s for a in parser._actions for s in a.option_strings}
    for a in args:
        if a.startswith("--"):
            assert a.split("=", 1)[0] in known, f"{prog} has no flag {a} (see {prog} --help)"
    subst = subst or {}
    args = [re.sub(r"\$\((\w+)\)", lambda m: subst[m.group(1)], a) for a in args]
    return parser.parse_args(args)


def check_serve_config(ns, config_file=None):
    """The v2v-serve line would start: config validated (curve key files are checked by
    path elsewhere, the corpus is not there)."""
    ns.config = str(config_file) if config_file else None
    ns.curve_secret_key = ns.curve_allow = None
    ns.insecure = True
    return config_from_args(ns)


def port_of(endpoint):
    return int(endpoint.rsplit(":", 1)[1])


def k8s_docs(folder: Path = K8S) -> dict:
    """{(kind, name): object} of the manifests a kustomization folder lists as resources of its
    own (files, not other folders), as written there."""
    kz = yaml.safe_load((folder / "kustomization.yaml").read_text())
    docs = {}
    for r in kz.get("resources", []):
        if (folder / r).is_file():
            for d in yaml.safe_load_all((folder / r).read_text()):
                if d:
                    docs[(d["kind"], d["metadata"]["name"])] = d
    return docs


def under(path, mounts):
    """The mount (dict) that holds ``path``, the longest match."""
    best = None
    for m in mounts:
        mp = m["mountPath"].rstrip("/")
        if path == mp or path.startswith(mp + "/"):
            if best is None or len(mp) > len(best["mountPath"]):
                best = m
    assert best is not None, f"{path}: no volume mounted there"
    return best


# ---------------------------------------------------------------------------------- images
def test_server_image_is_slim_without_torch_nonroot_with_probe_on_its_metrics_port():
    img = dockerfile("Dockerfile.server")
    assert re.fullmatch(r"python:3\.1\d-slim", img["from"]), img["from"]
    assert any('pip install ".[server,s3]"' in r for r in img["run"])  # s3: a corpus in a bucket
    pyproject = (ROOT / "pyproject.toml").read_text()
    base = re.search(r"^dependencies = \[(.*?)^\]", pyproject, re.S | re.M).group(1)
    server_extra = re.search(r"^server = \[(.*?)^\]", pyproject, re.S | re.M).group(1)
    assert "torch" not in base and "torch" not in server_extra  # a decode host installs no torch
    assert all(p in server_extra and p not in base for p in ("numba", "av>=", "opencv"))  # nor does a client
    assert img["user"] not in ("root", "0") and img["entrypoint"] == ["v2v-serve"]
    ns = check_flags("v2v-serve", img["cmd"])
    cfg = check_serve_config(ns)
    assert port_of(cfg.bind) in img["expose"] and cfg.metrics_port in img["expose"]
    assert cfg.metrics_host == "0.0.0.0"  # reachable from outside the container
    probe = " ".join(img["healthcheck"])
    assert f"127.0.0.1:{cfg.metrics_port}/healthz" in probe
    for src, _ in img["copies"]:
        assert (ROOT / src).exists(), src


def test_trainer_image_is_pytorch_cuda_runtime_with_client_and_trainer():
    img = dockerfile("Dockerfile.trainer")
    assert re.fullmatch(r"pytorch/pytorch:[\w.]+-cuda[\w.]+-cudnn\d+-runtime", img["from"]), img["from"]
    assert any('pip install ".[client,trainer]"' in r for r in img["run"])
    assert img["user"] not in ("root", "0") and img["entrypoint"] == ["v2v-train"]
    ns = check_flags("v2v-train", img["cmd"])
    load_trainer_config(str(image_file(img, ns.config)))
    for src, _ in img["copies"]:
        assert (ROOT / src).exists(), src


# ---------------------------------------------------------------------------------- compose
def defaults(value):
    """A compose value as compose runs it when no variable is set: every ``${VAR:-default}``
    replaced by its default and ``$$`` (compose's escape) by ``$``."""
    if isinstance(value, list):
        return [defaults(v) for v in value]
    return re.sub(r"\$\{\w+:-([^}]*)\}", r"\1", value).replace("$$", "$")


def compose_file(*names: str) -> dict:
    """deploy/'s compose files merged as ``docker compose -f a -f b`` merges them, for what these
    files set: mappings key by key, a later file's command or entrypoint replacing the earlier
    one's. Any other list set by two files fails here (compose merges those its own way)."""

    def merge(a, b, key=None):
        if isinstance(a, dict) and isinstance(b, dict):
            return {k: merge(a[k], b[k], k) if k in a and k in b else b.get(k, a.get(k)) for k in {**a, **b}}
        assert key in ("command", "entrypoint") or not isinstance(a, list), f"{key}: a list set by two files"
        return b

    out = {}
    for n in names:
        out = merge(out, yaml.safe_load((DEPLOY / n).read_text()))
    return out


def image_owns(image: dict, path: str) -> bool:
    """Whether the image's RUN lines make ``path`` and give it to the image's user (a volume
    mounted there starts with that owner and is writable)."""
    runs = " ".join(image["run"])
    return bool(re.search(rf"mkdir -p [^&]*{re.escape(path)}(\s|$)", runs)) and bool(
        re.search(rf"chown {image['user']}:{image['user']} [^&]*{re.escape(path)}(\s|$)", runs))


def compose_services(comp: dict, tmp_path: Path) -> dict:
    """{name: (prog, args, namespace, config or None, mounts, service)} for every service, its
    flags checked against the program's parser, its paths against its mounts and image."""
    svcs = comp["services"]
    built = {s["image"]: s["build"] for s in svcs.values() if "build" in s}
    named_volumes = set(comp.get("volumes", {}))
    out = {}
    for name, s in svcs.items():
        build = s.get("build") or built[s["image"]]  # an image another service builds
        assert (DEPLOY / build["context"] / build["dockerfile"]).is_file()
        img = dockerfile(Path(build["dockerfile"]).name)
        argv = s.get("entrypoint", img["entrypoint"]) + defaults(s.get("command", img.get("cmd", [])))
        mounts = []
        for v in s.get("volumes", []):
            parts = defaults(v).split(":")
            if len(parts) == 1:  # an anonymous volume: made for each container, its own
                mounts.append({"mountPath": parts[0], "source": None, "readOnly": False})
                continue
            src, dst = parts[:2]
            if src.startswith((".", "/")):
                assert (DEPLOY / src).is_dir(), f"{name}: {src} is no folder"
            else:
                assert src in named_volumes, f"{name}: volume {src} not declared"
            mounts.append({"mountPath": dst, "source": src, "readOnly": v.endswith(":ro")})
        p = program(argv)
        if p is None:
            # the key maker: run its shell line against a scratch folder, then check the files
            assert argv[:2] == ["sh", "-c"] and "v2v-keygen" in argv[2]
            keys_mount = under("/keys", mounts)["mountPath"]
            line = argv[2].replace(keys_mount, str(tmp_path / "keys")).replace(
                "v2v-keygen", f"{shlex.quote(sys.executable)} -m v2v_server.ops.keygen")
            subprocess.run(["sh", "-c", line], check=True, capture_output=True, timeout=60)
            out[name] = (None, argv, None, None, mounts, s)
            continue
        prog, args = p
        ns = check_flags(prog, args)
        for flag in PATH_FLAGS:
            for path in flag_values(args, flag):
                if path.startswith("/opt/v2v/"):
                    image_file(img, path)
                else:
                    under(path, mounts)
        cfg = check_serve_config(ns) if prog == "v2v-serve" else None
        if cfg is not None and cfg.frame_cache_gb > 0:
            # the frame cache on a writable volume of each container's own (an anonymous volume:
            # every replica of a scaled service gets one; a named one would be shared by them),
            # made and owned in the image
            m = under(cfg.cache_dir, mounts)
            assert m["source"] is None and not m["readOnly"], f"{name}: {cfg.cache_dir} on {m}"
            assert image_owns(img, m["mountPath"]), f"{name}: the image does not make {m['mountPath']} for its user"
        out[name] = (prog, args, ns, cfg, mounts, s)
    return out


def same_corpus_and_cache(a, b) -> None:
    """Two v2v-serve configs that read the same corpus share, into the same frame cache, under
    the same recipe (so the entries one stores are the ones the other looks up)."""
    for key in ("videos", "cache_dir", "frame_cache_gb", "frame_cache_format"):
        assert getattr(a, key) == getattr(b, key), key
    assert a.serving.shard_spec == b.serving.shard_spec
    assert a.recipe.fingerprint() == b.recipe.fingerprint()


def seconds(duration: str) -> int:
    """A compose duration (``30s``, ``1h30m``) in seconds."""
    parts = re.findall(r"(\d+)([hms])", duration)
    assert "".join(n + u for n, u in parts) == duration, duration
    return sum(int(n) * {"h": 3600, "m": 60, "s": 1}[u] for n, u in parts)


def test_compose_one_scalable_server_service_and_a_trainer_reading_it_by_name(tmp_path):
    """`server` is one service of identical hosts serving one plan (no --shard) that
    ``--scale server=N`` can run N of: no container name, no fixed host port (the stream port
    stays on the compose network, metrics get a host port Docker picks per replica). The trainer
    connects to the service's name, which Docker's DNS resolves to every replica."""
    comp = compose_file("docker-compose.yml")
    svcs = compose_services(comp, tmp_path)
    (name, (_, args, ns, cfg, mounts, s)), = [(n, v) for n, v in svcs.items() if v[0] == "v2v-serve"]
    trainers = {n: v for n, v in svcs.items() if v[0] == "v2v-train"}
    assert "--shard" not in args and cfg.shard is None and cfg.serving.shard_spec == (0, 1)
    assert "container_name" not in s and s["deploy"]["replicas"] >= 2
    assert s["ports"]
    for p in s["ports"]:
        if isinstance(p, dict):
            assert "published" not in p and p["target"] == cfg.metrics_port, p
        else:  # "CONTAINER" alone: the host port is Docker's pick
            assert str(p) == str(cfg.metrics_port), p
    # /dev/shm holds the workers' slot rings: Docker's default 64 MiB would refuse them
    assert size_bytes(s["shm_size"]) >= shm_bytes(cfg.workers, cfg.sequence_length, cfg.num_bins, cfg.crop_size)
    hc = " ".join(s["healthcheck"]["test"])
    assert f"127.0.0.1:{cfg.metrics_port}/readyz" in hc  # healthy = ready: the trainer starts on a serving fleet
    for flag in ("--curve-secret-key", "--curve-allow"):
        assert flag_values(args, flag)[0].startswith("/keys/")
    (tname, (_, _, tns, _, tmounts, ts)), = trainers.items()
    tcfg = apply_overrides(load_trainer_config(str(image_file(dockerfile("Dockerfile.trainer"), tns.config))), tns.set)
    assert tns.connect == f"tcp://{name}:{port_of(cfg.bind)}"  # one name for every replica
    assert ts["depends_on"][name] == {"condition": "service_healthy"}
    # the keys the servers and the trainer name are the ones the key maker writes
    keys = tmp_path / "keys"
    assert (keys / Path(flag_values(args, "--curve-secret-key")[0]).relative_to("/keys")).is_file()
    assert list((keys / Path(flag_values(args, "--curve-allow")[0]).relative_to("/keys")).glob("*.key"))
    for kf in tcfg["stream"]["curve_keys"]:
        under(kf, tmounts)
        assert (keys / Path(kf).relative_to("/keys")).is_file()
    from v2v_client.endpoints import load_curve_keys

    load_curve_keys(*[str(keys / Path(k).relative_to("/keys")) for k in tcfg["stream"]["curve_keys"]])


def test_compose_each_server_replica_keeps_a_frame_cache_of_its_own(tmp_path):
    """The server caches frames (--frame-cache-gb, --cache-dir) on an anonymous volume, one per
    replica, and mounts no named volume writable: a named volume is mounted by every replica, and
    a cache folder must not be shared (writers are told apart by process id, and each container
    has its own ids). The check refuses a named cache volume."""
    comp = compose_file("docker-compose.yml")
    svcs = compose_services(comp, tmp_path)
    (_, _, _, cfg, mounts, s), = [v for v in svcs.values() if v[0] == "v2v-serve"]
    assert cfg.frame_cache_gb > 0 and cfg.cache_dir
    assert under(cfg.cache_dir, mounts)["source"] is None
    assert all(m["readOnly"] or m["source"] is None for m in mounts), mounts
    # the same file with the cache on a named volume is refused
    shared = json.loads(json.dumps(comp))
    shared["volumes"]["cache"] = None
    shared["services"]["server"]["volumes"] = [
        "cache:/var/cache/v2v" if v == cfg.cache_dir else v for v in s["volumes"]]
    with pytest.raises(AssertionError, match="/var/cache/v2v on"):
        compose_services(shared, tmp_path)


@pytest.mark.parametrize("files", [("docker-compose.yml", "docker-compose.warm.yml"),
                                   ("docker-compose.yml", "docker-compose.bucket.yml", "docker-compose.warm.yml")],
                         ids=["folder", "bucket"])
def test_compose_warm_override_fills_each_replicas_cache_then_serves_in_the_same_container(files, tmp_path):
    """docker-compose.warm.yml runs, in each replica, `v2v-serve <its line> --warm-cache` and then
    the server with the same line (so the warm-up fills that replica's own cache); a failed
    warm-up starts no server. The entrypoint is run here with a stand-in v2v-serve recording each
    line it is given. The health check's start period covers the warm-up."""
    base = compose_file(*files[:-1])["services"]["server"]
    comp = compose_file(*files)
    s = comp["services"]["server"]
    assert s["command"] == base["command"] and comp["volumes"] == compose_file(*files[:-1])["volumes"]
    argv = defaults(s["entrypoint"]) + defaults(s["command"])
    line = defaults(base["command"])
    bindir, calls = tmp_path / "bin", tmp_path / "calls.jsonl"
    bindir.mkdir()
    (bindir / "v2v-serve").write_text(
        f"#!{sys.executable}\nimport json, os, sys\n"
        "open(os.environ['CALLS'], 'a').write(json.dumps(sys.argv[1:]) + '\\n')\n"
        "sys.exit(int(os.environ['WARM_EXIT']) if '--warm-cache' in sys.argv else 0)\n")
    (bindir / "v2v-serve").chmod(0o755)

    def run(warm_exit):
        calls.unlink(missing_ok=True)
        env = {"PATH": f"{bindir}:/usr/bin:/bin", "CALLS": str(calls), "WARM_EXIT": str(warm_exit)}
        rc = subprocess.run(argv, env=env, timeout=60).returncode
        return rc, [json.loads(ln) for ln in calls.read_text().splitlines()]

    assert run(0) == (0, [line + ["--warm-cache"], line])
    assert run(2) == (2, [line + ["--warm-cache"]])
    ns = check_flags("v2v-serve", line + ["--warm-cache"])
    assert ns.warm_cache
    wcfg = check_serve_config(ns)
    scfg = check_serve_config(check_flags("v2v-serve", line))
    same_corpus_and_cache(wcfg, scfg)
    assert wcfg.workers == scfg.workers and wcfg.frame_cache_gb > 0
    if "docker-compose.bucket.yml" in files:
        assert wcfg.videos.startswith("s3://")
    else:  # the mounts are the server's: compose_services checks its cache volume is its own
        (_, _, _, _, mounts, _), = [v for v in compose_services(comp | {"services": {
            **comp["services"], "server": {**s, "entrypoint": ["v2v-serve"]}}}, tmp_path).values()
            if v[0] == "v2v-serve"]
        assert under(wcfg.cache_dir, mounts)["source"] is None
    hc, bhc = s["healthcheck"], base["healthcheck"]
    assert seconds(hc["start_period"]) >= 3600 > seconds(bhc["start_period"])
    assert {k: v for k, v in hc.items() if k != "start_period"} == {k: v for k, v in bhc.items() if k != "start_period"}


# ---------------------------------------------------------------------------------- kubernetes
K8S_FOLDERS = sorted(f.parent for f in DEPLOY.glob("k8s*/kustomization.yaml"))
needs_kubectl = pytest.mark.skipif(shutil.which("kubectl") is None, reason="kubectl not installed")


def test_kustomizations_list_every_file_in_their_folder():
    for folder in K8S_FOLDERS:
        kz = yaml.safe_load((folder / "kustomization.yaml").read_text())
        listed = {r for r in kz.get("resources", []) if (folder / r).is_file()}
        listed |= {p["path"] for p in kz.get("patches", []) if "path" in p}
        files = {f.name for f in folder.glob("*.yaml")} - {"kustomization.yaml"}
        assert listed == files, folder.name


def _container(doc):
    (c,) = doc["spec"]["template"]["spec"]["containers"]
    return c


def _mounts(doc, docs):
    """The container's mounts with what each volume is: configmap data key, secret items, the
    claim a volume per pod is made from (a StatefulSet's volumeClaimTemplates, or a generic
    ephemeral volume), ..."""
    spec = doc["spec"]["template"]["spec"]
    vols = {}
    for v in spec["volumes"]:
        vols[v["name"]] = dict(v, claimTemplate=v["ephemeral"]["volumeClaimTemplate"]["spec"]) if "ephemeral" in v else v
    for claim in doc["spec"].get("volumeClaimTemplates", []):  # a StatefulSet's volume per pod
        assert claim["metadata"]["name"] not in vols
        vols[claim["metadata"]["name"]] = {"name": claim["metadata"]["name"], "claimTemplate": claim["spec"]}
    out = []
    for m in _container(doc)["volumeMounts"]:
        v = dict(vols[m["name"]])
        m = dict(m, volume=v)
        if "configMap" in v:
            data = docs[("ConfigMap", v["configMap"]["name"])]["data"]
            assert m.get("subPath") in data, f"{m['mountPath']}: ConfigMap has no key {m.get('subPath')}"
            m["content"] = data[m["subPath"]]
        out.append(m)
    return out


def _check_path(path, mounts, secret_files):
    m = under(path, mounts)
    v = m["volume"]
    if "secret" in v:
        name = PurePosixPath(path).relative_to(m["mountPath"]).as_posix() if path != m["mountPath"] else None
        items = [i["path"] for i in v["secret"]["items"]]
        assert name is None or name in items, f"{path}: the Secret mount holds only {items}"
        for i in v["secret"]["items"]:
            secret_files.add(i["key"])
    return m


def _write(content: str) -> str:
    import tempfile

    f = tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False)
    f.write(content)
    f.close()
    return f.name


def check_server_pods(doc, docs, secret_files, shards=None):
    """The servers of a Deployment (the fleet: ``shards`` None, no --shard) or a StatefulSet
    (static shards: pod i serves ``i/shards``): flags exist and every pod's line parses with its
    config, the CPU request becomes --workers, /dev/shm holds the slot rings, paths lie on
    mounts, the frame cache on a claim of the pod's own below its size, ports and probes agree,
    requests equal limits. Returns (config, {port name: port}, frame-cache mount)."""
    c = _container(doc)
    env = {e["name"]: e for e in c["env"]}
    ref = env["CPU_REQUEST"]["valueFrom"]["resourceFieldRef"]
    assert ref["resource"] == "requests.cpu" and ref["containerName"] == c["name"]
    args = c["args"]
    assert flag_values(args, "--workers") == ["$(CPU_REQUEST)"]
    cpu = str(c["resources"]["requests"]["cpu"])
    if shards is None:  # one plan over the whole corpus: no shard flag, no shard variables
        assert "--shard" not in args and not {"SHARD_INDEX", "SHARDS"} & env.keys()
        pods = [({"CPU_REQUEST": cpu}, (0, 1))]
    else:  # pod index -> --shard: the pod-index label (Kubernetes >= 1.28) via the downward API
        assert env["SHARDS"]["value"] == str(shards)
        assert env["SHARD_INDEX"]["valueFrom"]["fieldRef"]["fieldPath"] == \
            "metadata.labels['apps.kubernetes.io/pod-index']"
        assert flag_values(args, "--shard") == ["$(SHARD_INDEX)/$(SHARDS)"]
        pods = [({"SHARD_INDEX": str(i), "SHARDS": str(shards), "CPU_REQUEST": cpu}, (i, shards)) for i in range(shards)]
    mounts = _mounts(doc, docs)
    for subst, spec in pods:
        ns = check_flags("v2v-serve", args, subst)
        conf = _check_path(ns.config, mounts, secret_files)
        cfg = check_serve_config(ns, _write(conf["content"]))
        assert cfg.serving.shard_spec == spec and cfg.workers == int(cpu)
    # /dev/shm: a memory-backed emptyDir large enough for the workers' slot rings
    shm_mount, = [m for m in c["volumeMounts"] if m["mountPath"] == "/dev/shm"]
    shm_vol, = [v for v in doc["spec"]["template"]["spec"]["volumes"] if v["name"] == shm_mount["name"]]
    assert shm_vol["emptyDir"]["medium"] == "Memory"
    assert size_bytes(shm_vol["emptyDir"]["sizeLimit"]) >= shm_bytes(cfg.workers, cfg.sequence_length, cfg.num_bins,
                                                                      cfg.crop_size)
    for flag in PATH_FLAGS:
        for path in flag_values(args, flag):
            _check_path(path, mounts, secret_files)
    # the frame cache: on a claim of the pod's own (never shared), its budget below its size
    assert cfg.frame_cache_gb > 0 and cfg.cache_dir
    cache = _check_path(cfg.cache_dir, mounts, secret_files)
    claim = cache["volume"]["claimTemplate"]
    assert claim["accessModes"] == ["ReadWriteOnce"]
    assert cfg.frame_cache_gb * (1 << 30) < size_bytes(claim["resources"]["requests"]["storage"])
    # ports: stream and metrics exposed, probes on the metrics port
    ports = {p["name"]: p["containerPort"] for p in c["ports"]}
    assert ports["stream"] == port_of(cfg.bind) and ports["metrics"] == cfg.metrics_port
    assert cfg.metrics_host == "0.0.0.0"
    assert c["readinessProbe"]["httpGet"] == {"path": "/readyz", "port": "metrics"}
    assert c["livenessProbe"]["httpGet"] == {"path": "/healthz", "port": "metrics"}
    assert doc["spec"]["template"]["metadata"]["annotations"]["prometheus.io/port"] == str(cfg.metrics_port)
    return cfg, ports, cache


def check_trainer(job, docs, secret_files):
    """The trainer Job: torchrun -m trainer.train, its flags, config, output and key paths on its
    mounts. Returns its --connect endpoints."""
    t = _container(job)
    prog, targs = program(t["command"] + t["args"])
    assert prog == "v2v-train" and t["command"][0] == "torchrun"
    tns = check_flags("v2v-train", targs)
    tmounts = _mounts(job, docs)
    tcfg = load_trainer_config(_write(_check_path(tns.config, tmounts, secret_files)["content"]))
    for path in flag_values(targs, "--out"):
        _check_path(path, tmounts, secret_files)
    for kf in tcfg["stream"]["curve_keys"]:
        _check_path(kf, tmounts, secret_files)
    # no host answering (the fleet rescheduled, a shard moved) is waited out this long
    assert tcfg["stream"]["timeout_s"] >= 300
    return tns.connect.split(",")


def check_pod_basics(*docs) -> None:
    """requests == limits (Guaranteed QoS: no CPU throttling surprises for decoding), non-root,
    and the images deploy/ builds."""
    for doc in docs:
        c = _container(doc)
        assert c["resources"]["requests"] == c["resources"]["limits"], doc["metadata"]["name"]
        sc = doc["spec"]["template"]["spec"]["securityContext"]
        assert sc["runAsNonRoot"] is True and sc["fsGroup"] == sc["runAsUser"] == 10001
        assert c["image"].split(":")[0] in ("v2v-server", "v2v-trainer")


def test_k8s_fleet_deployment_service_pdb_job_agree():
    """The base: the servers are a Deployment (no --shard: one plan, any number of replicas), a
    headless Service naming every ready pod, a PDB, and a trainer reading the fleet by the
    Service's one name."""
    docs = k8s_docs()
    dep = docs[("Deployment", "v2v-server")]
    assert not [k for k in docs if k[0] == "StatefulSet"]
    svc = docs[("Service", "v2v-server")]
    pdb = docs[("PodDisruptionBudget", "v2v-server")]
    job = docs[("Job", "v2v-trainer")]
    labels = dep["spec"]["template"]["metadata"]["labels"]
    assert dep["spec"]["selector"]["matchLabels"].items() <= labels.items()
    assert svc["spec"]["selector"].items() <= labels.items() and svc["spec"]["clusterIP"] == "None"
    # a fleet reads the ready hosts: a pod joins the name once /readyz answers, and leaves it
    # when it stops being ready (terminating)
    assert svc["spec"]["publishNotReadyAddresses"] is False
    assert pdb["spec"]["selector"]["matchLabels"].items() <= labels.items() and pdb["spec"]["maxUnavailable"] == 1
    # a rollout never takes the fleet below its replicas: the new pod is ready before an old one goes
    assert dep["spec"]["strategy"]["rollingUpdate"]["maxUnavailable"] == 0
    assert dep["spec"]["replicas"] >= 2
    secret_files = set()
    cfg, ports, cache = check_server_pods(dep, docs, secret_files)
    assert cfg.shard is None
    # each pod's cache is a generic ephemeral volume (a claim per pod, gone with it), not a
    # claim by name, which every replica would mount
    assert "ephemeral" in cache["volume"] and "persistentVolumeClaim" not in cache["volume"]
    for sp in svc["spec"]["ports"]:
        assert sp["targetPort"] in ports and sp["port"] == ports[sp["targetPort"]]
    assert check_trainer(job, docs, secret_files) == [f"tcp://{svc['metadata']['name']}:{ports['stream']}"]
    # one Secret holds the four key files v2v-keygen makes for "server" and "trainer"
    assert secret_files == {"server.key", "server.key_secret", "trainer.key", "trainer.key_secret"}
    check_pod_basics(dep, job)
    assert _container(dep)["image"].split(":")[0] == "v2v-server" and _container(job)["image"].split(":")[0] == "v2v-trainer"


def test_k8s_manifests_match_the_kubernetes_schemas():
    """Every manifest a kustomization folder holds as a resource of its own (the base, the HPA,
    the shards' StatefulSet), as written."""
    kv = pytest.importorskip("kubernetes_validate", reason="kubernetes-validate not installed (dev extra)")
    checked = set()
    for folder in K8S_FOLDERS:
        for (kind, name), doc in k8s_docs(folder).items():
            for version in ("1.29", "1.32"):
                kv.validate(doc, version, strict=True)  # raises ValidationError naming the field
            checked.add(kind)
    assert {"Deployment", "StatefulSet", "HorizontalPodAutoscaler", "Service", "Job"} <= checked


def _kustomize(path: Path) -> dict:
    out = subprocess.run(["kubectl", "kustomize", str(path)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return {(d["kind"], d["metadata"]["name"]): d for d in yaml.safe_load_all(out.stdout) if d}


BASE_KINDS = ["ConfigMap", "Deployment", "Job", "PodDisruptionBudget", "Service"]
OVERLAY_KINDS = {
    "k8s": BASE_KINDS,
    "k8s-autoscale": sorted(BASE_KINDS + ["HorizontalPodAutoscaler"]),
    "k8s-bucket": BASE_KINDS,
    "k8s-warm": BASE_KINDS,
    "k8s-shards": ["ConfigMap", "Job", "PodDisruptionBudget", "Service", "StatefulSet"],
}


@needs_kubectl
@pytest.mark.parametrize("overlay", sorted(OVERLAY_KINDS))
def test_kustomize_renders_each_overlay_to_objects_that_match_the_schemas(overlay):
    assert sorted(OVERLAY_KINDS) == sorted(f.name for f in K8S_FOLDERS if f.name != "k8s-warm-cache")
    docs = _kustomize(DEPLOY / overlay)
    assert sorted(kind for kind, _ in docs) == OVERLAY_KINDS[overlay]
    assert all(d["metadata"]["labels"]["app.kubernetes.io/part-of"] == "v2v" for d in docs.values())
    kv = pytest.importorskip("kubernetes_validate", reason="kubernetes-validate not installed (dev extra)")
    for doc in docs.values():
        for version in ("1.29", "1.32"):
            kv.validate(doc, version, strict=True)


@needs_kubectl
def test_k8s_autoscale_overlay_sizes_the_fleet_by_what_the_job_asks():
    """deploy/k8s-autoscale: an autoscaling/v2 HPA on the Pods metric deploy/prometheus-adapter
    serves (the share of each host's capacity the job asks of it: harness.fleet_sim's run of this
    file is tests/test_fleet_sim_autoscale.py), below 1, at least two hosts, growing on the last
    minute's lowest recommendation and shrinking after minutes, one host at a time; it owns the
    replica count (the overlay drops the field), and everything else is the base's."""
    docs, base = _kustomize(DEPLOY / "k8s-autoscale"), _kustomize(K8S)
    hpa = docs[("HorizontalPodAutoscaler", "v2v-server")]
    dep, base_dep = docs[("Deployment", "v2v-server")], base[("Deployment", "v2v-server")]
    assert hpa["apiVersion"] == "autoscaling/v2"
    ref = hpa["spec"]["scaleTargetRef"]
    assert (ref["apiVersion"], ref["kind"], ref["name"]) == (dep["apiVersion"], dep["kind"], dep["metadata"]["name"])
    (metric,) = hpa["spec"]["metrics"]
    adapter = yaml.safe_load((DEPLOY / "prometheus-adapter" / "values.yaml").read_text())
    (rule,) = adapter["rules"]["custom"]
    assert metric["type"] == "Pods" and metric["pods"]["metric"]["name"] == rule["name"]["as"]
    target = metric["pods"]["target"]
    assert target["type"] == "AverageValue" and target["averageValue"].endswith("m")
    share = int(target["averageValue"][:-1]) / 1000
    assert 0.5 <= share < 1  # 1: the job asks all the fleet makes, already behind
    # the pods are scraped where the adapter's series come from
    annotations = dep["spec"]["template"]["metadata"]["annotations"]
    assert annotations["prometheus.io/scrape"] == "true" and annotations["prometheus.io/path"] == "/metrics"
    assert flag_values(_container(dep)["args"], "--metrics-port") == [annotations["prometheus.io/port"]]
    spec = hpa["spec"]
    assert 2 <= spec["minReplicas"] <= base_dep["spec"]["replicas"] < spec["maxReplicas"]
    assert spec["behavior"]["scaleDown"]["stabilizationWindowSeconds"] >= 300
    assert spec["behavior"]["scaleUp"]["stabilizationWindowSeconds"] <= 60
    down = spec["behavior"]["scaleDown"]
    assert down["policies"] == [{"type": "Pods", "value": 1, "periodSeconds": down["policies"][0]["periodSeconds"]}]
    # what deploy/README.md says of it
    readme = " ".join((DEPLOY / "README.md").read_text().split())
    assert f"{spec['minReplicas']} to {spec['maxReplicas']} hosts, {share:.2f} of each host's capacity asked" in readme
    assert f"shrinks after {down['stabilizationWindowSeconds'] // 60} minutes of lower asks, one host at a time" in readme
    assert "replicas" not in dep["spec"]
    assert {**dep, "spec": {**dep["spec"], "replicas": base_dep["spec"]["replicas"]}} == base_dep
    assert {k: v for k, v in docs.items() if k[0] not in ("HorizontalPodAutoscaler", "Deployment")} == \
        {k: v for k, v in base.items() if k[0] != "Deployment"}


@needs_kubectl
def test_k8s_shards_overlay_runs_static_shards_as_a_statefulset():
    """deploy/k8s-shards: the Deployment gone, a StatefulSet whose pod index is the shard and
    whose SHARDS equals replicas, each with a cache claim kept per ordinal; the trainer lists
    every shard by its stable name, which resolves while the shard starts. Apart from the shard
    and the cache claim, the pods are the fleet's."""
    docs, base = _kustomize(DEPLOY / "k8s-shards"), _kustomize(K8S)
    assert ("Deployment", "v2v-server") not in docs
    sts = docs[("StatefulSet", "v2v-server")]
    svc = docs[("Service", sts["spec"]["serviceName"])]
    pdb, job = docs[("PodDisruptionBudget", "v2v-server")], docs[("Job", "v2v-trainer")]
    labels = sts["spec"]["template"]["metadata"]["labels"]
    assert sts["spec"]["selector"]["matchLabels"].items() <= labels.items()
    assert svc["spec"]["selector"].items() <= labels.items() and pdb["spec"]["selector"]["matchLabels"].items() <= labels.items()
    assert svc["spec"]["publishNotReadyAddresses"] is True and svc["spec"]["clusterIP"] == "None"
    replicas = sts["spec"]["replicas"]
    secret_files = set()
    cfg, ports, cache = check_server_pods(sts, docs, secret_files, shards=replicas)
    assert cache["name"] in [c["metadata"]["name"] for c in sts["spec"]["volumeClaimTemplates"]]
    want = [f"tcp://{sts['metadata']['name']}-{i}.{svc['metadata']['name']}:{ports['stream']}" for i in range(replicas)]
    assert check_trainer(job, docs, secret_files) == want
    check_pod_basics(sts, job)
    # the rest is the fleet's: the container but for the shard, the volumes but for the cache
    dep = base[("Deployment", "v2v-server")]
    c, bc = _container(sts), _container(dep)
    i = c["args"].index("--shard")
    assert c["args"][:i] + c["args"][i + 2:] == bc["args"]
    assert [e for e in c["env"] if e["name"] not in ("SHARD_INDEX", "SHARDS")] == bc["env"]
    assert {k: v for k, v in c.items() if k not in ("args", "env")} == {k: v for k, v in bc.items() if k not in ("args", "env")}
    spec, bspec = sts["spec"]["template"]["spec"], dep["spec"]["template"]["spec"]
    assert {k: v for k, v in spec.items() if k not in ("containers", "volumes")} == \
        {k: v for k, v in bspec.items() if k not in ("containers", "volumes")}
    bvols = {v["name"]: v for v in bspec["volumes"]}
    assert {v["name"]: v for v in spec["volumes"]} == {n: v for n, v in bvols.items() if n != cache["name"]}
    claim, = [t for t in sts["spec"]["volumeClaimTemplates"] if t["metadata"]["name"] == cache["name"]]
    assert claim["spec"] == bvols[cache["name"]]["ephemeral"]["volumeClaimTemplate"]["spec"]
    assert sts["spec"]["template"]["metadata"] == dep["spec"]["template"]["metadata"]
    # the other objects are the base's, but for the Service's published addresses and the trainer's list
    assert {k: v for k, v in docs.items() if k[0] in ("ConfigMap", "PodDisruptionBudget")} == \
        {k: v for k, v in base.items() if k[0] in ("ConfigMap", "PodDisruptionBudget")}


def _store_env(env: dict) -> None:
    """A bucket corpus's configuration: the endpoint as a variable, the keys from a Secret."""
    assert env["AWS_ENDPOINT_URL"]["value"].startswith("http")
    for k in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY"):
        ref = env[k]["valueFrom"]["secretKeyRef"]
        assert ref["name"] == "v2v-s3" and ref["key"] == k


@needs_kubectl
def test_k8s_bucket_overlay_reads_the_corpus_from_a_bucket():
    docs = _kustomize(DEPLOY / "k8s-bucket")
    dep = docs[("Deployment", "v2v-server")]
    c = _container(dep)
    env = {e["name"]: e for e in c["env"]}
    _store_env(env)
    assert "CPU_REQUEST" in env and "SHARD_INDEX" not in env  # the base's variables stay: a fleet
    assert flag_values(c["args"], "--videos") == ["s3://v2v-corpus/webvid/"]
    ns = check_flags("v2v-serve", c["args"], {"CPU_REQUEST": "4"})
    ns.config = None
    cfg = check_serve_config(ns)
    assert cfg.videos == "s3://v2v-corpus/webvid/" and cfg.shard is None
    assert all(v["name"] != "videos" for v in dep["spec"]["template"]["spec"]["volumes"])  # no corpus volume
    # every other mount of the base stays (a mount's merge key is its path: deleting by name drops them all)
    base = _container(k8s_docs()[("Deployment", "v2v-server")])["volumeMounts"]
    assert c["volumeMounts"] == [m for m in base if m["mountPath"] != "/data/videos"]
    _mounts(dep, {("ConfigMap", "v2v-config"): k8s_docs()[("ConfigMap", "v2v-config")]})  # each names a volume


@needs_kubectl
@pytest.mark.parametrize("overlay", ["k8s-warm", "k8s-bucket", "k8s-shards"])
def test_k8s_warm_cache_component_runs_the_servers_line_with_warm_cache_first(overlay, tmp_path):
    """The optional component (deploy/k8s-warm-cache) gives each server pod an init container
    running the server container's own line with --warm-cache: same image, environment
    (CPU request, and the shard index where there are shards), mounts (corpus, frame cache) and
    resources, so it fills the cache the server then reads. Added last to another overlay (the
    bucket's, the shards'), it copies that overlay's line."""
    if overlay == "k8s-warm":
        docs = _kustomize(DEPLOY / "k8s-warm")
    else:  # an overlay of another overlay with the component, as deploy/k8s-warm-cache says
        shutil.copytree(DEPLOY, tmp_path / "deploy")
        (tmp_path / "deploy" / "mine").mkdir()
        (tmp_path / "deploy" / "mine" / "kustomization.yaml").write_text(
            f"resources: [../{overlay}]\ncomponents: [../k8s-warm-cache]\n")
        docs = _kustomize(tmp_path / "deploy" / "mine")
    kind = "StatefulSet" if overlay == "k8s-shards" else "Deployment"
    server = docs[(kind, "v2v-server")]
    spec = server["spec"]["template"]["spec"]
    c, (warm,) = _container(server), spec["initContainers"]
    assert warm["name"] == "warm-cache" and warm["args"] == c["args"] + ["--warm-cache"]
    for key in ("image", "env", "volumeMounts", "resources"):
        assert warm[key] == c[key], key
    cpu = str(c["resources"]["requests"]["cpu"])
    subst, shard = {"CPU_REQUEST": cpu}, (0, 1)
    if kind == "StatefulSet":
        shard = (1, server["spec"]["replicas"])
        subst.update(SHARD_INDEX="1", SHARDS=str(shard[1]))
    ns = check_flags("v2v-serve", warm["args"], subst)
    assert ns.warm_cache
    cfg = check_serve_config(ns, _write(docs[("ConfigMap", "v2v-config")]["data"]["server.yaml"]))
    assert cfg.frame_cache_gb > 0 and cfg.serving.shard_spec == shard and cfg.workers == int(cpu)
    assert cfg.videos == ("s3://v2v-corpus/webvid/" if overlay == "k8s-bucket" else "/data/videos")
    assert any(m["mountPath"] == cfg.cache_dir for m in warm["volumeMounts"])
    kv = pytest.importorskip("kubernetes_validate", reason="kubernetes-validate not installed (dev extra)")
    for version in ("1.29", "1.32"):
        kv.validate(server, version, strict=True)


def test_compose_bucket_override_and_raycluster_read_the_bucket():
    """docker-compose.bucket.yml changes the server's corpus to a bucket and adds its
    credentials; the rest of the line is the base file's (workers, frame cache, bind, keys)."""
    comp = yaml.safe_load((DEPLOY / "docker-compose.bucket.yml").read_text())
    base = yaml.safe_load((DEPLOY / "docker-compose.yml").read_text())
    assert set(comp["services"]) == {"server"} <= set(base["services"])
    s = comp["services"]["server"]
    assert s["environment"]["AWS_SHARED_CREDENTIALS_FILE"] == "/run/secrets/aws_credentials"
    assert "AWS_ENDPOINT_URL" in s["environment"] and s["secrets"] == ["aws_credentials"]
    args = defaults(s["command"])
    assert "--shard" not in args
    ns = check_flags("v2v-serve", args)
    ns.config = None
    cfg = check_serve_config(ns)
    assert cfg.videos == "s3://v2v-corpus/webvid/"
    bns = check_flags("v2v-serve", defaults(base["services"]["server"]["command"]))
    bns.config = None
    bcfg = check_serve_config(bns)
    bcfg = type(bcfg).from_dict({**bcfg.to_dict(), "videos": cfg.videos}, source="base")
    same_corpus_and_cache(cfg, bcfg)
    assert cfg.to_dict() == bcfg.to_dict()
    assert "aws_credentials" in comp["secrets"]
    ray = ray_docs()[("RayCluster", "v2v")]
    pods = [ray["spec"]["headGroupSpec"]] + ray["spec"]["workerGroupSpecs"]
    for g in pods:
        _store_env({e["name"]: e for e in g["template"]["spec"]["containers"][0]["env"]})


# ---------------------------------------------------------------------------------- KubeRay
def ray_docs(text: str = None) -> dict:
    text = text if text is not None else (DEPLOY / "ray" / "raycluster.yaml").read_text()
    return {(d["kind"], d["metadata"]["name"]): d for d in yaml.safe_load_all(text) if d}


def _ray_config_file(docs: dict, path: str, groups: dict) -> str:
    """A local copy of the file every pod of ``groups`` reads at ``path``: the ConfigMap key
    its mount holds there (the same in each)."""
    contents = set()
    for g in groups.values():
        spec = g["template"]["spec"]
        vols = {v["name"]: v for v in spec["volumes"]}
        m = under(path, spec["containers"][0]["volumeMounts"])
        cm = vols[m["name"]]["configMap"]["name"]
        contents.add(docs[("ConfigMap", cm)]["data"][PurePosixPath(path).relative_to(m["mountPath"]).as_posix()])
    (content,) = contents
    return _write(content)


def _ray_serve_config(docs: dict, path: str, groups: dict):
    """The ServeConfig the pods of ``groups`` read at ``path``."""
    from v2v_server.ops.config import load_config

    return load_config(_ray_config_file(docs, path, groups))


def _pod(spec: dict) -> dict:
    return {"apiVersion": "v1", "kind": "Pod", "metadata": {"name": "v2v"}, "spec": spec}


def test_raycluster_pods_that_decode_or_scan_keep_a_frame_cache():
    """The job line (the file's header) reads the serve config the head mounts; that config
    turns the frame cache on (cache_dir, frame_cache_gb), and the head (the driver's scan) and
    the CPU group (the V2V actors) mount a volume of their own there, larger than the budget.
    Every pod template is a valid Pod spec."""
    text = (DEPLOY / "ray" / "raycluster.yaml").read_text()
    docs = ray_docs(text)
    ray = docs[("RayCluster", "v2v")]
    groups = {"head": ray["spec"]["headGroupSpec"], **{g["groupName"]: g for g in ray["spec"]["workerGroupSpecs"]}}
    comments = [ln.lstrip("#").strip() for ln in text.splitlines() if ln.startswith("#")]
    first = next(i for i, ln in enumerate(comments) if ln.startswith("ray job submit"))
    last = next(i for i in range(first, len(comments)) if not comments[i].endswith("\\"))
    job = " ".join(ln.rstrip("\\").strip() for ln in comments[first:last + 1])
    prog, args = program(shlex.split(job.split(" -- ", 1)[1]))
    ns = check_flags(prog, args)
    assert ns.engine == "ray" and ns.serve_config
    cfg = _ray_serve_config(docs, ns.serve_config, {"head": groups["head"], "v2v-cpu": groups["v2v-cpu"]})
    assert cfg.frame_cache_gb > 0 and cfg.cache_dir
    for name in ("head", "v2v-cpu"):
        spec = groups[name]["template"]["spec"]
        vols = {v["name"]: v for v in spec["volumes"]}
        mounts = spec["containers"][0]["volumeMounts"]
        under(cfg.videos, mounts)
        cache = vols[under(cfg.cache_dir, mounts)["name"]]
        assert "emptyDir" in cache, name  # node-local, the pod's own
        assert cfg.frame_cache_gb * (1 << 30) < size_bytes(cache["emptyDir"]["sizeLimit"]), name
    assert "v2v_cpu" in groups["v2v-cpu"]["rayStartParams"]["resources"]  # the actors decode there only
    kv = pytest.importorskip("kubernetes_validate", reason="kubernetes-validate not installed (dev extra)")
    for g in groups.values():
        kv.validate(_pod(g["template"]["spec"]), "1.32", strict=True)
    kv.validate(docs[("ConfigMap", "v2v-ray-serve")], "1.32", strict=True)


@pytest.mark.skipif(shutil.which("kubectl") is None, reason="kubectl not installed")
def test_ray_warm_overlay_fills_each_cpu_pods_cache_with_the_jobs_config():
    """deploy/ray-warm: each CPU-group pod runs ``v2v-serve --warm-cache`` first, with the
    serve config the job reads (same corpus, recipe and cache), one process per CPU the group
    declares, and the worker container's image, environment, mounts and resources."""
    docs = _kustomize(DEPLOY / "ray-warm")
    assert ray_docs()[("ConfigMap", "v2v-ray-serve")] == docs[("ConfigMap", "v2v-ray-serve")]
    ray = docs[("RayCluster", "v2v")]
    cpu, gpu = ray["spec"]["workerGroupSpecs"]
    spec = cpu["template"]["spec"]
    (warm,), worker = spec["initContainers"], spec["containers"][0]
    for key in ("image", "env", "volumeMounts", "resources"):
        assert warm[key] == worker[key], key
    prog, args = program(warm["command"])
    ns = check_flags(prog, args)
    assert prog == "v2v-serve" and ns.warm_cache
    want = _ray_serve_config(docs, ns.config, {"v2v-cpu": cpu})
    cfg = check_serve_config(ns, _ray_config_file(docs, ns.config, {"v2v-cpu": cpu}))
    same_corpus_and_cache(cfg, want)
    assert cfg.to_dict() == {**want.to_dict(), "workers": cfg.workers, "insecure": True}  # the test's insecure
    assert cfg.workers == int(cpu["rayStartParams"]["num-cpus"]) == int(worker["resources"]["requests"]["cpu"])
    assert "initContainers" not in gpu["template"]["spec"] and "initContainers" not in ray["spec"]["headGroupSpec"]["template"]["spec"]
    kv = pytest.importorskip("kubernetes_validate", reason="kubernetes-validate not installed (dev extra)")
    kv.validate(_pod(spec), "1.32", strict=True)

"""The packages' import graph has no cycle, the wire package stands alone, and the client reaches
the server package only for the demo's in-process server (module-level and function-level imports both count)."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("v2v_wire", "v2v_server", "v2v_client", "trainer")
#: what v2v_client may import from v2v_server: the in-process server the demo runs (the demo
#: needs a decode host's install anyway); everything else it speaks is in v2v_wire
CLIENT_MAY_IMPORT = {"v2v_server.service.local"}


def _module(path: Path) -> str:
    return ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")


def _type_only(tree: ast.AST) -> set:
    """ids of the import nodes inside ``if TYPE_CHECKING:`` blocks (annotations only, no import at run time)."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and getattr(node.test, "id", getattr(node.test, "attr", "")) == "TYPE_CHECKING":
            out |= {id(n) for b in node.body for n in ast.walk(b)}
    return out


def import_graph(runtime_only: bool = False) -> dict:
    """{module: set of project modules it imports}, over PACKAGES (``runtime_only``: imports
    under ``if TYPE_CHECKING:`` left out)."""
    mods = {_module(p): p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")}
    graph = {}
    for name, path in mods.items():
        pkg = name if path.name == "__init__.py" else name.rpartition(".")[0]
        deps = set()
        tree = ast.parse(path.read_text())
        skip = _type_only(tree) if runtime_only else set()
        for node in ast.walk(tree):
            if id(node) in skip:
                continue
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                    base = ".".join(parts + ([base] if base else []))
                targets = [base] + [f"{base}.{a.name}" for a in node.names]
            else:
                continue
            deps.update(t for t in targets if t in mods and t != name)
        graph[name] = deps
    return graph


def find_cycle(graph: dict):
    """One cycle as a list of modules, or None."""
    state, stack = {}, []

    def visit(n):
        state[n] = 1
        stack.append(n)
        for m in sorted(graph[n]):
            if state.get(m) == 1:
                return stack[stack.index(m):] + [m]
            if m not in state:
                found = visit(m)
                if found:
                    return found
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state:
            found = visit(n)
            if found:
                return found
    return None


def test_find_cycle_finds_one():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_no_import_cycle():
    assert find_cycle(import_graph()) is None


def test_client_uses_only_the_servers_public_wire_modules():
    graph = import_graph()
    used = {m for n, deps in graph.items() if n.startswith("v2v_client") for m in deps if m.startswith("v2v_server")}
    assert used <= CLIENT_MAY_IMPORT | {"v2v_server", "v2v_server.service"}, sorted(used - CLIENT_MAY_IMPORT)


def test_wire_package_stands_alone():
    graph = import_graph()
    used = {m for n, deps in graph.items() if n.startswith("v2v_wire") for m in deps if not m.startswith("v2v_wire")}
    assert not used, sorted(used)


#: The server's stage folders, lowest first: each imports only the stages before it (and
#: ``v2v_server.checks``, ``v2v_server.faults``, ``v2v_server.settings`` and ``v2v_server.luma``, the
#: one uint16 -> uint8 conversion that flow, decode and the sample maker use, and
#: ``v2v_server.disk_cache``, the one budgeted on-disk cache and the cache folder's default, that the
#: sources' object cache and the frames' frame cache both use, below all of them), at run time
#: and for annotations alike (an ``if TYPE_CHECKING:`` import counts). ``sources`` (where a
#: video's bytes come from: list, open, identity) sits below ``frames`` (what a pass reads of
#: them: decode, scale, cache, shots, windows, the index), which takes a source. ``ops``
#: (settings, metrics, logs) sits below the ``service`` that uses them; the Ray engine
#: (``ray_data``, the other engine beside the service) above them all; the command that wires
#: everything, ``v2v-serve``, is above every stage.
STAGES = ("flow", "sources", "frames", "simulation", "samples", "delivery", "ops", "service", "ray_data")
COMMANDS = {"v2v_server.cli"}
#: what a stage may import from v2v_server besides the stages below it (the package itself runs
#: on any import of a module in it)
BELOW_ALL = {"v2v_server", "v2v_server.checks", "v2v_server.faults", "v2v_server.settings", "v2v_server.luma",
             "v2v_server.disk_cache"}
#: names a parameter carrying the whole server configuration goes by
CONFIG_NAMES = {"cfg", "config", "cfg_dict", "serve_config"}


def test_each_stage_imports_only_the_stages_below_it():
    graph = import_graph()  # TYPE_CHECKING imports included: no stage names a higher stage's type
    bad = []
    for n, deps in graph.items():
        parts = n.split(".")
        if parts[0] != "v2v_server" or len(parts) < 2 or parts[1] not in STAGES or n in COMMANDS:
            continue
        below = STAGES[:STAGES.index(parts[1]) + 1]
        for m in deps:
            mp = m.split(".")
            if mp[0] == "v2v_server" and m not in BELOW_ALL and not (len(mp) > 1 and mp[1] in below):
                bad.append(f"{n} imports {m}")
    assert not bad, bad


def functions_taking_the_configuration() -> list:
    """``module:function`` of every function or method of the stages below ``ops`` with a
    parameter named as the whole configuration (``CONFIG_NAMES``) or annotated ``ServeConfig``:
    those stages take their own settings (``python -m tests.test_import_graph`` prints them)."""
    out = []
    for stage in STAGES[:STAGES.index("ops")]:
        for path in sorted((ROOT / "v2v_server" / stage).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    continue
                args = node.args.posonlyargs + node.args.args + node.args.kwonlyargs
                if any(a.arg in CONFIG_NAMES or "ServeConfig" in ast.unparse(a.annotation or ast.Constant(""))
                       for a in args):
                    out.append(f"{_module(path)}:{node.name}")
    return out


def test_no_stage_below_ops_takes_the_configuration():
    assert functions_taking_the_configuration() == []


if __name__ == "__main__":
    print(find_cycle(import_graph()) or "no cycle")
    taking = functions_taking_the_configuration()
    print(f"{len(taking)} function(s) below ops taking the configuration" + "".join(f"\n  {f}" for f in taking))

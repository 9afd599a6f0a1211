"""The suite reads only what the repository holds: no test, harness or bench path leads out of
it (a fresh clone with nothing beside it runs every test; ``harness/data.py`` names the test
material). Two checks: the source of ``tests/``, ``harness/`` and ``bench/`` is read for paths
that climb above the repository root, and ``tests/conftest.py`` refuses, while the suite runs,
any read of a folder beside the repository (``in_beside``)."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

from .conftest import ROOT, in_beside

FOLDERS = ("tests", "harness", "bench")
#: the one line allowed to name the folder beside the repository: the guard that refuses it
GUARD = ("tests/conftest.py", 'BESIDE = ROOT.parent / "shared"')
#: a path expression that climbs: ``parents[N]``, a chain of ``.parent``, ``dirname(dirname(``,
#: a ``..`` path component in a string, or the material folder that CI keeps beside the clone
CLIMBS = {
    "parents": re.compile(r"__file__\)(?:\.resolve\(\))?\.parents\[(\d+)\]"),
    "parent": re.compile(r"__file__\)(?:\.resolve\(\))?((?:\.parent)+)"),
    "dirname": re.compile(r"((?:os\.path\.dirname\()+)os\.path\.abspath\(__file__\)"),
    "root_parent": re.compile(r"\bROOT\.parent\b"),
    "dotdot": re.compile(r"""(?:\bROOT\b|__file__\)\S*)\s*(?:/|,)\s*["']\.\.[/"']"""),
    "shared": re.compile(r"""["']shared["']\s*/|/\s*["']shared["']|["']\.\./shared"""),
}


def climbs(text: str, depth: int) -> list:
    """``(line number, line)`` of each path in the source ``text`` of a file ``depth`` folders
    below ``ROOT`` that leads above ``ROOT``."""
    out = []
    for n, line in enumerate(text.splitlines(), 1):
        bad = any(int(m) > depth for m in CLIMBS["parents"].findall(line))
        bad |= any(g.count(".parent") > depth + 1 for g in CLIMBS["parent"].findall(line))
        bad |= any(g.count("dirname(") > depth + 1 for g in CLIMBS["dirname"].findall(line))
        bad |= any(CLIMBS[k].search(line) is not None for k in ("root_parent", "dotdot", "shared"))
        if bad:
            out.append((n, line.strip()))
    return out


def test_no_test_harness_or_bench_path_leads_out_of_the_repository():
    found = {}
    for folder in FOLDERS:
        for p in sorted((ROOT / folder).rglob("*.py")):
            if p.resolve() == Path(__file__).resolve():
                continue  # this file's examples below
            lines = climbs(p.read_text(encoding="utf-8"), len(p.relative_to(ROOT).parts) - 1)
            lines = [(n, s) for n, s in lines if (p.relative_to(ROOT).as_posix(), s) != GUARD]
            if lines:
                found[str(p.relative_to(ROOT))] = lines
    ci = (ROOT / ".ci" / "run").read_text()
    assert "../shared" not in ci and "shared/data" not in ci
    assert not found, found


@pytest.mark.parametrize("line, depth, bad", [
    ('ROOT = Path(__file__).resolve().parents[1]', 1, False),
    ('EVENTS = Path(__file__).resolve().parents[2] / "data"', 1, True),
    ('EVENTS = Path(__file__).resolve().parents[2] / "data"', 2, False),
    ('X = Path(__file__).resolve().parent.parent / "v2v_server"', 1, False),
    ('X = Path(__file__).resolve().parent.parent.parent / "x"', 1, True),
    ('h = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))', 1, False),
    ('h = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))', 1, True),
    ('SHARED = ROOT.parent / "shared" / "data"', 1, True),
    ('p = here / "shared" / "videos"', 1, True),
    ('p = "../shared/data/events/x.raw"', 1, True),
    ('q = Path("data/events") / name', 1, False),
    ('q = os.path.join(os.path.dirname(__file__), "..", "..", "x")', 1, True),
    ('q = ROOT / ".." / "x"', 1, True),
    ('bad = "../../etc/passwd"  # a traversal the server must refuse', 1, False),
])
def test_the_source_check_finds_paths_that_climb(line, depth, bad):
    """The source check on known lines: each climbing form is found, in-repo paths are not."""
    assert bool(climbs(line, depth)) == bad, line


def test_a_read_beside_the_repository_is_refused_while_the_suite_runs():
    """The runtime guard: opening or listing the material folder CI keeps beside the clone
    fails, naming the path, whether or not it exists; the repository stays readable."""
    beside = ROOT.parent / "shared" / "data" / "videos" / "bikes.mp4"
    assert in_beside(str(beside)) and in_beside(bytes(beside)) and in_beside(beside)
    assert not in_beside(str(ROOT / "tests" / "data" / "events")) and not in_beside(str(ROOT.parent / "sharedx"))
    with pytest.raises(PermissionError, match="outside the repository: .*shared"):
        open(beside, "rb")
    with pytest.raises(PermissionError, match="outside the repository"):
        list((ROOT.parent / "shared").iterdir())
    assert (ROOT / "tests" / "data" / "events" / "README.md").read_text()

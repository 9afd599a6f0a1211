"""``python -m harness.code_shape`` as a test: no class and no function of the installed packages,
the benches and the harness is over the bounds docs/architecture.md states (read from the doc,
their one owner) is named in the report, and a unit over a bound is named without failing the run:
a size bound flags a smell to read, never a reason to cut code where the line count falls."""
from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

from harness.code_shape import BOUNDS_DOC, stated_limits

ROOT = Path(__file__).resolve().parents[1]


def _code_shape(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "harness.code_shape", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=120, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})


def test_the_report_reads_every_package_with_the_bounds_the_architecture_doc_states():
    limit_class, limit_function = stated_limits(ROOT)
    doc = " ".join((ROOT / BOUNDS_DOC).read_text().split())
    assert f"no class over {limit_class} lines, no function over {limit_function} lines" in doc
    r = _code_shape()
    for folder in ("v2v_wire", "v2v_server", "v2v_client", "trainer", "bench", "harness"):  # every folder is read
        assert any(line.split()[0] == folder for line in r.stdout.splitlines() if line.strip()), folder
    assert f"over the limits (class > {limit_class}, function > {limit_function} lines):" in r.stdout, \
        r.stdout[-3000:] + r.stderr[-2000:]
    assert r.returncode == 0


def test_a_class_or_function_over_a_bound_is_named_and_the_report_still_exits_0(tmp_path):
    limit_class, limit_function = stated_limits(ROOT)
    body = "\n".join(f"    x{i} = {i}" for i in range(limit_class))  # with its first line: one over
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "big.py").write_text(
        f"class Big:\n{body}\n\n\ndef long():\n" + "\n".join(f"    y{i} = {i}" for i in range(limit_function - 1))
        + "\n" + textwrap.dedent("""
        def fits():
            return 1
        """))
    r = _code_shape("--root", str(tmp_path), "pkg")
    assert r.returncode == 0, r.stdout + r.stderr
    over = r.stdout.split("over the limits")[1].splitlines()[1:]
    assert [line.split() for line in over] == [["class", str(limit_class + 1), "Big", "(pkg/big.py:1)"]]
    assert f"{limit_function}  long  (pkg/big.py:" in r.stdout  # exactly at the bound: listed, not over

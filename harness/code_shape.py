"""The shape of the code: the largest classes and functions, and lines per subpackage.

Usage: ``python -m harness.code_shape [--top N] [--limit-class N] [--limit-function N] [PATH ...]``
(default paths: the packages ``v2v_wire v2v_server v2v_client trainer``, and ``bench harness``, the
benches and what tests and benches share, held to the same bounds). Prints, for each subpackage (a
folder with Python files), its modules and lines; then the ``N`` largest classes and functions
with their file and line; then every class and function over the limits, to be read: a size
over a bound flags a smell (a class whose state splits, a function doing two things), never a
reason to cut code where the line count falls, so the report exits 0 (a usage error exits 2). The limits default to the bounds
docs/architecture.md states (:func:`stated_limits`: the doc is their one owner;
``tests/test_code_shape.py`` runs this with them).

A class's or function's size is its source lines, from its first decorator to its last line
(``ast`` end_lineno), docstrings and comments included. Numba kernels (functions decorated with
``numba.njit``/``numba.jit``, ``njit``/``jit``, called or not) are left out: their length
follows the loop they compile, not the structure of the service. Nested functions count in
their own right and within their parent.
"""
from __future__ import annotations

import argparse
import ast
import re
import sys
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Iterable, List, Tuple

DEFAULT_PATHS = ("v2v_wire", "v2v_server", "v2v_client", "trainer", "bench", "harness")
#: Where the bounds are stated, relative to the repository root, and the sentence that states them.
BOUNDS_DOC = "docs/architecture.md"
BOUNDS_SENTENCE = re.compile(r"no\s+class\s+over\s+(\d+)\s+lines,\s+no\s+function\s+over\s+(\d+)")
NUMBA_DECORATORS = {"njit", "jit"}


@dataclass(frozen=True)
class Unit:
    """One class or function: ``kind`` ("class" or "function"), qualified ``name``, ``path``,
    first ``line`` and ``lines`` (count)."""

    kind: str
    name: str
    path: str
    line: int
    lines: int


def is_numba_kernel(node: ast.AST) -> bool:
    """True for a function decorated with ``numba.njit``/``numba.jit`` (or ``njit``/``jit``
    imported from numba), with or without arguments."""
    for d in getattr(node, "decorator_list", ()):
        target = d.func if isinstance(d, ast.Call) else d
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", None)
        if name in NUMBA_DECORATORS:
            return True
    return False


def units(path: Path, root: Path) -> List[Unit]:
    """The classes and functions of one Python file (numba kernels left out).

    Raises:
        SyntaxError: the file does not parse (the message names it).
    """
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    out: List[Unit] = []

    def walk(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                name = prefix + child.name
                if not is_numba_kernel(child):
                    first = min([child.lineno] + [d.lineno for d in child.decorator_list])
                    kind = "class" if isinstance(child, ast.ClassDef) else "function"
                    out.append(Unit(kind, name, path.relative_to(root).as_posix(), first,
                                    child.end_lineno - first + 1))
                walk(child, name + ".")
            else:
                walk(child, prefix)

    walk(tree, "")
    return out


def python_files(paths: Iterable[str], root: Path) -> List[Path]:
    files: List[Path] = []
    for p in paths:
        p = (root / p)
        files += [p] if p.is_file() else sorted(f for f in p.rglob("*.py") if "__pycache__" not in f.parts)
    return files


def subpackage_lines(files: List[Path], root: Path) -> Dict[str, Tuple[int, int]]:
    """folder (relative to ``root``) -> (modules, lines) of the Python files directly in it."""
    out: Dict[str, List[int]] = defaultdict(lambda: [0, 0])
    for f in files:
        d = f.parent.relative_to(root).as_posix()
        out[d][0] += 1
        out[d][1] += len(f.read_text(encoding="utf-8").splitlines())
    return {k: (v[0], v[1]) for k, v in sorted(out.items())}


def stated_limits(root: Path) -> Tuple[int, int]:
    """(lines a class may have, lines a function may have) as ``BOUNDS_DOC`` under ``root``
    states them ("no class over N lines, no function over M ...").

    Raises:
        ValueError: the doc states no bounds (naming the doc and the sentence looked for).
    """
    doc = root / BOUNDS_DOC
    m = BOUNDS_SENTENCE.search(doc.read_text(encoding="utf-8"))
    if m is None:
        raise ValueError(f"{doc}: states no bounds (looked for {BOUNDS_SENTENCE.pattern!r})")
    return int(m.group(1)), int(m.group(2))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("paths", nargs="*", default=list(DEFAULT_PATHS), help="folders or files, relative to --root")
    ap.add_argument("--root", default=".", help="repository root (default: the current folder)")
    ap.add_argument("--top", type=int, default=8, help="largest classes and functions to list (default 8)")
    ap.add_argument("--limit-class", type=int, help=f"lines a class may have (default: {BOUNDS_DOC}'s bound)")
    ap.add_argument("--limit-function", type=int, help=f"lines a function may have (default: {BOUNDS_DOC}'s bound)")
    args = ap.parse_args(argv)
    root = Path(args.root).resolve()
    if args.limit_class is None or args.limit_function is None:
        stated = stated_limits(Path(__file__).resolve().parents[1])
        args.limit_class = stated[0] if args.limit_class is None else args.limit_class
        args.limit_function = stated[1] if args.limit_function is None else args.limit_function
    files = python_files(args.paths, root)
    print(f"{'subpackage':<32} {'modules':>7} {'lines':>7}")
    for d, (n, lines) in subpackage_lines(files, root).items():
        print(f"{d:<32} {n:>7} {lines:>7}")
    all_units = [u for f in files for u in units(f, root)]
    over = []
    for kind, limit in (("class", args.limit_class), ("function", args.limit_function)):
        mine = sorted((u for u in all_units if u.kind == kind), key=lambda u: -u.lines)
        print(f"\nlargest {kind}es:" if kind == "class" else f"\nlargest {kind}s:")
        for u in mine[: args.top]:
            print(f"  {u.lines:>5}  {u.name}  ({u.path}:{u.line})")
        over += [u for u in mine if u.lines > limit]
    print(f"\nover the limits (class > {args.limit_class}, function > {args.limit_function} lines): {len(over)}")
    for u in over:
        print(f"  {u.kind:<8} {u.lines:>5}  {u.name}  ({u.path}:{u.line})")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Derive tests/data/v2v_paper_cuts.json: the evaluation sequences and cuts of the V2V paper as
the authors' repository (HYLZ-2019/V2V) defines them, read without running their code:
``CUT_SECONDS`` of ``scripts/ijrr_to_h5.py`` and ``scripts/mvsec_to_h5.py``, ``use_seqs`` of
``scripts/evaid_to_h5.py`` (Python literals, parsed with ``ast``), and the sequence names of
``config/{hqf,ijrr,mvsec,evaid}_test.txt``. ``tests/test_trainer_protocol.py`` checks
``trainer.protocol``'s built-in tables against it.

    python harness/paper_cuts.py /path/to/V2V > tests/data/v2v_paper_cuts.json
"""
from __future__ import annotations

import ast
import json
import sys
from pathlib import Path


def literal_dict(path: Path, name: str) -> dict:
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == name for t in node.targets):
            return {k: list(v) for k, v in ast.literal_eval(node.value).items()}
    raise KeyError(f"{path}: no {name} = {{...}}")


def main() -> None:
    repo = Path(sys.argv[1])
    out = {"source": "HYLZ-2019/V2V 62ce9c8, built by harness/paper_cuts.py",
           "cuts": {"ijrr": literal_dict(repo / "scripts/ijrr_to_h5.py", "CUT_SECONDS"),
                    "mvsec": literal_dict(repo / "scripts/mvsec_to_h5.py", "CUT_SECONDS"),
                    "evaid": literal_dict(repo / "scripts/evaid_to_h5.py", "use_seqs")},
           "test_lists": {ds: [Path(line.strip()).stem for line in (repo / f"config/{ds}_test.txt").read_text().splitlines()
                               if line.strip()] for ds in ("hqf", "ijrr", "mvsec", "evaid")}}
    json.dump(out, sys.stdout, indent=1)
    print()


if __name__ == "__main__":
    main()

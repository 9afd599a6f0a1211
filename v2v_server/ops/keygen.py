"""``v2v-keygen``: CurveZMQ key pairs for the server and its clients."""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import List, Optional, Tuple

from v2v_wire.commands import writable_problem


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(
        prog="v2v-keygen",
        description="Make a CurveZMQ key pair: NAME.key (public, give it to peers) and NAME.key_secret "
                    "(keep it). The server takes its .key_secret with --curve-secret-key and a folder of "
                    "allowed client .key files with --curve-allow; a client takes its own .key_secret and "
                    "the server's .key.")
    p.add_argument("name", help="key name, e.g. server or trainer-01")
    p.add_argument("--out", default=".", help="folder to write the key files to (default: .)")
    a = p.parse_args(argv)
    import zmq.auth

    out = Path(a.out)
    why = writable_problem(out, folder=True)
    if why:
        print(f"v2v-keygen: --out {out}: {why}", file=sys.stderr)
        return 2
    for suffix in (".key", ".key_secret"):
        if (out / f"{a.name}{suffix}").exists():
            print(f"v2v-keygen: {out / (a.name + suffix)} exists; not overwriting", file=sys.stderr)
            return 2
    public, secret = _key_pair(out, a.name, zmq.auth.create_certificates)
    print(f"public key: {public}\nsecret key: {secret}")
    return 0


def _key_pair(out: Path, name: str, create) -> Tuple[Path, Path]:
    """The key pair ``name`` made by ``create`` (``zmq.auth.create_certificates``) in a
    temporary folder inside ``out``, then moved into ``out``: both files or neither, whatever
    interrupts it (the secret one readable by its owner only)."""
    tmp = Path(tempfile.mkdtemp(prefix=f".{name}.", dir=out))
    moved: List[Path] = []
    try:
        made = [Path(p) for p in create(str(tmp), name)]
        made[1].chmod(0o600)
        for p in made:
            os.replace(p, out / p.name)
            moved.append(out / p.name)
        return out / made[0].name, out / made[1].name
    except BaseException:
        for p in moved:
            p.unlink(missing_ok=True)
        raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    from v2v_wire.commands import main_of_module

    sys.exit(main_of_module("v2v-keygen", main))

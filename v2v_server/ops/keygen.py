"""``v2v-keygen``: CurveZMQ key pairs for the server and its clients."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import List, Optional


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
    out.mkdir(parents=True, exist_ok=True)
    for suffix in (".key", ".key_secret"):
        if (out / f"{a.name}{suffix}").exists():
            print(f"v2v-keygen: {out / (a.name + suffix)} exists; not overwriting", file=sys.stderr)
            return 2
    public, secret = zmq.auth.create_certificates(str(out), a.name)
    Path(secret).chmod(0o600)
    print(f"public key: {public}\nsecret key: {secret}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Speed / accuracy benchmark: ``python bench/tradeoff.py --out DIR`` (see v2v_server/tradeoff.py)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from v2v_server.tradeoff import main  # noqa: E402

if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

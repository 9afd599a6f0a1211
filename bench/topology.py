"""Draw the scale-out topology of the README: N decode shards feeding M trainer ranks.

Run: ``python -m bench.topology --out docs/img/topology.png`` (matplotlib; SVG or PNG by suffix).
"""
from __future__ import annotations

import argparse
import sys
from typing import List, Optional


def draw(out: str, shards: int = 3, ranks: int = 2) -> None:
    """Boxes and arrows: the corpus split by hash over ``shards`` CPU hosts (v2v-serve
    --shard i/N, W workers each, /metrics), every trainer rank fetching its rows of the one plan
    from each of them."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import FancyBboxPatch

    fig, ax = plt.subplots(figsize=(9.5, 4.6))
    ax.set_xlim(0, 10)
    ax.set_ylim(0, 5)
    ax.axis("off")

    def box(x, y, w, h, text, fc, fs=9):
        ax.add_patch(FancyBboxPatch((x, y), w, h, boxstyle="round,pad=0.05", fc=fc, ec="#333", lw=1))
        ax.text(x + w / 2, y + h / 2, text, ha="center", va="center", fontsize=fs)

    def arrow(x0, y0, x1, y1, color="#555"):
        ax.annotate("", xy=(x1, y1), xytext=(x0, y0),
                    arrowprops=dict(arrowstyle="->", color=color, lw=1.0, shrinkA=2, shrinkB=2))

    box(0.1, 1.6, 1.6, 1.8, "video corpus\n(shared volume\nor a copy per host)\n\nshard of a file =\nBLAKE2b(path) mod N",
        "#f3f3f3", 8)
    ys = [4.2 - i * (3.3 / max(1, shards - 1)) for i in range(shards)] if shards > 1 else [2.5]
    for i, y in enumerate(ys):
        label = f"CPU host {i}: v2v-serve --shard {i}/{shards}\nW decode + V2V workers\n:5555 stream   :9464 /metrics"
        box(2.6, y - 0.42, 3.0, 0.84, label, "#dbe9f6", 8)
        arrow(1.75, 2.5, 2.55, y)
    rys = [3.4 - i * (1.8 / max(1, ranks - 1)) for i in range(ranks)] if ranks > 1 else [2.5]
    for r, y in enumerate(rys):
        box(7.0, y - 0.4, 2.8, 0.8, f"GPU rank {r}: V2VStreamDataset\n(all shards, rank={r}, world_size={ranks})",
            "#e2f0d9", 8)
        for ysrv in ys:
            arrow(5.65, ysrv, 6.95, y, "#4a7ab5")
    ax.text(8.4, 4.4, "fetches of plan positions, rows back over ZeroMQ\n(CurveZMQ off loopback); position t is\n"
            "shard t mod N's t // N; checkpoint: a position",
            ha="center", va="center", fontsize=8, color="#4a7ab5")
    ax.text(5.0, 0.02, "each position of an epoch's plan is read by exactly one rank; content = f(seed, epoch, "
            "sample id) whichever host made it", ha="center", fontsize=8)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="docs/img/topology.png")
    p.add_argument("--shards", type=int, default=3)
    p.add_argument("--ranks", type=int, default=2)
    a = p.parse_args(argv)
    draw(a.out, a.shards, a.ranks)
    print(a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The flow-grid expansion with and without numba: ``python -m bench.flowgrid``.

A client-only install (``pip install v2v[client]``) has no numba; ``v2v_wire.flowgrid`` then
expands a tracked option's ``flow_grid`` with numpy array operations (the same float32 bits).
This prints the milliseconds per sample of the default recipe (L = 40 fields, an 8 x 8 grid,
128 x 128 crops; best of ``--rounds``, one thread) of the numba loop, the numpy path and the
torch ops (``v2v_client.flowgrid._expand_torch``, one torch thread), and the ratios against
numba measured in the same run; it checks the three give the same bits first.
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def best_ms(fn, rounds: int) -> float:
    """Best wall time of ``fn()`` over ``rounds`` calls, milliseconds (one warm-up call first)."""
    fn()
    best = float("inf")
    for _ in range(rounds):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best * 1e3


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=30)
    p.add_argument("--fields", type=int, default=40, help="flow fields per sample (L)")
    p.add_argument("--grid", type=int, default=8, help="grid points per side (n)")
    p.add_argument("--crop", type=int, default=128, help="crop size, pixels")
    a = p.parse_args(argv)
    import torch

    from v2v_client.flowgrid import _expand_torch
    from v2v_wire.flowgrid import HAVE_NUMBA, expand_grids

    torch.set_num_threads(1)
    g = np.random.default_rng(0).normal(0, 3, (a.fields, 2, a.grid, a.grid)).astype(np.float32)
    size = (a.crop, a.crop)
    paths = {"numpy": lambda: expand_grids(g, size, use_numba=False),
             "torch": lambda: _expand_torch(torch.from_numpy(g), *size).numpy()}
    if HAVE_NUMBA:
        paths = {"numba": lambda: expand_grids(g, size, use_numba=True), **paths}
    ref = next(iter(paths.values()))().view(np.int32)
    for name, fn in paths.items():
        assert np.array_equal(fn().view(np.int32), ref), f"{name} differs from {next(iter(paths))}"
    ms = {name: best_ms(fn, a.rounds) for name, fn in paths.items()}
    base = ms.get("numba")
    print(f"| path | ms per sample ({a.fields} x 2 x {a.grid} x {a.grid} -> {a.crop} x {a.crop}) | x numba |")
    print("|---|---|---|")
    for name, v in ms.items():
        print(f"| {name} | {v:.2f} | {v / base:.1f} |" if base else f"| {name} | {v:.2f} | - |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Every scenario the simulator runs, by name: the seeded families (``families.py``) and the
issue's named scenarios (``named.py``), and :func:`run_seeds` that runs one over many seeds."""
from __future__ import annotations

import functools
import time
from dataclasses import dataclass
from typing import Callable, Dict, Iterable, Optional

from harness.delivery_sim.families import FAILS_ON_MAIN, FAMILIES, MAIN
from harness.delivery_sim.named import NAMED
from harness.delivery_sim.run import simulate


@dataclass(frozen=True)
class Scenario:
    """A named way to build a run from a seed (``build(seed, trace) -> Run``); ``doc``: one
    line; ``xfail``: what the delivery path does wrong here today (None: it holds)."""

    name: str
    build: Callable
    doc: str
    xfail: Optional[str] = None


def _doc(fn) -> str:
    return (fn.__doc__ or "").strip().splitlines()[0] if fn.__doc__ else ""


SCENARIOS: Dict[str, Scenario] = {name: Scenario(name, fn, _doc(fn), FAILS_ON_MAIN.get(name))
                                  for name, fn in FAMILIES.items()}
SCENARIOS.update({name: Scenario(name, fn, _doc(fn), why) for name, (fn, why) in NAMED.items()})
SCENARIOS.update({f"{name}/main": Scenario(f"{name}/main", functools.partial(fn, profile=MAIN),
                                           f"{_doc(fn)} (the faults it survives today)")
                  for name, fn in FAMILIES.items() if name not in ("elastic", "ddp")})


def run_one(name: str, seed: int, trace: bool = False):
    """One seed of scenario ``name``: its ``run.Result``."""
    return simulate(SCENARIOS[name].build(seed, trace), name)


def run_seeds(name: str, seeds: Iterable[int], trace: bool = False) -> dict:
    """Run ``seeds`` of ``name``: ``{"scenario", "seeds", "failed", "failures": [{"seed", "kind",
    "what", "replay"}], "seconds", "seeds_per_s", "results"}`` (``results``: every ``Result`` when
    tracing, else the failing ones)."""
    t0 = time.perf_counter()
    results, failures, n = [], [], 0
    for seed in seeds:
        r = run_one(name, seed, trace)
        n += 1
        if not r.ok:
            failures.append({"seed": seed, "kind": r.violation.kind, "what": str(r.violation), "replay": r.replay()})
        if trace or not r.ok:
            results.append(r)
    dt = time.perf_counter() - t0
    return {"scenario": name, "seeds": n, "failed": len(failures), "failures": failures, "seconds": dt,
            "seeds_per_s": n / dt if dt > 0 else 0.0, "results": results}

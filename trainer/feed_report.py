"""Whether a run was fed: the line ``v2v-train`` ends with (``summary.json``'s ``feed``, the
TensorBoard text ``feed``), from the loop's own figures and the server's.

The loop measures what it trained (``samples_per_s``), the share of its wall time it waited for
batches (``data_wait_fraction``) and the model's own rate, its samples over the time it did not
wait (``model_samples_per_s``), each from the end of the first step on (the first batch and the
first step, compile included, are start-up: ``startup_s``). A server serving by plan reports its
workers, its frame cache and the seconds its workers spent per stage (``plan_server.stream_info``'s
``feed``). A run that waited is fed at the server's rate, so each worker made ``samples_per_s /
workers``: the workers that would feed the model are its rate over that, and with a frame cache
each worker skips the decode share of its time after a video's first epoch.
"""
from __future__ import annotations

import math
from typing import Optional

__all__ = ["STARVED_ABOVE", "feed_line"]

#: A run that waited for more than this share of its time was starved by its server.
STARVED_ABOVE = 0.05


def feed_line(summary: dict, server: Optional[dict] = None) -> str:
    """One line saying whether the run was fed, and if not what would feed it.

    Args:
        summary: the loop's summary (``trainer.loop.train_loop``): ``samples_per_s``,
            ``data_wait_fraction``, ``model_samples_per_s`` (None when no step was timed).
        server: the server's ``feed`` figures (``workers``, ``frame_cache_gb``, ``busy_s``: stage
            -> worker seconds), or None when it did not report them (the Ray engine).

    Returns:
        e.g. ``"starved: 3.1 samples/s, waiting 62 % of the time for batches; the model alone
        trains 8.2 samples/s: about 2 more decode workers at this recipe (3 in all, 2.6 samples/s
        each), or --frame-cache-gb (decode is 70 % of the workers' time: then 1 in all)"``.
    """
    fed, wait, model = (summary.get(k) for k in ("samples_per_s", "data_wait_fraction", "model_samples_per_s"))
    if not fed or wait is None or not model:
        return "not measured: no step after the first"
    head = f"{fed:.1f} samples/s, waiting {100 * wait:.0f} % of the time for batches; the model alone trains " \
           f"{model:.1f} samples/s"
    if wait <= STARVED_ABOVE:
        return f"fed: {head}: the model sets the pace, more decode workers would not speed it up"
    workers = (server or {}).get("workers")
    if not isinstance(workers, int) or workers < 1:
        return f"starved: {head}: add decode workers or hosts (the server did not report its workers)"
    each = fed / workers
    need = max(workers + 1, math.ceil(model / each))
    line = (f"starved: {head}: about {need - workers} more decode worker(s) at this recipe ({need} in all, "
            f"{each:.2f} samples/s each)")
    busy = server.get("busy_s") or {}
    total = sum(v for v in busy.values() if isinstance(v, (int, float)))
    decode = busy.get("decode", 0.0) / total if total > 0 else 0.0
    if not server.get("frame_cache_gb") and decode >= 0.2:
        cached = math.ceil(model / (each / (1.0 - decode))) if decode < 1 else 1
        line += (f", or --frame-cache-gb (decode is {100 * decode:.0f} % of the workers' time, paid once per video "
                 f"with it: then about {cached} in all)")
    return line

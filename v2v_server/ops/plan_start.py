"""The manifest a server serving by plan starts from (docs/plan.md): each served video's slots.

The slots are the windows ``--check`` finds (``frames.check.check_corpus``: answered by the host's
corpus index while a video's identity holds, else read, in ``processes`` processes, and recorded
there), so they are exact: a decode never gives more, and fewer only when a file changes or breaks
(padding rows, ``delivery.plan_feed``). A video that gives no window has 0 slots and is logged as
``v2v-serve`` logs a skipped file.
"""
from __future__ import annotations

import logging
from typing import Dict, Tuple

from v2v_server.frames.check import check_corpus
from v2v_server.ops.startup import Startup
from v2v_wire.plan import Manifest

log = logging.getLogger("v2v.serve")


def plan_manifest(start: Startup, processes: int = 1) -> Tuple[Manifest, Dict[str, str]]:
    """The manifest of ``start``'s served videos and the reasons of those that give no window.

    Args:
        start: the start-up path's result (``ops.startup.start_source``).
        processes: decoding processes for the videos the corpus index does not know.
    Returns:
        ``(manifest, skipped)``: the slots of every video of ``start.videos`` (0 for one that
        gives no window, known from the index or read) and video -> reason for those.
    """
    recipe = start.config.recipe
    served = start.served
    verdicts = check_corpus(recipe.windows, recipe.decode, start.source, served, processes, start.caches)
    slots = {v.path: v.windows if v.usable else 0 for v in verdicts}
    skipped = {v.path: v.reason for v in verdicts if not v.usable}
    for rel, (_, reason) in start.skipped.items():
        slots[rel], skipped[rel] = 0, reason
    for rel, reason in sorted(skipped.items()):
        log.warning("skipped %s: %s", start.source.where(rel), reason)
    return Manifest.of(slots, recipe.crops_per_window), skipped

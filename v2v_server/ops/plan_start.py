"""The manifest a server serving by plan starts from (docs/plan.md): each served video's slots.

Chosen by the numbers of docs/plan_slots.md (``bench/plan_slots.py``): a video's slots are the
windows ``frames.check.count_windows`` finds, in ``processes`` processes. With ``shot_cuts: off``
(and static windows kept) that is its packet count's bound, about 40x cheaper than a decode and
within 2 % of the windows decoded (the slots a decode leaves empty are padding rows); with shot
cuts avoided or static windows skipped a bound would pad half the slots, so the frames are read as
``--check`` reads them, and the host's corpus index answers for every file it knows. A decode never
gives more windows than its slots (``delivery.plan_feed.SlotsExceeded`` names one that does). A
video that gives no window has 0 slots and is logged as ``v2v-serve`` logs a skipped file.
"""
from __future__ import annotations

import logging
from typing import Dict, Tuple

from v2v_server.frames.check import count_windows
from v2v_server.frames.video_pool import map_videos
from v2v_server.ops.startup import Startup
from v2v_wire.plan import Manifest

log = logging.getLogger("v2v.serve")


def plan_manifest(start: Startup, processes: int = 1) -> Tuple[Manifest, Dict[str, str]]:
    """The manifest of ``start``'s served videos and the reasons of those that give no window.

    Args:
        start: the start-up path's result (``ops.startup.start_source``).
        processes: processes counting the videos.
    Returns:
        ``(manifest, skipped)``: the slots of every video of ``start.videos`` (0 for one that
        gives no window) and video -> reason for those.
    """
    recipe = start.config.recipe
    served = start.served
    counts = map_videos(count_windows, (recipe.windows, recipe.decode, recipe.reads), start.source, start.caches,
                        served, processes)
    slots = {rel: n if reason is None else 0 for rel, (n, reason) in zip(served, counts)}
    skipped = {rel: reason for rel, (_, reason) in zip(served, counts) if reason is not None}
    for rel, (_, reason) in start.skipped.items():
        slots[rel], skipped[rel] = 0, reason
    for rel, reason in sorted(skipped.items()):
        log.warning("skipped %s: %s", start.source.where(rel), reason)
    return Manifest.of(slots, recipe.crops_per_window), skipped

"""The manifest a server serving by plan starts from (docs/delivery.md): each served video's slots
where the host's corpus index knows them (a video's windows, as a decode of it found them, its
identity unchanged), None for the others, and each one's tag (one ``stat`` of a file, a store's
listing entry), which the plan's identity covers. Nothing is read at start: the plan unfolds as the
server's decodes find the windows of the videos it does not know (``v2v_wire.plan.EpochPlan``),
so a corpus never scanned costs no pass before its first batch. A decode never gives more windows
than its slots (``delivery.plan_schedule.SlotsExceeded`` names one that does). A video the index knows
to give no window has 0 slots.
"""
from __future__ import annotations

from v2v_server.ops.startup import Startup
from v2v_wire.plan import Manifest


def plan_manifest(start: Startup) -> Manifest:
    """The manifest of ``start``'s videos (``ops.startup.start_source``'s result): the slots its
    corpus index knows (``start.known``; 0 for those it knows to give no window), None for the rest,
    and each one's tag (``VideoSource.listed_tag``: a file's ``stat``, a store's listing entry),
    which the plan's identity covers.

    Raises:
        ValueError: no video files, or every video known to give no window."""
    if not start.videos:
        raise ValueError(f"no video files under {start.source.root}")
    known = start.known.windows
    tags = {rel: start.source.listed_tag(rel) for rel in start.videos}
    manifest = Manifest.of({rel: known.get(rel) for rel in start.videos}, start.config.recipe.crops_per_window, tags)
    if manifest.samples == 0:
        raise ValueError(f"--videos {start.source.root}: no video gives a window at this layout (--check says why)")
    return manifest

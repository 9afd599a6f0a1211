"""The recipes of docs/corpora.md run on generated corpora in each corpus's shape: samples per
epoch and per clip-hour, and every entry skipped with why.

``python -m bench.corpus_recipes [--clips 3] [--hd-height 1080] [--json docs/corpus_recipes.json]``
writes, in a temporary folder, five corpora made from real footage (camera motion over the
photographs ``harness.motion_clips`` renders, one shot each; WebVid's montage from the bundled
``webvid_like_596x336.mp4``), ``--clips`` sets their size, HD frames are upscaled (``cv2.resize``,
INTER_CUBIC) to ``--hd-height`` rows at 16:9:

* ``webvid``: a folder of 596 x 336 clips of 18 s (WebVid's frame size and length), one of them
  the bundled montage;
* ``openvid``: OpenVid-style stored zip parts of HD clips and a CSV with OpenVid-1M's header,
  naming each clip by its bare file name as OpenVid's does, with a short row, a row the filter
  drops and a row whose clip is in no part, given with the parts as a brace range so that each
  row is paired with its part's member (``archive_members.pair_members``);
* ``panda``: HD source videos of three shots each (hard cuts) and a Panda-70M CSV of one
  timestamp range per shot;
* ``webdataset``: two uncompressed tar shards of ``KEY.mp4`` + ``KEY.json`` samples;
* ``phone``: portrait phone clips at 30 fps, stored landscape with a display matrix turning
  them a quarter (``.mp4`` and ``.mov``).

Each recipe's command (:data:`RECIPES`, the text docs/corpora.md shows) runs as ``v2v-serve``
would, ``python -m v2v_server.cli`` with this checkout on ``PYTHONPATH``, in the corpus
folder, ``XDG_CACHE_HOME`` in the temporary folder (the corpus index starts empty), and its
``--check`` report is read back. Footage listed: the seconds of every video the listing names
(frames / fps of the written file; a range's length), a table's filtered and short rows
included, a row whose video exists nowhere not.
"""
from __future__ import annotations

import argparse
import csv
import io
import itertools
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import tarfile
import tempfile
import zipfile
from pathlib import Path
from typing import Dict, Iterable, Iterator, List, Optional, Tuple

import cv2
import numpy as np

from harness.corpus import OPENVID_HEADER
from harness.data import ROOT, SAMPLE_VIDEOS
from harness.motion_clips import render_clip, source_images

#: The command of each recipe, run in the corpus folder.
RECIPES = {
    "webvid": "v2v-serve --videos webvid/ --keep-top-fraction 0.54 --check",
    "openvid": "v2v-serve --videos 'parts/OpenVid_part{0..LAST}.zip' --video-list OpenVidHD.csv "
               "--video-list-filter '\"motion score\" > 0.5' --keep-top-fraction 1.0 --frame-height 336 --check",
    "panda": "v2v-serve --videos videos/ --video-list panda70m.csv --video-list-column '{videoID}.mp4' "
             "--keep-top-fraction 1.0 --frame-height 336 --check",
    "webdataset": "v2v-serve --videos 'shards/shard-{000000..000001}.tar' --keep-top-fraction 1.0 --check",
    "phone": "v2v-serve --videos phone/ --keep-top-fraction 1.0 --frame-height 336 --check",
}
PANDA_HEADER = ["videoID", "url", "timestamp", "caption", "matching_score"]
MONTAGE = "webvid_like_596x336.mp4"


class Footage:
    """Renders one-shot clips (grey ``uint8 (T, H, W)``) of a camera moving over real photographs
    and encodes them; ``hd``: (height, width) of HD footage."""

    def __init__(self, hd_height: int):
        self.photos = [img for _, img in source_images()]
        self.hd = (hd_height, 2 * round(hd_height * 16 / 9 / 2))
        self.count = 0

    def shot(self, frames: int, size: Tuple[int, int]) -> Iterator[np.ndarray]:
        """A new shot of ``frames`` frames at ``size`` (H, W), frame by frame; HD sizes rendered
        at 336 rows and upscaled as they are taken (an HD shot is never held whole)."""
        self.count += 1
        base = size if size[0] <= 360 else (336, 2 * round(336 * size[1] / size[0] / 2))
        clip = render_clip(self.photos[self.count % len(self.photos)], base, frames,
                           np.random.default_rng(self.count))
        return iter(clip) if base == size else \
            (cv2.resize(f, (size[1], size[0]), interpolation=cv2.INTER_CUBIC) for f in clip)


def encode(path: Path, frames: Iterable[np.ndarray], fps: int = 25, rotation: Optional[int] = None) -> float:
    """Write grey ``uint8 (H, W)`` frames as H.264 (libx264 ultrafast, crf 20) at ``fps``;
    ``rotation``: a display matrix, degrees counter-clockwise. Returns the seconds it lasts."""
    import av

    path.parent.mkdir(parents=True, exist_ok=True)
    count = 0
    with av.open(str(path), "w") as c:
        s = c.add_stream("libx264", rate=fps)
        s.options = {"crf": "20", "preset": "ultrafast"}
        if rotation is not None:
            s.set_display_rotation(rotation)
        for f in frames:
            if not count:
                s.width, s.height, s.pix_fmt = f.shape[1], f.shape[0], "yuv420p"
            count += 1
            for p in s.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(f), format="gray").reformat(format="yuv420p")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    return count / fps


def seconds_of(path: Path) -> float:
    """Frames / average frame rate of the video at ``path`` (frames counted from packets)."""
    import av

    with av.open(str(path)) as c:
        s = c.streams.video[0]
        frames = sum(1 for p in c.demux(s) if p.size)
        return frames / float(s.average_rate)


def make_webvid(root: Path, fp: Footage, clips: int) -> float:
    """``webvid/``: ``clips`` one-shot 596 x 336 clips of 450 frames (18 s) and WebVid's montage."""
    total = sum(encode(root / "webvid" / f"{1066687000 + i}.mp4", fp.shot(450, (336, 596))) for i in range(clips))
    shutil.copy(SAMPLE_VIDEOS / MONTAGE, root / "webvid" / MONTAGE)
    return total + seconds_of(root / "webvid" / MONTAGE)


def make_openvid(root: Path, fp: Footage, clips: int) -> float:
    """``parts/OpenVid_part{0..clips-1}.zip`` (stored), one HD clip of 260 or 450 frames each, part
    0 also a short clip (150 frames) and a clip the filter drops; ``OpenVidHD.csv`` of them all
    and of one clip in no part."""
    tmp = root / "openvid_clips"
    rows, total = [], 0.0
    for k in range(clips):
        frames = (260, 450)[k % 2]
        total += encode(tmp / f"clip_{k:04d}.mp4", fp.shot(frames, fp.hd))
        rows.append((f"clip_{k:04d}.mp4", k, frames, 2.5 + k))
    total += encode(tmp / "short_0000.mp4", fp.shot(150, fp.hd))
    rows.append(("short_0000.mp4", 0, 150, 3.1))
    shutil.copy(tmp / "clip_0000.mp4", tmp / "still_0000.mp4")
    total += rows[0][2] / 25
    rows.append(("still_0000.mp4", 0, rows[0][2], 0.21))
    (root / "parts").mkdir()
    for k in range(clips):
        with zipfile.ZipFile(root / "parts" / f"OpenVid_part{k}.zip", "w", zipfile.ZIP_STORED) as z:
            for name, part, _, _ in rows:
                if part == k:
                    z.write(tmp / name, name)
    shutil.rmtree(tmp)
    rows.append(("not_downloaded.mp4", None, 300, 1.7))
    with open(root / "OpenVidHD.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(OPENVID_HEADER)
        for name, _, frames, motion in rows:
            w.writerow([name, f'A camera pans over "{name}", slowly, in daylight.', 5.1, motion, 0.98, "pan_right",
                        frames, 25.0, round(frames / 25, 2)])
    return total


def make_panda(root: Path, fp: Footage, clips: int) -> float:
    """``videos/`` of ``clips`` HD source videos, each three shots of 300, 120 and 260 frames cut
    hard, and ``panda70m.csv``: per video one row whose ``timestamp`` holds one range per shot
    (0.2 s inside each shot). Returns the seconds the ranges span."""
    shots, total = (300, 120, 260), 0.0
    with open(root / "panda70m.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(PANDA_HEADER)
        for v in range(clips):
            vid = f"-{v:02d}Xk9aQ_zY"
            encode(root / "videos" / f"{vid}.mp4", itertools.chain.from_iterable(fp.shot(n, fp.hd) for n in shots))
            starts = np.cumsum((0,) + shots) / 25
            pairs = [[clock(a + 0.2), clock(b - 0.2)] for a, b in zip(starts[:-1], starts[1:])]
            total += sum(b - a - 0.4 for a, b in zip(starts[:-1], starts[1:]))
            w.writerow([vid, f"https://www.youtube.com/watch?v={vid}", str(pairs),
                        str([f"shot {i}, a camera over a photograph" for i in range(3)]), str([0.41, 0.39, 0.44])])
    return total


def clock(t: float) -> str:
    """``t`` seconds as Panda-70M writes a time: ``0:00:12.480``."""
    ms = round(t * 1000)
    return f"{ms // 3_600_000}:{ms // 60_000 % 60:02d}:{ms // 1000 % 60:02d}.{ms % 1000:03d}"


def make_webdataset(root: Path, fp: Footage, clips: int) -> float:
    """``shards/shard-00000{0,1}.tar``: ``clips`` samples each, ``KEY.mp4`` (640 x 360, 250, 450
    or 150 frames in turn) beside ``KEY.json``."""
    (root / "shards").mkdir()
    total, key = 0.0, 0
    for s in range(2):
        with tarfile.open(root / "shards" / f"shard-{s:06d}.tar", "w") as tar:
            for _ in range(clips):
                clip = root / f"{key:06d}.mp4"
                total += encode(clip, fp.shot((250, 450, 150)[key % 3], (360, 640)))
                tar.add(clip, clip.name)
                meta = json.dumps({"key": f"{key:06d}", "caption": "a camera over a photograph"}).encode()
                info = tarfile.TarInfo(f"{key:06d}.json")
                info.size = len(meta)
                tar.addfile(info, io.BytesIO(meta))
                clip.unlink()
                key += 1
    return total


def make_phone(root: Path, fp: Footage, clips: int) -> float:
    """``phone/``: ``clips`` portrait clips at 30 fps of 300, 450 or 600 frames in turn, stored
    landscape (HD) with a display matrix of 90 degrees, ``.mp4`` and ``.mov`` in turn."""
    return sum(encode(root / "phone" / f"IMG_{4000 + i}{('.mp4', '.mov')[i % 2]}", fp.shot((300, 450, 600)[i % 3], fp.hd),
                      fps=30, rotation=90) for i in range(clips))


MAKERS = {"webvid": make_webvid, "openvid": make_openvid, "panda": make_panda, "webdataset": make_webdataset,
          "phone": make_phone}
LINE = re.compile(r"^(?P<path>\S.*?)\s+(?P<verdict>\d+ window\(s\)|unusable|ignored)\s+(?P<detail>.*)$")
SUMMARY = re.compile(r"^(\d+) usable video\(s\) of (\d+), (\d+) sample\(s\) per epoch", re.M)


def run_command(command: str, cwd: Path, env: Dict[str, str]) -> str:
    """Run a recipe's shell text in ``cwd``, ``v2v-serve`` being this checkout's
    ``python -m v2v_server.cli``; its stdout. Raises ``RuntimeError`` with its output when it fails."""
    argv = shlex.split(command)
    if argv[0] == "v2v-serve":
        argv = [sys.executable, "-m", "v2v_server.cli", *argv[1:]]
        p = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True)
    else:  # a shell step (a heredoc)
        p = subprocess.run(["bash", "-c", command.replace("python ", f"{shlex.quote(sys.executable)} ", 1)],
                           cwd=cwd, env=env, capture_output=True, text=True)
    # --check exits 2 when no entry is usable: a report all the same
    if p.returncode != 0 and not (argv[0] == sys.executable and p.returncode == 2 and SUMMARY.search(p.stdout)):
        raise RuntimeError(f"{command}: exit {p.returncode}\n{p.stdout}\n{p.stderr}")
    return p.stdout


def read_check(out: str) -> dict:
    """The figures of a ``--check`` report: entries, usable, samples, every line's ``[entry,
    verdict, detail]`` and those of the entries that give none."""
    summary = SUMMARY.search(out)
    if summary is None:
        raise ValueError(f"no --check summary line in:\n{out}")
    verdicts = [[m["path"], m["verdict"], m["detail"]] for m in map(LINE.match, out.splitlines()[1:])
                if m and not SUMMARY.match(m[0])]
    return {"entries": int(summary[2]), "usable": int(summary[1]), "samples": int(summary[3]),
            "skipped": [v for v in verdicts if v[1] in ("unusable", "ignored")], "verdicts": verdicts}


def recipe(name: str, clips: int) -> str:
    """The command of ``name``'s recipe for a corpus of ``clips`` clips (OpenVid's parts: a brace
    range up to the last part, ``LAST`` in :data:`RECIPES`; 185 for OpenVid-1M itself)."""
    return RECIPES[name].replace("LAST", str(clips - 1))


def run(clips: int, hd_height: int, only: Optional[List[str]] = None) -> dict:
    """Generate every corpus and run its recipe; the report (see the module's docstring)."""
    fp = Footage(hd_height)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep),
               "XDG_CACHE_HOME": str(Path(tmp, "cache"))}
        for name, make in MAKERS.items():
            if only and name not in only:
                continue
            root = Path(tmp, name)
            root.mkdir()
            footage_s = make(root, fp, clips)
            row = {"corpus": name, "command": recipe(name, clips)}
            row.update(read_check(run_command(row["command"], root, env)))
            row["footage_s"] = round(footage_s, 2)
            row["samples_per_clip_hour"] = round(row["samples"] / (footage_s / 3600), 1)
            rows.append(row)
    return {"clips": clips, "hd_height": hd_height, "recipes": rows}


def markdown(report: dict, command: str) -> str:
    """The docs table of ``report``."""
    out = [f"`{command}`:", "", "| corpus | entries | usable | samples per epoch | footage, min | samples per clip-hour |",
           "|---|---:|---:|---:|---:|---:|"]
    for r in report["recipes"]:
        out.append(f"| {r['corpus']} | {r['entries']} | {r['usable']} | {r['samples']} | {r['footage_s'] / 60:.1f} "
                   f"| {r['samples_per_clip_hour']:.0f} |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clips", type=int, default=3, help="size of each corpus (clips per folder, part, shard)")
    ap.add_argument("--hd-height", type=int, default=1080, help="rows of HD footage (16:9), upscaled")
    ap.add_argument("--only", nargs="*", choices=sorted(MAKERS), help="these corpora only")
    ap.add_argument("--json", type=Path, default=None, help="write the report here too")
    args = ap.parse_args(argv)
    report = run(args.clips, args.hd_height, args.only)
    report["command"] = "python -m bench.corpus_recipes " + " ".join(argv if argv is not None else sys.argv[1:])
    print(json.dumps(report, indent=2))
    print(markdown(report, report["command"]))
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

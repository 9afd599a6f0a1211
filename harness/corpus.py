"""A corpus of broken and awkward video files mixed among good ones (for fault tests and bench)."""
from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Dict

import numpy as np


def write_video(path: Path, n: int, w: int, h: int, codec: str = "mpeg4", pix_fmt: str = "yuv420p",
                vfr: bool = False, gray: bool = False) -> Path:
    """A synthetic clip of ``n`` frames: a bright bar sliding over a gradient."""
    import av
    from fractions import Fraction

    with av.open(str(path), "w") as c:
        s = c.add_stream(codec, rate=25)
        s.width, s.height, s.pix_fmt = w, h, pix_fmt
        if vfr:
            s.codec_context.time_base = Fraction(1, 1000)
        t = 0
        rng = np.random.default_rng(n + w)
        for i in range(n):
            img = np.tile(np.linspace(30, 200, w, dtype=np.uint8), (h, 1))
            x = (i * max(1, w // 50)) % w
            img[:, x:x + max(2, w // 20)] = 250
            if gray:
                frame = av.VideoFrame.from_ndarray(img, format="gray")
            else:
                frame = av.VideoFrame.from_ndarray(np.repeat(img[..., None], 3, axis=2), format="rgb24")
            if vfr:
                frame.pts = t
                frame.time_base = Fraction(1, 1000)
                t += int(rng.choice([20, 40, 80]))  # 12.5 to 50 fps
            for p in s.encode(frame):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    return path


def make_fault_corpus(root: Path, good_dir: Path, window: int) -> Dict[str, str]:
    """Fill ``root`` with the good clips of ``good_dir`` plus one file of each kind of trouble.

    ``window`` is the frames one sample spans. Returns {relative path: expectation}, where the
    expectation is "usable" or "skipped" (or "ignored" for entries that are no video at all).
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    exp: Dict[str, str] = {}
    for p in sorted(Path(good_dir).glob("*.mp4")):
        shutil.copy(p, root / p.name)
        exp[p.name] = "usable"
    bikes = (Path(good_dir) / "bikes.mp4").read_bytes()
    (root / "zero_length.mp4").write_bytes(b"")
    (root / "truncated.mp4").write_bytes(bikes[: len(bikes) // 3])
    (root / "random_bytes.mp4").write_bytes(np.random.default_rng(0).bytes(200_000))
    (root / "text_file.mp4").write_text("this is not a video\n" * 100)
    (root / "unsupported_codec.mp4").write_bytes(bikes.replace(b"avc1", b"zzzz").replace(b"avcC", b"zzzC"))
    exp.update({"zero_length.mp4": "skipped", "truncated.mp4": "skipped", "random_bytes.mp4": "skipped",
                "text_file.mp4": "skipped", "unsupported_codec.mp4": "skipped"})
    write_video(root / "one_frame.mp4", 1, 160, 120)
    write_video(root / "shorter_than_window.mp4", window - 1, 160, 120)
    write_video(root / "smaller_than_crop.mp4", window, 64, 48)
    write_video(root / "large_4k.mp4", window, 3840, 2160)
    write_video(root / "variable_rate.mkv", window, 320, 240, vfr=True)
    write_video(root / "grayscale.mkv", window, 320, 240, codec="ffv1", pix_fmt="gray", gray=True)
    write_video(root / "ten_bit.mkv", window, 320, 240, codec="ffv1", pix_fmt="yuv420p10le")
    exp.update({"one_frame.mp4": "skipped", "shorter_than_window.mp4": "skipped", "smaller_than_crop.mp4": "usable",
                "large_4k.mp4": "usable", "variable_rate.mkv": "usable", "grayscale.mkv": "usable",
                "ten_bit.mkv": "usable"})
    shutil.copy(Path(good_dir) / "bikes.mp4", root / "deleted_during_epoch.mp4")
    exp["deleted_during_epoch.mp4"] = "skipped"  # the caller deletes it after the server scanned
    os.symlink("symlink_loop.mp4", root / "symlink_loop.mp4")
    (root / "sub").mkdir()
    os.symlink("..", root / "sub" / "loop_dir")
    os.symlink(str((Path(good_dir) / "bikes.mp4").resolve()), root / "outside_root.mp4")
    (root / "notes.txt").write_text("metadata, not a video\n")
    (root / "thumbnail.jpg").write_bytes(b"\xff\xd8\xff\xe0" + bytes(100))
    exp.update({"symlink_loop.mp4": "ignored", "outside_root.mp4": "ignored", "notes.txt": "ignored",
                "thumbnail.jpg": "ignored"})
    return exp


def write_size_change_video(path: Path, first: int, second: int, size1=(320, 240), size2=(256, 192)) -> Path:
    """An MPEG-PS clip (``.mpg``) whose frame size changes after ``first`` frames: two
    MPEG-2 streams of different sizes, one after the other (``second`` frames of ``size2``).
    A decoder reads it as one stream of ``first + second - 1`` or so frames."""
    import tempfile

    path = Path(path)
    with tempfile.TemporaryDirectory() as d:
        a = write_video(Path(d) / "a.mpg", first, *size1, codec="mpeg2video")
        b = write_video(Path(d) / "b.mpg", second, *size2, codec="mpeg2video")
        path.write_bytes(a.read_bytes() + b.read_bytes())
    return path


#: OpenVid-1M's CSV header (OpenVid-1M.csv, OpenVidHD.csv).
OPENVID_HEADER = ["video", "caption", "aesthetic score", "motion score", "temporal consistency score",
                  "camera motion", "frame", "fps", "seconds"]


def write_openvid(root: Path, clips: Path) -> Dict[str, str]:
    """An OpenVid-1M-style download under ``root``: zip parts ``parts/OpenVid_part0.zip``
    (stored), ``OpenVid_part1.zip`` (deflated, its clip in a folder, as some of OpenVid's
    parts hold theirs) and ``OpenVid_part2.zip`` split into ``_partaa`` / ``_partab`` pieces;
    ``OpenVid.csv`` with OpenVid's header naming each clip by its bare file name as OpenVid's
    does, a quoted caption holding a comma, plus a row too short by its ``frame`` column, a row
    of motion score 0.1 and a row naming a clip in no part. Under ``root/ref``, the members as
    plain files in folders named like the parts (their sample ids). Returns member id -> clip.
    """
    import csv
    import zipfile

    layout = {"OpenVid_part0.zip/alpha_0.mp4": "bikes.mp4", "OpenVid_part0.zip/beta_3.mp4": "bigbuckbunny.mp4",
              "OpenVid_part1.zip/videos/gamma_1.mp4": "webvid_like_596x336.mp4",
              "OpenVid_part2.zip/delta_0.mp4": "bikes.mp4"}
    parts, ref = root / "parts", root / "ref"
    parts.mkdir(parents=True, exist_ok=True)
    for rel, clip in layout.items():
        (ref / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(clips / clip, ref / rel)
        part, name = rel.split("/", 1)
        method = zipfile.ZIP_DEFLATED if part == "OpenVid_part1.zip" else zipfile.ZIP_STORED
        with zipfile.ZipFile(parts / part, "a", method) as z:
            z.write(ref / rel, name)
    joined = parts / "OpenVid_part2.zip"
    data = joined.read_bytes()
    (parts / "OpenVid_part2_partaa").write_bytes(data[:len(data) // 2])
    (parts / "OpenVid_part2_partab").write_bytes(data[len(data) // 2:])
    joined.unlink()
    with open(root / "OpenVid.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(OPENVID_HEADER)
        for rel in layout:
            name = rel.rsplit("/", 1)[1]
            w.writerow([name, f"a scene, {name}", 5.1, 0.9, 0.99, "pan_right", 300, 25, 12.0])
        w.writerow(["short_9.mp4", "too short", 5.0, 0.9, 0.99, "static", 12, 25, 0.48])
        w.writerow(["calm_2.mp4", "barely moves", 5.0, 0.1, 0.99, "static", 300, 25, 12.0])
        w.writerow(["elsewhere_5.mp4", "in a part not downloaded", 5.0, 0.9, 0.99, "static", 300, 25, 12.0])
    return layout


def write_zip_parts(parts: Path, ref: Path, clips: Path) -> Dict[str, str]:
    """OpenVid-style zip parts of the clips in ``clips`` under ``parts``, and under ``ref`` the
    same members as plain files in folders named like the parts (so both give the same sample
    ids): ``p-0.zip`` stored (two clips and a ``readme.txt``), ``p-1.zip`` deflated (a clip in
    a subfolder), ``p-2.zip`` ZIP64 (written by Info-ZIP's ``zip -fz``), and ``p-3.zip`` stored
    and split into ``p-3_partaa``, ``_partab``, ``_partac`` as ``split -n 3`` cuts it (the
    joined file is not kept). Returns member id -> the clip it holds.

    Raises:
        FileNotFoundError: no ``zip`` command (Info-ZIP) on PATH.
    """
    import subprocess
    import zipfile

    layout = {"p-0.zip/000000.mp4": "bikes.mp4", "p-0.zip/000001.mp4": "webvid_like_596x336.mp4",
              "p-1.zip/clips/000000.mp4": "bigbuckbunny.mp4", "p-2.zip/000000.mp4": "bikes.mp4",
              "p-3.zip/000000.mp4": "webvid_like_596x336.mp4", "p-3.zip/000001.mp4": "bikes.mp4"}
    parts.mkdir(parents=True, exist_ok=True)
    for rel, clip in layout.items():
        (ref / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(clips / clip, ref / rel)
    with zipfile.ZipFile(parts / "p-0.zip", "w", zipfile.ZIP_STORED) as z:
        for name in ("000000.mp4", "000001.mp4"):
            z.write(ref / "p-0.zip" / name, name)
        z.writestr("readme.txt", "OpenVid-style part\n")
    with zipfile.ZipFile(parts / "p-1.zip", "w", zipfile.ZIP_DEFLATED) as z:
        z.write(ref / "p-1.zip/clips/000000.mp4", "clips/000000.mp4")
    subprocess.run(["zip", "-q", "-fz", "-0", str((parts / "p-2.zip").resolve()), "000000.mp4"],
                   cwd=ref / "p-2.zip", check=True)
    joined = parts / "p-3.zip"
    with zipfile.ZipFile(joined, "w", zipfile.ZIP_STORED) as z:
        for name in ("000000.mp4", "000001.mp4"):
            z.write(ref / "p-3.zip" / name, name)
    data = joined.read_bytes()
    cut = [0, len(data) // 3, 2 * len(data) // 3, len(data)]
    for i, suffix in enumerate(("aa", "ab", "ac")):
        (parts / f"p-3_part{suffix}").write_bytes(data[cut[i]:cut[i + 1]])
    joined.unlink()
    return layout


def write_scenes_video(path: Path, parts) -> Path:
    """An MPEG-PS clip (``.mpg``) of ``parts``, each ``(scene, frames, width, height)`` one MPEG-2
    stream after the other (a decoder reads them as one stream whose frame size changes where
    two parts differ). ``scene`` "a": a bright bar sliding right over a horizontal gradient; "b":
    a dark bar sliding left over a vertical one. Consecutive parts of one scene continue it
    (scaled to the part's size: no shot cut); a change of scene is a hard cut."""
    import tempfile

    import av

    path = Path(path)
    data, at = b"", {"a": 0, "b": 0}
    with tempfile.TemporaryDirectory() as d:
        for j, (scene, n, w, h) in enumerate(parts):
            part = Path(d) / f"{j}.mpg"
            with av.open(str(part), "w") as c:
                s = c.add_stream("mpeg2video", rate=25)
                s.width, s.height, s.pix_fmt = w, h, "yuv420p"
                for i in range(at[scene], at[scene] + n):
                    if scene == "a":
                        img = np.tile(np.linspace(30, 200, w, dtype=np.uint8), (h, 1))
                        x, lit = int((0.1 + 0.01 * i) * w), 250
                    else:
                        img = np.tile(np.linspace(220, 40, h, dtype=np.uint8)[:, None], (1, w))
                        x, lit = int((0.8 - 0.01 * i) * w), 10
                    img[:, x:x + max(2, w // 20)] = lit
                    for p in s.encode(av.VideoFrame.from_ndarray(np.repeat(img[..., None], 3, axis=2), format="rgb24")):
                        c.mux(p)
                for p in s.encode():
                    c.mux(p)
            at[scene] += n
            data += part.read_bytes()
    path.write_bytes(data)
    return path

"""What frame size costs a worker, and what scaling frames to the recipe (``frame_height``) buys:
``python -m bench.frame_scale --out docs``.

Sources: the first ``--frames`` frames of real footage (``--clip``, the bundled WebVid-sized
street clip by default), resized (OpenCV INTER_CUBIC, colour) to each of ``--sizes`` and
re-encoded with PyAV's libx264 (preset medium, yuv420p, 25 fps) at a bitrate usual for that
size (``BITRATES``). Every size holds the same scenes, so the rows differ by frame size only.
Upscaled footage has no detail above the original's, so it encodes (and decodes) more easily
than camera-native HD at the same bitrate: the HD rows are a lower bound of the cost.

Measured per source, in this process, rounds interleaved, medians:

* the decode bound: frames per CPU-second of PyAV, one thread, luma at full range
  (``decode.decode_luma``, what a worker's pass reads), and its ratio to the first size;
* decoding with ``frame_height`` (``--height``, 336 by default): frames per CPU-second of the
  same pass scaled, keeping the top ``--keep-top`` (the recipe's ``keep_top_fraction``, 0.54)
  of the scaled rows (``decode_luma(..., kept, height)``, what a worker's pass reads), and the
  scaling alone, CPU-ms per frame (``decode.scale_frame`` on decoded frames);
* against the whole frame (the way frames were scaled before ``scale_frame`` resized only the
  rows that feed the kept rows): the same two figures with the whole frame expanded and scaled
  and the kept rows cut afterwards (``decode_luma(..., None, height)``, ``scale_frame(g,
  height)[:kept]``), in the same rounds, and the ratios;
* cached bytes per hour of video: the bytes a ``raw`` frame-cache entry holds per frame (real
  entries, written through ``frames.video_read.read_video``: the kept 54 % of each frame), times
  25 fps x 3600 s, without and with ``frame_height``;
* decode threads per worker (``--threads``, 1 2 4) at the sizes of 720 rows and more
  (``--threads-from``): frames
  per CPU-second and per wall-second, ratios to one thread.
"""
from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
import time
from fractions import Fraction
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence, Tuple

from bench.speed import clip_path
from v2v_server.frames.frame_pass import DecodeSettings
from v2v_server.samples.recipe import SampleRecipe

#: libx264 bitrates (bits/s) by frame height: common upload bitrates for 25-30 fps SDR video.
BITRATES = {336: 1_000_000, 720: 5_000_000, 1080: 8_000_000}
SIZES = ((596, 336), (1280, 720), (1920, 1080))
FPS = 25


def bitrate(height: int) -> int:
    """The bitrate for a frame height: the nearest of ``BITRATES``'s heights scaled by area."""
    near = min(BITRATES, key=lambda h: abs(h - height))
    return max(50_000, int(BITRATES[near] * (height / near) ** 2))


def make_source(clip: Path, out: Path, size: Tuple[int, int], frames: int) -> Path:
    """``clip``'s first ``frames`` frames resized to ``size`` (W, H) and encoded to ``out`` with
    libx264 at :func:`bitrate`."""
    import av
    import cv2

    w, h = size
    with av.open(str(clip)) as src, av.open(str(out), "w") as dst:
        s = dst.add_stream("libx264", rate=FPS)
        s.width, s.height, s.pix_fmt = w, h, "yuv420p"
        s.bit_rate = bitrate(h)
        s.options = {"preset": "medium"}
        for i, fr in enumerate(src.decode(video=0)):
            if i == frames:
                break
            rgb = cv2.resize(fr.to_ndarray(format="rgb24"), (w, h), interpolation=cv2.INTER_CUBIC)
            frame = av.VideoFrame.from_ndarray(rgb, format="rgb24")
            frame.pts, frame.time_base = i, Fraction(1, FPS)
            for p in s.encode(frame):
                dst.mux(p)
        for p in s.encode():
            dst.mux(p)
    return out


def _rate(passes: Callable[[], int], min_cpu_s: float) -> Tuple[float, float]:
    """(frames per CPU-second, frames per wall-second) of ``passes()`` repeated until at least
    ``min_cpu_s`` CPU-seconds (all threads of this process) were spent."""
    n, c0, w0 = 0, time.process_time(), time.perf_counter()
    while True:
        n += passes()
        cpu = time.process_time() - c0
        if cpu >= min_cpu_s:
            return n / cpu, n / (time.perf_counter() - w0)


def _decode(path: Path, threads: int = 1, height: int = 0, keep: float = 1.0) -> int:
    """Frames of one pass over ``path``: luma at full range, scaled to ``height`` rows (0: not),
    the top ``keep`` of them kept (1.0: the whole frame scaled, as before only kept rows were)."""
    from v2v_server.frames.decode import decode_luma, open_video
    from v2v_server.frames.frame_pass import kept_rows

    c, s, _ = open_video(path, threads)
    rows = None if keep >= 1.0 else (lambda h: kept_rows(keep, h))
    return sum(1 for _ in decode_luma(c, s, rows, height))


def _scale_ms(path: Path, height: int, min_cpu_s: float, keep: float = 1.0, whole: bool = False) -> float:
    """CPU-ms per frame of ``scale_frame`` on the decoded full-range frames of ``path``, keeping
    the top ``keep`` of the scaled rows; ``whole``: the whole frame scaled, then those rows cut."""
    from v2v_server.frames.decode import iter_luma, scale_frame
    from v2v_server.frames.frame_pass import kept_rows

    frames = [g.copy() for g in iter_luma(path)]
    kept = kept_rows(keep, height)

    def one() -> int:
        for g in frames:
            if whole:
                scale_frame(g, height)[:kept]
            else:
                scale_frame(g, height, kept)
        return len(frames)
    return 1e3 / _rate(one, min_cpu_s)[0]


def entry_bytes_per_frame(path: Path, height: int, cache: Path) -> float:
    """Bytes per frame of the ``raw`` frame-cache entry a worker's pass writes for ``path`` (the
    default kept 54 %; ``frame_height`` = ``height``), read from the cache's own listing."""
    from v2v_server.frames.host_caches import HostCaches
    from v2v_server.frames.video_read import read_video, reraise
    from v2v_server.sources.local import LocalSource

    cfg = SampleRecipe(sequence_length=2, num_bins=2, crop_size=8, max_samples_per_video=1000,
                      frame_height=height)
    caches = HostCaches.open(str(cache), frame_cache_gb=64.0)
    fc = caches.frame_cache
    with read_video(LocalSource(path.parent), path.name, cfg.reads, caches, handler=reraise) as read:
        n = sum(1 for _ in read.frames)  # the read stores the entry of its whole pass, as a worker's does
    sizes = [size for _, size, _ in fc.disk.entries()]
    assert len(sizes) == 1, sizes
    return sizes[0] / n


def measure(clip: Path, sizes: Sequence[Tuple[int, int]], frames: int, height: int, threads: Sequence[int],
            rounds: int, min_cpu_s: float, threads_from: int = 720,
            keep: float = DecodeSettings.keep_top_fraction) -> dict:
    """The rows of the report (see the module docstring); medians over ``rounds`` interleaved rounds."""
    tmp = Path(tempfile.mkdtemp(prefix="v2v-fscale-"))
    try:
        t0 = time.perf_counter()
        srcs = {}
        for w, h in sizes:
            d = tmp / f"{w}x{h}"
            d.mkdir()
            srcs[(w, h)] = make_source(clip, d / f"{w}x{h}.mp4", (w, h), frames)
        encode_s = time.perf_counter() - t0
        runs: Dict[str, List[float]] = {}
        hd = [s for s in sizes if s[1] >= threads_from]
        for _ in range(rounds):
            for (w, h), p in srcs.items():
                runs.setdefault(f"decode {w}x{h}", []).append(_rate(lambda: _decode(p), min_cpu_s)[0])
                runs.setdefault(f"decode+scale {w}x{h}", []).append(
                    _rate(lambda: _decode(p, 1, height, keep), min_cpu_s)[0])
                runs.setdefault(f"decode+scale whole {w}x{h}", []).append(
                    _rate(lambda: _decode(p, 1, height), min_cpu_s)[0])
                runs.setdefault(f"scale_ms {w}x{h}", []).append(_scale_ms(p, height, min_cpu_s / 2, keep))
                runs.setdefault(f"scale_ms whole {w}x{h}", []).append(
                    _scale_ms(p, height, min_cpu_s / 2, keep, whole=True))
            for (w, h) in hd:
                for t in threads:
                    cpu, wall = _rate(lambda: _decode(srcs[(w, h)], t), min_cpu_s)
                    runs.setdefault(f"threads {w}x{h} {t} cpu", []).append(cpu)
                    runs.setdefault(f"threads {w}x{h} {t} wall", []).append(wall)
        med = {k: statistics.median(v) for k, v in runs.items()}
        rows = []
        for (w, h), p in srcs.items():
            cache_plain = entry_bytes_per_frame(p, 0, tmp / f"cache-{w}x{h}-0")
            cache_scaled = entry_bytes_per_frame(p, height, tmp / f"cache-{w}x{h}-{height}")
            rows.append({"size": f"{w}x{h}", "width": w, "height": h, "bitrate": bitrate(h),
                         "file_bytes": p.stat().st_size, "frames": frames,
                         "decode_fps_cpu": med[f"decode {w}x{h}"],
                         "decode_scaled_fps_cpu": med[f"decode+scale {w}x{h}"],
                         "decode_scaled_whole_fps_cpu": med[f"decode+scale whole {w}x{h}"],
                         "scale_ms": med[f"scale_ms {w}x{h}"], "scale_whole_ms": med[f"scale_ms whole {w}x{h}"],
                         "cache_bytes_per_frame": cache_plain, "cache_bytes_per_frame_scaled": cache_scaled})
        thread_rows = [{"size": f"{w}x{h}", "threads": t, "fps_cpu": med[f"threads {w}x{h} {t} cpu"],
                        "fps_wall": med[f"threads {w}x{h} {t} wall"]} for (w, h) in hd for t in threads]
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {"clip": clip.name, "frames": frames, "height": height, "keep": keep, "rounds": rounds, "min_cpu_s": min_cpu_s,
            "encode_s": encode_s, "rows": rows, "threads": thread_rows}


def markdown(r: dict, command: str) -> str:
    """The report: how the sources were made, the scale table, the kept rows against the whole
    frame, the threads table."""
    import os

    hgt, keep = r["height"], r["keep"]
    base = r["rows"][0]
    hour = FPS * 3600
    lines = [
        "# Frame scale: what frame size costs a worker, and `frame_height`",
        "",
        f"`{command}` (`bench/frame_scale.py`), on this project's machine: {os.cpu_count()} cores, shared with "
        "other work while it ran. Every ratio is to a row of the same run; "
        f"{r['rounds']} interleaved rounds, medians.",
        "",
        f"Sources: the first {r['frames']} frames of `{r['clip']}` (real street footage, 596 x 336), resized with "
        "OpenCV INTER_CUBIC and re-encoded with PyAV's libx264 (preset medium, yuv420p, 25 fps) at "
        + ", ".join(f"{row['bitrate'] / 1e6:g} Mbit/s at {row['size']}" for row in r["rows"])
        + ". The 720 and 1080 rows are upscaled footage: it holds no detail above the original's, so it decodes "
        "more easily than camera-native HD at the same bitrate; read those rows as a lower bound of the cost.",
        "",
        f"| source | decode bound, frames/CPU-s | vs {base['size']} | with `frame_height: {hgt}`, frames/CPU-s | "
        f"scaling to {hgt} rows, CPU-ms/frame | share of a decoded frame's CPU | cached bytes per hour, raw | "
        f"with `frame_height: {hgt}` |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in r["rows"]:
        dec = row["decode_fps_cpu"]
        scaled = row["height"] != hgt
        share = row["scale_ms"] * dec / 1e3
        lines.append(
            f"| {row['size']} | {dec:,.0f} | {dec / base['decode_fps_cpu']:.2f}x | {row['decode_scaled_fps_cpu']:,.0f} | "
            + (f"{row['scale_ms']:.2f} | {share:.0%} | " if scaled else "none (already that height) | - | ")
            + f"{row['cache_bytes_per_frame'] * hour / 1e9:.1f} GB | {row['cache_bytes_per_frame_scaled'] * hour / 1e9:.1f} GB |")
    lines += [
        "",
        "Decode bound: PyAV, one thread, luma at full range (`decode.decode_luma`, the pass a worker reads). "
        f"With `frame_height`: the same pass scaled, the top {keep:g} of the scaled rows kept (`keep_top_fraction` "
        f"{keep:g}). Scaling: `decode.scale_frame` (OpenCV INTER_AREA on full-range luma, the source rows that feed "
        f"the kept rows only) alone, on decoded frames; "
        f"its share is its CPU over one frame's decoding. Cached bytes: a real `raw` entry written by a worker's "
        f"pass (the default `keep_top_fraction` 0.54: the kept rows of each frame), per frame, times {FPS} fps x 3600 s.",
        "",
    ]
    lines += _kept_rows_section(r)
    top = r["rows"][-1]
    if top["height"] > hgt:
        lines += [
            f"At {top['size']}, `frame_height: {hgt}` caches {top['cache_bytes_per_frame'] / top['cache_bytes_per_frame_scaled']:.1f}x "
            f"fewer bytes per frame and makes a worker's decoding pass {top['decode_fps_cpu'] / top['decode_scaled_fps_cpu']:.2f}x "
            f"as costly per frame (decoding and scaling against decoding alone); its frames then have the "
            f"{hgt}-row field of view a {base['size']} source gives every crop.",
            "",
        ]
    return "\n".join(lines + _threads_section(r))


def _kept_rows_section(r: dict) -> List[str]:
    """The report's lines comparing scaling the kept rows only with scaling the whole frame
    (none when nothing is scaled or every row is kept)."""
    hgt, keep = r["height"], r["keep"]
    lines: List[str] = []
    scaled = [row for row in r["rows"] if row["height"] != hgt]
    if scaled and keep < 1.0:
        lines += [
            f"Scaling only the kept rows against scaling the whole frame and cutting the kept rows afterwards "
            f"(`keep_top_fraction` {keep:g}; the frames are equal value for value, `tests/test_frame_scale.py`), "
            "same rounds:",
            "",
            "| source | scaling, whole frame, CPU-ms/frame | kept rows only | CPU vs whole frame | "
            "decode + scale, whole frame, frames/CPU-s | kept rows only | speed vs whole frame |",
            "|---|---:|---:|---:|---:|---:|---:|",
        ]
        for row in scaled:
            lines.append(
                f"| {row['size']} | {row['scale_whole_ms']:.2f} | {row['scale_ms']:.2f} | "
                f"{row['scale_ms'] / row['scale_whole_ms']:.2f}x | {row['decode_scaled_whole_fps_cpu']:,.0f} | "
                f"{row['decode_scaled_fps_cpu']:,.0f} | "
                f"{row['decode_scaled_fps_cpu'] / row['decode_scaled_whole_fps_cpu']:.2f}x |")
        lines += ["", "With `keep_top_fraction` 1.0 (corpora without WebVid's watermark) every row is kept and "
                  "both ways do the same work.", ""]
    return lines


def _threads_section(r: dict) -> List[str]:
    """The report's lines on decode threads per worker (none when they were not measured)."""
    import os

    lines: List[str] = []
    if r["threads"]:
        lines += [
            f"Decode threads per worker (`decode_threads`), the same sources: frames per CPU-second (all threads of "
            f"the process) and per wall-second. This machine has {os.cpu_count()} cores, shared: a wall-clock gain "
            "here is at most 2x, and on a host whose cores are all busy with workers, only frames per CPU-second "
            "count.",
            "",
            "| source | decode_threads | frames/CPU-s | vs 1 thread | frames/wall-s | vs 1 thread |",
            "|---|---:|---:|---:|---:|---:|",
        ]
        one = {t["size"]: t for t in r["threads"] if t["threads"] == 1}
        for t in r["threads"]:
            o = one[t["size"]]
            lines.append(f"| {t['size']} | {t['threads']} | {t['fps_cpu']:,.0f} | {t['fps_cpu'] / o['fps_cpu']:.2f}x | "
                         f"{t['fps_wall']:,.0f} | {t['fps_wall'] / o['fps_wall']:.2f}x |")
        lines.append("")
        for size, o in one.items():
            best = max((t for t in r["threads"] if t["size"] == size), key=lambda t: t["fps_wall"])
            lines.append(f"At {size} the most frames per wall-second came with decode_threads {best['threads']} "
                         f"({best['fps_wall'] / o['fps_wall']:.2f}x one thread, at {best['fps_cpu'] / o['fps_cpu']:.2f}x its "
                         "frames per CPU-second).")
        lines += ["", "More decode threads pay only where a worker's cores would otherwise idle; with one worker "
                  "per core (`workers` = cores), keep `decode_threads: 1` and add workers.", ""]
    return lines


def _size(s: str) -> Tuple[int, int]:
    w, h = s.lower().split("x")
    return int(w), int(h)


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clip", default="webvid_like_596x336.mp4")
    ap.add_argument("--sizes", default=",".join(f"{w}x{h}" for w, h in SIZES), help="W x H of each source, comma list")
    ap.add_argument("--frames", type=int, default=150, help="frames per source")
    ap.add_argument("--height", type=int, default=336, help="the frame_height measured")
    ap.add_argument("--keep-top", type=float, default=DecodeSettings.keep_top_fraction,
                    help="the keep_top_fraction measured (default the recipe's)")
    ap.add_argument("--threads", default="1,2,4", help="decode_threads measured at 720 rows and more")
    ap.add_argument("--threads-from", type=int, default=720, help="measure decode_threads at sizes of this many rows and more")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--min-cpu-s", type=float, default=1.0, help="CPU-seconds per measurement at least")
    ap.add_argument("--out", help="write frame_scale.md and frame_scale.json to this folder")
    a = ap.parse_args(argv)
    r = measure(clip_path(a.clip), [_size(s) for s in a.sizes.split(",")], a.frames, a.height,
                [int(t) for t in a.threads.split(",")], a.rounds, a.min_cpu_s, a.threads_from, a.keep_top)
    args = sys.argv[1:] if argv is None else list(argv)
    text = markdown(r, " ".join(["python -m bench.frame_scale", *args]))
    print(text)
    if a.out:
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "frame_scale.md").write_text(text)
        (out / "frame_scale.json").write_text(json.dumps(r, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

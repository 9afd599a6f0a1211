"""What reading a video from inside a zip part costs, against the same clip as a plain file, in
one run.

``python -m bench.zip_members [--repeat 5] [--out DIR]`` puts each bundled clip into a zip part
twice (stored, and deflated at zlib's default level) and decodes every frame (``open_video``,
``decode_codes``: what the sample pass reads) of:

* ``file`` (baseline): the clip as a file of its own;
* ``stored``: the stored member, read in place by offset (``LocalSource.open``);
* ``deflated``: the deflated member, through zipfile's streaming reader.

Each clip is read as it is (its ``moov`` atom after the media data, as the bundled clips and
most encoders' default output have it: FFmpeg reads the end first, then seeks back) and remuxed
with ``movflags=faststart`` (``moov`` first). Per mode: CPU seconds per pass (best of
``--repeat``; the machine is shared, the best pass is the least disturbed), its ratio to the
file's, and the compressed bytes the reader took from the archive per byte of the member
(a seek backwards restarts decompression from the member's start), and the CPU milliseconds
to read the member whole without decoding (what the archive itself costs). Writes ``zip_members.md``
and ``zip_members.json`` under ``--out`` when given.
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
import zipfile
from pathlib import Path

from v2v_server.frames.decode import decode_codes, open_video
from v2v_server.sources.local import LocalSource
from v2v_server.sources.shards import open_member, zip_members

CLIPS = ("bikes.mp4", "webvid_like_596x336.mp4", "bigbuckbunny.mp4")
MODES = ("file", "stored", "deflated")


def faststart(src: Path, dst: Path) -> None:
    """``src`` remuxed (no re-encoding) with its ``moov`` atom first."""
    import av

    with av.open(str(src)) as i, av.open(str(dst), "w", options={"movflags": "faststart"}) as o:
        s = i.streams.video[0]
        out = o.add_stream_from_template(s)
        for pkt in i.demux(s):
            if pkt.dts is not None:
                pkt.stream = out
                o.mux(pkt)


class Counted:
    """A binary file that counts the bytes read from it."""

    def __init__(self, f):
        self.f, self.read_bytes = f, 0

    def read(self, n=-1):
        b = self.f.read(n)
        self.read_bytes += len(b)
        return b

    def __getattr__(self, k):
        return getattr(self.f, k)


def _decode(f) -> int:
    c, s, _ = open_video(f)
    try:
        return sum(1 for _ in decode_codes(c, s))
    finally:
        c.close()


def _pass(source: LocalSource, rel: str) -> float:
    t = time.process_time()
    with source.open(rel) as f:
        _decode(f)
    return time.process_time() - t


def _read_s(source: LocalSource, rel: str) -> float:
    """CPU seconds to read the member ``rel`` whole, front to back, without decoding."""
    t = time.process_time()
    with source.open(rel) as f:
        while f.read(1 << 20):
            pass
    return time.process_time() - t


def _read_ratio(part: Path, name: str) -> float:
    """Bytes taken from the archive per byte of the member while it is decoded."""
    with open(part, "rb") as raw:
        entry = zip_members(raw).members[name]
        f = Counted(raw)
        _decode(open_member(f, name, entry))
    return f.read_bytes / entry.compressed


def measure(root: Path, work: Path, repeat: int, clips=CLIPS) -> list:
    rows = []
    for clip in clips:
        for layout in ("moov last", "moov first"):
            name = clip if layout == "moov last" else f"fast_{clip}"
            src = work / name
            if layout == "moov last":
                src.write_bytes((root / clip).read_bytes())
            else:
                faststart(root / clip, src)
            for mode, method in (("stored", zipfile.ZIP_STORED), ("deflated", zipfile.ZIP_DEFLATED)):
                with zipfile.ZipFile(work / f"{mode}.zip", "a", method) as z:
                    z.write(src, name)
            time.sleep(0.1)  # past the racy window: the parts' indexes are kept
            source = LocalSource(work)
            rels = {"file": name, "stored": f"stored.zip/{name}", "deflated": f"deflated.zip/{name}"}
            best = {m: min(_pass(source, rels[m]) for _ in range(repeat)) for m in MODES}
            with zipfile.ZipFile(work / "deflated.zip") as z:
                info = z.getinfo(name)
            rows.append({"clip": clip, "layout": layout, "bytes": src.stat().st_size,
                         "deflated_bytes": info.compress_size, "frames": _decode(src),
                         **{f"{m}_cpu_s": best[m] for m in MODES},
                         **{f"{m}_ratio": best[m] / best["file"] for m in MODES[1:]},
                         **{f"{m}_read_ms": 1e3 * min(_read_s(source, rels[m]) for _ in range(repeat)) for m in MODES[1:]},
                         "stored_read_per_byte": _read_ratio(work / "stored.zip", name),
                         "deflated_read_per_byte": _read_ratio(work / "deflated.zip", name)})
    return rows


def report(rows: list, command: str) -> str:
    lines = [f"`{command}`", "",
             "| clip | layout | frames | MiB | deflated MiB | file, CPU s | stored | ratio | deflated | ratio | "
             "bytes read per member byte: stored | deflated | read whole, ms: stored | deflated |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['clip']} | {r['layout']} | {r['frames']} | {r['bytes'] / 2**20:.2f} | "
                     f"{r['deflated_bytes'] / 2**20:.2f} | {r['file_cpu_s']:.3f} | {r['stored_cpu_s']:.3f} | "
                     f"{r['stored_ratio']:.2f} | {r['deflated_cpu_s']:.3f} | {r['deflated_ratio']:.2f} | "
                     f"{r['stored_read_per_byte']:.2f} | {r['deflated_read_per_byte']:.2f} | "
                     f"{r['stored_read_ms']:.1f} | {r['deflated_read_ms']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--out", default=None, help="folder for zip_members.md and .json")
    p.add_argument("--clips", default=",".join(CLIPS), help="bundled clips to measure, comma-separated")
    args = p.parse_args(argv)
    root = Path(__file__).resolve().parents[1] / "v2v_server" / "sample_videos"
    with tempfile.TemporaryDirectory() as tmp:
        rows = measure(root, Path(tmp), args.repeat, args.clips.split(","))
    command = "python -m bench.zip_members" + (f" --repeat {args.repeat}" if args.repeat != 5 else "") + (
        f" --clips {args.clips}" if args.clips != ",".join(CLIPS) else "")
    text = report(rows, command)
    print(text)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "zip_members.md").write_text(text)
        (out / "zip_members.json").write_text(json.dumps({"command": command, "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Loading and filtering a corpus's metadata table: DuckDB, polars and pyarrow on a generated
table with OpenVid-1M's header (``video,caption,aesthetic score,motion score,temporal consistency
score,camera motion,frame,fps,seconds``), as CSV and as Parquet.

Each engine runs in a fresh process (its import counted, its peak RSS its own), in rounds over
all engines (so that each meets a shared machine's load alike; best and median reported), and gives the list
of paths of the rows that pass ``frame >= 201 and "motion score" > 0.5``, as ``--video-list``
needs them. DuckDB and polars take that filter as SQL text (what a user writes); pyarrow has no
expression parser, so its filter is built in code (the lower bound of what a parser would cost).
``v2v`` is ``video_list.read_video_list`` end to end (DuckDB with the table loaded and file access
off, the path column, the rows too short for a 201-frame window skipped: every row the filter
keeps has ``frame >= 201``, so it keeps as many).

    python -m bench.video_tables --rows 1000000 --out docs
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HEADER = ["video", "caption", "aesthetic score", "motion score", "temporal consistency score", "camera motion",
          "frame", "fps", "seconds"]
FILTER = 'frame >= 201 and "motion score" > 0.5'
ENGINES = ("duckdb", "polars", "pyarrow", "v2v")


def make_table(path: Path, rows: int, seed: int = 0) -> None:
    """A CSV of ``rows`` rows with OpenVid's header: captions quoted, holding commas and quotes."""
    import numpy as np
    import pyarrow as pa
    import pyarrow.csv as pacsv

    rng = np.random.default_rng(seed)
    fps = rng.choice([24.0, 25.0, 29.97, 30.0, 60.0], rows)
    frame = rng.integers(30, 900, rows)
    words = np.array(["a", "man", "walks", "on", "the", "beach,", "\"slowly\"", "camera", "pans", "over", "city"])
    caps = [" ".join(words[rng.integers(0, len(words), 12)]) for _ in range(rows)]
    table = pa.table({
        "video": [f"clip_{i:07d}.mp4" for i in range(rows)], "caption": caps,
        "aesthetic score": rng.uniform(3, 7, rows).round(3), "motion score": rng.uniform(0, 2, rows).round(3),
        "temporal consistency score": rng.uniform(0.9, 1, rows).round(3),
        "camera motion": rng.choice(["static", "pan_left", "zoom_in", "tilt_up"], rows),
        "frame": frame, "fps": fps, "seconds": (frame / fps).round(2)})
    pacsv.write_csv(table, path, pacsv.WriteOptions(quoting_style="needed"))
    import pyarrow.parquet as pq

    pq.write_table(table, path.with_suffix(".parquet"))


CHILD = r'''
import sys, time
t0 = time.perf_counter()
engine, path = sys.argv[1], sys.argv[2]
csv = path.endswith(".csv")
if engine == "v2v":  # read_video_list end to end: DuckDB, the filter, the path column
    from v2v_server.sources.video_list import read_video_list
    from v2v_server.sources.video_tables import TableSettings
    paths = read_video_list(path, TableSettings(None, FILTER)).videos
elif engine == "duckdb":
    import duckdb
    con = duckdb.connect()
    con.execute("SET enable_progress_bar = false")
    src = f"read_csv('{path}', header=true)" if csv else f"read_parquet('{path}')"
    paths = [r[0] for r in con.execute(f"SELECT video FROM {src} WHERE {FILTER}").fetchall()]
elif engine == "polars":
    import polars as pl
    df = pl.read_csv(path) if csv else pl.read_parquet(path)
    paths = df.filter(pl.sql_expr(FILTER))["video"].to_list()
else:
    import pyarrow.compute as pc
    if csv:
        import pyarrow.csv as pacsv
        t = pacsv.read_csv(path)
    else:
        import pyarrow.parquet as pq
        t = pq.read_table(path)
    t = t.filter((pc.field("frame") >= 201) & (pc.field("motion score") > 0.5))
    paths = t["video"].to_pylist()
s = time.perf_counter() - t0
hwm = next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmHWM"))  # resets at exec
print(len(paths), round(s, 3), hwm // 1024)
'''


def run_once(engine: str, path: Path) -> dict:
    """One fresh process: seconds from start (imports included) to the list of paths, peak RSS
    in MiB, and the rows kept."""
    out = subprocess.run([sys.executable, "-c", f"FILTER = {FILTER!r}\n" + CHILD, engine, str(path)],
                         capture_output=True, text=True, check=True).stdout.splitlines()[-1].split()
    return {"kept": int(out[0]), "seconds": float(out[1]), "rss_mib": int(out[2])}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--rows", type=int, default=1_000_000)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", help="folder for video_tables.json")
    a = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        csv = Path(tmp) / "openvid.csv"
        t0 = time.perf_counter()
        make_table(csv, a.rows)
        print(f"generated {a.rows} rows in {time.perf_counter() - t0:.1f} s: CSV {csv.stat().st_size / 2**20:.0f} MiB, "
              f"Parquet {csv.with_suffix('.parquet').stat().st_size / 2**20:.0f} MiB", flush=True)
        runs = {(fmt, e): [] for fmt in ("csv", "parquet") for e in ENGINES}
        for _ in range(a.repeats):  # rounds over every engine: each meets the shared machine's load alike
            for fmt, engine in runs:
                runs[fmt, engine].append(run_once(engine, csv.with_suffix("." + fmt)))
        results = []
        for (fmt, engine), got in runs.items():
            secs = sorted(g["seconds"] for g in got)
            r = {"engine": engine, "format": fmt, "kept": got[0]["kept"], "best_s": secs[0],
                 "median_s": secs[len(secs) // 2], "rss_mib": max(g["rss_mib"] for g in got)}
            results.append(r)
            print(f"{engine:<8} {fmt:<8} best {r['best_s']:6.2f} s  median {r['median_s']:6.2f} s  "
                  f"{r['rss_mib']:5d} MiB  kept {r['kept']}", flush=True)
    if len({g["kept"] for got in runs.values() for g in got}) != 1:
        raise SystemExit(f"engines disagree on the rows kept: {results}")
    if a.out:
        Path(a.out, "video_tables.json").write_text(json.dumps({"rows": a.rows, "filter": FILTER,
                                                                  "results": results}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

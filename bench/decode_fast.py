"""Decoder shortcuts as a speed/accuracy trade: ``python -m bench.decode_fast``.

Each ``decode_fast`` setting (``v2v_server.frames.decode.DECODE_FAST``: FFmpeg's H.264 decoder skipping
its deblocking filter on no frames, non-reference frames, B-frames or every frame) is measured
against full decoding on

* the bundled clips (``v2v_server/sample_videos``, held-out style), and
* a corpus of H.264 files encoded here with PyAV's libx264 from the bundled clips' first
  ``--frames`` frames, one per combination of CRF (18, 23, 28, 35), GOP (12, 250), B-frames
  (0, 3) and profile (baseline: no B-frames; main; high), cycling over the three sources.

For each setting: decoding speed (luma frames per CPU-second, one thread, best of
``--rounds``), and the samples' error against full decoding with the same recipe, seed,
sensor parameters and noise (a short recipe, L = 8, 128 x 128 crops): voxels as normalised L1
(``sum |v - v_full| / sum |v_full|``), frames as PSNR (dB, over all samples), flow as mean
end-point error (px). For scale, the same normalised L1 between voxels simulated with V2V's
own noise at sigma = 0.03 and without noise (decoded in full), per file: a setting whose voxel
error stays under it changes the training data less than the simulator's noise does ("files
over their noise" counts the files where it does not).

``--json PATH`` keeps every file's numbers; ``--plot PATH`` draws the trade (matplotlib, the
``bench`` extra): decode speed-up against voxel error per setting, and each file's voxel
error against its own noise level.
"""
from __future__ import annotations

import argparse
import itertools
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CLIPS = ROOT / "v2v_server" / "sample_videos"
SETTINGS = ("off", "noref", "bidir", "all")


def make_corpus(out: Path, frames: int) -> list:
    """Encode the corpus into ``out``; returns the file names."""
    import av

    from v2v_server.frames.decode import iter_luma

    sources = []
    for clip in sorted(CLIPS.glob("*.mp4")):
        it = iter_luma(clip)
        f = [g for _, g in zip(range(frames), it)]
        it.close()
        h, w = (f[0].shape[0] // 2) * 2, (f[0].shape[1] // 2) * 2
        sources.append((clip.stem, np.stack([x[:h, :w] for x in f])))
    names = []
    combos = [(crf, gop, bf, prof) for crf, gop, bf, prof in itertools.product((18, 23, 28, 35), (12, 250), (0, 3),
                                                                                ("baseline", "main", "high"))
              if not (prof == "baseline" and bf)]
    for k, (crf, gop, bf, prof) in enumerate(combos):
        stem, src = sources[k % len(sources)]
        name = f"{stem}_crf{crf}_g{gop}_b{bf}_{prof}.mp4"
        c = av.open(str(out / name), "w")
        s = c.add_stream("libx264", rate=25)
        s.width, s.height, s.pix_fmt = src.shape[2], src.shape[1], "yuv420p"
        s.options = {"crf": str(crf), "g": str(gop), "bf": str(bf), "profile": prof, "preset": "veryfast"}
        for g in src:
            yuv = np.full((g.shape[0] * 3 // 2, g.shape[1]), 128, np.uint8)
            yuv[:g.shape[0]] = g
            for p in s.encode(av.VideoFrame.from_ndarray(yuv, format="yuv420p")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
        c.close()
        names.append(name)
    return names


def decode_speed(path: Path, fast: str) -> float:
    """Luma frames per CPU-second of decoding ``path`` with ``fast`` (one thread)."""
    from v2v_server.frames.decode import decode_luma, open_video

    container, stream, _ = open_video(path, 1, fast)
    t0, n = time.process_time(), 0
    for _ in decode_luma(container, stream):
        n += 1
    return n / max(time.process_time() - t0, 1e-9)


def has_b_frames(path: Path) -> bool:
    """Whether ``path`` has B-frames (what ``noref`` and ``bidir`` can skip work on)."""
    import av

    with av.open(str(path)) as c:
        return any(f.pict_type == av.video.frame.PictureType.B for f in c.decode(video=0))


def samples(root: Path, name: str, fast: str, noise=None) -> dict:
    from v2v_server.ops.config import ServeConfig
    from v2v_server.samples.make import video_samples
    from v2v_server.sources.local import LocalSource
    from v2v_wire.outputs import DEFAULT_OUTPUTS

    kw = {} if noise is None else {"ranges": {"noise_std": [noise, noise], "hot_pixel_fraction": [0.0, 0.0]}}
    if noise is not None or fast == "ref":
        kw.setdefault("ranges", {"noise_std": [0.0, 0.0], "hot_pixel_fraction": [0.0, 0.0]})
    cfg = ServeConfig(shot_cuts="off", sequence_length=8, crop_size=128, keep_top_fraction=1.0, max_samples_per_video=2,
                      decode_fast="off" if fast == "ref" else fast, **kw)
    return {sid: a for sid, a, _ in video_samples(cfg, LocalSource(root), name, 0, DEFAULT_OUTPUTS)}


def errors(ref: dict, got: dict) -> dict:
    vl1 = sum(np.abs(got[s]["voxels"].astype(np.int64) - ref[s]["voxels"]).sum() for s in ref)
    vref = sum(np.abs(ref[s]["voxels"].astype(np.int64)).sum() for s in ref)
    se = np.mean([np.mean((got[s]["frames"].astype(float) - ref[s]["frames"]) ** 2) for s in ref])
    epe = np.mean([np.linalg.norm(got[s]["flow"].astype(np.float32) - ref[s]["flow"].astype(np.float32), axis=1).mean()
                   for s in ref])
    return {"voxel_nl1": vl1 / max(vref, 1), "psnr": 10 * np.log10(255 ** 2 / se) if se > 0 else float("inf"),
            "epe": float(epe)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=90, help="frames per corpus file")
    p.add_argument("--rounds", type=int, default=5, help="decoding speed: best of this many rounds per file")
    p.add_argument("--json", help="write every file's numbers here")
    p.add_argument("--plot", help="draw the trade into this image (PNG)")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="v2v-decode-fast-") as d:
        corpus = Path(d)
        names = make_corpus(corpus, args.frames)
        files = [(CLIPS, c.name) for c in sorted(CLIPS.glob("*.mp4"))] + [(corpus, n) for n in names]
        # per file, best of the rounds; each round decodes every file once per setting, the
        # settings in a rotating order, so a change of the shared machine's speed hits them alike
        fps = {s: [0.0] * len(files) for s in SETTINGS}
        for r in range(args.rounds):
            for i, (root, name) in enumerate(files):
                for k in range(len(SETTINGS)):
                    s = SETTINGS[(k + r + i) % len(SETTINGS)]
                    fps[s][i] = max(fps[s][i], decode_speed(root / name, s))
        speed = {s: float(np.mean(v)) for s, v in fps.items()}
        bframes = [has_b_frames(root / name) for root, name in files]
        rows = {s: [] for s in SETTINGS[1:]}
        noise = []
        for root, name in files:
            full = samples(root, name, "off")
            if not full:
                continue
            quiet, noisy = samples(root, name, "ref"), samples(root, name, "off", noise=0.03)
            noise.append(errors(quiet, noisy)["voxel_nl1"])
            i = files.index((root, name))
            for s in SETTINGS[1:]:
                rows[s].append(dict(errors(full, samples(root, name, s)), noise=noise[-1], file=name,
                                    speedup=fps[s][i] / fps["off"][i], b_frames=bframes[i]))
    print(f"{len(files)} files ({len(names)} encoded here, 3 bundled), {args.frames} frames each for the encoded ones\n")
    nb = sum(r["b_frames"] for r in rows[SETTINGS[1]])
    print(f"| decode_fast | decode frames/CPU-s | vs off | vs off, the {nb} files with B-frames | voxel nL1 mean | "
          "voxel nL1 max | files over their noise | frames PSNR dB (min) | flow EPE px (mean) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    print(f"| off | {speed['off']:.0f} | 1.00x | 1.00x | 0 | 0 | 0 | inf | 0 |")
    for s in SETTINGS[1:]:
        r = rows[s]
        v = [x["voxel_nl1"] for x in r]
        over = sum(x["voxel_nl1"] > x["noise"] for x in r)
        withb = np.mean([x["speedup"] for x in r if x["b_frames"]])
        print(f"| {s} | {speed[s]:.0f} | {speed[s] / speed['off']:.2f}x | {withb:.2f}x | {np.mean(v):.4f} | {np.max(v):.4f} | "
              f"{over} of {len(r)} | {min(x['psnr'] for x in r):.1f} | {np.mean([x['epe'] for x in r]):.3f} |")
    print(f"\nV2V's own noise at sigma = 0.03 against none, full decoding: voxel nL1 mean {np.mean(noise):.4f}, "
          f"min {np.min(noise):.4f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"frames": args.frames, "decode_fps": speed, "files": rows}, indent=1))
    if args.plot:
        plot(speed, rows, args.plot)
    return 0


def plot(speed: dict, rows: dict, path: str) -> None:
    """Left: decode speed-up against voxel error, one point per setting (mean; bar from the
    best to the worst file; hollow: the speed-up over the files with B-frames only) over the
    band of V2V's own sigma-0.03 noise. Right: each file's
    voxel error against its own noise level (under the diagonal: less than the noise)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11.5, 4))
    noise = [x["noise"] for x in rows[SETTINGS[1]]]
    ax.axhspan(min(noise), max(noise), color="0.9", label="V2V noise, sigma 0.03 (per file)")
    ax.plot([1.0], [0.0], "ko")
    ax.annotate("off", (1.0, 0.0), textcoords="offset points", xytext=(6, 4))
    for s in SETTINGS[1:]:
        v = np.array([x["voxel_nl1"] for x in rows[s]])
        x = speed[s] / speed["off"]
        bar = ax.errorbar([x], [v.mean()], yerr=[[v.mean() - v.min()], [v.max() - v.mean()]], fmt="o", capsize=3)
        xb = float(np.mean([r["speedup"] for r in rows[s] if r["b_frames"]]))
        ax.plot([xb], [v.mean()], "o", mfc="none", color=bar[0].get_color())
        ax.annotate(s, (x, v.mean()), textcoords="offset points", xytext=(6, 4))
        bx.scatter([r["noise"] for r in rows[s]], v, s=12, label=s)
    ax.plot([], [], "ko", mfc="none", label="files with B-frames only")
    ax.set_xlabel("decode frames/CPU-s vs off (filled: all files)")
    ax.set_ylabel("voxel error (normalised L1 vs full decoding)")
    ax.set_yscale("symlog", linthresh=0.01)
    ax.legend(loc="upper left", fontsize=8)
    lim = max(max(noise), max(max(r["voxel_nl1"] for r in rows[s]) for s in SETTINGS[1:])) * 1.1
    xs = np.linspace(0, lim, 200)
    bx.plot(xs, xs, "k--", lw=1, label="error = noise")
    bx.set_yscale("symlog", linthresh=0.01)
    bx.set_xlabel("V2V noise at sigma 0.03 (normalised L1), per file")
    bx.set_ylabel("voxel error of the setting, per file")
    bx.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1))
    fig.suptitle(f"decode_fast: speed against voxel error ({len(noise)} files)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    sys.exit(main())

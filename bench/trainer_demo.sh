#!/usr/bin/env bash
# CPU demo of the trainer: a small E2VID trained from a real v2v-serve on 127.0.0.1 on the
# bundled clips plus camera-motion clips over bundled still photographs (harness/motion_clips.py),
# evaluated on a held-out clip against the constant-mean-image baseline.
#
#   bash bench/trainer_demo.sh [OUT_DIR] [STEPS_FAST] [STEPS_TOTAL]
#
# OUT_DIR (default runs/trainer_demo) receives videos_train/ and videos_heldout/ (copies:
# the server ignores links that leave its root), serve.log, the run in e2vid/, and
# eval_<checkpoint>_<H>x<W>.json for every checkpoint at 360x640 and 144x256.
# STEPS_FAST (default 600) steps at lr 1e-3, then up to STEPS_TOTAL (default 2400) at lr 3e-4,
# resumed from checkpoint_last.pt (the stream position comes back with it).
# About 1 step/s on 2 CPU cores. Results of one run: docs/trainer.md.
set -euo pipefail
OUT=${1:-runs/trainer_demo}
STEPS_FAST=${2:-600}
STEPS_TOTAL=${3:-2400}
PORT=${V2V_DEMO_PORT:-5621}
HERE=$(cd "$(dirname "$0")/.." && pwd)
mkdir -p "$OUT" && OUT=$(cd "$OUT" && pwd)
cd "$HERE"
CLIPS="$HERE/v2v_server/sample_videos"

mkdir -p "$OUT/videos_train" "$OUT/videos_heldout"
# bikes.mp4 and webvid_like_596x336.mp4 are one source (the second is the first played forward
# then backward), so both train; bigbuckbunny.mp4 is never served.
cp "$CLIPS/bikes.mp4" "$CLIPS/webvid_like_596x336.mp4" "$OUT/videos_train/"
cp "$CLIPS/bigbuckbunny.mp4" "$OUT/videos_heldout/"
# one street source is too little variety for a reconstruction network (it learns one scene's
# brightness for where no events fire): add E2VID-style camera motion over 14 still photographs.
python -m harness.motion_clips --out "$OUT/videos_train" --frames 250 --size 272 480 --seed 0 > /dev/null

# --keep-top-fraction 1.0: these clips carry no watermark, so crops come from the whole frame.
python -m v2v_server.cli --videos "$OUT/videos_train" --workers 1 --bind "tcp://127.0.0.1:$PORT" \
    --sequence-length 16 --num-bins 5 --crop-size 64 --batch-size 4 --keep-top-fraction 1.0 \
    --seed 0 > "$OUT/serve.log" 2>&1 &
SERVER=$!
trap 'kill -INT $SERVER 2>/dev/null || true; wait $SERVER 2>/dev/null || true' EXIT

TRAIN=(python -m trainer.train --config trainer/configs/e2vid.yaml --connect "tcp://127.0.0.1:$PORT"
       --out "$OUT/e2vid" --device cpu --set model.base_num_channels=16 --set log.image_every=400
       --set log.checkpoint_every=200 --no-progress)
"${TRAIN[@]}" --max-steps "$STEPS_FAST" --set optim.lr=1e-3
"${TRAIN[@]}" --max-steps "$STEPS_TOTAL" --set optim.lr=3e-4 --resume auto

for ck in "$OUT"/e2vid/checkpoint_0*.pt; do
    name=$(basename "$ck" .pt)
    for size in "360 640" "144 256"; do
        python -m trainer.evaluate --checkpoint "$ck" --video "$OUT/videos_heldout/bigbuckbunny.mp4" \
            --size $size --device cpu > "$OUT/eval_${name}_${size/ /x}.json"
    done
done
python - "$OUT" <<'EOF'
import glob, json, os, sys
print("| checkpoint | size | MSE | baseline MSE | SSIM | baseline SSIM |")
print("|---|---|---|---|---|---|")
for f in sorted(glob.glob(os.path.join(sys.argv[1], "eval_*.json"))):
    m = json.load(open(f))["mean"]
    ck, size = os.path.basename(f)[5:-5].rsplit("_", 1)
    print(f"| {ck} | {size} | {m['mse']:.4f} | {m['base_mse']:.4f} | {m['ssim']:.3f} | {m['base_ssim']:.3f} |")
EOF

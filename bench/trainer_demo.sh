#!/usr/bin/env bash
# CPU demo of the trainer: a small reconstruction network (E2VID, HyperE2VID or ETNet) or E-RAFT
# trained from a real v2v-serve on 127.0.0.1 on the bundled clips plus camera-motion clips over
# bundled still photographs (harness/motion_clips.py), evaluated on a held-out clip against the
# constant-mean-image baseline (E-RAFT: end-point error on held-out clips with known motion,
# harness/eraft_demo.py, against zero flow).
#
#   bash bench/trainer_demo.sh [OUT_DIR] [STEPS_FAST] [STEPS_TOTAL] [TASK]
#
# TASK: e2vid (default; base 16 channels), hypere2vid (base 16 channels) or etnet (tokens of
# 64, 4 heads, 1 encoder and 1 decoder layer per scale, feed-forward 128) or eraft (2 iterations,
# 3 correlation levels so that 64-pixel crops work, gradient norm clipped to 1 as RAFT trains,
# the authors' constant lr 1e-4 in both phases: at 1e-3 it stays at near-zero flow; the
# motion clips only; eval_eraft.jsonl holds the held-out EPEs).
# OUT_DIR (default runs/trainer_demo) receives videos_train/ and videos_heldout/ (copies:
# the server ignores links that leave its root; eraft serves videos_motion/, the motion
# clips), serve.log, the run in TASK/, and eval_<TASK>_<checkpoint>_<H>x<W>.json for every
# checkpoint at 360x640 and 144x256.
# STEPS_FAST (default 600) steps at lr 1e-3, then up to STEPS_TOTAL (default 2400) at lr 3e-4
# (eraft: 1e-4 both), resumed from checkpoint_last.pt (the stream position comes back with it).
# About 1 step/s on 2 CPU cores (E2VID). Results of one run: docs/trainer.md.
# Environment: V2V_DEMO_PORT (5621), V2V_DEMO_SEQ (sequence length, 16), V2V_DEMO_CKPT_EVERY
# (200), V2V_DEMO_SIZES (evaluation sizes, "360x640 144x256"), V2V_DEMO_BATCH (4): smaller values
# for a shorter run.
set -euo pipefail
OUT=${1:-runs/trainer_demo}
STEPS_FAST=${2:-600}
STEPS_TOTAL=${3:-2400}
TASK=${4:-e2vid}
LR_FAST=1e-3 LR_SLOW=3e-4 WORKERS=1
case "$TASK" in
    e2vid|hypere2vid) SIZE_SETS=(--set model.base_num_channels=16) ;;
    etnet) SIZE_SETS=(--set model.d_model=64 --set model.nhead=4 --set model.encoder_layers=1
                      --set model.decoder_layers=1 --set model.dim_feedforward=128) ;;
    eraft) SIZE_SETS=(--set model.iters=2 --set model.corr_levels=3 --set optim.clip_grad_norm=1.0)
           LR_FAST=1e-4 LR_SLOW=1e-4 ;;
    *) echo "TASK must be e2vid, hypere2vid, etnet or eraft" >&2; exit 2 ;;
esac
PORT=${V2V_DEMO_PORT:-5621}
SEQ=${V2V_DEMO_SEQ:-16}
CKPT_EVERY=${V2V_DEMO_CKPT_EVERY:-200}
SIZES=${V2V_DEMO_SIZES:-"360x640 144x256"}
BATCH=${V2V_DEMO_BATCH:-4}
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
[ -n "$(ls "$OUT"/videos_train/motion_* 2>/dev/null)" ] ||
    python -m harness.motion_clips --out "$OUT/videos_train" --frames 250 --size 272 480 --seed 0 > /dev/null
SERVED="$OUT/videos_train"
if [ "$TASK" = eraft ]; then
    # E-RAFT trains on the motion clips only: their flow targets explain the change between
    # voxel boundaries, those of the street clips much less (warping by the stream's flow leaves
    # 19 of 28 grey levels of mean difference on bikes.mp4: python -m bench.flow --real). The
    # server's shuffle buffer (--shuffle epoch, the default) mixes clips in each batch with one
    # worker. docs/trainer.md has the runs.
    SERVED="$OUT/videos_motion"
    mkdir -p "$SERVED" && cp "$OUT"/videos_train/motion_* "$SERVED/"
fi

# --keep-top-fraction 1.0: these clips carry no watermark, so crops come from the whole frame.
python -m v2v_server.cli --videos "$SERVED" --workers "$WORKERS" --bind "tcp://127.0.0.1:$PORT" \
    --sequence-length "$SEQ" --num-bins 5 --crop-size 64 --batch-size "$BATCH" --keep-top-fraction 1.0 \
    --seed 0 > "$OUT/serve.log" 2>&1 &
SERVER=$!
trap 'kill -INT $SERVER 2>/dev/null || true; wait $SERVER 2>/dev/null || true' EXIT

TRAIN=(python -m trainer.train --config "trainer/configs/$TASK.yaml" --connect "tcp://127.0.0.1:$PORT"
       --out "$OUT/$TASK" --device cpu "${SIZE_SETS[@]}" --set log.image_every=400
       --set log.checkpoint_every="$CKPT_EVERY" --no-progress)
"${TRAIN[@]}" --max-steps "$STEPS_FAST" --set optim.lr="$LR_FAST"
"${TRAIN[@]}" --max-steps "$STEPS_TOTAL" --set optim.lr="$LR_SLOW" --resume auto

if [ "$TASK" = eraft ]; then
    python -m harness.eraft_demo "$OUT/$TASK"/checkpoint_0*.pt | tee "$OUT/eval_eraft.jsonl"
    python - "$OUT/eval_eraft.jsonl" <<'EOF'
import json, sys
print("| checkpoint | EPE (px) | zero-flow EPE (px) |")
print("|---|---|---|")
for line in open(sys.argv[1]):
    r = json.loads(line)
    print(f"| {r['checkpoint']} | {r['epe']:.3f} | {r['zero_flow_epe']:.3f} |")
EOF
    exit 0
fi

for ck in "$OUT/$TASK"/checkpoint_0*.pt; do
    name=$(basename "$ck" .pt)
    for size in $SIZES; do
        python -m trainer.evaluate --checkpoint "$ck" --video "$OUT/videos_heldout/bigbuckbunny.mp4" \
            --size ${size/x/ } --device cpu > "$OUT/eval_${TASK}_${name}_${size}.json"
    done
done
python - "$OUT" "$TASK" <<'EOF'
import glob, json, os, sys
print("| checkpoint | size | MSE | baseline MSE | SSIM | baseline SSIM |")
print("|---|---|---|---|---|---|")
task = sys.argv[2]
for f in sorted(glob.glob(os.path.join(sys.argv[1], f"eval_{task}_*.json"))):
    m = json.load(open(f))["mean"]
    ck, size = os.path.basename(f)[len(f"eval_{task}_"):-5].rsplit("_", 1)
    print(f"| {ck} | {size} | {m['mse']:.4f} | {m['base_mse']:.4f} | {m['ssim']:.3f} | {m['base_ssim']:.3f} |")
EOF

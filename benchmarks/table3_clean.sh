#!/bin/bash
# FuseSR Table 3 ablation on clean clips (docs/results-history.md, "The clean-clip benchmark"): render 4 training clips of the
# built-in scene and 4 unseen test clips (3 glTF assets + the built-in scene with another seed), evaluate the
# non-learned baselines, train FuseSR with the 4 settings of the HR G-buffer / demodulation switches for the same
# number of steps, evaluate each, and write the speed-against-error table and Pareto plot.
#
# Usage: benchmarks/table3_clean.sh OUT_DIR        (about 15 min of rendering + 4 x 14 min of training on 2 cores)
# Environment (defaults = the documented run): STEPS=1200 SIZE=320x180 TRAIN_FRAMES=1:16 TEST_FRAMES=1:8 CROP=40
# HR_SPP=64 LR_SPP=128 SHARED=../shared REFLECTANCE="[0.5, 2.0]" (data.reflectance_range; "[1.0, 1.0]" = the
# runs without the tint). A smoke run: STEPS=2 SIZE=64x36 TRAIN_FRAMES=1:5 TEST_FRAMES=1:2 CROP=8.
set -euo pipefail
OUT=${1:?usage: benchmarks/table3_clean.sh OUT_DIR}
cd "$(dirname "$0")/.."
B=.venv/bin/blendsr
PY=.venv/bin/python
STEPS=${STEPS:-1200}; SIZE=${SIZE:-320x180}; CROP=${CROP:-40}
TRAIN_FRAMES=${TRAIN_FRAMES:-1:16}; TEST_FRAMES=${TEST_FRAMES:-1:8}
SHARED=${SHARED:-../shared}
S7_FRAMES=$(( ${TEST_FRAMES%%:*} + 29 )):$(( ${TEST_FRAMES##*:} + 29 ))
R="--hr-size $SIZE --hr-spp ${HR_SPP:-64} --hr-denoise --lr-spp ${LR_SPP:-128} --no-progress"
mkdir -p "$OUT"

for s in 0 1 2; do $B render -o "$OUT/train_s$s" --seed $s --frames "$TRAIN_FRAMES" $R; done
$B render -o "$OUT/train_walk3" --seed 3 --camera-path walk --frames "$TRAIN_FRAMES" $R
G=$SHARED/scenes/gltf
gltf() {  # NAME ASSET [render_gltf options]: import once; later runs resume the saved .blend
  local name=$1 asset=$2; shift 2
  if [ -f "$OUT/$name.blend" ]; then
    $B render "$OUT/$name.blend" -o "$OUT/$name" --camera-path orbit --seed 0 --frames "$TEST_FRAMES" $R
  else
    $PY examples/render_gltf.py "$asset" -o "$OUT/$name" --frames "$TEST_FRAMES" "$@" $R
  fi
}
gltf test_bottle "$G/WaterBottle/glTF/WaterBottle.gltf" --hdri "$SHARED/scenes/hdri/empty_warehouse_01_1k.hdr"
gltf test_chair "$G/SheenChair/glTF/SheenChair.gltf"
gltf test_wicker "$G/ClearcoatWicker/glTF-Binary/ClearcoatWicker.glb"
$B render -o "$OUT/test_s7" --seed 7 --frames "$S7_FRAMES" $R

TRAIN="$OUT/train_s0 $OUT/train_s1 $OUT/train_s2 $OUT/train_walk3"
TEST="$OUT/test_bottle $OUT/test_chair $OUT/test_wicker $OUT/test_s7"
for c in $TRAIN $TEST; do $B validate "$c" > /dev/null; done

MODELS=bicubic,bilinear,demod-bilinear,demod-jbu
for m in bicubic bilinear demod-bilinear demod-jbu; do $B evaluate --model $m --data $TEST --json "$OUT/eval_$m.json"; done
for v in "true true" "false true" "true false" "false false"; do
  set -- $v
  run="$OUT/abl_hr$1_dm$2"
  if [ -f "$run/checkpoints/last.pt" ] && [ ! -f "$run/summary.json" ]; then
    $B train -o "$run" --resume                                   # an interrupted run continues bit-identically
  elif [ ! -f "$run/summary.json" ]; then
    $B train --model fusesr --data $TRAIN -o "$run" --config examples/train_config.toml --max-steps "$STEPS" \
      --set data.val_frames=2 --set data.crop="$CROP" --set data.batch_size=4 --set 'run.amp="none"' \
      --set 'model.fusesr.norm="none"' --set model.fusesr.hr_gbuffer=$1 --set model.fusesr.demodulation=$2 \
      --set run.progress=false \
      --set "data.reflectance_range=${REFLECTANCE:-[0.5, 2.0]}"
  fi
  $B evaluate --checkpoint "$run/checkpoints/last.pt" --data $TEST --json "$run.eval.json"
  last=${TRAIN_FRAMES##*:}   # the 2 held-out (data.val_frames) frames of the training clips
  $B evaluate --checkpoint "$run/checkpoints/last.pt" --data $TRAIN --frames $((last - 1)):$last --no-flip \
    --json "$run.heldout.json"
  MODELS="$MODELS,fusesr:$run/checkpoints/last.pt"
done
$B bench models --data $TEST --models "$MODELS" -o "$OUT/bench"
echo "done: $OUT/eval_*.json, $OUT/abl_*.eval.json, $OUT/bench/bench_models.md, $OUT/bench/pareto.png"

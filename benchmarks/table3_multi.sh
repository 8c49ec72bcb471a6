#!/bin/bash
# FuseSR Table 3 ablation trained on several scenes (not in docs/results.md: its last run predates upsampling by
# class and the guided base; it also renders the "unseen glTF-scene clips" of docs/results.md): the 4 built-in clips of
# benchmarks/table3_clean.sh plus 3 glTF assets that are not in its test set (Fox, GlassVaseFlowers,
# AnisotropyRotationTest), evaluated on table3_clean's unseen test clips, on the 2 held-out frames of every training
# clip, and on unseen clips of the glTF training scenes (another orbit seed, other frames).
#
# Usage: benchmarks/table3_multi.sh OUT_DIR   (OUT_DIR of a finished benchmarks/table3_clean.sh run, same settings;
#        about 10 min of rendering + 4 x 17 min of training on 2 cores)
# Environment: as table3_clean.sh (STEPS SIZE TRAIN_FRAMES TEST_FRAMES CROP HR_SPP LR_SPP SHARED), and
# VARIANTS="true,true false,true true,false false,false" (model.fusesr.hr_gbuffer,model.fusesr.demodulation), SEED=0.
# A smoke run: STEPS=2 SIZE=64x36 TRAIN_FRAMES=1:5 TEST_FRAMES=1:2 CROP=8 (after table3_clean.sh's smoke run).
set -euo pipefail
OUT=${1:?usage: benchmarks/table3_multi.sh OUT_DIR}
cd "$(dirname "$0")/.."
B=.venv/bin/blendsr
PY=.venv/bin/python
STEPS=${STEPS:-1200}; SIZE=${SIZE:-320x180}; CROP=${CROP:-40}; SEED=${SEED:-0}
TRAIN_FRAMES=${TRAIN_FRAMES:-1:16}; TEST_FRAMES=${TEST_FRAMES:-1:8}
SHARED=${SHARED:-../shared}
U_FRAMES=$(( ${TEST_FRAMES%%:*} + 29 )):$(( ${TEST_FRAMES##*:} + 29 ))
R="--hr-size $SIZE --hr-spp ${HR_SPP:-64} --hr-denoise --lr-spp ${LR_SPP:-128} --no-progress"
for c in train_s0 train_s1 train_s2 train_walk3 test_bottle test_chair test_wicker test_s7; do
  [ -f "$OUT/$c/manifest.json" ] || { echo "$OUT/$c: run benchmarks/table3_clean.sh $OUT first" >&2; exit 2; }
done

G=$SHARED/scenes/gltf
GLTF="$OUT/train_fox $OUT/train_glassvaseflowers $OUT/train_anisotropyrotationtest"
for a in Fox/glTF-Binary/Fox.glb GlassVaseFlowers/glTF-Binary/GlassVaseFlowers.glb \
         AnisotropyRotationTest/glTF-Binary/AnisotropyRotationTest.glb; do
  n=$(basename "${a%%/*}" | tr A-Z a-z)
  if [ -f "$OUT/train_$n.blend" ]; then   # imported once; later runs resume the saved .blend
    $B render "$OUT/train_$n.blend" -o "$OUT/train_$n" --camera-path orbit --seed 0 --frames "$TRAIN_FRAMES" $R
  else
    $PY examples/render_gltf.py "$G/$a" -o "$OUT/train_$n" --frames "$TRAIN_FRAMES" $R
  fi
  $B render "$OUT/train_$n.blend" -o "$OUT/unseen_$n" --camera-path orbit --seed 5 --frames "$U_FRAMES" $R
done

TRAIN="$OUT/train_s0 $OUT/train_s1 $OUT/train_s2 $OUT/train_walk3 $GLTF"
TEST="$OUT/test_bottle $OUT/test_chair $OUT/test_wicker $OUT/test_s7"
UNSEEN="$OUT/unseen_fox $OUT/unseen_glassvaseflowers $OUT/unseen_anisotropyrotationtest"
for c in $GLTF $UNSEEN; do $B validate "$c" > /dev/null; done
last=${TRAIN_FRAMES##*:}   # the 2 held-out (data.val_frames) frames of the training clips
for m in bilinear demod-bilinear demod-jbu; do
  $B evaluate --model $m --data $TRAIN --frames $((last - 1)):$last --no-flip --json "$OUT/multi_heldout_$m.json"
  $B evaluate --model $m --data $UNSEEN --no-flip --json "$OUT/multi_unseen_$m.json"
done
for v in ${VARIANTS:-true,true false,true true,false false,false}; do
  set -- ${v/,/ }
  run="$OUT/multi_hr$1_dm$2_seed$SEED"
  if [ -f "$run/checkpoints/last.pt" ] && [ ! -f "$run/summary.json" ]; then
    $B train -o "$run" --resume
  elif [ ! -f "$run/summary.json" ]; then
    $B train --model fusesr --data $TRAIN -o "$run" --config examples/train_config.toml --max-steps "$STEPS" \
      --set data.val_frames=2 --set data.crop="$CROP" --set data.batch_size=4 --set 'run.amp="none"' \
      --set model.fusesr.hr_gbuffer=$1 --set model.fusesr.demodulation=$2 --set run.seed=$SEED \
      --set run.progress=false \
      --set run.minutes=60
  fi
  $B evaluate --checkpoint "$run/checkpoints/last.pt" --data $TEST --json "$run.eval.json"
  $B evaluate --checkpoint "$run/checkpoints/last.pt" --data $TRAIN --frames $((last - 1)):$last --no-flip \
    --json "$run.heldout.json"
  $B evaluate --checkpoint "$run/checkpoints/last.pt" --data $UNSEEN --no-flip --json "$run.unseen.json"
done
echo "done: $OUT/multi_*.eval.json (unseen test set), *.heldout.json (held-out frames), *.unseen.json (unseen clips of the glTF training scenes)"

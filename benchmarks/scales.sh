#!/usr/bin/env bash
# PSNR against scale (docs/results-history.md, "PSNR against scale"): fourier-sr trained on a mix of scales {2, 3, 4} and
# scored at 2, 2.5, 3, 4 and the unseen 6, against bicubic, demod-jbu and fusesr-l trained per integer scale.
#   1. renders 4 training clips (built-in seeds 10-13, LR levels 2, 3, 4) and 2 test clips (seeds 20, 21, LR levels
#      2, 2.5, 3, 4, 6) at 240x120 (every scale divides it), 12 frames;
#   2. trains fourier-sr on every level of the training clips, fusesr-l at 2 and at 4, STEPS steps each;
#   3. benchmarks/scale_curve.py scores every model at every level it can take and writes the table and plot.
# Usage: benchmarks/scales.sh [DATA] [OUT]     (STEPS default 1000, THREADS 1)
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${1:-datasets/scales}
OUT=${2:-docs/bench/scales}
STEPS=${STEPS:-1000}
THREADS=${THREADS:-1}
PY=${PY:-.venv/bin/python}
export MALLOC_MMAP_THRESHOLD_=4294967296 MALLOC_TRIM_THRESHOLD_=68719476736
B="$PY -m gbuffer_export.cli"
R=(--hr-size 240x120 --frames 1:12 --hr-spp 16 --hr-denoise --lr-spp 16 --jitter halton --threads "$THREADS"
   --for-models fourier-sr,fusesr-l,demod-jbu,bicubic --no-progress)
for s in 10 11 12 13; do
  [ -f "$DATA/train/s$s/manifest.json" ] && $B validate "$DATA/train/s$s" --quick --no-progress >/dev/null 2>&1 && continue
  $B render -o "$DATA/train/s$s" --seed "$s" --camera-path orbit --scales 2,3,4 "${R[@]}"
done
for s in 20 21; do
  [ -f "$DATA/test/s$s/manifest.json" ] && $B validate "$DATA/test/s$s" --quick --no-progress >/dev/null 2>&1 && continue
  $B render -o "$DATA/test/s$s" --seed "$s" --camera-path orbit --scales 2,2.5,3,4,6 "${R[@]}"
done
for c in "$DATA"/train/s* "$DATA"/test/s*; do $B validate "$c" --quick --no-progress; done
COMMON=(--max-steps "$STEPS" --set data.crop=12 --set data.batch_size=4 --set data.val_frames=0
        --set run.progress=false --set run.threads="$THREADS" --set run.checkpoint_every=100)
train() {  # RUN-NAME MODEL CONFIG [--set ...]
  local name=$1 model=$2 config=$3; shift 3
  [ -f "$DATA/runs/$name/summary.json" ] && return 0
  local resume=(); [ -f "$DATA/runs/$name/checkpoints/last.pt" ] && resume=(--resume)
  $B train --model "$model" --data "$DATA"/train/s* -o "$DATA/runs/$name" --config "$config" "${COMMON[@]}" "$@" \
      "${resume[@]}"
}
train fourier-sr fourier-sr examples/fourier_sr_config.toml --set optim.lr=5e-4  # the authors' 1e-4 is for 300k steps
train fusesr-l-x2 fusesr-l examples/train_config.toml --set optim.warmup_steps=0 --set model.scale=2
train fusesr-l-x4 fusesr-l examples/train_config.toml --set optim.warmup_steps=0 --set model.scale=4
$PY benchmarks/scale_curve.py "$DATA"/test/s* -o "$OUT" --threads "$THREADS" --models bicubic,demod-jbu,\
fusesr-l:"$DATA/runs/fusesr-l-x2/checkpoints/last.pt",fusesr-l:"$DATA/runs/fusesr-l-x4/checkpoints/last.pt",\
fourier-sr:"$DATA/runs/fourier-sr/checkpoints/last.pt"

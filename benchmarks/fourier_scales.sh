#!/usr/bin/env bash
# fourier-sr on mixed scales (docs/results-history.md, "Shipped networks: fourier-sr on scales 2 and 4"):
#   1. renders benchmarks/zoo_scales_dataset.toml (the zoo clips with an LR level at 2x as well as 4x) and validates it,
#   2. fine-tunes the shipped fourier-sr (trained at 4x on the zoo clips, benchmarks/zoo.sh) on both levels of every
#      training clip, with zoo.sh's recipe (the authors' losses, the residual demod-bilinear base, LR crop 16, batch 4)
#      at a lower learning rate, for STEPS steps (resumes from RUNS/fourier_sr/checkpoints/last.pt),
#   3. scores the shipped and the fine-tuned weights and the baselines at 2x and 4x on the val and test splits
#      (benchmarks/scale_curve.py: OUT/val, OUT/test). RELEASE=1 then writes the fine-tuned weights as the shipped
#      pretrained:fourier-sr (benchmarks/release_weights.py: scores at 4x, and the scale curves beside them).
# Usage: benchmarks/fourier_scales.sh [DATASET] [RUNS] [OUT]; STEPS (1000), LR (2e-4), THREADS (2), INIT (the starting
# weights, default pretrained:fourier-sr; the shipped mixed-scale weights started from the 4x ones their JSON's
# init_from names).
set -euo pipefail
cd "$(dirname "$0")/.."
DS=${1:-datasets/zoo_scales}
RUNS=${2:-runs/zoo_scales}
OUT=${3:-docs/bench/fourier_scales}
STEPS=${STEPS:-1000}
LR=${LR:-2e-4}
THREADS=${THREADS:-2}
PY=${PY:-.venv/bin/python}
export MALLOC_MMAP_THRESHOLD_=4294967296 MALLOC_TRIM_THRESHOLD_=68719476736
B="$PY -m gbuffer_export.cli"
$B dataset benchmarks/zoo_scales_dataset.toml -o "$DS" --workers 2 --threads 1 --no-progress
$B validate "$DS" --quick --no-progress
run="$RUNS/fourier_sr"
cmd=($B train --model fourier-sr --data "$DS" -o "$run" --config examples/fourier_sr_config.toml --max-steps "$STEPS"
     --set data.crop=16 --set data.batch_size=4 --set data.val_frames=0 --set run.progress=false
     --set run.threads="$THREADS" --set run.checkpoint_every=100 --set run.keep_checkpoints=3
     --set model.fourier-sr.residual=true --set model.fourier-sr.zero_init_head=true --set model.scale=0
     --set run.init_from=\"${INIT:-pretrained:fourier-sr}\" --set optim.lr="$LR")
if [ ! -f "$run/summary.json" ]; then
  mkdir -p "$run"
  { printf 'blendsr'; printf ' %q' "${cmd[@]:3}"; echo; } > "$run/command.txt"
  extra=(); [ -f "$run/checkpoints/last.pt" ] && extra+=(--resume)
  "${cmd[@]}" "${extra[@]}"
fi
for split in val test; do
  clips=$($PY -c "import sys; from gbuffer_export.dataset.build import split_clips; print(' '.join(map(str, split_clips(sys.argv[1], sys.argv[2]))))" "$DS" "$split")
  # shellcheck disable=SC2086
  $PY benchmarks/scale_curve.py $clips -o "$OUT/$split" --threads "$THREADS" --no-flip \
      --models bicubic,demod-bilinear,demod-jbu,pretrained:fourier-sr,fourier-sr:"$run/checkpoints/last.pt"
done
if [ "${RELEASE:-0}" = 1 ]; then
  $PY benchmarks/release_weights.py "$DS" "$RUNS" --models fourier-sr --script benchmarks/fourier_scales.sh \
      --attach scale_curve_val="$OUT/val/scale_curve.json" --attach scale_curve_test="$OUT/test/scale_curve.json"
fi

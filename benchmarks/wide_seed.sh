#!/usr/bin/env bash
# Fine-tune a shipped seed network on the wide dataset (issue 40, "Make each shipped network earn its place";
# docs/results.md, first section):
#   1. renders examples/dataset_wide.toml (resumes when DATASET exists),
#   2. fine-tunes each of MODELS from its shipped weights on the train split with benchmarks/zoo.sh's recipe (its
#      paper's losses and optimiser from examples/*_config.toml, the residual demod-bilinear base, LR crop 16,
#      batch 4) at the learning rate LR, for STEPS steps (resumes from RUNS/<model>/checkpoints/last.pt),
#   3. scores it against the shipped weights on the val split: benchmarks/release_weights.py writes it as the
#      shipped weights only when the val rule (training/selection.py) says so.
# Usage: benchmarks/wide_seed.sh [DATASET] [RUNS]; MODELS ("rdg-s"; the models zoo.sh trains at 4x only: nsrd and
# nsrr-fec read buffers the wide spec does not render, fourier-sr is trained on 2x and 4x), STEPS (2000), LR (2e-4),
# THREADS (1), RELEASE=0: train only.
set -euo pipefail
cd "$(dirname "$0")/.."
DS=${1:-datasets/wide}
RUNS=${2:-runs/wide_seed}
MODELS=${MODELS:-"rdg-s"}
STEPS=${STEPS:-2000}
LR=${LR:-2e-4}
THREADS=${THREADS:-1}
PY=${PY:-.venv/bin/python}
export MALLOC_MMAP_THRESHOLD_=4294967296 MALLOC_TRIM_THRESHOLD_=68719476736
B="$PY -m gbuffer_export.cli"
$B dataset examples/dataset_wide.toml -o "$DS" --workers 1 --no-progress
for M in $MODELS; do
  case $M in
    rdg-s) OWN=(--config examples/rdg_config.toml --set data.window=8 --set model.rdg-s.demod=true
                --set optim.decay_steps="$STEPS") ;;
    *) echo "wide_seed.sh: $M is not fine-tuned here (see the usage)" >&2; exit 2 ;;
  esac
  run="$RUNS/${M//-/_}"
  cmd=($B train --model "$M" --data "$DS" -o "$run" --max-steps "$STEPS" "${OWN[@]}"
       --set data.crop=16 --set data.batch_size=4 --set data.val_frames=0 --set run.progress=false
       --set run.threads="$THREADS" --set run.checkpoint_every=100 --set run.keep_checkpoints=3
       --set "model.$M.residual=true" --set "model.$M.zero_init_head=true"
       --set "run.init_from=\"pretrained:$M\"" --set optim.lr="$LR")
  mkdir -p "$run"
  { printf 'blendsr'; printf ' %q' "${cmd[@]:3}"; echo; } > "$run/command.txt"  # $B is 3 words
  extra=(); [ -f "$run/checkpoints/last.pt" ] && extra+=(--resume)
  "${cmd[@]}" "${extra[@]}"
done
if [ "${RELEASE:-1}" = 1 ]; then
  $PY benchmarks/release_weights.py "$DS" "$RUNS" --models "${MODELS// /,}" --script benchmarks/wide_seed.sh \
      --env "STEPS=$STEPS LR=$LR"
fi

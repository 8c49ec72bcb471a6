#!/usr/bin/env bash
# Fine-tune the shipped seed networks on the wide dataset (issue 40, "Make each shipped network earn its place";
# docs/results.md, first section):
#   1. renders examples/dataset_wide.toml (resumes when DATASET exists; every buffer, LR at 4x and 2x),
#   2. fine-tunes each of MODELS from its shipped weights on the train split with its recipe in
#      benchmarks/seed_recipes.sh (as benchmarks/zoo.sh trained it: its paper's losses and optimiser, the residual
#      demod-bilinear base, LR crop 16, batch 4) at the learning rate LR, for STEPS steps (resumes from
#      RUNS/<model>/checkpoints/last.pt); fourier-sr on both LR levels (model.scale = 0: 2x and 4x, as
#      benchmarks/fourier_scales.sh), the others at 4x,
#   3. scores it against the shipped weights on the val split: benchmarks/release_weights.py writes it as the
#      shipped weights only when the val rule (training/selection.py) says so.
# Usage: benchmarks/wide_seed.sh [DATASET] [RUNS]; MODELS ("rdg-s"; any of rdg-s nsrd nsrr-fec fourier-sr),
# STEPS (2000), LR (2e-4), THREADS (1), MINUTES (set: each training also stops after M minutes of this invocation;
# resumable), RELEASE=0: train only.
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
# shellcheck source=benchmarks/seed_recipes.sh
. benchmarks/seed_recipes.sh
# a clip that failed or does not validate is left out of the splits (the dataset command then exits non-zero)
$B dataset examples/dataset_wide.toml -o "$DS" --workers 1 --no-progress \
    || echo "wide_seed.sh: $DS has clips left out (above); training on the others" >&2
for M in $MODELS; do
  case $M in
    rdg-s|nsrd|nsrr-fec) SCALE=(--set model.scale=4) ;;  # the 4x level (the dataset has 2x too)
    fourier-sr) SCALE=(--set model.scale=0) ;;
    *) echo "wide_seed.sh: $M is not fine-tuned here (see the usage)" >&2; exit 2 ;;
  esac
  # shellcheck disable=SC2207
  OWN=($(recipe "$M" "$STEPS"))
  run="$RUNS/${M//-/_}"
  # shellcheck disable=SC2046
  cmd=($B train --model "$M" --data "$DS" -o "$run" --max-steps "$STEPS" --config "${OWN[@]}" "${SCALE[@]}"
       $(common "$THREADS") --set "run.init_from=\"pretrained:$M\"" --set optim.lr="$LR")
  mkdir -p "$run"
  { printf 'blendsr'; printf ' %q' "${cmd[@]:3}"; echo; } > "$run/command.txt"  # $B is 3 words
  extra=(); [ -f "$run/checkpoints/last.pt" ] && extra+=(--resume)
  [ -n "${MINUTES:-}" ] && extra+=(--minutes "$MINUTES")
  "${cmd[@]}" "${extra[@]}"
done
[ "${RELEASE:-1}" = 1 ] || exit 0
for M in $MODELS; do  # one call per model, so that each JSON names the command that remakes that model alone
  $PY benchmarks/release_weights.py "$DS" "$RUNS" --models "$M" --script benchmarks/wide_seed.sh \
      --env "MODELS=$M STEPS=$STEPS LR=$LR${MINUTES:+ MINUTES=$MINUTES}"
done

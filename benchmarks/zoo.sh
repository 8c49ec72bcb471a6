#!/usr/bin/env bash
# The shipped seed networks (training/weights/{rdg_s,nsrd,nsrr_fec,fourier_sr,fusesr_fast}_x4.*; docs/results.md,
# "Shipped networks"):
#   1. renders benchmarks/zoo_dataset.toml (15 clips: train 10, val 3 built-in scenes, test SheenChair and
#      ClearcoatWicker; resumes when DATASET exists) and validates it,
#   2. trains each network with its paper's losses and optimiser (examples/*_config.toml, as benchmarks/networks.sh)
#      plus the residual demod-bilinear base (a deviation: docs/models/<model>.md, "Base"), LR crop 16, batch 4,
#      one thread, for its step count below (resumes from RUNS/NAME/checkpoints/last.pt; runs resume bit-identically,
#      so raising a count continues the same training; the cosine schedules decay over a fixed optim.decay_steps),
#   3. scores each on the val split (the only split that may choose between trainings) and the test split, writes
#      the float16 weights with the spec, the commands and the scores (benchmarks/release_weights.py),
#   4. one `blendsr bench models` table and Pareto plot on the test split for the five, the shipped fusesr and
#      fusesr-l (trained on examples/dataset_medium.toml) and the three baselines.
# Usage: benchmarks/zoo.sh [DATASET] [RUNS] [OUT]
#   MODELS (default all five), THREADS (1), MINUTES (set: each training also stops after M minutes of this
#   invocation; resumable), <MODEL>_STEPS (RDG_S_STEPS, NSRD_STEPS, NSRR_FEC_STEPS, FOURIER_SR_STEPS,
#   FUSESR_FAST_STEPS: the counts shipped), RELEASE=0 / BENCH=0 skip steps 3 / 4.
set -euo pipefail
cd "$(dirname "$0")/.."
DS=${1:-datasets/zoo}
RUNS=${2:-runs/zoo}
OUT=${3:-docs/bench/zoo}
THREADS=${THREADS:-1}
PY=${PY:-.venv/bin/python}
MODELS=${MODELS:-"rdg-s nsrd nsrr-fec fourier-sr fusesr-fast"}
export MALLOC_MMAP_THRESHOLD_=4294967296 MALLOC_TRIM_THRESHOLD_=68719476736
B="$PY -m gbuffer_export.cli"
$B dataset benchmarks/zoo_dataset.toml -o "$DS" --workers 1 --threads 2 --no-progress
$B validate "$DS" --quick --no-progress
# shellcheck source=benchmarks/seed_recipes.sh
. benchmarks/seed_recipes.sh
# shellcheck disable=SC2207
COMMON=($(common "$THREADS"))
steps() {  # the step count shipped for model $1 (the *_STEPS variables override)
  case $1 in
    rdg-s) echo "${RDG_S_STEPS:-2718}" ;;
    nsrd) echo "${NSRD_STEPS:-4302}" ;;
    nsrr-fec) echo "${NSRR_FEC_STEPS:-862}" ;;
    fourier-sr) echo "${FOURIER_SR_STEPS:-2035}" ;;
    fusesr-fast) echo "${FUSESR_FAST_STEPS:-24455}" ;;
  esac
}
train() {  # MODEL CONFIG [--set ...]: trains RUNS/<model with _>, writes the command beside the run
  local model=$1 config=$2; shift 2
  local run="$RUNS/${model//-/_}" n; n=$(steps "$model")
  local cmd=($B train --model "$model" --data "$DS" -o "$run" --config "$config" --max-steps "$n" "${COMMON[@]}" "$@")
  mkdir -p "$run"
  { printf 'blendsr'; printf ' %q' "${cmd[@]:3}"; echo; } > "$run/command.txt"  # $B is 3 words
  local extra=(); [ -f "$run/checkpoints/last.pt" ] && extra+=(--resume)
  [ -n "${MINUTES:-}" ] && extra+=(--minutes "$MINUTES")
  "${cmd[@]}" "${extra[@]}"
}
for M in $MODELS; do
  # shellcheck disable=SC2046
  case $M in
    rdg-s) train rdg-s $(recipe rdg-s 3000) ;;
    fusesr-fast) train fusesr-fast $(recipe fusesr-fast 20000) ;;
    nsrd|nsrr-fec|fourier-sr) train "$M" $(recipe "$M" 0) ;;
    *) echo "unknown model $M" >&2; exit 2 ;;
  esac
done
if [ "${RELEASE:-1}" = 1 ]; then
  $PY benchmarks/release_weights.py "$DS" "$RUNS" --models "${MODELS// /,}" --script benchmarks/zoo.sh
fi
[ "${BENCH:-1}" = 1 ] || exit 0
LIST=bicubic,demod-bilinear,demod-jbu,pretrained:fusesr,pretrained:fusesr-l
for M in $MODELS; do LIST="$LIST,pretrained:$M"; done
$B bench models --data "$DS" --split test --threads "$THREADS" --flip -o "$OUT" --models "$LIST"

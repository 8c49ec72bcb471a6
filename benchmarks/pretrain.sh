#!/usr/bin/env bash
# Remake the shipped pretrained weights (training/weights/*.safetensors + .json):
#   1. render the dataset of $SPEC (default examples/dataset_medium.toml, 67 clips; resumes when DATASET exists),
#   2. train fusesr and fusesr-l on its train split with benchmarks/pretrain.toml,
#   3. score them and the non-learned baselines on its val split (scenes that choose between trainings) and its test
#      split (assets never seen in training),
#   4. write the float16 weights with the spec, the commands and the scores beside them.
# Usage: [SPEC=spec.toml] benchmarks/pretrain.sh [DATASET] [RUNS]
#        (FUSESR_STEPS, FUSESR_L_STEPS: optimiser steps, default 8000 and 2500; THREADS: torch threads;
#        INIT=SPEC: start each model from the weights SPEC names, <M> replaced by the model name, e.g.
#        INIT='pretrained:<M>' fine-tunes the shipped weights, INIT='runs/a/<D>/checkpoints/last.pt' continues the
#        runs of RUNS=runs/a (<D>: the model's run folder, fusesr_l for fusesr-l); LR: optim.lr; MINUTES: each training also stops after
#        M minutes of this invocation, resumable; MODELS: default "fusesr fusesr-l"; RELEASE=0: no weights written;
#        SET: whitespace-separated KEY=VALUE overrides, each passed as --set with <M> replaced by the model name, e.g.
#        SET='model.<M>.residual_clamp="lr-range"')
# The weights shipped on 2026-11-26 (trained on examples/dataset_large.toml, fine-tuned from those of the medium
# dataset): see training/weights/fusesr_x4.json, "commands".
set -euo pipefail
cd "$(dirname "$0")/.."
SPEC=${SPEC:-examples/dataset_medium.toml}
DS=${1:-datasets/medium}
RUNS=${2:-runs/pretrain}
FUSESR_STEPS=${FUSESR_STEPS:-8000}
FUSESR_L_STEPS=${FUSESR_L_STEPS:-2500}
THREADS=${THREADS:-1}
PY=${PY:-.venv/bin/python}
export MALLOC_MMAP_THRESHOLD_=4294967296 MALLOC_TRIM_THRESHOLD_=68719476736
# Two runs started side by side on one dataset take turns here (blendsr dataset refuses a second run on a folder):
# the first renders or resumes it, the other waits for the lock (flock, util-linux), then finds it complete.
mkdir -p "$(dirname "$DS")"
(
  if command -v flock >/dev/null; then flock 9; fi
  $PY -m gbuffer_export.cli dataset "$SPEC" -o "$DS" --workers 2
  $PY -m gbuffer_export.cli validate "$DS" --quick --no-progress
) 9>"$DS.pretrain.lock"
MODELS=${MODELS:-"fusesr fusesr-l"}
for M in $MODELS; do
  R="$RUNS/${M//-/_}"
  if [ "$M" = fusesr ]; then STEPS=$FUSESR_STEPS; else STEPS=$FUSESR_L_STEPS; fi
  CMD=(train --model "$M" --data "$DS" -o "$R" --config benchmarks/pretrain.toml --max-steps "$STEPS"
       --set run.threads="$THREADS")
  if [ -n "${INIT:-}" ]; then I=${INIT//<M>/$M}; CMD+=(--set "run.init_from=\"${I//<D>/${M//-/_}}\""); fi
  [ -n "${LR:-}" ] && CMD+=(--set "optim.lr=$LR")
  for KV in ${SET:-}; do CMD+=(--set "${KV//<M>/$M}"); done
  mkdir -p "$R"
  { printf 'blendsr'; printf ' %q' "${CMD[@]}"; echo; } > "$R/command.txt"
  EXTRA=(); [ -f "$R/checkpoints/last.pt" ] && EXTRA+=(--resume)
  [ -n "${MINUTES:-}" ] && EXTRA+=(--minutes "$MINUTES")
  $PY -m gbuffer_export.cli "${CMD[@]}" "${EXTRA[@]}"
done
ENV="FUSESR_STEPS=$FUSESR_STEPS FUSESR_L_STEPS=$FUSESR_L_STEPS${INIT:+ INIT='$INIT'}${LR:+ LR=$LR}${SET:+ SET='$SET'}"
if [ "${RELEASE:-1}" = 1 ]; then  # RELEASE=0: train only (the script still exits 0)
  $PY benchmarks/release_weights.py "$DS" "$RUNS" --models "$(echo $MODELS | tr ' ' ,)" --env "$ENV"
fi

#!/usr/bin/env bash
# Every network of BlendSR trained at equal steps on one dataset with held-out assets, then one
# `blendsr bench models` table and Pareto plot on its test split (docs/results-history.md, "Networks on one dataset").
#   1. renders benchmarks/networks_dataset.toml (12 clips; resumes when DATASET exists),
#   2. trains each learned model for STEPS steps with its paper's losses (examples/*_config.toml) and the same
#      crop, batch and optimiser length; RDG on windows of WINDOW frames (the other recurrent
#      models: their configs' windows),
#   3. scores every model and the non-learned baselines on the test split (assets never seen in training).
# Usage: benchmarks/networks.sh [DATASET] [RUNS] [OUT]
#   STEPS (default 600), THREADS (1), MODELS (the learned runs, space-separated), BENCH=0: train only (to train
#   in several processes, then bench once)
set -euo pipefail
cd "$(dirname "$0")/.."
DS=${1:-datasets/networks}
RUNS=${2:-runs/networks}
OUT=${3:-docs/bench/networks}
STEPS=${STEPS:-600}
THREADS=${THREADS:-1}
WINDOW=${WINDOW:-8}   # RDG windows (the paper: 15; the clips have 12 frames); nsrd and nsrr-fec: their configs
PY=${PY:-.venv/bin/python}
MODELS=${MODELS:-"fusesr fusesr-l rdg rdg-s rdg-s-demod rdg-s-nogbuf rdg-s-nobrdf rdg-s-nomotion nsrd nsrr nsrr-fec fourier-sr fourier-sr-lr1e-4"}
export MALLOC_MMAP_THRESHOLD_=4294967296 MALLOC_TRIM_THRESHOLD_=68719476736
B="$PY -m gbuffer_export.cli"
$B dataset benchmarks/networks_dataset.toml -o "$DS" --workers 1 --no-progress
$B validate "$DS" --quick --no-progress
COMMON=(--max-steps "$STEPS" --set data.crop=16 --set data.batch_size=4 --set data.val_frames=0
        --set run.progress=false --set run.threads="$THREADS" --set run.checkpoint_every=100)
train() {  # RUN-NAME MODEL CONFIG [--set ...]
  local name=$1 model=$2 config=$3; shift 3
  local resume=(); [ -f "$RUNS/$name/checkpoints/last.pt" ] && resume=(--resume)
  [ -f "$RUNS/$name/summary.json" ] && return 0   # finished
  $B train --model "$model" --data "$DS" -o "$RUNS/$name" --config "$config" "${COMMON[@]}" "$@" "${resume[@]}"
}
LIST=bicubic,demod-bilinear,demod-jbu
for M in $MODELS; do
  case $M in
    fusesr|fusesr-l) train "$M" "$M" examples/train_config.toml --set optim.warmup_steps=0 ;;
    rdg|rdg-s) train "$M" "$M" examples/rdg_config.toml --set data.window="$WINDOW" ;;
    rdg-s-demod) train "$M" rdg-s examples/rdg_config.toml --set data.window="$WINDOW" --set model.rdg-s.demod=true ;;
    rdg-s-nogbuf) train "$M" rdg-s examples/rdg_config.toml --set data.window="$WINDOW" --set 'model.rdg-s.gbuffers=[]' ;;
    rdg-s-nobrdf) train "$M" rdg-s examples/rdg_config.toml --set data.window="$WINDOW" \
                    --set 'model.rdg-s.gbuffers=["normal","depth","motion"]' ;;
    rdg-s-nomotion) train "$M" rdg-s examples/rdg_config.toml --set data.window="$WINDOW" \
                      --set 'model.rdg-s.gbuffers=["normal","brdf","depth"]' ;;
    nsrd) train "$M" nsrd examples/nsrd_config.toml ;;
    nsrr) train "$M" nsrr examples/nsrr_fec_config.toml --set data.window=0 ;;
    nsrr-fec) train "$M" nsrr-fec examples/nsrr_fec_config.toml ;;
    fourier-sr) train "$M" fourier-sr examples/fourier_sr_config.toml --set optim.lr=5e-4 ;;  # 1e-4: 300k steps
    fourier-sr-lr1e-4) train "$M" fourier-sr examples/fourier_sr_config.toml ;;             # the authors' lr
    *) echo "unknown model $M" >&2; exit 2 ;;
  esac
  base=${M%%-s-*}; [ "$base" = "$M" ] || base=rdg-s
  [ "$M" = fourier-sr-lr1e-4 ] && base=fourier-sr
  LIST="$LIST,$base:$RUNS/$M/checkpoints/last.pt"
done
[ "${BENCH:-1}" = 1 ] || exit 0
$B bench models --data "$DS" --split test --threads "$THREADS" --flip -o "$OUT" --models "$LIST"

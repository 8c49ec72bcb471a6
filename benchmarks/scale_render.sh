#!/usr/bin/env bash
# The scale round's render in the order its runs wait for (issue 54; docs/training.md, "The scale set's round"):
#   1. the index (blendsr dataset --limit 0: plans every clip, renders nothing);
#   2. the val split (the val rule of every release reads it);
#   3. the training subsets of benchmarks/data_scaling.py as prefixes, smallest first (--multiples 1, then 1,3, then
#      1,3,10: each list holds the one before), so that each scaling run trains while the larger subsets render;
#   4. the test split (read once, at the round's end);
#   5. the rest of the set.
# Every step resumes (a killed run loses at most the frames in flight); rerun the same command on a new machine or
# after a stop. The subset lists go to LISTS (default DATASET.lists), written before any render.
# Usage: benchmarks/scale_render.sh [DATASET] [SPEC]   (defaults datasets/scale, examples/dataset_scale.toml)
#   W (default 2): --workers; SUBSETS (default "1 1,3 1,3,10"): the --multiples of each list, in render order;
#   UNIT: --unit-pixels of data_scaling.py (default: its own); DRY=1: print the commands, run only steps 1 and the
#   lists.
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${1:-datasets/scale}
SPEC=${2:-examples/dataset_scale.toml}
W=${W:-2}
LISTS=${LISTS:-$DATA.lists}
PY=${PY:-.venv/bin/python}
B=("$PY" -m gbuffer_export.cli dataset "$SPEC" -o "$DATA" --no-progress)
run() { echo "+ $*"; [ -n "${DRY:-}" ] || "$@"; }
[ -f "$DATA/dataset.json" ] || "${B[@]}" --limit 0
mkdir -p "$LISTS"
lists=()
for m in ${SUBSETS:-1 1,3 1,3,10}; do
  f="$LISTS/subset_${m//,/_}.txt"
  PYTHONPATH=$PWD "$PY" benchmarks/data_scaling.py "$DATA" -o - --multiples "$m" ${UNIT:+--unit-pixels "$UNIT"} \
      --list-clips "$f"
  lists+=("$f")
done
run "${B[@]}" --workers "$W" --split val
for f in "${lists[@]}"; do run "${B[@]}" --workers "$W" --clips "@$f"; done
run "${B[@]}" --workers "$W" --split test
run "${B[@]}" --workers "$W"

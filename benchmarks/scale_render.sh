#!/usr/bin/env bash
# The scale round's render in the order its runs wait for (issue 54; docs/training.md, "The scale set's round"):
#   1. the index (blendsr dataset --limit 0: plans every clip, renders nothing);
#   2. the val split (the val rule of every release reads it);
#   3. the training subsets of benchmarks/data_scaling.py as prefixes, smallest first (--multiples 1, then 1,3, then
#      1,3,10: each list holds the one before), so that each scaling run trains while the larger subsets render;
#   4. the test split (read once, at the round's end);
#   5. the rest of the set.
# `--order train-first` renders every train clip before val and `--order mixed` interleaves the splits; the release
# rule needs val first and the scaling runs their subsets next, hence the lists. Every step resumes (a killed run
# loses at most the frames in flight): rerun the same command after a stop or on a new machine. The subset lists go
# to LISTS (default DATASET.lists), written before any render.
# Usage: benchmarks/scale_render.sh [DATASET] [SPEC]   (defaults, in the repository: datasets/scale,
#   examples/dataset_scale.toml; paths given are read from where the command runs)
#   W (default 2): --workers; SUBSETS (default "1 1,3 1,3,10"): the --multiples of each list, in render order
#   (empty: no lists); UNIT: --unit-pixels of data_scaling.py (default: its own); DRY=1: print the render commands,
#   write only the index and the lists.
set -euo pipefail
here=$PWD
abs() { case $1 in /*) echo "$1" ;; *) echo "$here/$1" ;; esac; }
cd "$(dirname "$0")/.."
DATA=${1:+$(abs "$1")}; DATA=${DATA:-datasets/scale}
SPEC=${2:+$(abs "$2")}; SPEC=${SPEC:-examples/dataset_scale.toml}
W=${W:-2}
LISTS=${LISTS:-$DATA.lists}
PY=${PY:-.venv/bin/python}
B=("$PY" -m gbuffer_export.cli dataset "$SPEC" -o "$DATA" --no-progress)
run() { echo "+ $*"; [ "${DRY:-0}" = 1 ] || "$@"; }
[ -f "$DATA/dataset.json" ] || "${B[@]}" --limit 0
mkdir -p "$LISTS"
lists=()
read -r -a multiples <<< "${SUBSETS-1 1,3 1,3,10}"
for m in "${multiples[@]}"; do
  f="$LISTS/subset_${m//,/_}.txt"
  PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} "$PY" benchmarks/data_scaling.py "$DATA" -o - --multiples "$m" ${UNIT:+--unit-pixels "$UNIT"} \
      --list-clips "$f"
  lists+=("$f")
done
run "${B[@]}" --workers "$W" --split val
for f in "${lists[@]}"; do run "${B[@]}" --workers "$W" --clips "@$f"; done
run "${B[@]}" --workers "$W" --split test
run "${B[@]}" --workers "$W"

#!/usr/bin/env bash
# What limits the learned margin over demod-jbu, measured (docs/results-history.md, "What limits the learned margin"):
#   benchmarks/limits.sh [OUT=runs/limits] [DATASET=datasets/large]
# 1. resolution and ground-truth samples: the five test assets rendered three ways (benchmarks/limits/*.toml:
#    256x144 32 spp, 512x288 32 spp, 256x144 128 spp; same cameras), the shipped models scored on each;
# 2. distinct training scenes: FuseSR trained at equal steps on nested sets of 1, 4, 16, all scene ids of DATASET's
#    train split (benchmarks/data_scaling.py --by scene), scored on its test split; 4, 16, all again at 2000 steps;
# 3. training length: FuseSR on the whole train split for 250, 500, 1000 and 2000 steps (each its own cosine).
# Every training starts from scratch with benchmarks/pretrain.toml (zero_init_refine: at the guided base).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-runs/limits}
DATASET=${2:-datasets/large}
PY=.venv/bin/python
MODELS=${MODELS:-bicubic,demod-bilinear,demod-jbu,pretrained:fusesr,pretrained:fusesr-l}
for v in base gt128 hires; do
  .venv/bin/blendsr dataset "benchmarks/limits/$v.toml" -o "$OUT/data/$v" --workers 2 --no-progress
  $PY benchmarks/per_asset.py "$OUT/data/$v" --split test --models "$MODELS" -o "$OUT/$v.json" > "$OUT/$v.md"
done
export MALLOC_MMAP_THRESHOLD_=4294967296 MALLOC_TRIM_THRESHOLD_=68719476736
$PY benchmarks/data_scaling.py "$DATASET" -o "$OUT/scenes" --runs "$OUT/runs" --by scene --counts 1,4,16,all \
    --steps 500 --threads 2
$PY benchmarks/data_scaling.py "$DATASET" -o "$OUT/steps" --runs "$OUT/runs" --by scene --counts all \
    --steps 250,500,1000,2000 --threads 2     # reuses the run on all scenes at 500 steps
$PY benchmarks/data_scaling.py "$DATASET" -o "$OUT/scenes2000" --runs "$OUT/runs" --by scene --counts 4,16,all \
    --steps 2000 --threads 2                  # reuses the run on all scenes at 2000 steps

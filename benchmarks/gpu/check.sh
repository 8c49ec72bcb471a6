#!/usr/bin/env bash
# One device call (its steps are capped by timeouts summing to 8 min 50 s, inside a 600 s call; never run yet: no GPU was lent) for the GPU items of docs/results.md ("GPU measurements"):
# the CUDA-only tests, the 1080p 4x speed table of every model, loader against step, training throughput.
# Needs the wheels of fetch_wheels.sh carried as .whl. Writes its logs and tables to $OUT (default gpu_out).
# Usage: run(command="bash benchmarks/gpu/check.sh", carry=[".whl"], timeout_s=600)
set -u
OUT=${OUT:-gpu_out}; mkdir -p "$OUT"; export PYTHONUNBUFFERED=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl || exit 1
python3 -m pip install -q --no-index --no-deps --no-build-isolation --no-compile --target /tmp/site . || exit 1
export PYTHONPATH=/tmp/site PATH=/tmp/site/bin:$PATH
{ nvidia-smi -L; python3 -c "import torch; print(torch.__version__, torch.cuda.get_device_name())"; } | tee "$OUT/device.txt"
step() { echo "== $1 ($(date +%T))"; shift; timeout "$@"; echo "exit $?"; }
step "CUDA-only tests" 120 python3 -m pytest -q -p no:cacheprovider -k cuda tests/test_training_fastpath.py \
    tests/test_cli_interface.py 2>&1 | tee "$OUT/cuda_tests.log"
step "speed table" 200 blendsr bench models --device cuda --size 1920x1080 --precision none,bf16 --compile off,on \
    --eager-reference --repeats 30 --warmup 5 -o "$OUT/speed" 2>&1 | tee "$OUT/bench_models.log"
for w in 0 8; do
  step "loader, $w workers" 45 blendsr bench loader --device cuda --model fusesr --batch 16 --crop 32 --amp bf16 \
      --batches 60 --steps 20 --workers $w 2>&1 | tee -a "$OUT/bench_loader.log"
done
python3 -c "from gbuffer_export.synthetic import make_synthetic_clip as m; m('/tmp/clip', frames=range(1, 9), hr_size=(512, 288))"
for w in 0 8; do
  step "train throughput, $w workers" 60 blendsr train --model fusesr --data /tmp/clip -o /tmp/tp$w --max-steps 300 \
      --set data.batch_size=16 --set data.crop=32 --set 'run.amp="bf16"' --set run.progress=false \
      --set data.workers=$w 2>&1 | tail -3 | tee -a "$OUT/train.log"
  cp /tmp/tp$w/summary.json "$OUT/train_summary_w$w.json" 2>/dev/null
done

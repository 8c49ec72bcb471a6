#!/usr/bin/env bash
# One device call for the GPU items of docs/results.md. Two sets, chosen by CHECK (each fits one 600 s call):
# CHECK=all (default; "GPU: CUDA tests, 1080p speed, profile and training throughput"): the CUDA-only tests, the
#   1080p 4x speed table of every model (eager, then compiled), loader against step, training throughput. Step
#   timeouts sum to 530 s (measured on an H200, 2026-11-26: 52, 69, 14+17, 28+19 s, and about 160 s for the tests,
#   which compile 13 models). Writes log.txt, speed_eager.json/.md, speed_compiled.json, train_summary_w0.json,
#   train_summary_w8.json.
# CHECK=speed (issue 44, the fused HR stage; docs/evaluation.md "Inference paths"): the CUDA tests of the fused path
#   (Triton kernels against the torch path, two launches, every guided model against the CPU fp32 reference), the
#   1080p 4x table of the guided models with --path reference,fast,fused (bf16, eager and compiled; kernels per
#   frame, ratio to the roofline, each output checked against the fp32 reference), and the profile of the fast and
#   fused paths. Step timeouts sum to 490 s (not yet run on a GPU). Writes log.txt, speed_paths.json/.md, profile_paths.txt.
# CHECK=clamp: the CUDA tests of the fused path (the residual clamps' kernel included) and the 1080p frame time of
#   fusesr-l and fusesr-fast with residual_clamp none, lr-range and lr-guided (bf16, fused path). Writes log.txt,
#   speed_clamp.json/.md.
# CHECK=graph (issue 58: one CUDA graph per frame, the replay timer; docs/evaluation.md "Inference paths"): the CUDA
#   tests of the paths (FrameGraph against eager; InferenceModel.step of every recurrent model, output and state,
#   graph against the same prepared model run eagerly), then the 1080p 4x table of every model
#   with --path fast,fused,graph (bf16, eager): graph variants timed as N=200 replays between two CUDA events in 5
#   rounds (median, spread), kernels per frame, ratio to the roofline, every output against the fp32 reference
#   (bilinear's graph row on an H200: 0.067 ms, 12x its roofline: about 17 graph nodes at about 4 us, a node's
#   floor). Step timeouts sum to 500 s (H200, 2026-11-29: 86 s of tests before the five recurrent cases, about 100 s
#   of table). Writes log.txt,
#   speed_graph.json/.md; a second call on another machine:
#   python3 benchmarks/gpu/compare.py A/speed_graph.json B/speed_graph.json (the spread between machines).
# CHECK=nss (issue 57 item 4): one optimizer step of Arm's NSS-v1 model by the model gym's Trainer on a BlendSR
#   export: benchmarks/gpu/nss_gym_step.sh, which needs .nss-gym (benchmarks/gpu/fetch_nss_gym.sh) carried instead of
#   .whl: run(command="CHECK=nss bash benchmarks/gpu/check.sh", carry=[".nss-gym"], timeout_s=600).
# Needs the wheels of fetch_wheels.sh carried as .whl (about 5 MB; the image's torch brings triton).
# Usage: run(command="bash benchmarks/gpu/check.sh", carry=[".whl"], timeout_s=600)
#        run(command="CHECK=speed bash benchmarks/gpu/check.sh", carry=[".whl"], timeout_s=600)
#        run(command="CHECK=graph bash benchmarks/gpu/check.sh", carry=[".whl"], timeout_s=600)
# CPU dry run of the same steps: DEV=cpu SIZE=128x72 REPEATS=2 STEPS=5 [CHECK=speed COMPILE=off] bash benchmarks/gpu/check.sh
set -u
[ "${CHECK:-}" = nss ] && exec bash "$(dirname "$0")/nss_gym_step.sh"
OUT=${OUT:-gpu_out}; DEV=${DEV:-cuda}; SIZE=${SIZE:-1920x1080}; REPEATS=${REPEATS:-30}; STEPS=${STEPS:-300}
CHECK=${CHECK:-all}; COMPILE=${COMPILE:-both}  # COMPILE: the speed set's --compile (off for a quick CPU dry run)
mkdir -p "$OUT"; export PYTHONUNBUFFERED=1; W=/tmp/blendsr_gpu; rm -rf "$W"; mkdir -p "$W"; LOG="$OUT/log.txt"
if [ "$DEV" = cuda ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl || exit 1
  python3 -m pip install -q --no-index --no-deps --no-build-isolation --no-compile --ignore-requires-python --target /tmp/site . || exit 1
  # pip --target writes no console script for a local package: a two-line blendsr on PATH instead
  mkdir -p /tmp/site/bin; printf '#!/bin/sh\nexec python3 -c "import sys; from gbuffer_export.cli import main; sys.exit(main())" "$@"\n' \
      > /tmp/site/bin/blendsr && chmod +x /tmp/site/bin/blendsr
  export PYTHONPATH=/tmp/site PATH=/tmp/site/bin:$PATH
  nvidia-smi -L >> "$LOG"
fi
python3 -c "import torch; print('torch', torch.__version__, torch.cuda.get_device_name() if torch.cuda.is_available() else 'cpu')" >> "$LOG"
python3 -c "import triton; print('triton', triton.__version__)" >> "$LOG" 2>&1
step() { echo "== $1 ($(date +%T))" >> "$LOG"; shift; timeout "$@" >> "$LOG" 2>&1; echo "exit $?" >> "$LOG"; }
bench=(blendsr bench models --device "$DEV" --size "$SIZE" --repeats "$REPEATS" --warmup 5 --no-progress)
if [ "$CHECK" = clamp ]; then  # the residual clamps' CUDA tests and their cost on the fused path (about 150 s)
  [ "$DEV" = cuda ] && step "CUDA tests of the fused path" 150 python3 -m pytest -v -p no:cacheprovider \
      --durations=0 -k cuda tests/train/hr_stage_cases.py
  step "speed, fusesr-l and fusesr-fast with each residual_clamp (bf16, fused, eager and compiled)" 150 \
      "${bench[@]}" --precision bf16 --compile "$COMPILE" --path fused --models \
      'pretrained:fusesr-l?residual_clamp=none,pretrained:fusesr-l?residual_clamp=lr-range,pretrained:fusesr-l?residual_clamp=lr-guided,pretrained:fusesr-fast?residual_clamp=none,pretrained:fusesr-fast?residual_clamp=lr-range,pretrained:fusesr-fast?residual_clamp=lr-guided' \
      -o "$W/clamp"
  cp "$W/clamp/bench_speed.json" "$OUT/speed_clamp.json" && cp "$W/clamp/bench_speed.md" "$OUT/speed_clamp.md"
  exit 0
fi
if [ "$CHECK" = graph ]; then  # issue 58: one CUDA graph per frame, every model (about 500 s of step timeouts)
  [ "$DEV" = cuda ] && step "CUDA tests of the inference paths and the fused HR stage" 200 python3 -m pytest -v \
      -p no:cacheprovider --durations=0 -k cuda tests/train/test_inference_paths.py tests/train/hr_stage_cases.py
  step "speed table, fast / fused / graph (bf16; graph: CUDA graph replays)" 300 "${bench[@]}" --precision bf16 \
      --compile off --path fast,fused,graph --repeats 200 -o "$W/graph" \
      --models bilinear,bicubic,demod-bilinear,demod-jbu,fusesr-fast,fusesr-l,fusesr,nsrd,rdg
  cp "$W/graph/bench_speed.json" "$OUT/speed_graph.json" && cp "$W/graph/bench_speed.md" "$OUT/speed_graph.md"
  exit 0
fi
if [ "$CHECK" = speed ]; then
  GUIDED=demod-bilinear,demod-jbu,fusesr-fast,fusesr-l,fusesr
  [ "$DEV" = cuda ] && step "CUDA tests of the fused path" 150 python3 -m pytest -v -p no:cacheprovider \
      --durations=0 -k cuda tests/train/hr_stage_cases.py
  step "speed table, reference / fast / fused (bf16, eager and compiled)" 270 "${bench[@]}" --models "$GUIDED" \
      --precision bf16 --compile "$COMPILE" --path reference,fast,fused -o "$W/paths"
  cp "$W/paths/bench_speed.json" "$OUT/speed_paths.json" && cp "$W/paths/bench_speed.md" "$OUT/speed_paths.md"
  step "profile, fast and fused paths (bf16, eager)" 70 python3 benchmarks/gpu/profile.py --device "$DEV" \
      --size "$SIZE" --models "$GUIDED" --path fast,fused --repeats 10 -o "$OUT/profile_paths.txt"
  exit 0
fi
step "speed table, eager" 80 "${bench[@]}" --precision none,bf16 --compile off --eager-reference -o "$W/eager"
cp "$W/eager/bench_speed.json" "$OUT/speed_eager.json" && cp "$W/eager/bench_speed.md" "$OUT/speed_eager.md"
step "speed table, compiled (the targets' models, bf16)" 120 "${bench[@]}" --compile on -o "$W/compiled" \
    --models fusesr-fast,fusesr-l,fusesr,demod-bilinear,demod-jbu --precision bf16
cp "$W/compiled/bench_speed.json" "$OUT/speed_compiled.json"
for w in 0 8; do
  step "loader, $w workers" 25 blendsr bench loader --device "$DEV" --model fusesr --batch 16 --crop 32 --amp bf16 \
      --batches 60 --steps 20 --workers $w
done
python3 -c "from gbuffer_export.synthetic import make_synthetic_clip as m; m('$W/clip', frames=range(1, 9), hr_size=(512, 288))"
for w in 0 8; do
  step "train throughput, $w workers" 40 blendsr train --model fusesr --data "$W/clip" -o "$W/tp$w" \
      --max-steps "$STEPS" --set data.batch_size=16 --set data.crop=32 --set 'run.amp="bf16"' \
      --set run.progress=false --set data.workers=$w --set "run.device=\"$DEV\""
  cp "$W/tp$w/summary.json" "$OUT/train_summary_w$w.json"
done
[ "$DEV" = cuda ] && step "CUDA-only tests" 200 python3 -m pytest -v -p no:cacheprovider --durations=0 -k cuda \
    tests/train/test_fastpath.py tests/cli/test_interface.py  # the fused path's CUDA tests: CHECK=speed

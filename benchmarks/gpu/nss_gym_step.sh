#!/usr/bin/env bash
# One optimizer step of Arm's NSS-v1 model, by the model gym's own Trainer (benchmarks/nss_gym_step.py), on a
# BlendSR export, on the CUDA machine (issue 57 item 4). Nothing is fetched there: it needs .nss-gym/ staged here by
# benchmarks/gpu/fetch_nss_gym.sh (the wheels the image lacks and the export's safetensors; about 18 MB).
# Usage: run(command="bash benchmarks/gpu/nss_gym_step.sh", carry=[".nss-gym"], timeout_s=600)
#        (or CHECK=nss bash benchmarks/gpu/check.sh). About 1-5 min: slangtorch JIT-builds the NSS shaders first.
# Writes $OUT/log.txt and $OUT/nss_gym_step.json (losses before/after, lr, grad norm, parameters changed, stages).
# PY, NGMG_STUBS, EXTRA_PATH: for a CPU dry run of this script elsewhere (fetch_nss_gym.sh says how).
# Exit: 0 the step ran; 2 .nss-gym missing; 4 no CUDA compiler (slangtorch needs nvcc, ninja and a C++ compiler);
# 3 the forward refused (no CUDA device); 1 anything else (the traceback is in the log).
set -u -o pipefail
OUT=${OUT:-gpu_out}; STAGE=${STAGE:-.nss-gym}; W=/tmp/blendsr_nss_gym; PY=${PY:-python3}
mkdir -p "$OUT"; LOG=$OUT/log.txt; export PYTHONUNBUFFERED=1; rm -rf "$W" /tmp/ngmg-site
say() { echo "$*" | tee -a "$LOG"; }
if [ ! -d "$STAGE/wheels" ] || [ ! -d "$STAGE/safetensors" ]; then
  say "nss_gym_step.sh: $STAGE/wheels or $STAGE/safetensors missing: run benchmarks/gpu/fetch_nss_gym.sh on the development machine and carry .nss-gym"
  exit 2
fi
"$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/ngmg-site \
    "$STAGE"/wheels/*.whl 2>&1 | tee -a "$LOG" || exit 1
# the image's torchvision matches its torch: stub only executorch (model export) and pyiqa (an unused metric)
export PYTHONPATH=$PWD/benchmarks/ngmg_stubs:/tmp/ngmg-site${EXTRA_PATH:+:$EXTRA_PATH} NGMG_STUBS=${NGMG_STUBS:-executorch pyiqa}
{
  nvidia-smi -L
  "$PY" -c "import torch, torchvision; print('torch', torch.__version__, 'CUDA', torch.version.cuda, 'torchvision', torchvision.__version__, 'device', torch.cuda.get_device_name() if torch.cuda.is_available() else None)"
  "$PY" -c "from torch.utils.cpp_extension import CUDA_HOME; print('CUDA_HOME', CUDA_HOME)"
  echo "nvcc: $(command -v nvcc || echo missing) $(nvcc --version 2>/dev/null | tail -1)"
  echo "ninja: $(command -v ninja || echo missing); c++: $(command -v c++ || echo missing)"
} 2>&1 | tee -a "$LOG"
if ! command -v nvcc >/dev/null && ! "$PY" -c "from torch.utils.cpp_extension import CUDA_HOME; assert CUDA_HOME" 2>/dev/null; then
  say "nss_gym_step.sh: no nvcc on PATH and no CUDA_HOME: slangtorch JIT-builds the NSS-v1 Slang shaders with nvcc, ninja and a C++ compiler (torch.utils.cpp_extension) at the first forward, so the step cannot run on this image"
  exit 4
fi
# torch's CUDA headers include cusparse.h etc.; where the toolkit lacks them, take the pip nvidia-* headers
CH=$("$PY" -c "from torch.utils.cpp_extension import CUDA_HOME; print(CUDA_HOME or '')" 2>/dev/null)
if [ ! -e "$CH/include/cusparse.h" ]; then
  for d in $("$PY" -c "import nvidia; print(*nvidia.__path__)" 2>/dev/null); do
    for h in $(find "$d" -name cusparse.h -o -name cublas_v2.h 2>/dev/null); do export CPATH=$(dirname "$h")${CPATH:+:$CPATH}; done
  done
  say "no cusparse.h in CUDA_HOME (${CH:-none})/include; CPATH=${CPATH:-none found}"
fi
timeout 500 "$PY" benchmarks/nss_gym_step.py "$STAGE/safetensors" "$W" --json "$OUT/nss_gym_step.json" 2>&1 \
  | tee -a "$LOG"
rc=$?
say "exit $rc"
exit $rc

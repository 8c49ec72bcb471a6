#!/usr/bin/env bash
# Load a BlendSR NSS export with Arm's own code (neural-graphics-model-gym): its EXR -> safetensors converter
# (scripts/safetensors_generator, reader NSSv1_0_1, which lives in the repository, not in the wheel) and then its
# NSSDataset (ng_model_gym.usecases.nss.data.dataset, the class its trainer uses), one training window.
# Not part of the test suite (installs a virtual environment of its own).
#
#   benchmarks/check_nss_consumer.sh [NSS_EXPORT]      (default: render a tiny clip with --scales 2,4 and export
#                                                       it: Arm's converter reads the x2/ level only)
#
# The temporary folder (the render, the default export, the safetensors, the converter's log) is removed on exit;
# KEEP=1 keeps it and prints where it is.
#
# A local clone serves where GitHub cannot be reached: NGMG_REPO=/path/to/neural-graphics-model-gym.
#
# Environment:
#   VENV=...              the virtual environment to create/reuse (default .venv-ngmg in the repository)
#   NGMG_REPO=...         a checkout of arm/neural-graphics-model-gym (default: git clone into $VENV/src)
#   NGMG_REUSE_SITE=...   a site-packages holding torch, numpy and OpenEXR to reuse (e.g. BlendSR's venv's);
#                         then ng-model-gym is installed with --no-deps plus its light dependencies, instead of
#                         the full pinned set (torch 2.11 with CUDA, executorch, ...: gigabytes). executorch 1.2.0
#                         (the model gym's export path) and torchvision (torcheval's FID) do not import against
#                         another torch (aten.transpose.Dimname / torchvision::nms), so this mode replaces both,
#                         and pyiqa (an unused metric), with stub modules (benchmarks/ngmg_stubs/sitecustomize.py):
#                         the data and training code never calls them.
#   PY=python3.11         the interpreter (ng-model-gym needs Python 3.10-3.12)
#   STEP=1                after the dataset, one optimizer step of the gym's NSS-v1 model with its own Trainer
#                         (benchmarks/nss_gym_step.py; STEP_ARGS passes options, STEP_JSON=FILE keeps its record).
#                         Exit 0: the step ran; 3: the forward refused a machine without CUDA (Slang shaders)
#   STAGE=DIR             copy the converter's safetensors to DIR/safetensors (for the GPU step, which has no
#                         Blender: benchmarks/gpu/fetch_nss_gym.sh)
set -euo pipefail
REPO=$(cd "$(dirname "$0")/.." && pwd)
VENV=${VENV:-$REPO/.venv-ngmg}
PY=${PY:-python3.11}
WORK=$(mktemp -d /tmp/blendsr-ngmg.XXXXXX)
cleanup() { if [ -n "${KEEP:-}" ]; then echo "kept $WORK"; else rm -rf "$WORK"; fi; }
trap cleanup EXIT
BLENDSR_PY=${BLENDSR_PY:-$REPO/.venv/bin/python}
[ -x "$BLENDSR_PY" ] || BLENDSR_PY=python3

if [ ! -x "$VENV/bin/python" ]; then
  "$PY" -m venv "$VENV"
  if [ -n "${NGMG_REUSE_SITE:-}" ]; then
    echo "$NGMG_REUSE_SITE" > "$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')/blendsr-reuse.pth"
    "$VENV/bin/pip" install -q --no-deps ng-model-gym
    "$VENV/bin/pip" install -q safetensors torcheval tqdm pydantic rich typer click psutil gputil gpustat \
      memory-profiler ruamel.yaml tabulate joblib cloudpickle slangtorch==1.3.19 tensorboard lightning-utilities
    "$VENV/bin/pip" install -q --no-deps torchao==0.17.0 tosa-tools==2026.2.1 lpips==0.1.4 torchmetrics==1.8.2
    touch "$VENV/reuse-site"
  else
    "$VENV/bin/pip" install -q ng-model-gym
  fi
fi
"$VENV/bin/python" -c "import importlib.metadata as m; print('ng-model-gym', m.version('ng-model-gym'))"

if [ -z "${NGMG_REPO:-}" ]; then
  NGMG_REPO=$VENV/src/neural-graphics-model-gym
  [ -d "$NGMG_REPO" ] || git clone -q --depth 1 https://github.com/arm/neural-graphics-model-gym "$NGMG_REPO"
fi

{ [ -e "$VENV/reuse-site" ] || [ -d "$VENV/stubs" ]; } && export PYTHONPATH=$REPO/benchmarks/ngmg_stubs  # stubs/: an older venv
EXPORT=${1:-}
if [ -z "$EXPORT" ]; then
  (cd "$REPO" && PYTHONPATH=$REPO "$BLENDSR_PY" -m gbuffer_export.cli render -o "$WORK/clip" --hr-size 64x36 \
     --frames 1:6 --scales 2,4 --hr-spp 2 --lr-spp 1 --threads 1 --buffers radiance,depth,motion --no-progress)
  (cd "$REPO" && PYTHONPATH=$REPO "$BLENDSR_PY" -m gbuffer_export.cli export-dataset "$WORK/clip" --format nss \
     -o "$WORK/nss")
  EXPORT=$WORK/nss
fi

echo "== Arm's converter (scripts.safetensors_generator.safetensors_writer, reader NSSv1_0_1) on $EXPORT"
(cd "$NGMG_REPO" && "$VENV/bin/python" -m scripts.safetensors_generator.safetensors_writer -src "$EXPORT" \
   -dst "$WORK/st" -threads 1 -reader NSSv1_0_1 -logging_output_dir "$WORK/log")
ls -R "$WORK/st" | head

echo "== Arm's NSSDataset on the safetensors"
"$VENV/bin/python" - "$WORK/st" <<'PY'
import sys
from pathlib import Path
from types import SimpleNamespace

import safetensors
import torch
from ng_model_gym.core.data.data_utils import DataLoaderMode
from ng_model_gym.usecases.nss.data.dataset import NSSDataset

root = Path(sys.argv[1])
for p in sorted(root.rglob("*.safetensors")):
    with safetensors.safe_open(p, framework="pt") as f:
        print(p.name, {k: tuple(f.get_slice(k).get_shape()) for k in sorted(f.keys())})
cfg = SimpleNamespace(
    dataset=SimpleNamespace(path=SimpleNamespace(train=root), exposure=2, tonemapper="reinhard",
                            gt_augmentation=False, health_check=False),
    model=SimpleNamespace(recurrent_samples=2, scale=2.0))
ds = NSSDataset(cfg, DataLoaderMode.TRAIN)
x, y = ds[0]
show = lambda d: {k: (tuple(v.shape), str(v.dtype)) for k, v in d.items()} if isinstance(d, dict) else tuple(d.shape)
print("NSSDataset windows:", len(ds))
print("x:", show(x))
print("y:", show(y))
m = x["motion"] if isinstance(x, dict) and "motion" in x else None
if m is not None:
    print("motion (pixels, as the model gym reads it): |max|", float(m.abs().max()))
print("OK: ng-model-gym's NSSDataset loaded the BlendSR export")

PY

if [ -n "${STAGE:-}" ]; then  # keep the converter's output for the GPU step (benchmarks/gpu/fetch_nss_gym.sh)
  rm -rf "$STAGE/safetensors" && mkdir -p "$STAGE" && cp -r "$WORK/st" "$STAGE/safetensors"
  echo "staged $(du -sh "$STAGE/safetensors" | cut -f1) of safetensors in $STAGE/safetensors"
fi
if [ -n "${STEP:-}" ]; then
  echo "== one optimizer step of the model gym's NSS-v1 model (benchmarks/nss_gym_step.py)"
  rc=0
  "$VENV/bin/python" "$REPO/benchmarks/nss_gym_step.py" "$WORK/st" "$WORK/step" --json "${STEP_JSON:-$WORK/step.json}" \
    ${STEP_ARGS:-} || rc=$?
  [ "$rc" = 3 ] && echo "the model gym's NSS-v1 forward needs CUDA (its Slang shaders): run benchmarks/gpu/nss_gym_step.sh there"
  exit "$rc"
fi

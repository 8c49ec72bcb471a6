#!/usr/bin/env bash
# Stage, on the development machine, what the GPU step of Arm's NSS model needs (benchmarks/gpu/nss_gym_step.sh),
# into .nss-gym/ (ignored; carried to the device machine, which reaches no network and has no Blender):
#   .nss-gym/wheels/       ng-model-gym 0.4.0 (--no-deps) and the packages the CUDA image lacks, for its Python 3.12
#                          (the image holds torch 2.11 CUDA, torchvision, torchmetrics, tensorboard, numpy, rich, typer,
#                          ninja, nvcc); executorch and pyiqa are not carried but stubbed (benchmarks/ngmg_stubs)
#   .nss-gym/safetensors/  a tiny BlendSR render (64x36, 6 frames, scales 2,4) exported with --format nss and
#                          converted by Arm's own converter (benchmarks/check_nss_consumer.sh, Python 3.11 + bpy)
# Usage (repository root): NGMG_REPO=/path/to/neural-graphics-model-gym NGMG_REUSE_SITE=... \
#                          bash benchmarks/gpu/fetch_nss_gym.sh; echo /.nss-gym/ >> .git/info/exclude
# (NGMG_REPO and NGMG_REUSE_SITE as for check_nss_consumer.sh; SKIP_EXPORT=1 stages the wheels only; a CPU dry run
# of nss_gym_step.sh here: PYVER=3.11 STAGE=.nss-gym-311 SKIP_EXPORT=1, then PY=... STAGE=.nss-gym-311 there.)
set -euo pipefail
STAGE=${STAGE:-.nss-gym}; PYVER=${PYVER:-3.12}
rm -rf "$STAGE/wheels" && mkdir -p "$STAGE/wheels"
get() {
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version "$PYVER" --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    --platform manylinux1_x86_64 -d "$STAGE/wheels" "$@"
}
# the gym's own pins where it has them (its METADATA), else what pip serves
get ng-model-gym==0.4.0 slangtorch==1.3.19 pydantic==2.12.5 pydantic-core==2.41.5 annotated-types \
    typing-inspection lpips==0.1.4 torcheval==0.0.7 torchao==0.17.0 blessed wcwidth \
    memory-profiler==0.61.0 "typing-extensions>=4.14.1"
# GPUtil 1.4.0 and gpustat 1.1.1 are published as source archives only: build their (pure Python) wheels here
python3 -m pip wheel -q --no-deps -w "$STAGE/wheels" gputil==1.4.0 gpustat==1.1.1
# slangtorch's wheel carries Windows builds of the Slang compiler beside the Linux ones: drop them (and their
# RECORD lines), 21 MB -> about 11 MB, so that the repository and .nss-gym fit the 64 MiB a device call carries
python3 - "$STAGE"/wheels/slangtorch-*.whl <<'PY'
import os, sys, zipfile
src = sys.argv[1]; tmp = src + ".tmp"
windows = lambda name: name.endswith((".dll", ".exe", ".lib", ".pdb"))
with zipfile.ZipFile(src) as zin, zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as zout:
    for item in zin.infolist():
        if windows(item.filename):
            continue
        data = zin.read(item.filename)
        if item.filename.endswith(".dist-info/RECORD"):
            data = b"".join(l for l in data.splitlines(True) if not windows(l.split(b",")[0].decode()))
        zout.writestr(item, data)
os.replace(tmp, src)
PY
ls -l "$STAGE/wheels"
if [ -z "${SKIP_EXPORT:-}" ]; then
  STAGE=$STAGE bash benchmarks/check_nss_consumer.sh
fi
du -sh "$STAGE" "$STAGE"/*

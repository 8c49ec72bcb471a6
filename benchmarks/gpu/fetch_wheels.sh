#!/usr/bin/env bash
# Download, on the development machine, the wheels a bare CUDA machine lacks for BlendSR's torch half, into .whl/
# (Python 3.12 x86-64: the CUDA image's python3 holds torch, numpy, scipy, safetensors, onnx and pytest already;
# bpy 5.0.1 exists only for Python 3.11, so Cycles cannot run there). About 5 MB.
# Usage (repository root): bash benchmarks/gpu/fetch_wheels.sh; echo /.whl/ >> .git/info/exclude
set -euo pipefail
rm -rf .whl && mkdir -p .whl
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl \
    "OpenEXR>=3.2" "colour-science>=0.4.7" "pytorch-msssim>=1.0" "flip-evaluator>=1.5" "tomli-w>=1.0"
ls -l .whl

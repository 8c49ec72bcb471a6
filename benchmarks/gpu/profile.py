"""Where the 1080p 4x inference time of a model goes on a GPU: torch.profiler over a few forward passes of the
prepared inference path (bf16, channels-last, no compile; ``--path fast`` or ``fused``), kernels grouped by family.

Usage: python benchmarks/gpu/profile.py [--models demod-jbu,fusesr-fast,fusesr-l,fusesr] [--size 1920x1080]
       [--device cuda] [--repeats 10] [--path fast,fused] [-o OUT.txt]
Prints, per model and path: the kernels launched per frame, the GPU time per frame by family (fused HR stage,
convolution, element-wise, resampling, reduction, copy/layout, other; the share of the fused HR stage is the
issue-44 measure "HR stage at most a quarter of the frame") and the 15 most expensive kernels. Random inputs (as
bench models). On the CPU (``--device cpu``) the times are the operators' own CPU times and the fused HR stage is
its compiled C++ kernels (``cpp_fused``: without ``torch.compile`` of the model they are the HR stage's alone).
"""
from __future__ import annotations

import argparse
import re
import sys
from collections import defaultdict
from pathlib import Path

# Run as a script, this file's folder comes first on sys.path and the file shadows the standard library's profile
# module, which torch's compiler stack imports (through cProfile): take the folder off the path.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

# First match wins; the patterns name kernels as CUDA reports them (a bare "cat" would also match "scatter" and
# "replication", which the 2026-11-26 H200 run counted as copy/layout: docs/results.md says so).
FAMILIES = [("fused HR stage", r"hr_pixels_kernel|pixel_filter_kernel|cpp_fused"),
            ("convolution/matmul", r"conv|cudnn|implicit_gemm|gemm|xmma|cutlass|nvjet|wgrad|dgrad|fprop"),
            ("resampling", r"grid_sampler|upsample|interp"),
            ("gather/pad", r"scatter_gather|index_select|gather|replication_pad|reflection_pad"),
            ("copy/layout/cast", r"copy_kernel|catarraybatchedcopy|transpose|permute|memcpy|memset"),
            ("reduction", r"reduce_kernel|reduceop"),
            ("element-wise", r"elementwise|vectorized|unrolled|pointwise|triton")]


def family(name: str) -> str:
    low = name.lower()
    return next((f for f, pat in FAMILIES if re.search(pat, low)), "other")


def profile(name: str, size, device, repeats: int, precision: str, path: str = "fast") -> str:
    import torch
    from torch.profiler import ProfilerActivity, profile as tprofile

    from training.config import ModelConfig
    from training.inference.export import example_inputs
    from training.inference.fastpath import forward, prepare_inference
    from training.inference.loading import InferenceModel
    from training.models import build_model

    m = InferenceModel(build_model(ModelConfig(name=name, scale=4), 4).eval(), name).to(device)
    batch = {k: torch.from_numpy(v).to(device) for k, v in example_inputs(m, None, size).items()}
    if device.type == "cpu":  # inductor's C++ kernels named in the profile
        import torch._inductor.config as inductor_config
        inductor_config.cpp.enable_kernel_profile = True
    prepare_inference(m, device, precision, path=path)
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    with torch.inference_mode():
        for _ in range(3):
            forward(m, batch)
        if device.type == "cuda":
            torch.cuda.synchronize()
        with tprofile(activities=acts) as prof:
            for _ in range(repeats):
                forward(m, batch)
            if device.type == "cuda":
                torch.cuda.synchronize()
    kernels = [e for e in prof.key_averages() if e.device_type.name == ("CUDA" if device.type == "cuda" else "CPU")]
    attr = "device_time_total" if device.type == "cuda" else "self_cpu_time_total"
    by_family, launches = defaultdict(float), 0
    for e in kernels:
        t = getattr(e, attr, 0.0)
        by_family[family(e.key)] += t / repeats / 1000.0
        launches += e.count
    total = sum(by_family.values())
    lines = [f"== {name} ({precision}, {path} path, {size[0]}x{size[1]}): {launches / repeats:.0f} kernels per frame, "
             f"{total:.3f} ms of kernel time per frame"]
    lines += [f"   {f:<13} {ms:8.3f} ms  {100 * ms / max(total, 1e-9):5.1f} %"
              for f, ms in sorted(by_family.items(), key=lambda x: -x[1])]
    top = sorted(kernels, key=lambda e: -getattr(e, attr, 0.0))[:15]
    lines += [f"   {getattr(e, attr, 0.0) / repeats / 1000.0:8.3f} ms  x{e.count // repeats:<4} {e.key[:110]}"
              for e in top]
    return "\n".join(lines)


def main() -> None:
    import torch
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--models", default="demod-jbu,fusesr-fast,fusesr-l,fusesr")
    p.add_argument("--size", default="1920x1080")
    p.add_argument("--device", default="cuda")
    p.add_argument("--precision", default="bf16")
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument("--path", default="fast", help="comma-separated inference paths: fast, fused")
    p.add_argument("-o", dest="out")
    a = p.parse_args()
    size = tuple(int(v) for v in a.size.split("x"))
    text = "\n".join(profile(n, size, torch.device(a.device), a.repeats, a.precision, path)
                     for n in a.models.split(",") for path in a.path.split(","))
    print(text)
    if a.out:
        with open(a.out, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()

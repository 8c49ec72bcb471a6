"""Devices and precision (torch): which device a run uses, which autocast dtype a precision means there, and where a
model lives. Shared by the trainer, evaluation and the inference fast path (imports nothing of them)."""
from __future__ import annotations

from contextlib import nullcontext

import torch

from training.config import ConfigError

#: The one precision vocabulary (run.amp, --amp, --precision, ``prepare_inference``): "none" runs in float32 (no
#: autocast), "bf16"/"fp16" autocast to that dtype, "auto" picks per device (``amp_dtype``).
PRECISIONS = ("none", "bf16", "fp16", "auto")


def resolve_device(name: str, option: str = "--device") -> torch.device:
    """'auto' | 'cpu' | 'cuda' -> a device; ``option`` names where the value came from in the error (the CLI flag,
    or the configuration key 'run.device' of training)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"{option} cuda: no CUDA device is available to torch {torch.__version__} "
                          f"(use {option} auto or cpu)")
    return torch.device(name)


def set_threads(threads: int = 0) -> int:
    """torch's intra-op threads: ``threads``, or with 0 ``OMP_NUM_THREADS`` where it is set, else the cores this
    process may use (affinity and cgroup quota: ``gbuffer_export.resources.default_threads``; torch's own default
    counts every core of the machine). Returns the count set. The one place training, evaluation, the benchmarks and
    the demo set it."""
    from gbuffer_export.resources import default_threads
    n = int(threads) or default_threads()
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
    return n


def cpu_bf16_supported() -> bool:
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def amp_dtype(mode: str, device: torch.device) -> torch.dtype | None:
    """Autocast dtype: 'auto' picks bf16 where the hardware has it (CPU avx512-bf16/AMX, CUDA >= Ampere),
    fp16 on older CUDA GPUs, and full precision otherwise. ConfigError for a name outside ``PRECISIONS``."""
    if mode not in PRECISIONS:
        raise ConfigError(f"precision {mode!r}: choose one of {', '.join(PRECISIONS)}")
    if mode == "none":
        return None
    if mode == "bf16":
        return torch.bfloat16
    if mode == "fp16":
        return torch.float16
    if device.type == "cuda":
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
    return torch.bfloat16 if cpu_bf16_supported() else None


def dtype_label(dtype: torch.dtype | None) -> str:
    """Short name of the dtype a precision ran in (tables, peaks): fp32 (no autocast), bf16 or fp16."""
    return {None: "fp32", torch.bfloat16: "bf16", torch.float16: "fp16"}[dtype]


def autocast(device: torch.device, dtype: torch.dtype | None):
    if dtype is None:
        return nullcontext()
    return torch.autocast(device_type=device.type, dtype=dtype)


def model_device(model) -> torch.device:
    """Where ``model`` runs: an ``InferenceModel``'s ``device``, else the device of a module's first tensor."""
    if not isinstance(model, torch.nn.Module):
        return model.device
    for t in list(model.parameters()) + list(model.buffers()):
        return t.device
    return getattr(model, "device", torch.device("cpu"))

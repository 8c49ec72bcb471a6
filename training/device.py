"""Devices and precision (torch): which device a run uses, which autocast dtype a precision means there, and where a
model lives. Shared by the trainer, evaluation and the inference fast path (imports nothing of them)."""
from __future__ import annotations

from contextlib import nullcontext

import torch

from training.config import ConfigError


def resolve_device(name: str, option: str = "--device") -> torch.device:
    """'auto' | 'cpu' | 'cuda' -> a device; ``option`` names where the value came from in the error (the CLI flag,
    or the configuration key 'run.device' of training)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"{option} cuda: no CUDA device is available to torch {torch.__version__} "
                          f"(use {option} auto or cpu)")
    return torch.device(name)


def cpu_bf16_supported() -> bool:
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def amp_dtype(mode: str, device: torch.device) -> torch.dtype | None:
    """Autocast dtype: 'auto' picks bf16 where the hardware has it (CPU avx512-bf16/AMX, CUDA >= Ampere),
    fp16 on older CUDA GPUs, and full precision otherwise."""
    if mode == "none":
        return None
    if mode == "bf16":
        return torch.bfloat16
    if mode == "fp16":
        return torch.float16
    if device.type == "cuda":
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
    return torch.bfloat16 if cpu_bf16_supported() else None


def autocast(device: torch.device, dtype: torch.dtype | None):
    if dtype is None:
        return nullcontext()
    return torch.autocast(device_type=device.type, dtype=dtype)


def model_device(model: torch.nn.Module) -> torch.device:
    for t in list(model.parameters()) + list(model.buffers()):
        return t.device
    return getattr(model, "device", torch.device("cpu"))

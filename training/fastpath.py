"""The inference fast path (torch): what ``evaluate``, ``upscale``, ``bench models``, the add-on preview and
``export`` run.

``prepare_inference(model, device, precision, compile)`` turns an eval-mode model into its fast form, in place:

- ``model.fast_ops``: the non-learned parts (class-aware and guided upsampling, remodulation, pixel filter) use
  ``training.models.fast_ops`` (fewer, fused-friendly kernels; same outputs within float rounding);
- BatchNorm folded into the preceding convolution (``model.norm = "batch"``, ``fusesr-fast`` with BatchNorm);
- channels-last weights and inputs (cuDNN and oneDNN run NHWC natively: no layout conversions between layers);
- ``precision`` fp32, bf16 or fp16 autocast (``auto``: bf16 where the device has it, fp16 on older GPUs, else fp32);
- ``compile``: ``torch.compile`` (inductor; mode ``reduce-overhead`` on CUDA, i.e. CUDA graphs replayed for a
  fixed input size), which also fuses the element-wise chains and gathers of the non-learned parts.

``forward(model, batch)`` (``InferenceModel.forward``) runs it with those settings. The reference path (fp32, eager,
NCHW, reference ops) is a model fresh from ``build_model``; tests/train/test_fastpath.py compares every
setting with it on the CPU.
"""
from __future__ import annotations

import torch
import torch.nn as nn
from gbuffer_export.errors import BlendSRError
from training.device import amp_dtype, dtype_label
from training.inference_model import InferenceModel, as_inference, channels_last_batch


def _fused(conv: nn.Conv2d, bn: nn.BatchNorm2d) -> nn.Conv2d:
    return torch.nn.utils.fusion.fuse_conv_bn_eval(conv, bn)


def fold_batchnorm(model: nn.Module) -> int:
    """Fold every eval-mode BatchNorm2d that directly follows a Conv2d (in an ``nn.Sequential``, or as the
    ``norm1``/``norm2`` of a block after its ``depthwise``/``pointwise`` convolution) into that convolution.
    Returns the number folded. Only for inference: the model's state dict changes."""
    if model.training:
        raise ValueError("fold_batchnorm needs a model in eval mode")
    n = 0
    for mod in list(model.modules()):
        if isinstance(mod, nn.Sequential):
            names = list(mod._modules)
            for a, b in zip(names[:-1], names[1:]):
                ca, cb = mod._modules[a], mod._modules[b]
                if isinstance(ca, nn.Conv2d) and isinstance(cb, nn.BatchNorm2d):
                    mod._modules[a] = _fused(ca, cb)
                    mod._modules[b] = nn.Identity()
                    n += 1
        for conv_name, bn_name in (("depthwise", "norm1"), ("pointwise", "norm2")):
            ca, cb = getattr(mod, conv_name, None), getattr(mod, bn_name, None)
            if isinstance(ca, nn.Conv2d) and isinstance(cb, nn.BatchNorm2d):
                setattr(mod, conv_name, _fused(ca, cb))
                setattr(mod, bn_name, nn.Identity())
                n += 1
    # a DWSConv followed by BatchNorm in a Sequential: fold into its pointwise convolution
    for mod in list(model.modules()):
        if isinstance(mod, nn.Sequential):
            names = list(mod._modules)
            for a, b in zip(names[:-1], names[1:]):
                ca, cb = mod._modules[a], mod._modules[b]
                pw = getattr(ca, "pointwise", None)
                if isinstance(pw, nn.Conv2d) and isinstance(cb, nn.BatchNorm2d) and pw.bias is not None:
                    ca.pointwise = _fused(pw, cb)
                    mod._modules[b] = nn.Identity()
                    n += 1
    return n


def prepare_inference(model, device: torch.device | str | None = None, precision: str = "none",
                      compile: bool = False, channels_last: bool = True, fast_ops: bool = True) -> InferenceModel:
    """Make ``model`` (eval mode) the fast inference model described in the module doc, in place; returns it as an
    ``InferenceModel`` (``model`` itself when it is one, else a new one around the module). Settings are kept as
    its ``settings`` dict and applied by ``forward``. ``precision`` (``training.device.PRECISIONS``) is validated
    for ``device``."""
    wrapped = as_inference(model)
    model = wrapped.module
    model.eval()
    if device is not None:
        wrapped.to(device)
    dev = wrapped.device
    dtype = amp_dtype(precision, dev)
    if fast_ops:
        model.fast_ops = True
        fold_batchnorm(model)
    if channels_last:
        model.to(memory_format=torch.channels_last)
    if dev.type == "cuda":
        torch.backends.cudnn.benchmark = True  # fixed frame sizes: the fastest cuDNN algorithms, chosen once
    compiled = None
    if compile:
        mode = "reduce-overhead" if dev.type == "cuda" else None
        compiled = torch.compile(model, mode=mode, dynamic=False)
    # kept out of the module tree (not a submodule, not in the state dict)
    wrapped.settings = {"dtype": dtype, "channels_last": bool(channels_last), "compiled": compiled,
                         "precision": dtype_label(dtype), "compile": bool(compile), "fast_ops": bool(fast_ops)}
    return wrapped


def forward(model, batch: dict, amp: torch.dtype | None = None) -> torch.Tensor:
    """SR of ``batch`` (tensors on the model's device) with an InferenceModel's settings (``prepare_inference``;
    ``InferenceModel.forward``); a plain module: a plain call. ``amp`` overrides the prepared precision when
    given."""
    return as_inference(model).forward(batch, amp)


__all__ = ["prepare_inference", "forward", "fold_batchnorm", "channels_last_batch"]

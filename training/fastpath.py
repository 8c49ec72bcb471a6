"""The inference fast path (torch): what ``evaluate``, ``upscale``, ``bench models``, the add-on preview and
``export`` run.

``prepare_inference(model, device, precision, compile)`` turns an eval-mode model into its fast form, in place:

- ``model.fast_ops``: the non-learned parts (class-aware and guided upsampling, remodulation, pixel filter) use
  ``training.models.fast_ops`` (fewer, fused-friendly kernels; same outputs within float rounding);
- BatchNorm folded into the preceding convolution (``model.norm = "batch"``, ``fusesr-fast`` with BatchNorm);
- channels-last weights and inputs (cuDNN and oneDNN run NHWC natively: no layout conversions between layers);
- ``precision`` fp32, bf16 or fp16 autocast (``auto``: bf16 where the device has it, fp16 on older GPUs, else fp32);
- ``compile``: ``torch.compile`` (inductor; mode ``reduce-overhead`` on CUDA, i.e. CUDA graphs replayed for a
  fixed input size), which also fuses the element-wise chains and gathers of the non-learned parts;
- ``path``: ``fast`` (the above) or ``fused``: the HR stage of the guided models in one fused pass
  (``training.kernels.hr_stage``: Triton kernels on CUDA, inductor-compiled C++ on the CPU; ``SRModel.hr_impl``)
  and, with a bf16/fp16 precision, the weights held in that dtype (``hold_weights``) instead of autocast, which
  casts every weight on every call.

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


#: max |out - fp32 reference| / max |fp32 reference| a prepared model may reach, by the precision it computes in
#: (the label of ``training.device.dtype_label``): fp32 reorders sums and uses other exp/log implementations
#: (inductor's), bf16/fp16 round every activation. tests/train and ``bench models --path`` check it.
TOLERANCE = {"fp32": 2e-5, "bf16": 2e-2, "fp16": 4e-3}

#: ``prepare_inference`` paths: ``fast`` (fast ops, autocast) and ``fused`` (fused HR stage, weights held in the
#: precision's dtype). The reference path is the model as built (fp32 eager, reference ops).
PATHS = ("fast", "fused")
_HELD = (nn.Conv2d, nn.ConvTranspose2d, nn.Linear)


def _cast_input(module, args):
    """Forward pre-hook: floating tensor inputs to the dtype of the module's weight (a no-op when they match)."""
    dt = module.weight.dtype
    return tuple(a.to(dt) if torch.is_tensor(a) and a.is_floating_point() and a.dtype != dt else a for a in args)


def hold_weights(model: nn.Module, dtype: torch.dtype) -> int:
    """Convert the weights and biases of every convolution and linear layer to ``dtype`` (inference only) and give
    each layer with a weight a pre-hook that brings its input to its weight's dtype, so the network runs in
    ``dtype`` without autocast: a cast happens where an fp32 tensor enters a layer (the network's inputs), not for
    every weight on every call. Normalisation layers keep fp32 weights (their input is cast up). Returns the number
    of layers converted."""
    n = 0
    for mod in model.modules():
        w = getattr(mod, "weight", None)
        if not isinstance(w, torch.nn.Parameter):
            continue
        if isinstance(mod, _HELD):
            mod.to(dtype)
            n += 1
        mod.register_forward_pre_hook(_cast_input)
    return n


def prepare_inference(model, device: torch.device | str | None = None, precision: str = "none",
                      compile: bool = False, channels_last: bool = True, fast_ops: bool = True,
                      path: str = "fast") -> InferenceModel:
    """Make ``model`` (eval mode) the fast inference model described in the module doc, in place; returns it as an
    ``InferenceModel`` (``model`` itself when it is one, else a new one around the module). Settings are kept as
    its ``settings`` dict and applied by ``forward``. ``precision`` (``training.device.PRECISIONS``) is validated
    for ``device``; ``path`` is one of ``PATHS``."""
    if path not in PATHS:
        raise BlendSRError(f"inference path {path!r}: choose one of {', '.join(PATHS)}")
    wrapped = as_inference(model)
    model = wrapped.module
    model.eval()
    if device is not None:
        wrapped.to(device)
    dev = wrapped.device
    dtype = amp_dtype(precision, dev)
    if fast_ops or path == "fused":
        model.fast_ops = True
        fold_batchnorm(model)
    held = None
    if path == "fused":
        from training.kernels.hr_stage import default_impl
        model.hr_impl = default_impl(dev)
        if dtype is not None:
            hold_weights(model, dtype)
            held, dtype = dtype, None  # no autocast: the weights are in the precision's dtype
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
                        "precision": dtype_label(held or dtype), "compile": bool(compile),
                        "fast_ops": bool(fast_ops or path == "fused"), "path": path,
                        "hr_impl": model.hr_impl, "weights": dtype_label(held) if held else None,
                        # the fused HR stage reads every HR channel as a contiguous plane (vectorised loads on
                        # the CPU, coalesced on CUDA): only the network's LR inputs go channels-last
                        "channels_last_levels": ("lr",) if path == "fused" else ("lr", "hr")}
    return wrapped


def prepared_batch(model, batch: dict) -> dict:
    """``batch`` in the layout ``forward`` gives a prepared model (bench models times the forward pass alone)."""
    settings = model.settings if isinstance(model, InferenceModel) else {}
    if not settings.get("channels_last"):
        return batch
    return channels_last_batch(batch, settings.get("channels_last_levels", ("lr", "hr")))


def forward(model, batch: dict, amp: torch.dtype | None = None) -> torch.Tensor:
    """SR of ``batch`` (tensors on the model's device) with an InferenceModel's settings (``prepare_inference``;
    ``InferenceModel.forward``); a plain module: a plain call. ``amp`` overrides the prepared precision when
    given."""
    return as_inference(model).forward(batch, amp)


__all__ = ["prepare_inference", "forward", "fold_batchnorm", "channels_last_batch", "hold_weights", "PATHS",
           "TOLERANCE", "prepared_batch"]

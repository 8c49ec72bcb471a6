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
  casts every weight on every call; ``graph``: ``fused`` run as one graph per frame: on the CPU the whole model
  compiled by inductor with ``freezing`` (weights prepacked for oneDNN, convolution + ReLU and convolution + residual
  add in one oneDNN call, the element-wise ops between them fused into C++ loops, no layout copies); on CUDA one
  CUDA graph per frame (``training.inference.frame_graph.FrameGraph``: static input and state buffers, the HR stage's kernels
  inside); ``reference``: the model as built (nothing changed); ``auto`` (the default of every command and of the
  add-on): the fastest of ``AUTO_ORDER`` that passes the reference check on the first frame (``AutoPath``).

``forward(model, batch)`` (``InferenceModel.forward``) runs it with those settings. The reference path (fp32, eager,
NCHW, reference ops) is a model fresh from ``build_model``; tests/train/test_fastpath.py compares every
setting with it on the CPU.
"""
from __future__ import annotations

import logging

import torch
import torch.nn as nn
from gbuffer_export.errors import BlendSRError
from training.device import amp_dtype, dtype_label
from training.inference.model import InferenceModel, as_inference, channels_last_batch

log = logging.getLogger(__name__)


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

#: ``prepare_inference`` paths: ``fast`` (fast ops, autocast), ``fused`` (fused HR stage, weights held in the
#: precision's dtype) and ``graph`` (``fused`` as one compiled graph or CUDA graph per frame). The reference path is
#: the model as built (fp32 eager, reference ops).
PATHS = ("fast", "fused", "graph")
#: what ``--path`` takes: ``auto`` (the default: ``AutoPath``), the reference path, and ``PATHS``
PATH_CHOICES = ("auto", "reference", *PATHS)
#: ``auto``'s candidates, fastest first (measured: docs/bench/speed-cpu-default on the CPU, where graph is 2x and more
#: faster than fast at 1080p; on CUDA graph removes the host share of fused): the first that builds, runs and
#: passes the reference check on the first frame is kept; the reference path is the last resort.
AUTO_ORDER = ("graph", "fused", "fast")
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
    for ``device``; ``path`` is one of ``PATH_CHOICES`` (``auto``: ``AutoPath`` chooses on the first frame)."""
    if path not in PATH_CHOICES:
        raise BlendSRError(f"inference path {path!r}: choose one of {', '.join(PATH_CHOICES)}")
    wrapped = as_inference(model)
    wrapped.module.eval()
    if device is not None:
        wrapped.to(device)
    if path == "auto":
        AutoPath(wrapped, precision, compile, channels_last).start()
        return wrapped
    if path == "reference":
        wrapped.settings = {"dtype": None, "channels_last": False, "compiled": None, "precision": "fp32",
                            "compile": False, "fast_ops": False, "path": "reference", "hr_impl": None,
                            "weights": None}
        return wrapped
    _prepare_path(wrapped, precision, compile, channels_last, fast_ops, path)
    return wrapped


def _prepare_path(wrapped: InferenceModel, precision: str, compile: bool, channels_last: bool, fast_ops: bool,
                  path: str) -> None:
    """``prepare_inference`` of one of ``PATHS``."""
    model = wrapped.module
    dev = wrapped.device
    dtype = amp_dtype(precision, dev)
    if fast_ops or path != "fast":
        model.fast_ops = True
        fold_batchnorm(model)
    held = None
    if path in ("fused", "graph"):
        from training.kernels.hr_stage import default_impl
        model.hr_impl = default_impl(dev)
        if dtype is not None:
            hold_weights(model, dtype)
            held, dtype = dtype, None  # no autocast: the weights are in the precision's dtype
    if channels_last:
        model.to(memory_format=torch.channels_last)
    if dev.type == "cuda":
        torch.backends.cudnn.benchmark = True  # fixed frame sizes: the fastest cuDNN algorithms, chosen once
    compiled = _compiled(model, dev, compile, path)
    # kept out of the module tree (not a submodule, not in the state dict)
    wrapped.settings = {"dtype": dtype, "channels_last": bool(channels_last), "compiled": compiled,
                        "precision": dtype_label(held or dtype), "compile": compiled is not None,
                        "fast_ops": bool(fast_ops or path != "fast"), "path": path,
                        "hr_impl": model.hr_impl, "weights": dtype_label(held) if held else None,
                        # one CUDA graph per frame (InferenceModel.forward and .step build them)
                        "frame_graph": path == "graph" and dev.type == "cuda",
                        # the fused HR stage reads every HR channel as a contiguous plane (vectorised loads on
                        # the CPU, coalesced on CUDA): only the network's LR inputs go channels-last
                        "channels_last_levels": ("lr",) if path != "fast" else ("lr", "hr")}


def _compiled(model: nn.Module, dev: torch.device, compile: bool, path: str):
    """The ``torch.compile`` of ``model`` the settings ask for, or None. ``graph`` on the CPU: inductor with
    ``freezing`` (module doc); on CUDA the CUDA graph is ``FrameGraph``'s, so a compiled module there runs
    without inductor's own CUDA graphs."""
    if path == "graph" and dev.type != "cuda":
        return torch.compile(model, dynamic=False, options={"freezing": True})
    if not compile:
        return None
    mode = "reduce-overhead" if dev.type == "cuda" and path != "graph" else None
    return torch.compile(model, mode=mode, dynamic=False)


#: the environment variable that sets the default inference path of the commands and the add-on (unset: auto)
PATH_ENV = "BLENDSR_INFERENCE_PATH"


def default_path() -> str:
    """The inference path of a command or preview given no ``--path``: ``$BLENDSR_INFERENCE_PATH`` when set (the
    test suite sets ``fast``), else ``auto``; BlendSRError for a value outside ``PATH_CHOICES``."""
    import os
    path = os.environ.get(PATH_ENV, "").strip() or "auto"
    if path not in PATH_CHOICES:
        raise BlendSRError(f"{PATH_ENV}={path!r}: choose one of {', '.join(PATH_CHOICES)}")
    return path


class AutoPath:
    """``path="auto"``: the fastest inference path that passes the reference check. The model is prepared for the
    first path of ``AUTO_ORDER`` at once; its first frame (``InferenceModel.forward`` or ``.step``: ``check``)
    also runs through the reference path (a pristine copy of the module, fp32 eager), and a path that fails to
    build or run, or whose output differs from the reference's by more than ``TOLERANCE`` of its precision, is
    replaced by the next (a warning names why); the reference path itself is the last resort. The choice is logged
    and kept as ``settings['path']`` (``settings['auto']`` says how it was reached); the pristine copy is dropped
    after the check."""

    def __init__(self, wrapped: InferenceModel, precision: str, compile: bool, channels_last: bool):
        import copy
        self.wrapped, self.precision, self.compile, self.channels_last = wrapped, precision, compile, channels_last
        self.pristine = copy.deepcopy(wrapped.module)
        self.todo = list(AUTO_ORDER)
        self.notes: list[str] = []

    def start(self) -> None:
        self._next()

    def _next(self) -> None:
        import copy
        path = self.todo.pop(0) if self.todo else "reference"
        self.wrapped.module = copy.deepcopy(self.pristine)
        prepare_inference(self.wrapped, None, self.precision, self.compile, self.channels_last, path=path)
        self.wrapped.settings["auto"] = self

    def check(self, call, pick=lambda r: r):
        """The first frame: ``call()`` (the output with the current settings; ``pick`` takes the SR image out of
        it) on each candidate until one passes (class doc); returns its output."""
        from training.inference.model import InferenceModel
        ref = InferenceModel(self.pristine, self.wrapped.spec)
        ref.to(self.wrapped.device)
        want = self._swap(ref, call)
        want_sr = pick(want).float()
        while True:
            path = self.wrapped.settings["path"]
            if path == "reference":
                self.notes.append("reference: the last resort")
                return self._done(want, None, None)
            try:
                got = call()
                err = float((pick(got).float() - want_sr).abs().max()) / max(float(want_sr.abs().max()), 1e-30)
            except Exception as exc:  # noqa: BLE001 - a path that cannot run here: the next one
                why = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
                self.notes.append(f"{path}: failed ({why})")
                log.warning("inference path %s fails here (%s); trying the next", path, why)
                self._next()
                continue
            tol = TOLERANCE[self.wrapped.settings["precision"]]
            if err <= tol:
                return self._done(got, err, tol)
            self.notes.append(f"{path}: error {err:.2e} > {tol:.0e}")
            log.warning("inference path %s differs from the reference by %.2e of its peak (tolerance %.0e); "
                        "trying the next", path, err, tol)
            self._next()

    def _swap(self, ref: InferenceModel, call):
        """``call()`` with the reference module and no settings in the wrapped model's place."""
        w = self.wrapped
        module, settings = w.module, w.settings
        w.module, w.settings = ref.module, {}
        try:
            return call()
        finally:
            w.module, w.settings = module, settings

    def _done(self, out, err, tol):
        s = self.wrapped.settings
        if s["path"] == "reference":
            self.wrapped.module = self.pristine
        s["auto"] = {"checked": True, "max_rel_err": err, "tolerance": tol, "rejected": list(self.notes)}
        log.info("inference path: %s (auto%s)", s["path"], "" if err is None else
                 f"; max |out - fp32 reference| / max |reference| = {err:.2e} <= {tol:.0e}")
        self.pristine = None
        return out


def path_record(model) -> dict:
    """What an output records of the inference path that ran (evaluate's JSON, upscale.json, the add-on's
    result.json): path, precision, weights, HR stage implementation, compiled, and how ``auto`` chose."""
    s = as_inference(model).settings
    auto = s.get("auto")
    rec = {"path": s.get("path", "reference"), "precision": s.get("precision", "fp32"),
           "weights": s.get("weights"), "hr_impl": s.get("hr_impl"), "compiled": bool(s.get("compile")),
           "frame_graph": bool(s.get("frame_graph"))}
    if isinstance(auto, dict):
        rec["auto"] = auto
    elif auto is not None:
        rec["auto"] = {"checked": False}
    return rec


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
           "PATH_CHOICES", "AUTO_ORDER", "AutoPath", "path_record", "default_path",
           "TOLERANCE", "prepared_batch"]

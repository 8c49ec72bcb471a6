"""The per-pixel math of the HR stage, written once for both of its implementations.

Every function here is element-wise and reads its primitives from the module global ``ops``: ``TorchOps`` (torch
tensors; ``hr_stage.hr_stage_torch``, the CPU path that inductor compiles) by default, ``triton.language`` in the
copies ``jit_for_triton`` makes for the Triton kernels (``hr_triton``). The primitives used are those both offer
with the same meaning: exp, log, abs, floor, where, maximum, minimum. No Python control flow on values, no lists.

The references these reproduce (tests/train/hr_stage_cases.py compares): ``resample.upsample`` (pixel-centre
bilinear with jitter, borders clamped), ``base.upsample_by_class`` / ``base.demodulated_mask``,
``guided.guide_features`` / ``guided.upsample_guided``, ``transforms.inverse_transform`` (log1p), and
``SRModel.remodulate`` (L_D F_used + E), and the FuseSR family's ``residual_clamp`` (``range_add``,
``range_pick``, ``similar``, ``open_if_empty``, ``clamp_to_range``; ``guided.tap_range`` is its reference).
"""
from __future__ import annotations

import types


class TorchOps:
    """The primitives of ``triton.language`` the helpers use, on torch tensors (Python numbers allowed as the
    second operand of maximum/minimum and as a branch of where)."""
    import torch as _t
    exp = staticmethod(_t.exp)
    log = staticmethod(_t.log)
    abs = staticmethod(_t.abs)
    floor = staticmethod(_t.floor)
    where = staticmethod(_t.where)

    @staticmethod
    def maximum(a, b):
        return TorchOps._t.clamp(a, min=b) if isinstance(b, (int, float)) else TorchOps._t.maximum(a, b)

    @staticmethod
    def minimum(a, b):
        return TorchOps._t.clamp(a, max=b) if isinstance(b, (int, float)) else TorchOps._t.minimum(a, b)


ops = TorchOps

#: ``guided.guide_features``: depth clamped to [DEPTH_MIN, DEPTH_MAX] (NaN and +inf -> DEPTH_MAX) before the log.
DEPTH_MIN, DEPTH_MAX = 1e-4, 1e6
#: float32's largest value: ``torch.nan_to_num``'s replacement of +-inf in the normals.
F32_MAX = 3.4028234663852886e38
#: ``base.upsample_by_class``: a class-restricted bilinear sum below this falls back to the plain bilinear value.
CLASS_EPS = 1e-6
#: ``residual_clamp = "lr-guided"``: a tap bounds an HR pixel only where its joint bilateral range weight
#: (``similarity``) is at least this, i.e. it lies within about 1.2 guide sigmas of the pixel's depth and normal (the
#: same surface). Chosen on the wide val split against 0.1 (docs/training.md, "FuseSR").
CLAMP_SIMILARITY = 0.5
#: ``open_if_empty``'s bound: finite, so that margin * (hi - lo) and the inverse log1p of it stay finite.
OPEN_BOUND = 1e30
#: ``transforms.inverse_transform``: the exponent is clamped here.
EXP_CLAMP = 80.0


def tap_position(i, scale, jit):
    """LR sample position u of HR pixel index ``i`` along one axis (``resample.upsample``): the HR pixel centre
    (i + 0.5) / scale minus the LR pixel centre offset 0.5 and the jitter ``jit`` (LR pixels)."""
    return (i + 0.5) / scale - 0.5 - jit


def tap_weight(u, f):
    """Bilinear weight of the LR index ``f`` (float, unclamped) for position ``u``: max(1 - |u - f|, 0)."""
    return ops.maximum(1.0 - ops.abs(u - f), 0.0)


def tap_index(f, n):
    """LR index ``f`` (float) clamped to [0, n - 1] (the border rule), still float."""
    return ops.minimum(ops.maximum(f, 0.0), n - 1.0)


def demodulated(f0, f1, f2):
    """1.0 where a pixel was divided by its F_beta (any channel of F_used != 1), else 0.0
    (``base.demodulated_mask``)."""
    return ops.where((f0 != 1.0) | (f1 != 1.0) | (f2 != 1.0), 1.0, 0.0)


def guide_depth(d, sigma):
    """log(depth) / sigma_depth with depth's NaN and +inf -> DEPTH_MAX, clamped (``guided.guide_features``)."""
    d = ops.where(d == d, d, DEPTH_MAX)
    return ops.log(ops.minimum(ops.maximum(d, DEPTH_MIN), DEPTH_MAX)) / sigma


def guide_normal(n, sigma):
    """normal / sigma_normal with NaN -> 0 and +-inf -> +-F32_MAX (``guided.guide_features``)."""
    n = ops.where(n == n, n, 0.0)
    return ops.minimum(ops.maximum(n, -F32_MAX), F32_MAX) / sigma


def similarity(d2):
    """The joint bilateral range weight exp(-|g_HR - g_LR|^2 / 2) of a squared guide distance."""
    return ops.exp(-0.5 * d2)


def class_or_plain(num, den, plain):
    """The class-restricted bilinear value num / den where den > CLASS_EPS, else the plain bilinear one."""
    return ops.where(den > CLASS_EPS, num / ops.maximum(den, CLASS_EPS), plain)


def guided_or_fallback(num, den, fallback, floor):
    """The joint bilateral value num / den where the weights sum to ``floor`` or more, else ``fallback``."""
    return ops.where(den >= floor, num / ops.maximum(den, floor), fallback)


def head(net, base):
    """The FuseSR family's residual head: ReLU(net + base)."""
    return ops.maximum(net + base, 0.0)


def inverse_log1p(y):
    """``transforms.inverse_transform(y, "log1p")`` for y >= 0 (after ``head``): exp(min(y, EXP_CLAMP)) - 1."""
    return ops.exp(ops.minimum(y, EXP_CLAMP)) - 1.0


def range_add(lo, hi, v, use):
    """The running range (lo, hi) of LR tap values widened by ``v`` where ``use`` (a boolean)."""
    return ops.where(use, ops.minimum(lo, v), lo), ops.where(use, ops.maximum(hi, v), hi)


def range_pick(cden, class_bound, plain_bound):
    """A bound of the taps the base reads: over the taps of the HR pixel's class where their bilinear weights sum
    above CLASS_EPS (``class_or_plain`` takes the class-restricted value there), else over all 4 taps."""
    return ops.where(cden > CLASS_EPS, class_bound, plain_bound)


def similar(sim):
    """``residual_clamp = "lr-guided"``: True where a tap of range weight ``sim`` is the HR pixel's surface."""
    return sim >= CLAMP_SIMILARITY


def open_if_empty(lo, hi):
    """A tap range (lo, hi) left empty (lo > hi: no tap was added) opened to (-OPEN_BOUND, OPEN_BOUND): no bound
    (``residual_clamp = "lr-guided"`` where no tap is the pixel's surface)."""
    empty = lo > hi
    return ops.where(empty, -OPEN_BOUND, lo), ops.where(empty, OPEN_BOUND, hi)


def clamp_to_range(v, lo, hi, margin):
    """``residual_clamp = "lr-range"``: ``v`` clamped to [lo - margin (hi - lo), hi + margin (hi - lo)], the LR
    range of the taps its base reads widened by ``margin`` of its width."""
    pad = margin * (hi - lo)
    return ops.minimum(ops.maximum(v, lo - pad), hi + pad)


def remodulate(irr, fbeta, emission):
    """The point sample L_D F_used + E (``SRModel.remodulate`` before its pixel filter)."""
    return irr * fbeta + emission


HELPERS = ("tap_position", "tap_weight", "tap_index", "demodulated", "guide_depth", "guide_normal", "similarity",
           "class_or_plain", "guided_or_fallback", "head", "inverse_log1p", "range_add", "range_pick", "similar",
           "open_if_empty", "clamp_to_range",
           "remodulate")


def jit_for_triton() -> dict:
    """{name: triton.jit function} for every helper: the same code objects, with ``ops`` bound to
    ``triton.language`` (and the constants) in their globals. Imports triton."""
    import triton
    import triton.language as tl
    g = {k: tl.constexpr(v) for k, v in globals().items() if k.isupper()}  # Triton reads constexpr globals only
    g["ops"] = tl
    out = {}
    for name in HELPERS:
        fn = globals()[name]
        copy = types.FunctionType(fn.__code__, g, name, fn.__defaults__, fn.__closure__)
        copy.__module__, copy.__qualname__, copy.__doc__ = fn.__module__, fn.__qualname__, fn.__doc__
        out[name] = triton.jit(copy)
    g.update(out)  # helpers calling helpers (none now) would find the jitted ones
    return out

"""The HR stage of the guided models, fused: everything that runs at HR around the network of ``demod-bilinear``,
``demod-jbu`` and the FuseSR family (``fusesr``, ``fusesr-l``, ``fusesr-fast``), in one pass over the HR pixels
and one pass of the pixel filter.

Per HR pixel (one definition of the math: ``hr_math``; every step reproduces a reference in ``models/``):

1. the 4 bilinear LR taps of its centre with the frame's jitter (``resample.upsample``), borders clamped;
2. the plain bilinear value and, with ``by_class``, the class-restricted one: only the taps whose demodulation
   class (F_used != 1) is the HR pixel's, renormalised (``base.upsample_by_class``);
3. with ``guided``, the joint bilateral value: taps weighted by exp(-|g_HR - g_LR|^2 / 2) on the scaled guides
   [log depth / sigma_d, normal / sigma_n] and by the class match, falling back to step 2's value where the
   weights sum below ``floor`` (``guided.upsample_guided``);
4. with ``head`` (FuseSR family), ReLU(network output + that base), then the inverse log1p transform with
   ``log1p``;
5. with ``remod``, the point sample L_D F_used + E (``SRModel.remodulate``);

then the separable pixel filter ``taps`` x ``taps`` (edges replicated) over the result.

Implementations (``run``): ``triton`` on CUDA (``hr_triton``: one kernel for steps 1-5, one for the filter; LR
guides and classes computed per tap from the raw LR buffers, so nothing else is launched), and ``torch``
(``hr_stage_torch``: the same helpers on tensors, the taps as gathers from one stacked LR tensor). On the CPU the
fast path runs ``compiled``: ``hr_stage_torch`` under ``torch.compile``, whose C++ backend (inductor) fuses the
gathers and the element-wise chain into a few vectorised loops; Triton's CPU interpreter is for tests only.
Demodulation itself (the eps rule) runs where the inputs are read (``training.inference``, ``training.cache``:
``gbuffer_export.demod``) and is not repeated here: the models receive L_D and F_used.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import NamedTuple

import torch

from training.kernels import hr_math as m

IMPLS = ("torch", "compiled", "triton")


@dataclass(frozen=True)
class HRStage:
    """What one model's HR stage does (module doc). ``inv_sigmas``: (1 / sigma_depth, 1 / sigma_normal) of the
    guides, None without ``guided``; ``taps``: the 1-D pixel filter (None: no filter)."""
    scale: int
    by_class: bool
    guided: bool
    inv_sigmas: tuple[float, float] | None
    head: bool
    log1p: bool
    remod: bool
    taps: tuple[float, ...] | None
    floor: float = 1e-4


class HRInputs(NamedTuple):
    """The tensors of one HR stage, channel-first (any memory layout). ``lr`` (B, 3, h, w) the LR image to upsample;
    ``jitter`` (B, 2) or None; F_used (B, 3, ., .) at both levels (class and remodulation); depth (B, 1, ., .) and
    normal (B, 3, ., .) at both levels (guides); ``hr_emission`` (B, 3, H, W); ``net`` (B, 3, H, W) the network's
    output (``head``). Unused ones may be None."""
    lr: torch.Tensor
    jitter: torch.Tensor | None = None
    lr_fbeta: torch.Tensor | None = None
    hr_fbeta: torch.Tensor | None = None
    lr_depth: torch.Tensor | None = None
    lr_normal: torch.Tensor | None = None
    hr_depth: torch.Tensor | None = None
    hr_normal: torch.Tensor | None = None
    hr_emission: torch.Tensor | None = None
    net: torch.Tensor | None = None


def tap_axes(n_lr: int, scale: int, jit: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """[(index (B, n) long, weight (B, n))] of the 2 taps along one axis of n = n_lr * scale HR pixels; ``jit``
    (B, 1) the jitter along the axis."""
    i = torch.arange(n_lr * scale, device=jit.device, dtype=torch.float32).view(1, -1)
    u = m.tap_position(i, float(scale), jit)
    f = torch.floor(u)
    return [(m.tap_index(f + d, n_lr).long(), m.tap_weight(u, f + d)) for d in (0.0, 1.0)]


def _lr_planes(spec: HRStage, t: HRInputs) -> torch.Tensor:
    """(B, K, h w) float32: the image (3), the scaled guide (4, ``guided``) and the class (1, ``by_class``)."""
    planes = [t.lr.float()]
    if spec.guided:
        planes += [m.guide_depth(t.lr_depth[:, :1].float(), spec.inv_sigmas[0]),
                   m.guide_normal(t.lr_normal.float(), spec.inv_sigmas[1])]
    if spec.by_class:
        f = t.lr_fbeta.float()
        planes.append(m.demodulated(f[:, 0:1], f[:, 1:2], f[:, 2:3]))
    return torch.cat(planes, dim=1).flatten(2)


def hr_stage_torch(spec: HRStage, t: HRInputs) -> torch.Tensor:
    """The HR stage (module doc) on tensors: (B, 3, H, W) float32."""
    b, _, h, w = t.lr.shape
    s = spec.scale
    hh, ww = h * s, w * s
    jit = torch.zeros(b, 2, device=t.lr.device) if t.jitter is None else t.jitter.float()
    xs, ys = tap_axes(w, s, jit[:, :1]), tap_axes(h, s, jit[:, 1:2])
    lr_all = _lr_planes(spec, t)
    k = lr_all.shape[1]
    if spec.by_class:
        f = t.hr_fbeta.float()
        cls = m.demodulated(f[:, 0:1], f[:, 1:2], f[:, 2:3])
    if spec.guided:
        g_hr = torch.cat([m.guide_depth(t.hr_depth[:, :1].float(), spec.inv_sigmas[0]),
                          m.guide_normal(t.hr_normal.float(), spec.inv_sigmas[1])], dim=1)
    plain = cnum = cden = gnum = gden = 0.0
    for iy, wy in ys:
        for ix, wx in xs:
            idx = (iy.view(b, hh, 1) * w + ix.view(b, 1, ww)).view(b, 1, hh * ww)
            v = torch.gather(lr_all, 2, idx.expand(-1, k, -1)).view(b, k, hh, ww)
            x = v[:, :3]
            wb = wy.view(b, 1, hh, 1) * wx.view(b, 1, 1, ww)
            plain = plain + wb * x
            if spec.by_class:
                same = v[:, k - 1:] == cls
                wc = torch.where(same, wb, 0.0)
                cnum, cden = cnum + wc * x, cden + wc
            if spec.guided:
                d2 = (v[:, 3:7] - g_hr).square().sum(dim=1, keepdim=True)
                wg = wb * m.similarity(d2)
                if spec.by_class:
                    wg = torch.where(same, wg, 0.0)
                gnum, gden = gnum + wg * x, gden + wg
    out = m.class_or_plain(cnum, cden, plain) if spec.by_class else plain
    if spec.guided:
        out = m.guided_or_fallback(gnum, gden, out, spec.floor)
    if spec.head:
        out = m.head(t.net.float(), out)
        if spec.log1p:
            out = m.inverse_log1p(out)
    if spec.remod:
        out = m.remodulate(out, t.hr_fbeta.float(), t.hr_emission.float())
    if spec.taps is not None:
        from training.models.fast_ops import shift_filter
        out = shift_filter(out, spec.taps)
    return out


@functools.lru_cache(maxsize=None)
def _compiled(spec: HRStage):
    return torch.compile(functools.partial(hr_stage_torch, spec), dynamic=False)


def triton_available() -> bool:
    """Whether the Triton kernels can run here: triton importable and a CUDA device."""
    if not torch.cuda.is_available():
        return False
    try:
        import triton  # noqa: F401
    except ImportError:
        return False
    return True


def default_impl(device: torch.device) -> str:
    """The fused implementation for ``device``: triton on CUDA when available, else compiled (module doc)."""
    return "triton" if device.type == "cuda" and triton_available() else "compiled"


def run(spec: HRStage, t: HRInputs, impl: str = "compiled") -> torch.Tensor:
    """The HR stage with implementation ``impl`` (``IMPLS``): (B, 3, H, W) float32."""
    if impl == "triton":
        from training.kernels.hr_triton import hr_stage_triton
        return hr_stage_triton(spec, t)
    if impl == "compiled":
        return _compiled(spec)(t)
    if impl == "torch":
        return hr_stage_torch(spec, t)
    raise ValueError(f"HR stage implementation {impl!r}: choose one of {', '.join(IMPLS)}")


__all__ = ["HRStage", "HRInputs", "IMPLS", "run", "hr_stage_torch", "default_impl", "triton_available"]

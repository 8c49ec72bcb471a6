"""Fast versions of the non-learned parts of the models (torch): the inference fast path (``SRModel.fast_ops``).

Each function computes what its reference in ``base.py`` / ``guided.py`` computes, with fewer and cheaper kernels;
tests/train/test_fastpath.py compares every one with its reference. What changes:

- ``shift_filter``: the separable pixel filter of the remodulation as shifted slices multiplied by constant taps
  (element-wise, channels-last friendly), instead of two single-channel convolutions over a (B C, 1, H, W) reshape
  (two thirds of ``demod-bilinear``'s CPU time at 960x544 went to those convolutions).
- ``remodulate``: L_D F_used + E as one ``addcmul``.
- ``upsample_by_class``: the five upsamplings of the class-aware bilinear step (each building its HR sampling grid)
  as one upsampling of 11 stacked channels.
- ``upsample_guided``: the joint bilateral upsampling gathers its 4 taps column-then-row (the 2 LR columns of every
  HR column at LR height, then whole rows) instead of a flat gather with an (H W) index per tap, and accumulates
  with ``addcmul``.

All of it is element-wise work, gathers with per-row/per-column indices and small concatenations: ``torch.compile``
(inductor) fuses it into a few kernels on GPU (indirect loads included), so no hand-written kernel is needed.
Under ONNX export or tracing the batch-1 ``index_select`` shortcut is replaced by ``gather`` so the exported graph
keeps a dynamic batch.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from training.kernels.filters import shift_filter


def _tracing() -> bool:
    return torch.jit.is_tracing() or torch.onnx.is_in_onnx_export()


def take(t: torch.Tensor, dim: int, idx: torch.Tensor) -> torch.Tensor:
    """Per-image index along ``dim`` of (B, ...): ``idx`` (B, n) long -> t with ``dim`` of size n."""
    if t.shape[0] == 1 and not _tracing():
        return t.index_select(dim, idx[0])
    view = [idx.shape[0]] + [1] * (t.dim() - 1)
    view[dim] = idx.shape[1]
    shape = list(t.shape)
    shape[dim] = idx.shape[1]
    return torch.gather(t, dim, idx.view(view).expand(shape))


def remodulate(irradiance: torch.Tensor, fbeta_used: torch.Tensor, emission: torch.Tensor,
               taps: tuple[float, ...] | None) -> torch.Tensor:
    """K * (L_D F_used + E) (``SRModel.remodulate``)."""
    dt = irradiance.dtype
    out = torch.addcmul(emission.to(dt), irradiance, fbeta_used.to(dt))
    return out if taps is None else shift_filter(out, taps)


def upsample_bilinear(x: torch.Tensor, scale: int, jitter: torch.Tensor | None = None) -> torch.Tensor:
    """``base.upsample(x, scale, "bilinear", jitter)``: one ``grid_sample`` (or ``interpolate`` without jitter).
    A separable two-pass version (gather the LR columns, then rows) measured 3x slower on the CPU: PyTorch's
    gather along the innermost axis is slow there, while ``grid_sample`` is vectorised."""
    from training.models.resample import upsample
    return upsample(x, scale, "bilinear", jitter)


def upsample_by_class(x: torch.Tensor, lr_mask: torch.Tensor, hr_mask: torch.Tensor, scale: int,
                      jitter: torch.Tensor | None = None) -> torch.Tensor:
    """``base.upsample_by_class`` with its five upsamplings done as one of 11 stacked channels."""
    c = x.shape[1]
    m = lr_mask.to(x.dtype)
    inv = 1.0 - m
    u = upsample_bilinear(torch.cat([x, x * m, m, x * inv, inv], dim=1), scale, jitter)
    plain, num1, den1 = u[:, :c], u[:, c:2 * c], u[:, 2 * c:2 * c + 1]
    num0, den0 = u[:, 2 * c + 1:3 * c + 1], u[:, 3 * c + 1:]
    ok1 = (den1 > 1e-6) & (hr_mask > 0.5)
    ok0 = (den0 > 1e-6) & ((1.0 - hr_mask) > 0.5)
    out = torch.where(ok1, num1 / den1.clamp(min=1e-6), plain)
    return torch.where(ok0, num0 / den0.clamp(min=1e-6), out)


def upsample_guided(x: torch.Tensor, lr_guide: torch.Tensor, hr_guide: torch.Tensor, scale: int,
                    fallback: torch.Tensor, jitter: torch.Tensor | None = None,
                    classes: tuple[torch.Tensor, torch.Tensor] | None = None, floor: float = 1e-4) -> torch.Tensor:
    """``guided.upsample_guided`` with row-then-column gathers (module doc). float32 inside like the reference."""
    b, c, h, w = x.shape
    hh, ww = h * scale, w * scale
    dev = x.device
    g = lr_guide.shape[1]
    jx, jy = (torch.zeros(b, 1, device=dev), torch.zeros(b, 1, device=dev)) if jitter is None else \
        (jitter[:, :1].float(), jitter[:, 1:2].float())
    ux = (torch.arange(ww, device=dev, dtype=torch.float32) + 0.5) / scale - 0.5 - jx   # (B, W) LR index space
    uy = (torch.arange(hh, device=dev, dtype=torch.float32) + 0.5) / scale - 0.5 - jy   # (B, H)
    x0, y0 = torch.floor(ux), torch.floor(uy)
    lr_class, hr_class = classes if classes is not None else (None, None)
    parts = [x.float(), lr_guide.float()] + ([lr_class.float()] if lr_class is not None else [])
    lr_all = torch.cat(parts, dim=1)                                                     # (B, K, h, w)
    hr_g = hr_guide.float()
    hr_c = hr_class.float() if hr_class is not None else None
    cols = []
    for dx in (0, 1):  # the column gathers at LR height (s times fewer elements), then whole-row copies
        ix = (x0 + dx).clamp(0, w - 1).long()
        wx = (1.0 - (ux - (x0 + dx)).abs()).clamp(min=0.0)
        cols.append((take(lr_all, 3, ix), wx.view(b, 1, 1, ww)))                         # (B, K, h, W)
    num = den = None
    for dy in (0, 1):
        iy = (y0 + dy).clamp(0, h - 1).long()
        wy = (1.0 - (uy - (y0 + dy)).abs()).clamp(min=0.0).view(b, 1, hh, 1)
        for col, wx in cols:
            v = take(col, 2, iy)                                                         # (B, K, H, W)
            d2 = (v[:, c:c + g] - hr_g).square().sum(dim=1, keepdim=True)
            wt = torch.exp(-0.5 * d2) * (wy * wx)
            if hr_c is not None:
                wt = torch.where(v[:, c + g:] == hr_c, wt, torch.zeros((), device=dev))
            num = wt * v[:, :c] if num is None else torch.addcmul(num, wt, v[:, :c])
            den = wt if den is None else den + wt
    out = torch.where(den >= floor, num / den.clamp(min=floor), fallback.float())
    return out.to(x.dtype)

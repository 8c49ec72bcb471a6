"""Torch mirror of ``gbuffer_export.demod``: the same rules, on tensors, for the GPU/ONNX side.

    L_D = (I - E) / F_used,   I = L_D * F_used + E

F_used = clip(F_beta, eps, FBETA_MAX) on surface pixels, 1 on background and UNTRUSTED-flag pixels and where F_beta
is not finite. Radiance/emission are sanitised first (NaN -> 0, +-Inf -> +-RADIANCE_CAP, clipped to the cap).
Tensors are channel-first: radiance/emission/F_beta (..., 3, H, W) (F_beta may have 1 channel), flags (..., 1, H, W)
or (..., H, W) integer. Arithmetic in float64 like the numpy version; results float32. ``tests/test_training_demod``
checks equality with the numpy implementation.
"""
from __future__ import annotations

import torch

from gbuffer_export.errors import BlendSRError
from gbuffer_export.conventions import UNTRUSTED, Flag
from gbuffer_export.demod import DEFAULT_EPS, EPS_MIN, FBETA_MAX, RADIANCE_CAP


def sanitize(x: torch.Tensor) -> torch.Tensor:
    """NaN -> 0, +-Inf -> +-RADIANCE_CAP, finite values clipped to [-RADIANCE_CAP, RADIANCE_CAP] (float64)."""
    x = x.to(torch.float64)
    return torch.nan_to_num(x, nan=0.0, posinf=RADIANCE_CAP, neginf=-RADIANCE_CAP).clamp(-RADIANCE_CAP, RADIANCE_CAP)


def flag_masks(flags: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor:
    """Boolean (..., 1, H, W): pixels where F_used := 1 (background or any UNTRUSTED bit)."""
    if flags is None:
        return torch.zeros_like(like[..., :1, :, :], dtype=torch.bool)
    f = flags
    if f.dim() == like.dim() - 1:
        f = f.unsqueeze(-3)
    if f.is_floating_point():
        f = torch.nan_to_num(f, nan=0.0, posinf=0.0, neginf=0.0)
    f = f.to(torch.int64)
    return (f & int(Flag.BACKGROUND | UNTRUSTED)) != 0


def fbeta_for_division(fbeta: torch.Tensor, flags: torch.Tensor | None = None, eps: float = DEFAULT_EPS,
                       like: torch.Tensor | None = None) -> torch.Tensor:
    """The F_beta that demodulation divides by: (..., 3, H, W) float64 holding float32-representable values."""
    eps = float(eps)
    if not (EPS_MIN <= eps <= 1.0):
        raise BlendSRError(f"demodulation eps {eps!r} must lie in [{EPS_MIN}, 1]")
    f = fbeta.to(torch.float64)
    if f.shape[-3] == 1:
        f = f.expand(*f.shape[:-3], 3, *f.shape[-2:])
    f = torch.where(torch.isfinite(f), f.clamp(eps, FBETA_MAX), torch.ones_like(f))
    f = torch.where(flag_masks(flags, f if like is None else like), torch.ones_like(f), f)
    return f.to(torch.float32).to(torch.float64)


def demodulate(radiance: torch.Tensor, emission: torch.Tensor | None, fbeta: torch.Tensor,
               flags: torch.Tensor | None = None, eps: float = DEFAULT_EPS) -> tuple[torch.Tensor, torch.Tensor]:
    """(L_D, F_used), both (..., 3, H, W) float32 and finite. Same rules as ``gbuffer_export.demod.demodulate``."""
    i = sanitize(radiance)
    e = torch.zeros_like(i) if emission is None else sanitize(emission).expand_as(i)
    f = fbeta_for_division(fbeta, flags, eps, like=i)
    return ((i - e) / f).to(torch.float32), f.to(torch.float32)


def remodulate(irradiance: torch.Tensor, fbeta_used: torch.Tensor, emission: torch.Tensor | None) -> torch.Tensor:
    """I = L_D * F_used + E as float32 (inputs sanitised like the numpy version)."""
    irr = torch.nan_to_num(irradiance.to(torch.float64), nan=0.0, posinf=RADIANCE_CAP / EPS_MIN,
                           neginf=-RADIANCE_CAP / EPS_MIN)
    f = torch.nan_to_num(fbeta_used.to(torch.float64), nan=1.0, posinf=FBETA_MAX, neginf=0.0)
    out = irr * f
    if emission is not None:
        out = out + sanitize(emission)
    lim = float(torch.finfo(torch.float32).max)
    return out.clamp(-lim, lim).to(torch.float32)


__all__ = ["demodulate", "remodulate", "fbeta_for_division", "sanitize"]

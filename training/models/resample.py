"""Pixel-centre-aligned upsampling with per-frame LR jitter (torch): the one resampling every model and the fast
ops share (a module of its own so that ``base`` and ``fast_ops`` do not import each other)."""
from __future__ import annotations

import torch
import torch.nn.functional as F


def upsample(x: torch.Tensor, scale: int, mode: str, jitter: torch.Tensor | None = None) -> torch.Tensor:
    """Bilinear/bicubic upsampling of (B, C, h, w) by ``scale`` with pixel-centre alignment (align_corners=False).
    With ``jitter`` (B, 2, LR pixels) the LR samples sit at their jittered positions: the HR pixel centre at LR
    position u is interpolated at grid position u - jitter (edges clamped). Zero jitter = plain interpolation."""
    if jitter is None:
        return F.interpolate(x, scale_factor=scale, mode=mode, align_corners=False)
    b, _, h, w = x.shape
    j = jitter.to(x.dtype)
    xs = (torch.arange(w * scale, device=x.device, dtype=x.dtype) + 0.5) / scale
    ys = (torch.arange(h * scale, device=x.device, dtype=x.dtype) + 0.5) / scale
    gx = (2.0 * (xs.view(1, 1, -1) - j[:, 0].view(b, 1, 1)) / w - 1.0).expand(b, h * scale, w * scale)
    gy = (2.0 * (ys.view(1, -1, 1) - j[:, 1].view(b, 1, 1)) / h - 1.0).expand(b, h * scale, w * scale)
    return F.grid_sample(x, torch.stack([gx, gy], dim=-1), mode=mode, padding_mode="border", align_corners=False)

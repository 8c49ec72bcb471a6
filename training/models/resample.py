"""Pixel-centre-aligned upsampling with per-frame LR jitter (torch): the one resampling every model and the fast
ops share (a module of its own so that ``base`` and ``fast_ops`` do not import each other)."""
from __future__ import annotations

import torch
import torch.nn.functional as F


def upsample(x: torch.Tensor, scale: float, mode: str, jitter: torch.Tensor | None = None) -> torch.Tensor:
    """Bilinear/bicubic upsampling of (B, C, h, w) by ``scale`` with pixel-centre alignment (align_corners=False).
    ``scale`` may be non-integer where h * scale and w * scale are integers (2.5 on a 32 x 16 image): the output is
    (round(h * scale), round(w * scale)) and HR pixel centre u sits at LR position u / scale. With ``jitter``
    (B, 2, LR pixels) the LR samples sit at their jittered positions: the HR pixel centre at LR position u is
    interpolated at grid position u - jitter (edges clamped). Zero jitter = plain interpolation."""
    b, _, h, w = x.shape
    if float(scale).is_integer():  # h * scale stays symbolic under ONNX tracing
        scale = int(scale)
        hh, ww = h * scale, w * scale
        if jitter is None:
            return F.interpolate(x, scale_factor=scale, mode=mode, align_corners=False)
    else:
        hh, ww = round(h * scale), round(w * scale)
        if jitter is None:
            return F.interpolate(x, size=(hh, ww), mode=mode, align_corners=False)
    j = jitter.to(x.dtype)
    xs = (torch.arange(ww, device=x.device, dtype=x.dtype) + 0.5) / scale
    ys = (torch.arange(hh, device=x.device, dtype=x.dtype) + 0.5) / scale
    gx = (2.0 * (xs.view(1, 1, -1) - j[:, 0].view(b, 1, 1)) / w - 1.0).expand(b, hh, ww)
    gy = (2.0 * (ys.view(1, -1, 1) - j[:, 1].view(b, 1, 1)) / h - 1.0).expand(b, hh, ww)
    return F.grid_sample(x, torch.stack([gx, gy], dim=-1), mode=mode, padding_mode="border", align_corners=False)

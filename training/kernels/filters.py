"""The separable pixel filter of the remodulation as shifted slices multiplied by constant taps (torch): the fast
ops' form (``training.models.fast_ops``) and the fused HR stage's fallback for filters longer than its kernel takes
(``training.kernels.hr_triton``)."""
from __future__ import annotations

import torch
import torch.nn.functional as F


def shift_filter(x: torch.Tensor, taps: tuple[float, ...]) -> torch.Tensor:
    """Separable convolution of (B, C, H, W) with ``taps`` x ``taps`` (odd length, Python floats), edges
    replicated: ``training.models.base.separable_filter`` as shifted slices."""
    k = len(taps) // 2
    if k == 0:
        return x * taps[0]
    h, w = x.shape[-2:]
    y = F.pad(x, (0, 0, k, k), mode="replicate")
    acc = y[..., 0:h, :] * taps[0]
    for i in range(1, len(taps)):
        acc = torch.add(acc, y[..., i:i + h, :], alpha=taps[i])
    y = F.pad(acc, (k, k, 0, 0), mode="replicate")
    out = y[..., 0:w] * taps[0]
    for i in range(1, len(taps)):
        out = torch.add(out, y[..., i:i + w], alpha=taps[i])
    return out

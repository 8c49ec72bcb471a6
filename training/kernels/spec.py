"""What one fused HR stage does and the tensors it reads (``hr_stage``'s module doc has the steps); shared by
its torch path (``hr_stage``) and its Triton kernels (``hr_triton``)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch


@dataclass(frozen=True)
class HRStage:
    """What one model's HR stage does (``hr_stage``'s module doc). ``sigmas``: (sigma_depth, sigma_normal) of the
    guides, None without ``guided``; ``taps``: the 1-D pixel filter (None: no filter); ``clamp``: with ``head``, the
    margin of the FuseSR family's ``residual_clamp`` (step 4b of ``hr_stage``), None: off; ``clamp_guided``: its
    ``"lr-guided"`` range (the taps of the pixel's surface only; needs ``guided``)."""
    scale: int
    by_class: bool
    guided: bool
    sigmas: tuple[float, float] | None
    head: bool
    log1p: bool
    remod: bool
    taps: tuple[float, ...] | None
    floor: float = 1e-4
    clamp: float | None = None
    clamp_guided: bool = False

    def __post_init__(self):
        if self.clamp_guided and not self.guided:
            raise ValueError("HRStage: clamp_guided needs guided (it weighs the taps by the guides)")


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

"""A test-only learned model that takes any scale >= 1 (``SCALES = None``): bilinear upsampling of the LR radiance
by the batch's scale plus a learned 1x1 convolution. It records the scales of the batches it saw."""
from __future__ import annotations

import torch.nn as nn

from training.models.base import SRModel, current, upsample


class TinyAnyScale(SRModel):
    learned = True
    NAME = "tiny-any"  # the row test_scales_training.py registers
    SCALES = None
    seen: list[float] = []

    def __init__(self, scale, **keys):
        super().__init__(scale, **keys)
        self.mix = nn.Conv2d(3, 3, 1)

    def needs(self):
        return ("lr/radiance",)

    def forward(self, batch):
        s = self.batch_scale(batch)
        TinyAnyScale.seen.append(s)
        up = upsample(current(batch, "lr/radiance"), s, "bilinear")
        return up + 0.01 * self.mix(up)

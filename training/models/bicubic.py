"""``bicubic``: bicubic upsampling (a = -0.75, PyTorch's kernel) of the LR radiance, negative lobes clamped at 0."""
from __future__ import annotations

from training.models.base import SRModel, current, upsample


class Bicubic(SRModel):
    learned = False
    NAME = "bicubic"
    SCALES = None  # any scale >= 1: the factor of each batch (batch['scale'])

    def needs(self):
        return ("lr/radiance",) + self.jitter_keys()

    def forward(self, batch):
        return upsample(current(batch, "lr/radiance"), self.batch_scale(batch), "bicubic",
                        self.frame_jitter(batch)).clamp(min=0.0)

"""``bilinear``: bilinear upsampling of the LR radiance (no training, no G-buffers)."""
from __future__ import annotations

from training.models.base import SRModel, current, upsample


class Bilinear(SRModel):
    learned = False
    NAME = "bilinear"
    SCALES = None  # any scale >= 1: the factor of each batch (batch['scale'])
    mode = "bilinear"

    def needs(self):
        return ("lr/radiance",) + self.jitter_keys()

    def forward(self, batch):
        return upsample(current(batch, "lr/radiance"), self.batch_scale(batch), self.mode, self.frame_jitter(batch))

"""``demod-bilinear``: the honest non-learned baseline with HR G-buffers.

SR = K * (bilinear(L_D^LR) F_used^HR + E^HR), where L_D^LR = (I^LR - E^LR) / F_used^LR (``gbuffer_export.demod``)
and K is the ground truth's pixel filter (``model.remod_filter``, ``SRModel.remodulate``): the point-sampled HR
G-buffers give point samples, the reference averages its samples with K. The HR material detail comes from the HR
F_beta; no ground truth is used. With ``model.upsample_by_class`` (default on) the bilinear step never mixes
demodulated pixels with pixels where F_used = 1 (background, UNTRUSTED flags): ``base.upsample_by_class``.
It never reads the HR geometry (``demod-jbu`` does).
"""
from __future__ import annotations

from training.models.base import SRModel, current


class DemodBilinear(SRModel):
    learned = False
    NAME = "demod-bilinear"
    demod = True

    def needs(self):
        keys = ("lr/irradiance", "hr/fbeta_used", "hr/emission") + self.upsample_keys()
        return tuple(dict.fromkeys(keys)) + self.jitter_keys()

    def forward(self, batch):
        if self.hr_impl:  # the fused HR stage (training.kernels.hr_stage): the same math in one pass
            return self.fused_hr(batch, current(batch, "lr/irradiance"), self.frame_jitter(batch))
        irr = self.upsample_input(current(batch, "lr/irradiance"), batch, self.frame_jitter(batch))
        return self.remodulate(irr, batch)

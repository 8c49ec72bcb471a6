"""``demod-jbu``: the non-learned baseline that reads the HR geometry.

SR = K * (JBU(L_D^LR) F_used^HR + E^HR): ``demod-bilinear`` with the bilinear step replaced by joint bilateral
upsampling guided by HR depth and normals (``guided.upsample_guided``; Kopf et al. 2007): an HR pixel interpolates
only the LR samples of its class that lie on a similar surface (``model.demod-jbu.guide_sigma_depth``, relative
depth, and ``guide_sigma_normal``), falling back to the class-aware bilinear value where none does. It uses every HR
G-buffer a G-buffer network gets except albedo, with no training: a network with HR G-buffers that cannot beat it
has not learned to use them.
"""
from __future__ import annotations

from training.models.demod_bilinear import DemodBilinear


class DemodJBU(DemodBilinear):
    """``DemodBilinear`` whose ``upsample_input`` is guided (``SRModel.guided``); needs and forward are shared."""

    NAME = "demod-jbu"

    def __init__(self, scale: int, **keys):
        super().__init__(scale, **keys)  # keys: SRModel's; options: DemodJBUOptions
        self.guided = True
        self.guide_sigmas = (self.options.guide_sigma_depth, self.options.guide_sigma_normal)

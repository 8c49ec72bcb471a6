"""``fusesr-l``: the performance-oriented FuseSR ("Ours l" of the paper): no history frames, the fusion network at
half width (64 channels, HR branch 32) and every convolution of the fusion network depthwise-separable.
The encoder, head and remodulation are those of ``fusesr`` (see its docstring)."""
from __future__ import annotations

from training.models.fusesr import FuseSR


class FuseSRLight(FuseSR):
    learned = True
    NAME = "fusesr-l"
    default_history = 0  # width 64: training.models.options.FuseSRLightOptions
    hr_channels = 32
    separable = True

"""VGG-16 perceptual distance from a weights file that the user supplies (torch; no torchvision, no download).

The layers are defined here (13 3x3 convolutions with ReLU and 4 max-pools, the ``features`` part of VGG-16) and
take a state dict in torchvision's layout: keys ``features.N.weight`` / ``features.N.bias`` (or ``N.weight``),
N the index in the ``features`` sequence. The distance is the sum over relu1_2, relu2_2, relu3_3 and relu4_3 of the
mean squared feature difference, on tonemapped images normalised with the ImageNet mean and deviation.
"""
from __future__ import annotations

from pathlib import Path

import torch
import torch.nn as nn

from gbuffer_export.config import ConfigError

CFG = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M")
TAPS = (3, 8, 15, 22)  # indices (in ``features``) of relu1_2, relu2_2, relu3_3, relu4_3
MEAN = (0.485, 0.456, 0.406)
STD = (0.229, 0.224, 0.225)


def vgg16_features() -> nn.Sequential:
    layers: list[nn.Module] = []
    cin = 3
    for v in CFG:
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(cin, v, 3, padding=1), nn.ReLU(inplace=False)]
            cin = v
    return nn.Sequential(*layers)


class VGGFeatures(nn.Module):
    def __init__(self):
        super().__init__()
        self.features = vgg16_features()[: TAPS[-1] + 1]
        self.register_buffer("mean", torch.tensor(MEAN).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(STD).view(1, 3, 1, 1))
        for p in self.parameters():
            p.requires_grad_(False)
        self.eval()

    @classmethod
    def from_file(cls, path: str | Path) -> "VGGFeatures":
        """Load VGG-16 weights from ``path``; ConfigError when missing or not a VGG-16 state dict."""
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"{path}: VGG-16 weights file not found; the perceptual loss needs weights you "
                              "supply (BlendSR downloads nothing); set loss.perceptual_weight = 0 to train without")
        try:
            sd = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:
            raise ConfigError(f"{path}: cannot read VGG-16 weights ({exc})") from None
        if isinstance(sd, dict) and "state_dict" in sd:
            sd = sd["state_dict"]
        m = cls()
        own = m.features.state_dict()
        picked = {}
        for k in own:
            for cand in (f"features.{k}", k):
                if cand in sd:
                    picked[k] = sd[cand]
                    break
        missing = [k for k in own if k not in picked]
        if missing:
            raise ConfigError(f"{path}: not a VGG-16 state dict (missing {', '.join(missing[:3])} ...)")
        try:
            m.features.load_state_dict(picked)
        except RuntimeError as exc:
            raise ConfigError(f"{path}: VGG-16 weights have the wrong shapes ({str(exc).splitlines()[0]})") from None
        return m

    def train(self, mode: bool = True):  # always frozen
        return super().train(False)

    def taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = (x - self.mean) / self.std
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in TAPS:
                out.append(x)
        return out

    def distance(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Sum over taps of mean squared feature differences; a, b tonemapped (B, 3, H, W) in [0, 1]."""
        return sum(((fa - fb) ** 2).mean() for fa, fb in zip(self.taps(a), self.taps(b)))

"""VGG-16 perceptual distance from torchvision's ImageNet weights file, which the user downloads (torch; no
torchvision, nothing downloaded at run time).

The layers are defined here (13 3x3 convolutions with ReLU and 4 max-pools, the ``features`` part of VGG-16) and
take a state dict in torchvision's layout: keys ``features.N.weight`` / ``features.N.bias`` (or ``N.weight``),
N the index in the ``features`` sequence. The weights are torchvision's ``vgg16-397923af.pth`` (``VGG16_URL``, the
ImageNet weights the FuseSR paper's perceptual loss used, 553,433,881 bytes); ``loss.vgg_weights`` names the file and
its sha256 must be ``VGG16_SHA256`` (``require_vgg_file``). The distance is the sum over relu1_2, relu2_2, relu3_3
and relu4_3 of the mean squared feature difference, on tonemapped images normalised with the ImageNet mean and
deviation.
"""
from __future__ import annotations

import functools
import hashlib
import os
from pathlib import Path

import torch
import torch.nn as nn

from gbuffer_export.config import ConfigError

CFG = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M")
TAPS = (3, 8, 15, 22)  # indices (in ``features``) of relu1_2, relu2_2, relu3_3, relu4_3
MEAN = (0.485, 0.456, 0.406)
STD = (0.229, 0.224, 0.225)

KEY = "loss.vgg_weights"
VGG16_FILE = "vgg16-397923af.pth"  # torchvision's VGG16_Weights.IMAGENET1K_V1; the name holds its sha256's first 8
VGG16_URL = f"https://download.pytorch.org/models/{VGG16_FILE}"
VGG16_SHA256 = "397923af8e79cdbb6a7127f12361acd7a2f83e06b05044ddf496e83de57a5bf0"
VGG16_BYTES = 553_433_881


def download_hint() -> str:
    """What to download and where to point ``loss.vgg_weights`` (the tail of every error of this module)."""
    return (f"download {VGG16_URL} ({VGG16_BYTES / 2**20:.0f} MiB, sha256 {VGG16_SHA256}) yourself and set "
            f"{KEY} to its path (BlendSR downloads nothing), or set loss.perceptual_weight = 0")


@functools.lru_cache(maxsize=8)
def _sha256(path: str, size: int, mtime_ns: int) -> str:  # size, mtime: a changed file is hashed again
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


def require_vgg_file(path: str | os.PathLike, check_hash: bool = True) -> Path:
    """``path`` as a Path when it names a file whose sha256 is ``VGG16_SHA256`` (with ``check_hash``; without, the
    file only has to exist); ConfigError (one line naming ``loss.vgg_weights`` and what to download) otherwise."""
    if not str(path):
        raise ConfigError(f"loss.perceptual_weight > 0 needs {KEY}: {download_hint()}")
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"{KEY} {path}: file not found; {download_hint()}")
    if check_hash:
        st = p.stat()
        got = _sha256(str(p.resolve()), st.st_size, st.st_mtime_ns)
        if got != VGG16_SHA256:
            raise ConfigError(f"{KEY} {path}: sha256 {got[:16]}... is not that of {VGG16_FILE} (a different or "
                              f"damaged file); {download_hint()}")
    return p


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
        """Load VGG-16 weights from ``path`` (torchvision's ``VGG16_FILE``, hash checked); ConfigError when missing,
        another file or not a VGG-16 state dict."""
        path = require_vgg_file(path)
        try:
            sd = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:
            raise ConfigError(f"{KEY} {path}: cannot read VGG-16 weights ({exc}); {download_hint()}") from None
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
            raise ConfigError(f"{KEY} {path}: not a VGG-16 state dict (missing {', '.join(missing[:3])} ...); "
                              f"{download_hint()}")
        try:
            m.features.load_state_dict(picked)
        except RuntimeError as exc:
            raise ConfigError(f"{KEY} {path}: VGG-16 weights have the wrong shapes ({str(exc).splitlines()[0]}); "
                              f"{download_hint()}") from None
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

"""``fusesr-fast``: the fast FuseSR variant of the authors' public code (``FuseSR_Fast``), written from its layer sizes.

LR current frame only (no history). Layer by layer at scale s (LR resolution unless stated):

    encoder   7 -> 32 (3x3, ReLU) = F_s, then four depthwise-separable 3x3 convolutions 32 -> 16 -> 12 -> 12 -> 16,
              each followed by ReLU (and BatchNorm with the option ``norm = "batch"``, as the authors)
    expand    16 -> 32 (3x3, ReLU)
    fuse_in   [expand, pixel-unshuffled HR F_beta (3 s^2 channels), jitter maps (2)] -> 32 (3x3, ReLU)
    blocks    6 inverted residual blocks of 32 channels, expansion 1: x + pw1x1(ReLU6(dw3x3(x))) (BatchNorm after
              both convolutions with ``norm = "batch"``, else the convolutions carry biases)
    head      [blocks, F_s] (64) -> 3 s^2 (3x3), pixel shuffle to HR
    refine    3 -> 3 (3x3, HR)

Unlike ``fusesr`` there is no HR G-buffer branch: the HR F_beta enters the fusion convolution unshuffled, as in the
authors' code. The frame around the network is ``fusesr``'s: log1p input transform, ratio-normalised depth, the
jitter maps, the residual base (``residual``; with ``guided_upsample`` the joint bilateral upsampling
guided by HR depth and normals, which then become inputs), the final ReLU and the remodulation through the ground
truth's pixel filter. ``guided_upsample = false`` reads exactly the authors' inputs (LR irradiance, depth,
normal and HR F_beta) plus the jitter.

Size at 4x with the defaults (``norm = "none"``): 68 188 parameters (68 108 with BatchNorm and without the two
jitter channels, the authors' count); about 4.3 K multiply-accumulates per HR pixel (66 872 per LR pixel / 16 plus
the 81 of the HR refinement); ``confidence_gate`` adds 1 040 parameters (a 1x1 conv 64 -> 16) and 64
multiply-accumulates per HR pixel. Options: the ``[model.fusesr-fast]`` table
(``training.models.options.FuseSRFastOptions``; ``width`` and ``blocks`` change the backbone, defaults 32 and 6).

HR geometry (``hr_geometry``, default off; not in the authors' network): the fusion convolution's pre-activation
gains a 1x1 convolution of the pixel-unshuffled HR normalised depth, normals and albedo (7 s^2 channels -> ``width``),
the HR G-buffers FuseSR's HR branch reads and the authors' fast network leaves out (it reads only the HR F_beta,
which is 1 wherever demodulation is off). At 4x: 3 616 parameters and 224 multiply-accumulates per HR pixel. It
starts at zero, so ``run.init_from`` weights trained without it (which start it fresh) give the same output.
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from gbuffer_export.errors import BlendSRError
from training.models.base import DWSConv, conv, current, depth_features, frame
from training.models.fusesr import HR_GEOMETRY_CHANNELS, HR_GEOMETRY_KEYS, FuseSRFrame
from training.transforms import forward_transform

PRIMARY = 32
ENCODER_CHANNELS = (16, 12, 12, 16)


class FastEncoder(nn.Module):
    """7 -> 32 (ReLU) = F_s, then 32-16-12-12-16 separable convolutions with ReLU. Returns (F_s, F_f)."""

    def __init__(self, cin: int = 7, norm: str = "none"):
        super().__init__()
        self.shallow = nn.Sequential(conv(cin, PRIMARY), nn.ReLU(inplace=True))
        layers = []
        for a, b in zip((PRIMARY,) + ENCODER_CHANNELS[:-1], ENCODER_CHANNELS):
            layers.append(DWSConv(a, b))  # depthwise 3x3 then pointwise 1x1, both biased (the authors' DWS)
            if norm == "batch":
                layers.append(nn.BatchNorm2d(b))
            layers.append(nn.ReLU(inplace=True))
        self.main = nn.Sequential(*layers)

    def forward(self, x):
        s = self.shallow(x)
        return s, self.main(s)


class InvertedResidual(nn.Module):
    """MobileNetV2 block with expansion 1: x + pw1x1(ReLU6(dw3x3(x))), BatchNorm after each convolution with
    ``norm = "batch"`` (convolutions without bias then), else biased convolutions."""

    def __init__(self, channels: int, norm: str = "none"):
        super().__init__()
        bn = norm == "batch"
        self.depthwise = nn.Conv2d(channels, channels, 3, padding=1, groups=channels, bias=not bn)
        self.norm1 = nn.BatchNorm2d(channels) if bn else nn.Identity()
        self.pointwise = nn.Conv2d(channels, channels, 1, bias=not bn)
        self.norm2 = nn.BatchNorm2d(channels) if bn else nn.Identity()

    def forward(self, x):
        return x + self.norm2(self.pointwise(F.relu6(self.norm1(self.depthwise(x)))))


class FuseSRFast(FuseSRFrame):
    NAME = "fusesr-fast"
    FRESH_PARAMETERS = FuseSRFrame.GATE_PARAMETERS + ("hr_in.weight", "hr_in.bias")

    def __init__(self, scale: int, **keys):
        super().__init__(scale, **keys)  # keys: SRModel's; options: FuseSRFastOptions (switches read by FuseSRFrame)
        if self.config.history > 0:
            raise BlendSRError(f"model.history {self.config.history}: fusesr-fast reads no history (set -1 or 0)")
        self.history = 0
        opt = self.options
        norm, width, blocks = opt.norm, opt.width, opt.blocks
        s = self.scale
        self.encoder = FastEncoder(7, norm)
        self.expand = nn.Sequential(conv(ENCODER_CHANNELS[-1], width), nn.ReLU(inplace=True))
        cin = width + (3 * s * s if self.use_hr else 0) + (2 if self.use_jitter else 0)
        self.fuse_in = nn.Sequential(conv(cin, width), nn.ReLU(inplace=True))
        self.blocks = nn.Sequential(*[InvertedResidual(width, norm) for _ in range(blocks)])
        self.head = conv(width + PRIMARY, 3 * s * s)
        self.refine = conv(3, 3)
        self.confidence = self.confidence_head(width + PRIMARY)
        self.hr_in = None  # hr_geometry (module doc): 1x1 conv of the unshuffled HR geometry into the fusion
        if opt.hr_geometry and self.use_hr:
            self.hr_in = nn.Conv2d(HR_GEOMETRY_CHANNELS * s * s, width, 1)
            nn.init.zeros_(self.hr_in.weight)  # starts as the network without it (run.init_from: FRESH_PARAMETERS)
            nn.init.zeros_(self.hr_in.bias)
        if opt.zero_init_refine and self.residual:
            nn.init.zeros_(self.refine.weight)
            nn.init.zeros_(self.refine.bias)

    def needs(self):
        keys = [self.color_key, "lr/depth", "lr/normal", "depth_ref"]
        if self.use_hr or self.demod:
            keys.append("hr/fbeta_used")
        if self.demod:
            keys.append("hr/emission")
        if self.hr_in is not None:
            keys += HR_GEOMETRY_KEYS
        if self.residual:
            keys += self.upsample_keys(self.demod)
        return tuple(dict.fromkeys(keys + list(self.fallback_keys()))) + self.jitter_keys()

    def forward(self, batch):
        color = forward_transform(frame(batch, self.color_key, 0), self.transform)
        x = torch.cat([color, depth_features(batch, "lr", 0, self.depth_norm), current(batch, "lr/normal")], dim=1)
        f_s, f_f = self.encoder(x)
        feats = [self.expand(f_f)]
        if self.use_hr:
            feats.append(F.pixel_unshuffle(current(batch, "hr/fbeta_used").to(f_f.dtype), self.scale))
        j_t = self.frame_jitter(batch)
        if j_t is not None:
            feats.append(j_t.to(f_f.dtype).view(-1, 2, 1, 1).expand(-1, -1, *f_f.shape[-2:]))
        z = self.fuse_in[0](torch.cat(feats, dim=1))
        if self.hr_in is not None:
            z = z + self.hr_in(F.pixel_unshuffle(self.hr_geometry(batch).to(z.dtype), self.scale))
        y = self.blocks(self.fuse_in[1](z))
        head_in = torch.cat([y, f_s], dim=1)
        y = self.refine(F.pixel_shuffle(self.head(head_in), self.scale))
        return self.output(self.gated(y, head_in, batch), x[:, :3], batch, j_t)

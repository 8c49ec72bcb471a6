"""``nsrr`` and ``nsrr-fec``: Neural Supersampling for Real-time Rendering (NSRR, Xiao et al. 2020) and its
extension with auxiliary feature enhancement and feature caching (Zhong, Chen, Wang and Huo, Journal of Database
Management 34(3), 2023), written from the papers. docs/models/nsrr_fec.md lists the sizes and every deviation.

Per LR frame the RGB-D input is [T(radiance) 3, depth 1] (T = ``model.input_transform``, log1p by default; depth
normalised by ``model.depth_norm`` with the current frame's reference). Colour: the current frame's T(radiance)
goes through the BT.709 R'G'B' -> Y'CbCr matrix (full range, chroma centred at 0; ``gbuffer_export.colour_spaces``), the network's
3 output channels through its inverse, then T^-1. T first: BT.709 defines Y'CbCr on non-linear R'G'B', and T is the
project's non-linear encoding of HDR radiance (the matrix applied to linear radiance would give log a signed
chroma to compress).

- Feature extraction (one network for every frame): 3x3 convs 4 -> 32 -> 32 -> 8, ReLU after each, concatenated
  with its input: 12 channels per LR frame.
- Zero upsampling: each LR sample's 12 features go to the HR pixel that holds its jittered position
  ((p + 0.5 + j) * s, ``lr_jitter``; the centre without jitter), the other HR pixels are 0.
- History (``history`` = 4 previous frames; ``model.history`` 1..4 overrides): backward warping at HR with the LR
  motion bilinearly upsampled (at the jittered positions) and multiplied by s; no jitter term, the zero-upsampled
  samples already sit at their jittered HR positions.
- Feature reweighting: 3x3 convs on the zero-upsampled RGB-D of the current frame and the warped previous frames
  (4 (history + 1) channels) -> 32 -> 32 (ReLU) -> history; 5 (tanh + 1), a weight in [0, 10] per previous frame
  that multiplies its 12 warped features.
- Reconstruction: a U-Net at HR on [current 12, reweighted previous 12 x history (, G-buffer features 17)]:
  3x3 convs 64, 32 | max-pool, 64, 64 | max-pool, 128, 128 | bilinear x2, concat, 64, 64 | bilinear x2, concat,
  32, 3 (ReLU after every conv but the last). HR sides are padded (zeros) to a multiple of 4, the output cropped.

``nsrr`` (base NSRR, not recurrent): the window holds the 4 previous LR frames; each goes through feature
extraction in RGB (only the current frame is in Y'CbCr, as NSRR does), is zero-upsampled and warped to the current
frame by accumulative backward warping (frame t-k warped k times, with the motion of frames t-k+1 .. t).

``nsrr-fec`` (recurrent, ``training.recurrent``): every frame in Y'CbCr, so the current frame's zero-upsampled
features are cached and reused as history. The state is the cache: ``history`` HR feature maps (B, 12, H, W) in the
previous frame's screen space, newest first. Each step warps every cached map once with the current frame's motion,
reweights and reconstructs, then caches [current, the newest history - 1 warped maps]. At a clip's first frame the
current features stand in for the whole history. Enhancement: HR G-buffers [albedo 3, metallic 1, normal 3,
roughness 1, specular 1] go through a feature extractor of the same structure (9 -> 32 -> 32 -> 8, concatenated with
the input: 17 channels) into the reconstruction input.

Deviation (``[model.nsrr]`` / ``[model.nsrr-fec]`` ``residual``, default off = the paper): the U-Net's output (after
Y'CbCr -> RGB) is added to T(demod-bilinear's upsampling of L_D) (``SRModel.demod_base``) and the sum, T(L_D^HR), is
inverted and remodulated with HR F_beta and emission, so the network learns a correction of ``demod-bilinear``; the
inputs stay the paper's. ``zero_init_head`` starts the U-Net's last conv at 0, so a fresh network is exactly that
baseline (docs/models/nsrr_fec.md, "Base").
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from gbuffer_export.errors import BlendSRError
from gbuffer_export.colour_spaces import RGB_TO_YCBCR_709, YCBCR_TO_RGB_709
from training.models.base import (SRModel, backward_warp, current, depth_features, frame, jitter, upsample,
                                  zero_init)
from training.transforms import forward_transform, inverse_transform

HISTORY = 4                      # previous frames (NSRR: 4)
FEATURES = (32, 32, 8)           # feature extraction widths; its output is concatenated with its input
REWEIGHT = (32, 32)              # feature reweighting hidden widths
WEIGHT_RANGE = 10.0              # reweighting output range [0, WEIGHT_RANGE]
UNET = ((64, 32), (64, 64), (128, 128), (64, 64), (32,))  # encoder 1, 2, bottleneck, decoder 1, 2 (then 3)
#: HR G-buffers of the enhancement (clip buffer, channels): UE4's base colour, metallic, normal, roughness, specular.
GBUFFERS = (("albedo", 3), ("metallic", 1), ("normal", 3), ("roughness", 1), ("specular", 1))
PAD = 4                          # two 2x2 max-pools


def ycbcr_matrices() -> tuple[np.ndarray, np.ndarray]:
    """(R'G'B' -> Y'CbCr, Y'CbCr -> R'G'B') 3x3 float64: ITU-R BT.709 weights, full range, chroma centred at 0
    (``gbuffer_export.colour_spaces``, tested there against colour-science)."""
    return RGB_TO_YCBCR_709, YCBCR_TO_RGB_709


def apply_matrix(x: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    """3x3 colour matrix ``m`` applied per pixel to (B, 3, H, W), in x's dtype (products and a sum: no autocast)."""
    return (m.to(x.dtype).view(1, 3, 3, 1, 1) * x.unsqueeze(1)).sum(dim=2)


def zero_upsample(x: torch.Tensor, scale: int, jitter: torch.Tensor | None) -> torch.Tensor:
    """(B, C, h, w) -> (B, C, s h, s w): LR pixel p's values at HR pixel floor((p + 0.5 + j) s) of its s x s block
    (j the frame's jitter (B, 2), LR pixels, x then y; 0 when None), zeros elsewhere."""
    b, c, h, w = x.shape
    s = scale
    if jitter is None:
        k = torch.full((b,), (s // 2) * s + s // 2, dtype=torch.long, device=x.device)
    else:
        pos = torch.floor((0.5 + jitter.to(torch.float32)) * s).clamp(0, s - 1).long()  # (B, 2) within the block
        k = pos[:, 1] * s + pos[:, 0]
    onehot = (torch.arange(s * s, device=x.device).view(1, -1) == k.view(-1, 1)).to(x.dtype)  # (B, s^2)
    y = x.unsqueeze(2) * onehot.view(b, 1, s * s, 1, 1)  # pixel_shuffle reads channel c s^2 + dy s + dx
    return F.pixel_shuffle(y.reshape(b, c * s * s, h, w), s)


def conv(cin: int, cout: int) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 3, padding=1)


class FeatureExtractor(nn.Module):
    """3x3 convs cin -> 32 -> 32 -> 8 with ReLU, concatenated with the input: cin + 8 channels."""

    def __init__(self, cin: int):
        super().__init__()
        widths = (cin,) + FEATURES
        self.convs = nn.ModuleList([conv(a, b) for a, b in zip(widths[:-1], widths[1:])])
        self.out_channels = cin + FEATURES[-1]

    def forward(self, x):
        y = x
        for c in self.convs:
            y = F.relu(c(y))
        return torch.cat([y, x], dim=1)


class Reweighting(nn.Module):
    """Weights in [0, WEIGHT_RANGE] (B, n, H, W) for n previous frames from the RGB-D of all n + 1 frames."""

    def __init__(self, n: int):
        super().__init__()
        widths = (4 * (n + 1),) + REWEIGHT
        self.hidden = nn.ModuleList([conv(a, b) for a, b in zip(widths[:-1], widths[1:])])
        self.out = conv(REWEIGHT[-1], n)

    def forward(self, x):
        for c in self.hidden:
            x = F.relu(c(x))
        return 0.5 * WEIGHT_RANGE * (torch.tanh(self.out(x)) + 1.0)


class UNet(nn.Module):
    """The reconstruction U-Net (module doc): cin -> 3, sides multiples of 4."""

    def __init__(self, cin: int):
        super().__init__()
        (e1a, e1b), (e2a, e2b), (ba, bb), (d1a, d1b), (d2a,) = UNET
        self.enc1 = nn.ModuleList([conv(cin, e1a), conv(e1a, e1b)])
        self.enc2 = nn.ModuleList([conv(e1b, e2a), conv(e2a, e2b)])
        self.bottleneck = nn.ModuleList([conv(e2b, ba), conv(ba, bb)])
        self.dec1 = nn.ModuleList([conv(bb + e2b, d1a), conv(d1a, d1b)])
        self.dec2 = nn.ModuleList([conv(d1b + e1b, d2a)])
        self.out = conv(d2a, 3)

    @staticmethod
    def _run(layers, x):
        for c in layers:
            x = F.relu(c(x))
        return x

    def forward(self, x):
        s1 = self._run(self.enc1, x)
        s2 = self._run(self.enc2, F.max_pool2d(s1, 2))
        y = self._run(self.bottleneck, F.max_pool2d(s2, 2))
        y = F.interpolate(y, scale_factor=2.0, mode="bilinear", align_corners=False)
        y = self._run(self.dec1, torch.cat([y, s2], dim=1))
        y = F.interpolate(y, scale_factor=2.0, mode="bilinear", align_corners=False)
        y = self._run(self.dec2, torch.cat([y, s1], dim=1))
        return self.out(y)


class NSRR(SRModel):
    """Base NSRR (module doc): 4 previous frames read from the window, accumulative backward warping."""

    learned = True
    enhanced = False

    NAME = "nsrr"

    def __init__(self, scale: int, **keys):
        super().__init__(scale, **keys)  # keys: SRModel's; options: NSRROptions
        cfg = self.config
        n = HISTORY if cfg.history < 0 else int(cfg.history)
        if not 1 <= n <= 4:
            raise BlendSRError(f"model.history {cfg.history}: {cfg.name} needs 1..4 previous frames")
        self.n_prev = n
        self.history = 0 if self.recurrent else n
        to_ycbcr, to_rgb = ycbcr_matrices()
        self.register_buffer("to_ycbcr", torch.tensor(to_ycbcr, dtype=torch.float32), persistent=False)
        self.register_buffer("to_rgb", torch.tensor(to_rgb, dtype=torch.float32), persistent=False)
        self.features = FeatureExtractor(4)
        self.reweight = Reweighting(n)
        cin = self.features.out_channels * (n + 1)
        if self.enhanced:
            self.gbuffer_features = FeatureExtractor(sum(c for _, c in GBUFFERS))
            cin += self.gbuffer_features.out_channels
        self.unet = UNet(cin)
        opt = self.options
        self.residual = self.demod = bool(opt.residual)
        if opt.zero_init_head:  # a fresh network outputs its residual base (module doc)
            zero_init(self.unet.out)

    def needs(self):
        keys = ("lr/radiance", "lr/depth", "depth_ref", "lr/motion")
        if self.enhanced:
            keys += tuple(f"hr/{name}" for name, _ in GBUFFERS)
        if self.residual:
            keys += self.base_keys() + ("hr/fbeta_used", "hr/emission")
        return tuple(dict.fromkeys(keys)) + self.jitter_keys()

    # ------------------------------------------------------------------ pieces
    def rgbd(self, batch: dict, back: int, ycbcr: bool) -> torch.Tensor:
        """(B, 4, h, w) [T(radiance) (in Y'CbCr when ``ycbcr``), normalised depth] of frame t - back."""
        img = forward_transform(frame(batch, "lr/radiance", back), self.transform)
        if ycbcr:
            img = apply_matrix(img, self.to_ycbcr)
        d = depth_features(batch, "lr", back, self.depth_norm).to(img.dtype)
        return torch.cat([img, d], dim=1)

    def frame_features(self, batch: dict, back: int, ycbcr: bool) -> torch.Tensor:
        """(B, 12, H, W) zero-upsampled features of frame t - back."""
        j = jitter(batch, back) if self.use_jitter else None
        return zero_upsample(self.features(self.rgbd(batch, back, ycbcr)), self.scale, j)

    def hr_motion(self, batch: dict, back: int) -> torch.Tensor:
        """(B, 2, H, W) backward motion of frame t - back in HR pixels: LR motion upsampled at its jittered samples."""
        j = jitter(batch, back) if self.use_jitter else None
        return upsample(frame(batch, "lr/motion", back), self.scale, "bilinear", j) * self.scale

    def gbuffer_input(self, batch: dict, dtype) -> torch.Tensor:
        return torch.cat([current(batch, f"hr/{name}").to(dtype) for name, _ in GBUFFERS], dim=1)

    def reconstruct(self, cur: torch.Tensor, prev: list[torch.Tensor], batch: dict) -> torch.Tensor:
        """HR radiance (B, 3, H, W) from the current and the warped previous features (B, 12, H, W) each. With
        ``residual`` the U-Net's output (in RGB) is T(L_D^HR) - the base, remodulated (module doc)."""
        w = self.reweight(torch.cat([cur[:, -4:]] + [p[:, -4:] for p in prev], dim=1))
        parts = [cur] + [p * w[:, i:i + 1] for i, p in enumerate(prev)]
        if self.enhanced:
            parts.append(self.gbuffer_features(self.gbuffer_input(batch, cur.dtype)))
        x = torch.cat(parts, dim=1)
        h, wd = x.shape[-2:]
        ph, pw = (-h) % PAD, (-wd) % PAD
        if ph or pw:
            x = F.pad(x, (0, pw, 0, ph))
        y = apply_matrix(self.unet(x)[:, :, :h, :wd].float(), self.to_rgb)
        if not self.residual:
            return inverse_transform(y, self.transform)
        y = y + self.demod_base(batch, self.frame_jitter(batch)).float()
        return self.remodulate(inverse_transform(y, self.transform), batch)

    # ------------------------------------------------------------------ forward
    def forward(self, batch):
        cur = self.frame_features(batch, 0, ycbcr=True)
        prev = []
        for k in range(1, self.n_prev + 1):
            f = self.frame_features(batch, k, ycbcr=False)
            for i in range(k - 1, -1, -1):  # accumulative: frame t-i's motion brings t-i-1 into t-i
                f, _ = backward_warp(f, self.hr_motion(batch, i).to(f.dtype))
            prev.append(f)
        return self.reconstruct(cur, prev, batch)


class NSRRFEC(NSRR):
    """NSRR with feature enhancement and caching (module doc); recurrent, the state is the feature cache."""

    NAME = "nsrr-fec"
    recurrent = True
    enhanced = True

    def state_shapes(self, lr_h: int, lr_w: int, batch: int = 1) -> list[tuple[int, ...]]:
        """The cache: ``history`` maps (B, 12, H, W) at HR, newest first."""
        c = self.features.out_channels
        return [(batch, c, lr_h * self.scale, lr_w * self.scale)] * self.n_prev

    def step(self, batch: dict, state: list[torch.Tensor] | None = None, reset: torch.Tensor | None = None):
        """SR (B, 3, H, W) of the last frame of ``batch`` and the new cache. ``state`` None: a clip's first frame.
        ``reset`` (B,) float, 1 where an element starts a clip and its ``state`` is ignored (the ONNX graph's
        explicit form of None)."""
        cur = self.frame_features(batch, 0, ycbcr=True)
        if state is None:
            prev = [cur] * self.n_prev
        else:
            m = self.hr_motion(batch, 0).to(cur.dtype)
            prev = [backward_warp(s.to(cur.dtype), m)[0] for s in state]  # each cached map warped once
            if reset is not None:
                r = reset.to(cur.dtype).view(-1, 1, 1, 1)
                prev = [r * cur + (1 - r) * p for p in prev]
        sr = self.reconstruct(cur, prev, batch)
        return sr, [cur] + prev[:-1]

    def forward(self, batch):
        """Every frame of the batch in order from a reset state; the SR of the last one."""
        from training.models.window import frame_slice
        t = batch["lr/radiance"].shape[1]
        state, sr = None, None
        for i in range(t):
            sr, state = self.step(frame_slice(batch, i), state)
        return sr

"""``rdg`` and ``rdg-s``: RDG, the recurrent asymmetric U-Net with decoupled G-buffer guidance (Zhou et al.,
CVPR 2025), written from the paper and the layer sizes of the authors' public code (``sunny2109/RDG``).

Inputs, all LR and all of the current frame: the image T(radiance) (T = ``model.input_transform``, log1p by
default, inverted at the output), the G-buffers normal, pre-integrated BRDF (``lr/fbeta``), depth (normalised by
``model.depth_norm``: d / (d + median depth of the frame), background 1) and motion; the state is the three
decoder outputs of the previous frame. Width C = 36 (``rdg``) or 16 (``rdg-s``), the option ``width`` (the
``[model.rdg]`` / ``[model.rdg-s]`` table, ``training.models.options.RDGOptions``).

- Shallow 3x3 conv 3 (+2 jitter channels, below) -> C.
- Encoder: EncodeLayer(C) [DFM + CCM, both residual], 3x3 stride-2 conv C -> 2C, EncodeLayer(2C), 3x3 stride-2 conv
  2C -> 3C, EncodeLayer(3C) (the middle).
- DFM(C): depthwise 3x3 conv C -> 2C then 1x1 2C -> 2C, split into a gate g and a content c (C each);
  c -> CycleFC 1x7 -> CycleFC 7x1; GELU(g) * 1x1conv([x, c]) (2C -> C); 1x1 conv C -> C.
- CycleFC (deformable sampling with constant integer offsets and a 1x1 kernel): channel i is shifted by
  (i + 3) mod 7 - 3 pixels along the sampling axis (zeros beyond the border), then a 1x1 convolution mixes the
  channels. The authors call torchvision's deform_conv2d with these offsets; the shift is exactly equivalent and
  exports to ONNX.
- CCM(C): 3x3 conv C -> 2C, GELU, 1x1 conv 2C -> C.
- Decoder, at 1/4, 1/2 and 1 times the LR size: DecodeLayer(3C), then twice [bilinear x2 and 3x3 conv to the
  next width, plus alpha * the encoder skip (alpha per channel, starts at 0), DecodeLayer]. DecodeLayer(D):
  HFB, CTR and CCM, each residual. Its output is this level's hidden state for the next frame.
- HFB(D): x' = 3x3 conv(x), g' = 3x3 conv([normal, BRDF] resized to the level) (6 -> D);
  1x1 conv [x' GELU(g'), g' GELU(x')] (2D -> D).
- CTR(D): the previous frame's hidden state of this level is warped to the current frame with the motion; Q from
  the current features (1x1 conv D -> 2D, depthwise 3x3), K and V from the warped state (1x1 conv D -> 4D,
  depthwise 3x3); Q splits into Q1, Q2 (D each). Attention over channels in 4 heads as in the authors' code
  (Q1 and K L2-normalised over the pixels, softmax over K's channels; the paper's Eq. 5 reads spatial); the
  output, Q2 and the level's depth go through a 1x1 conv (2D + 1 -> D). The authors' unused ``alpha`` parameter of
  CTR is kept (created, never read) so that the parameter counts equal the published ones; it has no gradient.
- Head: (+ the shallow features) 3x3 conv C -> 3 s^2, pixel shuffle, T^-1.

At a clip's first frame (no state) CTR attends to the current features themselves with zero motion, as the
authors do. The LR input is padded (zeros, bottom/right) to a multiple of 4 and the output cropped.

Deviations from the authors' code (docs/training.md, "RDG"):
- the motion of frame t warps frame t-1 into t (the authors index the motion of frame t-1); the motion is resized
  to each level and divided by the size ratio (the authors resize without rescaling); warping samples at pixel
  centres (``base.backward_warp``), zero outside the image;
- LR jitter (``model.jitter``, default on): the current frame's jitter enters the shallow conv as 2 constant
  channels (18 C extra parameters: 648 for RDG, 288 for RDG-s) and the jitter difference j_t - j_(t-1) is added
  to the motion of the warp, as ``base.history_offsets`` does;
- the image enters as T(radiance), not 8-bit PNG values; with the option ``demod`` it is T(L_D), the demodulated
  irradiance, and the output is remodulated with HR F_beta and emission (``SRModel.remodulate``), which makes the
  network read those two HR buffers;
- the option ``gbuffers`` (default all of normal, brdf, depth, motion) lists the G-buffers read; a removed one is
  fed as zeros (the layers stay, as in the paper's ablations, whose parameter counts do not change);
- the option ``residual`` (with ``demod``; default off): the head's output is added to T(demod-bilinear's upsampling
  of L_D) (``SRModel.demod_base``), so the network learns a correction of ``demod-bilinear``; ``zero_init_head``
  starts the head at 0, so a fresh network is exactly that baseline (docs/models/rdg.md, "Base").

Recurrent interface (``training.recurrent``): ``step(batch, state, reset=None) -> (SR, state)`` on the last frame of
``batch``; ``forward(batch)`` runs every frame of the batch from a reset state and returns the last SR.
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from training.models.base import SRModel, backward_warp, current, depth_features, zero_init
from training.models.options import RDG_GBUFFERS as GBUFFERS  # the G-buffers RDG can read
from training.transforms import forward_transform, inverse_transform

HEADS = 4
LEVELS = 3  # decoder levels = hidden states: 1/4, 1/2, 1 of the (padded) LR size
PAD = 4


class CycleFC(nn.Module):
    """Deformable sampling with the constant offsets of CycleMLP and a 1x1 kernel: channel i shifted by
    ((i + k // 2) mod k) - k // 2 pixels along ``axis`` ('h' for 1 x k: along the width; 'v' for k x 1: along the
    height), zeros outside, then a 1x1 convolution."""

    def __init__(self, channels: int, k: int, axis: str):
        super().__init__()
        self.k = k
        self.axis = axis
        self.weight = nn.Parameter(torch.empty(channels, channels, 1, 1))
        self.bias = nn.Parameter(torch.empty(channels))
        nn.init.kaiming_uniform_(self.weight, a=5 ** 0.5)
        bound = 1 / channels ** 0.5
        nn.init.uniform_(self.bias, -bound, bound)
        shifts = [(i + k // 2) % k - k // 2 for i in range(channels)]
        order = sorted(range(channels), key=lambda i: (shifts[i], i))
        self.groups = []  # (shift, first, last) over the channels sorted by shift
        for i, c in enumerate(order):
            if not self.groups or self.groups[-1][0] != shifts[c]:
                self.groups.append((shifts[c], i, i + 1))
            else:
                self.groups[-1] = (shifts[c], self.groups[-1][1], i + 1)
        self.register_buffer("order", torch.tensor(order, dtype=torch.long), persistent=False)
        self.shifts = shifts

    def shift(self, x: torch.Tensor) -> torch.Tensor:
        """The channels sorted by shift (``order``), each sampled at p + shift (0 beyond the border)."""
        r = self.k // 2
        h, w = x.shape[-2:]
        x = x.index_select(1, self.order)
        pad = (r, r, 0, 0) if self.axis == "h" else (0, 0, r, r)
        x = F.pad(x, pad)
        parts = []
        for s, a, b in self.groups:
            if self.axis == "h":
                parts.append(x[:, a:b, :, r + s: r + s + w])
            else:
                parts.append(x[:, a:b, r + s: r + s + h, :])
        return torch.cat(parts, dim=1)

    def forward(self, x):
        return F.conv2d(self.shift(x), self.weight.index_select(1, self.order), self.bias)


class DFM(nn.Module):
    """Dynamic feature modulator (module doc)."""

    def __init__(self, dim: int):
        super().__init__()
        self.proj_in = nn.Sequential(nn.Conv2d(dim, 2 * dim, 3, padding=1, groups=dim), nn.Conv2d(2 * dim, 2 * dim, 1))
        self.cycle_h = CycleFC(dim, 7, "h")
        self.cycle_v = CycleFC(dim, 7, "v")
        self.merge = nn.Conv2d(2 * dim, dim, 1)
        self.proj_out = nn.Conv2d(dim, dim, 1)

    def forward(self, x):
        g, c = self.proj_in(x).chunk(2, dim=1)
        c = self.cycle_v(self.cycle_h(c))
        return self.proj_out(F.gelu(g) * self.merge(torch.cat([x, c], dim=1)))


class CCM(nn.Module):
    """3x3 conv dim -> 2 dim, GELU, 1x1 conv back."""

    def __init__(self, dim: int):
        super().__init__()
        self.fn = nn.Sequential(nn.Conv2d(dim, 2 * dim, 3, padding=1), nn.GELU(), nn.Conv2d(2 * dim, dim, 1))

    def forward(self, x):
        return self.fn(x)


class EncodeLayer(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.dfm = DFM(dim)
        self.ccm = CCM(dim)

    def forward(self, x):
        x = self.dfm(x) + x
        return self.ccm(x) + x


class HFB(nn.Module):
    """High-frequency feature booster: cross-gating of the features and the [normal, BRDF] G-buffers."""

    def __init__(self, dim: int, g_dim: int = 6):
        super().__init__()
        self.conv_g = nn.Conv2d(g_dim, dim, 3, padding=1)
        self.conv_x = nn.Conv2d(dim, dim, 3, padding=1)
        self.proj_out = nn.Conv2d(2 * dim, dim, 1)

    def forward(self, x, g):
        a, b = self.conv_x(x), self.conv_g(g)
        return self.proj_out(torch.cat([a * F.gelu(b), b * F.gelu(a)], dim=1))


class CTR(nn.Module):
    """Cross-frame temporal refiner: channel attention of the current features (Q) over the warped previous hidden
    state (K, V), fused with Q2 and depth."""

    def __init__(self, dim: int, heads: int = HEADS):
        super().__init__()
        hidden = 2 * dim
        self.heads = heads
        self.to_q = nn.Sequential(nn.Conv2d(dim, hidden, 1), nn.Conv2d(hidden, hidden, 3, padding=1, groups=hidden))
        self.to_kv = nn.Sequential(nn.Conv2d(dim, 2 * hidden, 1),
                                   nn.Conv2d(2 * hidden, 2 * hidden, 3, padding=1, groups=2 * hidden))
        self.proj_out = nn.Conv2d(hidden + 1, dim, 1)
        # the authors' parameter, created and never read (module doc); no gradient reaches it
        self.alpha = nn.Parameter(torch.zeros(1, 1, hidden // (2 * heads), hidden // heads), requires_grad=False)

    def forward(self, x, depth, prev):
        b, _, h, w = x.shape
        q1, q2 = self.to_q(x).chunk(2, dim=1)
        k, v = self.to_kv(prev).chunk(2, dim=1)
        n = self.heads
        q1 = F.normalize(q1.reshape(b, n, -1, h * w), dim=-1)
        k = F.normalize(k.reshape(b, n, -1, h * w), dim=-1)
        v = v.reshape(b, n, -1, h * w)
        att = torch.softmax(q1 @ k.transpose(-1, -2) + 1e-7, dim=-1)  # (b, n, D/n, 2D/n): across channels
        out = (att @ v).reshape(b, -1, h, w)
        return self.proj_out(torch.cat([out, q2, depth], dim=1))


class DecodeLayer(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.hfb = HFB(dim)
        self.ctr = CTR(dim)
        self.ccm = CCM(dim)

    def forward(self, x, g, depth, prev, reset=None):
        """``prev``: the warped previous state (None at a clip's first frame: the current features stand in for
        it); ``reset`` (B,) 1 where an element starts a clip (its ``prev`` is ignored)."""
        x = self.hfb(x, g) + x
        if prev is None:
            prev = x
        elif reset is not None:
            r = reset.to(x.dtype).view(-1, 1, 1, 1)
            prev = r * x + (1 - r) * prev
        x = self.ctr(x, depth, prev) + x
        return self.ccm(x) + x


class Up(nn.Module):
    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, 3, padding=1)

    def forward(self, x):
        return self.conv(F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=False))


def resize(x: torch.Tensor, size) -> torch.Tensor:
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    return F.interpolate(x, size=size, mode="bilinear", align_corners=False)


class RDG(SRModel):
    learned = True
    recurrent = True

    NAME = "rdg"

    def __init__(self, scale: int, **keys):
        super().__init__(scale, **keys)  # keys: SRModel's; options: RDGOptions (RDGSmallOptions)
        self.history = 0
        opt = self.options
        self.demod = bool(opt.demod)
        self.gbuffers = tuple(opt.gbuffers)
        c = opt.width
        self.dim = c
        self.first = nn.Conv2d(3 + (2 if self.use_jitter else 0), c, 3, padding=1)
        self.encoders = nn.ModuleList([EncodeLayer(c), EncodeLayer(2 * c)])
        self.downs = nn.ModuleList([nn.Conv2d(c, 2 * c, 3, stride=2, padding=1),
                                    nn.Conv2d(2 * c, 3 * c, 3, stride=2, padding=1)])
        self.middle = EncodeLayer(3 * c)
        self.middle_decoder = DecodeLayer(3 * c)
        self.ups = nn.ModuleList([Up(3 * c, 2 * c), Up(2 * c, c)])
        self.skip_alphas = nn.ParameterList([nn.Parameter(torch.zeros(1, 2 * c, 1, 1)),
                                             nn.Parameter(torch.zeros(1, c, 1, 1))])
        self.decoders = nn.ModuleList([DecodeLayer(2 * c), DecodeLayer(c)])
        self.head = nn.Conv2d(c, 3 * self.scale * self.scale, 3, padding=1)
        self.residual = bool(opt.residual)
        if opt.zero_init_head:  # a fresh network outputs its residual base: demod-bilinear (module doc)
            zero_init(self.head)

    # ------------------------------------------------------------------ inputs
    def needs(self):
        keys = ["lr/irradiance" if self.demod else "lr/radiance"]
        for name, ks in (("normal", ["lr/normal"]), ("brdf", ["lr/fbeta"]), ("depth", ["lr/depth", "depth_ref"]),
                         ("motion", ["lr/motion"])):
            if name in self.gbuffers:
                keys += ks
        if self.demod:
            keys += ["hr/fbeta_used", "hr/emission"]
        if self.residual:
            keys += [k for k in self.base_keys() if k not in keys]
        return tuple(keys) + self.jitter_keys()

    def state_shapes(self, lr_h: int, lr_w: int, batch: int = 1) -> list[tuple[int, ...]]:
        """Shapes of the state for an LR frame of lr_h x lr_w: the three hidden states (1/4, 1/2, 1 of the LR size
        padded to a multiple of 4) and the previous frame's LR jitter (B, 2)."""
        h, w = -(-lr_h // PAD) * PAD, -(-lr_w // PAD) * PAD
        c = self.dim
        return [(batch, 3 * c, h // 4, w // 4), (batch, 2 * c, h // 2, w // 2), (batch, c, h, w), (batch, 2)]

    def _inputs(self, batch):
        key = "lr/irradiance" if self.demod else "lr/radiance"
        img = forward_transform(current(batch, key), self.transform)
        b, _, h, w = img.shape

        def zeros(c):
            return torch.zeros(b, c, h, w, dtype=img.dtype, device=img.device)
        normal = current(batch, "lr/normal").to(img.dtype) if "normal" in self.gbuffers else zeros(3)
        brdf = current(batch, "lr/fbeta").to(img.dtype) if "brdf" in self.gbuffers else zeros(3)
        depth = depth_features(batch, "lr", 0, self.depth_norm).to(img.dtype) if "depth" in self.gbuffers \
            else zeros(1)
        motion = current(batch, "lr/motion").to(img.dtype) if "motion" in self.gbuffers else zeros(2)
        j = self.frame_jitter(batch)
        j = torch.zeros(b, 2, dtype=img.dtype, device=img.device) if j is None else j.to(img.dtype)
        return img, torch.cat([normal, brdf], dim=1), depth, motion, j

    # ------------------------------------------------------------------ forward
    def step(self, batch: dict, state: list[torch.Tensor] | None = None, reset: torch.Tensor | None = None):
        """SR (B, 3, H, W) of the last frame of ``batch`` and the new state (``state_shapes``). ``state`` None: a
        clip's first frame. ``reset`` (B,) float, 1 where an element starts a clip and its ``state`` is ignored
        (the ONNX graph's explicit form of None)."""
        img, g, depth, motion, j = self._inputs(batch)
        b, _, h, w = img.shape
        x = img
        if self.use_jitter:  # the current frame's jitter as two constant channels
            x = torch.cat([x, j.view(-1, 2, 1, 1).expand(-1, -1, h, w)], dim=1)
        if state is not None and self.use_jitter and "motion" in self.gbuffers:
            # frame t-1's pixel q holds its sample at q + j_(t-1): offset = m + j_t - j_(t-1) (base.history_offsets)
            motion = motion + (j - state[3].to(j.dtype)).view(-1, 2, 1, 1)
        ph, pw = (-h) % PAD, (-w) % PAD
        if ph or pw:
            x, g, depth, motion = (F.pad(t, (0, pw, 0, ph)) for t in (x, g, depth, motion))
        x = self.first(x)
        res = x
        skips = []
        for enc, down in zip(self.encoders, self.downs):
            x = enc(x)
            skips.append(x)
            x = down(x)
        x = self.middle(x)
        new_state = []
        for level, dec in enumerate([self.middle_decoder, *self.decoders]):
            if level:
                x = self.ups[level - 1](x) + self.skip_alphas[level - 1] * skips[-level]
            size = tuple(x.shape[-2:])
            prev = None
            if state is not None:  # motion in pixels of this level: resized and divided by the size ratio
                ratio = 2 ** (LEVELS - 1 - level)
                prev, _ = backward_warp(state[level].to(x.dtype), resize(motion, size) / ratio)
            x = dec(x, resize(g, size), resize(depth, size), prev, reset if state is not None else None)
            new_state.append(x)
        x = x + res
        y = F.pixel_shuffle(self.head(x[:, :, :h, :w]), self.scale)
        if self.residual:  # a correction of T(demod-bilinear's upsampled L_D); not in the paper (module doc)
            y = y + self.demod_base(batch, self.frame_jitter(batch)).to(y.dtype)
        out = inverse_transform(y.float(), self.transform)
        if self.demod:
            out = self.remodulate(out, batch)
        return out, new_state + [j]

    def forward(self, batch):
        """Every frame of the batch in order from a reset state; the SR of the last one."""
        from training.models.window import frame_slice
        t = batch["lr/irradiance" if self.demod else "lr/radiance"].shape[1]
        state, sr = None, None
        for i in range(t):
            sr, state = self.step(frame_slice(batch, i), state)
        return sr


class RDGSmall(RDG):
    """RDG at width 16 (``RDGSmallOptions``)."""

    NAME = "rdg-s"

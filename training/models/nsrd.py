"""``nsrd``: NSRD, neural super-resolution with radiance demodulation (Li et al., CVPR 2024), a frame-recurrent
network on the demodulated LR irradiance, written from the supplement (Figure 4, Table 2) and the layer sizes of the
authors' public code (``Riga2/NSRD``). Sizes below at scale s; LR frames h x w.

Inputs of frame t (LR): x_t = [T(L_D), normal, depth] (7 channels; T = ``model.input_transform``, log1p by default;
depth normalised by ``model.depth_norm``), its motion and forward motion (``motion_next``), its jitter; HR F_beta
and emission for the output. The state (``state_shapes``) carries what the next frame needs: the ConvLSTM's hidden
and cell (64 channels), the HR output T(L_D^HR) of frame t, x_t and x_(t-1), the motion and motion_next of frame t,
its disocclusion mask, the jitters of frames t and t-1, and whether a previous frame exists.

- Current frame: 3x3 conv 7 (+2 jitter channels, below) -> 32.
- Previous frames t-1, t-2: x_(t-k) warped to frame t at LR (``base.history_offsets``: motion accumulated along the
  chain, plus the jitter difference) with its disocclusion mask appended (8 channels), through one gated conv
  shared by both frames: LeakyReLU_0.2(conv 8 -> 32) * sigmoid(conv 8 -> 32), then BatchNorm (the authors').
- Mask of frame t-1: NSRD's dual motion vectors, the torch twin of ``gbuffer_export.disocclusion.from_motion``
  (1 where |motion_t(p) + motion_next_(t-1)(q)| > 0.1 px or q leaves the image); of frame t-2: that mask or frame
  t-1's own mask warped to frame t (a surface is usable in t-2 only if it was visible in t-1 and t-2). At a clip's
  first frame both masks are 1 and the previous frames are the current one.
- Previous output: T(L_D^HR) of frame t-1 warped at HR with the LR motion upsampled at the jittered sample
  positions and multiplied by s (HR frames are not jittered), pixel-unshuffled (3 s^2 channels), 3x3 conv -> 32.
- ConvLSTM: gates = 3x3 conv [current, prev 1, prev 2, output features (128), hidden (64)] 192 -> 256, split
  into input, forget, output and cell gates.
- U-Net on the hidden state (64 channels, RCAB reduction 16): 3 RCAB | max-pool | 2 RCAB | max-pool | 3 RCAB |
  bilinear x2, concat skip, 3x3 conv 128 -> 64, 2 RCAB | bilinear x2, concat skip, 3x3 conv 128 -> 64, 3 RCAB. The
  LR input of the U-Net is padded (zeros, bottom/right) to a multiple of 4 and cropped after it.
- Head: 3x3 conv 64 -> 32, 3x3 conv 32 -> 3 s^2, pixel shuffle: T(L_D^HR), then T^-1 and remodulation with HR
  F_beta and emission through the ground truth's pixel filter (``SRModel.remodulate``, as FuseSR).

Parameters at 4x without jitter: 1,610,852 = the authors' code (their Table 2's 1610.79 K omits the BatchNorm's 64);
the jitter adds 2 x 9 x 32 = 576. Deviations from the authors' code: docs/models/nsrd.md.

Deviation (``[model.nsrd]`` ``residual``, default off = the authors' head): the head's output is added to
T(demod-bilinear's upsampling of L_D) (``SRModel.upsample_input``: bilinear by class at the jittered positions), so
the network learns a correction of ``demod-bilinear``; ``zero_init_head`` starts the last conv at 0, so a fresh
network is exactly that baseline. The state's previous output is then the sum.

Recurrent interface (``training.recurrent``): ``step(batch, state, reset=None) -> (SR, state)`` on the last frame of
``batch``; ``forward(batch)`` runs every frame of the batch from a reset state and returns the last SR.
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from training.models.base import SRModel, backward_warp, current, depth_features, history_offsets, zero_init
from training.models.resample import upsample
from training.transforms import forward_transform, inverse_transform

FEATS = 32       # output channels of the input convolutions (current, previous frames, previous output)
HIDDEN = 64      # ConvLSTM hidden state and U-Net width
PREVIOUS = 2     # previous LR frames
IN_CH = 7        # T(L_D) 3, normal 3, depth 1
REDUCTION = 16   # RCAB channel attention
LEAK = 0.2       # gated conv's LeakyReLU slope
PAD = 4          # the U-Net pools twice
TOL_PX = 0.1     # dual-motion-vector tolerance, LR pixels (= gbuffer_export.disocclusion.TOL_PX)


def conv(cin: int, cout: int, k: int = 3) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, k, padding=k // 2)


class GatedConv(nn.Module):
    """LeakyReLU(conv(x)) * sigmoid(conv_gate(x)), then BatchNorm."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.feature = conv(cin, cout)
        self.gate = conv(cin, cout)
        self.norm = nn.BatchNorm2d(cout)

    def forward(self, x):
        return self.norm(F.leaky_relu(self.feature(x), LEAK) * torch.sigmoid(self.gate(x)))


class RCAB(nn.Module):
    """Residual channel attention block: x + CA(conv(relu(conv(x)))), CA = global average, 1x1 C -> C/r, ReLU,
    1x1 C/r -> C, sigmoid, scaling the channels."""

    def __init__(self, c: int, reduction: int = REDUCTION):
        super().__init__()
        self.body = nn.Sequential(conv(c, c), nn.ReLU(inplace=True), conv(c, c))
        self.attention = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Conv2d(c, c // reduction, 1), nn.ReLU(inplace=True),
                                       nn.Conv2d(c // reduction, c, 1), nn.Sigmoid())

    def forward(self, x):
        y = self.body(x)
        return x + y * self.attention(y)


def rcabs(n: int, c: int = HIDDEN) -> nn.Sequential:
    return nn.Sequential(*[RCAB(c) for _ in range(n)])


class ConvLSTM(nn.Module):
    """One ConvLSTM cell: gates = 3x3 conv([x, h]) split into input, forget, output, cell."""

    def __init__(self, cin: int, hidden: int = HIDDEN):
        super().__init__()
        self.gates = conv(cin + hidden, 4 * hidden)

    def forward(self, x, h, c):
        i, f, o, g = self.gates(torch.cat([x, h], dim=1)).chunk(4, dim=1)
        c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
        return torch.sigmoid(o) * torch.tanh(c), c


class UNet(nn.Module):
    """RCAB U-Net: 3 | pool | 2 | pool | 3 | up, conv 128 -> 64, 2 | up, conv 128 -> 64, 3."""

    def __init__(self, c: int = HIDDEN):
        super().__init__()
        self.enc1, self.enc2, self.center = rcabs(3, c), rcabs(2, c), rcabs(3, c)
        self.dec2 = nn.Sequential(conv(2 * c, c), rcabs(2, c))
        self.dec1 = nn.Sequential(conv(2 * c, c), rcabs(3, c))

    def forward(self, x):
        e1 = self.enc1(x)
        e2 = self.enc2(F.max_pool2d(e1, 2))
        y = self.center(F.max_pool2d(e2, 2))
        y = self.dec2(torch.cat([F.interpolate(y, scale_factor=2.0, mode="bilinear", align_corners=False), e2], 1))
        return self.dec1(torch.cat([F.interpolate(y, scale_factor=2.0, mode="bilinear", align_corners=False), e1], 1))


def disocclusion(motion: torch.Tensor, motion_next_prev: torch.Tensor, offset: torch.Tensor,
                 tol: float = TOL_PX) -> torch.Tensor:
    """(B, 1, h, w) 1 where frame t's pixel shows a surface frame t-1 did not see: |motion(p) + motion_next_(t-1)
    sampled at p + offset| > tol, or the sample leaves the image. The torch twin of
    ``gbuffer_export.disocclusion.from_motion`` (``offset`` = motion + jitter_t - jitter_(t-1))."""
    fwd, valid = backward_warp(motion_next_prev, offset)
    err = torch.linalg.vector_norm(motion + fwd, dim=1, keepdim=True)
    return 1.0 - valid * (err <= tol).to(valid.dtype)


class NSRD(SRModel):
    learned = True
    recurrent = True
    demod = True

    NAME = "nsrd"

    def __init__(self, scale: int, **keys):
        super().__init__(scale, **keys)  # keys: SRModel's; options: NSRDOptions
        self.history = 0  # previous frames come from the state, not from the batch
        s = self.scale
        self.current_conv = conv(IN_CH + (2 if self.use_jitter else 0), FEATS)
        self.previous_conv = GatedConv(IN_CH + 1, FEATS)
        self.output_conv = conv(3 * s * s, FEATS)
        self.lstm = ConvLSTM(FEATS * (PREVIOUS + 2), HIDDEN)
        self.unet = UNet(HIDDEN)
        self.head = nn.Sequential(conv(HIDDEN, FEATS), conv(FEATS, 3 * s * s))
        opt = self.options
        self.residual = bool(opt.residual)
        if opt.zero_init_head:  # a fresh network outputs its residual base: demod-bilinear (module doc)
            zero_init(self.head[-1])

    def needs(self):
        keys = ("lr/irradiance", "lr/normal", "lr/depth", "depth_ref", "lr/motion", "lr/motion_next",
                "hr/fbeta_used", "hr/emission") + (self.base_keys() if self.residual else ())
        return tuple(dict.fromkeys(keys)) + self.jitter_keys()

    def state_shapes(self, lr_h: int, lr_w: int, batch: int = 1) -> list[tuple[int, ...]]:
        """Shapes of the state for an LR frame of lr_h x lr_w (module doc): hidden, cell (padded to a multiple of
        4), HR output, x_t, x_(t-1), motion, motion_next, mask, jitter of t and t-1, has-previous flag."""
        ph, pw = (lr_h + PAD - 1) // PAD * PAD, (lr_w + PAD - 1) // PAD * PAD
        s = self.scale
        lr = lambda c: (batch, c, lr_h, lr_w)  # noqa: E731
        return [(batch, HIDDEN, ph, pw), (batch, HIDDEN, ph, pw), (batch, 3, s * lr_h, s * lr_w), lr(IN_CH),
                lr(IN_CH), lr(2), lr(2), lr(1), (batch, 2), (batch, 2), (batch, 1)]

    def _features(self, batch) -> torch.Tensor:
        img = forward_transform(current(batch, "lr/irradiance"), self.transform)
        depth = depth_features(batch, "lr", 0, self.depth_norm).to(img.dtype)
        return torch.cat([img, current(batch, "lr/normal").to(img.dtype), depth], dim=1)

    def _fresh_state(self, x, j) -> list[torch.Tensor]:
        """The state standing in for a clip's start: no history (the previous frames are the current one, fully
        disoccluded), zero ConvLSTM state and previous output."""
        b, _, h, w = x.shape
        ph, pw = (h + PAD - 1) // PAD * PAD, (w + PAD - 1) // PAD * PAD  # (ONNX integer Div truncates)
        z = lambda *shape: torch.zeros(*shape, dtype=x.dtype, device=x.device)  # noqa: E731
        s = self.scale
        return [z(b, HIDDEN, ph, pw), z(b, HIDDEN, ph, pw), z(b, 3, s * h, s * w), x, x, z(b, 2, h, w),
                z(b, 2, h, w), torch.ones_like(x[:, :1]), j, j, z(b, 1)]

    def step(self, batch: dict, state: list[torch.Tensor] | None = None, reset: torch.Tensor | None = None):
        """SR (B, 3, H, W) of the last frame of ``batch`` and the new state (``state_shapes``). ``state`` None: a
        clip's first frame. ``reset`` (B,) float, 1 where an element starts a clip and its ``state`` is ignored
        (the ONNX graph's explicit form of None)."""
        x = self._features(batch)
        b, _, h, w = x.shape
        motion = current(batch, "lr/motion").to(x.dtype)
        motion_next = current(batch, "lr/motion_next").to(x.dtype)
        jt = self.frame_jitter(batch)
        j = torch.zeros(b, 2, dtype=x.dtype, device=x.device) if jt is None else jt.to(x.dtype)
        fresh = self._fresh_state(x, j)
        if state is None:
            state = fresh
        else:
            state = [t.to(x.dtype) for t in state]
            if reset is not None:
                r = reset.to(x.dtype)
                state = [r.view(-1, *([1] * (f.dim() - 1))) * f + (1 - r.view(-1, *([1] * (f.dim() - 1)))) * t
                         for f, t in zip(fresh, state)]
        hid, cell, out_prev, x1, x2, m1, mn1, mask1_prev, j1, j2, seen = state

        # offsets to frames t-1 and t-2 through the shared history machinery (a 3-frame view of the carried data)
        chain = {"lr/motion": torch.stack([m1, m1, motion], dim=1),
                 "lr_jitter": torch.stack([j2, j1, j], dim=1)}
        off1, off2 = history_offsets(chain, PREVIOUS, self.use_jitter)
        new_mask = 1.0 - seen.view(-1, 1, 1, 1) * (1.0 - disocclusion(motion, mn1, off1))
        carried, _ = backward_warp(mask1_prev, off1)
        masks = [new_mask, torch.maximum(new_mask, carried)]
        prev = []
        for xk, off, mk in zip((x1, x2), (off1, off2), masks):
            warped, _ = backward_warp(xk, off)
            prev.append(self.previous_conv(torch.cat([warped, mk], dim=1)))

        cur_in = x if jt is None else torch.cat([x, j.view(-1, 2, 1, 1).expand(-1, -1, h, w)], dim=1)
        hr_motion = upsample(motion, self.scale, "bilinear", jt) * self.scale  # LR px -> HR px
        out_warped, _ = backward_warp(out_prev, hr_motion)
        feats = torch.cat([self.current_conv(cur_in), *prev,
                           self.output_conv(F.pixel_unshuffle(out_warped, self.scale))], dim=1)
        feats = F.pad(feats, (0, (-w) % PAD, 0, (-h) % PAD))  # always (a no-op at multiples of 4): ONNX keeps the Pad
        hid, cell = self.lstm(feats, hid, cell)
        y = F.pixel_shuffle(self.head(self.unet(hid)[:, :, :h, :w]), self.scale)
        if self.residual:  # a correction of T(demod-bilinear's upsampled L_D); not in the paper (module doc)
            y = y + self.demod_base(batch, jt).to(y.dtype)
        out = self.remodulate(inverse_transform(y.float(), self.transform), batch)
        new_state = [hid, cell, y, x, x1, motion, motion_next, new_mask, j, j1, torch.ones_like(seen)]
        return out, new_state

    def forward(self, batch):
        """Every LR frame of the batch in order from a reset state; the SR of the last one (HR keys may hold the
        current frame only: ``frame_slice`` aligns them at the end)."""
        from training.models.window import frame_slice
        state, sr = None, None
        for i in range(batch["lr/irradiance"].shape[1]):
            sr, state = self.step(frame_slice(batch, i), state)
        return sr

"""``fourier-sr``: arbitrary-scale super-resolution with high-frequency Fourier mapping (Zhang et al., "Deep
Fourier-based Arbitrary-scale Super-resolution for Real-time Rendering", SIGGRAPH 2024), written from the paper and
the layer sizes of the authors' public code (``iamxym/Deep-Fourier-based-Arbitrary-scale-Super-resolution-for-
Real-time-Rendering``, ``final_net.py``). One network serves every scale s > 0, integer or not: the HR size is the
HR G-buffers' size, s enters the sub-pixel geometry and the phase. docs/models/fourier_sr.md has the derivation of
every size and each deviation.

Inputs of frame t (HR size H x W = s h x s w; "half HR" = ceil(H/2) x ceil(W/2), the grid the network works on):

- LR: the demodulated irradiance L_D (``lr/irradiance``) as T(L_D), T = ``model.input_transform`` (log1p); depth
  (normalised by ``model.depth_norm``), normal and albedo, only for the spatial mask.
- HR: depth, normal, albedo, the spatial mask Phi_spat (Eq. 3-6: |D - Up(d)| > 0.01, mean |A - Up(a)| > 0.1,
  N . normalise(Up(n)) < 0.9; thresholds in ``FourierSROptions``); F_used and emission for the remodulation; the
  HR motion to warp the state.
- State (recurrent, the paper's Fig. 3): the previous frame's output T(L_D^HR) (B, 3, H, W) and its HR G-buffers
  [depth, normal, albedo] (B, 7, H, W).

Network (channel counts from the authors' code; 531,883 parameters at any scale):

- LR extractor at LR: 3x3 convs 3 -> 32 -> 48 -> 48 -> 64, ReLU after each; split into the amplitude features
  (32) and the low-frequency features (32, bilinearly resampled to half HR at the jittered LR sample positions).
- HR G-buffer extractor at half HR: [depth 1, normal 3, albedo 3, Phi_spat 1] space-to-depth 2 (32 channels),
  3x3 conv to 64 + ReLU, then three times [double residual conv (x + ReLU(conv(ReLU(conv(x))))), dilated 3x3 conv
  (dilation 2) + ReLU] with the last dilated conv before the last double residual conv; split into the frequency
  features (32) and the low-frequency features (32).
- Temporal branch at half HR: the previous output and G-buffers warped to frame t with the HR motion; the soft
  temporal masks (Eq. 7-10) |D_t - W(D_t-1)|, (1 - N_t . W(N_t-1)) / 2 (clipped at 0), |A_t - W(A_t-1)|
  (5 channels, 1 where the warp leaves the image) and the warped output (3): 8 channels, space-to-depth 2, three
  gated 3x3 convs (conv x sigmoid(conv to 1 channel), the LWG layer) 32 -> 32 -> 32 -> 16, ReLU after each. At a
  clip's first frame the masks are 0 and the warped output is the bilinear upsampling of T(L_D^LR) (the authors').
- HFFM (Eq. 2) at half HR: amplitude = 3x3 conv (32 -> 64) of the amplitude features read at the nearest LR
  sample; frequency = 3x3 conv (32 -> 64) of the frequency features, as 32 2-vectors dotted with the sub-pixel
  offset delta = 2 (x - x*) (LR pixels; x the half-HR pixel centre, x* the nearest LR sample, both where they were
  sampled: the LR jitter moves x*); phase P = w / s (32 weights, no bias; the authors' 1x1 conv of 1/s);
  [cos(pi (F . delta + P)), sin(...)] (64) times the amplitude, then a 1x1 MLP 64-64-64-64-12 (ReLU) and a 3x3 conv
  12 -> 12.
- Low-frequency branch: 3x3 convs [LR 32, temporal 16, HR 32] = 80 -> 64 -> 48 -> 12, ReLU after each.
- Depth-to-space 2 of (high + low) (12 -> 3 channels at HR), 3x3 conv 3 -> 3, crop to H x W: T(L_D^HR).
- SR = K * (T^-1(.) F_used^HR + E^HR) (``SRModel.remodulate``: point-sampled HR G-buffers, the ground truth's
  pixel filter K). The state keeps T(L_D^HR), never the remodulated radiance.

Deviation (``[model.fourier-sr]`` ``residual``, default off = the paper): T(L_D^HR) is the network's output plus
T(demod-bilinear's upsampling of L_D) at the clip's scale (``SRModel.demod_base``, any scale), so the network learns a
correction of ``demod-bilinear``; the state keeps the sum. ``zero_init_head`` starts the last 3x3 conv at 0, so a
fresh network is exactly that baseline (docs/models/fourier_sr.md, "Base").

Recurrent interface (``training.recurrent``): ``step(batch, state, reset=None) -> (SR, state)`` on the last frame of
``batch``; ``forward(batch)`` runs every frame of the batch from a reset state and returns the last SR. The scale is
``batch["scale"]`` (B,) when the batch has it, else the HR / LR width ratio.
"""
from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F

from training.models.options import FourierSROptions
from training.models.base import SRModel, backward_warp, batch_factor, conv, current, depth_features, zero_init
from training.transforms import forward_transform, inverse_transform

LR_CHANNELS = (32, 48, 48, 64)   # LR extractor widths after the 3-channel input
HR_WIDTH = 64                    # HR G-buffer extractor width; split 32 frequency + 32 low-frequency
TEMPORAL_CHANNELS = (32, 32, 16)  # gated convs of the temporal branch
FUSION_CHANNELS = (64, 48)       # low-frequency branch, then 12 = 3 x 2 x 2
MLP_WIDTH = 64                   # HFFM: C in Eq. 2
GBUFFER_CHANNELS = 7             # depth 1, normal 3, albedo 3


def lr_positions(n_out: int, pitch: int, scale: torch.Tensor, jit: torch.Tensor) -> torch.Tensor:
    """(B, n_out) positions on the LR sampling grid (LR pixels; LR pixel i spans [i, i + 1)) of output samples
    whose centres lie at ``pitch`` (k + 0.5) HR pixels, k < n_out: (pitch (k + 0.5) / s) - jitter, because LR
    pixel i holds the sample taken at i + 0.5 + jitter. ``scale`` (B,), ``jit`` (B,) of one axis."""
    k = torch.arange(n_out, device=scale.device, dtype=scale.dtype)
    return (pitch * (k.view(1, -1) + 0.5)) / scale.view(-1, 1) - jit.view(-1, 1)


def sample_lr(x: torch.Tensor, px: torch.Tensor, py: torch.Tensor, mode: str) -> torch.Tensor:
    """``x`` (B, C, h, w) read at the LR positions px (B, W_out) x py (B, H_out) (``lr_positions``): bilinear
    (edges clamped) or nearest. Returns (B, C, H_out, W_out) float32."""
    h, w = x.shape[-2:]
    gx = 2.0 * px / w - 1.0
    gy = 2.0 * py / h - 1.0
    grid = torch.stack([gx.unsqueeze(1).expand(-1, gy.shape[1], -1),
                        gy.unsqueeze(2).expand(-1, -1, gx.shape[1])], dim=-1)
    # float32 positions and values: a bf16 grid misplaces samples by whole pixels on large images
    return F.grid_sample(x.float(), grid.float(), mode=mode, padding_mode="border", align_corners=False)


def nearest_offsets(p: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """For LR positions ``p`` (B, m) on an axis of ``n`` LR pixels: the centre of the nearest LR sample (the
    pixel containing p, clamped to the image) and the sub-pixel offset p - centre (LR pixels; in [-0.5, 0.5) inside
    the image)."""
    centre = torch.floor(p).clamp(0, n - 1) + 0.5
    return centre, p - centre


def spatial_mask(hr: torch.Tensor, up: torch.Tensor, opts: FourierSROptions) -> torch.Tensor:
    """Phi_spat (Eq. 3-6), (B, 1, H, W) in {0, 1}: 1 where the HR G-buffers ``hr`` [depth, normal, albedo]
    (B, 7, H, W) differ from the upsampled LR ones ``up`` (same layout): depth difference above ``mask_depth``,
    cosine of the normals below ``mask_normal`` (the upsampled normal renormalised), mean albedo difference above
    ``mask_albedo``."""
    d = (hr[:, :1] - up[:, :1]).abs() > opts.mask_depth
    n_up = up[:, 1:4] / up[:, 1:4].norm(dim=1, keepdim=True).clamp(min=1e-6)
    n = (hr[:, 1:4] * n_up).sum(dim=1, keepdim=True) < opts.mask_normal
    a = (hr[:, 4:7] - up[:, 4:7]).abs().mean(dim=1, keepdim=True) > opts.mask_albedo
    return (d | n | a).to(hr.dtype)


def temporal_masks(cur: torch.Tensor, warped: torch.Tensor) -> torch.Tensor:
    """Phi_temp (Eq. 7-10), (B, 5, H, W) in [0, 1]: |D_t - W(D_t-1)|, (1 - N_t . W(N_t-1)) / 2 clipped at 0,
    |A_t - W(A_t-1)| per channel, from G-buffers [depth 1, normal 3, albedo 3]."""
    d = (cur[:, :1] - warped[:, :1]).abs()
    n = (1.0 - (cur[:, 1:4] * warped[:, 1:4]).sum(dim=1, keepdim=True)).clamp(min=0.0) / 2.0
    a = (cur[:, 4:7] - warped[:, 4:7]).abs()
    return torch.cat([d, n, a], dim=1)


class DoubleResidual(nn.Module):
    """x + ReLU(conv(ReLU(conv(x)))), 3x3 convolutions."""

    def __init__(self, c: int):
        super().__init__()
        self.body = nn.Sequential(conv(c, c), nn.ReLU(inplace=True), conv(c, c), nn.ReLU(inplace=True))

    def forward(self, x):
        return x + self.body(x)


class GatedConv(nn.Module):
    """The LWG layer: 3x3 conv(x) * sigmoid(3x3 conv(x) to one channel), then ReLU."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.feature = conv(cin, cout)
        self.gate = conv(cin, 1)

    def forward(self, x):
        return F.relu(self.feature(x) * torch.sigmoid(self.gate(x)))


def plain_stack(cin: int, widths) -> nn.Sequential:
    """3x3 convs through ``widths``, ReLU after each."""
    layers = []
    for c in widths:
        layers += [conv(cin, c), nn.ReLU(inplace=True)]
        cin = c
    return nn.Sequential(*layers)


class FourierSR(SRModel):
    learned = True
    recurrent = True
    SCALES = None  # any positive scale, integer or not

    NAME = "fourier-sr"

    def __init__(self, scale, **keys):
        super().__init__(scale, **keys)  # keys: SRModel's; options: FourierSROptions (the mask thresholds)
        self.history = 0
        self.demod = True
        self.opts = self.options
        half = HR_WIDTH // 2
        self.lr_extractor = plain_stack(3, LR_CHANNELS)
        self.hr_extractor = nn.Sequential(
            conv(4 * (GBUFFER_CHANNELS + 1), HR_WIDTH), nn.ReLU(inplace=True), DoubleResidual(HR_WIDTH),
            nn.Conv2d(HR_WIDTH, HR_WIDTH, 3, padding=2, dilation=2), nn.ReLU(inplace=True), DoubleResidual(HR_WIDTH),
            nn.Conv2d(HR_WIDTH, HR_WIDTH, 3, padding=2, dilation=2), nn.ReLU(inplace=True), DoubleResidual(HR_WIDTH))
        cin = 4 * (5 + 3)
        gated = []
        for c in TEMPORAL_CHANNELS:
            gated.append(GatedConv(cin, c))
            cin = c
        self.temporal = nn.Sequential(*gated)
        self.fusion = plain_stack(LR_CHANNELS[-1] // 2 + TEMPORAL_CHANNELS[-1] + half, FUSION_CHANNELS + (12,))
        self.coef = conv(LR_CHANNELS[-1] // 2, MLP_WIDTH)
        self.freq = conv(half, MLP_WIDTH)
        # P(r): the authors' bias-free 1x1 conv of 1/s, as a vector of MLP_WIDTH / 2 weights (same init bound)
        self.phase = nn.Parameter(torch.empty(MLP_WIDTH // 2).uniform_(-1.0, 1.0))
        self.mlp = nn.Sequential(nn.Conv2d(MLP_WIDTH, MLP_WIDTH, 1), nn.ReLU(inplace=True),
                                 nn.Conv2d(MLP_WIDTH, MLP_WIDTH, 1), nn.ReLU(inplace=True),
                                 nn.Conv2d(MLP_WIDTH, MLP_WIDTH, 1), nn.ReLU(inplace=True),
                                 nn.Conv2d(MLP_WIDTH, 12, 1))
        self.hf_conv = conv(12, 12)
        self.last = conv(3, 3)
        self.residual = bool(self.opts.residual)
        if self.opts.zero_init_head:  # a fresh network outputs its residual base: demod-bilinear (module doc)
            zero_init(self.last)

    # ------------------------------------------------------------------ inputs
    def needs(self):
        keys = ["lr/irradiance", "lr/depth", "lr/normal", "lr/albedo", "depth_ref",
                "hr/depth", "hr/normal", "hr/albedo", "hr/motion", "hr/fbeta_used", "hr/emission"]
        if self.residual:
            keys += [k for k in self.base_keys() if k not in keys]
        return tuple(keys) + self.jitter_keys()

    @staticmethod
    def batch_scale(batch: dict, b: int, lr_w: int, hr_w: int, ref: torch.Tensor) -> torch.Tensor:
        """(B,) float32 scale: ``batch["scale"]`` when present, else the HR / LR width ratio (today's clips)."""
        s = batch.get("scale")
        if s is None:
            return torch.full((b,), hr_w / lr_w, dtype=torch.float32, device=ref.device)
        if not s.is_cuda and ref.is_cuda:  # a host value (one CUDA graph per frame: FrameGraph): no copy to capture
            return torch.full((b,), batch_factor(s), dtype=torch.float32, device=ref.device)
        return s.reshape(-1).to(device=ref.device, dtype=torch.float32).expand(b)

    def state_shapes(self, hr_h: int, hr_w: int, batch: int = 1) -> list[tuple[int, ...]]:
        """Shapes of the state for an HR frame of hr_h x hr_w: the previous T(L_D^HR) and its HR G-buffers."""
        return [(batch, 3, hr_h, hr_w), (batch, GBUFFER_CHANNELS, hr_h, hr_w)]

    # ------------------------------------------------------------------ parts
    def hffm(self, amp: torch.Tensor, freq_feat: torch.Tensor, qx: torch.Tensor, qy: torch.Tensor,
             scale: torch.Tensor) -> torch.Tensor:
        """Eq. 2 on the half-HR grid whose pixel centres sit at the LR positions qx (B, W2), qy (B, H2): 12
        channels (3 colours x 2 x 2 sub-pixels). The phase arguments are computed in float32 (cos/sin of
        low-precision arguments would be wrong by whole fractions of a period under bf16 autocast)."""
        h, w = amp.shape[-2:]
        cx, dx = nearest_offsets(qx, w)
        cy, dy = nearest_offsets(qy, h)
        coef = sample_lr(self.coef(amp), cx, cy, "nearest")                       # (B, 64, H2, W2)
        freq = self.freq(freq_feat).float()                                       # (B, 64, H2, W2)
        rel = torch.stack([(2.0 * dx).unsqueeze(1).expand(-1, dy.shape[1], -1),
                           (2.0 * dy).unsqueeze(2).expand(-1, -1, dx.shape[1])], dim=1)  # (B, 2, H2, W2)
        arg = (freq.unflatten(1, (-1, 2)) * rel.unsqueeze(1)).sum(dim=2)          # (B, 32, H2, W2)
        arg = arg + (self.phase.float().view(1, -1) / scale.view(-1, 1)).view(arg.shape[0], -1, 1, 1)
        fourier = torch.cat([torch.cos(math.pi * arg), torch.sin(math.pi * arg)], dim=1)
        return self.hf_conv(self.mlp(coef * fourier.to(coef.dtype)))

    # ------------------------------------------------------------------ forward
    def step(self, batch: dict, state: list[torch.Tensor] | None = None, reset: torch.Tensor | None = None):
        """SR (B, 3, H, W) of the last frame of ``batch`` and the new state (``state_shapes``). ``state`` None: a
        clip's first frame. ``reset`` (B,) float, 1 where an element starts a clip and its ``state`` is ignored
        (the ONNX graph's explicit form of None)."""
        img = forward_transform(current(batch, "lr/irradiance"), self.transform)
        b, _, h, w = img.shape
        hr_g = torch.cat([depth_features(batch, "hr", 0, self.depth_norm), current(batch, "hr/normal"),
                          current(batch, "hr/albedo")], dim=1).to(img.dtype)
        big_h, big_w = hr_g.shape[-2:]
        scale = self.batch_scale(batch, b, w, big_w, img)
        j = self.frame_jitter(batch)
        j = torch.zeros(b, 2, device=img.device) if j is None else j.float()
        # LR positions of the HR pixel centres (full HR) and of the half-HR pixel centres
        px, py = lr_positions(big_w, 1, scale, j[:, 0]), lr_positions(big_h, 1, scale, j[:, 1])
        h2, w2 = (big_h + 1) // 2, (big_w + 1) // 2
        qx, qy = lr_positions(w2, 2, scale, j[:, 0]), lr_positions(h2, 2, scale, j[:, 1])

        lr_g = torch.cat([depth_features(batch, "lr", 0, self.depth_norm), current(batch, "lr/normal"),
                          current(batch, "lr/albedo")], dim=1).to(img.dtype)
        mask = spatial_mask(hr_g, sample_lr(lr_g, px, py, "bilinear"), self.opts)

        first = torch.cat([torch.zeros_like(hr_g[:, :5]), sample_lr(img, px, py, "bilinear")], dim=1)
        if state is None:
            temp_in = first
        else:
            prev = torch.cat([state[1].to(img.dtype), state[0].to(img.dtype)], dim=1)
            warped, valid = backward_warp(prev, current(batch, "hr/motion").to(img.dtype))
            masks = temporal_masks(hr_g, warped[:, :GBUFFER_CHANNELS]) * valid + (1.0 - valid)
            temp_in = torch.cat([masks, warped[:, GBUFFER_CHANNELS:]], dim=1)
            if reset is not None:
                temp_in = torch.where(reset.view(-1, 1, 1, 1) > 0.5, first, temp_in)

        ph, pw = big_h % 2, big_w % 2
        hr_in = torch.cat([hr_g, mask], dim=1)
        if ph or pw:  # odd HR size (non-integer scales): replicate a row / column, crop at the end
            hr_in = F.pad(hr_in, (0, pw, 0, ph), mode="replicate")
            temp_in = F.pad(temp_in, (0, pw, 0, ph), mode="replicate")

        lr_feat = self.lr_extractor(img)
        amp, lr_low = torch.chunk(lr_feat, 2, dim=1)
        hr_feat = self.hr_extractor(F.pixel_unshuffle(hr_in, 2))
        freq_feat, hr_low = torch.chunk(hr_feat, 2, dim=1)
        temporal = self.temporal(F.pixel_unshuffle(temp_in, 2))
        low = self.fusion(torch.cat([sample_lr(lr_low, qx, qy, "bilinear"), temporal, hr_low], dim=1))
        high = self.hffm(amp, freq_feat, qx, qy, scale)
        y = self.last(F.pixel_shuffle(high + low, 2))[:, :, :big_h, :big_w]
        if self.residual:  # a correction of T(demod-bilinear's upsampled L_D) at this scale (module doc)
            base = self.demod_base(batch, self.frame_jitter(batch), scale=big_w / w)
            y = y + base[:, :, :big_h, :big_w].to(y.dtype)
        out = self.remodulate(inverse_transform(y.float(), self.transform), batch)
        return out, [y, hr_g]

    def forward(self, batch):
        """The frames of the batch in order from a reset state; the SR of the last one. Keys may hold different
        numbers of frames (all ending at the current one): the frames every image key has are run."""
        t = min(v.shape[1] for k, v in batch.items() if "/" in k)
        state, sr = None, None
        for i in range(t):
            back = t - 1 - i
            sub = {k: (v[:, v.shape[1] - 1 - back: v.shape[1] - back] if v.dim() >= 2 else v)
                   for k, v in batch.items()}
            sr, state = self.step(sub, state)
        return sr

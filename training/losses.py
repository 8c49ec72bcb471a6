"""Training losses (torch). All take SR and ground truth as linear radiance (B, 3, H, W) float32 and compare them in
``loss.space`` (log1p, the evaluation tonemap, or linear); SSIM and the perceptual loss always use the tonemap
(values in [0, 1]).

- pixel: L1 or Charbonnier sqrt(d^2 + eps^2) (eps >= 1e-6: smaller values give NaN gradients in fp16)
- ssim: 1 - SSIM (pytorch-msssim, 11x11 Gaussian window, data range 1)
- fft (``loss.fft``): 'ortho', mean |FFT2(a) - FFT2(b)| / sqrt(H W) (orthonormal FFT); 'rfft', the mean of
  |Re| and |Im| of RFFT2(a) - RFFT2(b) unnormalised (RDG's code)
- temporal (``loss.temporal``): 'warped', the mean over valid pixels of |(a_t - W(a_t-1)) - (b_t - W(b_t-1))|,
  W = backward warp with HR motion; 'difference', the mean of ((a_t - a_t-1) - (b_t - b_t-1))^2 without warping
  (the consistency loss of RDG's code)
- baseline (``loss.baseline_weight``): the mean of max(0, |a - b| - |j - b|), j the guided baseline ``demod-jbu``
  on the same batch in the same space: zero wherever the network is at least as close to the ground truth as the
  non-learned baseline, so it weighs only the pixels where the network loses to it (not in the papers; the worst
  case of docs/results.md is the per-clip margin over that baseline)
- perceptual: VGG-16 features from a user-supplied weights file (``training.perceptual``)
"""
from __future__ import annotations

import torch
from pytorch_msssim import ssim

from training.models.base import backward_warp
from training.transforms import loss_space, tonemap


def pixel_loss(a: torch.Tensor, b: torch.Tensor, kind: str, eps: float) -> torch.Tensor:
    d = a - b
    if kind == "l1":
        return d.abs().mean()
    return torch.sqrt(d * d + eps * eps).mean()


def ssim_loss(a_tm: torch.Tensor, b_tm: torch.Tensor) -> torch.Tensor:
    """1 - SSIM of tonemapped images (sides must be >= 11 pixels)."""
    return 1.0 - ssim(a_tm, b_tm, data_range=1.0, size_average=True)


def fft_loss(a: torch.Tensor, b: torch.Tensor, kind: str = "ortho") -> torch.Tensor:
    """'ortho': mean modulus of the orthonormal 2-D FFT difference; 'rfft': mean absolute value of the real and
    imaginary parts of the unnormalised real FFT difference (RDG's code; about sqrt(H W) times larger)."""
    if kind == "rfft":
        d = torch.fft.rfft2(a.float()) - torch.fft.rfft2(b.float())
        return torch.stack([d.real, d.imag], dim=-1).abs().mean()
    fa = torch.fft.fft2(a.float(), norm="ortho")
    fb = torch.fft.fft2(b.float(), norm="ortho")
    return (fa - fb).abs().mean()


def baseline_loss(a: torch.Tensor, b: torch.Tensor, j: torch.Tensor) -> torch.Tensor:
    """The hinge over the baseline (module doc): mean of max(0, |a - b| - |j - b|), all three in the loss space."""
    return torch.relu((a - b).abs() - (j - b).abs()).mean()


def temporal_loss(a_t, a_prev, b_t, b_prev, motion) -> torch.Tensor:
    """Temporal consistency: SR frame differences after warping should match the ground truth's."""
    wa, valid = backward_warp(a_prev, motion)
    wb, _ = backward_warp(b_prev, motion)
    diff = ((a_t - wa) - (b_t - wb)).abs() * valid
    return diff.sum() / (valid.sum() * a_t.shape[1]).clamp(min=1.0)


def difference_loss(a_t, a_prev, b_t, b_prev) -> torch.Tensor:
    """Temporal consistency without motion: SR frame differences should match the ground truth's (MSE)."""
    d = (a_t - a_prev) - (b_t - b_prev)
    return (d * d).mean()


class Criterion(torch.nn.Module):
    """The weighted sum of the configured terms. ``forward`` returns (total, {term: value})."""

    def __init__(self, cfg):
        super().__init__()
        self.cfg = cfg
        self.vgg = None
        if cfg.perceptual_weight > 0:
            from training.perceptual import VGGFeatures
            self.vgg = VGGFeatures.from_file(cfg.vgg_weights)

    def forward(self, sr, gt, sr_prev=None, gt_prev=None, motion=None, base=None):
        """``base``: the baseline's SR of the same frame (the ``baseline`` term; skipped when None)."""
        c = self.cfg
        terms: dict[str, torch.Tensor] = {}
        a, b = loss_space(sr, c.space), loss_space(gt, c.space)
        if c.pixel_weight > 0:
            terms["pixel"] = pixel_loss(a, b, c.pixel, c.charbonnier_eps)
        if c.ssim_weight > 0 or self.vgg is not None:
            a_tm, b_tm = tonemap(sr), tonemap(gt)
            if c.ssim_weight > 0:
                terms["ssim"] = ssim_loss(a_tm, b_tm)
            if self.vgg is not None:
                terms["perceptual"] = self.vgg.distance(a_tm, b_tm)
        if c.fft_weight > 0:
            terms["fft"] = fft_loss(a, b, getattr(c, "fft", "ortho"))
        if c.temporal_weight > 0 and sr_prev is not None:
            if getattr(c, "temporal", "warped") == "difference":
                terms["temporal"] = difference_loss(a, loss_space(sr_prev, c.space), b, loss_space(gt_prev, c.space))
            else:
                terms["temporal"] = temporal_loss(a, loss_space(sr_prev, c.space), b, loss_space(gt_prev, c.space),
                                                  motion)
        if c.baseline_weight > 0 and base is not None:
            terms["baseline"] = baseline_loss(a, b, loss_space(base, c.space))
        weights = {"pixel": c.pixel_weight, "ssim": c.ssim_weight, "fft": c.fft_weight,
                   "temporal": c.temporal_weight, "perceptual": c.perceptual_weight,
                   "baseline": c.baseline_weight}
        total = sum(weights[k] * v for k, v in terms.items())
        return total, terms

"""Image metrics of the evaluation (torch, on H x W x 3 float32 linear radiance given as numpy arrays).

- ``psnr``: PSNR of the tonemapped images (``transforms.tonemap``: sRGB OETF of Reinhard x / (1 + x)), peak 1.
- ``ssim``: SSIM of the tonemapped images (pytorch-msssim, Gaussian 11x11 window sigma 1.5, data range 1).
- ``psnr_hdr``: PSNR on linear values with the fixed peak ``HDR_PEAK`` = 1 (scene-linear units, no clamping).
- ``tpsnr``: PSNR (peak 1) between the tonemapped frame differences SR_t - SR_t-1 and GT_t - GT_t-1.
- ``warp_error``: mean |T(SR_t) - W(T(SR_t-1))| over pixels whose warp stays inside the image, W the backward warp
  with the clip's HR motion vectors of frame t, T the tonemap. ``warp_error_gt`` is the same for the ground truth
  (what disocclusions and shading changes alone give).
- ``delta_e_itp``: mean Delta E ITP (ITU-R BT.2124) of the linear HDR images shown with radiance 1 at
  ``ITP_WHITE_NITS`` cd/m^2 (colour-science's ICtCp, BT.2100 PQ); optional (``evaluate --delta-e-itp``).
PSNR values are capped at ``PSNR_CAP`` dB (identical images) so that JSON stays finite.

The worst case (docs/evaluation.md, "The worst case"), beside the means:

- ``worst_share``: the share of a frame's squared tonemapped error (the PSNR's) carried by its worst
  ``WORST_FRACTION`` of pixels.
- ``artifact_mask``: "artifact pixels", where the tonemapped error of the model (``pixel_error``, the largest of the
  three channels) is above ``ARTIFACT_ERROR`` while that of the baseline ``BASELINE`` is below ``ARTIFACT_BASELINE``:
  a visible error the guided non-learned upsampling does not make (the streaks of a network that fails on content).
"""
from __future__ import annotations

import math

import numpy as np
import torch
from pytorch_msssim import ssim as _ssim

from gbuffer_export.errors import BlendSRError
from training.models.base import backward_warp
from training.transforms import HDR_PEAK, tonemap

PSNR_CAP = 100.0
#: Luminance (cd/m^2) at which Delta E ITP shows linear radiance 1: the HDR reference white of ITU-R BT.2408.
ITP_WHITE_NITS = 203.0
#: The worst case: the baseline a model must not fall below, per clip and per pixel.
BASELINE = "demod-jbu"
#: The share of the squared error in this fraction of the pixels (the worst ones) is ``worst_share``.
WORST_FRACTION = 0.01
#: An artifact pixel: the model's tonemapped error above ARTIFACT_ERROR where the baseline's is below
#: ARTIFACT_BASELINE (``pixel_error``: the largest of the three channels' absolute differences, values in [0, 1]).
ARTIFACT_ERROR = 0.25
ARTIFACT_BASELINE = 0.05
TRANSFORM = "reinhard-srgb: sRGB_OETF(x / (1 + x)) per channel, x = max(linear radiance, 0); values in [0, 1]"


def _t(a: np.ndarray) -> torch.Tensor:
    """H x W x C numpy -> 1 x C x H x W float32 tensor."""
    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).permute(2, 0, 1)[None]


def psnr_from_mse(mse: float, peak: float = 1.0) -> float:
    if not math.isfinite(mse):
        return float("nan")
    if mse <= peak * peak * 10 ** (-PSNR_CAP / 10):
        return PSNR_CAP
    return 10.0 * math.log10(peak * peak / mse)


def tonemapped(a: np.ndarray) -> torch.Tensor:
    return tonemap(_t(a))


def psnr_tm(sr: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float | None:
    """PSNR of the tonemapped images, over ``mask`` (H x W bool) when given (None when the mask is empty)."""
    d = (tonemapped(sr) - tonemapped(gt)) ** 2
    if mask is not None:
        m = torch.from_numpy(mask)[None, None].expand_as(d)
        if not bool(m.any()):
            return None
        return psnr_from_mse(float(d[m].mean()))
    return psnr_from_mse(float(d.mean()))


def ssim_tm(sr: np.ndarray, gt: np.ndarray) -> float:
    a, b = tonemapped(sr), tonemapped(gt)
    if min(a.shape[-2:]) < 11:
        raise BlendSRError(f"SSIM needs images of at least 11 x 11 pixels, got {tuple(a.shape[-2:])}")
    return float(_ssim(a, b, data_range=1.0, size_average=True))


def psnr_hdr(sr: np.ndarray, gt: np.ndarray) -> float:
    return psnr_from_mse(float(np.mean((sr.astype(np.float64) - gt.astype(np.float64)) ** 2)), HDR_PEAK)


def tpsnr(sr: np.ndarray, sr_prev: np.ndarray, gt: np.ndarray, gt_prev: np.ndarray) -> float:
    ds = tonemapped(sr) - tonemapped(sr_prev)
    dg = tonemapped(gt) - tonemapped(gt_prev)
    return psnr_from_mse(float(((ds - dg) ** 2).mean()))


def warp_error(cur: np.ndarray, prev: np.ndarray, motion: np.ndarray) -> float | None:
    """Mean absolute tonemapped difference between ``cur`` and ``prev`` warped with ``motion`` (H x W x 2)."""
    warped, valid = backward_warp(tonemapped(prev), _t(motion).to(torch.float32))
    n = float(valid.sum()) * 3
    if n == 0:
        return None
    return float(((tonemapped(cur) - warped).abs() * valid).sum() / n)


def delta_e_itp(sr: np.ndarray, gt: np.ndarray) -> float:
    """Mean Delta E ITP (ITU-R BT.2124; 1 is about one just-noticeable difference) of two H x W x 3 linear
    Linear Rec.709 images: radiance 1 is shown at ``ITP_WHITE_NITS`` cd/m^2, converted to BT.2020 and clipped to
    the PQ range [0, 10000] cd/m^2, then ICtCp (BT.2100 PQ) and Delta E ITP per pixel, all with colour-science."""
    from gbuffer_export.colour_spaces import TRAINING_SPACE, colour_module, conversion_matrix
    colour = colour_module()
    m = conversion_matrix(TRAINING_SPACE, "Linear Rec.2020")

    def ictcp(a: np.ndarray) -> np.ndarray:
        nits = np.clip(ITP_WHITE_NITS * (np.asarray(a, np.float64) @ m.T), 0.0, 10000.0)
        return colour.RGB_to_ICtCp(nits, method="ITU-R BT.2100-2 PQ")

    return float(np.mean(colour.delta_E(ictcp(sr), ictcp(gt), method="ITP")))


def squared_error(sr: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """H x W squared tonemapped error, the mean over channels (its mean over pixels is ``psnr``'s MSE)."""
    return ((tonemapped(sr) - tonemapped(gt)) ** 2).mean(dim=1)[0].numpy()


def pixel_error(sr: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """H x W tonemapped error per pixel: the largest of the three channels' |T(sr) - T(gt)| (values in [0, 1])."""
    return (tonemapped(sr) - tonemapped(gt)).abs().amax(dim=1)[0].numpy()


def worst_share(sq: np.ndarray, fraction: float = WORST_FRACTION) -> float | None:
    """The share of the summed squared error ``sq`` (H x W, ``squared_error``) in its worst ``fraction`` of pixels
    (at least one pixel); None for an error-free frame."""
    flat = np.asarray(sq, np.float64).ravel()
    total = float(flat.sum())
    if total <= 0.0:
        return None
    n = max(1, int(math.ceil(fraction * flat.size)))
    return float(np.partition(flat, flat.size - n)[flat.size - n:].sum() / total)


def artifact_mask(error: np.ndarray, baseline_ok: np.ndarray) -> np.ndarray:
    """H x W bool: artifact pixels of a model with ``pixel_error`` ``error`` where ``baseline_ok`` (H x W bool) says
    the baseline's error is below ``ARTIFACT_BASELINE`` (``baseline_good``)."""
    return (error > ARTIFACT_ERROR) & baseline_ok


def baseline_good(baseline_error: np.ndarray) -> np.ndarray:
    """H x W bool: where the baseline's ``pixel_error`` is below ``ARTIFACT_BASELINE``."""
    return baseline_error < ARTIFACT_BASELINE

"""Value transforms shared by models, losses and metrics (torch).

- HDR input transform: ``log1p`` (sign-preserving log(1 + |x|)) or ``none``; models feed transformed radiance /
  irradiance to their convolutions and invert the transform on their output.
- The evaluation tonemap (one operator for every model, see docs/evaluation.md): Reinhard's global operator
  x / (1 + x) per channel on linear radiance (negative values clamped to 0), then the sRGB OETF (IEC 61966-2-1).
  Output in [0, 1], float.
- Depth normalisation: 'ratio' d / (d + ref) with ref the median finite depth of the current frame (LR level,
  scene units), 'inverse' 1 / (1 + d); background (+inf) gives 1 ('ratio') or 0 ('inverse').
"""
from __future__ import annotations

import torch
from gbuffer_export.errors import BlendSRError

#: Peak used by PSNR on linear HDR values: psnr_hdr = 10 log10(HDR_PEAK^2 / MSE) (scene-linear units).
HDR_PEAK = 1.0


def forward_transform(x: torch.Tensor, kind: str) -> torch.Tensor:
    """HDR transform applied to radiance-like inputs."""
    if kind == "log1p":
        return torch.sign(x) * torch.log(1.0 + x.abs())  # log(1 + x), not log1p: ONNX has no Log1p
    if kind == "none":
        return x
    raise BlendSRError(f"unknown input transform {kind!r}")


def inverse_transform(y: torch.Tensor, kind: str) -> torch.Tensor:
    """Inverse of ``forward_transform`` (the exponent is clamped at 80 to stay finite in float32)."""
    if kind == "log1p":
        return torch.sign(y) * (torch.exp(y.abs().clamp(max=80.0)) - 1.0)  # no Expm1 in ONNX
    if kind == "none":
        return y
    raise BlendSRError(f"unknown input transform {kind!r}")


def srgb_oetf(x: torch.Tensor) -> torch.Tensor:
    """sRGB encoding (IEC 61966-2-1) of linear values, clipped to [0, 1]. Written in torch so that it
    differentiates (finite gradient at 0) and runs on the GPU; tests compare it with colour-science's
    (``gbuffer_export.colour_spaces.srgb_encode``)."""
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp(min=0.0031308).pow(1.0 / 2.4) - 0.055)


def tonemap(x: torch.Tensor) -> torch.Tensor:
    """The evaluation tonemap: sRGB_OETF(Reinhard(max(x, 0))), Reinhard(v) = v / (1 + v); values in [0, 1].
    Its numpy reference is ``gbuffer_export.preview.tonemap``."""
    x = torch.nan_to_num(x.float(), nan=0.0, posinf=1e30).clamp(min=0.0)
    return srgb_oetf(x / (1.0 + x))


def normalize_depth(depth: torch.Tensor, ref: torch.Tensor | float, kind: str) -> torch.Tensor:
    """Depth (scene units, +inf on background) to [0, 1]. ``ref`` broadcasts against ``depth``."""
    finite = torch.isfinite(depth) & (depth > 0)
    d = torch.where(finite, depth, torch.ones_like(depth))
    if kind == "ratio":
        out = d / (d + ref)
        return torch.where(finite, out, torch.ones_like(out))
    if kind == "inverse":
        out = 1.0 / (1.0 + d)
        return torch.where(finite, out, torch.zeros_like(out))
    raise BlendSRError(f"unknown depth normalisation {kind!r}")


def loss_space(x: torch.Tensor, kind: str) -> torch.Tensor:
    """Where pixel losses compare SR and ground truth: log1p, the evaluation tonemap, or linear."""
    if kind == "log1p":
        return torch.log1p(x.clamp(min=0.0))
    if kind == "tonemap":
        return tonemap(x)
    if kind == "linear":
        return x
    raise BlendSRError(f"unknown loss space {kind!r}")

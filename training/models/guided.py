"""Joint bilateral upsampling guided by the HR geometry (torch).

Kopf et al., "Joint Bilateral Upsampling" (SIGGRAPH 2007), restricted to the bilinear footprint: an HR pixel
interpolates its 4 bilinear LR neighbours with weights

    w_i = bilinear_i * exp(-|g_HR - g_LR,i|^2 / 2) * [class_i == class_HR]

where g = [log(depth) / sigma_depth, normal / sigma_normal] (camera-space unit normal, ``docs/clip-format.md``), so
an HR pixel takes its value from the LR samples that lie on the same surface: across a silhouette between two lit
objects, or a crease between two faces, bilinear interpolation mixes the two shadings, this does not. Log depth makes
``sigma_depth`` a relative tolerance (0.1: about 10 % in depth). Where the weights sum to less than ``floor`` (no
neighbour on a similar surface) the HR pixel keeps the fallback (the class-aware bilinear value).

Written by hand: torch and kornia offer bilateral *filters* at one resolution, not the joint upsampling between two
levels with per-batch sub-pixel jitter that the LR samples here need. Coordinates follow ``base.upsample``: the HR
pixel centre at LR position u samples the LR grid at u - jitter, borders clamped.
"""
from __future__ import annotations

import torch

#: Batch keys the guides are made of, at both levels.
GUIDE_KEYS = ("lr/depth", "lr/normal", "hr/depth", "hr/normal")


def guide_features(depth: torch.Tensor, normal: torch.Tensor, sigma_depth: float,
                   sigma_normal: float) -> torch.Tensor:
    """(B, 4, H, W) scaled guide [log(depth) / sigma_depth, normal / sigma_normal] from view depth (B, 1, H, W, scene
    units) and camera-space normal (B, 3, H, W); depth clamped to [1e-4, 1e6] (background +inf and NaN -> 1e6)."""
    depth = torch.nan_to_num(depth[:, :1].float(), nan=1e6, posinf=1e6, neginf=1e-4).clamp(1e-4, 1e6)
    normal = torch.nan_to_num(normal.float())
    return torch.cat([torch.log(depth) / sigma_depth, normal / sigma_normal], dim=1)


def upsample_guided(x: torch.Tensor, lr_guide: torch.Tensor, hr_guide: torch.Tensor, scale: int,
                    fallback: torch.Tensor, jitter: torch.Tensor | None = None,
                    classes: tuple[torch.Tensor, torch.Tensor] | None = None, floor: float = 1e-4) -> torch.Tensor:
    """Joint bilateral upsampling of ``x`` (B, C, h, w) by ``scale`` (module doc).

    ``lr_guide`` (B, G, h, w) and ``hr_guide`` (B, G, H, W) are scaled guides (``guide_features``); ``fallback``
    (B, C, H, W) is used where the weights sum below ``floor``; ``jitter`` (B, 2) LR pixels as in ``base.upsample``;
    ``classes``: optional 0/1 classes that must match, (LR (B, 1, h, w), HR (B, 1, H, W)) (e.g.
    ``base.demodulated_mask``). Returns (B, C, H, W) in the dtype of ``x``."""
    b, c, h, w = x.shape
    hh, ww = h * scale, w * scale
    dt = x.dtype
    dev = x.device
    zero = torch.zeros(b, 1, device=dev, dtype=torch.float32)
    jx, jy = (zero, zero) if jitter is None else (jitter[:, :1].float(), jitter[:, 1:2].float())
    ux = (torch.arange(ww, device=dev, dtype=torch.float32) + 0.5) / scale - 0.5 - jx   # (B, W) LR index space
    uy = (torch.arange(hh, device=dev, dtype=torch.float32) + 0.5) / scale - 0.5 - jy   # (B, H)
    x0, y0 = torch.floor(ux), torch.floor(uy)
    g = lr_guide.shape[1]
    lr_class, hr_class = classes if classes is not None else (None, None)
    parts = [x.float(), lr_guide.float()] + ([lr_class.float()] if lr_class is not None else [])
    lr_all = torch.cat(parts, dim=1).flatten(2)                                          # (B, C + G (+1), h w)
    hr_g = hr_guide.float()
    num = torch.zeros(b, c, hh, ww, device=dev, dtype=torch.float32)
    den = torch.zeros(b, 1, hh, ww, device=dev, dtype=torch.float32)
    for dy in (0, 1):
        iy = (y0 + dy).clamp(0, h - 1).long()
        wy = (1.0 - (uy - (y0 + dy)).abs()).clamp(min=0.0)
        for dx in (0, 1):
            ix = (x0 + dx).clamp(0, w - 1).long()
            wx = (1.0 - (ux - (x0 + dx)).abs()).clamp(min=0.0)
            idx = (iy.view(b, hh, 1) * w + ix.view(b, 1, ww)).view(b, 1, hh * ww)
            v = torch.gather(lr_all, 2, idx.expand(-1, lr_all.shape[1], -1)).view(b, -1, hh, ww)
            d2 = (v[:, c:c + g] - hr_g).square().sum(dim=1, keepdim=True)
            wt = wy.view(b, 1, hh, 1) * wx.view(b, 1, 1, ww) * torch.exp(-0.5 * d2)
            if lr_class is not None:
                wt = wt * (v[:, c + g:] == hr_class.float()).float()
            num = num + wt * v[:, :c]
            den = den + wt
    out = torch.where(den >= floor, num / den.clamp(min=floor), fallback.float())
    return out.to(dt)


def tap_range(x: torch.Tensor, scale: int, jitter: torch.Tensor | None = None,
              classes: tuple[torch.Tensor, torch.Tensor] | None = None,
              guides: tuple[torch.Tensor, torch.Tensor] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(lo, hi) (B, C, H, W) float32: per channel, the range of ``x`` (B, C, h, w) over the 4 bilinear LR taps of
    each HR pixel (``upsample_guided``'s footprint, borders clamped) and, with ``classes``, over those of the HR
    pixel's class where their bilinear weights sum above ``hr_math.CLASS_EPS`` (there the base is a convex
    combination of them; else over all 4): every value ``upsample_guided`` and its fallbacks can return lies in it.
    With ``guides`` (LR, HR scaled guides as in ``upsample_guided``; ``residual_clamp = "lr-guided"``): over the taps
    of the pixel's class whose range weight passes ``hr_math.similar`` only, open (``hr_math.open_if_empty``) where
    none does. The reference of the fused HR stage's step 4b (``kernels.hr_stage``; the bounds of ``residual_clamp``)."""
    from training.kernels import hr_math as m
    b, c, h, w = x.shape
    hh, ww = h * scale, w * scale
    zero = torch.zeros(b, 1, device=x.device, dtype=torch.float32)
    jx, jy = (zero, zero) if jitter is None else (jitter[:, :1].float(), jitter[:, 1:2].float())
    ux = m.tap_position(torch.arange(ww, device=x.device, dtype=torch.float32), float(scale), jx)   # (B, W)
    uy = m.tap_position(torch.arange(hh, device=x.device, dtype=torch.float32), float(scale), jy)   # (B, H)
    x0, y0 = torch.floor(ux), torch.floor(uy)
    lr_class, hr_class = classes if classes is not None else (None, None)
    lr_all = torch.cat([x.float()] + ([lr_class.float()] if lr_class is not None else []) +
                       ([guides[0].float()] if guides is not None else []), dim=1).flatten(2)
    k = c + (1 if lr_class is not None else 0)  # where the guides start (an int: the ONNX trace adds to c)
    big = torch.full((b, c, hh, ww), m.F32_MAX, device=x.device)
    plo, phi, clo, chi = big, -big, big, -big
    cden = torch.zeros(b, 1, hh, ww, device=x.device)
    for dy in (0.0, 1.0):
        iy = m.tap_index(y0 + dy, h).long()
        wy = m.tap_weight(uy, y0 + dy)
        for dx in (0.0, 1.0):
            ix = m.tap_index(x0 + dx, w).long()
            wb = wy.view(b, 1, hh, 1) * m.tap_weight(ux, x0 + dx).view(b, 1, 1, ww)
            idx = (iy.view(b, hh, 1) * w + ix.view(b, 1, ww)).view(b, 1, hh * ww)
            v = torch.gather(lr_all, 2, idx.expand(-1, lr_all.shape[1], -1)).view(b, -1, hh, ww)
            plo, phi = torch.minimum(plo, v[:, :c]), torch.maximum(phi, v[:, :c])
            if lr_class is None and guides is None:
                continue
            same = v[:, c:k] == hr_class.float() if lr_class is not None else torch.ones_like(cden, dtype=torch.bool)
            if guides is not None:
                same = same & m.similar(m.similarity((v[:, k:] - guides[1].float()).square().sum(1, keepdim=True)))
            clo, chi = m.range_add(clo, chi, v[:, :c], same)
            cden = cden + torch.where(same, wb, 0.0)
    if guides is not None:
        return m.open_if_empty(clo, chi)
    if lr_class is None:
        return plo, phi
    return m.range_pick(cden, clo, plo), m.range_pick(cden, chi, phi)

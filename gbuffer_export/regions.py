"""Pixel regions of an HR frame, for breaking an error down by where it lies (pure numpy).

A super-resolution model remodulates with point-sampled HR G-buffers while the ground truth is averaged over its
pixel filter, so the models of this field err most where a pixel straddles two surfaces. ``pixel_regions`` splits a
frame into four disjoint regions from its flags and depth; each pixel gets the first that applies:

- ``silhouette``: within ``EDGE_PX`` pixels (8-neighbourhood) of a boundary between background and a surface, on
  either side of it (object outlines against the sky, the horizon);
- ``depth_edge``: a surface pixel within ``EDGE_PX`` pixels of a depth discontinuity (one object in front of
  another): the second difference of inverse depth along x or y, centred on the pixel, exceeds ``DEPTH_EDGE_RATIO``
  times its inverse depth. Inverse depth is affine in the image on any plane, so a plane seen at a grazing angle
  has no depth edge however fast its depth grows;
- ``background``: the other background pixels (``Flag.BACKGROUND``);
- ``interior``: the other surface pixels.

``material_regions`` splits the same frame by what its G-buffers can describe: a rough opaque surface is its
G-buffers (albedo, normal, roughness, metallic, specular) times the light arriving there, which varies slowly; a
glossy, coated or transmissive surface also shows a picture of its surroundings (a reflection, what lies behind the
glass) that no G-buffer holds, so an upscaler must invent its HR detail from the LR radiance alone. Each pixel gets
the first that applies:

- ``background``: no surface (``Flag.BACKGROUND``);
- ``transmission``: a transmissive material (``Flag.TRANSMISSION``): refraction shows what lies behind;
- ``coated``: a coat or thin-film layer (``Flag.COAT``, ``Flag.THIN_FILM``): a smooth reflective layer whose
  roughness no G-buffer carries (``roughness`` is the base layer's);
- ``unknown``: a surface whose roughness is not known: no material (``Flag.NO_MATERIAL``), or a shader other than
  one Principled BSDF (``Flag.NON_PRINCIPLED``) whose roughness reads 0: the roughness buffer is written only for a
  Principled, Diffuse (1) or Glossy BSDF, so a glass, mix or emission shader reads 0 (and so does a Glossy BSDF of
  roughness 0);
- ``glossy``: base roughness below ``GLOSSY_ROUGHNESS``: GGX alpha = r^2 < 0.0625, a reflection lobe narrow
  enough that the reflected scene keeps detail at the HR pixel scale;
- ``rough``: the other surfaces (a NaN roughness counts as rough).

``background`` is every background pixel here, while in ``pixel_regions`` the silhouette band takes its edge.

``training.evaluate`` scores every region (``regions`` and ``materials`` in the JSON of ``blendsr evaluate``).
"""
from __future__ import annotations

import numpy as np

from .conventions import Flag

REGIONS = ("silhouette", "depth_edge", "background", "interior")
EDGE_PX = 1
DEPTH_EDGE_RATIO = 0.05
MATERIALS = ("background", "transmission", "coated", "unknown", "glossy", "rough")
GLOSSY_ROUGHNESS = 0.25


def _neighbourhood(a: np.ndarray, reduce, fill) -> np.ndarray:
    """``reduce`` (np.maximum or np.minimum) of ``a`` (H x W) over each pixel's 3 x 3 neighbourhood; outside the
    image counts as ``fill``."""
    p = np.pad(a, 1, constant_values=fill)
    h, w = a.shape
    out = a.copy()
    for dy in range(3):
        for dx in range(3):
            out = reduce(out, p[dy:dy + h, dx:dx + w])
    return out


def dilate(mask: np.ndarray, px: int = EDGE_PX) -> np.ndarray:
    """``mask`` (H x W bool) grown by ``px`` pixels in the 8-neighbourhood."""
    out = np.asarray(mask, bool)
    for _ in range(px):
        out = _neighbourhood(out, np.maximum, False)
    return out


def pixel_regions(flags: np.ndarray, depth: np.ndarray) -> dict[str, np.ndarray]:
    """The regions of one frame: {name: H x W bool} for every name of ``REGIONS``, disjoint and covering the frame.
    ``flags``: H x W (or H x W x 1) uint32 ``conventions.Flag`` bits; ``depth``: H x W (or H x W x 1) distance
    along the view axis in metres (inf on background)."""
    fl = np.asarray(flags).reshape(np.shape(flags)[:2]).astype(np.uint32)
    d = np.asarray(depth, np.float64).reshape(np.shape(depth)[:2])
    if fl.shape != d.shape:
        raise ValueError(f"flags {fl.shape} and depth {d.shape} differ in size")
    bg = (fl & np.uint32(Flag.BACKGROUND)) != 0
    boundary = (dilate(bg, 1) & ~bg) | (dilate(~bg, 1) & bg)  # the pixels on either side of a bg/surface boundary
    silhouette = dilate(boundary, EDGE_PX - 1)
    inv = 1.0 / np.where(bg | ~np.isfinite(d) | (d <= 0), np.nan, d)  # NaN off the surfaces
    jump = np.zeros_like(bg)
    with np.errstate(invalid="ignore"):
        # inverse depth is affine in the image on a plane, so its second difference is 0 there and large across a
        # discontinuity (both pixels next to the step); NaN (background) compares False
        jump[:, 1:-1] |= np.abs(inv[:, :-2] - 2 * inv[:, 1:-1] + inv[:, 2:]) > DEPTH_EDGE_RATIO * inv[:, 1:-1]
        jump[1:-1, :] |= np.abs(inv[:-2, :] - 2 * inv[1:-1, :] + inv[2:, :]) > DEPTH_EDGE_RATIO * inv[1:-1, :]
    depth_edge = dilate(jump, EDGE_PX - 1) & ~bg & ~silhouette
    return {"silhouette": silhouette, "depth_edge": depth_edge, "background": bg & ~silhouette,
            "interior": ~bg & ~silhouette & ~depth_edge}


def material_regions(flags: np.ndarray, roughness: np.ndarray) -> dict[str, np.ndarray]:
    """The material classes of one frame: {name: H x W bool} for every name of ``MATERIALS``, disjoint and covering
    the frame. ``flags``: H x W (or H x W x 1) uint32 ``conventions.Flag`` bits; ``roughness``: H x W (or H x W x 1)
    the Principled base roughness in [0, 1]."""
    fl = np.asarray(flags).reshape(np.shape(flags)[:2]).astype(np.uint32)
    r = np.asarray(roughness, np.float64).reshape(np.shape(roughness)[:2])
    if fl.shape != r.shape:
        raise ValueError(f"flags {fl.shape} and roughness {r.shape} differ in size")
    left = np.ones(fl.shape, bool)
    out = {}
    for name, m in (("background", (fl & np.uint32(Flag.BACKGROUND)) != 0),
                    ("transmission", (fl & np.uint32(Flag.TRANSMISSION)) != 0),
                    ("coated", (fl & np.uint32(Flag.COAT | Flag.THIN_FILM)) != 0),
                    ("unknown", ((fl & np.uint32(Flag.NO_MATERIAL)) != 0)
                     | (((fl & np.uint32(Flag.NON_PRINCIPLED)) != 0) & (r == 0))),
                    ("glossy", r < GLOSSY_ROUGHNESS), ("rough", left)):
        out[name] = m & left
        left = left & ~m
    return out


def error_breakdown(sq_err: np.ndarray, regions: dict[str, np.ndarray]) -> dict[str, dict]:
    """Per region of ``regions``: ``fraction`` of the pixels, ``mse`` (mean of ``sq_err``, H x W, over the region;
    None when empty) and ``err_share`` (its part of the frame's summed ``sq_err``; None when that sum is 0)."""
    e = np.asarray(sq_err, np.float64)
    total = float(e.sum())
    out = {}
    for name, m in regions.items():
        n = int(m.sum())
        s = float(e[m].sum())
        out[name] = {"fraction": n / m.size, "mse": s / n if n else None,
                     "err_share": s / total if total > 0 else None}
    return out

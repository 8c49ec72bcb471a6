"""Cycles' pixel filters as discrete weights over neighbouring pixels (pure numpy).

A Cycles render averages samples x (pixels, relative to the pixel centre) drawn independently per axis from a 1-D
filter f over its support, so the image it returns is the scene convolved with the separable filter f(x) f(y).
The filter functions and width conventions are Cycles' (``intern/cycles/scene/film.cpp``, ``filter_table``), with
``width`` = the scene's ``cycles.filter_width`` in pixels:

- BOX: f = 1 on [-w/2, w/2];
- GAUSSIAN: f = exp(-8 x^2 / w^2) (sigma = w / 4) on [-1.5 w, 1.5 w];
- BLACKMAN_HARRIS: the 4-term Blackman-Harris window spanning [-w, w] (Cycles doubles the width for it).

``weights_1d`` integrates f over each neighbouring pixel: with a point-sampled image (one value per pixel, e.g. the
G-buffer or a remodulated prediction) taken as constant over its pixel, ``convolve(x, weights_1d(...))`` is the
image the filtered render would have produced. BlendSR renders its HR ground truth with BLACKMAN_HARRIS 1.5 px and
its G-buffers point-sampled (GAUSSIAN 0.01 px), both recorded in the manifest (``render.hr``, ``render.gbuffer``).
"""
from __future__ import annotations

import math

import numpy as np
from .errors import BlendSRError

FILTERS = ("BOX", "GAUSSIAN", "BLACKMAN_HARRIS")

#: (filter, width px) BlendSR renders with: the HR ground truth anti-aliased, LR frames and G-buffers point-sampled.
HR_REFERENCE_FILTER = ("BLACKMAN_HARRIS", 1.5)
POINT_FILTER = ("GAUSSIAN", 0.01)


def support(filter_type: str, width_px: float) -> float:
    """Half-width (pixels) outside which the filter is zero."""
    ft = _check(filter_type, width_px)
    return {"BOX": 0.5, "GAUSSIAN": 1.5, "BLACKMAN_HARRIS": 1.0}[ft] * float(width_px)


def evaluate(filter_type: str, width_px: float, x: np.ndarray) -> np.ndarray:
    """Unnormalised filter value at offsets ``x`` (pixels); 0 outside the support."""
    ft = _check(filter_type, width_px)
    x = np.asarray(x, dtype=np.float64)
    r = support(ft, width_px)
    if ft == "BOX":
        v = np.ones_like(x)
    elif ft == "GAUSSIAN":
        v = np.exp(-8.0 * (x / width_px) ** 2)
    else:
        a = 2.0 * math.pi * (x / (2.0 * r) + 0.5)
        v = 0.35875 - 0.48829 * np.cos(a) + 0.14128 * np.cos(2 * a) - 0.01168 * np.cos(3 * a)
    return np.where(np.abs(x) <= r, v, 0.0)


def weights_1d(filter_type: str, width_px: float, samples: int = 512) -> np.ndarray:
    """Normalised weights (2k+1,) of pixels at offsets -k..k: the filter's integral over each pixel [o-1/2, o+1/2]
    (midpoint rule with ``samples`` points per pixel). k is the smallest radius covering the support."""
    r = support(filter_type, width_px)
    k = max(0, math.ceil(r - 0.5))
    sub = (np.arange(samples) + 0.5) / samples - 0.5
    w = np.array([evaluate(filter_type, width_px, o + sub).sum() for o in range(-k, k + 1)])
    if w.sum() <= 0:  # a support narrower than the midpoint spacing: a point sample
        return np.array([1.0])
    return w / w.sum()


def convolve(image: np.ndarray, w1: np.ndarray) -> np.ndarray:
    """Separable convolution of ``image`` (H, W, C) with ``w1`` along y and x, edges replicated (float32)."""
    k = len(w1) // 2
    if k == 0:
        return np.asarray(image, dtype=np.float32).copy()
    a = np.pad(np.asarray(image, dtype=np.float64), ((k, k), (k, k), (0, 0)), mode="edge")
    h, w = image.shape[:2]
    a = sum(wi * a[i:i + h] for i, wi in enumerate(w1))
    a = sum(wi * a[:, i:i + w] for i, wi in enumerate(w1))
    return a.astype(np.float32)


def reference_filter(manifest: dict) -> tuple[str, float]:
    """(filter type, width px) of a clip's HR ground truth, from its manifest (BlendSR's ``HR_REFERENCE_FILTER`` when
    the manifest does not record it)."""
    hr = manifest.get("render", {}).get("hr", {})
    return str(hr.get("pixel_filter", HR_REFERENCE_FILTER[0])), float(hr.get("filter_width_px", HR_REFERENCE_FILTER[1]))


def _check(filter_type: str, width_px: float) -> str:
    ft = str(filter_type).upper()
    if ft not in FILTERS:
        raise BlendSRError(f"pixel filter {filter_type!r}: choose one of {', '.join(FILTERS)}")
    if not (float(width_px) > 0):
        raise BlendSRError(f"pixel filter width {width_px!r}: must be > 0 pixels")
    return ft


def footprint_fbeta(point: np.ndarray, filtered: np.ndarray, background: np.ndarray, radius: int = 1) -> np.ndarray:
    """HR F_beta matching a pixel-filtered ground truth (H, W, 3 float32).

    ``point``: the point-sampled F_beta (1 on background); ``filtered``: the same colour passes rendered with the
    ground truth's pixel filter (the pixel's footprint average, what the filtered radiance was reflected by);
    ``background`` (H, W bool): point-sampled background mask. A texture finer than the pixel (a fabric weave)
    aliases in ``point`` at full contrast while the filtered radiance averages it, so L_D = I / F_point carries the
    inverted texture; ``filtered`` has none. Near background (within ``radius`` pixels, Chebyshev) the footprint
    averages in the sky's zero colour passes, so ``point`` is kept there, and wherever ``filtered`` is not finite or
    not positive in every channel while ``point`` is."""
    point = np.asarray(point, dtype=np.float32)
    filtered = np.asarray(filtered, dtype=np.float32)[..., :3]
    bg = np.asarray(background, dtype=bool)
    h, w = bg.shape
    near = np.pad(bg, radius, mode="edge")
    near = np.any([near[i:i + h, j:j + w] for i in range(2 * radius + 1) for j in range(2 * radius + 1)], axis=0)
    ok = ~near & np.all(np.isfinite(filtered), axis=-1) & (np.all(filtered > 0, axis=-1) | ~np.all(point > 0, axis=-1))
    return np.where(ok[..., None], filtered, point).astype(np.float32)


__all__ = ["FILTERS", "HR_REFERENCE_FILTER", "POINT_FILTER", "support", "evaluate", "weights_1d", "convolve",
           "reference_filter", "footprint_fbeta"]

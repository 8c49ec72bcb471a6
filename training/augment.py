"""Augmentations that keep every buffer consistent (numpy, arrays (..., H, W, C) keyed by 'level/buffer').

Dihedral transforms (the 8 symmetries of a square crop) are written as an optional transpose (swap image x and y)
followed by optional flips of x and of y. Image-space vectors follow the image:

- motion, motion_next and the LR jitter (x right, y down, pixels): transpose swaps (x, y); flip x negates x; flip y negates y.
  (The jitter is the offset of a pixel's sample from its centre, so it turns with the image like a motion vector.)
- camera-space normals (+X right, +Y up, +Z toward the viewer): their image direction is (X, -Y), so transpose maps
  (X, Y, Z) -> (-Y, -X, Z), flip x negates X, flip y negates Y. Z is unchanged (each transform is a mirror or
  rotation of the image plane, seen by a mirrored/rotated pinhole camera).

Exposure scaling multiplies radiance, irradiance and emission by one factor (F_beta and G-buffers unchanged), which
keeps radiance = F_beta * L_D + emission: the light gets brighter or darker.
Reflectance scaling multiplies radiance, emission, albedo, F_beta and the F_beta used for remodulation by one factor
per colour channel (irradiance unchanged), which also keeps radiance = F_beta_used * L_D + emission: the same light
falls on surfaces whose BRDF is tinted (interreflections are not recomputed). Where F_used = 1 (background,
UNTRUSTED flags; L_D = radiance - emission there) F_used stays 1 and L_D takes the tint instead. It teaches a model that the absolute
level and tint of the albedo / F_beta say nothing about the irradiance. Other buffers only move with the pixels.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

RADIOMETRIC = ("radiance", "irradiance", "emission")
REFLECTANCE = ("radiance", "emission", "albedo", "fbeta", "fbeta_used")  # irradiance: where F_used = 1


@dataclass(frozen=True)
class Augmentation:
    transpose: bool = False
    flip_x: bool = False
    flip_y: bool = False
    exposure: float = 1.0
    reflectance: tuple[float, float, float] = (1.0, 1.0, 1.0)

    @staticmethod
    def draw(rng: np.random.Generator, flip: bool, rotate: bool, exposure_range=(1.0, 1.0),
             reflectance_range=(1.0, 1.0)) -> "Augmentation":
        """Random augmentation: flips and transposes each with probability 1/2 when enabled (transpose plus a flip
        is a 90-degree rotation), exposure log-uniform in ``exposure_range``, each channel's reflectance factor
        log-uniform in ``reflectance_range``. Always draws the same number of variates, so the random stream does
        not depend on the switches."""
        u = rng.random(7)

        def log_uniform(v, lo_hi):
            lo, hi = np.log(lo_hi[0]), np.log(lo_hi[1])
            return float(np.exp(lo + v * (hi - lo)))

        return Augmentation(transpose=bool(rotate and u[0] < 0.5), flip_x=bool(flip and u[1] < 0.5),
                            flip_y=bool(flip and u[2] < 0.5), exposure=log_uniform(u[3], exposure_range),
                            reflectance=tuple(log_uniform(v, reflectance_range) for v in u[4:7]))


def _buffer(key: str) -> str:
    return key.rsplit("/", 1)[-1]


def apply_vector(v: np.ndarray, aug: Augmentation) -> np.ndarray:
    """Apply ``aug`` to image-space 2-vectors ``v`` (..., 2) (x right, y down): motion, jitter."""
    v = np.asarray(v)
    if aug.transpose:
        v = v[..., ::-1]
    return v * np.array([-1 if aug.flip_x else 1, -1 if aug.flip_y else 1], dtype=v.dtype)


def apply(key: str, a: np.ndarray, aug: Augmentation, unit: np.ndarray | None = None) -> np.ndarray:
    """Apply ``aug`` to array ``a`` (..., H, W, C) of buffer ``key``; returns a new array.

    ``unit`` (..., H, W, 1 bool, same orientation as ``a``): the pixels whose F_used is 1 (background, UNTRUSTED
    flags), needed for ``irradiance`` and ``fbeta_used`` under a reflectance tint: there F_used stays 1 and the
    tint moves into L_D (= radiance - emission), so F_used = 1 keeps marking them (``models.base.demodulated_mask``)."""
    name = _buffer(key)
    # radiometric scaling first: pointwise, so it commutes with the dihedral transform below
    if aug.exposure != 1.0 and name in RADIOMETRIC:
        a = a * np.asarray(aug.exposure, dtype=a.dtype)
    if aug.reflectance != (1.0, 1.0, 1.0):
        tint = np.asarray(aug.reflectance, dtype=a.dtype)
        if name in ("irradiance", "fbeta_used") and unit is None:
            raise ValueError(f"{key}: a reflectance tint needs the F_used = 1 mask (unit)")
        if name == "fbeta_used":
            a = np.where(unit, a, a * tint)
        elif name == "irradiance":
            a = np.where(unit, a * tint, a)
        elif name in REFLECTANCE:
            a = a * tint
    h_ax, w_ax = a.ndim - 3, a.ndim - 2
    if aug.transpose:
        a = np.swapaxes(a, h_ax, w_ax)
        if name == "normal":
            a = np.stack([-a[..., 1], -a[..., 0], a[..., 2]], axis=-1)
    if aug.flip_x:
        a = np.flip(a, axis=w_ax)
        if name == "normal":
            a = a * np.array([-1, 1, 1], dtype=a.dtype)
    if aug.flip_y:
        a = np.flip(a, axis=h_ax)
        if name == "normal":
            a = a * np.array([1, -1, 1], dtype=a.dtype)
    if name in ("motion", "motion_next"):
        a = apply_vector(a, aug)
    return np.ascontiguousarray(a)

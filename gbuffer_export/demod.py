"""BRDF demodulation and remodulation that never produce NaN or Inf (pure numpy).

    L_D = (I - E) / F_used            (demodulate)
    I   = L_D * F_used + E            (remodulate; same F_used, so the round trip is exact to float rounding)

with, per pixel and channel,

    F_used = clip(F_beta, eps, FBETA_MAX)   on ordinary surface pixels,
    F_used = 1                              on background pixels (``Flag.BACKGROUND``) and on pixels with any
                                            ``conventions.UNTRUSTED`` bit (documented fallback: the network
                                            then sees radiance minus emission there, not a wrong division),
    F_used = 1                              where F_beta itself is NaN or +-Inf (counted).

Sanitising rule for radiance I and emission E (applied before anything else, counted in ``DemodStats``):
NaN -> 0, +Inf -> +RADIANCE_CAP, -Inf -> -RADIANCE_CAP, and finite values are clipped to
[-RADIANCE_CAP, RADIANCE_CAP]. Negative finite values are kept (pixel filters produce them) and fireflies
up to RADIANCE_CAP are kept unchanged. The round trip reproduces the *sanitised* radiance.

``eps`` must lie in [EPS_MIN, 1]; with |I - E| <= 2 * RADIANCE_CAP the irradiance is bounded by
2 * RADIANCE_CAP / EPS_MIN = 2e15, far inside float32. Arrays: H x W x 3 float32 (F_beta may be H x W x 1);
flags H x W or H x W x 1 uint32. Arithmetic is done in float64 and the results are returned as float32.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import BlendSRError
from .conventions import UNTRUSTED, Flag

#: Largest magnitude kept in radiance/emission; +-Inf become +-RADIANCE_CAP (scene-linear units).
RADIANCE_CAP = 1.0e9
#: Largest F_beta used for division (a directional albedo is <= 1; bigger values are clamped).
FBETA_MAX = 1.0e3
#: Smallest accepted eps.
EPS_MIN = 1.0e-6
#: Default floor of F_beta (see VERIFIED-FACTS: the floor of a real material is about 0.012).
DEFAULT_EPS = 0.01


@dataclass(frozen=True)
class DemodStats:
    """What sanitising and clamping did, in pixel-channel counts (``untrusted`` and ``background`` in pixels)."""

    nan: int = 0              # NaN values in radiance or emission, set to 0
    pos_inf: int = 0          # +Inf values set to +RADIANCE_CAP
    neg_inf: int = 0          # -Inf values set to -RADIANCE_CAP
    clipped: int = 0          # finite values beyond +-RADIANCE_CAP clipped
    fbeta_nonfinite: int = 0  # F_beta values that were NaN/Inf (F_used := 1 there)
    fbeta_floored: int = 0    # F_beta values below eps (F_used := eps)
    fbeta_capped: int = 0     # F_beta values above FBETA_MAX
    background: int = 0       # pixels with Flag.BACKGROUND (F_used := 1)
    untrusted: int = 0        # non-background pixels with an UNTRUSTED bit (F_used := 1)

    @property
    def sanitised(self) -> int:
        """Number of radiance/emission values changed by the sanitising rule."""
        return self.nan + self.pos_inf + self.neg_inf + self.clipped


@dataclass(frozen=True)
class DemodResult:
    irradiance: np.ndarray   # H x W x 3 float32, L_D
    fbeta_used: np.ndarray   # H x W x 3 float32, the clamped F_beta the division used
    stats: DemodStats


def sanitize(values: np.ndarray) -> tuple[np.ndarray, dict[str, int]]:
    """Apply the sanitising rule (see module doc) to a float array; returns (float64 copy, counts)."""
    a = np.asarray(values, dtype=np.float64)
    nan = np.isnan(a)
    pinf = np.isposinf(a)
    ninf = np.isneginf(a)
    finite = ~(nan | pinf | ninf)
    big = finite & (np.abs(a) > RADIANCE_CAP)
    out = np.where(finite, np.clip(a, -RADIANCE_CAP, RADIANCE_CAP), 0.0)
    out[pinf] = RADIANCE_CAP
    out[ninf] = -RADIANCE_CAP
    return out, {"nan": int(nan.sum()), "pos_inf": int(pinf.sum()), "neg_inf": int(ninf.sum()),
                 "clipped": int(big.sum())}


def _check_eps(eps: float) -> float:
    eps = float(eps)
    if not (np.isfinite(eps) and EPS_MIN <= eps <= 1.0):
        raise BlendSRError(f"demodulation eps {eps!r} must lie in [{EPS_MIN}, 1]")
    return eps


def _as_hw3(name: str, a: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[:2] != shape or a.shape[2] not in (1, 3):
        raise ValueError(f"{name} has shape {a.shape}; expected {shape + (3,)} (or {shape + (1,)})")
    return np.broadcast_to(a, shape + (3,))


def _flag_masks(flags: np.ndarray | None, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(background, untrusted-but-not-background) H x W boolean masks."""
    if flags is None:
        z = np.zeros(shape, dtype=bool)
        return z, z
    f = np.asarray(flags)
    if f.ndim == 3 and f.shape[2] == 1:
        f = f[..., 0]
    if f.shape != shape:
        raise ValueError(f"flags has shape {np.shape(flags)}; expected {shape} or {shape + (1,)}")
    if f.dtype.kind == "f":
        f = np.nan_to_num(f, nan=0.0, posinf=0.0, neginf=0.0)
    f = f.astype(np.uint32)
    bg = (f & np.uint32(Flag.BACKGROUND)) != 0
    un = ((f & np.uint32(UNTRUSTED)) != 0) & ~bg
    return bg, un


def fbeta_for_division(fbeta: np.ndarray, flags: np.ndarray | None = None, eps: float = DEFAULT_EPS,
                       shape: tuple[int, int] | None = None) -> tuple[np.ndarray, dict[str, int]]:
    """The F_beta that demodulation divides by (H x W x 3 float64) and counts of what was changed."""
    eps = _check_eps(eps)
    fb = np.asarray(fbeta)
    shape = shape or fb.shape[:2]
    f = np.array(_as_hw3("fbeta", fb, shape), dtype=np.float64)
    nonfinite = ~np.isfinite(f)
    floored = ~nonfinite & (f < eps)
    capped = ~nonfinite & (f > FBETA_MAX)
    f = np.where(nonfinite, 1.0, np.clip(f, eps, FBETA_MAX))
    bg, un = _flag_masks(flags, shape)
    f[bg | un] = 1.0
    f = f.astype(np.float32).astype(np.float64)  # divide by exactly what is returned (float32)
    keep = ~(bg | un)[..., None]
    return f, {"fbeta_nonfinite": int((nonfinite & keep).sum()), "fbeta_floored": int((floored & keep).sum()),
               "fbeta_capped": int((capped & keep).sum()), "background": int(bg.sum()), "untrusted": int(un.sum())}


def undivided_mask(fbeta_used: np.ndarray) -> np.ndarray:
    """(..., H, W, 1) bool: pixels that demodulation did not divide (F_used exactly 1 in every channel: background,
    UNTRUSTED flags, non-finite F_beta), where L_D is radiance minus emission. ``fbeta_used``: (..., H, W, 3)."""
    return np.all(np.asarray(fbeta_used) == 1.0, axis=-1, keepdims=True)


def demodulate_full(radiance: np.ndarray, emission: np.ndarray | None, fbeta: np.ndarray,
                    flags: np.ndarray | None = None, eps: float = DEFAULT_EPS) -> DemodResult:
    """``demodulate`` plus the counts of sanitised and clamped values (``DemodResult.stats``)."""
    rad = np.asarray(radiance)
    if rad.ndim != 3 or rad.shape[2] != 3:
        raise ValueError(f"radiance has shape {rad.shape}; expected H x W x 3")
    shape = rad.shape[:2]
    i, c_i = sanitize(rad)
    if emission is None:
        e, c_e = np.zeros_like(i), {k: 0 for k in c_i}
    else:
        e, c_e = sanitize(_as_hw3("emission", emission, shape))
    f, c_f = fbeta_for_division(fbeta, flags, eps, shape)
    irr = (i - e) / f
    stats = DemodStats(**{k: c_i[k] + c_e[k] for k in c_i}, **c_f)
    return DemodResult(irr.astype(np.float32), f.astype(np.float32), stats)


def demodulate(radiance: np.ndarray, emission: np.ndarray | None, fbeta: np.ndarray,
               flags: np.ndarray | None = None, eps: float = DEFAULT_EPS) -> tuple[np.ndarray, np.ndarray]:
    """Demodulated irradiance L_D = (I - E) / F_used and F_used (both H x W x 3 float32, always finite).

    radiance, emission: H x W x 3 (emission None = 0); fbeta: H x W x 3 or H x W x 1; flags: H x W or
    H x W x 1 uint32 (None = all ordinary surface pixels). See the module doc for the rules."""
    r = demodulate_full(radiance, emission, fbeta, flags, eps)
    return r.irradiance, r.fbeta_used


def remodulate(irradiance: np.ndarray, fbeta_used: np.ndarray, emission: np.ndarray | None) -> np.ndarray:
    """Radiance I = L_D * F_used + E (H x W x 3 float32). Pass the ``fbeta_used`` that ``demodulate`` returned
    (not the raw F_beta) to get the sanitised radiance back. Non-finite inputs are sanitised first."""
    irr = np.asarray(irradiance, dtype=np.float64)
    if irr.ndim != 3 or irr.shape[2] != 3:
        raise ValueError(f"irradiance has shape {irr.shape}; expected H x W x 3")
    shape = irr.shape[:2]
    irr = np.nan_to_num(irr, nan=0.0, posinf=RADIANCE_CAP / EPS_MIN, neginf=-RADIANCE_CAP / EPS_MIN)
    f = np.nan_to_num(np.asarray(_as_hw3("fbeta_used", fbeta_used, shape), dtype=np.float64), nan=1.0,
                      posinf=FBETA_MAX, neginf=0.0)
    e = np.zeros_like(irr) if emission is None else sanitize(_as_hw3("emission", emission, shape))[0]
    out = irr * f + e
    lim = float(np.finfo(np.float32).max)
    return np.clip(out, -lim, lim).astype(np.float32)


__all__ = ["demodulate", "remodulate", "demodulate_full", "undivided_mask", "fbeta_for_division", "sanitize", "DemodResult",
           "DemodStats", "RADIANCE_CAP", "FBETA_MAX", "EPS_MIN", "DEFAULT_EPS"]

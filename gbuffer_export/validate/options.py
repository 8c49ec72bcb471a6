"""Tolerances of the value and motion checks (``ValidationOptions``)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from ..errors import BlendSRError


@dataclass(frozen=True)
class ValidationOptions:
    """Tolerances of the value and motion checks.

    motion_tol_px: hr motion tolerance, pixels of the hr level (|stored - reprojected| <= tol counts as agreeing).
    lr_motion_tol_px: tolerance of every LR level in pixels of that level; None uses ``motion_tol_px`` (each
        level's motion is checked against that level's own point-sampled depth, so the error sources are per pixel of the level).
    motion_min_fraction: least fraction of static surface pixels that must agree (edges may disagree).
    background_min_fraction: least fraction of background pixels that must carry the rotation-only motion.
    normal_tol / normal_min_fraction: | |n| - 1 | < normal_tol on at least this fraction of surface pixels.
    fbeta_max: upper end of the plausible fbeta range on surfaces; fbeta_max_outside: fraction of surface pixels
        allowed outside [0, fbeta_max] before it is an error (any pixel outside is a warning).
    range_eps: slack of the [0, 1] and >= 0 range checks (float rounding).
    background_eps: tolerance of "zero normal" and "fbeta == 1" on background pixels.
    min_pixels: fewer pixels than this in a motion class gives no finding (fraction too noisy).
    """

    motion_tol_px: float = 0.05
    lr_motion_tol_px: float | None = None
    motion_min_fraction: float = 0.8
    background_min_fraction: float = 0.9
    normal_tol: float = 1e-2
    normal_min_fraction: float = 0.99
    fbeta_max: float = 1.05
    fbeta_max_outside: float = 1e-3
    range_eps: float = 1e-4
    background_eps: float = 1e-3
    min_pixels: int = 8

    def __post_init__(self):
        for name in ("motion_tol_px", "normal_tol", "fbeta_max", "range_eps", "background_eps"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise BlendSRError(f"validation option {name}={v!r}: must be a positive number")
        if self.lr_motion_tol_px is not None and not (math.isfinite(self.lr_motion_tol_px)
                                                      and self.lr_motion_tol_px > 0):
            raise BlendSRError(f"validation option lr_motion_tol_px={self.lr_motion_tol_px!r}: must be positive")
        for name in ("motion_min_fraction", "background_min_fraction", "normal_min_fraction", "fbeta_max_outside"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0.0 <= v <= 1.0):
                raise BlendSRError(f"validation option {name}={v!r}: must be a fraction in [0, 1]")
        if not (isinstance(self.min_pixels, int) and self.min_pixels >= 1):
            raise BlendSRError(f"validation option min_pixels={self.min_pixels!r}: must be an integer >= 1")

    def tol_px(self, level: str) -> float:
        """Motion tolerance of ``level`` in pixels of that level."""
        if level != "hr" and self.lr_motion_tol_px is not None:
            return float(self.lr_motion_tol_px)
        return float(self.motion_tol_px)


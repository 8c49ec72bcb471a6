"""Motion checks of one frame and level: stored motion against ``reprojection_motion`` from the stored depth and
cameras on static surface pixels (neither MOVING nor ALPHA: an alpha-blended pixel's Vector pass averages the
layers its samples stopped at, its depth is sample 0's), and against the rotation-only motion on background
pixels (fractions within tolerance)."""
from __future__ import annotations

from typing import Any

import numpy as np

from ..conventions import Flag, reprojection_motion
from .report import Collector, fmt_frac


def check_motion(c: Collector, frame: int, lvl: str, b: dict[str, np.ndarray], cam: dict | None, surface) -> dict:
    """Compare stored motion with reprojection from depth and cameras (static surface pixels) and with the
    rotation-only motion (background pixels); returns this frame's and level's statistics."""
    o = c.opt
    tol = o.tol_px(lvl)
    motion, depth = b.get("motion"), b.get("depth")
    st: dict[str, Any] = {}
    if motion is None or depth is None or cam is None:
        return st
    d = depth[..., 0].astype(np.float64)
    mv = motion.astype(np.float64)
    fin = np.isfinite(d) & (d > 0)
    if surface is None:
        surface = fin
    static = surface & fin
    flags = b.get("flags")
    if flags is not None:
        # Moving objects are not static; alpha-blended pixels mix layers (Cycles averages the Vector pass over
        # samples that pass through or stop at the surface, while depth comes from sample 0 alone).
        static &= (flags[..., 0] & np.uint32(Flag.MOVING | Flag.ALPHA)) == 0
    background = ~surface
    # One call gives both fields: finite depth reprojects, +inf gets the rotation-only motion.
    jitter = cam.get("jitter", (0.0, 0.0))  # depth was sampled at p + jitter (see conventions)
    with np.errstate(all="ignore"):
        exp = reprojection_motion(np.where(static, d, np.inf), cam["intrinsics"], cam["world_from_camera"],
                                  cam["prev_intrinsics"], cam["prev_world_from_camera"], jitter)
    exp_ok = np.isfinite(exp).all(axis=-1)  # points behind the previous camera have no motion
    key = f"{lvl}/motion"
    for cls, mask, need in (("static", static, o.motion_min_fraction),
                            ("background", background, o.background_min_fraction)):
        usable = mask & exp_ok
        n = int(usable.sum())
        st[f"{cls}_pixels"] = n
        if not n:
            continue
        err = np.linalg.norm(mv[usable] - exp[usable], axis=-1)
        err = np.where(np.isfinite(err), err, np.inf)
        frac = float(np.mean(err <= tol))
        med = float(np.median(err))
        st[f"{cls}_fraction"], st[f"{cls}_median_px"] = frac, med
        if n < o.min_pixels or frac >= need:
            continue
        if cls == "static":
            c.add("motion-reprojection",
                     f"motion agrees with reprojection from depth and cameras within {tol:g} px on only "
                     f"{fmt_frac(frac)} of {n} static surface pixels (need {fmt_frac(need)}; median error "
                     f"{med:.4g} px)", frame=frame, key=key, fraction=frac, median_px=med, pixels=n)
        else:
            stored = float(np.median(np.linalg.norm(mv[usable], axis=-1)))
            expected = float(np.median(np.linalg.norm(exp[usable], axis=-1)))
            hint = (" (stored background motion is zero, as Blender's Vector pass leaves it: the exporter must "
                    "fill the rotation-only motion)" if stored == 0.0 and expected > tol else "")
            c.add("background-motion",
                     f"background motion matches the camera's rotation-only motion within {tol:g} px on only "
                     f"{fmt_frac(frac)} of {n} background pixels (need {fmt_frac(need)}; median error "
                     f"{med:.4g} px, median |stored| {stored:.4g} px, median |expected| {expected:.4g} px)"
                     f"{hint}", frame=frame, key=key, fraction=frac, median_px=med, pixels=n)
    return st

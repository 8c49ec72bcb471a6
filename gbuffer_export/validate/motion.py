"""Motion checks of one frame and level: stored ``motion`` (to frame t-1) and ``motion_next`` (to frame t+1) against
``reprojection_motion`` from the stored depth and cameras on static surface pixels (neither MOVING nor ALPHA: an
alpha-blended pixel's Vector pass averages the layers its samples stopped at, its depth is sample 0's), and against
the rotation-only motion on background pixels (fractions within tolerance). ``motion_next`` needs the next camera
in the frame record (``next_world_from_camera``, ``next_intrinsics``)."""
from __future__ import annotations

from typing import Any

import numpy as np

from ..conventions import Flag, reprojection_motion
from .records import floats, intrinsics_ok, pose_problem
from .report import Collector, fmt_frac

NEXT_KEYS = ("next_world_from_camera", "next_intrinsics")


def agreement(mv: np.ndarray, depth: np.ndarray, surface, flags, cam: dict, other_k, other_m, tol: float
              ) -> dict[str, tuple[np.ndarray, float, float]]:
    """Stored motion ``mv`` (H x W x 2) against the reprojection to the camera (``other_k``, ``other_m``), per
    pixel class: {'static': (errors, fraction within ``tol``, median), 'background': ...}; a class without usable
    pixels is left out. Static: surface pixels with finite depth, neither MOVING nor ALPHA; background: the rest,
    compared with the rotation-only motion (one call gives both: +inf depth reprojects without translation)."""
    d = depth[..., 0].astype(np.float64)
    fin = np.isfinite(d) & (d > 0)
    if surface is None:
        surface = fin
    static = surface & fin
    if flags is not None:
        static &= (flags[..., 0] & np.uint32(Flag.MOVING | Flag.ALPHA)) == 0
    with np.errstate(all="ignore"):  # depth was sampled at p + jitter (see conventions)
        exp = reprojection_motion(np.where(static, d, np.inf), cam["intrinsics"], cam["world_from_camera"],
                                  other_k, other_m, cam.get("jitter", (0.0, 0.0)))
    exp_ok = np.isfinite(exp).all(axis=-1)  # points behind the other camera have no motion
    out = {}
    for cls, mask in (("static", static), ("background", ~surface)):
        usable = mask & exp_ok
        if not usable.any():
            out[cls] = (np.zeros(0), 1.0, 0.0, usable, exp)
            continue
        err = np.linalg.norm(mv[usable].astype(np.float64) - exp[usable], axis=-1)
        err = np.where(np.isfinite(err), err, np.inf)
        out[cls] = (err, float(np.mean(err <= tol)), float(np.median(err)), usable, exp)
    return out


def check_motion(c: Collector, frame: int, lvl: str, b: dict[str, np.ndarray], cam: dict | None, surface) -> dict:
    """Compare stored motion with reprojection from depth and cameras (static surface pixels) and with the
    rotation-only motion (background pixels); returns this frame's and level's statistics."""
    o = c.opt
    tol = o.tol_px(lvl)
    motion, depth = b.get("motion"), b.get("depth")
    st: dict[str, Any] = {}
    if motion is None or depth is None or cam is None:
        return st
    key = f"{lvl}/motion"
    res = agreement(motion, depth, surface, b.get("flags"), cam, cam["prev_intrinsics"],
                    cam["prev_world_from_camera"], tol)
    for cls, need in (("static", o.motion_min_fraction), ("background", o.background_min_fraction)):
        err, frac, med, usable, exp = res[cls]
        n = len(err)
        st[f"{cls}_pixels"] = n
        if not n:
            continue
        st[f"{cls}_fraction"], st[f"{cls}_median_px"] = frac, med
        if n < o.min_pixels or frac >= need:
            continue
        if cls == "static":
            c.add("motion-reprojection",
                     f"motion agrees with reprojection from depth and cameras within {tol:g} px on only "
                     f"{fmt_frac(frac)} of {n} static surface pixels (need {fmt_frac(need)}; median error "
                     f"{med:.4g} px)", frame=frame, key=key, fraction=frac, median_px=med, pixels=n)
        else:
            stored = float(np.median(np.linalg.norm(motion[usable].astype(np.float64), axis=-1)))
            expected = float(np.median(np.linalg.norm(exp[usable], axis=-1)))
            hint = (" (stored background motion is zero, as Blender's Vector pass leaves it: the exporter must "
                    "fill the rotation-only motion)" if stored == 0.0 and expected > tol else "")
            c.add("background-motion",
                     f"background motion matches the camera's rotation-only motion within {tol:g} px on only "
                     f"{fmt_frac(frac)} of {n} background pixels (need {fmt_frac(need)}; median error "
                     f"{med:.4g} px, median |stored| {stored:.4g} px, median |expected| {expected:.4g} px)"
                     f"{hint}", frame=frame, key=key, fraction=frac, median_px=med, pixels=n)
    return st


def next_camera(record: dict) -> tuple[np.ndarray, np.ndarray] | str:
    """(next_world_from_camera 4x4, next_intrinsics (4,)) of one level's frame record, or a one-line problem."""
    missing = [k for k in NEXT_KEYS if k not in record]
    if missing:
        return f"record lacks {', '.join(missing)} (needed by motion_next)"
    m, k = floats(record["next_world_from_camera"]), floats(record["next_intrinsics"])
    problem = pose_problem(m)
    if problem:
        return f"next_world_from_camera {problem}"
    if not intrinsics_ok(k):
        return f"next_intrinsics {record['next_intrinsics']!r} is not (fx, fy, cx, cy) with positive focal"
    return m, k


def check_motion_next(c: Collector, frame: int, lvl: str, b: dict[str, np.ndarray], cam: dict | None,
                      record: dict | None, surface) -> None:
    """The ``motion`` check for ``motion_next``, towards the next camera of the level's frame ``record``."""
    mv, depth = b.get("motion_next"), b.get("depth")
    if mv is None or not isinstance(record, dict):
        return
    key = f"{lvl}/motion_next"
    nxt = next_camera(record)
    if isinstance(nxt, str):
        c.add("next-camera", nxt, frame=frame, key=key)
        return
    if depth is None or cam is None:
        return
    o = c.opt
    tol = o.tol_px(lvl)
    res = agreement(mv, depth, surface, b.get("flags"), cam, nxt[1], nxt[0], tol)
    for cls, code, what, need in (("static", "motion-next-reprojection", "static surface", o.motion_min_fraction),
                                  ("background", "motion-next-background", "background",
                                   o.background_min_fraction)):
        err, frac, med, _, _ = res[cls]
        n = len(err)
        if n < max(o.min_pixels, 1) or frac >= need:
            continue
        c.add(code, f"motion_next agrees with the motion to the next camera within {tol:g} px on only "
                    f"{fmt_frac(frac)} of {n} {what} pixels (need {fmt_frac(need)}; median error {med:.4g} px)",
              frame=frame, key=key, fraction=frac, median_px=med, pixels=n)

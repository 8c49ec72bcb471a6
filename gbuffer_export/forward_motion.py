"""Checks of the ``motion_next`` buffer (forward motion to frame t+1) for ``blendsr validate`` (pure numpy).

``motion_next`` follows the conventions of ``motion`` (pixels of the level, image coordinates, jitter excluded) but
points to frame t+1: ``p_next = p + motion_next``. A clip that has it records the camera of frame t+1 per level
(``next_world_from_camera``, ``next_intrinsics``). The check is the one ``motion`` gets, towards that camera:
static surface pixels (neither MOVING nor ALPHA) against reprojection from depth, background pixels against the
rotation-only motion.
"""
from __future__ import annotations

import numpy as np

from .conventions import Flag, reprojection_motion

BUFFER = "motion_next"
NEXT_KEYS = ("next_world_from_camera", "next_intrinsics")

#: Finding codes of these checks (merged into ``validate.CODES``).
CODES: dict[str, str] = {
    "next-camera": "a clip with motion_next lacks a rigid next_world_from_camera or a valid next_intrinsics",
    "motion-next-reprojection": "stored motion_next disagrees with reprojection to the next camera on static "
                                "surfaces",
    "motion-next-background": "background motion_next is not the rotation-only motion to the next camera",
}


def next_camera(record: dict) -> tuple[np.ndarray, np.ndarray] | str:
    """(next_world_from_camera 4x4, next_intrinsics (4,)) of one level's frame record, or a one-line problem."""
    missing = [k for k in NEXT_KEYS if k not in record]
    if missing:
        return f"record lacks {', '.join(missing)} (needed by motion_next)"
    try:
        m = np.asarray(record["next_world_from_camera"], dtype=np.float64)
        k = np.asarray(record["next_intrinsics"], dtype=np.float64)
    except (TypeError, ValueError):
        return "next_world_from_camera / next_intrinsics are not numbers"
    if m.shape != (4, 4) or not np.all(np.isfinite(m)) or \
            float(np.max(np.abs(m[:3, :3].T @ m[:3, :3] - np.eye(3)))) > 1e-4:
        return f"next_world_from_camera is not a finite rigid 4x4 matrix (shape {m.shape})"
    if k.shape != (4,) or not np.all(np.isfinite(k)) or k[0] <= 0 or k[1] <= 0:
        return f"next_intrinsics {record['next_intrinsics']!r} is not (fx, fy, cx, cy) with positive focal"
    return m, k


def check_motion_next(buffers: dict[str, np.ndarray], cam: dict | None, record: dict | None, surface, *,
                      tol: float, min_fraction: float, background_min_fraction: float, min_pixels: int
                      ) -> list[tuple[str, str, dict]]:
    """Findings (code, message, details) of one frame and level. ``buffers``: the level's arrays (H x W x C);
    ``cam``: its checked camera (``world_from_camera``, ``intrinsics``, ``jitter``); ``record``: its raw frame
    record (for the next camera); ``surface``: H x W bool or None (finite depth then)."""
    mv, depth = buffers.get(BUFFER), buffers.get("depth")
    if mv is None or not isinstance(record, dict):
        return []
    nxt = next_camera(record)
    if isinstance(nxt, str):
        return [("next-camera", nxt, {})]
    if depth is None or cam is None:
        return []
    m_next, k_next = nxt
    d = depth[..., 0].astype(np.float64)
    fin = np.isfinite(d) & (d > 0)
    surface = fin if surface is None else surface
    static = surface & fin
    flags = buffers.get("flags")
    if flags is not None:
        static &= (flags[..., 0] & np.uint32(Flag.MOVING | Flag.ALPHA)) == 0
    with np.errstate(all="ignore"):
        exp = reprojection_motion(np.where(static, d, np.inf), cam["intrinsics"], cam["world_from_camera"], k_next,
                                  m_next, cam.get("jitter", (0.0, 0.0)))
    ok = np.isfinite(exp).all(axis=-1)
    out = []
    for code, what, mask, need in (("motion-next-reprojection", "static surface", static, min_fraction),
                                   ("motion-next-background", "background", ~surface, background_min_fraction)):
        usable = mask & ok
        n = int(usable.sum())
        if n < max(min_pixels, 1):
            continue
        err = np.linalg.norm(mv[usable].astype(np.float64) - exp[usable], axis=-1)
        frac = float(np.mean(np.where(np.isfinite(err), err, np.inf) <= tol))
        if frac < need:
            med = float(np.median(err))
            out.append((code, f"motion_next agrees with the motion to the next camera within {tol:g} px on only "
                              f"{100 * frac:.1f}% of {n} {what} pixels (need {100 * need:.1f}%; median error "
                              f"{med:.4g} px)", {"fraction": frac, "median_px": med, "pixels": n}))
    return out

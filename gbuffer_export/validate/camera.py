"""Checks of what a clip's camera sees and how it moves: no black frame for any camera, and for a path planned
inside a level (manifest ``camera.kind`` walk or fly with its ``rules``) the rules the planner promised, measured on
the rendered frames: background fraction and median depth from the HR depth, speed from the frame records, eyes
inside the clip's split region, clearance as planned."""
from __future__ import annotations

import numpy as np

from .report import Collector

#: A frame fails when more than this fraction of its HR pixels is background (no surface, or a surface beyond the
#: level's extent such as a skybox or a far ground plane).
MAX_BACKGROUND = 0.5
SPEED_TOLERANCE = 1.02
#: ``empty-frame``: an HR frame whose depth is finite (a surface, not sky or background) on less than this share of
#: its pixels shows nothing of the scene. A walk under open sky keeps the ground in view (a level camera may show at
#: most MAX_BACKGROUND of background); a frame of only the added sky is a scene whose geometry was lost on import.
MIN_SURFACE_SHARE = 0.005


def check_black_frame(c: Collector, frame: int, lvl: str, b: dict[str, np.ndarray]) -> None:
    """A radiance that is zero, or not finite, on every pixel is a broken render (an unlit scene)."""
    rad = b.get("radiance")
    if rad is None or rad.size == 0:
        return
    finite = np.isfinite(rad)
    if not finite.any():
        c.add("black-frame", "radiance is not finite on any pixel", frame=frame, key=f"{lvl}/radiance")
    elif not np.any(rad[finite] != 0):
        c.add("black-frame", "radiance is 0 on every pixel (is the scene lit? blendsr render --light sky)",
              frame=frame, key=f"{lvl}/radiance")


def check_empty_frame(c: Collector, frame: int, b: dict[str, np.ndarray]) -> None:
    """``empty-frame``: the HR depth is finite on less than MIN_SURFACE_SHARE of the frame's pixels."""
    depth = b.get("depth")
    if depth is None or depth.size == 0:
        return
    share = float(np.isfinite(depth[..., 0]).mean())
    if share < MIN_SURFACE_SHARE:
        c.add("empty-frame", f"the HR depth is finite on {100 * share:.3g}% of the pixels (at least "
              f"{100 * MIN_SURFACE_SHARE:g}% needed): the frame shows no geometry, only sky or background; was the "
              "scene's geometry lost on import?", frame=frame, key="hr/depth", surface_share=share)


def level_report(manifest: dict) -> dict | None:
    cam = manifest.get("camera")
    if isinstance(cam, dict) and cam.get("kind") in ("walk", "fly") and isinstance(cam.get("rules"), dict):
        return cam
    return None


def check_level_view(c: Collector, frame: int, b: dict[str, np.ndarray], report: dict) -> dict | None:
    """Background fraction and median depth (metres) of one HR frame against the level's extent."""
    depth = b.get("depth")
    if depth is None:
        return None
    d = depth[..., 0].astype(np.float64) * float(report.get("metres_per_unit", 1.0))
    extent = float(report["level_extent_m"])
    surface = np.isfinite(d) & (d <= extent)
    bg = 1.0 - float(surface.mean())
    med = float(np.median(d[surface])) if surface.any() else float("inf")
    if bg >= MAX_BACKGROUND:
        c.add("camera-view", f"{100 * bg:.0f}% of the frame is background (sky, or beyond the level's extent of "
              f"{extent:.1f} m); a level camera must look at content", frame=frame, key="hr/depth", fraction=bg)
    if not med <= extent:
        c.add("camera-view", f"median depth {med:.1f} m is beyond the level's extent of {extent:.1f} m",
              frame=frame, key="hr/depth", median_m=med)
    return {"background_fraction": bg, "median_depth_m": med}


def _cell_box(region: dict):
    lo, hi = np.array(region["lo"], float), np.array(region["hi"], float)
    nx, ny = region["grid"]
    size = (hi - lo) / np.array([nx, ny], float)
    cells = region.get("cells")
    return lo, size, [tuple(x) for x in cells] if cells else None, (nx, ny)


def check_level_motion(c: Collector, frames: list[int], frame_data: dict, report: dict) -> None:
    """Eye speed per frame within the declared maximum, eyes in the region's cells, clearance as planned."""
    mpu = float(report.get("metres_per_unit", 1.0))
    fps = float(report.get("fps") or 24.0)
    vmax = float(report.get("declared_max_speed_mps", 0.0))
    eyes = {}
    for f in frames:
        rec = frame_data.get(f, {}).get("hr", {})
        try:
            eyes[f] = np.array(rec["world_from_camera"], float)[:3, 3]
            eyes.setdefault(f - 1, np.array(rec["prev_world_from_camera"], float)[:3, 3])
        except (KeyError, TypeError, ValueError, IndexError):
            continue
    for f in frames:
        if f in eyes and f - 1 in eyes and vmax > 0:
            v = float(np.linalg.norm(eyes[f] - eyes[f - 1])) * mpu * fps
            if v > vmax * SPEED_TOLERANCE:
                c.add("camera-motion", f"the camera moves at {v:.2f} m/s, above the declared {vmax:.2f} m/s",
                      frame=f, key="hr", speed_mps=v)
    region = report.get("region")
    if isinstance(region, dict) and region.get("lo") is not None:
        lo, size, cells, (nx, ny) = _cell_box(region)
        for f, e in sorted(eyes.items()):
            ij = np.floor((e[:2] - lo) / np.maximum(size, 1e-12)).astype(int)
            inside = 0 <= ij[0] < nx and 0 <= ij[1] < ny and (cells is None or tuple(ij) in cells)
            if not inside:
                c.add("camera-region", f"the eye ({e[0]:.2f}, {e[1]:.2f}) is outside the clip's split region",
                      frame=f, key="hr")
    clear, rule = report.get("clearance_m"), report.get("min_clearance_rule_m")
    if isinstance(clear, (int, float)) and isinstance(rule, (int, float)) and clear < rule:
        c.add("camera-motion", f"the planned path comes {clear:.3f} m from geometry, closer than its rule {rule} m")

"""Checks of the frame records: cameras (4x4 rigid), intrinsics (positive focal), jitter in [-0.5, 0.5] px, spp,
seed, seconds; every level describes the same camera (an LR level's intrinsics = hr intrinsics / its scale)."""
from __future__ import annotations

import numpy as np

from .report import Collector, as_int

_RECORD_KEYS = ("world_from_camera", "prev_world_from_camera", "intrinsics", "prev_intrinsics", "jitter", "spp",
                "seed", "seconds")


def floats(value) -> np.ndarray:
    """``value`` as a float64 array; an empty one when it is not numeric (the shape checks then fail)."""
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return np.zeros(0)


def pose_problem(a: np.ndarray) -> str | None:
    """Why ``a`` is not a camera pose (a finite rigid 4x4 world_from_camera), or None."""
    if a.shape != (4, 4) or not np.all(np.isfinite(a)):
        return f"is not a finite 4x4 matrix (shape {a.shape})"
    rot = a[:3, :3]
    rig = float(np.max(np.abs(rot.T @ rot - np.eye(3))))
    if not np.allclose(a[3], (0, 0, 0, 1), atol=1e-6) or rig > 1e-4:
        return f"is not rigid (|R^T R - I| max {rig:.2g}, bottom row {a[3].tolist()})"
    return None


def intrinsics_ok(k: np.ndarray) -> bool:
    """``k`` is finite (fx, fy, cx, cy) with positive focal lengths."""
    return k.shape == (4,) and bool(np.all(np.isfinite(k))) and k[0] > 0 and k[1] > 0


def check_record(c: Collector, frame: int, rec: dict, h: dict) -> dict[str, dict] | None:
    """Cameras of every level as arrays; a level whose record is unusable is left out."""
    cams: dict[str, dict] = {}
    for lvl in h["sizes"]:
        r = rec.get(lvl)
        if not isinstance(r, dict):
            c.add("record-incomplete", f"record lacks level {lvl!r}", frame=frame, key=lvl)
            continue
        missing = [k for k in _RECORD_KEYS if k not in r]
        if missing:
            c.add("record-incomplete", f"record lacks {', '.join(missing)}", frame=frame, key=lvl,
                     missing=missing)
        cam = {}
        ok = True
        for name in ("world_from_camera", "prev_world_from_camera"):
            if name not in r:
                ok = False
                continue
            a = floats(r[name])
            problem = pose_problem(a)
            if problem:
                c.add("bad-camera", f"{name} {problem}", frame=frame, key=lvl)
                ok = False
                continue
            cam[name] = a
        for name in ("intrinsics", "prev_intrinsics"):
            if name not in r:
                ok = False
                continue
            k = floats(r[name])
            if not intrinsics_ok(k):
                c.add("bad-camera", f"{name} {r[name]!r} is not (fx, fy, cx, cy) with positive focal",
                         frame=frame, key=lvl)
                ok = False
                continue
            cam[name] = k
        if "jitter" in r:
            j = floats(r["jitter"])
            if j.shape != (2,) or not np.all(np.isfinite(j)) or np.any(np.abs(j) > 0.5 + 1e-9):
                c.add("jitter-range", f"jitter {r['jitter']!r} is not two numbers in [-0.5, 0.5] px",
                         frame=frame, key=lvl)
            else:
                cam["jitter"] = (float(j[0]), float(j[1]))
        if "spp" in r and (as_int(r["spp"]) is None or as_int(r["spp"]) < 1):
            c.add("bad-record", f"spp {r['spp']!r} is not a positive integer", frame=frame, key=lvl)
        if "seed" in r and as_int(r["seed"]) is None:
            c.add("bad-record", f"seed {r['seed']!r} is not an integer", frame=frame, key=lvl)
        if "seconds" in r and not (isinstance(r["seconds"], dict) or r["seconds"] is None
                                   or (isinstance(r["seconds"], (int, float))
                                       and not isinstance(r["seconds"], bool))):
            c.add("bad-record", f"seconds {r['seconds']!r} is not a number or an object of timings",
                     frame=frame, key=lvl)
        if ok:
            cams[lvl] = cam
    for lvl in (k for k in cams if k != "hr"):
        if "hr" not in cams:
            break
        a, b = cams["hr"], cams[lvl]
        for name in ("world_from_camera", "prev_world_from_camera"):
            d = float(np.max(np.abs(a[name] - b[name])))
            if d > 1e-9 * max(1.0, float(np.max(np.abs(a[name])))):
                c.add("level-mismatch", f"hr and {lvl} {name} differ (max |diff| {d:.3g})", frame=frame,
                      key=lvl, max_diff=d)
        s = h["scales"][lvl]
        for name in ("intrinsics", "prev_intrinsics"):
            expect = a[name] / s
            d = float(np.max(np.abs(b[name] - expect)))
            if d > 1e-6 * float(np.max(np.abs(expect))):
                c.add("level-mismatch", f"{lvl} {name} {b[name].tolist()} != hr {name} / {s:g} = "
                                        f"{expect.tolist()} (max |diff| {d:.3g} px)", frame=frame, key=lvl,
                      max_diff=d)
    return cams

"""Checks of the frame records: cameras (4x4 rigid), intrinsics (positive focal), jitter in [-0.5, 0.5] px, spp,
seed, seconds; every level describes the same camera (an LR level's intrinsics = hr intrinsics / its scale); every
record belongs to the render the header describes (its spp and Cycles seeds, ``check_against_header``) and its
previous camera is the camera of the frame before (a clip never mixes frames of two renders)."""
from __future__ import annotations

import numpy as np

from ..conventions import pass_seed
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
        cam = _level_camera(c, frame, lvl, r)
        _check_record_numbers(c, frame, lvl, r)
        if cam is not None:
            cams[lvl] = cam
    if "hr" in cams:
        for lvl in (k for k in cams if k != "hr"):
            _check_level_cameras(c, frame, lvl, cams["hr"], cams[lvl], h["scales"][lvl])
    return cams


def _level_camera(c: Collector, frame: int, lvl: str, r: dict) -> dict | None:
    """One level's poses, intrinsics and jitter as arrays; None when a pose or intrinsics is missing or unusable
    (reported; a jitter out of range is reported and left out)."""
    cam, ok = {}, True
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
    return cam if ok else None


def _check_record_numbers(c: Collector, frame: int, lvl: str, r: dict) -> None:
    """A level record's spp (a positive integer), seed (an integer) and seconds (a number or timings)."""
    if "spp" in r and (as_int(r["spp"]) is None or as_int(r["spp"]) < 1):
        c.add("bad-record", f"spp {r['spp']!r} is not a positive integer", frame=frame, key=lvl)
    if "seed" in r and as_int(r["seed"]) is None:
        c.add("bad-record", f"seed {r['seed']!r} is not an integer", frame=frame, key=lvl)
    if "seconds" in r and not (isinstance(r["seconds"], dict) or r["seconds"] is None
                               or (isinstance(r["seconds"], (int, float))
                                   and not isinstance(r["seconds"], bool))):
        c.add("bad-record", f"seconds {r['seconds']!r} is not a number or an object of timings",
                 frame=frame, key=lvl)


def _check_level_cameras(c: Collector, frame: int, lvl: str, a: dict, b: dict, s: float) -> None:
    """An LR level's camera against HR's: the same poses, the intrinsics divided by the level's scale ``s``."""
    for name in ("world_from_camera", "prev_world_from_camera"):
        d = float(np.max(np.abs(a[name] - b[name])))
        if d > 1e-9 * max(1.0, float(np.max(np.abs(a[name])))):
            c.add("level-mismatch", f"hr and {lvl} {name} differ (max |diff| {d:.3g})", frame=frame,
                  key=lvl, max_diff=d)
    for name in ("intrinsics", "prev_intrinsics"):
        expect = a[name] / s
        d = float(np.max(np.abs(b[name] - expect)))
        if d > 1e-6 * float(np.max(np.abs(expect))):
            c.add("level-mismatch", f"{lvl} {name} {b[name].tolist()} != hr {name} / {s:g} = "
                                    f"{expect.tolist()} (max |diff| {d:.3g} px)", frame=frame, key=lvl,
                  max_diff=d)


def _header_spp(render: dict, part: str) -> int | None:
    v = render.get(part)
    return as_int(v.get("spp")) if isinstance(v, dict) else None


def check_against_header(c: Collector, frame: int, rec: dict, h: dict, render: dict, prev: dict | None) -> None:
    """A frame record from another render than the header's (a mixed clip: two renders wrote one folder) is an
    error: every level's ``spp`` must be the header's (``render.hr.spp``, ``render.lr.spp``), its Cycles ``seed``
    ``conventions.pass_seed(render.seed, frame, pass)`` (pass 0: the HR G-buffer, 1: HR, 2 + i: the i-th LR level)
    and, when the frame before is finished too (``prev``: its record), its ``prev_world_from_camera`` and
    ``prev_intrinsics`` the ``world_from_camera`` and ``intrinsics`` of that frame. Headers without ``render.seed``
    or spp (synthetic clips) skip those checks."""
    render = render if isinstance(render, dict) else {}
    seed = as_int(render.get("seed"))
    lr_levels = [lvl for lvl in h["sizes"] if lvl != "hr"]
    hint = "the frame comes from another render (a mixed clip); render the clip again into an empty folder"
    for lvl in h["sizes"]:
        r = rec.get(lvl)
        if not isinstance(r, dict):
            continue
        part = "hr" if lvl == "hr" else "lr"
        want = _header_spp(render, part)
        got = as_int(r.get("spp"))
        if want is not None and got is not None and got != want:
            c.add("mixed-clip", f"{lvl} record says {got} spp but the header's render.{part}.spp is {want}: {hint}",
                  frame=frame, key=lvl)
        if seed is None:
            continue
        seeds = [("seed", 1 if lvl == "hr" else 2 + lr_levels.index(lvl))]
        if lvl == "hr" and r.get("gbuffer_seed") is not None:
            seeds.append(("gbuffer_seed", 0))
        for name, pass_index in seeds:
            got = as_int(r.get(name))
            expect = pass_seed(seed, frame, pass_index)
            if got is not None and got != expect:
                c.add("mixed-clip", f"{lvl} {name} {got} is not frame {frame}'s seed under the header's render.seed "
                                    f"{seed} ({expect}): {hint}", frame=frame, key=lvl)
    if not isinstance(prev, dict):
        return
    for lvl in h["sizes"]:
        r, p = rec.get(lvl), prev.get(lvl)
        if not isinstance(r, dict) or not isinstance(p, dict):
            continue
        for mine, theirs, tol in (("prev_world_from_camera", "world_from_camera", 1e-6),
                                  ("prev_intrinsics", "intrinsics", 1e-6)):
            a, b = floats(r.get(mine)), floats(p.get(theirs))
            if a.shape != b.shape or a.size == 0 or not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
                continue  # malformed cameras are reported by check_record
            d = float(np.max(np.abs(a - b)))
            if d > tol * max(1.0, float(np.max(np.abs(b)))):
                c.add("mixed-clip", f"{lvl} {mine} differs from frame {frame - 1}'s {theirs} (max |diff| {d:.3g}): "
                                    f"{hint}", frame=frame, key=lvl, max_diff=d)

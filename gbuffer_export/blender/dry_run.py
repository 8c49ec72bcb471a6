"""``blendsr dataset --dry-run``'s planner (bpy layer): import each level of the spec once and plan every walk and
fly clip's camera as its dataset job would (the same configuration, geometry without sky meshes, rules, unit and
region: ``scene_setup.plan_scene_path``), without rendering. Per clip: the path it would take, or the reason it has
none and a fix that works for it (``level_cameras.suggest_fix``). Before that, every file the asset clips import
(their assets and clutter) is imported once as their jobs import it (``check_assets``), so that a file Blender
cannot import is found before the render, not hours into it."""
from __future__ import annotations

import logging
import tempfile
from pathlib import Path

from ..errors import BlendSRError

log = logging.getLogger(__name__)

LEVEL_KINDS = ("walk", "fly")


def plannable(job) -> bool:
    """A job whose camera the planner draws inside a level: a scene file's walk or fly clip."""
    return job.kind == "scene" and job.camera in LEVEL_KINDS


def _level(cfg, cache: dict):
    """(scene, its level geometry, the geometry's declared metres per unit) of ``cfg.scene``, loaded once."""
    from .render import load_scene
    from .render_setup import find_level, resolve_frames
    key = str(cfg.scene)
    if key not in cache:
        scene, info = load_scene(cfg)
        ll = find_level(cfg, scene, info, resolve_frames(cfg, scene)[0])
        cache.clear()  # loading a level replaces the previous one in Blender
        cache[key] = (scene, ll.level, ll.level.metres_per_unit)
    return cache[key]


def plan_job(job, cache: dict, tmp: Path) -> dict:
    """The dry run's record of one plannable job: ``{"id", "camera", "ok", ...}`` with the path's cell, move,
    frames, median view depth and unit, or the reason and a fix."""
    from .camera_paths import half_fov
    from .dataset_job import render_config
    from .level_cameras import PathError, suggest_fix
    from .render_setup import level_rules, resolve_frames
    from .scene_setup import LevelUnit, clip_plan, ensure_level_camera, plan_scene_path, spawn_points
    cfg = render_config(job, tmp / job.id)
    rec = {"id": job.id, "camera": job.camera, "scene": Path(job.asset).name,
           "cell": job.region["cell"] if job.region else None}
    try:
        scene, geom, declared = _level(cfg, cache)
    except BlendSRError as exc:
        return {**rec, "ok": False, "reason": str(exc), "fix": "check the file opens in Blender"}
    geom.metres_per_unit = declared  # each clip detects the unit afresh, as its own job does
    frames = resolve_frames(cfg, scene)
    fov = half_fov(scene, ensure_level_camera(scene).data)
    rules, region = level_rules(cfg), cfg.extra.get("region")
    try:
        clip = clip_plan(scene, job.camera, (frames[0], frames[-1]), cfg.seed, fov, region)
        path, unit = plan_scene_path(scene, geom, clip, rules, LevelUnit(cfg.unit_scale, cfg.scene))
    except PathError as exc:
        from .level_scale import resolve_unit_scale
        geom.metres_per_unit = declared
        unit = resolve_unit_scale(geom, cfg.unit_scale, cfg.scene, spawn_points(scene))
        fix = suggest_fix(geom, clip, rules, unit)
        return {**rec, "ok": False, "reason": str(exc), "fix": fix, "unit": unit.get("unit"),
                "metres_per_unit": unit["metres_per_unit"]}
    r = path.report
    return {**rec, "ok": True, "frames": len(path.eyes), "median_depth_m": round(r["median_depth_m"], 2),
            "speed_mps": round(r["speed_mps"], 3), "region_move": r.get("region_move"), "unit": unit.get("unit"),
            "metres_per_unit": unit["metres_per_unit"],
            "cells": (r.get("region") or {}).get("cells")}


def plan_jobs(jobs) -> list[dict]:
    """``plan_job`` for every plannable job, levels loaded once each (jobs grouped by file, in spec order)."""
    todo = [j for j in jobs if plannable(j)]
    order = {}
    for j in todo:
        order.setdefault(j.asset, []).append(j)
    out, cache = [], {}
    with tempfile.TemporaryDirectory(prefix="blendsr-dry-run-") as tmp:
        for group in order.values():
            for j in group:
                out.append(plan_job(j, cache, Path(tmp)))
    return out


def asset_files(jobs) -> list[str]:
    """Every file the ``kind = "assets"`` clips of ``jobs`` import (each one's asset and clutter), once, in order."""
    seen: dict[str, None] = {}
    for j in jobs:
        if j.kind == "assets":
            for path in (j.asset, *j.clutter):
                if path:
                    seen.setdefault(str(path), None)
    return list(seen)


def check_assets(files, report=None) -> list[dict]:
    """Import each file as a clip's job does (``assets.import_asset``: reference check, the glTF extensions BlendSR
    applies), each in a child process with the import limits (``import_sandbox.check_asset_in_child``: a crash, a
    hang or a hostile file stops that file only); per file ``{"asset", "ok", "objects"}`` or ``{"asset", "ok":
    False, "error"}``, each passed to ``report`` as soon as it is known."""
    from ..import_sandbox import check_asset_in_child
    out = []
    with tempfile.TemporaryDirectory(prefix="blendsr-asset-check-") as tmp:
        for path in files:
            try:
                rec = {"asset": path, "ok": True, "objects": check_asset_in_child(Path(path), Path(tmp))}
            except BlendSRError as exc:
                rec = {"asset": path, "ok": False, "error": str(exc).splitlines()[0]}
            out.append(rec)
            if report is not None:
                report(rec)
    return out


def describe_asset(rec: dict) -> str:
    """One line for an imported asset file."""
    if not rec["ok"]:
        error = rec["error"].removeprefix(f"{rec['asset']}: ")  # the error names the file too: once is enough
        return f"NO IMPORT {rec['asset']}: {error}"
    return f"IMPORTS {rec['asset']}: {rec['objects']} top-level object(s)"


def describe(rec: dict) -> str:
    """One line for a planned clip."""
    if not rec["ok"]:
        return f"NO PATH {rec['id']}: {rec['reason']}; fix: {rec['fix']}"
    move = rec.get("region_move")
    where = f" cell {tuple(rec['cell'])}" if rec.get("cell") is not None else ""
    if move:
        where += f" moved to {', '.join(str(tuple(c)) for c in move['to'])} ({move['reason']})"
    unit = f"{rec['unit']} ({rec['metres_per_unit']:g} m/unit)" if rec.get("unit") else \
        f"{rec['metres_per_unit']:g} m/unit"
    return (f"PATH {rec['id']}: {rec['camera']}{where}, {rec['frames']} eyes at {rec['speed_mps']:g} m/s, "
            f"median view depth {rec['median_depth_m']:g} m, unit {unit}")


"""A user's scene as it is (bpy layer): load a level file (``importers``: every format of the format table), check
it can render, pick its cameras, key cameras that move inside it, and choose Cycles' device (its light:
``lighting``).

BlendSR overrides only what its clip contract owns (size, samples, passes, camera, jitter); the world, lights,
materials, animation and visibility stay the file's. Every check is a one-line ``ConfigError`` naming the file
and the fix.
"""
from __future__ import annotations

from dataclasses import dataclass

import contextlib
import math
from pathlib import Path

import bpy
import numpy as np

from ..config import DEVICES, ConfigError
from ..typed_table import key_error
LEVEL_CAMERA_NAME = "BlendSR Level Camera"
#: Level cameras: a 24 mm lens on a 36 mm sensor (horizontal field of view 73.7 degrees, as games use).
LEVEL_LENS_MM = 24.0
GPU_TYPES = ("OPTIX", "CUDA", "HIP", "METAL", "ONEAPI")


# ----------------------------------------------------------------------------------------------
# Loading
# ----------------------------------------------------------------------------------------------

def load_scene_file(path: Path, allow_read=()):
    """Open or import ``path`` by the format table (``importers.load_level``: in a child process with limits, reading
    only its folder and ``allow_read``; a .blend as it is, every other format into an empty file; missing textures
    made neutral); returns (scene, report for the manifest's ``scene``)."""
    from .importers import load_level
    return load_level(Path(path), allow_read)


#: Renderable object types other than meshes (their geometry is not measured by ``geometry_summary``).
OTHER_GEOMETRY = ("CURVE", "SURFACE", "META", "FONT", "CURVES", "POINTCLOUD", "VOLUME")


def _mesh_box(mesh, world) -> tuple[int, int, int, np.ndarray | None]:
    """(vertices, faces, non-finite vertices, 8 x 3 world corners of the finite vertices' box or None)."""
    n = len(mesh.vertices)
    co = np.empty(n * 3, np.float64)
    mesh.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    ok = np.isfinite(co).all(axis=1)
    if not ok.any():
        return n, len(mesh.polygons), n, None
    lo, hi = co[ok].min(axis=0), co[ok].max(axis=0)
    corners = np.array([[(lo, hi)[(i >> k) & 1][k] for k in range(3)] + [1.0] for i in range(8)])
    return n, len(mesh.polygons), int((~ok).sum()), (np.asarray(world, np.float64) @ corners.T).T[:, :3]


def geometry_summary(scene):
    """The scene's renderable mesh geometry as ``scene_geometry.GeometrySummary`` (the meshes as stored, placed by
    their world matrices; curves, text, volumes and collection instancers only flagged as ``other``)."""
    from ..scene_geometry import GeometrySummary
    verts = faces = bad = 0
    boxes, other = [], False
    for ob in scene.objects:
        if ob.hide_render:
            continue
        if ob.type == "MESH" and ob.data is not None:
            n, f, b, box = _mesh_box(ob.data, ob.matrix_world)
            verts, faces, bad = verts + n, faces + f, bad + b
            if box is not None and f:
                boxes.append(box)
        elif ob.type in OTHER_GEOMETRY or (ob.type == "EMPTY" and ob.instance_type == "COLLECTION"):
            other = True
    pts = np.concatenate(boxes) if boxes else None
    ok = pts is not None and np.isfinite(pts).all()
    return GeometrySummary(verts, faces, bad, tuple(pts.min(axis=0)) if ok else None,
                           tuple(pts.max(axis=0)) if ok else None,
                           float(scene.unit_settings.scale_length or 1.0), other)


def check_scene_geometry(scene, path: Path) -> None:
    """ConfigError naming ``path`` when the scene's geometry is empty, degenerate, non-finite or absurdly large
    (``scene_geometry.geometry_problem``): refused before anything renders."""
    from ..scene_geometry import geometry_problem
    problem = geometry_problem(geometry_summary(scene))
    if problem:
        raise ConfigError(f"{path}: {problem}")


# ----------------------------------------------------------------------------------------------
# Cameras
# ----------------------------------------------------------------------------------------------

def scene_cameras(scene) -> list:
    """The file's camera objects in ``scene``, sorted by name (BlendSR's own left out)."""
    return sorted((ob for ob in scene.objects if ob.type == "CAMERA" and not ob.name.startswith("BlendSR ")),
                  key=lambda ob: ob.name)


def _names(cams, limit: int = 8) -> str:
    names = [c.name for c in cams]
    return ", ".join(names[:limit]) + (f" and {len(names) - limit} more" if len(names) > limit else "")


def pick_scene_camera(scene, choice: str, where, index: int = 0):
    """The camera ``choice`` names: ``scene`` (the active one), ``scene:NAME``, or ``scene:*`` (the active one,
    else the ``index``-th of the file's cameras by name, cycling)."""
    cams = scene_cameras(scene)
    name = choice.split(":", 1)[1] if ":" in choice else None
    if name and name != "*":
        ob = scene.objects.get(name)
        if ob is None or ob.type != "CAMERA":
            raise ConfigError(f"{where}: no camera named {name!r} in the scene"
                              + (f" (cameras: {_names(cams)})" if cams else " (it has no cameras)"))
        return ob
    if name == "*" and cams:
        return cams[index % len(cams)] if index or scene.camera is None else scene.camera
    if scene.camera is not None:
        return scene.camera
    if cams:
        raise ConfigError(f"{where}: the scene has {len(cams)} camera(s) but none is active ({_names(cams)}); "
                          "set camera_path scene:NAME or scene:*", key="camera_path")
    raise ConfigError(f"{where}: the scene has no camera; set camera_path walk, fly or orbit", key="camera_path")


def ensure_level_camera(scene):
    """The perspective camera ``BlendSR Level Camera`` (24 mm lens, 36 mm sensor), linked to ``scene``."""
    cam = bpy.data.objects.get(LEVEL_CAMERA_NAME)
    if cam is None or cam.type != "CAMERA":
        cam = bpy.data.objects.new(LEVEL_CAMERA_NAME, bpy.data.cameras.new(LEVEL_CAMERA_NAME))
    if cam.name not in scene.objects:
        scene.collection.objects.link(cam)
    cam.parent = None
    cam.constraints.clear()
    cam.scale = (1.0, 1.0, 1.0)
    d = cam.data
    d.type, d.lens_unit, d.lens, d.sensor_fit, d.sensor_width = "PERSP", "MILLIMETERS", LEVEL_LENS_MM, "AUTO", 36.0
    d.shift_x = d.shift_y = 0.0
    d.dof.use_dof = False
    return cam


def scene_fps(scene) -> float:
    return float(scene.render.fps) / float(scene.render.fps_base or 1.0)


@dataclass(frozen=True)
class LevelUnit:
    """A level's unit as asked (``unit_scale``: "auto", metres per unit or a unit name) and the file whose cues
    decide it when "auto" (its engine line; None: the scene's geometry alone); ``found``: the record
    ``level_scale.resolve_unit_scale`` gave for this geometry when it is already resolved (the render's unit
    stage), None to resolve it here."""
    scale: object = "auto"
    source: object = None
    found: dict | None = None


def make_level_camera(scene, kind: str, frames: tuple[int, int], seed: int, region=None, rules=None, geom=None,
                      unit: LevelUnit = LevelUnit()):
    """Key a ``kind`` ("walk" or "fly") path inside the level on frames ``start-1 .. end`` (``level_cameras``);
    returns (camera, report for the manifest). ``geom``: the level's geometry (default: every renderable object
    at the first frame; the renderer passes it without sky meshes, ``lighting.level_light``); its metres per unit
    are ``unit.scale`` ("auto": detected, ``level_scale``, and checked on the planned views; ``unit.source``: the
    level's file)."""
    from .camera_paths import half_fov, key_look_at
    from .level_geometry import from_scene

    start, end = int(frames[0]), int(frames[1])
    cam = ensure_level_camera(scene)
    cam.animation_data_clear()
    geom = geom if geom is not None else from_scene(scene, start)
    hfov, vfov = half_fov(scene, cam.data)
    path, found = plan_scene_path(scene, geom, clip_plan(scene, kind, frames, seed, (hfov, vfov), region), rules, unit)
    key_look_at(cam, np.arange(start - 1, end + 1), path.eyes, path.targets)
    lo, hi = geom.bounds()
    cam.data.clip_start = geom.units(0.05)
    cam.data.clip_end = max(float(np.linalg.norm(hi - lo)) * 1.1, geom.units(100.0))
    cam["blendsr_camera_path"] = kind
    cam["blendsr_camera_seed"] = int(seed)
    scene.camera = cam
    scene.frame_set(start)
    return cam, {**path.report, "hfov_deg": 2 * math.degrees(hfov), "lens_mm": LEVEL_LENS_MM,
                 "triangles": geom.n_triangles, "unit_scale": found}


def clip_plan(scene, kind: str, frames: tuple[int, int], seed: int, fov, region=None):
    """The ``level_cameras.ClipPlan`` of a clip on frames ``start .. end`` of ``scene`` (one eye before the first
    frame, at the scene's frame rate)."""
    from .level_cameras import ClipPlan
    return ClipPlan(kind, int(frames[1]) - int(frames[0]) + 2, scene_fps(scene), seed, tuple(fov), region)


def plan_scene_path(scene, geom, clip, rules=None, unit: LevelUnit = LevelUnit()):
    """(path, unit record) of a level camera in ``scene`` (``level_cameras.plan_in_unit``; ``clip``:
    ``clip_plan``; the unit resolved first unless ``unit.found`` holds it): what ``make_level_camera`` keys and
    ``blendsr dataset --dry-run`` reports, planned the same way."""
    from .level_cameras import PathRules, plan_in_unit
    found = unit.found
    if found is None:
        from .level_scale import resolve_unit_scale
        found = resolve_unit_scale(geom, unit.scale, unit.source, spawn_points(scene))
    return plan_in_unit(geom, clip, rules or PathRules(), found)


def spawn_points(scene) -> list:
    """World positions of the file's spawn points: objects named as a game names its player starts
    (``level_scale.SPAWN_NAMES``); their height over the floor is a unit cue."""
    import re
    from .level_scale import SPAWN_NAMES
    return [tuple(ob.matrix_world.translation) for ob in scene.objects
            if re.search(SPAWN_NAMES, ob.name, re.I) and not ob.name.startswith("BlendSR ")]


#: Bytes Cycles holds per triangle (vertices, normals, BVH nodes; measured order of magnitude for bpy 5.0).
BYTES_PER_TRIANGLE = 250


def scene_memory_bytes(scene) -> int:
    """Rough memory of ``scene`` in Cycles: its image textures (float images at 16 bytes a pixel, others 4) and
    its meshes' triangles (``BYTES_PER_TRIANGLE``; instances counted once per use)."""
    images = sum(im.size[0] * im.size[1] * (16 if im.is_float else 4) for im in bpy.data.images
                 if im.users and im.size[0] > 0)
    tris = 0
    for ob in scene.objects:
        if ob.type == "MESH" and not ob.hide_render and ob.data is not None:
            tris += sum(max(len(p.vertices) - 2, 0) for p in ob.data.polygons)
    return int(images + tris * BYTES_PER_TRIANGLE)


# ----------------------------------------------------------------------------------------------
# Device
# ----------------------------------------------------------------------------------------------

@contextlib.contextmanager
def _quiet_fds():
    """Silence file descriptors 1 and 2: probing a GPU backend that is absent makes Cycles print a warning
    ("CUEW initialization failed") into the terminal and its progress bars (BLENDSR_VERBOSE=1 keeps it)."""
    from .fds import captured
    with captured():
        yield


def _gpu_devices(kind: str) -> list:
    prefs = bpy.context.preferences.addons["cycles"].preferences
    with _quiet_fds():
        try:
            prefs.compute_device_type = kind
        except TypeError:  # this build has no such backend
            return []
        try:
            prefs.refresh_devices()
        except (AttributeError, RuntimeError):
            pass
        return [d for d in prefs.devices if d.type == kind]


def select_device(scene, requested: str) -> dict:
    """Set Cycles' device: ``cpu``, a GPU backend by name, or ``auto`` (the first backend of OptiX, CUDA, HIP,
    Metal, oneAPI that has a device, else the CPU). ConfigError when a named backend has no device."""
    if requested not in DEVICES:
        raise key_error("device", requested, f"choose one of {', '.join(DEVICES)}")
    from .devices import probe_devices
    probe_devices()  # once per process: Cycles' warnings about absent GPU libraries are dropped
    kinds = GPU_TYPES if requested == "auto" else (() if requested == "cpu" else (requested.upper(),))
    for kind in kinds:
        devs = _gpu_devices(kind)
        if devs:
            for d in bpy.context.preferences.addons["cycles"].preferences.devices:
                d.use = d.type == kind
            scene.cycles.device = "GPU"
            return {"device": kind, "names": [d.name for d in devs], "requested": requested}
    if requested not in ("auto", "cpu"):
        raise ConfigError(f"device {requested}: Cycles sees no {requested.upper()} device here; use cpu or auto",
                          key="device")
    scene.cycles.device = "CPU"
    return {"device": "CPU", "names": [_cpu_name()], "requested": requested}


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    import platform
    return platform.processor() or "CPU"

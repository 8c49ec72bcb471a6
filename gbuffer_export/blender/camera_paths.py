"""Seeded, collision-free camera animation framed from a scene's bounds (bpy layer).

Every path keys the camera's location and XYZ Euler rotation on every integer frame from ``start - 1`` to ``end``
with LINEAR interpolation, so evaluating the animation at an integer frame gives exactly the computed pose (up to
float32 storage) and the first frame's motion vectors are meaningful. Distances are in scene units; the framing is
normalised by the bounding sphere of the renderable geometry, so the same code frames a 7 cm toy and a 100 m building.

A mesh object whose custom property ``blendsr_ground`` is true, or that is flat, large and lowest (see
:func:`is_ground_box`), counts as ground: it is left out of the framing sphere, and cameras stay above it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import bpy
import numpy as np
from bpy_extras import anim_utils
from mathutils import Euler, Matrix
from ..errors import BlendSRError
from .materials import volume_domain

CAMERA_NAME = "BlendSR Camera"
CAMERA_KINDS = ("orbit", "walk")
GEOMETRY_TYPES = frozenset({"MESH", "CURVE", "SURFACE", "META", "FONT"})
GROUND_PROPERTY = "blendsr_ground"

#: Camera defaults: a 35 mm lens on a 36 mm sensor (horizontal field of view 54.4 degrees for landscape images).
LENS_MM = 35.0
SENSOR_MM = 36.0


@dataclass(frozen=True)
class Box:
    """World-space axis-aligned bounding box of one renderable object (or instance), scene units."""

    name: str
    lo: np.ndarray  # (3,) float64
    hi: np.ndarray  # (3,) float64
    ground: bool = False

    def union(self, other: "Box") -> "Box":
        return Box(self.name, np.minimum(self.lo, other.lo), np.maximum(self.hi, other.hi), self.ground or other.ground)


# ----------------------------------------------------------------------------------------------
# Bounds
# ----------------------------------------------------------------------------------------------

def _depsgraph(scene: bpy.types.Scene):
    if scene == bpy.context.scene:
        return bpy.context.evaluated_depsgraph_get()
    dg = scene.view_layers[0].depsgraph
    dg.update()
    return dg


def _renders(obj: bpy.types.Object) -> bool:
    if obj.hide_render:
        return False
    return not any(c.hide_render for c in obj.users_collection)


def object_boxes(scene: bpy.types.Scene) -> list[Box]:
    """World-space AABBs (of the evaluated, deformed geometry's local bounds) of every renderable geometry object
    and instance of ``scene`` at its current frame. Ground flags come from :func:`is_ground_box`."""
    dg = _depsgraph(scene)
    raw: list[tuple[str, np.ndarray, np.ndarray, bool]] = []
    for inst in dg.object_instances:
        ob = inst.object
        if ob.type not in GEOMETRY_TYPES:
            continue
        orig = ob.original
        if volume_domain(orig):   # fog: a medium, not a surface to frame or to keep clear of
            continue
        if not _renders(orig) or (inst.is_instance and inst.parent and not _renders(inst.parent.original)):
            continue
        corners = np.array([tuple(c) for c in ob.bound_box], dtype=np.float64)
        if not np.isfinite(corners).all():
            continue
        m = np.array(inst.matrix_world, dtype=np.float64)
        world = corners @ m[:3, :3].T + m[:3, 3]
        name = orig.name
        if inst.is_instance:
            name = f"{orig.name}@{inst.parent.original.name}#{'.'.join(map(str, inst.persistent_id))}"
        raw.append((name, world.min(axis=0), world.max(axis=0), bool(orig.get(GROUND_PROPERTY, False))))
    boxes = [Box(n, lo, hi, g) for n, lo, hi, g in raw]
    return [Box(b.name, b.lo, b.hi, b.ground or is_ground_box(b, boxes)) for b in boxes]


def is_ground_box(box: Box, boxes: list[Box]) -> bool:
    """Heuristic ground test: thin (height <= 2% of its larger side), covering at least 4x the floor area of the
    other objects' union, and not above their lowest point (within 1% of their extent)."""
    size = box.hi - box.lo
    if size[2] > 0.02 * max(size[0], size[1]) or max(size[0], size[1]) <= 0:
        return False
    others = [b for b in boxes if b is not box]
    if not others:
        return False
    lo = np.min([b.lo for b in others], axis=0)
    hi = np.max([b.hi for b in others], axis=0)
    ext = hi - lo
    area_others = max(ext[0], 1e-9) * max(ext[1], 1e-9)
    return bool(size[0] * size[1] >= 4.0 * area_others and box.hi[2] <= lo[2] + 0.01 * float(np.linalg.norm(ext)))


def scene_bounds(scene: bpy.types.Scene) -> tuple[np.ndarray, np.ndarray]:
    """(min_xyz, max_xyz), each a (3,) float64 array: world-space bounds of all renderable geometry of ``scene``
    (evaluated: modifiers, armatures and animation at the current frame). ValueError when there is none."""
    boxes = object_boxes(scene)
    if not boxes:
        raise BlendSRError(f"scene {scene.name!r} has no renderable geometry to frame")
    return np.min([b.lo for b in boxes], axis=0), np.max([b.hi for b in boxes], axis=0)


def clip_boxes(scene: bpy.types.Scene, frames: tuple[int, int], max_samples: int = 25) -> list[Box]:
    """Per-object boxes united over up to ``max_samples`` evenly spaced frames of ``start-1 .. end`` (moving objects
    sweep a larger box). Restores the scene's current frame."""
    start, end = frames
    keep = scene.frame_current
    samples = np.unique(np.round(np.linspace(start - 1, end, min(max_samples, end - start + 2))).astype(int))
    merged: dict[str, Box] = {}
    try:
        for f in samples:
            scene.frame_set(int(f))
            for b in object_boxes(scene):
                merged[b.name] = merged[b.name].union(b) if b.name in merged else b
    finally:
        scene.frame_set(keep)
    return list(merged.values())


def framing_sphere(boxes: list[Box]) -> tuple[np.ndarray, float]:
    """Centre (3,) and radius of the sphere around the union of the non-ground boxes (all boxes when every box is
    ground). The radius is at least 1e-6."""
    use = [b for b in boxes if not b.ground] or boxes
    if not use:
        raise BlendSRError("nothing to frame: the scene has no renderable geometry")
    lo = np.min([b.lo for b in use], axis=0)
    hi = np.max([b.hi for b in use], axis=0)
    return 0.5 * (lo + hi), max(0.5 * float(np.linalg.norm(hi - lo)), 1e-6)


def ground_height(boxes: list[Box]) -> float:
    """Top of the highest ground box; without ground, the lowest point of the geometry."""
    g = [b.hi[2] for b in boxes if b.ground]
    return float(max(g)) if g else float(min(b.lo[2] for b in boxes))


# ----------------------------------------------------------------------------------------------
# Keying
# ----------------------------------------------------------------------------------------------

def look_at_matrix(eye, target, roll: float = 0.0) -> Matrix:
    """3x3 rotation of a Blender camera (looks along its -Z, +Y up) at ``eye`` looking at ``target`` with world +Z
    up, rolled by ``roll`` radians about the view axis."""
    f = np.asarray(target, np.float64) - np.asarray(eye, np.float64)
    f /= np.linalg.norm(f)
    up = np.array([0.0, 0.0, 1.0])
    right = np.cross(f, up)
    if np.linalg.norm(right) < 1e-9:  # looking straight up or down
        right = np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, f)
    c, s = math.cos(roll), math.sin(roll)
    right, cam_up = c * right + s * cam_up, -s * right + c * cam_up
    return Matrix(np.stack([right, cam_up, -f], axis=1).tolist())


def continuous_eulers(matrices: list[Matrix]) -> np.ndarray:
    """XYZ Euler angles (N, 3) of rotation matrices, each chosen closest to the previous one (no 2*pi jumps)."""
    out, prev = [], None
    for m in matrices:
        e = m.to_euler("XYZ", prev) if prev is not None else m.to_euler("XYZ")
        out.append(tuple(e))
        prev = Euler(e, "XYZ")
    return np.array(out, dtype=np.float64)


def _channelbag(obj: bpy.types.ID, action_name: str):
    ad = obj.animation_data or obj.animation_data_create()
    old = ad.action
    ad.action = None
    if old is not None and old.users == 0:
        bpy.data.actions.remove(old)
    action = bpy.data.actions.new(action_name)
    ad.action = action
    slot = action.slots.new(id_type=obj.id_type, name=obj.name)
    ad.action_slot = slot
    return anim_utils.action_ensure_channelbag_for_slot(action, slot)


def key_channels(obj: bpy.types.ID, frames, channels: dict[str, np.ndarray], action_name: str | None = None) -> None:
    """Replace ``obj``'s animation by LINEAR keys: ``channels`` maps a data path (e.g. ``"location"``) to an
    (N, C) array of values at the N integer ``frames``."""
    frames = np.asarray(frames, dtype=np.float64)
    cb = _channelbag(obj, action_name or f"{obj.name} Action")
    for path, values in channels.items():
        values = np.asarray(values, dtype=np.float64)
        if values.ndim == 1:
            values = values[:, None]
        if values.shape[0] != frames.shape[0]:
            raise BlendSRError(f"{path}: {values.shape[0]} values for {frames.shape[0]} frames")
        for i in range(values.shape[1]):
            fc = cb.fcurves.new(path, index=i)
            fc.keyframe_points.add(len(frames))
            fc.keyframe_points.foreach_set("co", np.stack([frames, values[:, i]], axis=1).ravel().tolist())
            for kp in fc.keyframe_points:
                kp.interpolation = "LINEAR"
            fc.update()


def key_look_at(cam: bpy.types.Object, frames, eyes: np.ndarray, targets: np.ndarray, rolls=None) -> None:
    """Key ``cam`` (location + XYZ Euler, LINEAR) at integer ``frames`` to look from ``eyes[i]`` at ``targets[i]``."""
    rolls = np.zeros(len(eyes)) if rolls is None else np.asarray(rolls, np.float64)
    mats = [look_at_matrix(e, t, r) for e, t, r in zip(eyes, targets, rolls)]
    cam.rotation_mode = "XYZ"
    key_channels(cam, frames, {"location": np.asarray(eyes, np.float64), "rotation_euler": continuous_eulers(mats)})


# ----------------------------------------------------------------------------------------------
# Camera paths
# ----------------------------------------------------------------------------------------------

def _ensure_camera(scene: bpy.types.Scene) -> bpy.types.Object:
    cam = bpy.data.objects.get(CAMERA_NAME)
    if cam is None or cam.type != "CAMERA":
        cam = bpy.data.objects.new(CAMERA_NAME, bpy.data.cameras.new(CAMERA_NAME))
    if cam.name not in scene.objects:
        scene.collection.objects.link(cam)
    cam.parent = None
    cam.constraints.clear()
    cam.scale = (1.0, 1.0, 1.0)
    data = cam.data
    data.type = "PERSP"
    data.lens_unit = "MILLIMETERS"
    data.lens = LENS_MM
    data.sensor_fit = "AUTO"
    data.sensor_width = SENSOR_MM
    data.shift_x = data.shift_y = 0.0
    data.dof.use_dof = False
    return cam


def half_fov(scene: bpy.types.Scene, cam_data: bpy.types.Camera) -> tuple[float, float]:
    """(horizontal, vertical) half field of view in radians for the scene's render aspect (sensor fit AUTO)."""
    r = scene.render
    w = r.resolution_x * r.pixel_aspect_x
    h = r.resolution_y * r.pixel_aspect_y
    t = 0.5 * cam_data.sensor_width / cam_data.lens  # tan of the half angle along the larger side
    if w >= h:
        return math.atan(t), math.atan(t * h / w)
    return math.atan(t * w / h), math.atan(t)


def _inside_any(points: np.ndarray, boxes: list[Box], margin: float, floor: float) -> bool:
    """True when a point lies within ``margin`` of a non-ground box or less than ``margin`` above ``floor``."""
    if np.any(points[:, 2] < floor + margin):
        return True
    for b in boxes:
        if b.ground:
            inside = np.all((points >= b.lo - margin) & (points <= b.hi + margin), axis=1)
        else:
            inside = np.all((points > b.lo - margin) & (points < b.hi + margin), axis=1)
        if inside.any():
            return True
    return False


def _orbit(frames_all: np.ndarray, c: np.ndarray, radius: float, fit: float, floor: float, rng):
    start = frames_all[0] + 1
    dist = radius / math.sin(fit) * rng.uniform(0.85, 1.1)
    elev = math.radians(rng.uniform(12.0, 35.0))
    # Keep the eye above the ground even for flat scenes whose centre is close to it.
    min_z = floor + 0.1 * radius
    if c[2] + dist * math.sin(elev) < min_z:
        elev = math.asin(min(0.95, (min_z - c[2]) / dist))
    az0 = rng.uniform(0.0, 2.0 * math.pi)
    rate = math.radians(rng.uniform(0.5, 1.2)) * (1.0 if rng.random() < 0.5 else -1.0)  # per frame
    az = az0 + rate * (frames_all - start)
    eyes = c + dist * np.stack([math.cos(elev) * np.cos(az), math.cos(elev) * np.sin(az),
                                np.full_like(az, math.sin(elev))], axis=1)
    targets = np.repeat(c[None], len(frames_all), axis=0)
    return eyes, targets


def _walk_candidate(frames_all, c, radius, floor, rng, scale: float):
    """One seeded constant-speed walk: a wobbly loop around the centre whose radius dips towards it."""
    n = len(frames_all)
    speed = radius * rng.uniform(0.012, 0.022)           # scene units per frame
    r0 = radius * rng.uniform(1.0, 1.6) * scale
    a = rng.uniform(0.0, 0.35, size=2)
    ph = rng.uniform(0.0, 2.0 * math.pi, size=8)
    theta0 = rng.uniform(0.0, 2.0 * math.pi)
    turn = 1.0 if rng.random() < 0.5 else -1.0
    height = floor + radius * rng.uniform(0.35, 0.7)
    height = max(height, floor + 0.25 * radius)
    off = radius * rng.uniform(-0.15, 0.15, size=2)

    def curve(u):
        rho = r0 * (1.0 + a[0] * np.sin(2.0 * u + ph[0]) + a[1] * np.sin(3.0 * u + ph[1]))
        th = theta0 + turn * u
        z = height + 0.08 * radius * np.sin(1.5 * u + ph[2])
        return np.stack([c[0] + off[0] + rho * np.cos(th), c[1] + off[1] + rho * np.sin(th), z], axis=1)

    # Arc-length parametrisation so that the eye advances ``speed`` per frame.
    total = speed * (n - 1)
    u_max = 2.0 * math.pi
    while True:
        u = np.linspace(0.0, u_max, 4096 * int(math.ceil(u_max / (2 * math.pi))))
        p = curve(u)
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        if s[-1] >= total:
            break
        u_max *= 2.0
    uk = np.interp(np.arange(n) * speed, s, u)
    eyes = curve(uk)
    wander = radius * np.stack([0.25 * np.sin(0.7 * uk + ph[3]), 0.25 * np.sin(0.9 * uk + ph[4]),
                                0.12 * np.sin(1.1 * uk + ph[5])], axis=1)
    look = c + wander
    tangent = curve(uk + 1e-3) - curve(uk - 1e-3)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    ahead = eyes + radius * tangent
    ahead[:, 2] = look[:, 2]
    d = np.linalg.norm(look - eyes, axis=1)
    w = np.clip((d - 0.2 * radius) / (0.4 * radius), 0.0, 1.0)
    w = (w * w * (3.0 - 2.0 * w))[:, None]  # smoothstep: blends smoothly to looking ahead near the centre
    targets = w * look + (1.0 - w) * ahead

    # Dense samples between frames for the collision test.
    ud = np.interp(np.linspace(0.0, (n - 1) * speed, 8 * (n - 1) + 1), s, u)
    return eyes, targets, curve(ud)


def _walk(frames_all, c, radius, boxes, floor, rng, tries: int = 24):
    margin = 0.08 * radius
    for k in range(tries):
        scale = 1.0 + 0.1 * (k // 4)
        eyes, targets, dense = _walk_candidate(frames_all, c, radius, floor, rng, scale)
        if not _inside_any(dense, boxes, margin, floor):
            return eyes, targets
    # Fallback: widen a loop until it lies entirely outside the framing sphere (hence outside every non-ground box).
    eyes, targets, dense = _walk_candidate(frames_all, c, radius, floor, rng, 1.0)
    rho = np.linalg.norm(dense[:, :2] - c[:2], axis=1)
    grow = (radius + 2 * margin) / max(float(rho.min()), 1e-12)
    if grow > 1.0:
        eyes[:, :2] = c[:2] + (eyes[:, :2] - c[:2]) * grow
    return eyes, targets


def make_camera_path(scene: bpy.types.Scene, kind: str, frames: tuple[int, int], seed: int) -> bpy.types.Object:
    """Create (or reuse) the perspective camera ``"BlendSR Camera"``, key a seeded ``kind`` path ("orbit" or "walk")
    on every frame ``start-1 .. end``, set clipping from the bounds and make it ``scene.camera``.

    orbit: an arc around the centre of the framing sphere at a seeded elevation (12-35 degrees) and distance
    (the sphere fits the smaller field of view, x0.85-1.1), 0.5-1.2 degrees per frame, looking at the centre.
    walk: a constant-speed (1.2-2.2% of the sphere radius per frame) wobbly loop around and into the scene at a seeded
    eye height, with a smoothly wandering look-at target; every position (checked 8x per frame) stays 8% of the
    radius outside every object's box (united over the clip's frames) and above the ground.
    The same (scene, kind, frames, seed) gives the same keys."""
    if kind not in CAMERA_KINDS:
        raise BlendSRError(f"camera path {kind!r}: choose one of {', '.join(CAMERA_KINDS)}")
    start, end = int(frames[0]), int(frames[1])
    if end < start:
        raise BlendSRError(f"camera path frames {start}:{end}: end before start")
    cam = _ensure_camera(scene)
    old = cam.animation_data.action if cam.animation_data else None
    cam.animation_data_clear()
    if old is not None and old.users == 0:
        bpy.data.actions.remove(old)
    boxes = [b for b in clip_boxes(scene, (start, end)) if b.name != cam.name]
    if not boxes:
        raise BlendSRError(f"scene {scene.name!r} has no renderable geometry to frame")
    c, radius = framing_sphere(boxes)
    floor = ground_height(boxes)
    frames_all = np.arange(start - 1, end + 1)
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, CAMERA_KINDS.index(kind)])
    hfov, vfov = half_fov(scene, cam.data)
    if kind == "orbit":
        eyes, targets = _orbit(frames_all, c, radius, min(hfov, vfov), floor, rng)
    else:
        eyes, targets = _walk(frames_all, c, radius, boxes, floor, rng)
    key_look_at(cam, frames_all, eyes, targets)

    lo = np.min([b.lo for b in boxes], axis=0)
    hi = np.max([b.hi for b in boxes], axis=0)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    far = max(float(np.linalg.norm(corners[None] - eyes[:, None], axis=2).max()) * 1.1, 10.0 * radius)
    cam.data.clip_start = 0.02 * radius
    cam.data.clip_end = far
    cam["blendsr_camera_path"] = kind
    cam["blendsr_camera_seed"] = int(seed)
    scene.camera = cam
    return cam

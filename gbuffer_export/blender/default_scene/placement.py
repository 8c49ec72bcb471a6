"""Measuring a keyed mover against everything else in the scene, frame by frame (bpy layer over
``gbuffer_export.sweep``, which judges the candidate starts). Boxes are ``camera_paths.object_boxes``: the
evaluated (deformed, instanced, animated) geometry's world boxes, fog volumes left out."""
from __future__ import annotations

import bpy
import numpy as np
from mathutils import Vector

from ...conventions import Flag
from ..camera_paths import object_boxes
from ..materials import inspect_material, is_transmissive

#: The scene's custom property: the inclusive [first, last] frames a clip renders, on which placement is judged.
PLACED_FRAMES = "blendsr_placed_frames"
#: The scene's custom property: the names of what a family drew but found no room for (``left_out``).
LEFT_OUT = "blendsr_left_out"


def judged_frames(scene) -> range:
    """The frames placement is judged on: the scene's ``PLACED_FRAMES`` (default: its frame range)."""
    first, last = scene.get(PLACED_FRAMES, (scene.frame_start, scene.frame_end))
    return range(int(first), int(last) + 1)


def measure(scene, body, key) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per frame of ``judged_frames``: (``body``'s box relative to the start (0, 0), every other object's box
    (K, 2, 3), their ground flags (K,)), with ``body`` keyed by ``key((x, y, direction))`` at the origin heading +X
    (the caller keys it again where it goes). The scene is left at its start frame."""
    key((0.0, 0.0, 1.0))
    out = []
    for f in judged_frames(scene):
        scene.frame_set(int(f))
        boxes = object_boxes(scene)
        own = [np.stack([b.lo, b.hi]) for b in boxes if b.name == body.name]
        others = [b for b in boxes if b.name != body.name]
        out.append((own[0], np.array([np.stack([b.lo, b.hi]) for b in others]).reshape(-1, 2, 3),
                    np.array([b.ground for b in others], bool)))
    scene.frame_set(scene.frame_start)
    return out


def _see_through(ob, cache: dict) -> bool:
    """Whether a camera ray goes on through ``ob`` (evaluated): one of its materials is transmissive (glass) or cut
    by alpha (leaf cards, shards), ``materials.inspect_material``'s flags."""
    name = ob.original.name
    if name not in cache:
        mats = [s.material for s in ob.original.material_slots if s.material]
        infos = [(m, inspect_material(m, 0)) for m in mats]
        cache[name] = any(i.flags & int(Flag.ALPHA) or is_transmissive(m, i) for m, i in infos)
    return cache[name]


def _reaches(scene, dg, eye: np.ndarray, p: np.ndarray, cache: dict) -> bool:
    """Whether a ray from ``eye`` reaches ``p`` (within 1 cm) through glass and alpha-cut surfaces only."""
    origin, dist = eye, float(np.linalg.norm(p - eye))
    direction = (p - eye) / dist
    for _ in range(8):
        hit, loc, _, _, ob, _ = scene.ray_cast(dg, Vector(origin), Vector(direction), distance=dist + 0.01)
        loc = np.array(loc)
        if not hit or np.linalg.norm(loc - p) < 0.01:
            return bool(hit)
        if not _see_through(ob, cache):
            return False
        dist -= float(np.linalg.norm(loc - origin)) + 1e-3
        origin = loc + 1e-3 * direction
    return False


def seen_fraction(scene, body, frames, samples: int = 64) -> float:
    """The fraction of ``body``'s vertices (``samples`` of them, evenly by index) that the scene camera sees at
    ``frames``: inside its view, and the first opaque thing a ray from the camera meets (within 1 cm of the vertex;
    glass and alpha-cut surfaces let it on)."""
    from bpy_extras.object_utils import world_to_camera_view
    cam, seen, total, cache = scene.camera, 0, 0, {}
    if cam is None:
        return 1.0
    for f in frames:
        scene.frame_set(int(f))
        dg = bpy.context.evaluated_depsgraph_get()
        ev = body.evaluated_get(dg)
        mesh = ev.to_mesh()
        co = np.empty(3 * len(mesh.vertices))
        mesh.vertices.foreach_get("co", co)
        ev.to_mesh_clear()
        m = np.array(ev.matrix_world)
        pts = co.reshape(-1, 3)[:: max(1, len(co) // 3 // samples)] @ m[:3, :3].T + m[:3, 3]
        eye = np.array(cam.matrix_world.translation)
        for p in pts:
            total += 1
            u, v, depth = world_to_camera_view(scene, cam, Vector(p))
            if depth <= 0 or not (0 <= u <= 1 and 0 <= v <= 1):
                continue
            seen += _reaches(scene, dg, eye, p, cache)
    scene.frame_set(scene.frame_start)
    return seen / max(total, 1)


def unkey(obj) -> None:
    """Remove ``obj``'s animation and its action."""
    ad = obj.animation_data
    action = ad.action if ad else None
    obj.animation_data_clear()
    if action is not None and action.users == 0:
        bpy.data.actions.remove(action)


def remove(scene, rig, body) -> None:
    """Remove a mover that found no place (its objects, their data and the materials only it used), and record its
    name in the scene's ``LEFT_OUT``."""
    scene[LEFT_OUT] = [*scene.get(LEFT_OUT, []), body.name]
    unkey(rig)
    mesh, arm, mats = body.data, rig.data, [m for m in body.data.materials if m]
    bpy.data.objects.remove(body, do_unlink=True)
    bpy.data.objects.remove(rig, do_unlink=True)
    bpy.data.meshes.remove(mesh)
    bpy.data.armatures.remove(arm)
    for m in mats:
        if m.users == 0:
            bpy.data.materials.remove(m)

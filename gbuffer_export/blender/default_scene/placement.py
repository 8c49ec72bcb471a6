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


def _first_opaque(scene, dg, origin: np.ndarray, direction: np.ndarray, cache: dict):
    """The original name of the first thing a ray from ``origin`` along the unit ``direction`` meets that is not
    glass or cut by alpha (``_see_through``; it passes through at most 8 of those), or None."""
    for _ in range(8):
        hit, loc, _, _, ob, _ = scene.ray_cast(dg, Vector(origin), Vector(direction))
        if not hit:
            return None
        if not _see_through(ob, cache):
            return ob.original.name
        origin = np.array(loc) + 1e-3 * direction
    return None


def _camera_rays(scene, cam, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World origins and unit directions (N, 3) of the scene camera's rays through the view points ``uv`` (N, 2: 0..1
    from the left and from the bottom of the frame), perspective or orthographic."""
    tr, br, bl, tl = (np.array(v) for v in cam.data.view_frame(scene=scene))
    local = bl + uv[:, :1] * (br - bl) + uv[:, 1:] * (tl - bl)               # on the camera's frame plane
    m = np.array(cam.matrix_world)
    points = local @ m[:3, :3].T + m[:3, 3]
    if cam.data.type == "ORTHO":
        forward = -m[:3, 2] / np.linalg.norm(m[:3, 2])
        return points, np.broadcast_to(forward, points.shape)
    eye = m[:3, 3]
    rays = points - eye
    return np.broadcast_to(eye, points.shape), rays / np.linalg.norm(rays, axis=1, keepdims=True)


def _view_box(scene, cam, co: np.ndarray) -> tuple[float, float, float, float] | None:
    """The view-space box (u0, v0, u1, v1, within 0..1) of the world points ``co`` (N, 3) in front of the scene
    camera, or None when none is in view."""
    from bpy_extras.object_utils import world_to_camera_view
    uvd = np.array([tuple(world_to_camera_view(scene, cam, Vector(p))) for p in co])
    uvd = uvd[uvd[:, 2] > 0]
    if not len(uvd):
        return None
    lo, hi = np.clip(uvd[:, :2].min(axis=0), 0, 1), np.clip(uvd[:, :2].max(axis=0), 0, 1)
    return None if np.any(hi <= lo) else (lo[0], lo[1], hi[0], hi[1])


def frame_share(scene, body, frames, grid: tuple[int, int] = (128, 72)) -> float:
    """The share of the scene camera's frame (0..1) in which ``body`` is the first opaque surface (glass and alpha-cut
    surfaces let the ray on), mean over ``frames``: one ray through the centre of each cell of ``grid`` (columns,
    rows) of the frame, cast only within the box of ``body``'s evaluated vertices in view (the other cells cannot
    show it). What a clip shows of it, at the grid's resolution."""
    cam, cache, shares = scene.camera, {}, []
    if cam is None:
        return 1.0
    w, h = grid
    for f in frames:
        scene.frame_set(int(f))
        dg = bpy.context.evaluated_depsgraph_get()
        ev = body.evaluated_get(dg)
        mesh = ev.to_mesh()
        co = np.empty(3 * len(mesh.vertices))
        mesh.vertices.foreach_get("co", co)
        ev.to_mesh_clear()
        m = np.array(ev.matrix_world)
        box = _view_box(scene, cam, co.reshape(-1, 3) @ m[:3, :3].T + m[:3, 3])
        hits = 0
        if box is not None:
            i = np.arange(int(box[0] * w), min(w, int(np.ceil(box[2] * w))))
            j = np.arange(int(box[1] * h), min(h, int(np.ceil(box[3] * h))))
            uv = np.stack(np.meshgrid((i + 0.5) / w, (j + 0.5) / h), axis=-1).reshape(-1, 2)
            origins, dirs = _camera_rays(scene, cam, uv)
            hits = sum(_first_opaque(scene, dg, o, d, cache) == body.name for o, d in zip(origins, dirs))
        shares.append(hits / (w * h))
    scene.frame_set(scene.frame_start)
    return float(np.mean(shares)) if shares else 0.0


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

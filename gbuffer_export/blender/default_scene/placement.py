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


def _first_opaque(scene, dg, origin: np.ndarray, direction: np.ndarray, distance: float, cache: dict):
    """The original name of the first thing a ray from ``origin`` along the unit ``direction`` meets within
    ``distance`` that is not glass or cut by alpha (``_see_through``; it gives up after 8 of those), or None."""
    for _ in range(8):
        hit, loc, _, _, ob, _ = scene.ray_cast(dg, Vector(origin), Vector(direction), distance=distance)
        if not hit:
            return None
        if not _see_through(ob, cache):
            return ob.original.name
        step = float(np.dot(np.array(loc) - origin, direction)) + 1e-3
        origin, distance = origin + step * direction, distance - step
        if distance <= 0:
            return None
    return None


def _frame_plane(scene, cam) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The scene camera's world matrix (4, 4, scale removed) and, in its own space, its frame's bottom-left corner
    and the frame's right and up edges (``view_frame``: on the focal plane of a perspective camera)."""
    tr, br, bl, tl = (np.array(v) for v in cam.data.view_frame(scene=scene))
    return np.array(cam.matrix_world.normalized()), bl, br - bl, tl - bl


def _camera_rays(scene, cam, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World origins, unit directions (N, 3) and lengths (N,) of the scene camera's rays through the view points
    ``uv`` (N, 2: 0..1 from the left and from the bottom of the frame), from its near clipping plane to its far one,
    perspective or orthographic."""
    m, bl, right, up = _frame_plane(scene, cam)
    local = bl + uv[:, :1] * right + uv[:, 1:] * up
    near, far = cam.data.clip_start, cam.data.clip_end
    if cam.data.type == "ORTHO":
        local[:, 2] = -near
        forward = np.broadcast_to(-m[:3, 2], local.shape)
        return local @ m[:3, :3].T + m[:3, 3], forward, np.full(len(local), far - near)
    d = local / np.linalg.norm(local, axis=1, keepdims=True)              # camera space, from the eye
    t0, t1 = near / -d[:, 2], far / -d[:, 2]
    dirs = d @ m[:3, :3].T
    return m[:3, 3] + t0[:, None] * dirs, dirs, t1 - t0


def _view_box(scene, cam, co: np.ndarray) -> tuple[float, float, float, float] | None:
    """The view-space box (u0, v0, u1, v1, within 0..1, as ``world_to_camera_view`` measures) of the world points
    ``co`` (N, 3) beyond the scene camera's near plane; the whole frame when some lie nearer (a face from behind the
    camera may cross any of it); None when none is in view."""
    m, bl, right, up = _frame_plane(scene, cam)
    local = (co - m[:3, 3]) @ m[:3, :3]                                    # camera space
    depth = -local[:, 2]
    beyond = depth > cam.data.clip_start
    if not beyond.any():
        return None
    if not beyond.all():
        return 0.0, 0.0, 1.0, 1.0
    xy = local[:, :2] if cam.data.type == "ORTHO" else local[:, :2] * (-bl[2] / depth)[:, None]
    uv = (xy - bl[:2]) / np.array([right[0], up[1]])
    lo, hi = np.clip(uv.min(axis=0), 0, 1), np.clip(uv.max(axis=0), 0, 1)
    return None if np.any(hi <= lo) else (lo[0], lo[1], hi[0], hi[1])


def frame_share(scene, body, frames, grid: tuple[int, int] = (128, 72)) -> float:
    """The share of the scene camera's frame (0..1) in which ``body`` is the first opaque surface (glass and alpha-cut
    surfaces let the ray on), mean over ``frames``: one ray through the centre of each cell of ``grid`` (columns,
    rows) of the frame, cast only within the box of ``body``'s evaluated vertices in view (the other cells cannot
    show it). What a clip shows of it, at the grid's resolution; 1.0 in a scene without a camera (nothing to judge
    by)."""
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
            rays = zip(*_camera_rays(scene, cam, uv))
            hits = sum(_first_opaque(scene, dg, o, d, n, cache) == body.name for o, d, n in rays)
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

"""Measuring a keyed mover against everything else in the scene, frame by frame (bpy layer over
``gbuffer_export.sweep``, which judges the candidate starts). Boxes are ``camera_paths.object_boxes``: the
evaluated (deformed, instanced, animated) geometry's world boxes, fog volumes left out."""
from __future__ import annotations

import bpy
import numpy as np

from ..camera_paths import object_boxes


def measure(scene, frames, body, key) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per frame of ``frames``: (``body``'s box relative to the start (0, 0), every other object's box (K, 2, 3),
    their ground flags (K,)), with ``body`` keyed by ``key(start_xy, heading)`` at the origin heading +X (the
    caller keys it again where it goes). The scene is left at its start frame."""
    key((0.0, 0.0), np.pi / 2)
    out = []
    for f in frames:
        scene.frame_set(int(f))
        boxes = object_boxes(scene)
        own = [np.stack([b.lo, b.hi]) for b in boxes if b.name == body.name]
        others = [b for b in boxes if b.name != body.name]
        out.append((own[0], np.array([np.stack([b.lo, b.hi]) for b in others]).reshape(-1, 2, 3),
                    np.array([b.ground for b in others], bool)))
    scene.frame_set(scene.frame_start)
    return out


def unkey(obj) -> None:
    """Remove ``obj``'s animation and its action."""
    ad = obj.animation_data
    action = ad.action if ad else None
    obj.animation_data_clear()
    if action is not None and action.users == 0:
        bpy.data.actions.remove(action)


def remove(rig, body) -> None:
    """Remove a mover that found no place: its objects, their data and the materials only it used."""
    unkey(rig)
    mesh, arm, mats = body.data, rig.data, [m for m in body.data.materials if m]
    bpy.data.objects.remove(body, do_unlink=True)
    bpy.data.objects.remove(rig, do_unlink=True)
    bpy.data.meshes.remove(mesh)
    bpy.data.armatures.remove(arm)
    for m in mats:
        if m.users == 0:
            bpy.data.materials.remove(m)

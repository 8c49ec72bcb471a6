"""A procedural walking figure (bpy layer): the generator's animated character (``motion_character``), built in code
because nothing may be downloaded. One skinned mesh (legs, torso, arms and neck as lathed and swept tubes, a head, hands
and feet) deformed by an armature of 11 bones through an Armature modifier, with linear-blend weights across the
knees, elbows, waist and neck, so that its surface bends at the joints as a game character's does (not a set of rigid
parts). Its walk is keyed on every frame: the rig glides along its lane, the hips bob twice a cycle, the thighs swing,
the knees bend in the swing phase, the arms swing against the legs.

Units are metres. The figure is built ``height`` tall, standing on z = 0 at the origin and facing -Y in its rest
pose; its rig object turns it to face its walking direction. Every bone's rest direction is (anti)parallel to a world
axis and its roll is 0, so that a positive rotation about its local X moves a downward limb's tail toward +Y in
the rest frame (backward: the figure faces -Y); ``tests/render/test_scene_families.py`` checks it on the evaluated
mesh.
"""
from __future__ import annotations

import math

import bmesh
import bpy
import numpy as np
from mathutils import Vector

from ..camera_paths import key_channels
from .geometry import sphere

#: The bones for a figure 1 m tall: name -> (parent, head, tail); mirrored for ``.R`` (x -> -x).
_BONES_L = {
    "thigh.L": ("hips", (0.055, 0.0, 0.52), (0.055, 0.0, 0.28)),
    "shin.L": ("thigh.L", (0.055, 0.0, 0.28), (0.055, 0.0, 0.045)),
    "upperarm.L": ("spine", (0.135, 0.0, 0.81), (0.135, 0.0, 0.64)),
    "forearm.L": ("upperarm.L", (0.135, 0.0, 0.64), (0.135, 0.0, 0.47)),
}
BONES = {
    "hips": (None, (0.0, 0.0, 0.52), (0.0, 0.0, 0.62)),
    "spine": ("hips", (0.0, 0.0, 0.62), (0.0, 0.0, 0.84)),
    "head": ("spine", (0.0, 0.0, 0.84), (0.0, 0.0, 1.0)),
    **_BONES_L,
    **{k.replace(".L", ".R"): (p.replace(".L", ".R") if p.endswith(".L") else p, (-h[0], h[1], h[2]),
                                (-t[0], t[1], t[2])) for k, (p, h, t) in _BONES_L.items()},
}
#: Slot of each part's material: 0 skin, 1 shirt, 2 trousers.
SKIN, SHIRT, TROUSERS = 0, 1, 2


class Body:
    """The mesh under construction: a bmesh and each vertex's bone weights ({index: {bone: weight}})."""

    def __init__(self, height: float):
        self.bm, self.h, self.weights = bmesh.new(), height, {}

    def weigh(self, verts, weight_of) -> None:
        """Record ``weight_of(rest position in 1 m units)`` ({bone: w}) for each vertex of ``verts``."""
        self.bm.verts.index_update()
        for v in verts:
            self.weights[v.index] = weight_of(np.array(v.co) / self.h)


def _blend(s: float, joint: float, half: float, below: str, above: str) -> dict[str, float]:
    """Linear-blend weights across a joint at ``joint`` (half-width ``half``) along a limb parameter ``s``."""
    w = float(np.clip((s - joint + half) / (2 * half), 0.0, 1.0))
    return {k: v for k, v in ((below, 1.0 - w), (above, w)) if v > 0.0}


def _tube(body: Body, pts, radii, material: int, segments: int = 12, squash: float = 1.0) -> list:
    """A capped tube through ``pts`` (1 m units, (N, 3)) with ring radii ``radii``, its rings squashed to ``squash``
    of their depth along y; returns its vertices in creation order."""
    pts, h = np.asarray(pts, np.float64), body.h
    rings, made = [], []
    for i, (p, r) in enumerate(zip(pts, radii)):
        t = pts[min(i + 1, len(pts) - 1)] - pts[max(i - 1, 0)]
        t /= np.linalg.norm(t)
        u = np.cross(t, (0.0, 1.0, 0.0)) if abs(t[1]) < 0.9 else np.cross(t, (1.0, 0.0, 0.0))
        u /= np.linalg.norm(u)
        w = np.cross(t, u)
        ring = [body.bm.verts.new(tuple(h * (p + r * (math.cos(a) * u + squash * math.sin(a) * w))))
                for a in np.linspace(0.0, 2 * math.pi, segments, endpoint=False)]
        rings.append(ring)
        made += ring
    faces = [body.bm.faces.new((a[k], a[(k + 1) % segments], b[(k + 1) % segments], b[k]))
             for a, b in zip(rings[:-1], rings[1:]) for k in range(segments)]
    faces += [body.bm.faces.new(rings[0][::-1]), body.bm.faces.new(rings[-1])]
    for f in faces:
        f.smooth, f.material_index = True, material
    return made


def _ball(body: Body, center, radius: float, material: int, scale=(1.0, 1.0, 1.0)) -> list:
    """A UV sphere (1 m units) scaled by ``scale``; returns its vertices."""
    before = set(body.bm.verts)
    sphere(body.bm, (0.0, 0.0, 0.0), radius * body.h, 16, 10)
    made = [v for v in body.bm.verts if v not in before]
    for v in made:
        v.co = Vector(np.array(v.co) * scale + np.array(center) * body.h)
    for f in {f for v in made for f in v.link_faces}:
        f.material_index = material
    return made


def _limbs(body: Body) -> None:
    """Legs (thigh-shin blend across the knee, trousers) with feet, arms (upper-fore blend across the elbow, shirt
    sleeves) with hands."""
    for sx, side in ((1.0, "L"), (-1.0, "R")):
        leg = [(sx * 0.055, 0.0, z) for z in np.linspace(0.55, 0.045, 11)]
        verts = _tube(body, leg, np.interp(np.linspace(0.55, 0.045, 11), [0.045, 0.28, 0.55], [0.03, 0.042, 0.065]),
                      TROUSERS)
        body.weigh(verts, lambda p: _blend(-p[2], -0.28, 0.035, f"thigh.{side}", f"shin.{side}"))
        body.weigh(_ball(body, (sx * 0.055, -0.03, 0.02), 0.035, TROUSERS, (0.8, 1.9, 0.6)),
                   lambda p: {f"shin.{side}": 1.0})
        arm = [(sx * 0.135, 0.0, z) for z in np.linspace(0.82, 0.47, 9)]
        verts = _tube(body, arm, np.interp(np.linspace(0.82, 0.47, 9), [0.47, 0.64, 0.82], [0.022, 0.028, 0.036]),
                      SHIRT)
        body.weigh(verts, lambda p: _blend(-p[2], -0.64, 0.03, f"upperarm.{side}", f"forearm.{side}"))
        body.weigh(_ball(body, (sx * 0.135, 0.0, 0.445), 0.03, SKIN, (0.8, 0.6, 1.2)),
                   lambda p: {f"forearm.{side}": 1.0})


def _trunk(body: Body) -> None:
    """Torso (hips-spine blend at the waist, shoulder blend into the upper arms), neck and head."""
    zs = np.linspace(0.5, 0.84, 10)
    radii = np.interp(zs, [0.5, 0.56, 0.63, 0.74, 0.81, 0.84], [0.095, 0.1, 0.09, 0.105, 0.12, 0.08])
    verts = _tube(body, [(0.0, 0.0, z) for z in zs], radii, SHIRT, segments=16, squash=0.6)

    def torso(p):
        w = _blend(p[2], 0.62, 0.04, "hips", "spine")
        if p[2] > 0.77 and abs(p[0]) > 0.08:                 # the shoulders follow the upper arms a little
            w = {k: v * 0.7 for k, v in w.items()}
            w["upperarm.L" if p[0] > 0 else "upperarm.R"] = 0.3
        return w
    body.weigh(verts, torso)
    verts = _tube(body, [(0.0, 0.0, 0.83), (0.0, 0.0, 0.9)], [0.035, 0.032], SKIN, segments=10)
    body.weigh(verts, lambda p: _blend(p[2], 0.85, 0.02, "spine", "head"))
    body.weigh(_ball(body, (0.0, -0.005, 0.935), 0.065, SKIN, (0.85, 1.0, 1.15)), lambda p: {"head": 1.0})


def _armature(scene, name: str, height: float):
    """The rig object (its armature's bones of ``BONES`` scaled to ``height``), linked to ``scene``."""
    arm = bpy.data.armatures.new(name)
    rig = bpy.data.objects.new(name, arm)
    scene.collection.objects.link(rig)
    bpy.context.view_layer.objects.active = rig
    bpy.ops.object.mode_set(mode="EDIT")
    for bone, (parent, head, tail) in BONES.items():
        eb = arm.edit_bones.new(bone)
        eb.head, eb.tail, eb.roll = Vector(head) * height, Vector(tail) * height, 0.0
        if parent:
            eb.parent = arm.edit_bones[parent]
    bpy.ops.object.mode_set(mode="OBJECT")
    for pb in rig.pose.bones:
        pb.rotation_mode = "XYZ"
    return rig


def build_figure(scene, name: str, height: float, materials) -> tuple:
    """(rig, body): the armature object and its skinned mesh (parented to it, materials skin, shirt, trousers)."""
    rig = _armature(scene, f"{name} Rig", height)
    body = Body(height)
    _limbs(body)
    _trunk(body)
    mesh = bpy.data.meshes.new(name)
    body.bm.to_mesh(mesh)
    body.bm.free()
    for m in materials:
        mesh.materials.append(m)
    obj = bpy.data.objects.new(name, mesh)
    scene.collection.objects.link(obj)
    groups = {b: obj.vertex_groups.new(name=b) for b in BONES}
    for i, ws in body.weights.items():
        for bone, w in ws.items():
            groups[bone].add([i], w, "REPLACE")
    obj.parent = rig
    obj.modifiers.new("Armature", "ARMATURE").object = rig
    return rig, obj


def key_walk(rig, frames, start_xy, heading: float, m_per_frame: float, height: float, angles: dict, phase: float):
    """Key the walk on ``frames``: the rig glides from ``start_xy`` along ``heading`` (radians about +Z, 0 = the rest
    pose's -Y) at ``m_per_frame``, one cycle (two steps) per 1.1 ``height`` m; ``angles`` (radians): ``swing`` (thigh
    amplitude), ``knee`` (largest knee bend), ``arm`` (upper-arm amplitude)."""
    t = np.asarray(frames, np.float64) - frames[0]
    dist = m_per_frame * t
    ph = 2 * math.pi * dist / (1.1 * height) + phase
    fwd = np.array([math.sin(heading), -math.cos(heading)])
    xy = np.asarray(start_xy) + np.outer(dist, fwd)
    z = 0.012 * height * (1 - np.cos(2 * ph)) / 2                       # the hips rise twice a cycle
    zeros = np.zeros_like(t)
    chans = {"location": np.column_stack([xy, z])}
    for side, sign in (("L", 1.0), ("R", -1.0)):
        s = np.sin(ph + (0.0 if sign > 0 else math.pi))
        swing_fwd = -angles["swing"] * s                                  # negative about X: the leg forward
        knee = angles["knee"] * np.clip(np.sin(ph + (0.0 if sign > 0 else math.pi) + math.pi / 2), 0.0, 1.0) + 0.05
        chans[f'pose.bones["thigh.{side}"].rotation_euler'] = np.column_stack([swing_fwd, zeros, zeros])
        chans[f'pose.bones["shin.{side}"].rotation_euler'] = np.column_stack([knee, zeros, zeros])
        chans[f'pose.bones["upperarm.{side}"].rotation_euler'] = np.column_stack([angles["arm"] * s, zeros,
                                                                                   zeros])
        chans[f'pose.bones["forearm.{side}"].rotation_euler'] = np.column_stack(
            [-0.25 - 0.15 * np.clip(s, 0.0, 1.0), zeros, zeros])
    chans['pose.bones["spine"].rotation_euler'] = np.column_stack([zeros, zeros, 0.08 * np.sin(ph)])
    rig.rotation_mode = "XYZ"
    rig.rotation_euler = (0.0, 0.0, heading)
    key_channels(rig, frames, chans)

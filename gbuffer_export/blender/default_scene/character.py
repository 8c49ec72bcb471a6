"""A procedural walking figure (bpy layer): the generator's animated character (``motion_character``), built in code
because nothing may be downloaded. One skinned mesh (legs, torso, arms and neck as swept tubes, a head, hands and
feet) deformed by an armature of 13 bones through an Armature modifier, with linear-blend weights across the knees,
elbows, waist, shoulders and neck, so that its surface bends at the joints as a game character's does (not a set of
rigid parts). Its walk is keyed on every frame: the rig glides along its lane and two-bone IK (``leg_ik``) places
the legs: the stance leg straight with its foot put (the hips drop as the legs spread, and the cycle is as long as
the stance foot's travel), the swinging foot lifted and carried forward with the knee bent; the feet stay level,
the arms swing against the legs and the shoulders turn a little (``key_walk``).

Units are metres. The figure is built ``height`` tall, standing on z = 0 at the origin and facing -Y in its rest
pose; its rig object turns it to face its walking direction. Every bone's rest direction is vertical and its roll 0,
so its local X is the rig's +X and a positive rotation about it moves a downward limb's tail toward +Y (backward:
the figure faces -Y).
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
    "foot.L": ("shin.L", (0.055, 0.0, 0.045), (0.055, 0.0, 0.0)),
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
#: The thigh's and the shin's length, the leg's (hip joint to ankle) and the lateral half-width (shoulder and arm) of a
#: figure 1 m tall.
THIGH, SHIN = 0.24, 0.235
LEG, HALF_WIDTH = THIGH + SHIN, 0.18


class Body:
    """The mesh under construction: a bmesh and each vertex's bone weights ({BMVert: {bone: weight}}; bmesh may
    renumber its vertices while parts are added, so they are resolved to indices only once it is complete)."""

    def __init__(self, height: float):
        self.bm, self.h, self.weights = bmesh.new(), height, {}

    def weigh(self, verts, weight_of) -> None:
        """Record ``weight_of(rest position in 1 m units)`` ({bone: w}) for each vertex of ``verts``."""
        for v in verts:
            self.weights[v] = weight_of(np.array(v.co) / self.h)

    def indexed(self) -> dict[int, dict[str, float]]:
        """The weights by vertex index of the complete mesh (the order ``to_mesh`` keeps)."""
        self.bm.verts.index_update()
        return {v.index: w for v, w in self.weights.items()}


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
                   lambda p: {f"foot.{side}": 1.0})
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
    body.weigh(_ball(body, (0.0, -0.005, 0.925), 0.065, SKIN, (0.85, 1.0, 1.15)), lambda p: {"head": 1.0})


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
    weights = body.indexed()
    mesh = bpy.data.meshes.new(name)
    body.bm.to_mesh(mesh)
    body.bm.free()
    for m in materials:
        mesh.materials.append(m)
    obj = bpy.data.objects.new(name, mesh)
    scene.collection.objects.link(obj)
    groups = {b: obj.vertex_groups.new(name=b) for b in BONES}
    for i, ws in weights.items():
        for bone, w in ws.items():
            groups[bone].add([i], w, "REPLACE")
    obj.parent = rig
    obj.modifiers.new("Armature", "ARMATURE").object = rig
    return rig, obj


def _tri(x: np.ndarray) -> np.ndarray:
    """A triangle wave in [-1, 1] with the phase of sin(x)."""
    return 2.0 / math.pi * np.arcsin(np.sin(x))


def leg_ik(forward: np.ndarray, down: np.ndarray, thigh: float, shin: float) -> tuple[np.ndarray, np.ndarray]:
    """(thigh angle, knee bend), radians about the bones' X (positive: backward), that put the ankle ``forward`` and
    ``down`` of the hip joint (the law of cosines; the knee bends backward, a target out of reach is clamped to the
    straight leg)."""
    r = np.minimum(np.hypot(forward, down), thigh + shin)
    knee = math.pi - np.arccos(np.clip((thigh ** 2 + shin ** 2 - r ** 2) / (2 * thigh * shin), -1.0, 1.0))
    at_hip = np.arccos(np.clip((thigh ** 2 + r ** 2 - shin ** 2) / (2 * thigh * r), -1.0, 1.0))
    return np.arctan2(-forward, down) - at_hip, knee


def key_walk(rig, frames, start_xy, heading: float, m_per_frame: float, height: float, angles: dict, phase: float):
    """Key the walk on ``frames``: the rig glides from ``start_xy`` along ``heading`` (radians about +Z, 0 = the rest
    pose's -Y) at ``m_per_frame``; ``angles`` (radians): ``swing`` (the thighs' largest angle), ``knee`` (the knee's
    bend mid-swing), ``arm`` (the upper arms' largest angle). Each ankle's forward offset from the hips is a triangle
    wave of amplitude LEG sin(swing); in stance it moves back at a constant rate, which the cycle length
    4 LEG sin(swing) matches to the rig's speed, so the stance foot stays put. The hips drop by LEG (1 - cos(stance
    thigh angle)), so the straight stance leg keeps its ankle at the rest height; the swinging ankle rises by
    c cos(x) over its swing (x its phase, c the rise at which the knee bends by ``knee`` mid-swing), and ``leg_ik``
    places both legs."""
    t = np.asarray(frames, np.float64) - frames[0]
    leg, reach = LEG * height, LEG * height * math.sin(angles["swing"])
    ph = 2 * math.pi * m_per_frame * t / (4 * reach) + phase
    fwd = np.array([math.sin(heading), -math.cos(heading)])
    hips = leg * np.cos(np.arcsin(math.sin(angles["swing"]) * _tri(ph)))     # hip joint over the stance ankle
    rise = leg - height * math.sqrt(THIGH ** 2 + SHIN ** 2 + 2 * THIGH * SHIN * math.cos(angles["knee"]))
    zeros = np.zeros_like(t)
    chans = {}
    for side, offset in (("L", 0.0), ("R", math.pi)):
        x = ph + offset
        u = _tri(x)                                                          # the ankle forward at +1
        thigh, knee = leg_ik(reach * u, hips - rise * np.clip(np.cos(x), 0.0, None), THIGH * height, SHIN * height)
        for bone, angle in ((f"thigh.{side}", thigh), (f"shin.{side}", knee), (f"foot.{side}", -thigh - knee),
                            (f"upperarm.{side}", angles["arm"] * u),        # back while the leg is forward
                            (f"forearm.{side}", -0.25 - 0.2 * np.clip(-u, 0.0, 1.0))):
            chans[f'pose.bones["{bone}"].rotation_euler'] = np.column_stack([angle, zeros, zeros])
    chans['pose.bones["spine"].rotation_euler'] = np.column_stack([zeros, 0.08 * _tri(ph), zeros])  # a turn
    chans["location"] = np.column_stack([np.asarray(start_xy) + np.outer(m_per_frame * t, fwd), hips - leg])
    rig.rotation_mode = "XYZ"
    rig.rotation_euler = (0.0, 0.0, heading)
    key_channels(rig, frames, chans)

"""Mesh building blocks of the default scene (bmesh, no operators): boxes, cylinders, spheres, lathed profiles,
prisms, tubes along polylines, catenaries, extruded text, and the objects that hold them. Units are metres."""
from __future__ import annotations

import math

import bmesh
import bpy
import numpy as np
from mathutils import Matrix, Vector


def box(bm, center, size, rot_z: float = 0.0) -> None:
    """Box of ``size`` (x, y, z) centred at ``center``, turned by ``rot_z`` radians about +Z."""
    mat = Matrix.LocRotScale(Vector(center), Matrix.Rotation(rot_z, 3, "Z").to_quaternion(), Vector(size))
    bmesh.ops.create_cube(bm, size=1.0, matrix=mat)


def cylinder(bm, center, radius, depth, segments=12, axis="Z") -> None:
    """Capped cylinder; sides smooth, caps flat."""
    rot = {"Z": Matrix.Identity(3), "X": Matrix.Rotation(math.pi / 2, 3, "Y"),
           "Y": Matrix.Rotation(math.pi / 2, 3, "X")}[axis]
    mat = Matrix.Translation(Vector(center)) @ rot.to_4x4()
    res = bmesh.ops.create_cone(bm, cap_ends=True, cap_tris=False, segments=segments, radius1=radius,
                                radius2=radius, depth=depth, matrix=mat)
    faces = {f for v in res["verts"] for f in v.link_faces}
    for f in faces:
        f.smooth = len(f.verts) == 4


def sphere(bm, center, radius, u=48, v=24) -> None:
    res = bmesh.ops.create_uvsphere(bm, u_segments=u, v_segments=v, radius=radius,
                                    matrix=Matrix.Translation(Vector(center)))
    for f in {f for vv in res["verts"] for f in vv.link_faces}:
        f.smooth = True


def lathe(bm, profile, center=(0.0, 0.0, 0.0), segments=48, closed=False) -> None:
    """Surface of revolution about +Z of a (radius, z) polyline; radius-0 points become poles. ``closed`` joins the
    last profile point back to the first."""
    cx, cy, cz = center
    rings = []
    for r, z in profile:
        if r <= 0.0:
            rings.append([bm.verts.new((cx, cy, cz + z))])
        else:
            rings.append([bm.verts.new((cx + r * math.cos(2 * math.pi * k / segments),
                                        cy + r * math.sin(2 * math.pi * k / segments), cz + z))
                          for k in range(segments)])
    pairs = list(zip(rings[:-1], rings[1:])) + ([(rings[-1], rings[0])] if closed else [])
    for a, b in pairs:
        for k in range(segments):
            k1 = (k + 1) % segments
            if len(a) == 1 and len(b) == 1:
                continue
            if len(a) == 1:
                verts = (a[0], b[k1], b[k])
            elif len(b) == 1:
                verts = (a[k], a[k1], b[0])
            else:
                verts = (a[k], a[k1], b[k1], b[k])
            bm.faces.new(verts).smooth = True
    bmesh.ops.recalc_face_normals(bm, faces=bm.faces[:])


def prism_xz(bm, outline, y0: float, y1: float) -> None:
    """Prism from a convex (x, z) outline (counter-clockwise seen from -Y), extruded from y0 to y1."""
    front = [bm.verts.new((x, y0, z)) for x, z in outline]
    back = [bm.verts.new((x, y1, z)) for x, z in outline]
    bm.faces.new(front[::-1])
    bm.faces.new(back)
    n = len(outline)
    for i in range(n):
        j = (i + 1) % n
        bm.faces.new((front[i], front[j], back[j], back[i]))
    bmesh.ops.recalc_face_normals(bm, faces=bm.faces[:])


def catenary(p0, p1, sag: float, n: int) -> np.ndarray:
    t = np.linspace(0.0, 1.0, n)
    pts = np.outer(1 - t, p0) + np.outer(t, p1)
    pts[:, 2] -= 4.0 * sag * t * (1 - t)
    return pts


def tube(bm, points: np.ndarray, radius: float, segments: int = 6) -> None:
    """A thin tube along a polyline (parallel-transported rings, open ends)."""
    rings = []
    ref = np.array([0.0, 0.0, 1.0])
    for i, p in enumerate(points):
        t = points[min(i + 1, len(points) - 1)] - points[max(i - 1, 0)]
        t /= np.linalg.norm(t)
        if abs(t @ ref) > 0.9:
            ref = np.array([1.0, 0.0, 0.0])
        u = np.cross(t, ref)
        u /= np.linalg.norm(u)
        w = np.cross(t, u)
        rings.append([bm.verts.new(tuple(p + radius * (math.cos(a) * u + math.sin(a) * w)))
                      for a in np.linspace(0, 2 * math.pi, segments, endpoint=False)])
    for a, b in zip(rings[:-1], rings[1:]):
        for k in range(segments):
            k1 = (k + 1) % segments
            bm.faces.new((a[k], a[k1], b[k1], b[k])).smooth = True


def add_object(scene, name: str, bm, material, location=(0.0, 0.0, 0.0), rotation=(0.0, 0.0, 0.0)):
    """A mesh object from ``bm`` (freed) with one material, linked to ``scene``."""
    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    return link_mesh(scene, name, mesh, material, location, rotation)


def link_mesh(scene, name: str, mesh, material, location, rotation):
    """An object of ``mesh`` with ``material`` as its only material, placed and linked to ``scene``."""
    mesh.materials.clear()
    mesh.materials.append(material)
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    obj.rotation_euler = rotation
    scene.collection.objects.link(obj)
    return obj


def text_object(scene, name: str, body: str, size: float, material, location, rotation, extrude=0.002):
    """Extruded text converted to a mesh object (the font curve is removed)."""
    curve = bpy.data.curves.new(name, "FONT")
    curve.body = body
    curve.size = size
    curve.extrude = extrude
    curve.align_x = "CENTER"
    curve.align_y = "CENTER"
    curve.space_line = 1.15
    tmp = bpy.data.objects.new(name + " (font)", curve)
    scene.collection.objects.link(tmp)
    dg = bpy.context.evaluated_depsgraph_get()
    mesh = bpy.data.meshes.new_from_object(tmp.evaluated_get(dg))
    mesh.name = name
    bpy.data.objects.remove(tmp)
    bpy.data.curves.remove(curve)
    return link_mesh(scene, name, mesh, material, location, rotation)

"""The built-in default scene: a small courtyard still life built in code (bpy layer).

A café table on a tiled courtyard floor in front of a picket fence with a wire-mesh panel, a brick wall, string
lights and a painted sign, with props chosen for what a super-resolution network finds hard: sub-pixel wires,
fine checkers, text and text-like stripes, mirror-like and rough metals, an anisotropic brushed pot, glass, a
subsurface candle, small emissive bulbs and a ball rolling across the table. Lit by one of the HDR environments that
ship inside bpy plus a sun. Units are metres; +Z is up; the camera looks roughly along +Y.

Everything is deterministic in ``seed``: the seed moves and turns the props a little, varies colours, picks the
environment, its rotation, the sun and the camera's motion. Nothing is written to disk; the render engine and its
sampling are left to the caller.
"""
from __future__ import annotations

import math
from pathlib import Path

import bmesh
import bpy
import numpy as np
from mathutils import Matrix, Vector

from .camera_paths import GROUND_PROPERTY, key_channels, key_look_at, look_at_matrix

#: Environments (files ``<name>.exr`` in bpy's ``studiolights/world``) the seed picks from.
STUDIOLIGHTS = ("courtyard", "forest", "sunset", "city", "sunrise")

TABLE_TOP_Z = 0.76  # m, height of the table's top surface

#: What the default scene holds, for docs and tests: feature -> names of the objects (or world) that carry it.
DEFAULT_SCENE_FEATURES: dict[str, tuple[str, ...]] = {
    "ground (stone tiles with thin grout lines)": ("Floor",),
    "fine checker (2 cm squares)": ("Placemat",),
    "text-like stripes (newspaper columns)": ("Newspaper",),
    "extruded text": ("Sign Letters",),
    "thin wires (1.8-2.5 mm radius)": ("Wire Mesh", "Light String"),
    "picket fence": ("Fence Pickets", "Fence Rails", "Fence Posts"),
    "brick wall": ("Brick Wall",),
    "dielectrics": ("Ceramic Bowl", "Red Cube", "Table", "Terracotta Pot", "Shrub", "Sign Board", "Rolling Ball"),
    "metal, roughness 0.05": ("Chrome Sphere",),
    "metal, roughness 0.3": ("Gold Dish",),
    "metal, roughness 0.6": ("Copper Cup",),
    "anisotropic metal": ("Brushed Pot",),
    "glass (transmission 1)": ("Glass Vase", "Glass Paperweight"),
    "emission": ("Light Bulbs",),
    "subsurface": ("Candle",),
    "moving object (rolling, keyed from start-1)": ("Rolling Ball",),
    "animated perspective camera (keyed from start-1)": ("Camera",),
    "sun lamp": ("Sun",),
    "HDR environment from bpy's studiolights": ("BlendSR World",),
}


def studiolight_path(name: str) -> Path:
    """Path of one of bpy's bundled HDR environments (e.g. ``"courtyard"``); FileNotFoundError if missing."""
    root = bpy.utils.system_resource("DATAFILES", path="studiolights/world")
    path = Path(root) / f"{name}.exr"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: bpy studiolight {name!r} not found")
    return path


# ----------------------------------------------------------------------------------------------
# Materials
# ----------------------------------------------------------------------------------------------

class _Mat:
    """A material whose surface is one Principled BSDF, with helpers to drive its inputs by procedural textures."""

    def __init__(self, name: str, color=(0.8, 0.8, 0.8), metallic: float = 0.0, roughness: float = 0.5,
                 inputs: dict | None = None):
        self.mat = bpy.data.materials.new(name)
        self.nt = self.mat.node_tree
        self.bsdf = self.nt.nodes["Principled BSDF"]
        self.set("Base Color", (*color, 1.0))
        self.set("Metallic", metallic)
        self.set("Roughness", roughness)
        for key, value in (inputs or {}).items():
            self.set(key, value)

    def set(self, socket: str, value) -> None:
        v = value
        if socket.endswith("Color") and len(v) == 3:
            v = (*v, 1.0)
        self.bsdf.inputs[socket].default_value = v

    def node(self, kind: str, **props):
        n = self.nt.nodes.new(kind)
        for k, v in props.items():
            if k in n.inputs:
                n.inputs[k].default_value = v
            else:
                setattr(n, k, v)
        return n

    def link(self, out, inp) -> None:
        self.nt.links.new(out, inp)

    def coords(self, scale=(1.0, 1.0, 1.0), swizzle: str | None = None):
        """Object-space coordinates (metres), scaled, optionally reordered (e.g. ``"YZX"`` maps (y, z, x) to the
        texture's (x, y, z))."""
        tc = self.node("ShaderNodeTexCoord")
        out = tc.outputs["Object"]
        if swizzle:
            sep = self.node("ShaderNodeSeparateXYZ")
            comb = self.node("ShaderNodeCombineXYZ")
            self.link(out, sep.inputs[0])
            for dst, src in zip("XYZ", swizzle):
                self.link(sep.outputs[src], comb.inputs[dst])
            out = comb.outputs[0]
        mp = self.node("ShaderNodeMapping")
        mp.inputs["Scale"].default_value = scale
        self.link(out, mp.inputs["Vector"])
        return mp.outputs["Vector"]

    def ramp(self, fac, stops, interpolation: str = "LINEAR"):
        """Colour ramp with ``stops`` [(position, (r, g, b)), ...]; returns its Color output."""
        r = self.node("ShaderNodeValToRGB")
        r.color_ramp.interpolation = interpolation
        els = r.color_ramp.elements
        while len(els) < len(stops):
            els.new(0.5)
        for el, (pos, col) in zip(els, stops):
            el.position = pos
            el.color = (*col, 1.0)
        self.link(fac, r.inputs["Factor"])
        return r.outputs["Color"]

    def map_range(self, value, lo: float, hi: float):
        m = self.node("ShaderNodeMapRange")
        m.inputs["To Min"].default_value = lo
        m.inputs["To Max"].default_value = hi
        self.link(value, m.inputs["Value"])
        return m.outputs["Result"]

    def math(self, op: str, a, b=0.0):
        m = self.node("ShaderNodeMath", operation=op)
        for sock, v in ((m.inputs[0], a), (m.inputs[1], b)):
            if isinstance(v, bpy.types.NodeSocket):
                self.link(v, sock)
            else:
                sock.default_value = v
        return m.outputs[0]

    def mix(self, fac, a, b):
        m = self.node("ShaderNodeMix", data_type="RGBA")
        for sock, v in ((m.inputs["Factor"], fac), (m.inputs[6], a), (m.inputs[7], b)):
            if isinstance(v, bpy.types.NodeSocket):
                self.link(v, sock)
            else:
                sock.default_value = v if len(v) == 4 else (*v, 1.0)
        return m.outputs[2]


def _jitter_color(rng, color, amount=0.06):
    return tuple(float(np.clip(c * (1.0 + rng.uniform(-amount, amount)), 0.0, 1.0)) for c in color)


def _materials(rng) -> dict[str, bpy.types.Material]:
    mats: dict[str, bpy.types.Material] = {}

    # Stone tiles (30 cm) with 6 mm grout, per-tile colour variation and grime.
    m = _Mat("Stone Tiles", roughness=0.7)
    brick = m.node("ShaderNodeTexBrick", offset=0.0, offset_frequency=1, squash=1.0, squash_frequency=1)
    for k, v in {"Color1": (*_jitter_color(rng, (0.36, 0.33, 0.30)), 1), "Color2": (0.52, 0.48, 0.42, 1),
                 "Mortar": (0.10, 0.10, 0.09, 1), "Scale": 1.0, "Mortar Size": 0.006, "Mortar Smooth": 0.15,
                 "Bias": 0.0, "Brick Width": 0.30, "Row Height": 0.30}.items():
        brick.inputs[k].default_value = v
    m.link(m.coords(), brick.inputs["Vector"])
    noise = m.node("ShaderNodeTexNoise", Scale=4.0, Detail=8.0, Roughness=0.6)
    m.link(m.coords(), noise.inputs["Vector"])
    grime = m.ramp(noise.outputs["Factor"], [(0.3, (0.75, 0.75, 0.75)), (0.7, (1.0, 1.0, 1.0))])
    col = m.node("ShaderNodeMix", data_type="RGBA", blend_type="MULTIPLY")
    col.inputs["Factor"].default_value = 1.0
    m.link(brick.outputs["Color"], col.inputs[6])
    m.link(grime, col.inputs[7])
    m.link(col.outputs[2], m.bsdf.inputs["Base Color"])
    m.link(m.map_range(brick.outputs["Factor"], 0.62, 0.95), m.bsdf.inputs["Roughness"])
    mats["floor"] = m.mat

    # Red brick wall: bricks run along the wall (object y) in rows up z.
    m = _Mat("Red Brick", roughness=0.85)
    brick = m.node("ShaderNodeTexBrick", offset=0.5, offset_frequency=2, squash=1.0, squash_frequency=2)
    for k, v in {"Color1": (0.42, 0.12, 0.07, 1), "Color2": (*_jitter_color(rng, (0.55, 0.22, 0.12)), 1),
                 "Mortar": (0.55, 0.53, 0.48, 1), "Scale": 1.0, "Mortar Size": 0.008, "Mortar Smooth": 0.1,
                 "Bias": 0.0, "Brick Width": 0.22, "Row Height": 0.075}.items():
        brick.inputs[k].default_value = v
    m.link(m.coords(swizzle="YZX"), brick.inputs["Vector"])
    m.link(brick.outputs["Color"], m.bsdf.inputs["Base Color"])
    mats["brick"] = m.mat

    # Table wood: planks 15 cm wide along the table (x) with 3 mm dark joints and fine, slightly wavy grain.
    m = _Mat("Oak", roughness=0.5)
    co = m.coords()
    wave = m.node("ShaderNodeTexWave", wave_type="BANDS", bands_direction="Y", wave_profile="SAW")
    for k, v in {"Scale": 9.0, "Distortion": 1.5, "Detail": 2.0, "Detail Scale": 1.5, "Detail Roughness": 0.6}.items():
        wave.inputs[k].default_value = v
    m.link(m.coords(scale=(0.15, 1.0, 1.0)), wave.inputs["Vector"])
    grain = m.ramp(wave.outputs["Factor"], [(0.0, (0.20, 0.10, 0.045)), (0.35, (0.34, 0.19, 0.085)),
                                            (1.0, (0.45, 0.27, 0.13))])
    planks = m.node("ShaderNodeTexBrick", offset=0.5, offset_frequency=2, squash=1.0, squash_frequency=2)
    for k, v in {"Color1": (1, 1, 1, 1), "Color2": (0.8, 0.8, 0.8, 1), "Mortar": (0.05, 0.05, 0.05, 1),
                 "Scale": 1.0, "Mortar Size": 0.003, "Mortar Smooth": 0.2, "Bias": 0.0, "Brick Width": 1.0,
                 "Row Height": 0.15}.items():
        planks.inputs[k].default_value = v
    m.link(co, planks.inputs["Vector"])
    col = m.node("ShaderNodeMix", data_type="RGBA", blend_type="MULTIPLY")
    col.inputs["Factor"].default_value = 1.0
    m.link(grain, col.inputs[6])
    m.link(planks.outputs["Color"], col.inputs[7])
    m.link(col.outputs[2], m.bsdf.inputs["Base Color"])
    m.link(m.map_range(planks.outputs["Factor"], 0.45, 0.9), m.bsdf.inputs["Roughness"])
    mats["wood"] = m.mat

    # Checkered placemat, 2 cm squares.
    m = _Mat("Checker Cloth", roughness=0.8)
    chk = m.node("ShaderNodeTexChecker", Scale=50.0)
    chk.inputs["Color1"].default_value = (0.80, 0.78, 0.72, 1)
    chk.inputs["Color2"].default_value = (*_jitter_color(rng, (0.55, 0.04, 0.04)), 1)
    m.link(m.coords(), chk.inputs["Vector"])
    m.link(chk.outputs["Color"], m.bsdf.inputs["Base Color"])
    mats["checker"] = m.mat

    # Newspaper: rows of word-like blocks (lines 5.7 mm apart) in two columns with a headline band
    # (object coords of a 43 x 32 cm sheet, scaled to a 32 x 24 cm layout).
    m = _Mat("Newsprint", roughness=0.85)
    paper, ink = (0.78, 0.76, 0.70), (0.04, 0.04, 0.05)
    co = m.coords(scale=(1 / 1.35, 1 / 1.35, 1 / 1.35))
    words = m.node("ShaderNodeTexBrick", offset=0.43, offset_frequency=1, squash=0.6, squash_frequency=3)
    for k, v in {"Color1": (0, 0, 0, 1), "Color2": (1, 1, 1, 1), "Mortar": (1, 1, 1, 1), "Scale": 1.0,
                 "Mortar Size": 0.0011, "Mortar Smooth": 0.0, "Bias": 0.0, "Brick Width": 0.018,
                 "Row Height": 0.0042}.items():
        words.inputs[k].default_value = v
    m.link(co, words.inputs["Vector"])
    head = m.node("ShaderNodeTexBrick", offset=0.3, offset_frequency=1, squash=1.0, squash_frequency=1)
    for k, v in {"Color1": (0, 0, 0, 1), "Color2": (0.3, 0.3, 0.3, 1), "Mortar": (1, 1, 1, 1), "Scale": 1.0,
                 "Mortar Size": 0.004, "Mortar Smooth": 0.0, "Bias": 0.0, "Brick Width": 0.05,
                 "Row Height": 0.018}.items():
        head.inputs[k].default_value = v
    m.link(co, head.inputs["Vector"])
    sep = m.node("ShaderNodeSeparateXYZ")
    m.link(co, sep.inputs[0])
    x, y = sep.outputs["X"], sep.outputs["Y"]
    is_head = m.math("GREATER_THAN", y, 0.068)
    text = m.mix(is_head, words.outputs["Color"], head.outputs["Color"])
    ink_mask = m.ramp(text, [(0.0, (1, 1, 1)), (0.72, (0, 0, 0))], interpolation="CONSTANT")
    # Paper where outside the printed area or in the column gutter.
    margin_x = m.math("GREATER_THAN", m.math("ABSOLUTE", x), 0.145)
    margin_y = m.math("GREATER_THAN", m.math("ABSOLUTE", m.math("SUBTRACT", y, -0.005)), 0.1)
    gutter = m.math("MULTIPLY", m.math("LESS_THAN", m.math("ABSOLUTE", x), 0.004), m.math("LESS_THAN", y, 0.06))
    blank = m.math("MAXIMUM", m.math("MAXIMUM", margin_x, margin_y), gutter)
    printed = m.mix(blank, ink_mask, (0, 0, 0, 1))
    m.link(m.mix(printed, paper, ink), m.bsdf.inputs["Base Color"])
    mats["newsprint"] = m.mat

    mats["paint"] = _Mat("White Paint", (0.72, 0.70, 0.64), roughness=0.55).mat
    mats["sign"] = _Mat("Green Paint", (0.03, 0.13, 0.07), roughness=0.6).mat
    mats["letters"] = _Mat("Cream Paint", (0.85, 0.78, 0.58), roughness=0.45).mat
    mats["wire"] = _Mat("Dark Steel", (0.25, 0.25, 0.27), metallic=1.0, roughness=0.35).mat
    mats["chrome"] = _Mat("Chrome", (0.90, 0.90, 0.92), metallic=1.0, roughness=0.05).mat
    mats["gold"] = _Mat("Gold", _jitter_color(rng, (1.0, 0.77, 0.34), 0.03), metallic=1.0, roughness=0.3).mat
    mats["copper"] = _Mat("Copper", (0.95, 0.60, 0.45), metallic=1.0, roughness=0.6).mat
    mats["brushed"] = _Mat("Brushed Steel", (0.80, 0.80, 0.80), metallic=1.0, roughness=0.35,
                           inputs={"Anisotropic": 0.8, "Anisotropic Rotation": 0.0}).mat
    mats["glass"] = _Mat("Glass", (0.97, 1.0, 0.98), roughness=0.0,
                         inputs={"Transmission Weight": 1.0, "IOR": 1.5}).mat
    mats["ceramic"] = _Mat("Ceramic", (0.85, 0.85, 0.82), roughness=0.12).mat
    mats["plastic"] = _Mat("Red Plastic", _jitter_color(rng, (0.70, 0.05, 0.04)), roughness=0.4).mat
    mats["terracotta"] = _Mat("Terracotta", (0.55, 0.23, 0.12), roughness=0.85).mat
    mats["wax"] = _Mat("Candle Wax", (0.90, 0.85, 0.70), roughness=0.4,
                       inputs={"Subsurface Weight": 1.0, "Subsurface Radius": (1.0, 0.5, 0.25),
                               "Subsurface Scale": 0.02}).mat
    mats["bulb"] = _Mat("Warm Bulb", (1.0, 0.78, 0.45), roughness=0.3,
                        inputs={"Emission Color": (1.0, 0.72, 0.38), "Emission Strength": 25.0}).mat

    # Boxwood: fine leafy speckle.
    m = _Mat("Boxwood", roughness=0.7)
    n = m.node("ShaderNodeTexNoise", Scale=90.0, Detail=4.0, Roughness=0.7)
    m.link(m.coords(), n.inputs["Vector"])
    m.link(m.ramp(n.outputs["Factor"], [(0.35, (0.02, 0.06, 0.015)), (0.65, (0.12, 0.28, 0.05))]),
           m.bsdf.inputs["Base Color"])
    mats["boxwood"] = m.mat

    # Toy ball: coarse checker in object space so that its rolling is visible.
    m = _Mat("Toy Ball", roughness=0.25)
    chk = m.node("ShaderNodeTexChecker", Scale=28.0)
    chk.inputs["Color1"].default_value = (0.85, 0.62, 0.05, 1)
    chk.inputs["Color2"].default_value = (0.05, 0.15, 0.55, 1)
    m.link(m.coords(), chk.inputs["Vector"])
    m.link(chk.outputs["Color"], m.bsdf.inputs["Base Color"])
    mats["ball"] = m.mat
    return mats


# ----------------------------------------------------------------------------------------------
# Geometry (bmesh, no operators)
# ----------------------------------------------------------------------------------------------

def _box(bm, center, size, rot_z: float = 0.0) -> None:
    mat = Matrix.LocRotScale(Vector(center), Matrix.Rotation(rot_z, 3, "Z").to_quaternion(), Vector(size))
    bmesh.ops.create_cube(bm, size=1.0, matrix=mat)


def _cylinder(bm, center, radius, depth, segments=12, axis="Z") -> None:
    """Capped cylinder; sides smooth, caps flat."""
    rot = {"Z": Matrix.Identity(3), "X": Matrix.Rotation(math.pi / 2, 3, "Y"),
           "Y": Matrix.Rotation(math.pi / 2, 3, "X")}[axis]
    mat = Matrix.Translation(Vector(center)) @ rot.to_4x4()
    res = bmesh.ops.create_cone(bm, cap_ends=True, cap_tris=False, segments=segments, radius1=radius,
                                radius2=radius, depth=depth, matrix=mat)
    faces = {f for v in res["verts"] for f in v.link_faces}
    for f in faces:
        f.smooth = len(f.verts) == 4


def _sphere(bm, center, radius, u=48, v=24) -> None:
    res = bmesh.ops.create_uvsphere(bm, u_segments=u, v_segments=v, radius=radius,
                                    matrix=Matrix.Translation(Vector(center)))
    for f in {f for vv in res["verts"] for f in vv.link_faces}:
        f.smooth = True


def _lathe(bm, profile, center=(0.0, 0.0, 0.0), segments=48, closed=False) -> None:
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


def _prism_xz(bm, outline, y0: float, y1: float) -> None:
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


def _catenary(p0, p1, sag: float, n: int) -> np.ndarray:
    t = np.linspace(0.0, 1.0, n)
    pts = np.outer(1 - t, p0) + np.outer(t, p1)
    pts[:, 2] -= 4.0 * sag * t * (1 - t)
    return pts


def _tube(bm, points: np.ndarray, radius: float, segments: int = 6) -> None:
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


def _object(scene, name: str, bm, material, location=(0.0, 0.0, 0.0), rotation=(0.0, 0.0, 0.0)):
    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    mesh.materials.append(material)
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    obj.rotation_euler = rotation
    scene.collection.objects.link(obj)
    return obj


def _text_object(scene, name: str, body: str, size: float, material, location, rotation, extrude=0.002):
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
    mesh.materials.clear()
    mesh.materials.append(material)
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    obj.rotation_euler = rotation
    scene.collection.objects.link(obj)
    return obj


# ----------------------------------------------------------------------------------------------
# Scene
# ----------------------------------------------------------------------------------------------

def _equirect_direction(u: float, v: float) -> np.ndarray:
    """World direction of equirectangular texture coordinates (u, v) in [0, 1] (Cycles' convention)."""
    phi = (0.5 - u) * 2.0 * math.pi
    theta = (v - 0.5) * math.pi
    return np.array([math.cos(theta) * math.cos(phi), math.cos(theta) * math.sin(phi), math.sin(theta)])


def make_world(scene, image_path, rot_z: float = 0.0, strength: float = 1.0) -> np.ndarray | None:
    """Light ``scene`` with an equirectangular HDR environment rotated by ``rot_z`` radians about +Z, scaled so that
    its sky (upper hemisphere, values clipped at 50) averages a luminance of 0.8 times ``strength``. Returns the
    world direction of its sun (a pixel above 1000), or None."""
    world = bpy.data.worlds.new("BlendSR World")
    nt = world.node_tree
    bg = nt.nodes["Background"]
    env = nt.nodes.new("ShaderNodeTexEnvironment")
    img = bpy.data.images.load(str(image_path), check_existing=True)
    env.image = img
    env.projection = "EQUIRECTANGULAR"
    tc = nt.nodes.new("ShaderNodeTexCoord")
    mp = nt.nodes.new("ShaderNodeMapping")
    mp.inputs["Rotation"].default_value = (0.0, 0.0, rot_z)
    nt.links.new(tc.outputs["Generated"], mp.inputs["Vector"])
    nt.links.new(mp.outputs["Vector"], env.inputs["Vector"])
    nt.links.new(env.outputs["Color"], bg.inputs["Color"])

    w, h = img.size
    if w <= 0 or h <= 0:
        raise ValueError(f"{image_path}: the HDRI could not be read")
    px = np.empty(w * h * 4, dtype=np.float32)
    img.pixels.foreach_get(px)
    px = px.reshape(h, w, 4)[..., :3].astype(np.float64)  # row 0 is the bottom (v = 0)
    lum = px @ np.array([0.2126, 0.7152, 0.0722])
    weight = np.cos((np.arange(h) + 0.5) / h * math.pi - 0.5 * math.pi)[:, None] * np.ones((1, w))
    upper = slice(h // 2, h)
    sky = float((np.minimum(lum[upper], 50.0) * weight[upper]).sum() / weight[upper].sum())
    bg.inputs["Strength"].default_value = 0.8 * float(strength) / max(sky, 1e-3)
    world["blendsr_hdri"] = str(image_path)
    world["blendsr_hdri_rotation_deg"] = math.degrees(rot_z)
    world["blendsr_hdri_strength"] = float(strength)
    scene.world = world

    i, j = np.unravel_index(int(np.argmax(lum)), lum.shape)
    if lum[i, j] < 1000.0 or i < h // 2:
        return None
    e = _equirect_direction((j + 0.5) / w, (i + 0.5) / h)   # environment direction of the sun
    c, s = math.cos(-rot_z), math.sin(-rot_z)               # the mapping rotates world directions by +rot_z
    return np.array([c * e[0] - s * e[1], s * e[0] + c * e[1], e[2]])


def hdri_path(entry: str) -> Path:
    """A spec's HDRI entry (a file path or ``builtin:NAME``) as a file path."""
    if entry.startswith("builtin:"):
        return studiolight_path(entry.split(":", 1)[1])
    path = Path(entry)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: HDRI not found")
    return path


def _world(scene, rng, override: dict | None = None) -> np.ndarray | None:
    """The seed's environment from bpy's studiolights (or ``override``: hdri, rotation_deg, strength)."""
    name = STUDIOLIGHTS[int(rng.integers(len(STUDIOLIGHTS)))]
    rot_z = float(rng.uniform(0.0, 2.0 * math.pi))
    if override:
        sun = make_world(scene, hdri_path(override["hdri"]), math.radians(override.get("rotation_deg", 0.0)),
                         override.get("strength", 1.0))
        scene.world["blendsr_studiolight"] = override["hdri"]
        return sun
    sun = make_world(scene, studiolight_path(name), rot_z, 1.0)
    scene.world["blendsr_studiolight"] = name
    return sun


def _sun(scene, rng, env_sun: np.ndarray | None) -> None:
    """A sun lamp: along the environment's own sun when it has one (sharpening its shadows), else from the
    front left so that fence shadows fall on the floor behind it."""
    light = bpy.data.lights.new("Sun", "SUN")
    light.angle = math.radians(1.0)
    light.color = (1.0, 0.95, 0.88)
    az = math.radians(rng.uniform(200.0, 250.0))
    el = math.radians(rng.uniform(35.0, 55.0))
    direction = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    if env_sun is not None and env_sun[2] > 0.1:
        direction = env_sun / np.linalg.norm(env_sun)
        light.energy = 1.5
    else:
        light.energy = 2.5
    obj = bpy.data.objects.new("Sun", light)
    obj.location = tuple(10.0 * direction)
    obj.rotation_euler = look_at_matrix(direction, (0.0, 0.0, 0.0)).to_euler("XYZ")
    scene.collection.objects.link(obj)


def _courtyard(scene, mats, rng) -> None:
    # Floor (ground) 16 x 16 m.
    bm = bmesh.new()
    _box(bm, (0.0, 0.0, -0.05), (16.0, 16.0, 0.1))
    floor = _object(scene, "Floor", bm, mats["floor"])
    floor[GROUND_PROPERTY] = True

    # Picket fence along y = 1.6 from x = -2.8 to 0.8, wire-mesh panel from 0.8 to 2.8.
    fy = 1.6
    bm = bmesh.new()
    w, h = 0.045, 1.05
    for k, x in enumerate(np.arange(-2.75, 0.76, 0.085)):
        hh = h + 0.02 * math.sin(1.7 * k)
        outline = [(x - w / 2, 0.03), (x + w / 2, 0.03), (x + w / 2, hh), (x, hh + 0.03), (x - w / 2, hh)]
        _prism_xz(bm, outline, fy - 0.01, fy + 0.01)
    _object(scene, "Fence Pickets", bm, mats["paint"])
    bm = bmesh.new()
    for z in (0.25, 0.85):
        _box(bm, (-1.0, fy + 0.035, z), (3.6, 0.05, 0.09))
    _object(scene, "Fence Rails", bm, mats["paint"])
    bm = bmesh.new()
    for x in (-2.85, -1.0, 0.8, 2.85):
        _box(bm, (x, fy + 0.02, 0.6), (0.09, 0.09, 1.2))
    _object(scene, "Fence Posts", bm, mats["paint"])
    bm = bmesh.new()
    for z in np.arange(0.1, 1.11, 0.05):
        _tube(bm, np.array([[0.85, fy, z], [2.8, fy, z]]), 0.0018, 5)
    for x in np.arange(0.875, 2.8, 0.05):
        _tube(bm, np.array([[x, fy - 0.004, 0.08], [x, fy - 0.004, 1.12]]), 0.0018, 5)
    _object(scene, "Wire Mesh", bm, mats["wire"])

    # String lights: a sagging wire over the fence with small emissive bulbs.
    p0, p1 = np.array([-2.85, fy - 0.05, 1.42]), np.array([2.85, fy - 0.05, 1.42])
    pts = _catenary(p0, p1, 0.16, 64)
    bm = bmesh.new()
    _tube(bm, pts, 0.0025, 6)
    _object(scene, "Light String", bm, mats["wire"])
    bm = bmesh.new()
    for t in np.linspace(0.04, 0.96, 19):
        p = _catenary(p0, p1, 0.16, 1001)[int(round(t * 1000))]
        _sphere(bm, (p[0], p[1], p[2] - 0.035), 0.018, 12, 8)
    _object(scene, "Light Bulbs", bm, mats["bulb"])

    # Painted sign with text on the fence.
    bm = bmesh.new()
    _box(bm, (0.0, 0.0, 0.0), (1.22, 0.02, 0.34))
    _object(scene, "Sign Board", bm, mats["sign"], location=(-1.3, fy - 0.035, 0.8))
    _text_object(scene, "Sign Letters", "GARDEN CAFE\nopen daily 8 - 22  *  fresh bread  *  espresso\n"
                 "no. 17  -  courtyard entrance  -  please close the gate", 0.052, mats["letters"],
                 location=(-1.3, fy - 0.046, 0.81), rotation=(math.pi / 2, 0.0, 0.0))

    # Brick wall on the left.
    bm = bmesh.new()
    _box(bm, (0.0, 0.0, 0.0), (0.25, 4.6, 1.8))
    _object(scene, "Brick Wall", bm, mats["brick"], location=(-3.1, -0.65, 0.9))

    # Terracotta pot with a boxwood ball in front of the wire panel.
    pot = [(0.0, 0.0), (0.17, 0.0), (0.24, 0.38), (0.26, 0.40), (0.26, 0.43), (0.22, 0.43), (0.0, 0.36)]
    bm = bmesh.new()
    _lathe(bm, pot, segments=40)
    px = 1.9 + rng.uniform(-0.15, 0.15)
    _object(scene, "Terracotta Pot", bm, mats["terracotta"], location=(px, 1.05, 0.0))
    bm = bmesh.new()
    _sphere(bm, (0.0, 0.0, 0.0), 0.3, 40, 20)
    _object(scene, "Shrub", bm, mats["boxwood"], location=(px, 1.05, 0.62))


def _table_and_props(scene, mats, rng) -> None:
    z0 = TABLE_TOP_Z
    bm = bmesh.new()
    _box(bm, (0.0, 0.0, z0 - 0.02), (1.6, 0.9, 0.04))
    for sx in (-1, 1):
        for sy in (-1, 1):
            _box(bm, (sx * 0.72, sy * 0.37, (z0 - 0.04) / 2), (0.05, 0.05, z0 - 0.04))
    _object(scene, "Table", bm, mats["wood"])

    def jit(x, y, r=0.02):
        return x + rng.uniform(-r, r), y + rng.uniform(-r, r)

    x, y = jit(-0.42, 0.0)
    bm = bmesh.new()
    _box(bm, (0.0, 0.0, 0.0), (0.44, 0.32, 0.002))
    _object(scene, "Placemat", bm, mats["checker"], location=(x, y, z0 + 0.001),
            rotation=(0.0, 0.0, rng.uniform(-0.15, 0.15)))
    mx, my = x, y

    x, y = jit(0.36, -0.08)
    bm = bmesh.new()
    _box(bm, (0.0, 0.0, 0.0), (0.43, 0.32, 0.002))
    _object(scene, "Newspaper", bm, mats["newsprint"], location=(x, y, z0 + 0.001),
            rotation=(0.0, 0.0, rng.uniform(0.05, 0.2)))
    bm = bmesh.new()
    _sphere(bm, (0.0, 0.0, 0.0), 0.035, 48, 24)
    _object(scene, "Glass Paperweight", bm, mats["glass"], location=(x + 0.07, y - 0.04, z0 + 0.002 + 0.035))

    # Ceramic bowl on the placemat with a chrome sphere next to it.
    bowl = [(0.0, 0.0), (0.04, 0.0), (0.055, 0.006), (0.08, 0.035), (0.09, 0.062), (0.087, 0.065),
            (0.082, 0.062), (0.072, 0.036), (0.05, 0.012), (0.0, 0.009)]
    bm = bmesh.new()
    _lathe(bm, bowl, segments=48)
    _object(scene, "Ceramic Bowl", bm, mats["ceramic"], location=(mx - 0.07, my + 0.04, z0 + 0.002))
    bm = bmesh.new()
    _sphere(bm, (0.0, 0.0, 0.0), 0.05)
    _object(scene, "Chrome Sphere", bm, mats["chrome"], location=(mx + 0.12, my - 0.07, z0 + 0.002 + 0.05))

    # Gold dish, copper cup, brushed pot, glass vase, candle, red cube: back row.
    dish = [(0.0, 0.0), (0.05, 0.0), (0.1, 0.012), (0.12, 0.022), (0.116, 0.024), (0.095, 0.016),
            (0.0, 0.006)]
    bm = bmesh.new()
    _lathe(bm, dish, segments=56)
    x, y = jit(-0.1, 0.22)
    _object(scene, "Gold Dish", bm, mats["gold"], location=(x, y, z0))

    cup = [(0.0, 0.0), (0.035, 0.0), (0.04, 0.005), (0.042, 0.09), (0.038, 0.09), (0.036, 0.008), (0.0, 0.008)]
    bm = bmesh.new()
    _lathe(bm, cup, segments=40)
    x, y = jit(0.12, 0.12)
    _object(scene, "Copper Cup", bm, mats["copper"], location=(x, y, z0))

    pot = [(0.0, 0.0), (0.075, 0.0), (0.08, 0.006), (0.08, 0.13), (0.085, 0.135), (0.085, 0.14), (0.072, 0.14),
           (0.072, 0.012), (0.0, 0.012)]
    bm = bmesh.new()
    _lathe(bm, pot, segments=64)
    x, y = jit(0.5, 0.22)
    _object(scene, "Brushed Pot", bm, mats["brushed"], location=(x, y, z0))

    vase = [(0.0, 0.0), (0.04, 0.0), (0.05, 0.02), (0.056, 0.08), (0.042, 0.15), (0.024, 0.2), (0.03, 0.245),
            (0.026, 0.245), (0.02, 0.2), (0.037, 0.15), (0.051, 0.08), (0.045, 0.022), (0.036, 0.008),
            (0.0, 0.008)]
    bm = bmesh.new()
    _lathe(bm, vase, segments=64)
    x, y = jit(-0.58, 0.27)
    _object(scene, "Glass Vase", bm, mats["glass"], location=(x, y, z0))

    bm = bmesh.new()
    _cylinder(bm, (0.0, 0.0, 0.0), 0.028, 0.16, 32)
    x, y = jit(-0.3, 0.3)
    _object(scene, "Candle", bm, mats["wax"], location=(x, y, z0 + 0.08))

    bm = bmesh.new()
    _box(bm, (0.0, 0.0, 0.0), (0.06, 0.06, 0.06))
    x, y = jit(0.27, 0.3)
    _object(scene, "Red Cube", bm, mats["plastic"], location=(x, y, z0 + 0.03),
            rotation=(0.0, 0.0, rng.uniform(0.0, math.pi / 2)))


def _rolling_ball(scene, mats, rng, frames_all: np.ndarray) -> None:
    """A ball rolling back and forth along the table's front edge (rolls without slipping about +Y)."""
    radius = 0.045
    bm = bmesh.new()
    _sphere(bm, (0.0, 0.0, 0.0), radius, 40, 20)
    obj = _object(scene, "Rolling Ball", bm, mats["ball"])
    period = rng.uniform(60.0, 90.0)   # frames
    phase = rng.uniform(0.0, 2.0 * math.pi)
    amp, xc = 0.5, 0.0
    t = frames_all.astype(np.float64)
    x = xc + amp * np.sin(2.0 * math.pi * t / period + phase)
    loc = np.stack([x, np.full_like(x, -0.35), np.full_like(x, TABLE_TOP_Z + radius)], axis=1)
    rot = np.stack([np.zeros_like(x), (x - xc) / radius, np.zeros_like(x)], axis=1)
    obj.rotation_mode = "XYZ"
    key_channels(obj, frames_all, {"location": loc, "rotation_euler": rot})


def _camera(scene, rng, frames_all: np.ndarray) -> None:
    """A slow dolly in front of the table: the eye swings on an arc around it, looking at the table top."""
    data = bpy.data.cameras.new("Camera")
    data.lens = 30.0
    data.sensor_width = 36.0
    data.sensor_fit = "AUTO"
    data.clip_start = 0.05
    data.clip_end = 100.0
    cam = bpy.data.objects.new("Camera", data)
    scene.collection.objects.link(cam)
    t = frames_all.astype(np.float64)
    ph = rng.uniform(0.0, 2.0 * math.pi, size=5)
    period = rng.uniform(160.0, 240.0)
    w = 2.0 * math.pi / period
    az = math.radians(-90.0 + rng.uniform(-8.0, 8.0)) + math.radians(rng.uniform(20.0, 28.0)) * np.sin(w * t + ph[0])
    r = 1.75 + 0.15 * np.sin(0.7 * w * t + ph[1])
    zc = 1.45 + 0.06 * np.sin(1.3 * w * t + ph[2])
    eyes = np.stack([r * np.cos(az), 0.1 + r * np.sin(az), zc], axis=1)
    targets = np.stack([0.06 * np.sin(0.9 * w * t + ph[3]), 0.35 + 0.05 * np.sin(1.1 * w * t + ph[4]),
                        np.full_like(t, 0.80)], axis=1)
    key_look_at(cam, frames_all, eyes, targets)
    scene.camera = cam


def build_default_scene(seed: int = 0, frames: tuple[int, int] = (1, 48),
                        resolution: tuple[int, int] = (640, 360), world: dict | None = None,
                        sun: bool = True) -> bpy.types.Scene:
    """Reset Blender to an empty factory state and build the default courtyard scene in it.

    ``frames``: inclusive (start, end); animation is keyed on every frame from start-1 to end. ``resolution``:
    (width, height) in pixels at 100%. ``world``: replaces the seed's environment ({"hdri": path or
    "builtin:NAME", "rotation_deg": about +Z, "strength": multiplier of the normalised sky}); the layout, materials
    and camera of the seed stay the same. ``sun``: False removes the sun lamp. Returns the scene (also ``bpy.context.scene``). Engine and sampling are left
    at the factory values; the caller sets them."""
    start, end = int(frames[0]), int(frames[1])
    if end < start:
        raise ValueError(f"frames {start}:{end}: end is before start")
    w, h = int(resolution[0]), int(resolution[1])
    if w <= 0 or h <= 0:
        raise ValueError(f"resolution {w}x{h}: must be positive")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = start, end
    scene.frame_current = start
    scene.render.resolution_x, scene.render.resolution_y = w, h
    scene.render.resolution_percentage = 100
    scene.render.fps = 24
    scene["blendsr_default_scene_seed"] = int(seed)

    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x5CE7E])
    frames_all = np.arange(start - 1, end + 1)
    mats = _materials(rng)
    _sun(scene, rng, _world(scene, rng, world))
    if not sun:
        bpy.data.objects.remove(bpy.data.objects["Sun"], do_unlink=True)
    _courtyard(scene, mats, rng)
    _table_and_props(scene, mats, rng)
    _rolling_ball(scene, mats, rng, frames_all)
    _camera(scene, rng, frames_all)
    scene.frame_set(start)
    return scene

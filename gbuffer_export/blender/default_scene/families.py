"""The built-in generator's families (bpy layer): opt-in additions to the courtyard that games show and the courtyard
lacks, each a family (``gbuffer_export.dataset.families``) with a random stream of its own, so that adding one leaves
every other draw of the seed as it was. Units are metres; the courtyard's table stands at the origin, the fence along
y = 1.6, the scene camera's arc at y -1.8 to -1.2 looking along +Y.

materials (``mat_noise``, ``mat_voronoi``, ``mat_wave``, ``mat_brick``, ``mat_layered``): a plinth on the floor at the
family's own place beside or behind the table, in its pattern, topped by two bevelled primitives whose Principled
class is drawn from ``CLASSES`` (metal, dielectric, coat, sheen, transmission, anisotropy, emission), the pattern
driving base colour, roughness and bump.
``mat_surfaces``: the same classes and patterns on large surfaces (a wall panel, a floor slab, a 0.4-0.6 m block or
sphere).
geometry: ``railing`` (a balcony railing 1.15-1.25 m high between the camera and the table: balusters of 5-9 mm radius every 6-10 cm),
``wires`` (3-6 sagging wires of 1-2.5 mm radius across the courtyard), ``foliage_cards`` (20-40 leaf cards cut by an
alpha mask over a planter), ``stripes_panel`` (a panel of stripes, a grid or rings of 3-12 mm period: moire at LR),
``text_panel`` (a board of seeded text, letters 1.5-4 cm), ``scatter`` (60-140 bevelled pebbles and bolts on the floor).
light: ``neon`` (2-4 emissive tubes over the fence), ``small_emitters`` (4-8 small point lamps with visible LEDs),
``strong_sun`` (the sun 2.5-4x brighter and sharper), ``night`` (the sky at 1-5 %, the sun as a faint moon, one warm
street lamp).
camera (re-key the scene camera; with ``cameras = ["scene"]``): ``cam_pan`` (fast pans, 1.5-4 degrees a frame),
``cam_strafe`` (sideways at 2-5 cm a frame), ``cam_turn`` (a 60-120 degree turn in 4-8 frames), ``cam_cut`` (a cut
to another shot at frame start+1 .. start+6).
modifier-built geometry (``modifiers.py``, applied): ``boolean`` (a wall with windows and vents cut by an exact
Boolean, a machined block), ``displaced`` (a boulder and a column, subdivided and displaced by a procedural texture),
``instanced`` (hundreds of pebbles, bolts and grass tufts on a raised bed, scattered by a geometry node group).
``fog`` (a homogeneous Principled Volume in a box domain around the courtyard and its cameras). ``motion_objects``
(2-4 props gliding and spinning over the table, keyed on every frame). ``motion_character`` (1-2 walking figures,
skinned to a 13-bone armature: ``character.py``).

Each family's drawn parameters are kept on its objects as ``family_params`` (JSON), within ``RANGES``.
"""
from __future__ import annotations

import json
import logging
import math

import bmesh
import bpy
import numpy as np
from mathutils import Matrix, Vector

from ... import sweep
from ..camera_paths import key_channels, key_look_at
from . import placement
from .character import build_figure, key_walk
from .geometry import add_object, box, catenary, cylinder, lathe, sphere, text_object, tube
from .materials import Mat
from .modifiers import boolean_cut, displace, instance_on_faces

log = logging.getLogger(__name__)

#: Principled classes a material family's primitives draw from.
CLASSES = ("metal", "dielectric", "coat", "sheen", "transmission", "anisotropy", "emission")
#: Where each material family's plinth stands (x, y): beside the table or behind it, clear of the other families.
SLOTS = {"noise": (-1.05, 0.75), "voronoi": (1.05, 0.75), "wave": (-0.45, 1.15), "brick": (0.45, 1.15),
         "layered": (1.35, 0.25)}

#: Every drawn parameter's range (low, high), per family.
RANGES: dict[str, dict[str, tuple[float, float]]] = {
    **{f"mat_{p}": {"plinth_height_m": (0.8, 1.05), "scale_per_m": (12.0, 90.0), "roughness": (0.05, 0.6),
                    "bump": (0.05, 0.4), "size_m": (0.12, 0.2), "bevel_m": (0.005, 0.02)} for p in SLOTS},
    "mat_surfaces": {"wall_width_m": (1.6, 2.4), "wall_height_m": (1.0, 1.6), "floor_width_m": (1.6, 2.4),
                     "floor_depth_m": (1.2, 1.8), "object_m": (0.4, 0.6), "scale_per_m": (4.0, 30.0),
                     "roughness": (0.05, 0.6), "bump": (0.05, 0.4)},
    "railing": {"height_m": (1.15, 1.25), "radius_m": (0.005, 0.009), "spacing_m": (0.06, 0.10), "y_m": (-1.05, -0.95)},
    "wires": {"count": (3, 6), "radius_m": (0.001, 0.0025), "sag_m": (0.05, 0.2), "z_m": (1.0, 1.5), "y_m": (0.9, 1.5)},
    "foliage_cards": {"count": (20, 40), "card_m": (0.12, 0.25), "leaf_scale": (8.0, 20.0)},
    "stripes_panel": {"period_m": (0.003, 0.012), "kind": (0, 2), "tilt_rad": (-0.25, 0.25)},
    "text_panel": {"letter_m": (0.015, 0.04), "lines": (3, 6)},
    "scatter": {"count": (60, 140), "size_m": (0.01, 0.035)},
    "neon": {"count": (2, 4), "strength": (8.0, 30.0), "radius_m": (0.006, 0.01)},
    "small_emitters": {"count": (4, 8), "energy_w": (5.0, 30.0), "radius_m": (0.01, 0.02)},
    "strong_sun": {"gain": (2.5, 4.0), "angle_deg": (0.2, 0.5)},
    "night": {"sky_gain": (0.01, 0.05), "moon_w": (0.02, 0.08), "lamp_w": (30.0, 80.0)},
    "cam_pan": {"deg_per_frame": (1.5, 4.0), "span_deg": (20.0, 35.0)},
    "cam_strafe": {"m_per_frame": (0.02, 0.05)},
    "cam_turn": {"turn_deg": (60.0, 120.0), "frames": (4, 8), "start_offset": (0, 3)},
    "cam_cut": {"cut_offset": (1, 6)},
    "boolean": {"width_m": (0.6, 0.9), "height_m": (1.0, 1.3), "thickness_m": (0.08, 0.14), "bevel_m": (0.004, 0.015),
                "cols": (2, 5), "rows": (2, 4), "yaw_rad": (-0.35, 0.35), "block_m": (0.16, 0.26)},
    "displaced": {"rock_radius_m": (0.18, 0.3), "feature_m": (0.04, 0.15), "strength_m": (0.015, 0.05),
                  "column_radius_m": (0.08, 0.14), "column_height_m": (1.0, 1.5)},
    "instanced": {"density_per_m2": (250.0, 600.0), "length_m": (2.0, 3.0), "depth_m": (0.3, 0.4),
                  "height_m": (0.5, 0.6), "size_m": (0.015, 0.035)},
    "fog": {"density_per_m": (0.02, 0.1), "anisotropy": (0.1, 0.6)},
    "motion_objects": {"count": (2, 4), "size_m": (0.08, 0.2), "m_per_frame": (0.01, 0.06),
                       "deg_per_frame": (2.0, 12.0)},
    "motion_character": {"count": (1, 2), "height_m": (1.5, 1.9), "front_height_m": (1.45, 1.65),
                         "m_per_frame": (0.03, 0.07), "swing_deg": (18.0, 32.0), "knee_deg": (25.0, 55.0),
                         "arm_deg": (12.0, 30.0)},
}
#: The walkers' lanes keep their sides (their measured reach across the lane) this far (m) from the table top's edges
#: (|y| <= ``TABLE_HALF_DEPTH``); behind the table a lane lies up to ``LANE_SPREAD`` further back.
TABLE_HALF_DEPTH, LANE_CLEARANCE, LANE_SPREAD = 0.45, 0.02, 0.5
#: Walker 0's second choice: a lane behind the courtyard's fence (its posts end at y 1.665 m), its near side from
#: ``FENCE_LANE_Y`` up to ``LANE_SPREAD`` further back, seen through the pickets and the wire mesh.
FENCE_LANE_Y = 1.7
#: A walker's custom property: its start, JSON {"x_m", "lane_m" (y), "direction" (+1: +X, -1: -X)}.
WALK_START = "walk_start"
#: Starts drawn per walker and lane before it is left out (``motion_character``).
PLACE_TRIES = 16
#: Of the clear starts, how many are tried for the scene camera's view; the share of the frame the walker should
#: cover (``placement.frame_share``, mean of the first, middle and last frames shown), and below which it is left out
#: as out of view (0.5 %: about 12 LR pixels at 64x36; behind the courtyard's wall or the fence's pickets).
SEEN_TRIES, SEEN_MIN, SEEN_FLOOR = 8, 0.02, 0.005
NEON = ((1.0, 0.1, 0.6), (0.1, 0.9, 1.0), (0.3, 1.0, 0.2), (1.0, 0.45, 0.05), (0.6, 0.2, 1.0))


class Draw:
    """A family's draws from its own generator, each within ``RANGES[family]``, recorded for ``family_params``."""

    def __init__(self, family: str, rng):
        self.family, self.rng, self.params, self.objects = family, rng, {}, []

    def __call__(self, key: str, integer: bool = False):
        lo, hi = RANGES[self.family][key]
        v = int(self.rng.integers(lo, hi + 1)) if integer else float(self.rng.uniform(lo, hi))
        self.params.setdefault(key, v)
        return v

    def tag(self, obj):
        """Mark ``obj`` as the family's; every object tagged so far records the parameters drawn so far."""
        self.objects.append(obj)
        for o in self.objects:
            o["blendsr_family"] = self.family
            o["family_params"] = json.dumps(self.params, sort_keys=True)
        return obj


def _bevelled(bm, kind: str, center, size: float, bevel: float) -> None:
    """A bevelled cube, a cylinder with bevelled rims or a sphere (``kind``) of ``size`` centred at ``center``."""
    new = bmesh.new()
    if kind == "sphere":
        sphere(new, (0.0, 0.0, 0.0), size / 2, 24, 12)
    else:
        if kind == "cube":
            box(new, (0.0, 0.0, 0.0), (size, size, size))
        else:
            cylinder(new, (0.0, 0.0, 0.0), size / 2, size, 24)
        edges = [e for e in new.edges if len(e.link_faces) == 2 and
                 e.link_faces[0].normal.angle(e.link_faces[1].normal, 0.0) > 0.5]
        bmesh.ops.bevel(new, geom=edges, offset=min(bevel, size / 4), segments=3, affect="EDGES")
    bmesh.ops.translate(new, verts=new.verts, vec=Vector(center))
    mesh = bpy.data.meshes.new("tmp")
    new.to_mesh(mesh)
    new.free()
    bm.from_mesh(mesh)
    bpy.data.meshes.remove(mesh)


def _pattern(m: Mat, pattern: str, scale: float, rng):
    """The factor output (0..1) of ``pattern`` at ``scale`` per metre on object coordinates."""
    co = m.coords()
    if pattern == "noise":
        n = m.node("ShaderNodeTexNoise", Scale=scale, Detail=float(rng.uniform(2, 8)), Roughness=0.6)
        m.link(co, n.inputs["Vector"])
        return n.outputs["Factor"]
    if pattern == "voronoi":
        n = m.node("ShaderNodeTexVoronoi", feature="F1", Scale=scale)
        m.link(co, n.inputs["Vector"])
        return n.outputs["Distance"]
    if pattern == "wave":
        n = m.node("ShaderNodeTexWave", wave_type="BANDS", Scale=scale, Distortion=float(rng.uniform(0, 4)))
        m.link(co, n.inputs["Vector"])
        return n.outputs["Factor"]
    if pattern == "brick":
        n = m.node("ShaderNodeTexBrick", offset=0.5, offset_frequency=2)
        for k, v in {"Scale": 1.0, "Brick Width": 3.0 / scale, "Row Height": 1.2 / scale, "Mortar Size": 0.2 / scale,
                     "Color1": (1, 1, 1, 1), "Color2": (0.6, 0.6, 0.6, 1), "Mortar": (0, 0, 0, 1)}.items():
            n.inputs[k].default_value = v
        m.link(co, n.inputs["Vector"])
        return n.outputs["Factor"]
    # layered: multifractal noise (the former Musgrave) times Voronoi cells, plus fine wave scratches
    fbm = m.node("ShaderNodeTexNoise", noise_type="MULTIFRACTAL", Scale=scale / 4, Detail=10.0, Lacunarity=2.3)
    cells = m.node("ShaderNodeTexVoronoi", feature="F1", Scale=scale)
    wave = m.node("ShaderNodeTexWave", wave_type="RINGS", Scale=scale * 2)
    for n in (fbm, cells, wave):
        m.link(co, n.inputs["Vector"])
    mixed = m.math("MULTIPLY", fbm.outputs["Factor"], cells.outputs["Distance"])
    return m.math("ADD", m.math("MULTIPLY", wave.outputs["Factor"], 0.25), mixed)


def _family_material(name: str, pattern: str, cls: str, d: Draw, rng):
    """A Principled material of class ``cls`` whose colour, roughness and bump follow ``pattern``."""
    c0, c1 = rng.uniform(0.05, 0.95, size=3), rng.uniform(0.05, 0.95, size=3)
    rough = d("roughness")
    m = Mat(name, tuple(c0), roughness=rough)
    fac = _pattern(m, pattern, d("scale_per_m"), rng)
    col = m.ramp(fac, [(0.2, tuple(c0)), (0.8, tuple(c1))])
    m.link(col, m.bsdf.inputs["Base Color"])
    m.link(m.map_range(fac, rough, min(1.0, rough + 0.35)), m.bsdf.inputs["Roughness"])
    bump = m.node("ShaderNodeBump", Strength=d("bump"), Distance=0.002)
    m.link(fac, bump.inputs["Height"])
    m.link(bump.outputs["Normal"], m.bsdf.inputs["Normal"])
    inputs = {"metal": {"Metallic": 1.0}, "dielectric": {"IOR": float(rng.uniform(1.4, 1.7))},
              "coat": {"Coat Weight": float(rng.uniform(0.6, 1.0)), "Coat Roughness": float(rng.uniform(0.0, 0.2))},
              "sheen": {"Sheen Weight": float(rng.uniform(0.5, 1.0)), "Sheen Roughness": 0.4},
              "transmission": {"Transmission Weight": 1.0, "IOR": 1.5},
              "anisotropy": {"Metallic": 1.0, "Anisotropic": float(rng.uniform(0.5, 0.9)),
                             "Anisotropic Rotation": float(rng.uniform(0.0, 1.0))},
              "emission": {"Emission Strength": float(rng.uniform(2.0, 15.0))}}[cls]
    for k, v in inputs.items():
        m.set(k, v)
    if cls == "emission":
        m.link(col, m.bsdf.inputs["Emission Color"])
    return m.mat


def material_family(pattern: str):
    """The builder of material family ``mat_PATTERN``: a plinth at ``SLOTS[pattern]`` and two primitives on it."""
    def build(scene, mats, rng) -> None:
        d = Draw(f"mat_{pattern}", rng)
        x, y = SLOTS[pattern]
        h = d("plinth_height_m")
        plinth_mat = _family_material(f"{pattern.title()} Plinth", pattern, "dielectric", d, rng)
        bm = bmesh.new()
        _bevelled(bm, "cube", (0.0, 0.0, 0.0), 1.0, 0.02)
        bmesh.ops.scale(bm, vec=(0.4, 0.28, h), verts=bm.verts)
        bmesh.ops.translate(bm, vec=(0.0, 0.0, h / 2), verts=bm.verts)
        d.tag(add_object(scene, f"{pattern.title()} Plinth", bm, plinth_mat, location=(x, y, 0.0)))
        for k, (dx, kind) in enumerate(((-0.09, ("cube", "cylinder")[int(rng.integers(2))]), (0.09, "sphere"))):
            cls = CLASSES[int(rng.integers(len(CLASSES)))]
            size = d("size_m")
            bm = bmesh.new()
            _bevelled(bm, kind, (0.0, 0.0, size / 2), size, d("bevel_m"))
            mat = _family_material(f"{pattern.title()} {cls.title()}", pattern, cls, d, rng)
            obj = add_object(scene, f"{pattern.title()} Swatch {k + 1}", bm, mat, location=(x + dx, y, h),
                             rotation=(0.0, 0.0, float(rng.uniform(0, math.pi))))
            obj["principled_class"] = cls
            d.tag(obj)
    return build


def mat_surfaces(scene, mats, rng) -> None:
    """Material classes on surfaces as large as a game shows them: a wall panel (1.6-2.4 x 1.0-1.6 m, 6 cm thick)
    standing behind the table at y 1.2-1.3 (clear of the fence at 1.6), a floor slab (1.6-2.4 x 1.2-1.8 m, 1 cm, its
    top 2 mm above the floor) under the table and a bevelled block or sphere (0.4-0.6 m) beside it, 5-35 cm clear of
    the table top (|x| <= 0.8); each of a Principled class of ``CLASSES`` over a pattern of the material families
    (4-30 features per m), recorded as ``principled_class`` and ``pattern``."""
    d = Draw("mat_surfaces", rng)
    ww, wh = d("wall_width_m"), d("wall_height_m")
    fw, fd, size = d("floor_width_m"), d("floor_depth_m"), d("object_m")
    side = 1.0 if rng.uniform() < 0.5 else -1.0
    parts = (("Wall", (ww, 0.06, wh), (float(rng.uniform(-0.3, 0.3)), float(rng.uniform(1.2, 1.3)), wh / 2), "cube"),
             ("Floor", (fw, fd, 0.01), (0.0, float(rng.uniform(-0.1, 0.1)), -0.003), "cube"),
             ("Sculpture", (size, size, size), (side * (0.85 + size / 2 + float(rng.uniform(0.0, 0.3))),
                                                float(rng.uniform(0.1, 0.5)), size / 2),
              ("cube", "sphere")[int(rng.integers(2))]))
    for name, dims, loc, kind in parts:
        cls = CLASSES[int(rng.integers(len(CLASSES)))]
        pattern = tuple(SLOTS)[int(rng.integers(len(SLOTS)))]
        bm = bmesh.new()
        _bevelled(bm, kind, (0.0, 0.0, 0.0), 1.0, 0.04 if kind == "cube" else 0.0)
        bmesh.ops.scale(bm, vec=dims, verts=bm.verts)
        mat = _family_material(f"Surface {name} {cls.title()}", pattern, cls, d, rng)
        obj = add_object(scene, f"Surface {name}", bm, mat, location=loc,
                         rotation=(0.0, 0.0, float(rng.uniform(-0.1, 0.1))))
        obj["principled_class"], obj["pattern"] = cls, pattern
        d.tag(obj)


def railing(scene, mats, rng) -> None:
    """A balcony railing at y -1.05..-0.95 from x -1.6 to 1.6: round balusters, a top rail and a mid rail."""
    d = Draw("railing", rng)
    h, r, step, y = d("height_m"), d("radius_m"), d("spacing_m"), d("y_m")
    bm = bmesh.new()
    for x in np.arange(-1.6, 1.6 + 1e-9, step):
        cylinder(bm, (float(x), 0.0, h / 2), r, h, 8)
    box(bm, (0.0, 0.0, h + 0.02), (3.3, 0.05, 0.04))
    box(bm, (0.0, 0.0, 0.12), (3.3, 0.02, 0.02))
    d.tag(add_object(scene, "Railing", bm, mats["wire"], location=(0.0, y, 0.0)))


def wires(scene, mats, rng) -> None:
    """3-6 wires sagging across the courtyard from x -2.8 to 2.8 behind the table."""
    d = Draw("wires", rng)
    bm = bmesh.new()
    for _ in range(d("count", integer=True)):
        y0, z0, z1 = d("y_m"), d("z_m"), d("z_m")
        pts = catenary(np.array([-2.8, y0, z0]), np.array([2.8, y0 + rng.uniform(-0.1, 0.1), z1]), d("sag_m"), 96)
        tube(bm, pts, d("radius_m"), 6)
    d.tag(add_object(scene, "Wires", bm, mats["wire"]))


def foliage_cards(scene, mats, rng) -> None:
    """A planter at (1.2, 1.25) with 20-40 leaf cards (quads) whose alpha is cut by a Voronoi leaf mask."""
    d = Draw("foliage_cards", rng)
    bm = bmesh.new()
    box(bm, (0.0, 0.0, 0.15), (0.35, 0.25, 0.3))
    d.tag(add_object(scene, "Planter", bm, mats["terracotta"], location=(1.2, 1.25, 0.0)))
    m = Mat("Leaf Cards", (0.08, 0.3, 0.05), roughness=0.55, inputs={"Subsurface Weight": 0.2})
    cells = m.node("ShaderNodeTexVoronoi", feature="DISTANCE_TO_EDGE", Scale=d("leaf_scale"))
    uv = m.node("ShaderNodeTexCoord")
    m.link(uv.outputs["UV"], cells.inputs["Vector"])
    m.link(m.math("GREATER_THAN", cells.outputs["Distance"], 0.08), m.bsdf.inputs["Alpha"])
    bm = bmesh.new()
    uv_layer = bm.loops.layers.uv.new("UVMap")
    for _ in range(d("count", integer=True)):
        s = d("card_m")
        rot = Matrix.Rotation(rng.uniform(0, 2 * math.pi), 4, "Z") @ Matrix.Rotation(rng.uniform(-1.0, 1.0), 4, "X")
        c = Vector((rng.uniform(-0.2, 0.2), rng.uniform(-0.15, 0.15), rng.uniform(0.35, 0.95)))
        verts = [bm.verts.new(c + (rot @ Vector((sx * s / 2, 0.0, sz * s / 2, 0.0))).to_3d())
                 for sx, sz in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        face = bm.faces.new(verts)
        for loop, uv_co in zip(face.loops, ((0, 0), (1, 0), (1, 1), (0, 1))):
            loop[uv_layer].uv = uv_co
    d.tag(add_object(scene, "Foliage Cards", bm, m.mat, location=(1.2, 1.25, 0.0)))


def stripes_panel(scene, mats, rng) -> None:
    """A 0.9 x 0.6 m panel on two legs at y 1.45 (in front of the fence): stripes, a grid or rings (``kind`` 0-2)
    of 3-12 mm period, tilted up to 0.25 rad in its plane."""
    d = Draw("stripes_panel", rng)
    period, kind, tilt = d("period_m"), d("kind", integer=True), d("tilt_rad")
    m = Mat("Moire Stripes", (0.9, 0.9, 0.9), roughness=0.5)
    co = m.coords(swizzle="XZY")
    rot = m.node("ShaderNodeVectorRotate", rotation_type="Z_AXIS", Angle=tilt)
    m.link(co, rot.inputs["Vector"])
    sep = m.node("ShaderNodeSeparateXYZ")
    m.link(rot.outputs["Vector"], sep.inputs[0])
    if kind == 2:
        r = m.node("ShaderNodeVectorMath", operation="LENGTH")
        m.link(rot.outputs["Vector"], r.inputs[0])
        u = r.outputs["Value"]
    else:
        u = sep.outputs["X"]
    band = m.math("GREATER_THAN", m.math("PINGPONG", u, period / 2), period / 4)
    if kind == 1:
        band = m.math("MAXIMUM", band, m.math("GREATER_THAN", m.math("PINGPONG", sep.outputs["Y"], period / 2),
                                              period / 4))
    m.link(m.mix(band, (0.02, 0.02, 0.03), (0.85, 0.85, 0.8)), m.bsdf.inputs["Base Color"])
    bm = bmesh.new()
    box(bm, (0.0, 0.0, 0.0), (0.9, 0.01, 0.6))
    d.tag(add_object(scene, "Stripes Panel", bm, m.mat, location=(0.0, 1.45, 1.05)))
    bm = bmesh.new()
    for sx in (-1, 1):
        box(bm, (sx * 0.4, 0.0, 0.375), (0.03, 0.03, 0.75))
    d.tag(add_object(scene, "Stripes Panel Legs", bm, mats["paint"], location=(0.0, 1.47, 0.0)))


def text_panel(scene, mats, rng) -> None:
    """A 0.62 x 0.42 m board on the wire mesh at (1.3, 1.5) with 3-6 lines of seeded letters and digits."""
    d = Draw("text_panel", rng)
    size, lines = d("letter_m"), d("lines", integer=True)
    alphabet = "ABCDEFGHJKLMNPQRSTUVWXYZ0123456789abcdefghkmnpqrstuvwxyz -:#"
    per_line = max(4, int(0.56 / (0.62 * size)))
    body = "\n".join("".join(alphabet[int(i)] for i in rng.integers(len(alphabet), size=per_line))
                     for _ in range(min(lines, int(0.38 / (1.15 * size)))))
    bm = bmesh.new()
    box(bm, (0.0, 0.0, 0.0), (0.62, 0.015, 0.42))
    d.tag(add_object(scene, "Text Panel", bm, mats["paint"], location=(1.3, 1.5, 0.95)))
    ink = Mat("Text Ink", (0.02, 0.02, 0.05), roughness=0.4).mat
    d.tag(text_object(scene, "Text Panel Letters", body, size, ink, location=(1.3, 1.49, 0.95),
                      rotation=(math.pi / 2, 0.0, 0.0), extrude=0.001))


def scatter(scene, mats, rng) -> None:
    """60-140 bevelled pebbles, bolts and chips (1-3.5 cm) scattered on the floor beside and behind the table
    (x -1.6..1.6, y 0.5..1.45), each with one of the scene's materials."""
    d = Draw("scatter", rng)
    roles = ("chrome", "gold", "copper", "ceramic", "plastic", "terracotta", "paint")
    bms = {r: bmesh.new() for r in roles}
    for _ in range(d("count", integer=True)):
        s = d("size_m")
        kind = ("cube", "cylinder", "sphere")[int(rng.integers(3))]
        _bevelled(bms[roles[int(rng.integers(len(roles)))]], kind,
                  (rng.uniform(-1.6, 1.6), rng.uniform(0.5, 1.45), s / 2), s, s / 6)
    for r in roles:
        d.tag(add_object(scene, f"Scatter {r.title()}", bms[r], mats[r]))


def neon(scene, mats, rng) -> None:
    """2-4 neon tubes (zigzags and loops) above the fence at y 1.55, z 1.15-1.55, in saturated colours."""
    d = Draw("neon", rng)
    for k in range(d("count", integer=True)):
        x0, w = rng.uniform(-2.4, 1.6), rng.uniform(0.4, 0.8)
        n = int(rng.integers(3, 7))
        xs = np.linspace(x0, x0 + w, n)
        zs = 1.15 + 0.4 * rng.uniform(0, 1, size=n)
        pts = np.stack([xs, np.full(n, 1.55), zs], axis=1)
        pts = np.repeat(pts, 8, axis=0) + np.linspace(0, 1e-4, 8 * n)[:, None]   # dense points: round corners
        bm = bmesh.new()
        tube(bm, pts, d("radius_m"), 8)
        colour = NEON[int(rng.integers(len(NEON)))]
        m = Mat(f"Neon {k + 1}", colour, roughness=0.2,
                inputs={"Emission Color": colour, "Emission Strength": d("strength")})
        d.tag(add_object(scene, f"Neon {k + 1}", bm, m.mat))


def small_emitters(scene, mats, rng) -> None:
    """4-8 small point lamps (radius 1-2 cm, 5-30 W) at z 0.95-1.6 over the table and behind it, each with a
    visible emissive LED sphere."""
    d = Draw("small_emitters", rng)
    for k in range(d("count", integer=True)):
        p = (rng.uniform(-1.4, 1.4), rng.uniform(-0.3, 1.4), rng.uniform(0.95, 1.6))
        colour = tuple(rng.uniform(0.6, 1.0, size=3))
        lamp = bpy.data.lights.new(f"Emitter {k + 1}", "POINT")
        lamp.energy, lamp.color, lamp.shadow_soft_size = d("energy_w"), colour, d("radius_m")
        obj = bpy.data.objects.new(f"Emitter {k + 1}", lamp)
        obj.location = p
        scene.collection.objects.link(obj)
        d.tag(obj)
        bm = bmesh.new()
        sphere(bm, (0.0, 0.0, 0.0), 0.006, 12, 6)
        m = Mat(f"LED {k + 1}", colour, inputs={"Emission Color": colour, "Emission Strength": 40.0})
        d.tag(add_object(scene, f"LED {k + 1}", bm, m.mat, location=p))


def strong_sun(scene, mats, rng) -> None:
    """The sun 2.5-4 times brighter with a 0.2-0.5 degree disc (hard shadows); added along (-1, -1, 2) without one."""
    d = Draw("strong_sun", rng)
    sun = bpy.data.objects.get("Sun")
    if sun is None:
        sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", "SUN"))
        sun.rotation_euler = (0.6, 0.0, -2.4)
        scene.collection.objects.link(sun)
        sun.data.energy = 2.5
    sun.data.energy *= d("gain")
    sun.data.angle = math.radians(d("angle_deg"))
    d.tag(sun)


def night(scene, mats, rng) -> None:
    """Night: the sky at 1-5 % of its strength, the sun as a faint blue moon (0.02-0.08), and one warm street lamp
    (30-80 W) over the fence; the string lights and any emitters then light the scene."""
    d = Draw("night", rng)
    bg = scene.world.node_tree.nodes["Background"]
    bg.inputs["Strength"].default_value *= d("sky_gain")
    scene.world["family_params"] = json.dumps({"sky_gain": d.params["sky_gain"]})
    sun = bpy.data.objects.get("Sun")
    if sun is not None:
        sun.data.energy, sun.data.color = d("moon_w"), (0.6, 0.7, 1.0)
        d.tag(sun)
    lamp = bpy.data.lights.new("Street Lamp", "POINT")
    lamp.energy, lamp.color, lamp.shadow_soft_size = d("lamp_w"), (1.0, 0.7, 0.4), 0.05
    obj = bpy.data.objects.new("Street Lamp", lamp)
    obj.location = (rng.uniform(-1.5, 1.5), 1.3, 2.2)
    scene.collection.objects.link(obj)
    d.tag(obj)


def _camera_base(scene):
    cam = scene.camera
    frames = np.arange(scene.frame_start - 1, scene.frame_end + 1)
    return cam, frames, frames.astype(np.float64) - frames[0]


def _eye(rng, az_deg: float | None = None):
    az = math.radians(-90.0 + (rng.uniform(-20.0, 20.0) if az_deg is None else az_deg))
    r = rng.uniform(1.6, 1.9)
    return np.array([r * math.cos(az), 0.1 + r * math.sin(az), rng.uniform(1.3, 1.6)])


def _yaw_target(eye, yaw_rad: np.ndarray, dist: float = 1.9, z: float = 0.8) -> np.ndarray:
    """Targets ``dist`` m from ``eye`` along the yaw ``yaw_rad`` (0: +Y), at height ``z``."""
    return np.stack([eye[0] + dist * np.sin(yaw_rad), eye[1] + dist * np.cos(yaw_rad), np.full_like(yaw_rad, z)], 1)


def cam_pan(scene, mats, rng) -> None:
    """Fast pans from a fixed eye: the yaw sweeps back and forth over +-span at 1.5-4 degrees a frame."""
    d = Draw("cam_pan", rng)
    cam, frames, t = _camera_base(scene)
    eye, rate, span = _eye(rng), math.radians(d("deg_per_frame")), math.radians(d("span_deg"))
    yaw0 = math.atan2(-eye[0], 0.35 - eye[1])
    phase = rng.uniform(0, 4 * span)
    tri = np.abs(((rate * t + phase) % (4 * span)) - 2 * span) - span       # triangle wave in [-span, span]
    key_look_at(cam, frames, np.repeat(eye[None], len(t), 0), _yaw_target(eye, yaw0 + tri))
    d.tag(cam)


def cam_strafe(scene, mats, rng) -> None:
    """A strafe: the eye slides along x at 2-5 cm a frame (back and forth over 3 m), looking straight ahead."""
    d = Draw("cam_strafe", rng)
    cam, frames, t = _camera_base(scene)
    eye, v = _eye(rng, 0.0), d("m_per_frame")
    phase = rng.uniform(0, 6.0)
    x = np.abs(((v * t + phase) % 6.0) - 3.0) - 1.5
    eyes = np.stack([x, np.full_like(t, eye[1]), np.full_like(t, eye[2])], 1)
    key_look_at(cam, frames, eyes, eyes + np.array([0.0, 1.9, 0.8 - eye[2]]))
    d.tag(cam)


def cam_turn(scene, mats, rng) -> None:
    """A quick turn: from a fixed eye the yaw turns by 60-120 degrees (left or right) in 4-8 frames, starting 0-3
    frames after the first rendered frame (smoothstep), then holds."""
    d = Draw("cam_turn", rng)
    cam, frames, t = _camera_base(scene)
    eye = _eye(rng)
    turn = math.radians(d("turn_deg")) * (1 if rng.uniform() < 0.5 else -1)
    n, s0 = d("frames", integer=True), d("start_offset", integer=True) + 1
    u = np.clip((t - s0) / n, 0.0, 1.0)
    yaw = math.atan2(-eye[0], 0.35 - eye[1]) + turn * u * u * (3 - 2 * u)
    key_look_at(cam, frames, np.repeat(eye[None], len(t), 0), _yaw_target(eye, yaw))
    d.tag(cam)


def cam_cut(scene, mats, rng) -> None:
    """A cut: shot A (a slow push-in from one side) until frame start+k (k 1-6), then shot B from the other side."""
    d = Draw("cam_cut", rng)
    cam, frames, t = _camera_base(scene)
    k = d("cut_offset", integer=True) + 1
    side = 1 if rng.uniform() < 0.5 else -1
    a, b = _eye(rng, side * rng.uniform(10, 25)), _eye(rng, -side * rng.uniform(10, 25))
    ta, tb = np.array([rng.uniform(-0.3, 0.3), 0.3, 0.8]), np.array([rng.uniform(-0.3, 0.3), 0.5, 0.9])
    after = (t >= k)[:, None]
    push = (ta - a) / np.linalg.norm(ta - a) * 0.01 * t[:, None]
    eyes = np.where(after, b + push, a + push)
    key_look_at(cam, frames, eyes, np.where(after, tb, ta))   # integer frames: the cut lies between k-1 and k
    d.tag(cam)


def _bevelled_box(size, bevel: float):
    """A bmesh box of ``size`` (x, y, z) centred at the origin, every edge bevelled by ``bevel`` (2 segments)."""
    bm = bmesh.new()
    box(bm, (0.0, 0.0, 0.0), size)
    bmesh.ops.bevel(bm, geom=bm.edges[:], offset=bevel, segments=2, affect="EDGES")
    return bm


def _cutter(scene, name: str, bm):
    """A mesh object of the closed shells in ``bm`` (no material), for :func:`boolean_cut`."""
    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    obj = bpy.data.objects.new(name, mesh)
    scene.collection.objects.link(obj)
    return obj


def boolean(scene, mats, rng) -> None:
    """A bevelled wall segment (0.6-0.9 x 1.0-1.3 m, 8-14 cm thick) standing behind the table at y 0.8, turned up to
    0.35 rad, with a grid of 2-5 x 2-4 windows and a row of round vents cut through it (exact Boolean, applied), and
    at its foot a bevelled block (16-26 cm) with a bore through it and a slot across its top."""
    d = Draw("boolean", rng)
    w, h, t, bev = d("width_m"), d("height_m"), d("thickness_m"), d("bevel_m")
    cols, rows, yaw = d("cols", integer=True), d("rows", integer=True), d("yaw_rad")
    bm = _bevelled_box((w, t, h), bev)
    bmesh.ops.translate(bm, verts=bm.verts, vec=(0.0, 0.0, h / 2))
    wall = add_object(scene, "Boolean Wall", bm, Mat("Boolean Concrete", tuple(rng.uniform(0.35, 0.7, 3)),
                                                     roughness=0.8).mat, location=(0.0, 0.8, 0.0),
                      rotation=(0.0, 0.0, yaw))
    cut, m = bmesh.new(), 0.06                                          # margin between windows (m)
    ww, wh = (w - m * (cols + 1)) / cols, (0.72 * h - m * (rows + 1)) / rows
    for i in range(cols):
        for j in range(rows):
            box(cut, (-w / 2 + m + ww / 2 + i * (ww + m), 0.0, 0.2 * h + m + wh / 2 + j * (wh + m)), (ww, 3 * t, wh))
    for x in np.linspace(-w / 2 + 0.08, w / 2 - 0.08, max(3, int(w / 0.1))):
        cylinder(cut, (float(x), 0.0, 0.93 * h), 0.02, 3 * t, 16, axis="Y")
    boolean_cut(wall, _cutter(scene, "Boolean Wall Cutter", cut))
    d.tag(wall)
    s = d("block_m")
    bm = _bevelled_box((s, s, s), bev)
    block = add_object(scene, "Boolean Block", bm, Mat("Boolean Steel", (0.6, 0.6, 0.62), metallic=1.0,
                                                       roughness=float(rng.uniform(0.15, 0.45))).mat,
                       location=(float(rng.uniform(-0.2, 0.2)), 0.55, s / 2), rotation=(0.0, 0.0, yaw + 0.5))
    cut = bmesh.new()
    cylinder(cut, (0.0, 0.0, 0.0), s / 4, 2 * s, 32, axis="X")
    box(cut, (0.0, 0.0, s / 2), (2 * s, s / 6, s / 2))
    boolean_cut(block, _cutter(scene, "Boolean Block Cutter", cut))
    d.tag(block)


def displaced(scene, mats, rng) -> None:
    """A boulder (radius 18-30 cm) on the floor right of the table's front and a column (radius 8-14 cm, 1.0-1.5 m) at the right,
    each subdivided and displaced along its normals by a procedural texture (features 4-15 cm, 1.5-5 cm deep)."""
    d = Draw("displaced", rng)
    r = d("rock_radius_m")
    bm = bmesh.new()
    bmesh.ops.create_icosphere(bm, subdivisions=3, radius=r)
    bmesh.ops.scale(bm, vec=(1.0, float(rng.uniform(0.75, 1.0)), float(rng.uniform(0.55, 0.8))), verts=bm.verts)
    stone = Mat("Displaced Stone", tuple(rng.uniform(0.2, 0.5, 3)), roughness=float(rng.uniform(0.5, 0.9))).mat
    rock = add_object(scene, "Displaced Boulder", bm, stone, rotation=(0.0, 0.0, float(rng.uniform(0, math.pi))),
                      location=(float(rng.uniform(1.05, 1.3)), float(rng.uniform(-0.25, -0.05)), 0.3 * r))
    displace(rock, ("CLOUDS", "VORONOI", "STUCCI")[int(rng.integers(3))], d("feature_m"), d("strength_m"), 2,
             int(rng.integers(1 << 30)))
    d.tag(rock)
    cr, ch = d("column_radius_m"), d("column_height_m")
    bm = bmesh.new()
    lathe(bm, [(0.0, 0.0)] + [(cr, z) for z in np.linspace(0.0, ch, max(4, int(ch / cr)))] + [(0.0, ch)],
          segments=24)
    col = add_object(scene, "Displaced Column", bm, Mat("Displaced Sandstone", tuple(rng.uniform(0.45, 0.8, 3)),
                                                        roughness=0.7).mat, location=(1.55, 0.85, 0.0))
    displace(col, ("MARBLE", "CLOUDS", "WOOD")[int(rng.integers(3))], d("feature_m"), d("strength_m") * 0.6, 2,
             int(rng.integers(1 << 30)))
    d.tag(col)


def _source(name: str, bm, material):
    """A mesh object (not linked to a scene) for :func:`instance_on_faces`."""
    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    mesh.materials.append(material)
    return bpy.data.objects.new(name, mesh)


def _instance_sources(size: float, mats, rng) -> list:
    """A pebble, a bolt and a grass tuft, each about ``size`` m, standing on z = 0."""
    bm = bmesh.new()
    bmesh.ops.create_icosphere(bm, subdivisions=2, radius=size / 2)
    bmesh.ops.scale(bm, vec=(1.0, 0.8, 0.55), verts=bm.verts)
    for f in bm.faces:
        f.smooth = True
    pebble = _source("Pebble", bm, Mat("Pebble Stone", tuple(rng.uniform(0.3, 0.6, 3)), roughness=0.6).mat)
    bm = bmesh.new()
    cylinder(bm, (0.0, 0.0, size * 0.1), size * 0.45, size * 0.2, 6)
    cylinder(bm, (0.0, 0.0, size * 0.6), size * 0.2, size * 0.8, 10)
    bolt = _source("Bolt", bm, mats["chrome"])
    bm = bmesh.new()
    for a in np.linspace(0.0, 2 * math.pi, 6, endpoint=False):
        tip = Vector((0.35 * size * math.cos(a), 0.35 * size * math.sin(a), 2.2 * size))
        base = [Vector((0.08 * size * math.cos(a + da), 0.08 * size * math.sin(a + da), 0.0)) for da in (-0.6, 0.6)]
        bm.faces.new([bm.verts.new(v) for v in (*base, tip)])
    grass = _source("Grass Tuft", bm, Mat("Grass Blades", (0.12, 0.35, 0.06), roughness=0.5,
                                          inputs={"Subsurface Weight": 0.15}).mat)
    return [pebble, bolt, grass]


def instanced(scene, mats, rng) -> None:
    """A raised bed along the fence (2-3 m long, 0.3-0.4 m deep, 0.5-0.6 m high: seen over the table) at y 1.3, its
    soil strewn with pebbles, bolts and grass tufts (1.5-3.5 cm, scaled 0.6-1.6) through geometry nodes (Distribute
    Points on Faces at 250-600 per m2 + Instance on Points, realised): hundreds of small instances. The soil object
    records ``instance_count``."""
    d = Draw("instanced", rng)
    length, depth, h = d("length_m"), d("depth_m"), d("height_m")
    loc = (float(rng.uniform(-0.5, 0.5)), 1.3, 0.0)
    bm = bmesh.new()
    for sx in (-1, 1):
        box(bm, (sx * (length / 2 + 0.02), 0.0, h / 2), (0.04, depth + 0.08, h))
    for sy in (-1, 1):
        box(bm, (0.0, sy * (depth / 2 + 0.02), h / 2), (length, 0.04, h))
    d.tag(add_object(scene, "Instanced Planter", bm, mats["wood"], location=loc))
    bm = bmesh.new()                                                    # the soil: one quad, instances on top
    bm.faces.new([bm.verts.new((sx * length / 2, sy * depth / 2, h - 0.04))
                  for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    bed = add_object(scene, "Instanced Soil", bm, Mat("Gravel Soil", tuple(rng.uniform(0.12, 0.25, 3)),
                                                      roughness=0.9).mat, location=loc)
    count = instance_on_faces(bed, _instance_sources(d("size_m"), mats, rng), d("density_per_m2"), (0.6, 1.6),
                              int(rng.integers(1 << 30)))
    bed["instance_count"] = count
    d.tag(bed)


def fog(scene, mats, rng) -> None:
    """Fog where Cycles renders it: a box domain (9 x 9 x 4 m, the courtyard and every camera inside) whose only
    shader is a homogeneous Principled Volume of density 0.02-0.1 per m (anisotropy 0.1-0.6, a faint tint)."""
    d = Draw("fog", rng)
    mat = bpy.data.materials.new("Fog")
    nt = mat.node_tree
    for n in [n for n in nt.nodes if n.type != "OUTPUT_MATERIAL"]:
        nt.nodes.remove(n)
    vol = nt.nodes.new("ShaderNodeVolumePrincipled")
    vol.inputs["Density"].default_value = d("density_per_m")
    vol.inputs["Anisotropy"].default_value = d("anisotropy")
    vol.inputs["Color"].default_value = (*rng.uniform(0.85, 1.0, 3), 1.0)
    nt.links.new(vol.outputs["Volume"], nt.nodes["Material Output"].inputs["Volume"])
    bm = bmesh.new()
    box(bm, (0.0, 0.4, 1.95), (9.0, 9.0, 4.0))
    d.tag(add_object(scene, "Fog Volume", bm, mat))


def motion_objects(scene, mats, rng) -> None:
    """2-4 bevelled props (8-20 cm) flying over and behind the table (x -1.2..1.2, y 0.2..1.3, z 1.0..1.5), each
    keyed on every frame from start-1: a straight back-and-forth glide (over 0.3-0.6 m) at 1-6 cm a frame and a
    spin about a seeded axis at 2-12 degrees a frame, so that motion vectors carry object motion."""
    d = Draw("motion_objects", rng)
    frames = np.arange(scene.frame_start - 1, scene.frame_end + 1)
    t = (frames - frames[0]).astype(np.float64)
    for k in range(d("count", integer=True)):
        size, v, w = d("size_m"), d("m_per_frame"), math.radians(d("deg_per_frame"))
        cls = CLASSES[int(rng.integers(len(CLASSES)))]
        bm = bmesh.new()
        _bevelled(bm, ("cube", "cylinder", "sphere")[int(rng.integers(3))], (0.0, 0.0, 0.0), size, size / 10)
        mat = Mat(f"Mover {k + 1}", tuple(rng.uniform(0.1, 0.9, 3)), roughness=float(rng.uniform(0.1, 0.6)),
                  metallic=1.0 if cls in ("metal", "anisotropy") else 0.0).mat
        obj = add_object(scene, f"Mover {k + 1}", bm, mat)
        start = np.array([rng.uniform(-1.2, 1.2), rng.uniform(0.2, 1.3), rng.uniform(1.0, 1.5)])
        heading = rng.normal(size=3) * (1.0, 1.0, 0.3)
        span, phase = rng.uniform(0.3, 0.6), rng.uniform(0.0, 1.0)
        s = np.abs(((v * t / span + phase) % 2.0) - 1.0) * span      # a triangle wave in [0, span] metres
        axis = rng.normal(size=3)
        angle = w * t + rng.uniform(0.0, 2 * math.pi)
        quats = [Matrix.Rotation(a, 3, Vector(axis)).to_quaternion() for a in angle]
        obj.rotation_mode = "QUATERNION"
        key_channels(obj, frames, {"location": start + np.outer(s, heading / np.linalg.norm(heading)),
                                   "rotation_quaternion": np.array([tuple(q) for q in quats])})
        d.tag(obj)


def motion_character(scene, mats, rng) -> None:
    """1-2 walking figures (``character.py``: a mesh skinned to a 13-bone armature), each crossing the view along +X
    or -X at 3-7 cm a frame from x in -0.6..0.6, its thighs swinging 18-32 degrees, knees bent by 25-55 degrees
    mid-swing, arms swinging 12-30 degrees: deforming surfaces, keyed on every frame from start-1. The first
    (1.5-1.9 m) walks behind the table, the second (``front_height_m``, 1.45-1.65 m: between the table and the scene
    camera's arc, which comes to y -1.2 m, there is room for no taller one) in front of it (or, where a railing or a
    window takes the front, behind it like the first), each on a lane whose sides (measured over the walk) clear the
    table top by ``LANE_CLEARANCE``. Of the starts (x, lane, direction)
    drawn per walker (``_walker_starts``), those whose box clears every other object's box by ``LANE_CLEARANCE`` in
    every frame the clip renders (``placement.judged_frames``; ``gbuffer_export.sweep``: boxes topped within
    ``sweep.STEP_M`` of the ground are stepped through) are tried for the scene camera's view (``_seen_start``); a
    walker with none clear and in view is left out (the scene's ``placement.LEFT_OUT``). Build it after every other
    family, so that it sees them. Each walker's objects record its own draws (``family_params``) and its start
    (``WALK_START``)."""
    count = Draw("motion_character", rng)("count", integer=True)
    frames = np.arange(scene.frame_start - 1, scene.frame_end + 1)
    for k in range(count):
        d = Draw("motion_character", rng)
        d.params["count"] = count
        h, v = d("front_height_m" if k else "height_m"), d("m_per_frame")
        angles = {a: math.radians(d(f"{a}_deg")) for a in ("swing", "knee", "arm")}
        rig, body = build_figure(scene, f"Walker {k + 1}", h, _walker_materials(k, rng))
        phase = float(rng.uniform(0.0, 2 * math.pi))

        def key(start, rig=rig, h=h, v=v, angles=angles, phase=phase):     # (x, y, direction)
            placement.unkey(rig)
            key_walk(rig, frames, (float(start[0]), float(start[1])), start[2] * math.pi / 2, v, h, angles, phase)
        boxes = placement.measure(scene, body, key)
        starts = _walker_starts(k, boxes, rng)
        start = _seen_start(scene, body, key, starts[sweep.clear_mask(boxes, starts, LANE_CLEARANCE)])
        if start is None:
            log.info("motion_character: walker %d of %d left out: none of its %d starts clears the scene in the "
                     "camera's view", k + 1, count, len(starts))
            placement.remove(scene, rig, body)
            continue
        key(start)
        for ob in (rig, body):
            ob[WALK_START] = json.dumps({"x_m": float(start[0]), "lane_m": float(start[1]), "direction": int(start[2]),
                                         "frame_share": round(float(start[3]), 5)})
            d.tag(ob)


def _walker_starts(k: int, boxes: list, rng) -> np.ndarray:
    """The starts (x, lane y, direction +-1) drawn for walker ``k`` (``boxes``: ``placement.measure``'s), in the
    order they are tried: walker 0 ``PLACE_TRIES`` lanes behind the table, up to ``LANE_SPREAD`` back from its
    nearest, then as many behind the fence (``FENCE_LANE_Y``); walker 1 first ``PLACE_TRIES`` starts in front of
    the table, at its nearest lane (the camera's arc is close), then 32 more drawn as walker 0's are (for where a
    railing or a window takes the front; the boxes hold walker 0, so the two never meet)."""
    half = sweep.half_width(boxes)
    edge = TABLE_HALF_DEPTH + LANE_CLEARANCE + half
    if not k:
        return _behind_starts(edge, half, rng)
    front = np.column_stack([rng.uniform(-0.6, 0.6, PLACE_TRIES), -np.full(PLACE_TRIES, edge),
                             np.where(rng.uniform(size=PLACE_TRIES) < 0.5, 1.0, -1.0)])
    return np.vstack([front, _behind_starts(edge, half, rng)])


def _behind_starts(edge: float, half: float, rng) -> np.ndarray:
    """``PLACE_TRIES`` starts behind the table (lanes from ``edge`` back) and as many behind the fence."""
    lanes = (np.array([[edge], [FENCE_LANE_Y + half]]) + rng.uniform(0.0, LANE_SPREAD, (2, PLACE_TRIES))).ravel()
    n = len(lanes)
    return np.column_stack([rng.uniform(-0.6, 0.6, n), lanes, np.where(rng.uniform(size=n) < 0.5, 1.0, -1.0)])


def _seen_start(scene, body, key, starts: np.ndarray) -> np.ndarray | None:
    """Of ``starts`` (the clear ones, in the order drawn; the first ``SEEN_TRIES``), the first at which the walker
    covers at least ``SEEN_MIN`` of the scene camera's frame (``placement.frame_share`` on the first, middle and last
    frames shown), else the most seen; None without any, or when the most seen covers under ``SEEN_FLOOR`` (hidden:
    a wall between the camera and the lanes behind the fence). Returned as (x, y, direction, its frame share);
    ``key(start)`` keys the walker there."""
    shown = placement.judged_frames(scene)
    best, most = None, -1.0
    for start in starts[:SEEN_TRIES]:
        key(start)
        seen = placement.frame_share(scene, body, (shown[0], shown[len(shown) // 2], shown[-1]))
        if seen > most:
            best, most = np.append(start[:3], seen), seen
        if seen >= SEEN_MIN:
            break
    return best if most >= SEEN_FLOOR else None


def _walker_materials(k: int, rng) -> tuple:
    """Skin (subsurface), a sheen shirt and trousers of walker ``k``."""
    skin = Mat(f"Walker {k + 1} Skin", tuple(rng.uniform((0.25, 0.15, 0.1), (0.85, 0.6, 0.45))), roughness=0.45,
               inputs={"Subsurface Weight": 0.2}).mat
    shirt = Mat(f"Walker {k + 1} Shirt", tuple(rng.uniform(0.05, 0.9, 3)), roughness=0.8,
                inputs={"Sheen Weight": float(rng.uniform(0.2, 0.8))}).mat
    trousers = Mat(f"Walker {k + 1} Trousers", tuple(rng.uniform(0.03, 0.5, 3)),
                   roughness=float(rng.uniform(0.5, 0.9))).mat
    return skin, shirt, trousers


#: Family name -> (builder, stream): the stream of its generator (``np.random.default_rng([seed, stream])``).
FAMILIES = {
    **{f"mat_{p}": (material_family(p), 0x6A00 + i) for i, p in enumerate(SLOTS)},
    "mat_surfaces": (mat_surfaces, 0x6A10),
    "railing": (railing, 0x6B01), "wires": (wires, 0x6B02), "foliage_cards": (foliage_cards, 0x6B03),
    "stripes_panel": (stripes_panel, 0x6B04), "text_panel": (text_panel, 0x6B05), "scatter": (scatter, 0x6B06),
    "neon": (neon, 0x6C01), "small_emitters": (small_emitters, 0x6C02), "strong_sun": (strong_sun, 0x6C03),
    "night": (night, 0x6C04),
    "cam_pan": (cam_pan, 0x6D01), "cam_strafe": (cam_strafe, 0x6D02), "cam_turn": (cam_turn, 0x6D03),
    "cam_cut": (cam_cut, 0x6D04),
    "boolean": (boolean, 0x6B07), "displaced": (displaced, 0x6B08), "instanced": (instanced, 0x6B09),
    "fog": (fog, 0x6C05),
    "motion_objects": (motion_objects, 0x6E01), "motion_character": (motion_character, 0x6E02),
}

"""Opt-in props of the default scene (``props = [...]`` of a builtin dataset source): materials the courtyard
does not hold by default. Each prop draws from its own seeded generator, so a scene without it is the same scene
as before, and a scene with it keeps every other object where it was.

``broken_pane``: a cracked window pane in a painted wooden frame standing on the table's front half, facing the
courtyard camera: thin glass (transmission 1, a 4 mm slab) cut by an alpha mask into shards (cells 6-12 cm) along
cracks 3-8 mm wide, with 15-35 % of the shards missing (the scene seen through the holes), each shard tilted a little
(its own reflection), tinted edges with a metallic sheen along the cracks.

``window_pane``: the same cracked glass as a large window (1.3-1.7 x 0.75-0.95 m) in a frame standing on the floor
between the scene camera and the table, so that most of the frame is seen through glass: the table, its props and the
courtyard behind the pane. Units are metres.
"""
from __future__ import annotations

import bmesh
import numpy as np

from .families import FAMILIES
from .geometry import add_object, box
from .layout import TABLE_TOP_Z
from .materials import Mat, jitter_color


def add_props(scene, mats, seed: int, props) -> None:
    """Add each prop of ``props`` (names of ``OPTIONAL_PROPS``) with its own generator seeded by ``seed``. A camera
    family (``CAMERA_PROPS``) re-keys the scene camera: add it after the camera is keyed."""
    for name in props:
        build, stream, _ = _PROPS[name]
        build(scene, mats, np.random.default_rng([int(seed) & 0xFFFFFFFF, stream]))


def broken_pane(scene, mats, rng) -> None:
    """The pane (glass ``w`` x ``h``, 0.50-0.75 x 0.38-0.55 m) in a 3 cm frame whose bottom bar stands on the table
    top (its two feet sit inside the top, out of sight), at y = -0.22 m in front of the props, turned up to 0.1 rad
    about +Z; clear of the rolling ball's path (y = -0.35 m)."""
    w, h = rng.uniform(0.50, 0.75), rng.uniform(0.38, 0.55)
    x, rot = rng.uniform(-0.25, 0.25), rng.uniform(-0.1, 0.1)
    bar, z_glass = 0.03, TABLE_TOP_Z + 0.03 + h / 2  # frame bar (m); the glass above the bottom bar
    # sides as tall as the glass, and a foot under each (inside the table top, out of sight)
    _framed_pane(scene, mats, rng, "Broken Pane", (w, h, bar), (x, -0.22, z_glass), rot,
                 sides=((0.0, bar, h), (-(h / 2 + bar + 0.0125), 0.16, 0.025)))


def window_pane(scene, mats, rng) -> None:
    """A window (glass ``w`` x ``h``) whose frame stands on the floor at y = -0.65 m, between the scene camera's arc
    (y -1.8 to -1.2 m) and the table's front edge (y -0.45 m), its centre near the height where the camera's line
    of sight crosses it (about z 1.07-1.26 m; z 1.08-1.16), turned up to 0.12 rad about +Z. Its feet (0.3 m deep)
    end at least 2 mm short of the table's front legs."""
    w, h = rng.uniform(1.3, 1.7), rng.uniform(0.75, 0.95)
    x, z, rot = rng.uniform(-0.1, 0.1), rng.uniform(1.08, 1.16), rng.uniform(-0.12, 0.12)
    bar = 0.04                                                 # frame bar (m)
    post = z + h / 2 + bar                                     # the posts reach from the floor to the top bar
    _framed_pane(scene, mats, rng, "Window Pane", (w, h, bar), (x, -0.65, z), rot,
                 sides=((h / 2 + bar - post / 2, bar, post), (0.0125 - z, 0.3, 0.025)))  # posts, feet on the floor


def _framed_pane(scene, mats, rng, name: str, size, loc, rot: float, sides) -> None:
    """The objects "NAME Glass" (``_cracked_glass``, a 4 mm slab ``w`` x ``h`` of ``size`` = (w, h, bar)) and "NAME
    Frame" (paint: a top and a bottom bar ``bar`` thick, and on each side, x = +-(w + bar) / 2, a box per entry of
    ``sides``, (z centre, depth along y, height), in the pane's frame), both at ``loc`` turned by ``rot`` about +Z."""
    w, h, bar = size
    rotation = (0.0, 0.0, rot)
    bm = bmesh.new()
    box(bm, (0.0, 0.0, 0.0), (w, 0.004, h))
    add_object(scene, f"{name} Glass", bm, _cracked_glass(rng), location=loc, rotation=rotation)
    bm = bmesh.new()
    for sz in (-1, 1):   # top and bottom bars
        box(bm, (0.0, 0.0, sz * (h + bar) / 2), (w + 2 * bar, bar, bar))
    for sx in (-1, 1):
        for zc, depth, height in sides:
            box(bm, (sx * (w + bar) / 2, 0.0, zc), (bar, depth, height))
    add_object(scene, f"{name} Frame", bm, mats["paint"], location=loc, rotation=rotation)


def _cracked_glass(rng):
    """Glass whose alpha is 0 on cracks (Voronoi cell edges in the pane's x-z plane) and on missing shards (cells
    whose random value is above the kept fraction); the shard's normal tilted by its cell colour."""
    m = Mat("Broken Glass", jitter_color(rng, (0.75, 0.9, 1.0), 0.1), roughness=float(rng.uniform(0.02, 0.08)),
            inputs={"Transmission Weight": 1.0, "IOR": 1.5})
    scale, crack = float(rng.uniform(8.0, 16.0)), float(rng.uniform(0.0015, 0.004))  # cells per m; crack half-width m
    keep = float(rng.uniform(0.65, 0.85))
    co = m.coords(swizzle="XZY")             # the pane's plane is object x-z: both faces get the same shards
    cells = m.node("ShaderNodeTexVoronoi", voronoi_dimensions="2D", feature="F1", Scale=scale)
    edges = m.node("ShaderNodeTexVoronoi", voronoi_dimensions="2D", feature="DISTANCE_TO_EDGE", Scale=scale)
    offset = m.node("ShaderNodeVectorMath", operation="ADD")
    offset.inputs[1].default_value = (*rng.uniform(-50.0, 50.0, size=2), 0.0)  # which shards: seeded
    m.link(co, offset.inputs[0])
    for v in (cells, edges):
        m.link(offset.outputs["Vector"], v.inputs["Vector"])
    # Distance to edge is in cell units: a crack of ``crack`` metres is crack * scale of them.
    dist = edges.outputs["Distance"]
    solid = m.math("GREATER_THAN", dist, crack * scale)
    rnd = m.node("ShaderNodeSeparateColor")
    m.link(cells.outputs["Color"], rnd.inputs["Color"])
    kept = m.math("LESS_THAN", rnd.outputs["Red"], keep)     # a cell's red: uniform in [0, 1)
    m.link(m.math("MULTIPLY", solid, kept), m.bsdf.inputs["Alpha"])
    near = m.math("LESS_THAN", dist, 1.8 * crack * scale)
    m.link(m.math("MULTIPLY", near, 0.7), m.bsdf.inputs["Metallic"])
    edge_tint = (*jitter_color(rng, (0.5, 0.8, 0.7), 0.15), 1.0)
    m.link(m.mix(near, tuple(m.bsdf.inputs["Base Color"].default_value), edge_tint), m.bsdf.inputs["Base Color"])
    tilt = m.node("ShaderNodeVectorMath", operation="MULTIPLY_ADD")
    m.link(cells.outputs["Color"], tilt.inputs[0])
    tilt.inputs[1].default_value = (0.12, 0.12, 0.12)
    tilt.inputs[2].default_value = (-0.06, -0.06, -0.06)
    geo = m.node("ShaderNodeNewGeometry")
    add = m.node("ShaderNodeVectorMath", operation="ADD")
    m.link(geo.outputs["Normal"], add.inputs[0])
    m.link(tilt.outputs["Vector"], add.inputs[1])
    norm = m.node("ShaderNodeVectorMath", operation="NORMALIZE")
    m.link(add.outputs["Vector"], norm.inputs[0])
    m.link(norm.outputs["Vector"], m.bsdf.inputs["Normal"])
    return m.mat


#: Each prop: (builder, its generator's stream, the objects it adds; the generator's families of ``families.py``
#: tag theirs with ``blendsr_family`` instead, as their number is drawn).
_PROPS = {"broken_pane": (broken_pane, 0x9A7E, ("Broken Pane Glass", "Broken Pane Frame")),
          "window_pane": (window_pane, 0x3D15, ("Window Pane Glass", "Window Pane Frame")),
          **{name: (build, stream, ()) for name, (build, stream) in FAMILIES.items()}}
#: The families that re-key the scene camera (added after it).
CAMERA_PROPS = tuple(n for n in FAMILIES if n.startswith("cam_"))
#: The families placed clear of every other object (added last, when every other object is there).
LAST_PROPS = ("motion_character",)
#: Opt-in props -> the objects they add (docs and tests; the spec's ``BUILTIN_PROPS`` names the same props).
OPTIONAL_PROPS: dict[str, tuple[str, ...]] = {name: p[2] for name, p in _PROPS.items()}

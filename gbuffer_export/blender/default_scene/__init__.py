"""The built-in default scene: a small courtyard still life built in code (bpy layer).

A café table on a tiled courtyard floor in front of a picket fence with a wire-mesh panel, a brick wall, string
lights and a painted sign, with props chosen for what a super-resolution network finds hard: sub-pixel wires,
fine checkers, text and text-like stripes, mirror-like and rough metals, an anisotropic brushed pot, glass, a
subsurface candle, small emissive bulbs and a ball rolling across the table. Lit by one of the HDR environments that
ship inside bpy plus a sun. Units are metres; +Z is up; the camera looks roughly along +Y.

Everything is deterministic in ``seed``: the seed moves and turns the props a little, varies colours, picks the
environment, its rotation, the sun and the camera's motion. Nothing is written to disk; the render engine and its
sampling are left to the caller.

Modules: ``layout`` (where things are, the animation), ``materials``, ``lights`` (environment and sun),
``geometry`` (bmesh building blocks), ``props`` (opt-in props such as a broken glass pane), ``families`` (the
generator's opt-in families: procedural materials, thin and high-frequency geometry, game lights, game camera motion).
"""
from __future__ import annotations

import bpy
import numpy as np

from ...errors import BlendSRError
from .layout import TABLE_TOP_Z, animated_camera, courtyard, rolling_ball, table_and_props
from .lights import STUDIOLIGHTS, hdri_path, make_world, seeded_world, studiolight_path, sun_lamp
from .materials import make_materials
from .placement import LEFT_OUT, PLACED_FRAMES
from .props import CAMERA_PROPS, LAST_PROPS, OPTIONAL_PROPS, add_props

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


def build_default_scene(seed: int = 0, frames: tuple[int, int] = (1, 48),
                        resolution: tuple[int, int] = (640, 360), world: dict | None = None,
                        sun: bool = True, props: tuple[str, ...] = (),
                        shown: tuple[int, int] | None = None) -> bpy.types.Scene:
    """Reset Blender to an empty factory state and build the default courtyard scene in it.

    ``frames``: inclusive (start, end); animation is keyed on every frame from start-1 to end. ``resolution``:
    (width, height) in pixels at 100%. ``world``: replaces the seed's environment ({"hdri": path or
    "builtin:NAME", "rotation_deg": about +Z, "strength": multiplier of the normalised sky}); the layout, materials
    and camera of the seed stay the same. ``sun``: False removes the sun lamp. ``props``: opt-in props
    (``OPTIONAL_PROPS``, e.g. ``("broken_pane",)``), each from its own seeded stream: every other object stays as
    without them. ``shown``: the inclusive frames a clip will render (default ``frames``): what is placed clear of
    everything else (the walkers) is judged on those (``PLACED_FRAMES``). Returns the scene (also
    ``bpy.context.scene``). Engine and sampling are left at the factory values; the caller sets them."""
    start, end = int(frames[0]), int(frames[1])
    unknown = [p for p in props if p not in OPTIONAL_PROPS]
    if unknown:
        raise BlendSRError(f"props {', '.join(unknown)}: choose from {', '.join(OPTIONAL_PROPS)}")
    if end < start:
        raise BlendSRError(f"frames {start}:{end}: end is before start")
    w, h = int(resolution[0]), int(resolution[1])
    if w <= 0 or h <= 0:
        raise BlendSRError(f"resolution {w}x{h}: must be positive")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = start, end
    scene.frame_current = start
    scene.render.resolution_x, scene.render.resolution_y = w, h
    scene.render.resolution_percentage = 100
    scene.render.fps = 24
    scene["blendsr_default_scene_seed"] = int(seed)
    if shown is not None:
        scene[PLACED_FRAMES] = [int(f) for f in shown]

    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x5CE7E])
    frames_all = np.arange(start - 1, end + 1)
    mats = make_materials(rng)
    sun_lamp(scene, rng, seeded_world(scene, rng, world))
    if not sun:
        bpy.data.objects.remove(bpy.data.objects["Sun"], do_unlink=True)
    courtyard(scene, mats, rng)
    table_and_props(scene, mats, rng)
    add_props(scene, mats, seed, [p for p in props if p not in CAMERA_PROPS + LAST_PROPS])
    rolling_ball(scene, mats, rng, frames_all)
    animated_camera(scene, rng, frames_all)
    add_props(scene, mats, seed, [p for p in props if p in CAMERA_PROPS])
    add_props(scene, mats, seed, [p for p in props if p in LAST_PROPS])
    scene.frame_set(start)
    return scene


__all__ = ["DEFAULT_SCENE_FEATURES", "LEFT_OUT", "OPTIONAL_PROPS", "STUDIOLIGHTS", "TABLE_TOP_Z", "build_default_scene",
           "hdri_path",
           "make_world", "studiolight_path"]

"""Lighting of the default scene: an HDR environment (one of bpy's studiolights, or a given file) normalised to a
sky luminance, and a sun lamp along the environment's own sun when it has one."""
from __future__ import annotations

import math
from pathlib import Path

import bpy
import numpy as np

from ...errors import BlendSRError
from ..camera_paths import look_at_matrix

#: Environments (files ``<name>.exr`` in bpy's ``studiolights/world``) the seed picks from.
STUDIOLIGHTS = ("courtyard", "forest", "sunset", "city", "sunrise")


def studiolight_path(name: str) -> Path:
    """Path of one of bpy's bundled HDR environments (e.g. ``"courtyard"``); FileNotFoundError if missing."""
    root = bpy.utils.system_resource("DATAFILES", path="studiolights/world")
    path = Path(root) / f"{name}.exr"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: bpy studiolight {name!r} not found")
    return path


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
        raise BlendSRError(f"{image_path}: the HDRI could not be read")
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


def seeded_world(scene, rng, override: dict | None = None) -> np.ndarray | None:
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


def sun_lamp(scene, rng, env_sun: np.ndarray | None) -> None:
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

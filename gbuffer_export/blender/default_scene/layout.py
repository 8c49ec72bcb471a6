"""Layout of the default scene: the courtyard (floor, fence, wire mesh, string lights, sign, brick wall, potted
shrub), the table and its props, the rolling ball and the animated camera. Units are metres; +Z is up."""
from __future__ import annotations

import math

import bmesh
import bpy
import numpy as np

from ..camera_paths import GROUND_PROPERTY, key_channels, key_look_at
from .geometry import add_object, box, catenary, cylinder, lathe, prism_xz, sphere, text_object, tube

TABLE_TOP_Z = 0.76  # m, height of the table's top surface


def courtyard(scene, mats, rng) -> None:
    """Floor, picket fence, wire mesh, string lights, sign, brick wall and the potted shrub."""
    # Floor (ground) 16 x 16 m.
    bm = bmesh.new()
    box(bm, (0.0, 0.0, -0.05), (16.0, 16.0, 0.1))
    floor = add_object(scene, "Floor", bm, mats["floor"])
    floor[GROUND_PROPERTY] = True

    fy = 1.6
    _fence(scene, mats, fy)
    _string_lights(scene, mats, fy)
    _sign(scene, mats, fy)

    # Brick wall on the left.
    bm = bmesh.new()
    box(bm, (0.0, 0.0, 0.0), (0.25, 4.6, 1.8))
    add_object(scene, "Brick Wall", bm, mats["brick"], location=(-3.1, -0.65, 0.9))

    # Terracotta pot with a boxwood ball in front of the wire panel.
    pot = [(0.0, 0.0), (0.17, 0.0), (0.24, 0.38), (0.26, 0.40), (0.26, 0.43), (0.22, 0.43), (0.0, 0.36)]
    bm = bmesh.new()
    lathe(bm, pot, segments=40)
    px = 1.9 + rng.uniform(-0.15, 0.15)
    add_object(scene, "Terracotta Pot", bm, mats["terracotta"], location=(px, 1.05, 0.0))
    bm = bmesh.new()
    sphere(bm, (0.0, 0.0, 0.0), 0.3, 40, 20)
    add_object(scene, "Shrub", bm, mats["boxwood"], location=(px, 1.05, 0.62))


def _fence(scene, mats, fy: float) -> None:
    """The picket fence along y = ``fy`` from x = -2.8 to 0.8 (pickets, rails, posts) and the wire-mesh panel from
    0.8 to 2.8."""
    bm = bmesh.new()
    w, h = 0.045, 1.05
    for k, x in enumerate(np.arange(-2.75, 0.76, 0.085)):
        hh = h + 0.02 * math.sin(1.7 * k)
        outline = [(x - w / 2, 0.03), (x + w / 2, 0.03), (x + w / 2, hh), (x, hh + 0.03), (x - w / 2, hh)]
        prism_xz(bm, outline, fy - 0.01, fy + 0.01)
    add_object(scene, "Fence Pickets", bm, mats["paint"])
    bm = bmesh.new()
    for z in (0.25, 0.85):
        box(bm, (-1.0, fy + 0.035, z), (3.6, 0.05, 0.09))
    add_object(scene, "Fence Rails", bm, mats["paint"])
    bm = bmesh.new()
    for x in (-2.85, -1.0, 0.8, 2.85):
        box(bm, (x, fy + 0.02, 0.6), (0.09, 0.09, 1.2))
    add_object(scene, "Fence Posts", bm, mats["paint"])
    bm = bmesh.new()
    for z in np.arange(0.1, 1.11, 0.05):
        tube(bm, np.array([[0.85, fy, z], [2.8, fy, z]]), 0.0018, 5)
    for x in np.arange(0.875, 2.8, 0.05):
        tube(bm, np.array([[x, fy - 0.004, 0.08], [x, fy - 0.004, 1.12]]), 0.0018, 5)
    add_object(scene, "Wire Mesh", bm, mats["wire"])


def _string_lights(scene, mats, fy: float) -> None:
    """A sagging wire over the fence with small emissive bulbs."""
    p0, p1 = np.array([-2.85, fy - 0.05, 1.42]), np.array([2.85, fy - 0.05, 1.42])
    pts = catenary(p0, p1, 0.16, 64)
    bm = bmesh.new()
    tube(bm, pts, 0.0025, 6)
    add_object(scene, "Light String", bm, mats["wire"])
    bm = bmesh.new()
    for t in np.linspace(0.04, 0.96, 19):
        p = catenary(p0, p1, 0.16, 1001)[int(round(t * 1000))]
        sphere(bm, (p[0], p[1], p[2] - 0.035), 0.018, 12, 8)
    add_object(scene, "Light Bulbs", bm, mats["bulb"])


def _sign(scene, mats, fy: float) -> None:
    """A painted board with three lines of text on the fence."""
    bm = bmesh.new()
    box(bm, (0.0, 0.0, 0.0), (1.22, 0.02, 0.34))
    add_object(scene, "Sign Board", bm, mats["sign"], location=(-1.3, fy - 0.035, 0.8))
    text_object(scene, "Sign Letters", "GARDEN CAFE\nopen daily 8 - 22  *  fresh bread  *  espresso\n"
                 "no. 17  -  courtyard entrance  -  please close the gate", 0.052, mats["letters"],
                 location=(-1.3, fy - 0.046, 0.81), rotation=(math.pi / 2, 0.0, 0.0))


def table_and_props(scene, mats, rng) -> None:
    """The table (top at ``TABLE_TOP_Z``) and the props on it, each moved and turned a little by ``rng`` (in this
    order: the front props', then the back row's draws)."""
    _table(scene, mats)

    def jit(x, y, r=0.02):
        return x + rng.uniform(-r, r), y + rng.uniform(-r, r)
    _front_props(scene, mats, rng, jit)
    _back_row(scene, mats, rng, jit)


def _table(scene, mats) -> None:
    """A wooden table top at ``TABLE_TOP_Z`` on four legs."""
    z0 = TABLE_TOP_Z
    bm = bmesh.new()
    box(bm, (0.0, 0.0, z0 - 0.02), (1.6, 0.9, 0.04))
    for sx in (-1, 1):
        for sy in (-1, 1):
            box(bm, (sx * 0.72, sy * 0.37, (z0 - 0.04) / 2), (0.05, 0.05, z0 - 0.04))
    add_object(scene, "Table", bm, mats["wood"])


def _front_props(scene, mats, rng, jit) -> None:
    """Placemat with a ceramic bowl and a chrome sphere; newspaper with a glass paperweight."""
    z0 = TABLE_TOP_Z
    x, y = jit(-0.42, 0.0)
    bm = bmesh.new()
    box(bm, (0.0, 0.0, 0.0), (0.44, 0.32, 0.002))
    add_object(scene, "Placemat", bm, mats["checker"], location=(x, y, z0 + 0.001),
            rotation=(0.0, 0.0, rng.uniform(-0.15, 0.15)))
    mx, my = x, y

    x, y = jit(0.36, -0.08)
    bm = bmesh.new()
    box(bm, (0.0, 0.0, 0.0), (0.43, 0.32, 0.002))
    add_object(scene, "Newspaper", bm, mats["newsprint"], location=(x, y, z0 + 0.001),
            rotation=(0.0, 0.0, rng.uniform(0.05, 0.2)))
    bm = bmesh.new()
    sphere(bm, (0.0, 0.0, 0.0), 0.035, 48, 24)
    add_object(scene, "Glass Paperweight", bm, mats["glass"], location=(x + 0.07, y - 0.04, z0 + 0.002 + 0.035))

    # Ceramic bowl on the placemat with a chrome sphere next to it.
    bowl = [(0.0, 0.0), (0.04, 0.0), (0.055, 0.006), (0.08, 0.035), (0.09, 0.062), (0.087, 0.065),
            (0.082, 0.062), (0.072, 0.036), (0.05, 0.012), (0.0, 0.009)]
    bm = bmesh.new()
    lathe(bm, bowl, segments=48)
    add_object(scene, "Ceramic Bowl", bm, mats["ceramic"], location=(mx - 0.07, my + 0.04, z0 + 0.002))
    bm = bmesh.new()
    sphere(bm, (0.0, 0.0, 0.0), 0.05)
    add_object(scene, "Chrome Sphere", bm, mats["chrome"], location=(mx + 0.12, my - 0.07, z0 + 0.002 + 0.05))


def _back_row(scene, mats, rng, jit) -> None:
    """Gold dish, copper cup, brushed pot, glass vase, candle and red cube."""
    z0 = TABLE_TOP_Z
    dish = [(0.0, 0.0), (0.05, 0.0), (0.1, 0.012), (0.12, 0.022), (0.116, 0.024), (0.095, 0.016),
            (0.0, 0.006)]
    bm = bmesh.new()
    lathe(bm, dish, segments=56)
    x, y = jit(-0.1, 0.22)
    add_object(scene, "Gold Dish", bm, mats["gold"], location=(x, y, z0))

    cup = [(0.0, 0.0), (0.035, 0.0), (0.04, 0.005), (0.042, 0.09), (0.038, 0.09), (0.036, 0.008), (0.0, 0.008)]
    bm = bmesh.new()
    lathe(bm, cup, segments=40)
    x, y = jit(0.12, 0.12)
    add_object(scene, "Copper Cup", bm, mats["copper"], location=(x, y, z0))

    pot = [(0.0, 0.0), (0.075, 0.0), (0.08, 0.006), (0.08, 0.13), (0.085, 0.135), (0.085, 0.14), (0.072, 0.14),
           (0.072, 0.012), (0.0, 0.012)]
    bm = bmesh.new()
    lathe(bm, pot, segments=64)
    x, y = jit(0.5, 0.22)
    add_object(scene, "Brushed Pot", bm, mats["brushed"], location=(x, y, z0))

    vase = [(0.0, 0.0), (0.04, 0.0), (0.05, 0.02), (0.056, 0.08), (0.042, 0.15), (0.024, 0.2), (0.03, 0.245),
            (0.026, 0.245), (0.02, 0.2), (0.037, 0.15), (0.051, 0.08), (0.045, 0.022), (0.036, 0.008),
            (0.0, 0.008)]
    bm = bmesh.new()
    lathe(bm, vase, segments=64)
    x, y = jit(-0.58, 0.27)
    add_object(scene, "Glass Vase", bm, mats["glass"], location=(x, y, z0))

    bm = bmesh.new()
    cylinder(bm, (0.0, 0.0, 0.0), 0.028, 0.16, 32)
    x, y = jit(-0.3, 0.3)
    add_object(scene, "Candle", bm, mats["wax"], location=(x, y, z0 + 0.08))

    bm = bmesh.new()
    box(bm, (0.0, 0.0, 0.0), (0.06, 0.06, 0.06))
    x, y = jit(0.27, 0.3)
    add_object(scene, "Red Cube", bm, mats["plastic"], location=(x, y, z0 + 0.03),
            rotation=(0.0, 0.0, rng.uniform(0.0, math.pi / 2)))


def rolling_ball(scene, mats, rng, frames_all: np.ndarray) -> None:
    """A ball rolling back and forth along the table's front edge (rolls without slipping about +Y)."""
    radius = 0.045
    bm = bmesh.new()
    sphere(bm, (0.0, 0.0, 0.0), radius, 40, 20)
    obj = add_object(scene, "Rolling Ball", bm, mats["ball"])
    period = rng.uniform(60.0, 90.0)   # frames
    phase = rng.uniform(0.0, 2.0 * math.pi)
    amp, xc = 0.5, 0.0
    t = frames_all.astype(np.float64)
    x = xc + amp * np.sin(2.0 * math.pi * t / period + phase)
    loc = np.stack([x, np.full_like(x, -0.35), np.full_like(x, TABLE_TOP_Z + radius)], axis=1)
    rot = np.stack([np.zeros_like(x), (x - xc) / radius, np.zeros_like(x)], axis=1)
    obj.rotation_mode = "XYZ"
    key_channels(obj, frames_all, {"location": loc, "rotation_euler": rot})


def animated_camera(scene, rng, frames_all: np.ndarray) -> None:
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

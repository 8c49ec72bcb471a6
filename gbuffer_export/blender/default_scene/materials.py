"""Materials of the default scene: one Principled BSDF each, some driven by procedural textures (stone tiles,
bricks, wood planks, checkers, newsprint, foliage), with seeded colour variations."""
from __future__ import annotations

import bpy
import numpy as np


class Mat:
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


def jitter_color(rng, color, amount=0.06):
    """``color`` with each channel scaled by a seeded factor in [1 - amount, 1 + amount], clipped to [0, 1]."""
    return tuple(float(np.clip(c * (1.0 + rng.uniform(-amount, amount)), 0.0, 1.0)) for c in color)


def make_materials(rng) -> dict[str, bpy.types.Material]:
    """Every material of the scene by role ('floor', 'brick', 'wood', ..., 'ball'); colours varied by ``rng`` (drawn
    in this order: floor, brick, checker, gold, plastic)."""
    mats: dict[str, bpy.types.Material] = {}
    mats["floor"] = _stone_tiles(rng)
    mats["brick"] = _red_brick(rng)
    mats["wood"] = _oak()
    mats["checker"] = _checker_cloth(rng)
    mats["newsprint"] = _newsprint()
    mats.update(_plain_materials(rng))
    mats["boxwood"] = _boxwood()
    mats["ball"] = _toy_ball()
    return mats


def _stone_tiles(rng):
    """Stone tiles (30 cm) with 6 mm grout, per-tile colour variation and grime."""
    m = Mat("Stone Tiles", roughness=0.7)
    brick = m.node("ShaderNodeTexBrick", offset=0.0, offset_frequency=1, squash=1.0, squash_frequency=1)
    for k, v in {"Color1": (*jitter_color(rng, (0.36, 0.33, 0.30)), 1), "Color2": (0.52, 0.48, 0.42, 1),
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
    return m.mat


def _red_brick(rng):
    """Red brick wall: bricks run along the wall (object y) in rows up z."""
    m = Mat("Red Brick", roughness=0.85)
    brick = m.node("ShaderNodeTexBrick", offset=0.5, offset_frequency=2, squash=1.0, squash_frequency=2)
    for k, v in {"Color1": (0.42, 0.12, 0.07, 1), "Color2": (*jitter_color(rng, (0.55, 0.22, 0.12)), 1),
                 "Mortar": (0.55, 0.53, 0.48, 1), "Scale": 1.0, "Mortar Size": 0.008, "Mortar Smooth": 0.1,
                 "Bias": 0.0, "Brick Width": 0.22, "Row Height": 0.075}.items():
        brick.inputs[k].default_value = v
    m.link(m.coords(swizzle="YZX"), brick.inputs["Vector"])
    m.link(brick.outputs["Color"], m.bsdf.inputs["Base Color"])
    return m.mat


def _oak():
    """Table wood: planks 15 cm wide along the table (x) with 3 mm dark joints and fine, slightly wavy grain."""
    m = Mat("Oak", roughness=0.5)
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
    return m.mat


def _checker_cloth(rng):
    """Checkered placemat, 2 cm squares."""
    m = Mat("Checker Cloth", roughness=0.8)
    chk = m.node("ShaderNodeTexChecker", Scale=50.0)
    chk.inputs["Color1"].default_value = (0.80, 0.78, 0.72, 1)
    chk.inputs["Color2"].default_value = (*jitter_color(rng, (0.55, 0.04, 0.04)), 1)
    m.link(m.coords(), chk.inputs["Vector"])
    m.link(chk.outputs["Color"], m.bsdf.inputs["Base Color"])
    return m.mat


def _newsprint():
    """Newspaper: rows of word-like blocks (lines 5.7 mm apart) in two columns with a headline band (object coords
    of a 43 x 32 cm sheet, scaled to a 32 x 24 cm layout)."""
    m = Mat("Newsprint", roughness=0.85)
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
    return m.mat


def _plain_materials(rng) -> dict:
    """The single-colour materials by role (gold and plastic colours varied by ``rng``)."""
    mats = {}
    mats["paint"] = Mat("White Paint", (0.72, 0.70, 0.64), roughness=0.55).mat
    mats["sign"] = Mat("Green Paint", (0.03, 0.13, 0.07), roughness=0.6).mat
    mats["letters"] = Mat("Cream Paint", (0.85, 0.78, 0.58), roughness=0.45).mat
    mats["wire"] = Mat("Dark Steel", (0.25, 0.25, 0.27), metallic=1.0, roughness=0.35).mat
    mats["chrome"] = Mat("Chrome", (0.90, 0.90, 0.92), metallic=1.0, roughness=0.05).mat
    mats["gold"] = Mat("Gold", jitter_color(rng, (1.0, 0.77, 0.34), 0.03), metallic=1.0, roughness=0.3).mat
    mats["copper"] = Mat("Copper", (0.95, 0.60, 0.45), metallic=1.0, roughness=0.6).mat
    mats["brushed"] = Mat("Brushed Steel", (0.80, 0.80, 0.80), metallic=1.0, roughness=0.35,
                           inputs={"Anisotropic": 0.8, "Anisotropic Rotation": 0.0}).mat
    mats["glass"] = Mat("Glass", (0.97, 1.0, 0.98), roughness=0.0,
                         inputs={"Transmission Weight": 1.0, "IOR": 1.5}).mat
    mats["ceramic"] = Mat("Ceramic", (0.85, 0.85, 0.82), roughness=0.12).mat
    mats["plastic"] = Mat("Red Plastic", jitter_color(rng, (0.70, 0.05, 0.04)), roughness=0.4).mat
    mats["terracotta"] = Mat("Terracotta", (0.55, 0.23, 0.12), roughness=0.85).mat
    mats["wax"] = Mat("Candle Wax", (0.90, 0.85, 0.70), roughness=0.4,
                       inputs={"Subsurface Weight": 1.0, "Subsurface Radius": (1.0, 0.5, 0.25),
                               "Subsurface Scale": 0.02}).mat
    mats["bulb"] = Mat("Warm Bulb", (1.0, 0.78, 0.45), roughness=0.3,
                        inputs={"Emission Color": (1.0, 0.72, 0.38), "Emission Strength": 25.0}).mat
    return mats


def _boxwood():
    """Boxwood: fine leafy speckle."""
    m = Mat("Boxwood", roughness=0.7)
    n = m.node("ShaderNodeTexNoise", Scale=90.0, Detail=4.0, Roughness=0.7)
    m.link(m.coords(), n.inputs["Vector"])
    m.link(m.ramp(n.outputs["Factor"], [(0.35, (0.02, 0.06, 0.015)), (0.65, (0.12, 0.28, 0.05))]),
           m.bsdf.inputs["Base Color"])
    return m.mat


def _toy_ball():
    """Toy ball: coarse checker in object space so that its rolling is visible."""
    m = Mat("Toy Ball", roughness=0.25)
    chk = m.node("ShaderNodeTexChecker", Scale=28.0)
    chk.inputs["Color1"].default_value = (0.85, 0.62, 0.05, 1)
    chk.inputs["Color2"].default_value = (0.05, 0.15, 0.55, 1)
    m.link(m.coords(), chk.inputs["Vector"])
    m.link(chk.outputs["Color"], m.bsdf.inputs["Base Color"])
    return m.mat

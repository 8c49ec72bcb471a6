"""White-furnace scene for measuring F_beta (bpy layer).

A uniform world of radiance 1 (the world's Background node) and a grid of smooth spheres, one Principled material
each, invisible to every secondary ray (diffuse, glossy, transmission, volume scatter, shadow), visible to camera
rays. Every path leaving a sphere then sees radiance 1, so the rendered radiance minus emission is exactly the
directional albedo F_beta of the material at each pixel's view direction (up to Monte Carlo noise).

``build_furnace_scene`` saves the scene as a .blend and returns its layout (sphere centres, radius, material of
each sphere) so that pixels can be assigned to materials by ray casting in numpy (``gbuffer_export.furnace_layout``).
Run it in a subprocess (``python -m gbuffer_export.blender.furnace OUT.blend LAYOUT.json --size W H``).
"""
from __future__ import annotations

import json
import math
import sys
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path

import bpy
import bmesh  # noqa: E402  (bmesh exists only once bpy is imported)


@dataclass(frozen=True)
class FurnaceMaterial:
    """One sphere's material: Principled inputs by socket name, plus node options. ``group`` is 'standard' for
    opaque dielectrics and metals (the model's target), 'layered' for glass/coat/sheen/emission, 'hard' for the
    features the G-buffers cannot describe."""

    name: str
    group: str
    inputs: dict = field(default_factory=dict)
    distribution: str = "MULTI_GGX"
    bump: float = 0.0


def _materials() -> list[FurnaceMaterial]:
    out = []
    colours = {"white": (1.0, 1.0, 1.0), "grey": (0.5, 0.5, 0.5), "black": (0.0, 0.0, 0.0),
               "orange": (0.8, 0.3, 0.05)}
    roughs = (0.05, 0.2, 0.5, 0.8, 1.0)
    for cname, c in colours.items():
        for r in roughs:
            out.append(FurnaceMaterial(f"diel_{cname}_r{r:.2f}", "standard",
                                       {"Base Color": (*c, 1.0), "Roughness": r, "Metallic": 0.0}))
    metals = {"silver": (0.95, 0.93, 0.88), "gold": (1.0, 0.71, 0.29)}
    for cname, c in metals.items():
        for r in roughs:
            out.append(FurnaceMaterial(f"metal_{cname}_r{r:.2f}", "standard",
                                       {"Base Color": (*c, 1.0), "Roughness": r, "Metallic": 1.0}))
    out += [
        FurnaceMaterial("metal_black_r0.50", "standard", {"Base Color": (0, 0, 0, 1), "Roughness": 0.5,
                                                          "Metallic": 1.0}),
        FurnaceMaterial("metal_half_grey_r0.30", "standard", {"Base Color": (0.5, 0.5, 0.5, 1), "Roughness": 0.3,
                                                              "Metallic": 0.5}),
        FurnaceMaterial("diel_white_ior1.33_r0.30", "standard", {"Base Color": (1, 1, 1, 1), "Roughness": 0.3,
                                                                 "IOR": 1.33}),
        FurnaceMaterial("diel_grey_ior2.0_r0.30", "standard", {"Base Color": (0.5, 0.5, 0.5, 1), "Roughness": 0.3,
                                                               "IOR": 2.0}),
        FurnaceMaterial("diel_grey_level1_r0.30", "standard", {"Base Color": (0.5, 0.5, 0.5, 1), "Roughness": 0.3,
                                                               "Specular IOR Level": 1.0}),
        FurnaceMaterial("diel_black_level0_r0.30", "standard", {"Base Color": (0, 0, 0, 1), "Roughness": 0.3,
                                                                "Specular IOR Level": 0.0}),
        FurnaceMaterial("glass_r0.00", "layered", {"Base Color": (1, 1, 1, 1), "Roughness": 0.0,
                                                   "Transmission Weight": 1.0}),
        FurnaceMaterial("glass_r0.30", "layered", {"Base Color": (1, 1, 1, 1), "Roughness": 0.3,
                                                   "Transmission Weight": 1.0}),
        FurnaceMaterial("glass_tinted_r0.10", "layered", {"Base Color": (0.3, 0.8, 0.4, 1), "Roughness": 0.1,
                                                          "Transmission Weight": 1.0}),
        FurnaceMaterial("coat_orange_r0.50", "layered", {"Base Color": (0.8, 0.3, 0.05, 1), "Roughness": 0.5,
                                                         "Coat Weight": 1.0, "Coat Roughness": 0.05}),
        FurnaceMaterial("sheen_grey_r0.50", "layered", {"Base Color": (0.5, 0.5, 0.5, 1), "Roughness": 0.5,
                                                        "Sheen Weight": 1.0, "Sheen Roughness": 0.5}),
        FurnaceMaterial("emissive_grey_r0.40", "layered", {"Base Color": (0.5, 0.5, 0.5, 1), "Roughness": 0.4,
                                                           "Emission Color": (1.0, 0.5, 0.2, 1.0),
                                                           "Emission Strength": 0.7}),
        FurnaceMaterial("hard_aniso_metal_r0.40", "hard", {"Base Color": (0.95, 0.93, 0.88, 1), "Roughness": 0.4,
                                                           "Metallic": 1.0, "Anisotropic": 0.8}),
        FurnaceMaterial("hard_spectint_metal_r0.40", "hard", {"Base Color": (0.95, 0.93, 0.88, 1),
                                                              "Roughness": 0.4, "Metallic": 1.0,
                                                              "Specular Tint": (0.3, 0.6, 1.0, 1.0)}),
        FurnaceMaterial("hard_subsurface_r0.40", "hard", {"Base Color": (0.8, 0.6, 0.5, 1), "Roughness": 0.4,
                                                          "Subsurface Weight": 1.0, "Subsurface Scale": 0.2}),
        FurnaceMaterial("hard_bump_grey_r0.30", "hard", {"Base Color": (0.5, 0.5, 0.5, 1), "Roughness": 0.3},
                        bump=1.0),
        FurnaceMaterial("hard_alpha_grey_r0.30", "hard", {"Base Color": (0.5, 0.5, 0.5, 1), "Roughness": 0.3,
                                                          "Alpha": 0.5}),
        FurnaceMaterial("hard_ggx_single_metal_r0.80", "hard", {"Base Color": (0.95, 0.93, 0.88, 1),
                                                                "Roughness": 0.8, "Metallic": 1.0},
                        distribution="GGX"),
    ]
    return out


MATERIALS: tuple[FurnaceMaterial, ...] = tuple(_materials())


def _make_material(spec: FurnaceMaterial):
    mat = bpy.data.materials.new(spec.name)
    if mat.node_tree is None:  # Blender < 5 creates materials without nodes
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            mat.use_nodes = True
    tree = mat.node_tree
    node = next(n for n in tree.nodes if n.type == "BSDF_PRINCIPLED")
    node.distribution = spec.distribution
    for key, value in spec.inputs.items():
        node.inputs[key].default_value = value
    if spec.bump > 0:
        noise = tree.nodes.new("ShaderNodeTexNoise")
        noise.inputs["Scale"].default_value = 12.0
        bump = tree.nodes.new("ShaderNodeBump")
        bump.inputs["Strength"].default_value = spec.bump
        tree.links.new(noise.outputs["Fac"], bump.inputs["Height"])
        tree.links.new(bump.outputs["Normal"], node.inputs["Normal"])
    return mat


def _sphere_mesh(name: str, radius: float, segments: int = 128, rings: int = 64):
    mesh = bpy.data.meshes.new(name)
    bm = bmesh.new()
    bmesh.ops.create_uvsphere(bm, u_segments=segments, v_segments=rings, radius=radius)
    bm.to_mesh(mesh)
    bm.free()
    mesh.polygons.foreach_set("use_smooth", [True] * len(mesh.polygons))
    mesh.update()
    return mesh


def build_furnace_scene(blend_path: str | Path, size: tuple[int, int] = (1024, 768), columns: int = 8,
                        materials=MATERIALS) -> dict:
    """Build the furnace scene from factory settings, save it to ``blend_path`` and return its layout:
    {'spheres': [{'material', 'group', 'centre' (world xyz), 'radius'}], 'size': [W, H], 'columns', 'rows'}.
    Spheres sit on a grid in the world XZ plane; the perspective camera looks along +Y from far away."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.render.resolution_x, scene.render.resolution_y = size
    scene.render.resolution_percentage = 100
    scene.frame_start = scene.frame_end = 1
    world = bpy.data.worlds.new("Furnace")
    if world.node_tree is None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            world.use_nodes = True
    bg = world.node_tree.nodes["Background"]
    bg.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    bg.inputs["Strength"].default_value = 1.0
    scene.world = world

    n = len(materials)
    rows = math.ceil(n / columns)
    spacing, radius = 2.0, 0.85
    layout = {"size": list(size), "columns": columns, "rows": rows, "spacing": spacing, "spheres": []}
    for i, spec in enumerate(materials):
        col, row = i % columns, i // columns
        centre = ((col - (columns - 1) / 2) * spacing, 0.0, ((rows - 1) / 2 - row) * spacing)
        ob = bpy.data.objects.new(spec.name, _sphere_mesh(spec.name, radius))
        ob.location = centre
        ob.data.materials.append(_make_material(spec))
        for attr in ("visible_diffuse", "visible_glossy", "visible_transmission", "visible_volume_scatter",
                     "visible_shadow"):
            setattr(ob, attr, False)
        ob.visible_camera = True
        scene.collection.objects.link(ob)
        layout["spheres"].append({"material": spec.name, "group": spec.group, "centre": list(centre),
                                  "radius": radius, "spec": asdict(spec)})

    cam_data = bpy.data.cameras.new("FurnaceCamera")
    cam_data.type = "PERSP"
    cam_data.sensor_fit = "HORIZONTAL"
    distance = 60.0
    width_world = columns * spacing
    height_world = rows * spacing
    aspect = size[0] / size[1]
    # fit the wider of the two extents (sensor is horizontal): tan(fov/2) = half width / distance
    half_w = max(width_world / 2, height_world / 2 * aspect) * 1.02
    cam_data.angle = 2 * math.atan(half_w / distance)
    cam = bpy.data.objects.new("FurnaceCamera", cam_data)
    cam.location = (0.0, -distance, 0.0)
    cam.rotation_euler = (math.pi / 2, 0.0, 0.0)  # camera -Z looks along world +Y, camera +Y is world +Z
    scene.collection.objects.link(cam)
    scene.camera = cam
    layout["camera"] = {"location": list(cam.location), "angle": cam_data.angle}
    bpy.ops.wm.save_as_mainfile(filepath=str(Path(blend_path).resolve()))
    return layout


def main(argv=None) -> int:
    import argparse

    p = argparse.ArgumentParser(prog="python -m gbuffer_export.blender.furnace",
                                description="Build the white-furnace scene, save it and its layout (JSON).")
    p.add_argument("blend", type=Path, help=".blend file to write")
    p.add_argument("layout", type=Path, help="layout JSON to write")
    p.add_argument("--size", type=int, nargs=2, default=(1024, 768), metavar=("W", "H"),
                   help="render resolution stored in the scene, pixels")
    p.add_argument("--materials", default=None,
                   help="comma-separated subset of the material names (default: all %d)" % len(MATERIALS))
    p.add_argument("--columns", type=int, default=8, help="spheres per row")
    args = p.parse_args(argv)
    mats = MATERIALS
    if args.materials:
        names = [n.strip() for n in args.materials.split(",") if n.strip()]
        known = {m.name: m for m in MATERIALS}
        unknown = [n for n in names if n not in known]
        if unknown:
            p.error(f"unknown material(s) {', '.join(unknown)}; known: {', '.join(known)}")
        mats = tuple(known[n] for n in names)
    layout = build_furnace_scene(args.blend, tuple(args.size), columns=args.columns, materials=mats)
    args.layout.write_text(json.dumps(layout, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

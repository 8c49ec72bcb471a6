"""bpy probes for tests/render/test_scene_formats.py, run in a subprocess: ``python tests/format_probes.py PROBE JSON_ARGS``.
Each prints one line ``PROBE-RESULT {json}`` describing what Blender holds afterwards (bpy state is global and a
crash inside Blender kills the process).

roundtrip  build a tiny level (a 4 m floor, a 1 m box with a red material), export it to every format of the
           format table that Blender can write, import each file back through ``importers.load_level`` and report
           its format, world-space triangle count and bounds
missing    import an OBJ (+MTL) naming missing images and report the sockets its image nodes fed
gltf_missing  export a glTF with separate colour, roughness and normal textures, delete them, import it and
           report what its Principled BSDF reads
refusals   the one-line errors of a format whose add-on or operator this Blender lacks
units      load each level of a list and detect its unit (``level_scale.detect_unit_scale``)
gltf_iridescence  import each glTF as a level (``load_level``) and as a dataset asset (``import_asset``) and report
           each material's Principled thin film: IOR, thickness, and the nodes that compute a textured one; and
           what Blender's importer says of the file on its own
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import bpy  # noqa: E402
import numpy as np  # noqa: E402

from gbuffer_export.blender.importers import _operator, load_level  # noqa: E402
from gbuffer_export.blender.level_geometry import from_scene  # noqa: E402
from gbuffer_export.errors import BlendSRError  # noqa: E402
from gbuffer_export.scene_formats import SceneFormat  # noqa: E402

#: suffix -> exporter call (operator, keywords)
EXPORTERS = {
    ".glb": ("export_scene.gltf", {"export_format": "GLB"}),
    ".blend": ("wm.save_as_mainfile", {}),
    ".usdc": ("wm.usd_export", {}),
    ".usda": ("wm.usd_export", {}),
    ".obj": ("wm.obj_export", {"export_materials": True}),
    ".fbx": ("export_scene.fbx", {}),
    ".ply": ("wm.ply_export", {}),
    ".stl": ("wm.stl_export", {}),
    ".abc": ("wm.alembic_export", {"as_background_job": False, "start": 1, "end": 1}),
}


def _build_level():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.mesh.primitive_plane_add(size=4.0, location=(0.0, 0.0, 0.0))
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(1.0, 0.0, 0.5))
    mat = bpy.data.materials.new("Red")
    mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (0.8, 0.05, 0.05, 1.0)
    bpy.context.active_object.data.materials.append(mat)


def _summary(scene) -> dict:
    g = from_scene(scene, scene.frame_start)
    lo, hi = g.bounds()
    return {"triangles": g.n_triangles, "lo": lo.tolist(), "hi": hi.tolist(),
            "materials": sorted(m.name for m in bpy.data.materials if m.users)}


def roundtrip(args: dict) -> dict:
    out = {}
    for suffix, (op, kw) in EXPORTERS.items():
        _build_level()
        path = Path(args["dir"]) / f"level{suffix}"
        group, name = op.split(".")
        getattr(getattr(bpy.ops, group), name)(filepath=str(path), **kw)
        scene, report = load_level(path)
        out[suffix] = {"report": report, **_summary(scene)}
    return out


def _links(mat) -> dict:
    """{image node: [(output, to node type, to socket, its value now)]} and the Principled BSDF's inputs."""
    nt = mat.node_tree
    bsdf = next(n for n in nt.nodes if n.type == "BSDF_PRINCIPLED")
    images = {n.image.name: [[ln.from_socket.name, ln.to_node.type, ln.to_socket.name] for o in n.outputs
                             for ln in o.links] for n in nt.nodes if n.type == "TEX_IMAGE" and n.image}
    normal_maps = [list(n.inputs["Color"].default_value) for n in nt.nodes if n.type == "NORMAL_MAP"]
    return {"images": images, "base_color": list(bsdf.inputs["Base Color"].default_value),
            "base_color_linked": bsdf.inputs["Base Color"].is_linked, "alpha": bsdf.inputs["Alpha"].default_value,
            "alpha_linked": bsdf.inputs["Alpha"].is_linked, "normal_maps": normal_maps}


def missing(args: dict) -> dict:
    scene, report = load_level(Path(args["obj"]))
    return {"report": report, "materials": {m.name: _links(m) for m in bpy.data.materials if m.node_tree}}


def gltf_missing(args: dict) -> dict:
    import os
    folder = Path(args["dir"])
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.mesh.primitive_plane_add(size=4.0)
    mat = bpy.data.materials.new("Textured")
    bpy.context.active_object.data.materials.append(mat)
    nt = mat.node_tree
    bsdf = nt.nodes["Principled BSDF"]
    for name, socket, data in (("colour", "Base Color", False), ("rough", "Roughness", True), ("normal", None, True)):
        img = bpy.data.images.new(name, 4, 4)
        img.pixels[:] = [0.3] * 64
        img.filepath_raw, img.file_format = str(folder / f"{name}.png"), "PNG"
        img.save()
        if data:
            img.colorspace_settings.name = "Non-Color"
        node = nt.nodes.new("ShaderNodeTexImage")
        node.image = img
        if socket:
            nt.links.new(node.outputs["Color"], bsdf.inputs[socket])
        else:
            nm = nt.nodes.new("ShaderNodeNormalMap")
            nt.links.new(node.outputs["Color"], nm.inputs["Color"])
            nt.links.new(nm.outputs["Normal"], bsdf.inputs["Normal"])
    bpy.ops.export_scene.gltf(filepath=str(folder / "level.gltf"), export_format="GLTF_SEPARATE")
    for name in ("colour", "rough", "normal"):
        os.remove(folder / f"{name}.png")
    scene, report = load_level(folder / "level.gltf")
    mat = next(m for m in bpy.data.materials if m.users and m.node_tree)
    split = [list(n.inputs["Color"].default_value) for n in mat.node_tree.nodes if n.type == "SEPARATE_COLOR"]
    images_read = [n.image.name for n in mat.node_tree.nodes if n.type == "TEX_IMAGE" and n.image
                   and any(o.links for o in n.outputs)]
    return {"report": report, **_links(mat), "split": split, "images_read": images_read}


def refusals(args: dict) -> dict:
    out = {}
    fakes = {"addon": SceneFormat("Fake", (".fake",), "import_scene.fake", addon="io_blendsr_no_such_addon"),
             "operator": SceneFormat("Nothing", (".nothing",), "wm.blendsr_nothing_import")}
    for key, fmt in fakes.items():
        try:
            _operator(fmt, Path(args["file"]))
            out[key] = None
        except BlendSRError as exc:
            out[key] = str(exc)
    for junk in args.get("junk", []):
        try:
            load_level(Path(junk))
            out[junk] = None
        except BlendSRError as exc:
            out[junk] = str(exc)
    return out


def units(args: dict) -> dict:
    """Each level's unit as a level camera reads it: its geometry without sky meshes, its file's engine line and
    spawn points (``level_scale.resolve_unit_scale``)."""
    from gbuffer_export.blender.level_scale import resolve_unit_scale
    from gbuffer_export.blender.lighting import level_light
    from gbuffer_export.blender.scene_setup import spawn_points
    out = {}
    for p in args["levels"]:
        scene, _ = load_level(Path(p))
        out[p] = resolve_unit_scale(level_light(scene, scene.frame_start).level, "auto", p, spawn_points(scene))
    return out


def _film_inputs(socket) -> dict:
    """The node chain feeding a socket, depth first: [type, operation, constant inputs] per node."""
    chain, todo = [], [l.from_node for l in socket.links]
    while todo:
        node = todo.pop(0)
        consts = [float(i.default_value) for i in node.inputs if not i.is_linked and i.type == "VALUE"]
        chain.append([node.type, getattr(node, "operation", None), consts,
                      [list(node.image.pixels[:]) if node.type == "TEX_IMAGE" else None][0]])
        todo += [l.from_node for i in node.inputs for l in i.links]
    return {"chain": chain}


def _films() -> dict:
    out = {}
    for mat in bpy.data.materials:
        if mat.node_tree is None:
            continue
        for n in mat.node_tree.nodes:
            if n.type == "BSDF_PRINCIPLED":
                t = n.inputs["Thin Film Thickness"]
                base = [l.from_node for l in n.inputs["Base Color"].links]
                out[mat.name] = {"ior": n.inputs["Thin Film IOR"].default_value, "thickness": t.default_value,
                                 "base_colour_space": [b.image.colorspace_settings.name for b in base
                                                       if b.type == "TEX_IMAGE"],
                                 "linked": t.is_linked, **_film_inputs(t), "props": list(mat.keys()),
                                 "packed": [i.packed_file is not None for i in bpy.data.images]}
    return out


def gltf_iridescence(args: dict) -> dict:
    from gbuffer_export.blender.assets import import_asset
    out = {}
    for p in args["files"]:
        rec = {}
        bpy.ops.wm.read_factory_settings(use_empty=True)
        try:
            bpy.ops.import_scene.gltf(filepath=p)
            rec["blender_alone"] = "imported"
        except RuntimeError as exc:
            rec["blender_alone"] = str(exc).strip().splitlines()[-1]
        scene, report = load_level(Path(p))
        rec["level"], rec["report"] = _films(), report
        bpy.ops.wm.read_factory_settings(use_empty=True)
        import_asset(bpy.context.scene, Path(p))
        rec["asset"] = _films()
        out[p] = rec
    return out


if __name__ == "__main__":
    result = {"roundtrip": roundtrip, "missing": missing, "refusals": refusals, "units": units,
              "gltf_missing": gltf_missing, "gltf_iridescence": gltf_iridescence}[sys.argv[1]](json.loads(sys.argv[2]))
    print("PROBE-RESULT " + json.dumps(result, default=lambda o: np.asarray(o).tolist()))

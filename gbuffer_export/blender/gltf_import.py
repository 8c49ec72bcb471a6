"""Blender's glTF importer plus the material extensions BlendSR applies itself (bpy layer).

:func:`import_gltf` runs ``bpy.ops.import_scene.gltf`` on the file, or on the copy ``gbuffer_export.gltf_extensions``
prepares when the file uses ``KHR_materials_iridescence`` (which the importer ignores, or refuses when required),
and then wires each marked material's Principled BSDF thin film as that module's docstring says: Thin Film IOR, and
Thin Film Thickness from the factor, the thickness range and the extension's textures (Image Texture, Non-Color,
packed into the .blend; Separate Color; Math). Every caller of the glTF importer goes through here:
``assets.import_asset`` (dataset assets and clutter) and ``importers.import_level`` (a .gltf/.glb scene).
"""
from __future__ import annotations

import logging
import tempfile
from pathlib import Path

import bpy

from ..gltf_extensions import EXTRAS_KEY, IRIDESCENCE, prepare_gltf

log = logging.getLogger(__name__)


def _image_channel(nt, tex: dict, channel: str, loaded: dict):
    """The ``channel`` output of the texture ``tex`` ({"path", "uv"}) sampled in node tree ``nt``; ``loaded`` holds
    the images this import loaded (one per file)."""
    # a datablock of its own: the importer's image of the same file may be a colour texture (sRGB), which setting
    # Non-Color here would change for every material that samples it
    image = loaded.get(tex["path"])
    if image is None:
        image = loaded[tex["path"]] = bpy.data.images.load(tex["path"], check_existing=False)
        image.colorspace_settings.name = "Non-Color"
    if image.packed_file is None:
        image.pack()  # as the importer packs its images; the scratch folder is removed after the import
    node = nt.nodes.new("ShaderNodeTexImage")
    node.image = image
    if tex["uv"]:
        uv = nt.nodes.new("ShaderNodeUVMap")
        uv.uv_map = "UVMap.%03d" % tex["uv"]  # the importer's name of TEXCOORD_n (n > 0)
        nt.links.new(uv.outputs["UV"], node.inputs["Vector"])
    split = nt.nodes.new("ShaderNodeSeparateColor")
    nt.links.new(node.outputs["Color"], split.inputs["Color"])
    return split.outputs[channel]


def _math(nt, a, b, operation: str = "MULTIPLY"):
    node = nt.nodes.new("ShaderNodeMath")
    node.operation = operation
    for socket, value in zip(node.inputs, (a, b)):
        if isinstance(value, (int, float)):
            socket.default_value = value
        else:
            nt.links.new(value, socket)
    return node.outputs[0]


def apply_iridescence(mat, spec: dict, loaded: dict | None = None) -> None:
    """Thin film on every Principled BSDF of ``mat`` from a resolved KHR_materials_iridescence ``spec``."""
    nt, loaded = mat.node_tree, {} if loaded is None else loaded
    for bsdf in [n for n in nt.nodes if n.type == "BSDF_PRINCIPLED"]:
        bsdf.inputs["Thin Film IOR"].default_value = spec["ior"]
        socket = bsdf.inputs["Thin Film Thickness"]
        thick_tex, factor_tex = spec.get("thickness_texture"), spec.get("factor_texture")
        if thick_tex is None and factor_tex is None:
            socket.default_value = spec["factor"] * spec["thickness_max"]
            continue
        if thick_tex is not None:  # thickness = mix(min, max, texture G)
            span = _math(nt, _image_channel(nt, thick_tex, "Green", loaded),
                         spec["thickness_max"] - spec["thickness_min"])
            value = _math(nt, span, spec["thickness_min"], "ADD")
        else:
            value = spec["thickness_max"]
        value = _math(nt, value, spec["factor"])
        if factor_tex is not None:
            value = _math(nt, value, _image_channel(nt, factor_tex, "Red", loaded))
        nt.links.new(value, socket)


def import_gltf(path: Path, op=None, **options) -> set:
    """``op`` (``bpy.ops.import_scene.gltf`` by default) on ``path`` or its prepared copy; then the thin films.
    Returns the operator's result; its RuntimeError (an importer failure) passes to the caller."""
    op = op or bpy.ops.import_scene.gltf
    with tempfile.TemporaryDirectory(prefix="blendsr-gltf-") as tmp:
        prepared = prepare_gltf(Path(path), Path(tmp))
        if prepared is None:
            return op(filepath=str(path), **options)
        before = set(bpy.data.materials)
        result = op(filepath=str(prepared[0]), **options)
        films, done, loaded = prepared[1], 0, {}
        for mat in [m for m in bpy.data.materials if m not in before]:
            token = mat.get(EXTRAS_KEY)
            if token is None:
                continue
            del mat[EXTRAS_KEY]
            if isinstance(token, str) and token in films and mat.node_tree is not None:
                apply_iridescence(mat, films[token], loaded)
                done += 1
        log.info("%s: %s applied as Principled thin film on %d material(s) (%s)", path, IRIDESCENCE, done,
                 ", ".join(f["material"] for f in films.values()))
        return result


__all__ = ["apply_iridescence", "import_gltf"]

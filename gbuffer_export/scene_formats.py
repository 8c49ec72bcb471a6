"""What counts as a level: the one table of scene file formats (pure Python, no bpy).

Each row names a format, the file suffixes it owns and the Blender operator that loads it. The render
(``gbuffer_export.blender.importers`` runs the operator), ``RenderConfig`` and dataset spec validation (a suffix
outside the table is refused) and docs/rendering.md ("Scene formats") all read this table; a test checks the
docs against it.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class SceneFormat:
    """One loadable format. ``operator``: the bpy operator (``"wm.obj_import"``) that imports the file into an
    empty Blender file (``wm.open_mainfile`` opens a .blend as it is); ``addon``: the Blender add-on that
    provides it (enabled on demand), None for a built-in operator; ``options``: keyword arguments passed to it;
    ``brings``: what the importer reads besides meshes (docs)."""

    name: str
    suffixes: tuple[str, ...]
    operator: str
    addon: str | None = None
    options: tuple[tuple[str, object], ...] = ()
    brings: str = ""


#: The formats, in the order the docs list them.
SCENE_FORMATS: tuple[SceneFormat, ...] = (
    SceneFormat("Blender", (".blend",), "wm.open_mainfile",
                brings="everything: opened as it is (its scene, world, lights, cameras, render settings)"),
    SceneFormat("glTF", (".gltf", ".glb"), "import_scene.gltf", addon="io_scene_gltf2",
                brings="materials and textures, cameras, lights (KHR_lights_punctual), animation"),
    SceneFormat("USD", (".usd", ".usda", ".usdc", ".usdz"), "wm.usd_import",
                brings="materials (UsdPreviewSurface) and textures, cameras, lights, the stage's up axis and "
                       "metres per unit"),
    SceneFormat("OBJ", (".obj",), "wm.obj_import",
                brings="materials and textures of its .mtl (Y up converted to Blender's Z up)"),
    SceneFormat("FBX", (".fbx",), "import_scene.fbx", addon="io_scene_fbx",
                brings="materials and textures, cameras, lights, animation, the file's axes and unit"),
    SceneFormat("PLY", (".ply",), "wm.ply_import", brings="vertex colours (no materials)"),
    SceneFormat("STL", (".stl",), "wm.stl_import", brings="geometry only (no materials)"),
    # as_background_job: the bpy module never runs Blender's job system, a background import would never finish
    SceneFormat("Alembic", (".abc",), "wm.alembic_import", options=(("as_background_job", False),),
                brings="animated geometry (a mesh cache read at each frame), cameras; no materials"),
)

#: Every suffix of the table (lower case, with the dot).
SCENE_SUFFIXES: tuple[str, ...] = tuple(s for f in SCENE_FORMATS for s in f.suffixes)


def scene_format(path: str | Path) -> SceneFormat | None:
    """The row whose suffixes hold ``path``'s suffix (case-insensitive), None when no row does."""
    suffix = Path(path).suffix.lower()
    return next((f for f in SCENE_FORMATS if suffix in f.suffixes), None)


def formats_text() -> str:
    """'.blend, .gltf, ...' for messages."""
    return ", ".join(SCENE_SUFFIXES)

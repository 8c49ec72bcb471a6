"""Load a level file of any format Blender imports (bpy layer), and make its missing textures neutral.

The formats and the operator of each are one table, ``gbuffer_export.scene_formats.SCENE_FORMATS``; this module
runs the operator (a .blend is opened, every other format imported into an empty file) and then checks the
images the file's materials and world use:

- a texture whose file is missing or unreadable renders in Cycles as magenta. Every link from such an image node
  is replaced by a neutral constant: a colour image gives mid grey (linear albedo 0.5) and alpha 1 (opaque); a
  data image gives 0.5, a flat normal (0.5, 0.5, 1) into a Normal Map node, and (occlusion 1, roughness 0.5,
  metallic 0) into a glTF occlusion-roughness-metallic split (a Separate Color node);
- the files are named in one warning line, and returned for the clip manifest (``scene.missing_textures``).
"""
from __future__ import annotations

import contextlib
import logging
from pathlib import Path

import bpy

from ..config import ConfigError
from ..scene_formats import SCENE_FORMATS, SceneFormat, formats_text, scene_format
from .gltf_import import import_gltf

log = logging.getLogger(__name__)

#: Linear albedo a missing colour texture renders as.
NEUTRAL_ALBEDO = 0.5
#: A missing data texture's value (roughness, specular, a mask).
NEUTRAL_DATA = 0.5
FLAT_NORMAL = (0.5, 0.5, 1.0, 1.0)
#: glTF's occlusion-roughness-metallic texture split by a Separate Color node: R occlusion, G roughness, B metallic.
NEUTRAL_ORM = (1.0, 0.5, 0.0, 1.0)
#: At most this many files are named in the warning line (the manifest lists all).
WARN_FILES = 12


def _operator(fmt: SceneFormat, path: Path):
    """The bpy operator of ``fmt``, its add-on enabled first; ConfigError naming why when this Blender lacks it."""
    if fmt.addon:
        import addon_utils
        if not addon_utils.check(fmt.addon)[1]:
            try:
                mod = addon_utils.enable(fmt.addon, default_set=False)
            except Exception as exc:  # an add-on's own import error
                mod = None
                why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            else:
                why = "not installed"
            if mod is None:
                raise ConfigError(f"{path}: this Blender cannot import {fmt.name} (its add-on {fmt.addon} is {why}); "
                                  "export the level as glTF (.glb) or .blend")
    group, name = fmt.operator.split(".")
    op = getattr(getattr(bpy.ops, group), name)
    try:
        op.get_rna_type()
    except (KeyError, RuntimeError, AttributeError):
        raise ConfigError(f"{path}: this Blender build has no {fmt.name} importer (bpy.ops.{fmt.operator}); "
                          "export the level as glTF (.glb) or .blend") from None
    return op


@contextlib.contextmanager
def _importer_output(what: str):
    """Capture descriptors 1 and 2 while an importer runs (it prints a line per missing image, per object, per
    timing): kept as one debug record (``blendsr -v``); ``BLENDSR_VERBOSE=1`` lets it through as it is."""
    from .fds import captured
    with captured() as out:
        yield
    if out.text.strip():
        log.debug("%s importer said:\n%s", what, out.text.strip())


def load_level(path: Path, allow_read=()):
    """Open or import ``path`` by its row of the format table in a child process (``import_sandbox``: memory and
    time limits, references checked by ``scene_refs``), then open the .blend it saved; returns (scene, report for
    the manifest's ``scene``: the format, the missing textures, files read from allowed folders outside the scene's).
    ConfigError (one line) for an unknown suffix, a refused reference, a format this Blender cannot import, an
    importer that fails or crashes. Ctrl-C while the child imports: it is killed, KeyboardInterrupt."""
    import shutil
    import tempfile
    from ..import_sandbox import import_in_child
    from ..interrupt import check_interrupt
    from ..scene_refs import check_scene_file
    path = Path(path)
    check_scene_file(path)
    fmt = scene_format(path)
    if fmt is None:
        raise ConfigError(f"{path}: not a scene file (one of {formats_text()})")
    work = Path(tempfile.mkdtemp(prefix="blendsr-import-"))
    try:
        report = import_in_child(path, fmt.name, allow_read, work)["report"]
        check_interrupt()
        with _importer_output("Blender"):
            bpy.ops.wm.open_mainfile(filepath=str(work / "level.blend"), load_ui=False)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    check_interrupt()
    warn_missing(path, report.get("missing_textures", []))
    return bpy.context.scene, report


@contextlib.contextmanager
def _fbx_light_fix():
    """Blender 5.0's FBX importer sets ``light.cycles.cast_shadow``, which Cycles no longer has (it reads the light's
    own ``use_shadow``, which the importer sets first): every FBX with a lamp failed with an AttributeError. The
    property is declared for the import and removed afterwards, so lamps import with their shadow setting."""
    try:
        from cycles.properties import CyclesLightSettings as cls  # Cycles' own add-on (bpy.types does not list it)
    except ImportError:
        cls = None
    add = cls is not None and "cast_shadow" not in cls.bl_rna.properties
    if add:
        cls.cast_shadow = bpy.props.BoolProperty(default=True)
    try:
        yield
    finally:
        if add:
            del cls.cast_shadow


def import_level(path: Path, allow_read=()) -> dict:
    """Open or import ``path`` in this process (the import child, ``import_job``): its images checked against the
    allowed folders before any is read, missing textures made neutral; returns the manifest's report."""
    path = Path(path)
    fmt = scene_format(path)
    if fmt.operator == "wm.open_mainfile":
        with _importer_output(fmt.name):
            bpy.ops.wm.open_mainfile(filepath=str(path), load_ui=False)
    else:
        bpy.ops.wm.read_factory_settings(use_empty=True)
        op = _operator(fmt, path)
        fix = _fbx_light_fix() if fmt.name == "FBX" else contextlib.nullcontext()
        try:
            with _importer_output(fmt.name), fix:  # missing images are named once below
                if fmt.operator == "import_scene.gltf":  # with the extensions BlendSR adds (gltf_import)
                    result = import_gltf(path, op, **dict(fmt.options))
                else:
                    result = op(filepath=str(path), **dict(fmt.options))
        except RuntimeError as exc:
            raise ConfigError(f"{path}: the {fmt.name} importer failed ({_importer_error(exc)})") from None
        if "FINISHED" not in result:
            raise ConfigError(f"{path}: the {fmt.name} importer failed ({', '.join(sorted(result)).lower()}: not a "
                              f"readable {fmt.name} file)")
        scene = bpy.context.scene
        scene.render.resolution_x, scene.render.resolution_y = 1920, 1080
    report = {"format": fmt.name}
    check_file_nodes(path, allow_read)
    outside = check_image_files(path, allow_read)
    if outside:
        report["read_outside"] = outside
    missing = neutralise_missing_textures(path)
    if missing:
        report["missing_textures"] = missing
    return report


def _importer_error(exc: RuntimeError) -> str:
    """The line of an operator's error that says what went wrong: a Python importer's exception line (the last
    line of its traceback), else the first line."""
    lines = [ln.strip() for ln in str(exc).strip().splitlines() if ln.strip()]
    if lines and "Traceback" in lines[0]:
        said = [ln for ln in lines if not ln.startswith(("File ", "Location:", "^", "Error: Python")) and ":" in ln
                and not ln.startswith(("return ", "fbx_", "_"))]
        return said[-1][:200] if said else "a Python error in the importer"
    return lines[0] if lines else "no message"


#: Geometry nodes that read a file named by a socket when the tree is evaluated (the path may be computed: it
#: cannot be checked before the render evaluates it), refused in a scene file.
FILE_READING_NODES = ("GeometryNodeImportCSV", "GeometryNodeImportOBJ", "GeometryNodeImportPLY",
                      "GeometryNodeImportSTL", "GeometryNodeImportText", "GeometryNodeImportVDB")


def _node_trees():
    yield from bpy.data.node_groups
    for coll in (bpy.data.materials, bpy.data.worlds, bpy.data.lights):
        for idb in coll:
            if getattr(idb, "node_tree", None) is not None:
                yield idb.node_tree


def check_file_nodes(level: Path, allow_read=()) -> None:
    """ConfigError (one line) for a node that reads a file the resolver cannot check before evaluation (geometry
    nodes' Import nodes); an IES texture's external file goes through the one resolver."""
    from ..scene_refs import read_roots, resolve_ref
    roots = read_roots(level, allow_read)
    for tree in _node_trees():
        for node in tree.nodes:
            if node.bl_idname in FILE_READING_NODES:
                raise ConfigError(f"{level}: node {node.name!r} of {tree.name!r} ({node.bl_idname}) reads a file "
                                  "named when the scene is evaluated; such nodes are refused (apply or remove it)")
            if node.bl_idname == "ShaderNodeTexIES" and node.mode == "EXTERNAL" and node.filepath:
                resolve_ref(level, bpy.path.abspath(node.filepath), Path(level).parent, roots,
                            f"IES file of node {node.name!r}")


def check_image_files(level: Path, allow_read=()) -> list[str]:
    """Every file image of the loaded scene, checked by the one resolver (``scene_refs.resolve_ref``) before its
    pixels are read: ConfigError (one line) for one outside the allowed folders; returns those read from allowed
    folders outside the level's."""
    from ..scene_refs import read_roots, resolve_ref
    roots = read_roots(level, allow_read)
    outside = []
    for im in bpy.data.images:
        if im.source not in ("FILE", "SEQUENCE", "MOVIE", "TILED"):
            continue
        # a .blend's packed image is data of the file itself; an importer that packs (glTF) has read the path
        # during the import: that path is checked like any other
        if im.packed_file is not None and Path(level).suffix.lower() == ".blend":
            continue
        raw = im.filepath_raw or im.filepath
        if not raw:
            continue
        real = resolve_ref(level, bpy.path.abspath(raw, library=im.library), Path(level).parent, roots,
                           f"image {im.name!r} file", missing_ok=True)
        if real is not None:
            outside.append(str(real))
    return sorted(set(outside))


# ----------------------------------------------------------------------------------------------
# Missing textures
# ----------------------------------------------------------------------------------------------

def _missing(image) -> bool:
    """A file image (not packed, not generated) that Blender cannot load: its file is absent or unreadable."""
    if image.source not in ("FILE", "SEQUENCE", "MOVIE", "TILED") or image.packed_file is not None:
        return False
    if image.source == "TILED":
        return not any(t.size[0] for t in image.tiles) if len(image.tiles) else True
    return image.size[0] == 0  # reading the size loads the image (the render loads it anyway)


def _named(image, base: Path) -> str:
    """The image's file as the level names it: relative to the level's folder when under it."""
    p = Path(bpy.path.abspath(image.filepath_raw or image.filepath, library=image.library))
    try:
        return p.resolve().relative_to(base.resolve()).as_posix()
    except ValueError:
        return str(p)


def _node_trees():
    """Every node tree a render may evaluate: materials, worlds, lights, node groups."""
    for coll in (bpy.data.materials, bpy.data.worlds, bpy.data.lights):
        for idb in coll:
            if getattr(idb, "node_tree", None) is not None:
                yield idb.node_tree
    yield from (g for g in bpy.data.node_groups if g.bl_idname == "ShaderNodeTree")


def _neutral(image, link) -> object:
    """The constant that replaces ``link`` (from a missing image's node): see the module doc."""
    to_node, to_sock = link.to_node, link.to_socket
    if link.from_socket.name == "Alpha":
        return 1.0
    data = image.colorspace_settings.is_data or image.colorspace_settings.name in ("Non-Color", "Raw")
    if to_node.type == "NORMAL_MAP":
        return FLAT_NORMAL
    if data and to_node.type in ("SEPARATE_COLOR", "SEPRGB"):
        return NEUTRAL_ORM
    v = NEUTRAL_DATA if data else NEUTRAL_ALBEDO
    return (v, v, v, 1.0) if to_sock.type == "RGBA" else v


def _set_default(sock, value) -> None:
    """Set an unlinked socket's value to ``value`` (a colour or a number), fitted to the socket's type."""
    if sock.type == "RGBA":
        sock.default_value = value if isinstance(value, tuple) else (value, value, value, 1.0)
    elif sock.type in ("VALUE", "INT"):
        sock.default_value = value[1] if isinstance(value, tuple) else value
    elif sock.type == "VECTOR" and hasattr(sock, "default_value") and len(sock.default_value) == 3:
        sock.default_value = value[:3] if isinstance(value, tuple) else (value, value, value)


def neutralise_missing_textures(level: Path) -> list[str]:
    """Replace every use of a missing image (module doc); return the files sorted (as the level names them, relative
    to its folder; ``warn_missing`` names them in one warning)."""
    images = {im.name: im for im in bpy.data.images if im.users and _missing(im)}
    if not images:
        return []
    used = set()
    for tree in _node_trees():
        for node in list(tree.nodes):
            image = getattr(node, "image", None) if node.type in ("TEX_IMAGE", "TEX_ENVIRONMENT") else None
            if image is None or image.name not in images:
                continue
            used.add(image.name)
            for link in [ln for out in node.outputs for ln in out.links]:
                value, sock = _neutral(image, link), link.to_socket
                tree.links.remove(link)
                _set_default(sock, value)
    base = Path(level).parent
    return sorted({_named(images[n], base) for n in used})


def warn_missing(level: Path, files: list[str]) -> None:
    """One warning line naming the missing texture files (the import child found them; the render warns)."""
    if files:
        shown = ", ".join(files[:WARN_FILES]) + (f" and {len(files) - WARN_FILES} more" if len(files) > WARN_FILES
                                                  else "")
        log.warning("%s: %d texture file(s) missing, rendered as mid grey (albedo %g), never magenta: %s",
                    Path(level).name, len(files), NEUTRAL_ALBEDO, shown)


__all__ = ["SCENE_FORMATS", "check_image_files", "import_level", "load_level", "neutralise_missing_textures"]

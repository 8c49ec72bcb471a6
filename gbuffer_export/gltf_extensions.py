"""glTF material extensions that Blender's importer lacks and BlendSR applies itself (core: standard library only).

Blender 5.0.1's glTF importer ignores ``KHR_materials_iridescence`` and refuses a file that lists it in
``extensionsRequired`` ("Extension KHR_materials_iridescence is not available on this addon version"), although
Cycles' Principled BSDF renders the same physics: a thin film of a given thickness (nm) and IOR on the base layer.
So, before the importer sees such a file, :func:`prepare_gltf` writes a copy into a scratch folder in which

- each material's extension is copied, resolved, into the material's ``extras`` under :data:`EXTRAS_KEY` (the
  importer copies a material's extras onto the Blender material as custom properties): factor, film IOR,
  thickness range in nm, and its textures as files in the scratch folder with their UV set;
- the extensions BlendSR applies are removed from ``extensionsRequired`` (they stay in ``extensionsUsed``);
- relative buffer and image URIs are made absolute (the copy is elsewhere); a .glb keeps its binary chunk.

After the import, ``gbuffer_export.blender.gltf_import`` wires each marked material's Principled BSDF: Thin Film IOR =
``iridescenceIor`` (default 1.3); Thin Film Thickness = ``factor x factor texture (R) x mix(min, max, thickness
texture (G))`` nm (defaults 100 and 400 nm; without a thickness texture the film is ``max`` thick, as the extension
says). The Principled BSDF has no film weight, so a factor below 1 thins the film instead of blending a filmless
layer in: exact at factors 0 and 1 (every sample asset uses 1), an approximation between. ``KHR_texture_transform``
on the iridescence textures is not applied.

Every other extension a file requires is left to the importer (which refuses the ones it lacks, in one line).
A file that uses none of :data:`APPLIED` is imported as it is (``prepare_gltf`` returns None).
"""
from __future__ import annotations

import base64
import json
import struct
from pathlib import Path
from urllib.parse import quote, unquote

from .scene_refs import SceneRefError, gltf_json

IRIDESCENCE = "KHR_materials_iridescence"
#: The extensions BlendSR applies after the import (Blender 5.0.1's importer does not).
APPLIED = (IRIDESCENCE,)
#: The material custom property (from glTF extras) that carries a resolved iridescence to the bpy layer.
EXTRAS_KEY = "blendsr_iridescence"
#: KHR_materials_iridescence's defaults.
DEFAULT_IOR = 1.3
DEFAULT_THICKNESS_NM = (100.0, 400.0)
MIME_SUFFIX = {"image/png": ".png", "image/jpeg": ".jpg", "image/webp": ".webp"}


def _number(ext: dict, key: str, default: float, path: Path) -> float:
    value = ext.get(key, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != value:
        raise SceneRefError(f"{path}: glTF {IRIDESCENCE}.{key} is not a number ({value!r})")
    return float(value)


def _glb_chunks(path: Path) -> tuple[bytes, bytes | None]:
    """The JSON and (if any) binary chunk of a .glb."""
    data = path.read_bytes()
    length = struct.unpack_from("<I", data, 12)[0]
    json_chunk = data[20:20 + length]
    rest = data[20 + length:]
    if len(rest) >= 8 and rest[4:8] == b"BIN\x00":
        n = struct.unpack_from("<I", rest, 0)[0]
        return json_chunk, rest[8:8 + n]
    return json_chunk, None


def _buffer_bytes(path: Path, doc: dict, index: int, glb_bin: bytes | None) -> bytes:
    buf = doc["buffers"][index]
    uri = buf.get("uri")
    if uri is None:
        if glb_bin is None:
            raise SceneRefError(f"{path}: glTF buffers[{index}] has no uri and the file has no binary chunk")
        return glb_bin
    if uri.startswith("data:"):
        return base64.b64decode(uri.split(",", 1)[1])
    return (path.parent / unquote(uri)).read_bytes()  # check_scene_refs kept it inside the allowed folders


def _texture_file(path: Path, doc: dict, info, glb_bin: bytes | None, out: Path, name: str) -> dict | None:
    """The texture of a textureInfo as {"path", "uv"}: an image file of the asset, or its bytes written to ``out``;
    None where the texture has no image source or its file is missing (the film then ignores that texture)."""
    if not isinstance(info, dict) or not isinstance(info.get("index"), int):
        raise SceneRefError(f"{path}: glTF {IRIDESCENCE}.{name} is not a textureInfo")
    textures = doc.get("textures", [])
    if not 0 <= info["index"] < len(textures) or not isinstance(textures[info["index"]].get("source"), int):
        return None
    images = doc.get("images", [])
    src = textures[info["index"]]["source"]
    if not 0 <= src < len(images):
        raise SceneRefError(f"{path}: glTF textures[{info['index']}].source {src} is not an image")
    img = images[src]
    uv = int(info.get("texCoord", 0))
    uri = img.get("uri")
    if isinstance(uri, str) and not uri.startswith("data:"):
        file = (path.parent / unquote(uri)).resolve()
        return {"path": str(file), "uv": uv} if file.is_file() else None  # a missing image: no texture
    if isinstance(uri, str):
        head, payload = uri.split(",", 1)
        data, mime = base64.b64decode(payload), head[5:].split(";")[0]
    else:
        view = doc["bufferViews"][img["bufferView"]]
        buf = _buffer_bytes(path, doc, view["buffer"], glb_bin)
        start = int(view.get("byteOffset", 0))
        data, mime = buf[start:start + int(view["byteLength"])], img.get("mimeType", "image/png")
    target = out / f"image{src}{MIME_SUFFIX.get(mime, '.png')}"
    target.write_bytes(data)
    return {"path": str(target), "uv": uv}


def resolved_iridescence(path: Path, doc: dict, ext: dict, glb_bin: bytes | None, out: Path) -> dict:
    """One material's KHR_materials_iridescence as the plain values the bpy layer applies (module doc)."""
    if not isinstance(ext, dict):
        raise SceneRefError(f"{path}: glTF {IRIDESCENCE} of a material is not an object")
    lo, hi = DEFAULT_THICKNESS_NM
    res = {"factor": _number(ext, "iridescenceFactor", 0.0, path),
           "ior": _number(ext, "iridescenceIor", DEFAULT_IOR, path),
           "thickness_min": _number(ext, "iridescenceThicknessMinimum", lo, path),
           "thickness_max": _number(ext, "iridescenceThicknessMaximum", hi, path)}
    for key, name in (("factor_texture", "iridescenceTexture"), ("thickness_texture", "iridescenceThicknessTexture")):
        if name in ext:
            tex = _texture_file(path, doc, ext[name], glb_bin, out, name)
            if tex is not None:
                res[key] = tex
    return res


def _absolute_uris(path: Path, doc: dict) -> None:
    for key in ("buffers", "images"):
        for item in doc.get(key, []):
            uri = item.get("uri")
            if isinstance(uri, str) and not uri.startswith("data:"):
                item["uri"] = quote((path.parent / unquote(uri)).resolve().as_posix())


def _write_glb(target: Path, doc: dict, glb_bin: bytes | None) -> None:
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<I4s", len(text), b"JSON") + text
    if glb_bin is not None:
        padded = glb_bin + b"\0" * (-len(glb_bin) % 4)
        chunks += struct.pack("<I4s", len(padded), b"BIN\x00") + padded
    target.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks)


def prepare_gltf(path: Path, out: Path) -> tuple[Path, list[str]] | None:
    """For a glTF that uses an extension of :data:`APPLIED`: the copy to import (written into the folder ``out``)
    and the names of the materials that carry it; None for any other file (import it as it is). One-line
    SceneRefError naming the file for a malformed extension."""
    path, out = Path(path), Path(out)
    doc = gltf_json(path)
    if not any(e in (doc.get("extensionsUsed") or []) for e in APPLIED):
        return None
    glb_bin = _glb_chunks(path)[1] if path.suffix.lower() == ".glb" else None
    marked = []
    for i, mat in enumerate(doc.get("materials") or []):
        ext = (mat.get("extensions") or {}).get(IRIDESCENCE)
        if ext is None:
            continue
        extras = mat.get("extras") if isinstance(mat.get("extras"), dict) else {}
        extras[EXTRAS_KEY] = resolved_iridescence(path, doc, ext, glb_bin, out)
        mat["extras"] = extras
        marked.append(str(mat.get("name") or f"Material_{i}"))
    required = [e for e in (doc.get("extensionsRequired") or []) if e not in APPLIED]
    if required:
        doc["extensionsRequired"] = required
    else:
        doc.pop("extensionsRequired", None)
    target = out / f"blendsr-{path.stem}{path.suffix.lower()}"
    _absolute_uris(path, doc)
    if path.suffix.lower() == ".glb":
        _write_glb(target, doc, glb_bin)
    else:
        target.write_text(json.dumps(doc))
    return target, marked


__all__ = ["APPLIED", "EXTRAS_KEY", "IRIDESCENCE", "prepare_gltf", "resolved_iridescence"]

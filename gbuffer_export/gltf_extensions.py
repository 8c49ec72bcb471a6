"""glTF material extensions that Blender's importer lacks and BlendSR applies itself (core: standard library only).

Blender 5.0.1's glTF importer ignores ``KHR_materials_iridescence`` and refuses a file that lists it in
``extensionsRequired`` ("Extension KHR_materials_iridescence is not available on this addon version"), although
Cycles' Principled BSDF renders the same physics: a thin film of a given thickness (nm) and IOR on the base layer.
So, before the importer sees such a file, :func:`prepare_gltf` writes a copy into a scratch folder in which

- each material's extension is checked (a malformed value or reference is one line naming the file) and resolved:
  factor, film IOR, thickness range in nm, and its textures as files (the asset's own, or embedded bytes written to
  the scratch folder) with their UV set. The settings stay in Python; the material's ``extras`` carry only a token
  under :data:`EXTRAS_KEY` (the importer copies a material's extras onto the Blender material as custom
  properties), and whatever the file itself put under that key is removed;
- the extensions BlendSR applies are removed from ``extensionsRequired`` (they stay in ``extensionsUsed``);
- relative buffer and image URIs are made absolute (the copy is elsewhere); a .glb keeps its binary chunk. URIs
  are read as the importer reads them (``scene_refs.uri_path``: backslashes are separators), the same paths
  ``check_scene_refs`` checked before.

After the import, ``gbuffer_export.blender.gltf_import`` wires each marked material's Principled BSDF: Thin Film IOR =
``iridescenceIor`` (default 1.3); Thin Film Thickness = ``factor x factor texture (R) x mix(min, max, thickness
texture (G))`` nm (defaults 100 and 400 nm; without a thickness texture the film is ``max`` thick, as the extension
says). The Principled BSDF has no film weight, so a factor below 1 thins the film instead of blending a filmless
layer in: exact where the factor is 0 or 1, an approximation between (IridescenceAbalone's factor texture: 8.3 %
of its texels between 0.05 and 0.95). Not applied to the iridescence textures: ``KHR_texture_transform`` and the
texture's sampler (Blender's defaults: repeat, linear). An ``EXT_texture_webp`` source is read; a source only an
unsupported extension gives (KTX2) leaves the film untextured.

Every other extension a file requires is left to the importer (which refuses the ones it lacks, in one line).
A file that uses none of :data:`APPLIED` is imported as it is (``prepare_gltf`` returns None).
"""
from __future__ import annotations

import base64
import binascii
import json
import math
import secrets
import struct
from pathlib import Path
from urllib.parse import quote, unquote_to_bytes

from .scene_refs import SceneRefError, gltf_items, gltf_json, uri_path

IRIDESCENCE = "KHR_materials_iridescence"
#: The extensions BlendSR applies after the import (Blender 5.0.1's importer does not).
APPLIED = (IRIDESCENCE,)
#: The material custom property (from glTF extras) that carries a resolved iridescence to the bpy layer.
EXTRAS_KEY = "blendsr_iridescence"
#: KHR_materials_iridescence's defaults.
DEFAULT_IOR = 1.3
DEFAULT_THICKNESS_NM = (100.0, 400.0)
MIME_SUFFIX = {"image/png": ".png", "image/jpeg": ".jpg", "image/webp": ".webp"}


def _bad(path: Path, what: str) -> SceneRefError:
    return SceneRefError(f"{path}: glTF {what}")


def _number(ext: dict, key: str, default: float, path: Path, lo: float, hi: float = math.inf) -> float:
    """``ext[key]`` (or ``default``): a finite number in [lo, hi], else one-line SceneRefError naming the file."""
    value = ext.get(key, default)
    ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    number = float(value) if ok and abs(value) < 1e300 else math.nan
    if not (math.isfinite(number) and lo <= number <= hi):
        raise _bad(path, f"{IRIDESCENCE}.{key} is {value!r}: not a number in [{lo:g}, {hi:g}]")
    return number


def _index(value, count: int, path: Path, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < count:
        raise _bad(path, f"{what} is {value!r}: not an index below {count}")
    return value


def _glb_chunks(path: Path) -> tuple[bytes, bytes | None]:
    """The JSON and (if any) binary chunk of a .glb (SceneRefError for a truncated binary chunk)."""
    data = path.read_bytes()
    length = struct.unpack_from("<I", data, 12)[0]
    rest = data[20 + length:]
    if len(rest) >= 8 and rest[4:8] == b"BIN\x00":
        n = struct.unpack_from("<I", rest, 0)[0]
        if len(rest) - 8 < n:
            raise SceneRefError(f"{path}: truncated glTF binary (its BIN chunk ends early)")
        return data[20:20 + length], rest[8:8 + n]
    return data[20:20 + length], None


def _data_uri(uri: str, path: Path, what: str) -> tuple[bytes, str]:
    """The bytes and media type of a ``data:`` URI (base64 or percent-encoded)."""
    head, sep, payload = uri.partition(",")
    if not sep:
        raise _bad(path, f"{what} is a data: URI without data")
    try:
        data = base64.b64decode(payload, validate=True) if head.endswith(";base64") else unquote_to_bytes(payload)
    except (binascii.Error, ValueError):  # ValueError: characters outside ASCII
        raise _bad(path, f"{what} is a data: URI whose base64 is malformed") from None
    return data, head[5:].split(";")[0]


def _buffer_bytes(path: Path, doc: dict, index, glb_bin: bytes | None, what: str) -> bytes:
    buffers = gltf_items(doc, "buffers", path)
    index = _index(index, len(buffers), path, what)
    uri = buffers[index].get("uri")
    if uri is None:
        if index != 0 or glb_bin is None:
            raise _bad(path, f"buffers[{index}] has no uri and is not a .glb's binary chunk")
        return glb_bin
    if not isinstance(uri, str):
        raise _bad(path, f"buffers[{index}].uri is not a string")
    if uri.startswith("data:"):
        return _data_uri(uri, path, f"buffers[{index}].uri")[0]
    try:  # check_scene_refs kept it inside the allowed folders
        return (path.parent / uri_path(uri)).read_bytes()
    except OSError as exc:
        raise _bad(path, f"buffers[{index}].uri {uri!r} cannot be read ({exc.strerror or exc})") from None


def _view_bytes(path: Path, doc: dict, index, glb_bin: bytes | None, what: str) -> bytes:
    views = gltf_items(doc, "bufferViews", path)
    view = views[_index(index, len(views), path, what)]
    buf = _buffer_bytes(path, doc, view.get("buffer"), glb_bin, f"bufferViews[{index}].buffer")
    start, length = view.get("byteOffset", 0), view.get("byteLength")
    if any(isinstance(v, bool) or not isinstance(v, int) or v < 0 for v in (start, length)) \
            or start + length > len(buf):
        raise _bad(path, f"bufferViews[{index}] does not fit its buffer ({len(buf)} bytes)")
    return buf[start:start + length]


def _image_source(path: Path, doc: dict, info, name: str) -> tuple[int | None, int]:
    """(image index or None, UV set) of the textureInfo ``info`` of the extension's ``name``."""
    what = f"{IRIDESCENCE}.{name}"
    if not isinstance(info, dict):
        raise _bad(path, f"{what} is not a textureInfo object")
    textures = gltf_items(doc, "textures", path)
    texture = textures[_index(info.get("index"), len(textures), path, f"{what}.index")]
    uv = info.get("texCoord", 0)
    if isinstance(uv, bool) or not isinstance(uv, int) or uv < 0:
        raise _bad(path, f"{what}.texCoord is {uv!r}: not a non-negative integer")
    webp = (texture.get("extensions") or {}).get("EXT_texture_webp") if isinstance(texture.get("extensions"),
                                                                                   dict) else None
    src = webp.get("source") if isinstance(webp, dict) and "source" in webp else texture.get("source")
    if src is None:
        return None, uv  # a source only an extension gives (KTX2): no image Blender reads
    return _index(src, len(gltf_items(doc, "images", path)), path, f"textures[{info['index']}].source"), uv


def _texture_file(path: Path, doc: dict, info, glb_bin: bytes | None, out: Path, name: str) -> dict | None:
    """The texture of a textureInfo as {"path", "uv"}: an image file of the asset, or its bytes written to ``out``;
    None where the texture has no image Blender reads or its file is missing (the film then ignores that texture,
    as the importer renders a missing image neutral). Malformed references: one-line SceneRefError."""
    src, uv = _image_source(path, doc, info, name)
    if src is None:
        return None
    img = gltf_items(doc, "images", path)[src]
    uri = img.get("uri")
    if uri is not None and not isinstance(uri, str):
        raise _bad(path, f"images[{src}].uri is not a string")
    if uri is not None and not uri.startswith("data:"):
        try:
            file = (path.parent / uri_path(uri)).resolve()
            found = file.is_file()
        except (ValueError, OSError):
            raise _bad(path, f"images[{src}].uri {uri!r} is not a file name") from None
        return {"path": str(file), "uv": uv} if found else None  # a missing image: no texture
    if uri is not None:
        data, mime = _data_uri(uri, path, f"images[{src}].uri")
    elif "bufferView" in img:
        data = _view_bytes(path, doc, img["bufferView"], glb_bin, f"images[{src}].bufferView")
        mime = img.get("mimeType", "image/png")
    else:
        raise _bad(path, f"images[{src}] has neither a uri nor a bufferView")
    target = out / f"image{src}{MIME_SUFFIX.get(mime, '.png')}"
    target.write_bytes(data)
    return {"path": str(target), "uv": uv}


def resolved_iridescence(path: Path, doc: dict, ext: dict, glb_bin: bytes | None, out: Path) -> dict:
    """One material's KHR_materials_iridescence as the plain values the bpy layer applies (module doc)."""
    if not isinstance(ext, dict):
        raise _bad(path, f"{IRIDESCENCE} of a material is not an object")
    lo, hi = DEFAULT_THICKNESS_NM
    res = {"factor": _number(ext, "iridescenceFactor", 0.0, path, 0.0, 1.0),
           "ior": _number(ext, "iridescenceIor", DEFAULT_IOR, path, 1.0),
           "thickness_min": _number(ext, "iridescenceThicknessMinimum", lo, path, 0.0),
           "thickness_max": _number(ext, "iridescenceThicknessMaximum", hi, path, 0.0)}
    for key, name in (("factor_texture", "iridescenceTexture"), ("thickness_texture", "iridescenceThicknessTexture")):
        if name in ext:
            tex = _texture_file(path, doc, ext[name], glb_bin, out, name)
            if tex is not None:
                res[key] = tex
    return res


def _absolute_uris(path: Path, doc: dict) -> None:
    for key in ("buffers", "images"):
        for item in gltf_items(doc, key, path):
            uri = item.get("uri")
            if isinstance(uri, str) and not uri.startswith("data:"):
                try:
                    item["uri"] = quote((path.parent / uri_path(uri)).resolve().as_posix())
                except (ValueError, OSError):  # a NUL, a lone surrogate, a name too long: no file has it
                    raise _bad(path, f"{key} uri {uri!r} is not a file name") from None


def _write_glb(target: Path, doc: dict, glb_bin: bytes | None) -> None:
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<I4s", len(text), b"JSON") + text
    if glb_bin is not None:
        padded = glb_bin + b"\0" * (-len(glb_bin) % 4)
        chunks += struct.pack("<I4s", len(padded), b"BIN\x00") + padded
    target.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks)


def _list_of_strings(doc: dict, key: str, path: Path) -> list[str]:
    value = doc.get(key) or []
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise _bad(path, f"{key} is not a list of names")
    return value


def prepare_gltf(path: Path, out: Path) -> tuple[Path, dict[str, dict]] | None:
    """For a glTF that uses an extension of :data:`APPLIED`: the copy to import (written into the folder ``out``)
    and the films by token: each iridescent material's extras carry only its token under :data:`EXTRAS_KEY`
    (``{token: {"material": name, **resolved}}``; the settings stay here, so a value the file itself puts under
    that key is removed, never applied: it could name any file). None for any other file (import it as it is).
    One-line SceneRefError naming the file for a malformed extension."""
    path, out = Path(path), Path(out)
    doc = gltf_json(path)
    if not any(e in _list_of_strings(doc, "extensionsUsed", path) for e in APPLIED):
        return None
    glb_bin = _glb_chunks(path)[1] if path.suffix.lower() == ".glb" else None
    nonce, films = secrets.token_hex(8), {}
    for i, mat in enumerate(gltf_items(doc, "materials", path)):
        exts = mat.get("extensions", {})
        if not isinstance(exts, dict):
            raise _bad(path, f"materials[{i}].extensions is not an object")
        extras = mat.get("extras") if isinstance(mat.get("extras"), dict) else None
        if extras is not None:
            extras.pop(EXTRAS_KEY, None)
        if exts.get(IRIDESCENCE) is None:
            continue
        token = f"{nonce}-{i}"
        films[token] = {"material": str(mat.get("name") or f"Material_{i}"),
                        **resolved_iridescence(path, doc, exts[IRIDESCENCE], glb_bin, out)}
        mat["extras"] = {**(extras or {}), EXTRAS_KEY: token}
    required = [e for e in _list_of_strings(doc, "extensionsRequired", path) if e not in APPLIED]
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
    return target, films


__all__ = ["APPLIED", "EXTRAS_KEY", "IRIDESCENCE", "prepare_gltf", "resolved_iridescence"]

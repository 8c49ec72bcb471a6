"""Hand-made glTF files for the iridescence tests (no bpy): two quads with UVs, each its own material; the first
material's film thickness is read from a 2x2 PNG (G channel), the second's is constant."""
from __future__ import annotations

import base64
import io
import json
import struct
from pathlib import Path

import numpy as np
from PIL import Image

#: G of the thickness texture's four texels: 0 (min), 255 (max) and two between.
TEXELS_G = (0, 255, 64, 191)


def png_bytes() -> bytes:
    rgb = np.zeros((2, 2, 3), np.uint8)
    rgb[..., 1] = np.array(TEXELS_G, np.uint8).reshape(2, 2)
    rgb[..., 0] = 255
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="PNG")
    return buf.getvalue()


def _geometry() -> tuple[bytes, list, list]:
    """Two unit quads side by side (positions, UVs, indices): the buffer, its views and accessors."""
    pos = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)
    idx = np.array([0, 1, 2, 0, 2, 3], np.uint16)
    blob = pos.tobytes() + uv.tobytes() + idx.tobytes()
    views = [{"buffer": 0, "byteOffset": 0, "byteLength": 48}, {"buffer": 0, "byteOffset": 48, "byteLength": 32},
             {"buffer": 0, "byteOffset": 80, "byteLength": 12}]
    accessors = [{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": [0, 0, 0],
                  "max": [1, 1, 0]},
                 {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC2"},
                 {"bufferView": 2, "componentType": 5123, "count": 6, "type": "SCALAR"}]
    return blob, views, accessors


def iridescent_doc(required: bool = True) -> tuple[dict, bytes]:
    """The glTF JSON (buffer 0 without a uri: the caller stores it) and its geometry bytes."""
    blob, views, accessors = _geometry()
    prim = {"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2}
    used = ["KHR_materials_iridescence", "KHR_materials_ior"]
    doc = {"asset": {"version": "2.0"}, "extensionsUsed": used, "scene": 0,
           "scenes": [{"nodes": [0, 1]}],
           "nodes": [{"mesh": 0, "name": "Textured"}, {"mesh": 1, "name": "Plain", "translation": [1.5, 0, 0]}],
           "meshes": [{"primitives": [dict(prim, material=0)]}, {"primitives": [dict(prim, material=1)]}],
           "materials": [
               {"name": "FilmTextured", "extras": {"kept": 1},
                "extensions": {"KHR_materials_iridescence": {
                    "iridescenceFactor": 1.0, "iridescenceIor": 1.5, "iridescenceThicknessMinimum": 200,
                    "iridescenceThicknessMaximum": 600, "iridescenceThicknessTexture": {"index": 0}}}},
               {"name": "FilmPlain", "extensions": {"KHR_materials_iridescence": {
                   "iridescenceFactor": 0.5, "iridescenceThicknessMaximum": 500}}}],
           "textures": [{"source": 0}], "images": [],
           "buffers": [{"byteLength": len(blob)}], "bufferViews": views, "accessors": accessors}
    if required:
        doc["extensionsRequired"] = ["KHR_materials_iridescence"]
    return doc, blob


def write_glb(path: Path, required: bool = True) -> Path:
    """A .glb whose texture is an embedded PNG (a buffer view of the binary chunk)."""
    doc, blob = iridescent_doc(required)
    png = png_bytes()
    blob += b"\0" * (-len(blob) % 4)
    doc["bufferViews"].append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(png)})
    doc["images"] = [{"bufferView": len(doc["bufferViews"]) - 1, "mimeType": "image/png"}]
    blob += png + b"\0" * (-len(png) % 4)
    doc["buffers"][0]["byteLength"] = len(blob)
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<I4s", len(text), b"JSON") + text + struct.pack("<I4s", len(blob), b"BIN\x00") + blob
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
    return path


def write_gltf(path: Path, required: bool = True, data_uri_image: bool = False) -> Path:
    """A .gltf beside its ``geometry.bin`` and ``film thickness.png`` (a name that needs URI quoting), or with the
    image as a data: URI. The textured material also samples that image as its base colour (sRGB)."""
    doc, blob = iridescent_doc(required)
    doc["materials"][0]["pbrMetallicRoughness"] = {"baseColorTexture": {"index": 0}}
    path.parent.mkdir(parents=True, exist_ok=True)
    (path.parent / "geometry.bin").write_bytes(blob)
    doc["buffers"][0]["uri"] = "geometry.bin"
    if data_uri_image:
        doc["images"] = [{"uri": "data:image/png;base64," + base64.b64encode(png_bytes()).decode()}]
    else:
        (path.parent / "film thickness.png").write_bytes(png_bytes())
        doc["images"] = [{"uri": "film%20thickness.png"}]
    path.write_text(json.dumps(doc))
    return path

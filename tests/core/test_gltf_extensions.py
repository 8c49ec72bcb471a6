"""gbuffer_export.gltf_extensions: the copy of a glTF whose KHR_materials_iridescence BlendSR applies (no bpy)."""
from __future__ import annotations

import json
import struct
from pathlib import Path
from urllib.parse import unquote

import pytest

from gbuffer_export.gltf_extensions import EXTRAS_KEY, _glb_chunks, prepare_gltf
from gbuffer_export.scene_refs import SceneRefError, check_scene_refs, gltf_json
from tests.gltf_fixtures import png_bytes, write_glb, write_gltf


def _film(doc: dict, films: dict) -> list[dict]:
    """Each material's resolved film, found by the token its extras carry in the copy."""
    return [{k: v for k, v in films[m["extras"][EXTRAS_KEY]].items() if k != "material"} for m in doc["materials"]]


def test_a_glb_requiring_iridescence_is_copied_with_the_film_in_extras_and_the_requirement_dropped(tmp_path):
    src = write_glb(tmp_path / "asset" / "film.glb")
    out = tmp_path / "scratch"
    out.mkdir()
    copy, films = prepare_gltf(src, out)
    names = [f["material"] for f in films.values()]
    assert copy.parent == out and copy.suffix == ".glb" and names == ["FilmTextured", "FilmPlain"]
    doc = gltf_json(copy)
    assert "extensionsRequired" not in doc and "KHR_materials_iridescence" in doc["extensionsUsed"]
    textured, plain = _film(doc, films)
    assert doc["materials"][0]["extras"]["kept"] == 1  # the material's own extras stay
    assert {k: textured[k] for k in ("factor", "ior", "thickness_min", "thickness_max")} == {
        "factor": 1.0, "ior": 1.5, "thickness_min": 200.0, "thickness_max": 600.0}
    # the embedded PNG is written out byte for byte, with its UV set
    assert Path(textured["thickness_texture"]["path"]).read_bytes() == png_bytes()
    assert textured["thickness_texture"]["uv"] == 0 and Path(textured["thickness_texture"]["path"]).parent == out
    # the extension's defaults: film IOR 1.3, thickness from 100 nm; no texture, no texture key
    assert plain == {"factor": 0.5, "ior": 1.3, "thickness_min": 100.0, "thickness_max": 500.0}
    # the binary chunk is kept: same geometry bytes, and the copy is a well-formed .glb
    data = copy.read_bytes()
    assert struct.unpack_from("<I", data, 8)[0] == len(data)
    assert _glb_chunks(copy)[1] == _glb_chunks(src)[1] and len(_glb_chunks(src)[1]) > 100
    assert check_scene_refs(copy) == []


def test_a_gltf_copy_elsewhere_points_at_the_assets_own_files(tmp_path):
    src = write_gltf(tmp_path / "asset" / "film.gltf", required=False)
    out = tmp_path / "scratch"
    out.mkdir()
    copy, films = prepare_gltf(src, out)
    doc = json.loads(copy.read_text())
    assert "extensionsRequired" not in doc
    uris = [unquote(doc["buffers"][0]["uri"]), unquote(doc["images"][0]["uri"])]
    assert uris == [str((src.parent / "geometry.bin").resolve().as_posix()),
                    str((src.parent / "film thickness.png").resolve().as_posix())]
    tex = _film(doc, films)[0]["thickness_texture"]
    assert tex["path"] == str((src.parent / "film thickness.png").resolve())  # read in place, not copied
    assert not any(p.suffix == ".png" for p in out.iterdir())


def test_a_data_uri_texture_is_decoded_and_a_missing_image_leaves_the_film_untextured(tmp_path):
    out = tmp_path / "scratch"
    out.mkdir()
    copy, films = prepare_gltf(write_gltf(tmp_path / "a" / "film.gltf", data_uri_image=True), out)
    assert Path(_film(json.loads(copy.read_text()), films)[0]["thickness_texture"]["path"]).read_bytes() == png_bytes()
    src = write_gltf(tmp_path / "b" / "film.gltf")
    (src.parent / "film thickness.png").unlink()
    copy, films = prepare_gltf(src, out)
    assert "thickness_texture" not in _film(json.loads(copy.read_text()), films)[0]


def test_other_required_extensions_stay_required_and_files_without_iridescence_are_imported_as_they_are(tmp_path):
    src = write_gltf(tmp_path / "a" / "film.gltf")
    doc = json.loads(src.read_text())
    doc["extensionsUsed"].append("EXT_meshopt_compression")
    doc["extensionsRequired"].append("EXT_meshopt_compression")
    src.write_text(json.dumps(doc))
    out = tmp_path / "scratch"
    out.mkdir()
    copy, _ = prepare_gltf(src, out)
    assert json.loads(copy.read_text())["extensionsRequired"] == ["EXT_meshopt_compression"]
    for m in doc["materials"]:
        m.pop("extensions")
    doc["extensionsUsed"] = ["KHR_materials_ior"]
    doc.pop("extensionsRequired")
    src.write_text(json.dumps(doc))
    assert prepare_gltf(src, out) is None


IRI = "KHR_materials_iridescence"


def _set_film(doc, value):
    doc["materials"][0]["extensions"][IRI] = value


def _set_tex(doc, **info):
    doc["materials"][0]["extensions"][IRI]["iridescenceThicknessTexture"] = info


#: (what to break in the .gltf fixture, the words of the one-line error)
MALFORMED = {
    "ior as a string": (lambda d: _set_film(d, {"iridescenceIor": "1.3"}), "iridescenceIor is '1.3'"),
    "film not an object": (lambda d: _set_film(d, "film"), "of a material is not an object"),
    "texture not an object": (lambda d: _set_film(d, {"iridescenceThicknessTexture": 0}), "not a textureInfo"),
    "infinite thickness": (lambda d: _set_film(d, {"iridescenceThicknessMaximum": float("inf")}),
                           "iridescenceThicknessMaximum is inf"),
    "huge thickness": (lambda d: _set_film(d, {"iridescenceThicknessMaximum": 10 ** 400}), "not a number in"),
    "negative thickness": (lambda d: _set_film(d, {"iridescenceThicknessMinimum": -5}), "[0, inf]"),
    "factor above 1": (lambda d: _set_film(d, {"iridescenceFactor": 1.5}), "iridescenceFactor is 1.5"),
    "ior below 1": (lambda d: _set_film(d, {"iridescenceIor": 0.5}), "iridescenceIor is 0.5"),
    "texture index out of range": (lambda d: _set_tex(d, index=3), "index is 3: not an index below 1"),
    "negative texture index": (lambda d: _set_tex(d, index=-1), "index is -1"),
    "boolean texture index": (lambda d: _set_tex(d, index=True), "index is True"),
    "texCoord a string": (lambda d: _set_tex(d, index=0, texCoord="a"), "texCoord is 'a'"),
    "negative texCoord": (lambda d: _set_tex(d, index=0, texCoord=-1), "texCoord is -1"),
    "textures not a list": (lambda d: d.update(textures={"0": {}}), "textures is not a list of objects"),
    "image source out of range": (lambda d: d["textures"][0].update(source=7), "textures[0].source is 7"),
    "image without data": (lambda d: d["images"][0].pop("uri"), "images[0] has neither a uri nor a bufferView"),
    "image view out of range": (lambda d: d["images"][0].update(uri=None, bufferView=9),
                                "images[0].bufferView is 9"),
    "image view too long": (lambda d: (d["images"][0].pop("uri"), d["images"][0].update(bufferView=0),
                                       d["bufferViews"][0].update(byteLength=10 ** 6)), "does not fit its buffer"),
    "data URI without data": (lambda d: d["images"][0].update(uri="data:image/png;base64"), "without data"),
    "data URI bad base64": (lambda d: d["images"][0].update(uri="data:image/png;base64,@@@"), "base64 is malformed"),
    "extensions a list": (lambda d: d["materials"][1].update(extensions=[]), "materials[1].extensions is not"),
    "material not an object": (lambda d: d["materials"].append(3), "materials is not a list of objects"),
    "data URI not ASCII": (lambda d: d["images"][0].update(uri="data:image/png;base64,\u00e9\u00e9"),
                           "base64 is malformed"),
    "required not a list": (lambda d: d.update(extensionsRequired=5), "extensionsRequired is not a list of names"),
    "NUL in a uri": (lambda d: d["images"][0].update(uri="a%00b.png"), "is not a file name"),
    "uri longer than a name": (lambda d: d["images"][0].update(uri="x" * 5000 + ".png"), "is not a file name"),
    "lone surrogate in a uri": (lambda d: d["buffers"][0].update(uri="geometry\ud800.bin"), "not a file name"),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_a_malformed_iridescence_is_one_line_naming_the_file(tmp_path, case):
    """Every malformed value or reference of the extension: SceneRefError naming the file, never a traceback of
    another kind and never a film silently dropped."""
    src = write_gltf(tmp_path / "a" / "film.gltf")
    doc = json.loads(src.read_text())
    breaks, words = MALFORMED[case]
    breaks(doc)
    src.write_text(json.dumps(doc))
    with pytest.raises(SceneRefError) as e:
        prepare_gltf(src, tmp_path)
    msg = str(e.value)
    assert msg.startswith(f"{src}: ") and words in msg and "\n" not in msg, msg


def test_a_film_the_file_itself_writes_into_the_extras_key_is_removed_never_applied(tmp_path):
    """The settings never travel through the file: a material's own ``blendsr_iridescence`` extra (which could name
    any file on the machine as its texture) is removed from the copy; only the tokens of this call's films remain."""
    src = write_gltf(tmp_path / "a" / "film.gltf")
    doc = json.loads(src.read_text())
    doc["materials"].append({"name": "Forged", "extras": {EXTRAS_KEY: {"factor": 1, "ior": 1.5, "thickness_min": 0,
                             "thickness_max": 1, "thickness_texture": {"path": "/etc/passwd", "uv": 0}}}})
    doc["materials"][1]["extras"] = {EXTRAS_KEY: "forged-token"}
    src.write_text(json.dumps(doc))
    out = tmp_path / "scratch"
    out.mkdir()
    copy, films = prepare_gltf(src, out)
    mats = json.loads(copy.read_text())["materials"]
    assert EXTRAS_KEY not in mats[2].get("extras", {}) and len(films) == 2
    assert {m["extras"][EXTRAS_KEY] for m in mats[:2]} == set(films) and "forged-token" not in films


def test_deeply_nested_json_is_one_line(tmp_path):
    src = tmp_path / "deep.gltf"
    src.write_text('{"asset": {"version": "2.0"}, "extras": ' + "[" * 100000 + "]" * 100000 + "}")
    with pytest.raises(SceneRefError, match=r"deep\.gltf: not a valid glTF file \(its JSON is nested too deeply"):
        prepare_gltf(src, tmp_path)


def test_a_buffer_file_that_cannot_be_read_and_a_truncated_glb_are_one_line(tmp_path):
    src = write_gltf(tmp_path / "a" / "film.gltf")
    doc = json.loads(src.read_text())
    doc["images"][0] = {"bufferView": 0}
    doc["buffers"][0]["uri"] = "gone.bin"
    src.write_text(json.dumps(doc))
    with pytest.raises(SceneRefError, match=r"film\.gltf: glTF buffers\[0\]\.uri 'gone\.bin' cannot be read"):
        prepare_gltf(src, tmp_path)
    glb = write_glb(tmp_path / "b" / "film.glb")
    glb.write_bytes(glb.read_bytes()[:-40])
    with pytest.raises(SceneRefError, match=r"film\.glb: truncated glTF binary"):
        prepare_gltf(glb, tmp_path)


def test_uris_are_read_as_the_importer_reads_them_backslashes_and_webp_sources_included(tmp_path):
    src = write_gltf(tmp_path / "a" / "film.gltf")
    (src.parent / "tex").mkdir()
    (src.parent / "film thickness.png").rename(src.parent / "tex" / "t.png")
    doc = json.loads(src.read_text())
    doc["images"] = [{"uri": "data:image/png;base64,AAAA"}, {"uri": "tex\\t.png"}]
    doc["textures"][0] = {"source": 0, "extensions": {"EXT_texture_webp": {"source": 1}}}
    src.write_text(json.dumps(doc))
    out = tmp_path / "scratch"
    out.mkdir()
    copy, films = prepare_gltf(src, out)
    tex = _film(json.loads(copy.read_text()), films)[0]["thickness_texture"]
    assert tex["path"] == str((src.parent / "tex" / "t.png").resolve())
    assert unquote(json.loads(copy.read_text())["images"][1]["uri"]) == (src.parent / "tex" / "t.png").as_posix()

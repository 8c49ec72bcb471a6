"""Every format of the format table (gbuffer_export/scene_formats.py) loads through one importer table
(gbuffer_export/blender/importers.py), and a level's missing textures render mid grey, named once."""
from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from tests.conftest import ENV, REPO, SHARED, requires_bpy
from gbuffer_export.config import RenderConfig
from gbuffer_export.dataset.spec import find_assets
from gbuffer_export.scene_formats import SCENE_FORMATS, SCENE_SUFFIXES, scene_format
from gbuffer_export.typed_table import ConfigError

PROBES = Path(__file__).resolve().parent.parent / "format_probes.py"


def run_probe(name: str, args: dict, timeout: int = 240) -> tuple[dict, str]:
    proc = subprocess.run([sys.executable, str(PROBES), name, json.dumps(args)], cwd=REPO, env=ENV,
                          capture_output=True, text=True, timeout=timeout)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("PROBE-RESULT ")]
    assert proc.returncode == 0 and lines, f"probe {name} failed ({proc.returncode}):\n{proc.stderr[-3000:]}"
    return json.loads(lines[-1][len("PROBE-RESULT "):]), proc.stderr


# ----------------------------------------------------------------------------------------------
# The table (no bpy)
# ----------------------------------------------------------------------------------------------

def test_one_table_names_every_format_blender_5_imports():
    names = [f.name for f in SCENE_FORMATS]
    assert names == ["Blender", "glTF", "USD", "OBJ", "FBX", "PLY", "STL", "Alembic"]
    assert len(set(SCENE_SUFFIXES)) == len(SCENE_SUFFIXES) and all(s == s.lower() for s in SCENE_SUFFIXES)
    assert scene_format("A/LEVEL.OBJ").name == "OBJ" and scene_format("x.mtl") is None


def test_the_docs_list_the_table():
    """docs/rendering.md's formats table has one row per format with its suffixes and operator."""
    text = (REPO / "docs" / "rendering.md").read_text()
    section = text.split("### Scene formats", 1)[1].split("\n#", 1)[0]
    rows = [ln for ln in section.splitlines() if ln.startswith("| ") and not ln.startswith("| format")]
    assert len(rows) == len(SCENE_FORMATS)
    for fmt, row in zip(SCENE_FORMATS, rows):
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert cells[0] == fmt.name and cells[1] == ", ".join(f"`{s}`" for s in fmt.suffixes), row
        assert f"`bpy.ops.{fmt.operator}`" in cells[2], row


def test_render_config_and_dataset_specs_accept_the_table_and_nothing_else(tmp_path):
    for suffix in SCENE_SUFFIXES:
        f = tmp_path / f"level_{suffix[1:]}{suffix}"
        f.write_bytes(b"x")
        RenderConfig(output=tmp_path / "out", scene=f)
    bad = tmp_path / "level.mtl"
    bad.write_text("newmtl a\n")
    with pytest.raises(ConfigError, match=r"level\.mtl: not a scene file \(one of \.blend, \.gltf, .*\.abc\)"):
        RenderConfig(output=tmp_path / "out", scene=bad)
    found = find_assets(SimpleNamespace(name="levels", kind="scene", paths=[str(tmp_path)]), None, "spec.toml")
    assert sorted(p.suffix for p in found) == sorted(SCENE_SUFFIXES)


# ----------------------------------------------------------------------------------------------
# Round trips and refusals (bpy, in a subprocess)
# ----------------------------------------------------------------------------------------------

@requires_bpy
@pytest.mark.bpy
def test_every_format_round_trips_through_the_table(tmp_path):
    """A floor and a box exported by Blender to each format and imported back by ``load_level``: the same 14
    triangles in the same place (Y-up formats converted back to Z up), materials where the format has them."""
    res, _ = run_probe("roundtrip", {"dir": str(tmp_path)})
    by_format = {r["report"]["format"] for r in res.values()}
    assert by_format == {f.name for f in SCENE_FORMATS}
    for suffix, r in res.items():
        assert r["report"] == {"format": scene_format(f"x{suffix}").name}, suffix
        assert r["triangles"] == 14, suffix
        assert np.allclose(r["lo"], [-2, -2, 0], atol=1e-4) and np.allclose(r["hi"], [2, 2, 1], atol=1e-4), suffix
        if suffix in (".glb", ".blend", ".usdc", ".usda", ".obj", ".fbx"):
            assert r["materials"] == ["Red"], suffix


@requires_bpy
@pytest.mark.bpy
def test_a_format_this_blender_cannot_import_or_a_broken_file_is_one_line_naming_why(tmp_path):
    rng = np.random.default_rng(0)
    junk = {}
    for suffix in (".fbx", ".ply", ".abc", ".usdc", ".glb"):
        junk[suffix] = tmp_path / f"junk{suffix}"
        junk[suffix].write_bytes(rng.integers(0, 256, 300, dtype=np.uint8).tobytes())
    res, _ = run_probe("refusals", {"file": str(tmp_path / "level.fake"), "junk": [str(p) for p in junk.values()]})
    assert "level.fake: this Blender cannot import Fake (its add-on io_blendsr_no_such_addon is" in res["addon"]
    assert "level.fake: this Blender build has no Nothing importer (bpy.ops.wm.blendsr_nothing_import)" in \
        res["operator"]
    assert all("export the level as glTF" in res[k] for k in ("addon", "operator"))
    for suffix, p in junk.items():
        name = scene_format(p).name
        msg = res[str(p)]  # the importer's own failure or crash (a child process), or the resolver's refusal (glTF)
        assert msg.startswith(f"{p}: the {name} importer failed (") or msg.startswith(f"{p}: not a {name}"), msg
    assert all("\n" not in m for m in res.values())


# ----------------------------------------------------------------------------------------------
# Missing textures
# ----------------------------------------------------------------------------------------------

def _obj_with_missing_textures(folder: Path) -> Path:
    """A 6 m floor and a 1 m box whose .mtl names three images that are not there (colour, normal map, alpha)
    and one that is (a 2x2 PNG written here)."""
    from PIL import Image
    tex = folder / "textures"
    tex.mkdir(parents=True)
    Image.new("RGB", (2, 2), (200, 180, 40)).save(tex / "present.png")
    (folder / "level.mtl").write_text(
        "newmtl floor\nKd 0.8 0.8 0.8\nmap_Kd textures/floor_diffuse.png\nmap_Bump textures/floor_normal.png\n\n"
        "newmtl crate\nKd 0.8 0.8 0.8\nmap_Kd textures/present.png\nmap_d textures/crate_alpha.png\n")
    v = [(-3, -3, 0), (3, -3, 0), (3, 3, 0), (-3, 3, 0)]
    v += [(x, y, z) for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (0.0, 1.0)]
    box = [(5, 7, 8, 6), (5, 6, 10, 9), (9, 10, 12, 11), (11, 12, 8, 7), (6, 8, 12, 10), (5, 9, 11, 7)]
    lines = ["mtllib level.mtl"] + [f"v {x} {z} {-y}" for x, y, z in v]  # OBJ is Y up
    lines += ["vt 0 0", "vt 1 0", "vt 1 1", "vt 0 1", "usemtl floor", "f 1/1 2/2 3/3 4/4", "usemtl crate"]
    lines += ["f " + " ".join(f"{i}/{k + 1}" for k, i in enumerate(face)) for face in box]
    path = folder / "level.obj"
    path.write_text("\n".join(lines) + "\n")
    return path


@requires_bpy
@pytest.mark.bpy
def test_missing_textures_become_neutral_and_are_named_once(tmp_path):
    obj = _obj_with_missing_textures(tmp_path / "lvl")
    res, err = run_probe("missing", {"obj": str(obj)})
    missing = ["textures/crate_alpha.png", "textures/floor_diffuse.png", "textures/floor_normal.png"]
    assert res["report"] == {"format": "OBJ", "missing_textures": missing}
    floor, crate = res["materials"]["floor"], res["materials"]["crate"]
    assert not floor["base_color_linked"] and floor["base_color"] == pytest.approx([0.5, 0.5, 0.5, 1.0])
    assert floor["images"] == {"floor_diffuse.png": [], "floor_normal.png": []}  # nothing reads them
    assert floor["normal_maps"] == [pytest.approx([0.5, 0.5, 1.0, 1.0])]         # a flat normal
    assert crate["base_color_linked"] and crate["images"]["present.png"] == [["Color", "BSDF_PRINCIPLED",
                                                                              "Base Color"]]
    assert not crate["alpha_linked"] and crate["alpha"] == 1.0
    warned = [ln for ln in err.splitlines() if "missing" in ln.lower() or "cannot load" in ln.lower()]
    assert warned == ["level.obj: 3 texture file(s) missing, rendered as mid grey (albedo 0.5), never magenta: "
                      + ", ".join(missing)], err[-2000:]


@requires_bpy
@pytest.mark.bpy
def test_a_gltfs_missing_data_textures_become_flat_normals_and_mid_roughness(tmp_path):
    """glTF splits occlusion-roughness-metallic with a Separate Color node: a missing texture there reads as
    occlusion 1, roughness 0.5, metallic 0; a missing normal map as a flat normal; colour as mid grey."""
    res, _ = run_probe("gltf_missing", {"dir": str(tmp_path)})
    assert res["report"] == {"format": "glTF", "missing_textures": ["colour.png", "normal.png", "rough.png"]}
    assert res["images_read"] == [] and res["split"] == [pytest.approx([1.0, 0.5, 0.0, 1.0])]
    assert res["normal_maps"] == [pytest.approx([0.5, 0.5, 1.0, 1.0])]
    assert res["base_color"] == pytest.approx([0.5, 0.5, 0.5, 1.0]) and not res["base_color_linked"]


RENDER = """
import json, sys
from gbuffer_export.config import RenderConfig
from gbuffer_export.blender.render import render_clip
from gbuffer_export.logs import configure_logging
configure_logging(0)
render_clip(RenderConfig(**json.loads(sys.argv[1])))
"""


def render_api(tmp_path: Path, **kw) -> subprocess.CompletedProcess:
    """``render_clip(RenderConfig(**kw))`` in a fresh process (the Python API, docs: README "Python API")."""
    kw = {"frames": [1, 2], "hr_size": [64, 36], "hr_spp": 2, "lr_spp": 1, "gbuffer_spp": 1, "threads": 1,
          "progress": False, **kw}
    return subprocess.run([sys.executable, "-c", RENDER, json.dumps(kw, default=str)], cwd=REPO, env=ENV,
                          capture_output=True, text=True, timeout=600)


def magenta_fraction(rgb: np.ndarray) -> float:
    """Pixels that look like Cycles' missing-texture colour: red and blue well above green."""
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    return float(((r > 2.5 * g + 1e-3) & (b > 2.5 * g + 1e-3)).mean())


@requires_bpy
@pytest.mark.bpy
def test_a_level_with_missing_textures_renders_grey_and_its_manifest_lists_them(tmp_path):
    from gbuffer_export.clip import open_clip
    obj = _obj_with_missing_textures(tmp_path / "lvl")
    out = tmp_path / "clip"
    r = render_api(tmp_path, output=str(out), scene=str(obj), camera_path="orbit", light="sky", frames=[1, 1])
    assert r.returncode == 0, r.stderr[-3000:]
    assert len(re.findall(r"texture file\(s\) missing", r.stderr)) == 1
    clip = open_clip(out)
    assert clip.manifest["scene"]["missing_textures"] == ["textures/crate_alpha.png", "textures/floor_diffuse.png",
                                                          "textures/floor_normal.png"]
    assert clip.manifest["scene"]["format"] == "OBJ"
    for f in clip.frames:
        albedo = clip.read(f, "hr/albedo")
        fg = albedo.sum(axis=-1) > 0
        assert fg.mean() > 0.05  # the orbit frames the level from outside
        grey = np.all(np.abs(albedo[fg] - 0.5) < 1e-3, axis=-1)  # the floor: 0.5 grey, no magenta
        assert grey.mean() > 0.3 and magenta_fraction(albedo) == 0.0
        assert magenta_fraction(clip.read(f, "hr/radiance")) < 0.01


@requires_bpy
@pytest.mark.bpy
def test_gltf_iridescence_becomes_the_principled_thin_film_where_blender_alone_refuses_the_file(tmp_path):
    """KHR_materials_iridescence (required) in a .glb with an embedded texture, a .gltf beside its files and the real
    IridescenceSuzanne: Blender 5.0.1's importer alone refuses each; through load_level (a scene) and import_asset
    (a dataset asset) each material gets Thin Film IOR and Thickness = factor x mix(min, max, texture G) nm."""
    from tests.gltf_fixtures import TEXELS_G, write_glb, write_gltf
    files = [write_glb(tmp_path / "a" / "film.glb"), write_gltf(tmp_path / "b" / "film.gltf")]
    suzanne = SHARED / "scenes/gltf_more/IridescenceSuzanne/glTF-Binary/IridescenceSuzanne.glb"
    if suzanne.is_file():
        files.append(suzanne)
    res, _ = run_probe("gltf_iridescence", {"files": [str(p) for p in files]})
    for path in files[:2]:
        rec = res[str(path)]
        assert "KHR_materials_iridescence is not available" in rec["blender_alone"]
        for films in (rec["level"], rec["asset"]):
            plain, textured = films["FilmPlain"], films["FilmTextured"]
            assert plain["ior"] == pytest.approx(1.3) and plain["thickness"] == 250 and not plain["linked"]
            assert textured["ior"] == 1.5 and textured["linked"] and textured["props"] == ["kept"]
            kinds = [(c[0], c[1]) for c in textured["chain"]]
            assert kinds == [("MATH", "MULTIPLY"), ("MATH", "ADD"), ("MATH", "MULTIPLY"), ("SEPARATE_COLOR", None),
                             ("TEX_IMAGE", None)]
            assert [c[2][0] for c in textured["chain"][:3]] == [1.0, 200.0, 400.0]  # factor, min, max - min
            green = sorted(round(v * 255) for v in textured["chain"][4][3][1::4])
            assert green == sorted(TEXELS_G) and all(textured["packed"])
        # the .gltf's base colour samples the film's file: it stays sRGB (the film reads its own Non-Color copy)
        assert rec["level"]["FilmTextured"]["base_colour_space"] == (["sRGB"] if path.suffix == ".gltf" else [])
    if len(files) == 3:
        films = res[str(suzanne)]["asset"]
        assert sorted((round(f["ior"], 2), f["thickness"] if not f["linked"] else "texture")
                      for f in films.values()) == [(1.33, 400.0), (1.33, 400.0), (1.8, "texture")]

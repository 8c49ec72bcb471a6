"""``light = "auto"`` and sky meshes: the rule on synthetic geometry, a synthetic level enclosed by a sky mesh
rendering lit, the unlit shared interiors lit, and the manifest's records. Rendered tiny (64x36, few spp)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import ENV, REPO, requires_bpy, run_cli, shared_or_skip
from tests.render.cli_batch import run_cli_batch
from gbuffer_export import open_clip

pytestmark = [requires_bpy, pytest.mark.bpy]

TINY = ["--hr-size", "64x36", "--hr-spp", "2", "--lr-spp", "1", "--gbuffer-spp", "1", "--threads", "1",
        "--no-progress", "--frames", "1:2"]
#: the synthetic sky level in one frame: each frame is a probe view and three Cycles renders, seconds each under its
#: sky texture, and the checks hold per frame (the shared interiors keep two: a one-frame walk in the garage stands
#: where it sees the sky, and the ceiling lamps are not added)
ONE_FRAME = ["--frames", "1:1"]
LUMA = np.array([0.2126, 0.7152, 0.0722])


def _manifest(clip: Path) -> dict:
    return json.loads((clip / "manifest.json").read_text())


def _luminance(clip: Path) -> np.ndarray:
    c = open_clip(clip)
    return np.stack([c.read(f, "hr/radiance")[..., :3] @ LUMA for f in c.manifest["frames"]])


# ----------------------------------------------------------------------------------------------
# The sky-mesh rule on synthetic geometry (no render)
# ----------------------------------------------------------------------------------------------

def _geometry(parts):
    """LevelGeometry of trimesh parts, one object each."""
    from gbuffer_export.blender.level_geometry import LevelGeometry
    verts, faces, owner, off = [], [], [], 0
    for k, m in enumerate(parts):
        verts.append(np.asarray(m.vertices))
        faces.append(np.asarray(m.faces) + off)
        owner.append(np.full(len(m.faces), k))
        off += len(m.vertices)
    return LevelGeometry(np.concatenate(verts), np.concatenate(faces), 1.0, [f"o{k}" for k in range(len(parts))],
                         np.concatenate(owner))


def _town():
    import trimesh
    ground = trimesh.creation.box((40, 40, 0.2), trimesh.transformations.translation_matrix((0, 0, -0.1)))
    houses = [trimesh.creation.box((4, 4, h), trimesh.transformations.translation_matrix((x, y, h / 2)))
              for x, y, h in ((-8, -8, 5), (8, -6, 7), (-6, 9, 4), (7, 8, 6))]
    return [ground, *houses]


def test_the_sky_mesh_rule_finds_domes_and_boxes_not_rooms_or_ground():
    import trimesh
    from gbuffer_export.blender.lighting import find_sky_meshes
    dome = trimesh.creation.icosphere(subdivisions=2, radius=120.0)
    dome.invert()  # faces turned inwards, as a skydome's
    found, report = find_sky_meshes(_geometry([*_town(), dome]), unlit=set())
    assert found == [5] and report[-1]["sky"] and report[-1]["front_faces_inside"] > 0.9
    outward = trimesh.creation.icosphere(subdivisions=2, radius=120.0)  # lit and facing out: not a sky
    assert find_sky_meshes(_geometry([*_town(), outward]), unlit=set())[0] == []
    assert find_sky_meshes(_geometry([*_town(), outward]), unlit={"o5"})[0] == [5]  # an unlit sky shader
    # A room's shell (its floor carries the furniture) is not a sky, even unlit; a ground plane neither.
    room = trimesh.creation.box((10, 8, 3), trimesh.transformations.translation_matrix((0, 0, 1.5)))
    room.invert()
    sofa = trimesh.creation.box((2, 1, 0.8), trimesh.transformations.translation_matrix((0, 0, 0.4)))
    found, report = find_sky_meshes(_geometry([room, sofa]), unlit={"o0"})
    assert found == [] and report[0]["upper_hits"] == 1.0 and abs(report[0]["gap_below"]) < 0.05
    assert find_sky_meshes(_geometry(_town()), unlit=set())[0] == []


def test_ceiling_lamps_stand_under_the_ceiling_of_the_eyes_storey():
    import trimesh
    from gbuffer_export.blender.lighting import ceiling_points, roofed
    at = trimesh.transformations.translation_matrix
    room = trimesh.creation.box((12, 9, 3), at((0, 0, 1.5)))
    room.invert()
    upstairs = trimesh.creation.box((12, 9, 3), at((0, 0, 4.6)))  # another storey over a 0.1 m slab
    upstairs.invert()
    pillar = trimesh.creation.box((2, 2, 3), at((1.5, 0, 1.5)))  # a solid where a grid point would fall
    geom = _geometry([room, upstairs, pillar])
    eyes = np.array([[-3.0, -2.0, 1.6], [-2.0, -1.0, 1.6], [0.0, -3.0, 1.6]])
    assert (roofed(geom, eyes) == 1.0).all()
    pts, heights, spacing = ceiling_points(geom, eyes)
    assert spacing == 3.0 and 6 <= len(pts) <= 12  # a 3 m grid over the 12 x 9 m room, the pillar's point left out
    assert np.allclose(pts[:, 2], 2.95) and np.allclose(heights, 2.95)  # 5 cm under this storey's ceiling
    assert not any(abs(p[0] - 1.5) < 1.0 and abs(p[1]) < 1.0 for p in pts)
    outward = _geometry([trimesh.creation.box((12, 9, 3), at((0, 0, 1.5)))])  # a default cube scaled into a room
    assert np.allclose(ceiling_points(outward, eyes)[0][:, 2], 2.95)
    outdoors = _geometry(_town())  # the eye is not under a roof; grid points inside the houses are not seen
    assert (roofed(outdoors, np.array([[0.0, 0.0, 1.6]])) == 0.0).all()
    assert len(ceiling_points(outdoors, np.array([[0.0, 0.0, 1.6]]))[0]) == 0


def test_luminance_stats_key_the_log_average():
    from gbuffer_export.blender.lighting import is_lit, luminance_stats
    lit = luminance_stats(np.full(100, 0.2))
    assert lit["log_average"] == pytest.approx(0.2) and lit["dark_fraction_keyed"] == 0.0 and is_lit(lit)
    dim = luminance_stats(np.full(100, 0.002))  # evenly lit but 7 stops under middle grey: too dim
    assert dim["dark_fraction"] == 0.0 and not is_lit(dim)
    spot = luminance_stats(np.r_[np.zeros(90), np.ones(10)])  # a lamp's pool of light in the dark
    assert spot["dark_fraction_keyed"] == pytest.approx(0.9) and not is_lit(spot)
    mask = np.r_[np.zeros(90, bool), np.ones(10, bool)]
    assert luminance_stats(np.r_[np.zeros(90), np.ones(10)], mask)["pixels"] == 10  # the level's pixels only


# ----------------------------------------------------------------------------------------------
# A synthetic level enclosed by a sky mesh
# ----------------------------------------------------------------------------------------------

SKY_LEVEL = r"""
import sys, bpy, bmesh
out, unlit = sys.argv[1], sys.argv[2] == "unlit"
bpy.ops.wm.read_factory_settings(use_empty=True)
s = bpy.context.scene
s.frame_start, s.frame_end = 1, 4

def mat(name, rgb, emit=False):
    m = bpy.data.materials.new(name)
    nt = m.node_tree
    if emit:  # an unlit sky shader: emission only
        nt.nodes.clear()
        e = nt.nodes.new("ShaderNodeEmission")
        e.inputs["Color"].default_value = (*rgb, 1.0)
        o = nt.nodes.new("ShaderNodeOutputMaterial")
        nt.links.new(e.outputs[0], o.inputs["Surface"])
    else:
        nt.nodes["Principled BSDF"].inputs["Base Color"].default_value = (*rgb, 1.0)
    return m

def obj(name, bm, m, loc=(0, 0, 0), scale=(1, 1, 1)):
    me = bpy.data.meshes.new(name)
    bm.to_mesh(me)
    bm.free()
    me.materials.append(m)
    ob = bpy.data.objects.new(name, me)
    ob.location, ob.scale = loc, scale
    s.collection.objects.link(ob)

def cube():
    bm = bmesh.new()
    bmesh.ops.create_cube(bm, size=1.0)
    return bm

grey, wall = mat("grey", (0.5, 0.5, 0.5)), mat("wall", (0.6, 0.45, 0.3))
obj("Ground", cube(), grey, (0, 0, -0.1), (40, 40, 0.2))
for k, (x, y, sx, sy) in enumerate(((0, 15, 30, 1), (0, -15, 30, 1), (15, 0, 1, 30), (-15, 0, 1, 30))):
    obj(f"Wall{k}", cube(), wall, (x, y, 2), (sx, sy, 4))
for k, (x, y) in enumerate(((-5, -4), (4, 5), (6, -6))):
    obj(f"Crate{k}", cube(), grey, (x, y, 1), (2, 2, 2))
bm = bmesh.new()
bmesh.ops.create_uvsphere(bm, u_segments=24, v_segments=12, radius=150.0)
bmesh.ops.reverse_faces(bm, faces=bm.faces)  # seen from inside
obj("Skydome", bm, mat("sky", (0.25, 0.45, 0.9), emit=unlit))
bpy.ops.wm.save_as_mainfile(filepath=out)
"""


def _sky_levels(tmp_path: Path) -> dict[str, Path]:
    """The level of ``SKY_LEVEL`` with an unlit (emission) dome and with a lit one, built in one process."""
    out = {kind: tmp_path / f"sky_{kind}.blend" for kind in ("unlit", "lit")}
    code = f"import sys\nSCRIPT = {SKY_LEVEL!r}\nfor out, kind in {[(str(v), k) for k, v in out.items()]!r}:\n" \
           "    sys.argv = ['sky', out, kind]\n    exec(SCRIPT, {})\n"
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, env=ENV, cwd=REPO, timeout=120)
    return out


def test_a_level_inside_a_sky_mesh_renders_lit_under_auto_and_sky(tmp_path):
    levels = _sky_levels(tmp_path)
    out, out_sky = tmp_path / "auto", tmp_path / "sky"
    # the unlit dome under auto and the lit dome under sky (made unlit, still no shadow): renders and validate in
    # one process (cli_batch)
    r, v, r_sky = run_cli_batch(["render", levels["unlit"], "-o", out, "--camera-path", "walk", *TINY, *ONE_FRAME],
                                ["validate", out],
                                ["render", levels["lit"], "-o", out_sky, "--camera-path", "walk", "--light", "sky",
                                 *TINY, *ONE_FRAME])
    assert r.returncode == 0, r.stderr[-2000:]
    light = _manifest(out)["light"]
    sky = light["sky_meshes"]
    assert sky["found"] == ["Skydome"] and sky["treated"] == [{"object": "Skydome", "visible": ["camera"],
                                                                "made_unlit": []}]
    dome = next(c for c in sky["candidates"] if c["object"] == "Skydome")
    assert dome["sky"] and dome["unlit"] and dome["upper_hits"] >= 0.9
    # its emission lights nothing once it is the sky: the file is unlit, the cameras see the sky: sun and sky
    assert light["scene_sources"]["emissive_materials"] == 0 and light["probe"]["scene_light"] is None
    assert light["added"] == ["sky"] and min(v["open_sky"] for v in light["views"]) >= 0.05
    assert light["probe"]["with_added_light"]["dark_fraction_keyed"] < 0.2
    y = _luminance(out)
    assert (y < 1e-3).mean() < 0.2 and y.mean() > 0.05  # lit: the dome neither shadows the sun nor the sky
    clip = open_clip(out)
    seen = [v for v in light["views"] if v["sees_sky"] > 0.05]
    assert seen  # the walls are low: the cameras see the sky, which is the dome, drawn as the game does
    for view in seen:
        assert (clip.read(view["frame"], "hr/depth") > 100).mean() >= 0.5 * view["sees_sky"]
    assert v.returncode == 0, v.stdout + v.stderr[-2000:]

    assert r_sky.returncode == 0, r_sky.stderr[-2000:]
    treated = _manifest(out_sky)["light"]["sky_meshes"]["treated"]
    assert treated == [{"object": "Skydome", "visible": ["camera"], "made_unlit": ["sky (unlit sky)"]}]
    y = _luminance(out_sky)
    assert (y < 1e-3).mean() < 0.2 and y.mean() > 0.05


# ----------------------------------------------------------------------------------------------
# Unlit shared interiors
# ----------------------------------------------------------------------------------------------

@pytest.mark.shared
@pytest.mark.parametrize("rel", ["scenes/levels/garage/garage.gltf", "scenes/levels/room/room.blend"])
def test_unlit_interiors_render_lit_by_auto_and_say_why(tmp_path, rel):
    scene = shared_or_skip(rel)
    out = tmp_path / "clip"
    r, v = run_cli_batch(["render", scene, "-o", out, "--camera-path", "walk", *TINY],  # the default light: auto
                         ["validate", out])
    assert r.returncode == 0, r.stderr[-2000:]
    light = _manifest(out)["light"]
    assert light["light"] == "auto" and light["added"] and light["why"]
    assert light["probe"]["with_added_light"]["log_average"] > light["rule"]["lit_min_log_average"]
    if "ceiling_lights" in light:
        c = light["ceiling_lights"]
        assert 1 <= c["lamps"] <= 64 and 1.5 < c["height_above_floor_m"][0] <= c["height_above_floor_m"][1] < 12
    assert "light auto:" in r.stderr  # one note naming what was added
    y = _luminance(out)
    assert (y < 1e-3).mean() < 0.2 and y.mean() > 0.02
    assert v.returncode == 0, v.stdout + v.stderr[-2000:]


@pytest.mark.shared
def test_sky_under_a_roof_names_a_fix_that_works_once(tmp_path):
    garage = shared_or_skip("scenes/levels/garage/garage.gltf")
    r = run_cli("render", garage, "-o", tmp_path / "s", "--camera-path", "walk", "--light", "sky", *TINY)
    assert r.returncode == 2
    line = r.stderr.strip().splitlines()[-1]
    assert line.count("stands under a roof") == 1 and "set --light auto" in line and "orbit" not in line

"""The shared levels (../shared/scenes/levels) through the format table: the OBJ game map with missing textures
renders grey with them named once, and every level's unit is detected (docs/rendering.md, "A level's unit")."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest

from tests.conftest import requires_bpy, run_cli, shared_or_skip
from tests.render.test_scene_formats import magenta_fraction, render_api, run_probe

pytestmark = [requires_bpy, pytest.mark.bpy, pytest.mark.shared]

STEELRIBS = "scenes/levels/steelribs/steelribs.obj"
STEELRIBS_MISSING = ["media/base/base3.png", "media/base/base4.png", "media/base/black.png", "media/base/white.png",
                     "media/nieb/complex/glass.png", "media/nieb/complex/light01.png", "media/nieb/complex/vent.png"]
#: level -> its true unit (metres per unit) and the evidence for it (issue 55: the detected unit must be within a
#: factor 1.5 of it). The glTF and .blend levels are in metres: glTF's unit is the metre, and the sizes agree
#: (garage: 6.8 x 7.6 x 3 m as ../shared/scenes/README.md gives it, a 2.74 m ceiling over the floor; living room
#: and room: 2.5 m and
#: 4.9 m ceilings; truck town: 2.7 m passages and houses about 10 m across, measured; dive arena: a three.js
#: shooter's arena (three.js and glTF units are metres) with a 6.2 m clear height under its platforms, 107 x 89 m
#: as ../shared/scenes/README.md gives it). steelribs is a Tesseract map written by Cube 2's /writeobj (its first
#: line: '# obj file of Cube 2 level'): the engine's player is 15 units tall with the eye 14 units over the feet,
#: about 0.12 m a unit.
LEVEL_TRUE_UNITS = {"living_room/living_room.glb": 1.0, "living_room/living_room.blend": 1.0, "room/room.glb": 1.0,
                    "room/room.blend": 1.0, "garage/garage.gltf": 1.0, "garage/garage.blend": 1.0,
                    "truck_town/town_model.gltf": 1.0, "dive_arena/level.glb": 1.0,
                    "dive_arena/blend_level/level.blend": 1.0, "steelribs/steelribs.obj": 0.12}
#: level -> the unit detected (measured 2026-11-28; docs/rendering.md has the cues)
LEVEL_UNITS = {k: ("cube" if v == 0.12 else "m") for k, v in LEVEL_TRUE_UNITS.items()}


def test_steelribs_renders_with_its_missing_textures_named_once_and_grey(tmp_path):
    from gbuffer_export.clip import open_clip
    level = shared_or_skip(STEELRIBS)
    out = tmp_path / "steelribs"
    r = render_api(tmp_path, output=str(out), scene=str(level), camera_path="fly", light="sky", seed=1,
                   frames=[1, 1])
    assert r.returncode == 0, r.stderr[-3000:]
    lines = [ln for ln in r.stderr.splitlines() if re.search(r"missing|cannot load", ln, re.I)]
    assert lines == ["steelribs.obj: 7 texture file(s) missing, rendered as mid grey (albedo 0.5), never magenta: "
                     + ", ".join(STEELRIBS_MISSING)], r.stderr[-3000:]
    clip = open_clip(out)
    m = clip.manifest
    assert m["scene"]["format"] == "OBJ" and m["scene"]["missing_textures"] == STEELRIBS_MISSING
    unit = m["camera"]["unit_scale"]
    assert unit["requested"] == "auto" and unit["unit"] == "cube" and m["camera"]["metres_per_unit"] == 0.12
    assert m["camera"]["speed_mps"] == pytest.approx(3.0, rel=1e-3)  # fly speed in metres of the depicted world
    for f in clip.frames:
        albedo = clip.read(f, "hr/albedo")
        fg = albedo.sum(axis=-1) > 0
        assert fg.mean() > 0.5 and np.all(np.abs(albedo[fg] - 0.5) < 1e-3)  # every texture is missing: all grey
        assert magenta_fraction(clip.read(f, "hr/radiance")) < 0.01
    v = run_cli("validate", out)
    assert v.returncode == 0, v.stdout + v.stderr


def test_a_given_unit_scale_sets_the_levels_metres(tmp_path):
    """unit_scale = 0.12 (Cube 2's unit): the fly moves 3 m/s = 25 units a second and the manifest says so."""
    level = shared_or_skip(STEELRIBS)
    out = tmp_path / "cube_units"
    r = render_api(tmp_path, output=str(out), scene=str(level), camera_path="fly", light="sky", seed=1,
                   unit_scale=0.12, frames=[1, 1])
    assert r.returncode == 0, r.stderr[-3000:]
    cam = json.loads((out / "manifest.json").read_text())["camera"]
    assert cam["metres_per_unit"] == 0.12 and cam["unit_scale"] == {"requested": 0.12, "metres_per_unit": 0.12,
                                                                    "declared": 1.0}
    assert cam["speed_mps"] == pytest.approx(3.0, rel=1e-3) and cam["clearance_m"] >= 0.25


#: one file of each shared level, the formats glTF (.gltf, .glb), .blend and OBJ among them; the other files hold
#: the same levels in another format (the same geometry through another importer): test_every_shared_levels_file
LEVELS_FAST = ("living_room/living_room.glb", "room/room.blend", "garage/garage.gltf", "truck_town/town_model.gltf",
               "dive_arena/blend_level/level.blend", "steelribs/steelribs.obj")


def _check_units(rels) -> None:
    paths = {rel: shared_or_skip(f"scenes/levels/{rel}") for rel in rels}
    res, _ = run_probe("units", {"levels": [str(p) for p in paths.values()]}, timeout=400)
    got = {rel: res[str(p)]["unit"] for rel, p in paths.items()}
    assert got == {rel: LEVEL_UNITS[rel] for rel in rels}, {rel: (res[str(p)]["cues"], res[str(p)]["scores"])
                                                            for rel, p in paths.items()}
    for rel, p in paths.items():
        ratio = res[str(p)]["metres_per_unit"] / LEVEL_TRUE_UNITS[rel]
        assert 1 / 1.5 <= ratio <= 1.5, (rel, res[str(p)])
    if "steelribs/steelribs.obj" in paths:
        assert res[str(paths["steelribs/steelribs.obj"])]["engine"]["unit"] == "cube"


def test_the_shared_levels_units_are_detected():
    """Each shared level, in one of its files (``LEVELS_FAST``)."""
    _check_units(LEVELS_FAST)


@pytest.mark.heavy
def test_every_shared_levels_file_has_its_unit_detected():
    """The files ``LEVELS_FAST`` leaves out: the same levels in their other formats (about 4 s a level loaded)."""
    _check_units([rel for rel in LEVEL_UNITS if rel not in LEVELS_FAST])
